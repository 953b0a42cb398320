"""Monte-Carlo benchmark of location and repair on plants of every element structure (issue 12).

Run::

    python -m bench.structures_mc [--runs 300] [--seed 0] [--samples 3000] [--jobs 1]
                                  [--clean-integrating 500] [--lost-lag | --gained-lag | --pure-gains]
                                  [--confirm-responses]
                                  [--out bench/results/structures_mc.json]

(``--lost-lag``: every mismatch a second lag the model has and the plant's element lacks; its default output
is ``bench/results/structures_mc_lost_lag.json``.  ``--gained-lag``: every mismatch a lag the plant's element
has and the model's lacks, a pure gain or a pure integrator in the model; ``bench/results/structures_mc_gained_lag.json``.
``--pure-gains``: the first-order input elements without a lead are pure gains in the plant and the model, every
mismatch a gain or dead-time change of one of them or its lag lost (the model's has one, the plant's not);
``bench/results/structures_mc_pure_gains.json``.
``--confirm-responses``: the analysis's option ``confirm_responses`` on; ``bench/results/structures_mc_confirm.json``.)

Every run draws a random closed loop (:func:`make_structures_scenario`; a pure function of
``(seed, index)``, so ``--jobs`` only changes the speed), simulates it under the internal-model MPC
(:func:`mpm_monitor.sim.closed_loop.run_closed_loop`, measured disturbances fed forward) and hands
the logged ``r, u, dv, y`` to :func:`mpm_monitor.core.pipeline.analyze` with its default options
(``alpha`` 0.01, the repair on).

The distribution (:class:`StructuresOptions` holds every number, fixed before any run was scored):

* size: ``n_outputs`` and ``n_inputs`` uniform in 2..4, 0 to 2 measured disturbances (uniform);
  every element present (a dense plant, the disturbances acting on every output);
* each output is integrating with probability 0.3 (every element of its row then has the pole at
  ``s = 0``, as a level integrates every flow); each element draws a structure: first order (0.4),
  second order (0.2), lead-lag (0.2) or inverse response (negative lead, 0.2); parameters: ``|K|``
  log-uniform in [0.5, 5] (in [0.02, 0.1] per second when integrating) with a random sign, ``tau``
  uniform in [10, 80] s ([2, 20] s when integrating), ``tau2`` uniform in [0.2, 0.6] ``tau``, a
  lead uniform in [0.2, 0.8] ``tau`` (negative for an inverse response), a delay uniform in 0..8
  samples (at least 1 where the element would otherwise act in the same sample);
* mismatched elements: 0, 1 or 2 (uniform), at distinct random positions; each gets a kind drawn
  uniformly from those its structure has, with a relative size ``s`` uniform in [0.2, 0.8]:

  - an input's element: ``gain`` (``integrator_gain`` on an integrating element), ``time_constant``,
    ``delay`` (``+- max(1, round(s theta))`` samples, a decrease only where the model element stays
    strictly proper), ``second_lag`` (``tau2``, where it has one), ``lead`` (where it has one);
  - a measured disturbance's element: ``disturbance_gain``;
  - a parameter ``p`` becomes ``p (1 + s)`` or ``p (1 - s)`` (the direction at random);

* excitation: PRBS setpoints of amplitude 1 switching with probability 1/2 on every output (as
  ``bench.monte_carlo``); plants with more inputs than outputs get an input dither (PRBS of
  amplitude 0.3 switching with probability 1/2) so that their inputs are not driven in an
  ``n_outputs``-dimensional subspace (the design that makes a fat plant's elements identifiable; the
  0.1 of ``bench.monte_carlo`` left the slow effects of lags and integrators of fat plants too weakly
  excited: on the 11 fat runs with a miss among the first 100, 5 of 17 mismatches were located with
  0.1, 10 with 0.3); measured disturbances: random steps of up to +-1
  (probability 0.02 per sample after 20 samples) plus noise of std 0.1 (pole 0.9); the paper's
  MPC tuning and noise.

Scoring (pooled over runs):

* false alarms: among the clean runs (no mismatch), the fraction with a located element, and with
  a flagged row; must stay at or below ``alpha``;
* elements: a located element on a true mismatch is a hit, elsewhere a false positive;
  ``precision = hits / (hits + false positives)``;
* **identifiable** mismatched elements are those the analysis does not report ambiguous (its
  collinearity check says the element's column can be told apart from the other columns in that
  row's regression).  ``recall`` counts hits over identifiable mismatches; ``recall_all`` counts
  every mismatch, an ambiguous one as a miss.  The column's measured separability
  (:func:`bench.scenarios.input_separability`, on the inputs and disturbances together) is recorded
  as a ground truth of collinearity;
* indicative, not an acceptance figure: each true mismatch's effect on the window (the RMS of the
  plant's minus the model's element response to the logged column, over the RMS of the model's; a
  gain error's relative size exactly) against the report's ``detectable_gain_change`` of that
  element (calibrated for gain errors; another kind's power differs), and the recall on each side;
* indicative too, and independent of the analysis: each true mismatch's power for an oracle that
  knows its exact response and the noise model (:mod:`bench.oracle`, at the Bonferroni level of one
  element, ``alpha / (N_FAMILIES m)``), and the recall in the bands of :data:`ORACLE_BANDS`;
* repair: for every located mismatched element, the repaired model's unit-step response of that
  element against the plant's over ``REPAIR_HORIZON`` samples; "within 10 %" when the largest
  difference is at most 10 % of the largest value of the plant's response (an integrating element's
  ramp included);
* ``--clean-integrating N``: N more clean runs (indices from ``CLEAN_INDEX_OFFSET``) of the same
  distribution with at least one integrating output, for the false-alarm rate of integrating loops.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.statistics import N_FAMILIES
from mpm_monitor.sim.closed_loop import ExcitationOptions, run_closed_loop
from mpm_monitor.sim.excitation import MeasuredDisturbanceOptions, PrbsOptions
from mpm_monitor.sim.mpc import MpcOptions
from mpm_monitor.sim.plant import DisturbanceOptions

from . import map_runs, write_json
from .oracle import oracle_power
from .scenarios import check_count_ranges, input_separability

STRUCTURES = ("first", "second", "lead", "inverse")
KINDS = ("gain", "integrator_gain", "time_constant", "delay", "second_lag", "lead", "disturbance_gain", "lost_lag",
         "gained_lag", "integrator_gained_lag", "lost_only_lag", "lost_pair")
#: The kind the report should give each kind of mismatch (a lag, a second lag, a lead or a lost lag is a
#: ``time_constant`` change; an integrator's or a disturbance's gain a ``gain``, as is a lost pair: a lead and a
#: lag that cancel leave only the gain's change).
REPORTED_KIND = {"gain": "gain", "integrator_gain": "gain", "time_constant": "time_constant", "delay": "delay",
                 "second_lag": "time_constant", "lead": "time_constant", "disturbance_gain": "gain",
                 "lost_lag": "time_constant", "gained_lag": "time_constant", "integrator_gained_lag": "time_constant",
                 "lost_only_lag": "time_constant", "lost_pair": "gain"}
#: Samples over which a repaired element's step response is compared with the plant's.
REPAIR_HORIZON = 300
#: Largest difference of the step responses, as a fraction of the plant response's largest value.
REPAIR_TOLERANCE = 0.10
#: An input whose separability is below this is "collinear" in the ground truth (as bench.monte_carlo).
SEPARABILITY_COLLINEAR = 1e-2
#: Indices of the ``--clean-integrating`` runs start here (distinct from the main runs').
CLEAN_INDEX_OFFSET = 1_000_000
#: The unmeasured disturbance and measurement noise of every run (the paper's).
NOISE = DisturbanceOptions()
#: Bands of the oracle's power (bench.oracle) the recall is split by: at least 0.9, 0.5 to 0.9, below 0.5.
ORACLE_BANDS = (0.9, 0.5)
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "structures_mc.json"
#: The name of the channel of white noise that ``--noise-candidate`` adds to every log.
NOISE_CANDIDATE = "noise_candidate"


@dataclasses.dataclass(frozen=True)
class StructuresOptions:
    """The distribution of the scenarios (module docstring).

    Attributes
    ----------
    min_size, max_size : int
        Range of ``n_outputs`` and of ``n_inputs``.
    max_disturbances : int
        Measured disturbances drawn uniformly in 0..max_disturbances.
    integrating_probability : float
        Probability that an output is integrating.
    structure_probabilities : tuple of float
        Probabilities of :data:`STRUCTURES` (first order, second order, lead-lag, inverse response).
    gain_range, integrating_gain_range : tuple of float
        Ranges of ``|K|`` (log-uniform), self-regulating and integrating (per second).
    tau_range, integrating_tau_range : tuple of float
        Ranges of the first lag, seconds.
    tau2_fraction, lead_fraction : tuple of float
        Ranges of ``tau2 / tau`` and ``|lead| / tau``.
    max_delay : int
        Largest plant delay, samples.
    min_mismatches, max_mismatches : int
        Range of the number of mismatched elements.
    size_range : tuple of float
        Range of the relative size ``s`` of a mismatch.
    dither_fat : bool
        Dither the inputs of plants with more inputs than outputs.
    dither_amplitude : float
        Amplitude of that dither's PRBS.
    setpoint_amplitude : float
        Amplitude of the setpoint PRBS.
    measured_disturbance : MeasuredDisturbanceOptions
        The measured disturbances' signal.
    lost_lag : bool
        Every mismatch is a lost lag instead (``--lost-lag``): the model has a second lag (``tau2``
        drawn from ``tau2_fraction`` of ``tau``) on an input's element whose plant element has none, at
        positions drawn among those elements.
    gained_lag : bool
        Every mismatch is a gained lag instead (``--gained-lag``): the model's element has no lag where the
        plant's has its one lag (a pure gain, or a pure integrator: ``integrator_gained_lag``), at positions
        drawn among the inputs' elements with one lag, no second lag and no lead whose lagless form acts a
        sample after its input at the earliest.
    pure_gains : bool
        Those same elements (the inputs' elements with one lag, no second lag and no lead, not integrating,
        whose lagless form acts a sample after its input at the earliest) are pure gains, in the plant and so
        in the model (``--pure-gains``), and every mismatch is a gain or a dead-time change of one of them, or a
        lag the plant's pure gain has lost (``lost_only_lag``: the model's element has a lag).
    two_lag_leads : bool
        Every lead-lag element (the ``lead`` structure) has a second lag too (``tau2`` drawn from
        ``tau2_fraction`` of ``tau``; ``--two-lag-leads``): a plant whose leads are declared over two lags,
        which the repair must keep where the data call for them.
    lost_pair : bool
        Every mismatch is a lost pair instead (``--lost-pair``): the model's element has a lead and a second
        lag that cancel (both ``s tau``, ``s`` drawn from ``tau2_fraction``) and a gain off by a factor drawn
        as the other mismatches' sizes, on an input's element whose plant element is first order (one lag,
        no lead), at positions drawn among those elements.
    """

    min_size: int = 2
    max_size: int = 4
    max_disturbances: int = 2
    integrating_probability: float = 0.3
    structure_probabilities: tuple = (0.4, 0.2, 0.2, 0.2)
    gain_range: tuple = (0.5, 5.0)
    integrating_gain_range: tuple = (0.02, 0.1)
    tau_range: tuple = (10.0, 80.0)
    integrating_tau_range: tuple = (2.0, 20.0)
    tau2_fraction: tuple = (0.2, 0.6)
    lead_fraction: tuple = (0.2, 0.8)
    max_delay: int = 8
    min_mismatches: int = 0
    max_mismatches: int = 2
    size_range: tuple = (0.2, 0.8)
    dither_fat: bool = True
    dither_amplitude: float = 0.3
    setpoint_amplitude: float = 1.0
    measured_disturbance: MeasuredDisturbanceOptions = MeasuredDisturbanceOptions(
        step_amplitude=1.0, switch_probability=0.02, min_hold=20, noise_std=0.1, noise_pole=0.9)
    lost_lag: bool = False
    gained_lag: bool = False
    pure_gains: bool = False
    two_lag_leads: bool = False
    lost_pair: bool = False

    def __post_init__(self):
        check_count_ranges(self)
        if self.lost_lag + self.gained_lag + self.pure_gains + self.lost_pair > 1:
            raise ValueError("lost_lag, gained_lag, pure_gains, lost_pair: expected at most one of them")
        if len(self.structure_probabilities) != len(STRUCTURES) or abs(sum(self.structure_probabilities) - 1) > 1e-9:
            raise ValueError(f"structure_probabilities: expected {len(STRUCTURES)} probabilities summing to 1, "
                             f"got {self.structure_probabilities!r}")
        lo, hi = self.size_range
        if not 0.0 < lo <= hi < 1.0:
            raise ValueError(f"size_range: expected 0 < low <= high < 1, got {self.size_range!r}")


@dataclasses.dataclass(frozen=True)
class StructuresScenario:
    """One random closed loop: plant, controller model, mismatches and experiment.

    Attributes
    ----------
    seed, index : int
    plant, model : PlantModel
        The true plant and the controller's model (same structures; the mismatched elements differ).
    mismatches : tuple of dict
        ``output``, ``column``, ``role``, ``kind``, ``size``, ``plant`` and ``model`` (the element's
        parameters) of every mismatched element.
    structures : list of list of str
        The structure of every element (:data:`STRUCTURES`).
    dither : bool
    loop_seed : int
    """

    seed: int
    index: int
    plant: PlantModel
    model: PlantModel
    mismatches: tuple
    structures: list
    dither: bool
    loop_seed: int

    def describe(self) -> dict:
        """Plain-JSON description."""
        return {"seed": self.seed, "index": self.index,
                "shape": [self.plant.n_outputs, self.plant.n_inputs, self.plant.n_disturbances],
                "integrating_outputs": [bool(b) for b in self.plant.integrating.any(axis=1)],
                "structures": self.structures, "dither": self.dither, "loop_seed": self.loop_seed,
                "mismatches": list(self.mismatches), "plant": self.plant.to_dict()}


def _log_uniform(rng, lo, hi) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _strictly_proper(model: PlantModel, i: int, j: int) -> bool:
    return model.discrete_element(i, j).strictly_proper


def _draw_plant(rng, ny: int, nu: int, nd: int, opts: StructuresOptions, name: str):
    nc = nu + nd
    integrating_rows = rng.random(ny) < opts.integrating_probability
    arrays = {k: np.zeros((ny, nc)) for k in ("gain", "time_constant", "time_constant2", "lead", "delay")}
    integrating = np.zeros((ny, nc), dtype=bool)
    structures = []
    for i in range(ny):
        structures.append([])
        for j in range(nc):
            integ = bool(integrating_rows[i])
            structure = STRUCTURES[int(rng.choice(len(STRUCTURES), p=opts.structure_probabilities))]
            structures[-1].append(structure)
            glo, ghi = opts.integrating_gain_range if integ else opts.gain_range
            tlo, thi = opts.integrating_tau_range if integ else opts.tau_range
            k = _log_uniform(rng, glo, ghi) * (-1.0 if rng.random() < 0.5 else 1.0)
            tau = float(rng.uniform(tlo, thi))
            arrays["gain"][i, j] = round(k, 4)
            arrays["time_constant"][i, j] = round(tau, 1)
            if structure in ("second", "inverse") and (structure == "second" or rng.random() < 0.5):
                arrays["time_constant2"][i, j] = round(tau * float(rng.uniform(*opts.tau2_fraction)), 1)
            elif structure == "lead" and opts.two_lag_leads:
                arrays["time_constant2"][i, j] = round(tau * float(rng.uniform(*opts.tau2_fraction)), 1)
            if structure in ("lead", "inverse"):
                lead = round(tau * float(rng.uniform(*opts.lead_fraction)), 1)
                arrays["lead"][i, j] = -lead if structure == "inverse" else lead
            arrays["delay"][i, j] = int(rng.integers(0, opts.max_delay + 1))
            integrating[i, j] = integ
    plant = PlantModel(sample_time=1.0, inputs=tuple(f"u{k + 1}" for k in range(nu)),
                       outputs=tuple(f"y{k + 1}" for k in range(ny)),
                       disturbances=tuple(f"dv{k + 1}" for k in range(nd)), integrating=integrating, name=name,
                       **arrays)
    delay = arrays["delay"].copy()
    for i in range(ny):
        for j in range(nc):
            if not _strictly_proper(plant, i, j):
                delay[i, j] = max(delay[i, j], 1)       # a lead-lag acts in the same sample: give it a dead time
    return plant.replace(delay=delay), structures


def _mismatch(rng, plant: PlantModel, model: PlantModel, i: int, j: int, opts: StructuresOptions):
    """The model with element (i, j) mismatched, and the mismatch's description."""
    el = plant.element(i, j)
    if opts.gained_lag:                 # the model lacks the lag the plant's element has
        new = model.with_element(i, j, time_constant=0.0)
        kind = "integrator_gained_lag" if el.get("integrating") else "gained_lag"
        return new, {"output": i, "column": j, "role": plant.role(j), "kind": kind, "size": 1.0,
                     "plant": el, "model": new.element(i, j)}
    if opts.lost_pair:                  # the model has a cancelling lead and second lag, and a gain off
        s = float(rng.uniform(*opts.tau2_fraction))
        pair = round(el["time_constant"] * s, 1)
        size = float(rng.uniform(*opts.size_range))
        factor = 1.0 + size if rng.random() < 0.5 else 1.0 - size
        new = model.with_element(i, j, time_constant2=pair, lead=pair, gain=el["gain"] * factor)
        return new, {"output": i, "column": j, "role": plant.role(j), "kind": "lost_pair", "size": round(size, 4),
                     "plant": el, "model": new.element(i, j)}
    if opts.lost_lag:                   # the model has a second lag the plant lacks
        s = float(rng.uniform(*opts.tau2_fraction))
        new = model.with_element(i, j, time_constant2=round(el["time_constant"] * s, 1))
        return new, {"output": i, "column": j, "role": plant.role(j), "kind": "lost_lag", "size": round(s, 4),
                     "plant": el, "model": new.element(i, j)}
    if plant.role(j) == "disturbance":
        kinds = ["disturbance_gain"]
    elif not el.get("time_constant") and not el.get("integrating"):     # a pure gain: the model's has a lag
        kinds = ["gain", "delay", "lost_only_lag"]                       # or not
        if kinds[int(rng.integers(len(kinds)))] == "lost_only_lag":
            tau = round(float(rng.uniform(*opts.tau_range)), 1)
            new = model.with_element(i, j, time_constant=tau)
            return new, {"output": i, "column": j, "role": plant.role(j), "kind": "lost_only_lag", "size": 1.0,
                         "plant": el, "model": new.element(i, j)}
        kinds = ["gain", "delay"]
    else:
        kinds = ["integrator_gain" if el.get("integrating") else "gain", "time_constant", "delay"]
        if el.get("time_constant2"):
            kinds.append("second_lag")
        if el.get("lead"):
            kinds.append("lead")
    kind = kinds[int(rng.integers(len(kinds)))]
    s = float(rng.uniform(*opts.size_range))
    factor = 1.0 + s if rng.random() < 0.5 else 1.0 - s
    if kind == "delay":
        d = int(round(el["delay"] / plant.sample_time))
        shift = max(1, int(round(s * d)))
        down = rng.random() < 0.5 and d - shift >= 0
        new = model.with_element(i, j, delay=(d - shift) * plant.sample_time) if down else None
        if new is None or not _strictly_proper(new, i, j):
            new = model.with_element(i, j, delay=(d + shift) * plant.sample_time)
    else:
        key = {"gain": "gain", "integrator_gain": "gain", "disturbance_gain": "gain", "time_constant": "time_constant",
               "second_lag": "time_constant2", "lead": "lead"}[kind]
        new = model.with_element(i, j, **{key: el[key] * factor})
    return new, {"output": i, "column": j, "role": plant.role(j), "kind": kind, "size": round(s, 4),
                 "plant": el, "model": new.element(i, j)}


