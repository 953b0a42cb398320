"""Batch closed loop: plant, MPC, excitation and measured disturbances for N samples without ROS.

The ROS nodes wrap the same objects (:class:`~mpm_monitor.sim.plant.PlantSimulator`,
:class:`~mpm_monitor.sim.mpc.InternalModelMpc`, :class:`~mpm_monitor.sim.excitation.PrbsGenerator`,
:class:`~mpm_monitor.sim.excitation.MeasuredDisturbanceGenerator`), so a batch run and a run through
the nodes with the same seeds produce the same samples.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from ..core.errors import ConfigurationError
from ..core.logged_data import LoggedData
from ..core.model import PlantModel
from .excitation import (
    MeasuredDisturbanceGenerator,
    MeasuredDisturbanceOptions,
    PrbsGenerator,
    PrbsOptions,
    ZeroGenerator,
)
from .mpc import InternalModelMpc, MpcOptions
from .plant import DisturbanceOptions, PlantSimulator


@dataclasses.dataclass
class ClosedLoopLog:
    """Signals of a closed-loop run, one row per sample.

    Attributes
    ----------
    t : ndarray, shape (n_samples,)
        Time in seconds.
    r : ndarray, shape (n_samples, n_outputs)
        Setpoints.
    u : ndarray, shape (n_samples, n_inputs)
        Plant inputs (including any dither).
    y : ndarray, shape (n_samples, n_outputs)
        Measured outputs.
    yhat : ndarray, shape (n_samples, n_outputs)
        The controller's model output ``Phat u``.
    d : ndarray, shape (n_samples, n_outputs)
        Prediction error ``y - yhat``.
    eps : ndarray, shape (n_samples, n_outputs)
        Controller input ``r - d``.
    disturbance : ndarray, shape (n_samples, n_outputs)
        The injected output disturbance ``v`` (simulation only).
    noise : ndarray, shape (n_samples, n_outputs)
        The injected measurement noise (simulation only).
    dither : ndarray, shape (n_samples, n_inputs)
        The additive input dither.
    inputs, outputs : tuple of str
        Channel names.
    sample_time : float
        Seconds per sample.
    dv : ndarray, shape (n_samples, n_disturbances)
        The plant's measured disturbances (shape (n_samples, 0) when it has none).
    disturbances : tuple of str
        Their names (the plant's).
    """

    t: np.ndarray
    r: np.ndarray
    u: np.ndarray
    y: np.ndarray
    yhat: np.ndarray
    d: np.ndarray
    eps: np.ndarray
    disturbance: np.ndarray
    noise: np.ndarray
    dither: np.ndarray
    inputs: tuple
    outputs: tuple
    sample_time: float
    dv: Optional[np.ndarray] = None
    disturbances: tuple = ()

    def __post_init__(self):
        self.disturbances = tuple(self.disturbances)
        if self.dv is None:
            self.dv = np.zeros((self.t.shape[0], len(self.disturbances)))

    @property
    def n_samples(self) -> int:
        return self.t.shape[0]

    def as_logged_data(self, source: str = "") -> LoggedData:
        """The setpoints, inputs and outputs as :class:`~mpm_monitor.core.logged_data.LoggedData`.

        What a user would hand to the analysis: ``t``, ``r``, ``u``, ``y``, the measured disturbances
        ``dv``, the channel names and the sample time of this run (the arrays are shared, not copied).

        Parameters
        ----------
        source : str
            Where the data came from, for messages (e.g. ``"paper case 3.2 (seed 1)"``).
        """
        return LoggedData(t=self.t, r=self.r, u=self.u, y=self.y, inputs=self.inputs, outputs=self.outputs,
                          sample_time=self.sample_time, source=source, dv=self.dv, disturbances=self.disturbances)


def operating_point_conflict(plant: PlantModel, controller_model: PlantModel) -> str:
    """What differs between the operating points of the plant's and the controller model's files ('' when nothing).

    The loop is simulated in deviations from one operating point (:func:`at_operating_point` writes its log at
    it): the two files' ``input_nominal``, ``output_nominal`` and the ``disturbance_nominal`` of the model's
    measured disturbances (by name, among the plant's) must agree.  Returns e.g.
    ``"input_nominal: u1 10 vs 12"``: the first key that differs, each channel that differs with both values.
    """
    pairs = [("input_nominal", plant.inputs, plant.input_nominal, controller_model.input_nominal),
             ("output_nominal", plant.outputs, plant.output_nominal, controller_model.output_nominal)]
    index = {name: j for j, name in enumerate(plant.disturbances)}
    shared = [name for name in controller_model.disturbances if name in index]
    pairs.append(("disturbance_nominal", shared,
                  np.array([plant.disturbance_nominal[index[name]] for name in shared], dtype=float),
                  np.array([controller_model.disturbance_nominal[controller_model.disturbances.index(name)]
                            for name in shared], dtype=float)))
    for key, names, of_plant, of_model in pairs:
        differ = [f"{name} {a:g} vs {b:g}" for name, a, b in zip(names, of_plant, of_model) if a != b]
        if differ:
            return f"{key}: {', '.join(differ)}"
    return ""


def at_operating_point(log: ClosedLoopLog, plant: PlantModel) -> ClosedLoopLog:
    """``log`` with its setpoints, outputs, inputs and measured disturbances at the plant's operating point.

    The loop runs in deviation variables; a model file's ``output_nominal``, ``input_nominal`` and
    ``disturbance_nominal`` say where those deviations are taken from, and every analysis subtracts them from
    the logged values.  So a log written for the analysis carries them: ``r + output_nominal``, ``y +
    output_nominal``, ``u + input_nominal``, ``dv + disturbance_nominal`` (the prediction error, the model's
    output and the other internal signals stay as they are).  ``log`` itself when the plant has no operating
    point (every nominal 0): the same arrays, bit for bit.

    Parameters
    ----------
    log : ClosedLoopLog
        A run of :func:`run_closed_loop` on ``plant``.
    plant : PlantModel
        Its plant (whose channels the log has).

    Returns
    -------
    ClosedLoopLog
    """
    def at(x, x0):          # a channel without an operating point keeps its own array
        return x + x0 if np.any(x0) else x

    y0, u0, d0 = plant.output_nominal, plant.input_nominal, plant.disturbance_nominal
    if not (np.any(y0) or np.any(u0) or np.any(d0)):
        return log
    return dataclasses.replace(log, r=at(log.r, y0), y=at(log.y, y0), u=at(log.u, u0), dv=at(log.dv, d0))


@dataclasses.dataclass(frozen=True)
class ExcitationOptions:
    """Setpoint PRBS and optional input dither of a closed-loop experiment.

    Attributes
    ----------
    setpoint : PrbsOptions
        PRBS on every setpoint (paper: band 0 to Nyquist).
    dither : PrbsOptions or None
        PRBS added to every plant input (the paper's second experiment); None = no dither.
    dither_amplitudes : tuple of float or None
        Amplitude of the dither on every input, in input units (0: no dither on that input),
        instead of ``dither.amplitude`` on all of them (e.g. a recommended experiment,
        :class:`mpm_monitor.core.experiment.Experiment`); the PRBS switches as ``dither`` says.
    """

    setpoint: PrbsOptions = PrbsOptions()
    dither: Optional[PrbsOptions] = None
    dither_amplitudes: Optional[tuple] = None


def seeded_generators(seed: int) -> dict:
    """Independent random generators for the plant, setpoints, dither and measured disturbances from one seed.

    The first three are those of the runs before measured disturbances existed (a spawned
    sequence does not depend on how many are spawned after it), so their samples are unchanged.
    """
    plant_ss, sp_ss, dither_ss, dv_ss = np.random.SeedSequence(seed).spawn(4)
    return {"plant": np.random.default_rng(plant_ss), "setpoint": np.random.default_rng(sp_ss),
            "dither": np.random.default_rng(dither_ss), "measured_disturbance": np.random.default_rng(dv_ss)}


def controller_columns(plant: PlantModel, controller_model: PlantModel) -> np.ndarray:
    """Where the controller model's measured disturbances are among the plant's, int (n_disturbances of the model,).

    The controller's model may leave out some of the plant's measured disturbances (no feedforward
    from them) but has no other.

    Raises
    ------
    ConfigurationError
        A disturbance of the controller model that the plant does not have.
    """
    index = {name: j for j, name in enumerate(plant.disturbances)}
    unknown = [d for d in controller_model.disturbances if d not in index]
    if unknown:
        raise ConfigurationError(f"controller model: measured disturbance(s) {', '.join(unknown)} not among the "
                                 f"plant's ({', '.join(plant.disturbances) or 'none'})")
    return np.array([index[d] for d in controller_model.disturbances], dtype=int)


def run_closed_loop(plant: PlantModel, controller_model: PlantModel, n_samples: int, *,
                    seed: int = 0, mpc: MpcOptions = MpcOptions(),
                    excitation: ExcitationOptions = ExcitationOptions(),
                    disturbance: DisturbanceOptions = DisturbanceOptions(),
                    setpoints: Optional[np.ndarray] = None,
                    output_disturbance: Optional[np.ndarray] = None,
                    measured_disturbance: MeasuredDisturbanceOptions = MeasuredDisturbanceOptions(),
                    dv: Optional[np.ndarray] = None) -> ClosedLoopLog:
    """Simulate the internal-model MPC loop for ``n_samples`` samples.

    Parameters
    ----------
    plant : PlantModel
        The true plant ``P``.
    controller_model : PlantModel
        The controller's model ``Phat`` (same inputs and outputs as ``plant``; its measured
        disturbances, fed forward, are the plant's or some of them).
    n_samples : int
        Number of samples.
    seed : int
        Seed of every random source (noise, PRBS, dither, measured disturbances).
    mpc : MpcOptions
        Controller tuning.
    excitation : ExcitationOptions
        Setpoint PRBS and input dither.
    disturbance : DisturbanceOptions
        Disturbance and measurement noise.
    setpoints : ndarray, shape (n_samples, n_outputs), optional
        Given setpoints instead of the PRBS.
    output_disturbance : ndarray, shape (n_samples, n_outputs), optional
        An extra disturbance added to the outputs (e.g. an unmeasured step).
    measured_disturbance : MeasuredDisturbanceOptions
        The signal of the plant's measured disturbances (when it has some and ``dv`` is not given).
    dv : ndarray, shape (n_samples, n_disturbances), optional
        Given measured disturbances of the plant instead of the generated ones.

    Returns
    -------
    ClosedLoopLog
    """
    if plant.inputs != controller_model.inputs or plant.outputs != controller_model.outputs:
        raise ConfigurationError(
            f"plant and controller model must have the same inputs and outputs: plant {list(plant.inputs)} / "
            f"{list(plant.outputs)}, model {list(controller_model.inputs)} / {list(controller_model.outputs)}")
    if plant.sample_time != controller_model.sample_time:
        raise ConfigurationError(f"plant and controller model must have the same sample_time: "
                                 f"{plant.sample_time:g} s vs {controller_model.sample_time:g} s")
    if int(n_samples) != n_samples or n_samples < 1:
        raise ConfigurationError(f"n_samples: expected an integer >= 1, got {n_samples!r}")
    n = int(n_samples)
    ny, nu, nd = plant.n_outputs, plant.n_inputs, plant.n_disturbances
    ff = controller_columns(plant, controller_model)
    rngs = seeded_generators(seed)
    sim = PlantSimulator(plant, disturbance, rngs["plant"])
    ctrl = InternalModelMpc(controller_model, mpc)
    if setpoints is None:
        r_all = PrbsGenerator(ny, excitation.setpoint, rngs["setpoint"]).generate(n)
    else:
        r_all = np.asarray(setpoints, dtype=float).reshape(n, ny)
    if excitation.dither is None:
        dither_all = ZeroGenerator(nu).generate(n)
    elif excitation.dither_amplitudes is None:
        dither_all = PrbsGenerator(nu, excitation.dither, rngs["dither"]).generate(n)
    else:
        amplitudes = np.asarray(excitation.dither_amplitudes, dtype=float)
        if amplitudes.shape != (nu,) or not np.all(np.isfinite(amplitudes)) or np.any(amplitudes < 0):
            raise ConfigurationError(f"dither_amplitudes: expected {nu} finite numbers >= 0 (one per input), "
                                     f"got {excitation.dither_amplitudes!r}")
        unit = dataclasses.replace(excitation.dither, amplitude=1.0, offset=0.0)
        dither_all = excitation.dither.offset + PrbsGenerator(nu, unit, rngs["dither"]).generate(n) * amplitudes
    extra = None if output_disturbance is None else np.asarray(output_disturbance, dtype=float).reshape(n, ny)
    if dv is not None:
        dv_all = np.asarray(dv, dtype=float).reshape(n, nd)
    elif nd:
        dv_all = MeasuredDisturbanceGenerator(nd, measured_disturbance, rngs["measured_disturbance"]).generate(n)
    else:
        dv_all = np.zeros((n, 0))
    out = {k: np.zeros((n, ny)) for k in ("y", "yhat", "d", "eps", "v", "noise")}
    u_all = np.zeros((n, nu))
    use_dither = excitation.dither is not None
    for k in range(n):
        y = sim.measure(None if extra is None else extra[k], dv_all[k] if nd else None)
        u = ctrl.step(r_all[k], y, dither_all[k] if use_dither else None, dv_all[k, ff] if ff.size else None)
        sim.apply(u)
        out["y"][k] = y
        out["yhat"][k] = ctrl.yhat
        out["d"][k] = ctrl.prediction_error
        out["eps"][k] = ctrl.controller_input
        out["v"][k] = sim.last_disturbance
        out["noise"][k] = sim.last_noise
        u_all[k] = u
    t = np.arange(n) * plant.sample_time
    return ClosedLoopLog(t=t, r=r_all, u=u_all, y=out["y"], yhat=out["yhat"], d=out["d"], eps=out["eps"],
                         disturbance=out["v"], noise=out["noise"], dither=dither_all,
                         inputs=plant.inputs, outputs=plant.outputs, sample_time=plant.sample_time, dv=dv_all,
                         disturbances=plant.disturbances)
