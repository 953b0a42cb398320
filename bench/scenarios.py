"""Random closed-loop mismatch scenarios for the Monte-Carlo benchmark (issue 3).

A scenario is a random first-order-plus-dead-time (FOPDT) plant, a controller model equal to it
except for 0 to 3 mismatched elements, and the closed-loop experiment (MPC tuning, setpoint PRBS,
optional input dither, the paper's noise).  It is a pure function of ``(seed, index)``: the same
pair always gives the same plant, model, mismatches and closed-loop seed, whatever other
scenarios are drawn, in whatever order or process.

Distribution (:class:`ScenarioOptions` holds every number):

* size: ``n_outputs`` and ``n_inputs`` drawn independently and uniformly from 2..8, so most
  plants are non-square (tall: more outputs than inputs; fat: more inputs than outputs);
* plant elements: gain magnitude log-uniform in [0.5, 5] with a random sign, time constant
  uniform in [10, 80] s, delay uniform in 0..8 samples (sample time 1 s); every element is
  non-zero (a dense plant); the time constant >= 10 s makes every element strictly proper;
* mismatched elements: 0, 1, 2 or 3 (uniform; at most ``n_outputs * n_inputs``), at distinct
  random positions, each of a kind drawn uniformly from ``gain``, ``time_constant``, ``delay``,
  ``missing`` and ``mixed``, with a relative size ``s`` uniform in [0.2, 1.0]:

  - ``gain``: model gain ``K (1 + s)`` or ``K (1 - s)`` (direction at random);
  - ``time_constant``: ``tau (1 + s)`` or ``tau (1 - min(s, 0.9))`` (a decrease is capped so the
    model keeps a lag);
  - ``delay``: ``theta +- max(1, round(s theta))`` samples (a decrease only when the result stays
    >= 0, so a plant delay of 0 always gets a larger model delay);
  - ``missing``: model gain 0 where the plant has an element (size 1);
  - ``mixed``: two or three of gain / time constant / delay, each with its own size (the
    reported size is the largest);

* MPC: the paper's tuning: Hp = 100, Hc = 30, output weight 1, input weight 1,
  input-rate weight 0.1, unconstrained;
* excitation: PRBS setpoints of amplitude 1 switching with probability 1/2 (0 to Nyquist, as in the
  paper) on every output; in a fraction ``dither_fraction`` (default 0.3) of the runs an additive
  PRBS input dither of amplitude 0.1 on every input (the paper's second experiment, case 3.3);
* noise: :class:`~mpm_monitor.sim.plant.DisturbanceOptions` defaults (the paper's: disturbance white
  noise std 7.5e-3 through z/(z - 0.95), measurement noise std 5e-3).

Ground truth of collinearity: with more inputs than outputs and no dither the inputs are driven by
``n_outputs`` setpoints (plus a small noise-driven part), so ``n_inputs - n_outputs`` directions of
``u`` are excited only by the noise -- the inputs move (nearly) collinearly and some elements cannot
be told apart.  :attr:`Scenario.collinear_expected` flags these runs, and
:func:`input_separability` measures, from the data, how far each input is from a combination of the
others (``1 - rho_max^2``).
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np
import scipy.linalg as sla

from mpm_monitor.core.model import PlantModel
from mpm_monitor.sim.closed_loop import ExcitationOptions
from mpm_monitor.sim.excitation import PrbsOptions
from mpm_monitor.sim.mpc import MpcOptions
from mpm_monitor.sim.plant import DisturbanceOptions

KINDS = ("gain", "time_constant", "delay", "missing", "mixed")


def check_count_ranges(opts) -> None:
    """Refuse options whose ``min_size .. max_size`` or ``min_mismatches .. max_mismatches`` is empty
    (shared by the scenario distributions of the benchmarks)."""
    if not 1 <= opts.min_size <= opts.max_size:
        raise ValueError(f"min_size, max_size: expected 1 <= min_size <= max_size, got {opts.min_size}, "
                         f"{opts.max_size}")
    if not 0 <= opts.min_mismatches <= opts.max_mismatches:
        raise ValueError(f"min_mismatches, max_mismatches: expected 0 <= min <= max, got "
                         f"{opts.min_mismatches}, {opts.max_mismatches}")


@dataclasses.dataclass(frozen=True)
class ScenarioOptions:
    """The distribution scenarios are drawn from (see the module docstring).

    Attributes
    ----------
    min_size, max_size : int
        Range of ``n_outputs`` and of ``n_inputs`` (each drawn independently).
    gain_range : tuple of float
        Range of ``|K|`` (log-uniform).
    tau_range : tuple of float
        Range of the time constants, seconds.
    max_delay : int
        Largest plant delay, samples.
    min_mismatches, max_mismatches : int
        Range of the number of mismatched elements (uniform in min..max; default 0..3).
    size_range : tuple of float
        Range of the relative mismatch size ``s``.
    kinds : tuple of str
        Mismatch kinds drawn uniformly.
    dither_fraction : float
        Probability that a run has input dither.
    dither_amplitude : float
        Amplitude of the input dither PRBS.
    dither_fat : bool
        Always dither a plant with more inputs than outputs (without it the MPC drives its inputs
        in an ``n_outputs``-dimensional subspace and some elements cannot be told apart by any
        method).
    setpoint_amplitude : float
        Amplitude of the setpoint PRBS.
    setpoint_switch_probability : float
        Probability of a setpoint switch at each sample once ``setpoint_min_hold`` has elapsed (0.5:
        the paper's flat spectrum).
    setpoint_min_hold : int
        Least samples between two setpoint switches.
    prediction_horizon, control_horizon : int
        MPC horizons, samples.
    sample_time : float
        Seconds per sample.
    delay_shift_range : tuple of int, optional
        A delay mismatch shifts the delay by a whole number of samples drawn uniformly from this range
        (inclusive; a decrease with probability 1/2 where the plant's delay allows it) instead of
        ``max(1, round(s theta))`` (:data:`FAR_DELAYS`).  None: the default draw.
    """

    min_size: int = 2
    max_size: int = 8
    gain_range: tuple = (0.5, 5.0)
    tau_range: tuple = (10.0, 80.0)
    max_delay: int = 8
    min_mismatches: int = 0
    max_mismatches: int = 3
    size_range: tuple = (0.2, 1.0)
    kinds: tuple = KINDS
    dither_fraction: float = 0.3
    dither_amplitude: float = 0.1
    dither_fat: bool = False
    setpoint_amplitude: float = 1.0
    setpoint_switch_probability: float = 0.5
    setpoint_min_hold: int = 1
    prediction_horizon: int = 100
    control_horizon: int = 30
    sample_time: float = 1.0
    delay_shift_range: Optional[tuple] = None

    def __post_init__(self):
        check_count_ranges(self)
        if self.delay_shift_range is not None:
            lo, hi = self.delay_shift_range
            if not 1 <= lo <= hi:
                raise ValueError(f"delay_shift_range: expected 1 <= low <= high samples, got {self.delay_shift_range!r}")
        bad = [k for k in self.kinds if k not in KINDS]
        if bad or not self.kinds:
            raise ValueError(f"kinds: expected a non-empty subset of {', '.join(KINDS)}, got {self.kinds!r}")
        if not 0.0 <= self.dither_fraction <= 1.0:
            raise ValueError(f"dither_fraction: expected a number in [0, 1], got {self.dither_fraction!r}")
        lo, hi = self.size_range
        if not 0.0 < lo <= hi <= 1.0:
            raise ValueError(f"size_range: expected 0 < low <= high <= 1, got {self.size_range!r}")


#: Setpoints moved in steps, as operators move them: each held at least 60 samples, then switched with
#: probability 1 % a sample (about 30 steps per setpoint in 3000 samples); ``--setpoint-steps`` of bench.monte_carlo.
SETPOINT_STEPS = ScenarioOptions(setpoint_switch_probability=0.01, setpoint_min_hold=60)

#: Delays far from the model's: one or two mismatched elements a run, each a delay shifted by 11 to 30 samples (more
#: than the repair's default ``max_delay_shift`` of 10) on plants with delays up to 40 samples (``--far-delays`` of
#: bench.repair_mc).
FAR_DELAYS = ScenarioOptions(kinds=("delay",), min_mismatches=1, max_mismatches=2, max_delay=40,
                             delay_shift_range=(11, 30))

#: Small loops: 1 to 3 outputs and 1 to 3 inputs (the fat ones 1x2, 1x3 and 2x3), the default design otherwise
#: (``--small`` of bench.experiment_mc: the experiment's prediction where one or two outputs tie the inputs).
SMALL = ScenarioOptions(min_size=1, max_size=3)

#: Still loops: every setpoint held at 0 and no dither, so the inputs move only with the controller's feedback
#: of the noise (``--still`` of bench.monte_carlo, bench.detectability and bench.experiment_mc).
STILL = ScenarioOptions(setpoint_amplitude=0.0, dither_fraction=0.0)


@dataclasses.dataclass(frozen=True)
class Mismatch:
    """One mismatched element.

    Attributes
    ----------
    output, input : int
        Row and column of the element.
    kind : str
        One of :data:`KINDS`.
    size : float
        Relative size of the change (largest over the changed parameters; 1 for ``missing``).
    plant : dict
        ``gain``, ``time_constant``, ``delay`` (seconds) of the plant element.
    model : dict
        The same for the model element.
    """

    output: int
    input: int
    kind: str
    size: float
    plant: dict
    model: dict


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A random closed-loop mismatch experiment.

    Attributes
    ----------
    seed, index : int
        The pair the scenario was drawn from.
    plant : PlantModel
        True plant ``P``.
    model : PlantModel
        Controller model ``Phat``.
    mismatches : tuple of Mismatch
    truth : ndarray of bool, shape (n_outputs, n_inputs)
        ``True`` where ``Delta_ij != 0``.
    dither : bool
        Whether the inputs carry a dither.
    mpc : MpcOptions
    excitation : ExcitationOptions
    disturbance : DisturbanceOptions
    loop_seed : int
        Seed of :func:`mpm_monitor.sim.closed_loop.run_closed_loop`.
    """

    seed: int
    index: int
    plant: PlantModel
    model: PlantModel
    mismatches: tuple
    truth: np.ndarray
    dither: bool
    mpc: MpcOptions
    excitation: ExcitationOptions
    disturbance: DisturbanceOptions
    loop_seed: int

    @property
    def shape(self) -> tuple:
        """``(n_outputs, n_inputs)``."""
        return (self.plant.n_outputs, self.plant.n_inputs)

    @property
    def shape_class(self) -> str:
        """``"square"``, ``"tall"`` (more outputs than inputs) or ``"fat"`` (more inputs)."""
        ny, nu = self.shape
        return "square" if ny == nu else ("tall" if ny > nu else "fat")

    @property
    def collinear_expected(self) -> bool:
        """More inputs than outputs and no dither: some input directions are excited by noise only."""
        ny, nu = self.shape
        return nu > ny and not self.dither

    def describe(self) -> dict:
        """Plain-JSON description (plant, model and mismatches)."""
        return {
            "seed": self.seed, "index": self.index, "shape": list(self.shape), "shape_class": self.shape_class,
            "dither": self.dither, "collinear_expected": self.collinear_expected, "loop_seed": self.loop_seed,
            "mismatches": [{"output": m.output, "input": m.input, "kind": m.kind, "size": round(m.size, 4),
                            "plant": m.plant, "model": m.model} for m in self.mismatches],
            "plant": self.plant.to_dict(),
        }


def _names(n: int, prefix: str) -> tuple:
    return tuple(f"{prefix}{k + 1}" for k in range(n))


def _element(gain, tau, delay) -> dict:
    return {"gain": float(gain), "time_constant": float(tau), "delay": float(delay)}


def _mismatch_element(rng: np.random.Generator, kind: str, gain: float, tau: float, delay_samples: int,
                      opts: ScenarioOptions):
    """New (gain, tau, delay_samples) of the model element and the relative size of the change."""
    lo, hi = opts.size_range

    def draw():
        return float(rng.uniform(lo, hi))

    def new_gain():
        s = draw()
        return gain * (1.0 + s if rng.random() < 0.5 else 1.0 - s), s

    def new_tau():
        s = draw()
        return (tau * (1.0 + s) if rng.random() < 0.5 else tau * (1.0 - min(s, 0.9))), s

    def new_delay():
        s = draw()
        shift = max(1, int(round(s * delay_samples)))
        if opts.delay_shift_range is not None:
            shift = int(rng.integers(opts.delay_shift_range[0], opts.delay_shift_range[1] + 1))
            s = shift / max(1, delay_samples)
        down = rng.random() < 0.5 and delay_samples - shift >= 0
        return delay_samples - shift if down else delay_samples + shift, s

    g, t, dl = gain, tau, delay_samples
    if kind == "gain":
        g, size = new_gain()
    elif kind == "time_constant":
        t, size = new_tau()
    elif kind == "delay":
        dl, size = new_delay()
    elif kind == "missing":
        g, size = 0.0, 1.0
    elif kind == "mixed":
        n_parts = int(rng.integers(2, 4))
        parts = rng.permutation(["gain", "time_constant", "delay"])[:n_parts]
        sizes = []
        for part in parts:
            if part == "gain":
                g, s = new_gain()
            elif part == "time_constant":
                t, s = new_tau()
            else:
                dl, s = new_delay()
            sizes.append(s)
        size = max(sizes)
    else:  # pragma: no cover - guarded by ScenarioOptions
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    return g, t, dl, size


def make_scenario(seed: int, index: int, options: ScenarioOptions = ScenarioOptions(),
                  n_mismatches: Optional[int] = None) -> Scenario:
    """Draw scenario ``index`` of the family ``seed``.

    Parameters
    ----------
    seed : int
        Family seed (>= 0).
    index : int
        Run index (>= 0).
    options : ScenarioOptions
        The distribution.
    n_mismatches : int, optional
        Force the number of mismatched elements (default: drawn from 0..max_mismatches).

    Returns
    -------
    Scenario
        Deterministic in ``(seed, index, options, n_mismatches)``.
    """
    ss = np.random.SeedSequence([int(seed), int(index)])
    rng = np.random.default_rng(ss)
    opts = options
    ny = int(rng.integers(opts.min_size, opts.max_size + 1))
    nu = int(rng.integers(opts.min_size, opts.max_size + 1))
    glo, ghi = opts.gain_range
    gain = np.exp(rng.uniform(np.log(glo), np.log(ghi), (ny, nu))) * np.where(rng.random((ny, nu)) < 0.5, -1.0, 1.0)
    gain = np.round(gain, 3)
    tau = np.round(rng.uniform(opts.tau_range[0], opts.tau_range[1], (ny, nu)), 1)
    delay = rng.integers(0, opts.max_delay + 1, (ny, nu))
    ts = opts.sample_time
    plant = PlantModel(sample_time=ts, inputs=_names(nu, "u"), outputs=_names(ny, "y"), gain=gain,
                       time_constant=tau, delay=delay * ts, name=f"random plant (seed {seed}, run {index})")
    k = int(rng.integers(opts.min_mismatches, opts.max_mismatches + 1)) if n_mismatches is None else int(n_mismatches)
    k = min(k, ny * nu)
    positions = rng.choice(ny * nu, size=k, replace=False)
    m_gain, m_tau, m_delay = gain.copy(), tau.copy(), delay.copy()
    mismatches = []
    truth = np.zeros((ny, nu), dtype=bool)
    for pos in sorted(int(p) for p in positions):
        i, j = divmod(pos, nu)
        kind = str(opts.kinds[int(rng.integers(len(opts.kinds)))])
        g, t, dl, size = _mismatch_element(rng, kind, gain[i, j], tau[i, j], int(delay[i, j]), opts)
        m_gain[i, j], m_tau[i, j], m_delay[i, j] = g, t, dl
        truth[i, j] = True
        mismatches.append(Mismatch(output=i, input=j, kind=kind, size=float(size),
                                   plant=_element(gain[i, j], tau[i, j], delay[i, j] * ts),
                                   model=_element(g, t, dl * ts)))
    model = plant.replace(gain=m_gain, time_constant=m_tau, delay=m_delay * ts,
                          name=f"random model (seed {seed}, run {index}, {k} mismatched)")
    dither = bool(rng.random() < opts.dither_fraction)
    if opts.dither_fat and nu > ny:
        dither = True   # the experiment design that makes a fat plant's elements identifiable
    excitation = ExcitationOptions(
        setpoint=PrbsOptions(amplitude=opts.setpoint_amplitude, switch_probability=opts.setpoint_switch_probability,
                             min_hold=opts.setpoint_min_hold),
        dither=PrbsOptions(amplitude=opts.dither_amplitude, switch_probability=0.5) if dither else None)
    mpc = MpcOptions(prediction_horizon=opts.prediction_horizon, control_horizon=opts.control_horizon,
                     output_weight=1.0, input_weight=1.0, input_rate_weight=0.1)
    loop_seed = int(rng.integers(0, 2**31 - 1))
    truth.setflags(write=False)
    return Scenario(seed=int(seed), index=int(index), plant=plant, model=model, mismatches=tuple(mismatches),
                    truth=truth, dither=dither, mpc=mpc, excitation=excitation, disturbance=DisturbanceOptions(),
                    loop_seed=loop_seed)


def input_separability(u: np.ndarray, max_lag: int = 10) -> np.ndarray:
    """Ground truth of collinear inputs: ``1 - rho_max^2`` of each input against the others.

    ``rho_max`` is the largest canonical correlation between the block ``u_j(k), .., u_j(k - L)``
    and the blocks of every other input over the same lags.  Near 0: some combination of the
    input's recent values is a combination of the other inputs' -- the closed loop drives it
    (dynamically) collinearly with them, so its elements cannot be separated from theirs.  (The
    same idea as the methods' own checks, on a different lag window, computed from the data only.)

    Parameters
    ----------
    u : ndarray, shape (n_samples, n_inputs)
    max_lag : int
        ``L``, samples.

    Returns
    -------
    ndarray, shape (n_inputs,)
        Values in [0, 1] (1 for a single input).
    """
    u = np.asarray(u, dtype=float)
    n, nu = u.shape
    out = np.ones(nu)
    if nu == 1:
        return out
    L = int(max_lag)
    uc = u - u.mean(axis=0)
    X = np.column_stack([uc[L - m:n - m, j] for j in range(nu) for m in range(L + 1)])
    X = X / np.maximum(np.sqrt(np.sum(X * X, axis=0)), 1e-300)
    G = X.T @ X
    w = L + 1
    for j in range(nu):
        blk = np.arange(j * w, (j + 1) * w)
        oth = np.setdiff1d(np.arange(nu * w), blk)
        g_jj, g_jo = G[np.ix_(blk, blk)], G[np.ix_(blk, oth)]
        schur = g_jj - g_jo @ np.linalg.pinv(G[np.ix_(oth, oth)], rcond=1e-13, hermitian=True) @ g_jo.T
        try:
            ev = sla.eigh(0.5 * (schur + schur.T), g_jj, eigvals_only=True)
            out[j] = float(np.clip(ev.min(), 0.0, 1.0))
        except (sla.LinAlgError, ValueError):
            out[j] = 0.0
    return out