def make_structures_scenario(seed: int, index: int, options: StructuresOptions = StructuresOptions(), *,
                             n_mismatches: Optional[int] = None,
                             integrating_output: bool = False) -> StructuresScenario:
    """Draw scenario ``index`` of family ``seed`` (see the module docstring).

    Parameters
    ----------
    seed, index : int
        The scenario is a pure function of them (and of the other arguments).
    options : StructuresOptions
    n_mismatches : int, optional
        Force the number of mismatched elements (default: uniform in the options' range).
    integrating_output : bool
        Redraw the plant until at least one output is integrating (for the clean integrating runs).

    Returns
    -------
    StructuresScenario
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 12]))
    while True:
        ny = int(rng.integers(options.min_size, options.max_size + 1))
        nu = int(rng.integers(options.min_size, options.max_size + 1))
        nd = int(rng.integers(0, options.max_disturbances + 1))
        plant, structures = _draw_plant(rng, ny, nu, nd, options, f"random plant (seed {seed}, run {index})")
        if not integrating_output or plant.integrating.any():
            break
    k = (int(rng.integers(options.min_mismatches, options.max_mismatches + 1)) if n_mismatches is None
         else int(n_mismatches))
    nc = plant.n_columns
    model = plant
    mismatches = []
    if options.lost_lag:                # among the inputs' elements without a second lag in the plant
        cells = [i * nc + j for i in range(ny) for j in range(nu) if plant.time_constant2[i, j] == 0]
        positions = rng.choice(cells, size=min(k, len(cells)), replace=False) if cells else []
    elif options.lost_pair:             # among the inputs' first-order elements (one lag, no lead, not integrating)
        cells = [i * nc + j for i in range(ny) for j in range(nu)
                 if plant.time_constant[i, j] > 0 and plant.time_constant2[i, j] == 0 and plant.lead[i, j] == 0
                 and not plant.integrating[i, j]]
        positions = rng.choice(cells, size=min(k, len(cells)), replace=False) if cells else []
    elif options.gained_lag or options.pure_gains:   # among the inputs' first-order and one-lag integrating elements
        cells = [i * nc + j for i in range(ny) for j in range(nu)
                 if plant.time_constant[i, j] > 0 and plant.time_constant2[i, j] == 0 and plant.lead[i, j] == 0
                 and _strictly_proper(plant.with_element(i, j, time_constant=0.0), i, j)
                 and not (options.pure_gains and plant.integrating[i, j])]
        if options.pure_gains:          # ... which are pure gains, in the plant and the model
            for pos in cells:
                plant = plant.with_element(*divmod(pos, nc), time_constant=0.0)
            model = plant
        positions = rng.choice(cells, size=min(k, len(cells)), replace=False) if cells else []
    else:
        positions = rng.choice(ny * nc, size=min(k, ny * nc), replace=False)
    for pos in sorted(int(p) for p in positions):
        model, m = _mismatch(rng, plant, model, *divmod(pos, nc), options)
        mismatches.append(m)
    model = model.replace(name=f"random model (seed {seed}, run {index}, {len(mismatches)} mismatched)")
    dither = bool(options.dither_fat and nu > ny)
    loop_seed = int(rng.integers(0, 2**31 - 1))
    return StructuresScenario(seed=int(seed), index=int(index), plant=plant, model=model,
                              mismatches=tuple(mismatches), structures=structures, dither=dither, loop_seed=loop_seed)


def simulate(sc: StructuresScenario, samples: int, options: StructuresOptions = StructuresOptions(),
             disturbance: DisturbanceOptions = NOISE):
    """The closed-loop log of a scenario (the paper's MPC tuning and, by default, noise)."""
    excitation = ExcitationOptions(
        setpoint=PrbsOptions(amplitude=options.setpoint_amplitude, switch_probability=0.5),
        dither=PrbsOptions(amplitude=options.dither_amplitude, switch_probability=0.5) if sc.dither else None)
    mpc = MpcOptions(prediction_horizon=100, control_horizon=30, output_weight=1.0, input_weight=1.0,
                     input_rate_weight=0.1)
    return run_closed_loop(sc.plant, sc.model, samples, seed=sc.loop_seed, mpc=mpc, excitation=excitation,
                           disturbance=disturbance, measured_disturbance=options.measured_disturbance)


def step_response_error(plant: PlantModel, repaired: PlantModel, i: int, j: int, n: int = REPAIR_HORIZON) -> float:
    """Largest difference of the unit-step responses of element (i, j) over ``n`` samples, as a
    fraction of the largest absolute value of the plant's (inf when the plant's is zero)."""
    s_plant = plant.discrete_element(i, j).step_response(n)
    s_rep = repaired.discrete_element(i, j).step_response(n)
    scale = float(np.max(np.abs(s_plant)))
    diff = float(np.max(np.abs(s_rep - s_plant)))
    return diff / scale if scale > 0 else float("inf")


def run_one(seed: int, index: int, samples: int, options: StructuresOptions = StructuresOptions(),
            clean_integrating: bool = False, element_window: str = "model", noise_candidate: bool = False,
            confirm_responses: bool = False) -> dict:
    """Draw, simulate, analyse and repair one scenario; return its JSON-ready record.

    With ``noise_candidate`` the log gains one channel ``noise_candidate`` of white noise (unit
    variance, seeded by ``(seed, index)``) that acts on nothing, and the analysis tries it as a
    candidate (``candidates="all"``): the model's elements are then tested in the family that the
    candidate's tests join.  ``candidates_located`` lists the outputs on which it was located (each a
    false positive).
    """
    sc = make_structures_scenario(seed, index, options, n_mismatches=0 if clean_integrating else None,
                                  integrating_output=clean_integrating)
    t0 = time.perf_counter()
    log = simulate(sc, samples, options)
    sim_time = time.perf_counter() - t0
    data = log.as_logged_data(f"structures scenario {seed}/{index}")
    if noise_candidate:
        noise = np.random.default_rng(np.random.SeedSequence([int(seed), int(index), 13])).standard_normal(data.n_samples)
        data = dataclasses.replace(data, extra={NOISE_CANDIDATE: noise})
    rec = sc.describe()
    rec["simulation_time_s"] = sim_time
    if not all(np.all(np.isfinite(a)) for a in (data.u, data.y, data.dv)):
        rec["error"] = "the loop diverged: the log holds values that are not finite"
        return rec
    sep = input_separability(np.column_stack([data.u, data.dv]))
    rec["separability"] = [float(x) for x in sep]
    rec["collinear_columns"] = [int(j) for j in np.flatnonzero(sep < SEPARABILITY_COLLINEAR)]
    analysis_options = AnalysisOptions(element_window=element_window, confirm_responses=confirm_responses)
    try:
        t0 = time.perf_counter()
        report = analyze(sc.model, data, analysis_options, candidates="all" if noise_candidate else None)
        rec["analyze_time_s"] = time.perf_counter() - t0
    except Exception as exc:  # noqa: BLE001 - a benchmark records a failure and goes on
        rec["error"] = f"{type(exc).__name__}: {exc}"
        return rec
    oi = {name: k for k, name in enumerate(sc.model.outputs)}
    ci = {name: k for k, name in enumerate(sc.model.columns)}
    if noise_candidate:         # the candidate is scored apart; the rest of the record is the model's elements
        rec["candidates_located"] = sorted(oi[e.output] for e in report.elements
                                           if e.mismatch and e.role == "candidate")
        report = dataclasses.replace(report, elements=[e for e in report.elements if e.role != "candidate"])
    rec["located"] = sorted([oi[e.output], ci[e.input]] for e in report.elements if e.mismatch)
    rec["ambiguous"] = sorted([oi[e.output], ci[e.input]] for e in report.elements if e.ambiguous and not e.mismatch)
    rec["rows"] = sorted(oi[r.output] for r in report.rows if r.mismatch)
    rec["kinds"] = {f"{oi[e.output]},{ci[e.input]}": e.kind for e in report.elements if e.mismatch}
    rec["released"] = sorted([oi[e.output], ci[e.input]] for e in report.elements if e.explained_by)
    # The size of each true mismatch's effect on the window, against what the window could detect: the
    # RMS of (plant - model) element response to the logged column over the RMS of the model element's
    # (for a gain error exactly its relative size), and the report's detectable_gain_change.
    columns = np.column_stack([data.u, data.dv]) if data.dv.size else np.asarray(data.u)
    detectable = {(oi[e.output], ci[e.input]): e.detectable_gain_change for e in report.elements}
    # ... and what an oracle that knows that effect's exact shape and the noise model would detect
    # (bench.oracle), at the Bonferroni level of one element of the analysis's element family.
    level = analysis_options.alpha / (N_FAMILIES * sc.model.n_outputs * sc.model.n_columns)
    rec["effects"] = {}
    for m in sc.mismatches:
        i, j = m["output"], m["column"]
        col = columns[:, j] - columns[:, j].mean()
        x_plant = sc.plant.discrete_element(i, j).respond(col)
        x_model = sc.model.discrete_element(i, j).respond(col) if sc.model.present[i, j] else np.zeros_like(col)
        x_model_c, dx = x_model - x_model.mean(), (x_plant - x_model) - (x_plant - x_model).mean()
        ref = float(np.sqrt(np.mean(x_model_c ** 2)))
        rec["effects"][f"{i},{j}"] = {"effect": float(np.sqrt(np.mean(dx ** 2))) / ref if ref > 0 else None,
                                      "detectable": detectable.get((i, j)),
                                      "oracle_power": oracle_power(dx, NOISE, level)}
    repaired = report.repaired_model if report.repaired_model is not None else sc.model
    rec["repair"] = [{"element": [i, j], "step_error": step_response_error(sc.plant, repaired, i, j),
                      "before": step_response_error(sc.plant, sc.model, i, j),
                      "repaired": repaired.element(i, j)} for i, j in rec["located"]]
    # What the detection of the repaired model locates in the rows it still flags (the report's located_after).
    rec["located_after"] = sorted([oi[x["output"]], ci[x["input"]]] for x in (report.repair or {}).get("located_after", [])
                                  if x["input"] in ci)
    rec["warnings"] = list(report.warnings)
    return rec


def _run_one_star(args):
    return run_one(*args)


# --------------------------------------------------------------------------- scoring
def _ratio(num, den) -> Optional[float]:
    return float(num) / float(den) if den else None


def score(records: Sequence[dict]) -> dict:
    """Pooled figures of the run records (module docstring)."""
    el = dict(tp=0, fp=0, fn=0, amb_true=0, amb_clean=0, amb_true_collinear=0, released_true=0, released_clean=0)
    seen = dict(hit=0, miss=0, unknown=0, below_hit=0, below_miss=0)   # effect vs detectable (not ambiguous)
    oracle = {band: dict(hit=0, miss=0) for band in ("high", "middle", "low", "unknown")}   # not ambiguous
    clean = dict(runs=0, located=0, rows=0)
    clean_int = dict(runs=0, located=0, rows=0)
    repair = dict(scored=0, within=0, fp_scored=0, fp_within=0)
    after = dict(new=0, new_drawn=0, new_runs=0, again=0, again_drawn=0)     # the repaired model's detection
    by_kind, by_role, reported = {}, {}, {}
    misses, false_pos, repair_fails, errors = [], [], [], []
    for rec in records:
        if "error" in rec:
            errors.append({"index": rec["index"], "error": rec["error"]})
            continue
        truth = {(m["output"], m["column"]): m for m in rec["mismatches"]}
        located = {tuple(x) for x in rec["located"]}
        ambiguous = {tuple(x) for x in rec["ambiguous"]} - located
        collinear = set(rec["collinear_columns"])
        if not truth:
            for cell in (clean, clean_int) if any(rec["integrating_outputs"]) else (clean,):
                cell["runs"] += 1
                cell["located"] += bool(located)
                cell["rows"] += bool(rec["rows"])
        for key in located - set(truth):
            el["fp"] += 1
            false_pos.append({"index": rec["index"], "element": list(key), "shape": rec["shape"],
                              "row_mismatched": any(o == key[0] for o, _ in truth)})
        el["amb_clean"] += len(ambiguous - set(truth))
        released = {tuple(x) for x in rec.get("released", [])}      # flagged, explained by the row's others
        el["released_true"] += len(released & set(truth))
        el["released_clean"] += len(released - set(truth))
        for key, m in truth.items():
            outcome = "hit" if key in located else ("ambiguous" if key in ambiguous else "miss")
            el[{"hit": "tp", "miss": "fn", "ambiguous": "amb_true"}[outcome]] += 1
            eff = rec.get("effects", {}).get(f"{key[0]},{key[1]}", {})
            if outcome != "ambiguous":
                if eff.get("effect") is None or eff.get("detectable") is None or not np.isfinite(eff["detectable"]):
                    seen["unknown"] += 1
                elif eff["effect"] >= eff["detectable"]:
                    seen[outcome] += 1
                else:
                    seen["below_" + outcome] += 1
                power = eff.get("oracle_power")
                band = "unknown" if power is None else "high" if power >= ORACLE_BANDS[0] else \
                    "middle" if power >= ORACLE_BANDS[1] else "low"
                oracle[band][outcome] += 1
            if outcome == "ambiguous" and key[1] in collinear:
                el["amb_true_collinear"] += 1
            for table, val in ((by_kind, m["kind"]), (by_role, m["role"])):
                table.setdefault(val, {"hit": 0, "miss": 0, "ambiguous": 0})[outcome] += 1
            if outcome == "hit":
                said = rec["kinds"].get(f"{key[0]},{key[1]}")
                cell = reported.setdefault(m["kind"], {"expected": REPORTED_KIND[m["kind"]], "right": 0, "hits": 0,
                                                       "said": {}})
                cell["hits"] += 1
                cell["right"] += said == cell["expected"]
                cell["said"][said] = cell["said"].get(said, 0) + 1
            if outcome != "hit":
                misses.append({"index": rec["index"], "element": list(key), "kind": m["kind"], "size": m["size"],
                               "outcome": outcome, "plant": m["plant"], "model": m["model"],
                               "row_flagged": key[0] in rec["rows"], "column_collinear": key[1] in collinear,
                               "effect": eff.get("effect"), "detectable": eff.get("detectable"),
                               "oracle_power": eff.get("oracle_power")})
        named = [tuple(x) for x in rec.get("located_after", [])]
        new = [k for k in named if k not in located]
        after["new"] += len(new)
        after["new_drawn"] += sum(k in truth for k in new)
        after["new_runs"] += bool(new)
        after["again"] += len(named) - len(new)
        after["again_drawn"] += sum(k in truth for k in named if k in located)
        for r in rec["repair"]:
            key = tuple(r["element"])
            ok = r["step_error"] <= REPAIR_TOLERANCE
            if key in truth:
                repair["scored"] += 1
                repair["within"] += ok
                if not ok:
                    repair_fails.append({"index": rec["index"], "element": list(key), "kind": truth[key]["kind"],
                                         "step_error": r["step_error"], "before": r["before"],
                                         "plant": truth[key]["plant"], "model": truth[key]["model"],
                                         "repaired": r["repaired"], "reported_kind": rec["kinds"].get(
                                             f"{key[0]},{key[1]}")})
            else:
                repair["fp_scored"] += 1
                repair["fp_within"] += ok
    for table in (by_kind, by_role):
        for cell in table.values():
            cell["recall"] = _ratio(cell["hit"], cell["hit"] + cell["miss"])
            cell["recall_all"] = _ratio(cell["hit"], cell["hit"] + cell["miss"] + cell["ambiguous"])
    for cell in (clean, clean_int):
        cell["rate_element"] = _ratio(cell["located"], cell["runs"])
        cell["rate_row"] = _ratio(cell["rows"], cell["runs"])
    for cell in oracle.values():
        cell["recall"] = _ratio(cell["hit"], cell["hit"] + cell["miss"])
    repair["fraction_within"] = _ratio(repair["within"], repair["scored"])
    repair["fp_fraction_within"] = _ratio(repair["fp_within"], repair["fp_scored"])
    times = [r["analyze_time_s"] for r in records if "analyze_time_s" in r]
    return {"runs": len(records) - len(errors), "errors": errors,
            "element": {**el, "precision": _ratio(el["tp"], el["tp"] + el["fp"]),
                        "recall": _ratio(el["tp"], el["tp"] + el["fn"]),
                        "recall_all": _ratio(el["tp"], el["tp"] + el["fn"] + el["amb_true"])},
            "effect_vs_detectable": {**seen, "recall_at_or_above": _ratio(seen["hit"], seen["hit"] + seen["miss"]),
                                     "recall_below": _ratio(seen["below_hit"], seen["below_hit"] + seen["below_miss"])},
            "oracle_power": oracle, "false_alarms": clean, "false_alarms_integrating": clean_int, "repair": repair,
            "located_after": after,
            "recall_by_kind": by_kind, "recall_by_role": by_role, "reported_kind": reported,
            "median_analyze_time_s": statistics.median(times) if times else None,
            "misses": misses, "false_positives": false_pos, "repair_failures": repair_fails}


# --------------------------------------------------------------------------- driver
def run_structures_mc(n_runs: int, seed: int = 0, samples: int = 3000, *, clean_integrating: int = 0, jobs: int = 1,
                      options: StructuresOptions = StructuresOptions(), element_window: str = "model",
                      noise_candidate: bool = False, confirm_responses: bool = False,
                      progress: Optional[Callable[[int, int, dict], None]] = None) -> dict:
    """Run the benchmark and score it.

    Parameters
    ----------
    n_runs : int
        Random scenarios of the main distribution (indices ``0 .. n_runs - 1``).
    seed : int
        Family seed.
    samples : int
        Samples per closed-loop run.
    clean_integrating : int
        Extra clean runs with at least one integrating output.
    jobs : int
        Worker processes.
    options : StructuresOptions
    element_window : str
        The analysis's ``element_window`` (``"model"``, its default, or ``"full"``).
    noise_candidate : bool
        Add a channel of white noise to every log and try it as a candidate (:func:`run_one`).
    confirm_responses : bool
        The analysis's ``confirm_responses`` (default False, the analysis's default).
    progress : callable, optional
        ``progress(done, total, record)`` after each run.

    Returns
    -------
    dict
        ``config``, ``summary`` (:func:`score` of the main runs), ``clean_integrating`` (the
        false-alarm figures of the extra runs) and ``runs`` (every record).
    """
    if int(n_runs) != n_runs or n_runs < 0 or clean_integrating < 0 or n_runs + clean_integrating < 1:
        raise ValueError(f"n_runs, clean_integrating: expected integers >= 0, at least one run, got "
                         f"{n_runs!r}, {clean_integrating!r}")
    tasks = [(seed, k, samples, options, False, element_window, noise_candidate, confirm_responses)
             for k in range(int(n_runs))]
    tasks += [(seed, CLEAN_INDEX_OFFSET + k, samples, options, True, element_window, noise_candidate, confirm_responses)
              for k in range(int(clean_integrating))]
    t0 = time.perf_counter()
    records = sorted(map_runs(_run_one_star, tasks, jobs, progress), key=lambda r: r["index"])
    main_runs = [r for r in records if r["index"] < CLEAN_INDEX_OFFSET]
    extra = [r for r in records if r["index"] >= CLEAN_INDEX_OFFSET]
    return {"config": {"runs": int(n_runs), "clean_integrating": int(clean_integrating), "seed": int(seed),
                       "samples": int(samples), "alpha": AnalysisOptions().alpha, "jobs": int(jobs),
                       "element_window": element_window, "noise_candidate": bool(noise_candidate),
                       "confirm_responses": bool(confirm_responses),
                       "options": _plain(options), "repair_horizon": REPAIR_HORIZON,
                       "repair_tolerance": REPAIR_TOLERANCE, "wall_time_s": time.perf_counter() - t0,
                       "machine": {"python": platform.python_version(), "platform": platform.platform(),
                                   "cpu_count": os.cpu_count()}},
            "summary": score(main_runs) if main_runs else None,
            "clean_integrating": score(extra)["false_alarms_integrating"] if extra else None,
            "runs": records}


def _plain(opts) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(opts).items()}


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.1f}%"


def _f3(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def format_table(result: dict) -> str:
    """The figures as plain text (what ``main`` prints)."""
    cfg = result["config"]
    alpha = cfg["alpha"]
    lines = [f"Structures Monte-Carlo: {cfg['runs']} runs (+{cfg['clean_integrating']} clean integrating), seed "
             f"{cfg['seed']}, {cfg['samples']} samples, alpha {alpha}, element window {cfg['element_window']}, "
             f"{'confirmed given the other responses, ' if cfg.get('confirm_responses') else ''}"
             f"wall {cfg['wall_time_s']:.0f} s"]
    s = result["summary"]
    if s:
        e, fa, fi, rp = s["element"], s["false_alarms"], s["false_alarms_integrating"], s["repair"]
        lines += [
            f"false alarms, clean runs: {fa['located']}/{fa['runs']} with a located element "
            f"({_pct(fa['rate_element'])}), "
            f"{fa['rows']}/{fa['runs']} with a flagged row ({_pct(fa['rate_row'])})",
            f"  of them with an integrating output: {fi['located']}/{fi['runs']} ({_pct(fi['rate_element'])})",
            f"element precision {_f3(e['precision'])} (hits {e['tp']}, false positives {e['fp']})",
            f"element recall, identifiable (not ambiguous) {_f3(e['recall'])} ({e['tp']}/{e['tp'] + e['fn']}); "
            f"ambiguous counted as a miss {_f3(e['recall_all'])} ({e['tp']}/{e['tp'] + e['fn'] + e['amb_true']})",
            f"ambiguous: mismatched {e['amb_true']} (column measured collinear: {e['amb_true_collinear']}), "
            f"clean {e['amb_clean']}",
            f"released (flagged, explained by the row's other located elements): mismatched "
            f"{e.get('released_true', 0)}, clean {e.get('released_clean', 0)}",
            f"repair: step response within {100 * REPAIR_TOLERANCE:.0f}% of the plant's over {REPAIR_HORIZON} samples "
            f"on {rp['within']}/{rp['scored']} located mismatched elements ({_pct(rp['fraction_within'])}); "
            f"false positives kept within: {rp['fp_within']}/{rp['fp_scored']}",
            "recall by kind (hits/(hits+misses); ambiguous apart):"]
        ev = s.get("effect_vs_detectable")
        if ev:
            lines.insert(-1, f"not ambiguous, by the mismatch's effect on the window (RMS of the plant-minus-model "
                             f"response over the model's) against the report's detectable gain change: at or above "
                             f"it {_f3(ev['recall_at_or_above'])} ({ev['hit']}/{ev['hit'] + ev['miss']}), below it "
                             f"{_f3(ev['recall_below'])} ({ev['below_hit']}/{ev['below_hit'] + ev['below_miss']}), "
                             f"no value {ev['unknown']}")
        orc = s.get("oracle_power")
        if orc:
            hi, lo = ORACLE_BANDS
            lines.insert(-1, "not ambiguous, by an oracle's power to detect the mismatch (it knows the effect's exact "
                             "response and the noise model; bench.oracle): " + ", ".join(
                                 f"{label} {_f3(orc[k]['recall'])} ({orc[k]['hit']}/{orc[k]['hit'] + orc[k]['miss']})"
                                 for k, label in (("high", f"at least {hi}"), ("middle", f"{lo} to {hi}"),
                                                  ("low", f"below {lo}")))
                             + (f", no value {orc['unknown']['hit'] + orc['unknown']['miss']}"
                                if orc["unknown"]["hit"] + orc["unknown"]["miss"] else ""))
        for table in (s["recall_by_kind"], s["recall_by_role"]):
            for key in sorted(table, key=lambda k: (KINDS.index(k) if k in KINDS else len(KINDS), k)):
                c = table[key]
                lines.append(f"  {key:18} {_f3(c['recall'])} ({c['hit']}/{c['hit'] + c['miss']}), ambiguous "
                             f"{c['ambiguous']}")
        rk = s.get("reported_kind", {})
        if rk:
            lines.append("kind reported on the hits (right: the kind the mismatch is; what was said):")
            for key in sorted(rk, key=lambda k: KINDS.index(k) if k in KINDS else len(KINDS)):
                c = rk[key]
                said = ", ".join(f"{k} {n}" for k, n in sorted(c["said"].items(), key=lambda kv: (-kv[1], str(kv[0]))))
                lines.append(f"  {key:18} {c['expected']:14} {c['right']}/{c['hits']} ({said})")
        la = s.get("located_after")
        if la:
            lines.append(f"elements the repaired model's detection locates that the first did not: {la['new']} (in "
                         f"{la['new_runs']} runs), drawn {la['new_drawn']}; located elements it locates again: "
                         f"{la['again']} (drawn {la['again_drawn']})")
        lines.append(f"median analyze time with the repair {_f3(s['median_analyze_time_s'])} s; errors "
                     f"{len(s['errors'])}")
    ci = result["clean_integrating"]
    if ci:
        lines.append(f"clean runs with an integrating output: {ci['located']}/{ci['runs']} with a located element "
                     f"({_pct(ci['rate_element'])}), {ci['rows']}/{ci['runs']} with a flagged row "
                     f"({_pct(ci['rate_row'])}); alpha {alpha}")
    if cfg.get("noise_candidate"):
        runs = [r for r in result["runs"] if "error" not in r]
        hit = [r for r in runs if r.get("candidates_located")]
        lines.append(f"a channel of white noise tried as a candidate in every run: located in {len(hit)} of "
                     f"{len(runs)} runs")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.structures_mc", description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=300, help="random closed loops (default 300)")
    parser.add_argument("--clean-integrating", type=int, default=500,
                        help="extra clean runs with an integrating output (default 500)")
    parser.add_argument("--seed", type=int, default=0, help="family seed (default 0)")
    parser.add_argument("--samples", type=int, default=3000, help="samples per run (default 3000)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--no-dither-fat", action="store_true", help="no input dither on plants with more inputs "
                        "than outputs (some of their elements then cannot be told apart)")
    parser.add_argument("--element-window", choices=("model", "full"), default="model",
                        help="the analysis's element_window (default model, the analysis's default)")
    parser.add_argument("--noise-candidate", action="store_true",
                        help="add a channel of white noise to every log and try it as a candidate")
    parser.add_argument("--lost-lag", action="store_true",
                        help="every mismatch a lost lag: the model has a second lag the plant's element lacks "
                        "(default output structures_mc_lost_lag.json)")
    parser.add_argument("--gained-lag", action="store_true",
                        help="every mismatch a lag the plant's element has and the model's lacks (a pure gain or a "
                        "pure integrator in the model; default output structures_mc_gained_lag.json)")
    parser.add_argument("--pure-gains", action="store_true",
                        help="the first-order input elements without lead are pure gains in the plant and the model, "
                        "every mismatch a gain or dead-time change of one or its lag lost (default output structures_mc_pure_gains.json)")
    parser.add_argument("--two-lag-leads", action="store_true",
                        help="every lead-lag element has a second lag too (default output structures_mc_two_lag_leads.json)")
    parser.add_argument("--lost-pair", action="store_true",
                        help="every mismatch a lost pair: the model's first-order element has a lead and a second lag "
                        "that cancel, and a gain off (default output structures_mc_lost_pair.json)")
    parser.add_argument("--confirm-responses", action="store_true",
                        help="the analysis's confirm_responses on (default output structures_mc_confirm.json)")
    parser.add_argument("--out", type=Path, default=None, help="JSON output")
    parser.add_argument("--quiet", action="store_true", help="no per-run progress lines")
    args = parser.parse_args(argv)
    if args.out is None:
        args.out = DEFAULT_OUT.with_name("structures_mc_lost_lag.json") if args.lost_lag else \
            DEFAULT_OUT.with_name("structures_mc_gained_lag.json") if args.gained_lag else \
            DEFAULT_OUT.with_name("structures_mc_pure_gains.json") if args.pure_gains else \
            DEFAULT_OUT.with_name("structures_mc_two_lag_leads.json") if args.two_lag_leads else \
            DEFAULT_OUT.with_name("structures_mc_lost_pair.json") if args.lost_pair else \
            DEFAULT_OUT.with_name("structures_mc_confirm.json") if args.confirm_responses else DEFAULT_OUT
    if args.runs < 0 or args.clean_integrating < 0 or args.samples < 100 or args.jobs < 1:
        parser.error("--runs and --clean-integrating must be >= 0, --jobs >= 1 and --samples >= 100")

    def progress(done, total, rec):
        if args.quiet:
            return
        if "error" in rec:
            print(f"[{done}/{total}] run {rec['index']}: ERROR {rec['error']}", flush=True)
            return
        truth = {(m["output"], m["column"]) for m in rec["mismatches"]}
        loc = {tuple(x) for x in rec["located"]}
        print(f"[{done}/{total}] run {rec['index']} {'x'.join(map(str, rec['shape']))} {len(truth)} mism "
              f"+{len(loc & truth)} fp{len(loc - truth)} miss{len(truth - loc)} amb{len(rec['ambiguous'])}", flush=True)

    try:
        result = run_structures_mc(args.runs, args.seed, args.samples, clean_integrating=args.clean_integrating,
                                   jobs=args.jobs, options=StructuresOptions(dither_fat=not args.no_dither_fat,
                                                                             lost_lag=args.lost_lag,
                                                                             gained_lag=args.gained_lag,
                                                                             pure_gains=args.pure_gains,
                                                                             two_lag_leads=args.two_lag_leads,
                                                                             lost_pair=args.lost_pair),
                                   element_window=args.element_window, noise_candidate=args.noise_candidate,
                                   confirm_responses=args.confirm_responses, progress=progress)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_table(result))
    write_json(args.out, result, default=_json_default)
    return 0


def _json_default(x):
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return float(x)
    if isinstance(x, np.ndarray):
        return x.tolist()
    if dataclasses.is_dataclass(x):
        return dataclasses.asdict(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


if __name__ == "__main__":
    sys.exit(main())
