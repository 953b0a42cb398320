"""A closed loop with an undeclared measured effect and other logged channels: the candidate channels' test case.

The plant is the paper's 3x3 Shell fractionator (:func:`~mpm_monitor.sim.cases.shell_plant`) with one
more column, a logged channel (``feed_temperature``) that drives one output through a first-order
element with dead time; the controller's model is the Shell model without that column (it matches
the plant otherwise).  The log also holds decoys the plant ignores -- a random walk
(``ambient``), a first-order filtered noise (``other_flow``) -- and a channel inside the loop,
``u2_flow``, a lagged response to the input ``u2`` (an intermediate flow the controller moves).  Only
``feed_temperature`` is a cause of the prediction error; ``u2_flow`` is not exogenous.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.elements import sample_parametric
from ..core.logged_data import LoggedData
from ..core.model import PlantModel
from .cases import paper_case
from .closed_loop import ClosedLoopLog, run_closed_loop
from .excitation import MeasuredDisturbanceGenerator, MeasuredDisturbanceOptions

#: The undeclared effect's channel and the decoys' names.
EFFECT_CHANNEL = "feed_temperature"
RANDOM_WALK_CHANNEL = "ambient"
FILTERED_NOISE_CHANNEL = "other_flow"
LOOP_CHANNEL = "u2_flow"


@dataclasses.dataclass(frozen=True)
class UndeclaredEffect:
    """The element of the undeclared channel on one output.

    Attributes
    ----------
    output : str
    gain : float
        Output units per channel unit (0: the channel has no effect).
    time_constant : float
        Seconds.
    delay : float
        Seconds, a multiple of the sample time (1 s).
    """

    output: str = "y1"
    gain: float = 0.8
    time_constant: float = 30.0
    delay: float = 4.0


#: The undeclared channel's signal: steps between random levels plus a filtered noise.
EFFECT_SIGNAL = MeasuredDisturbanceOptions(step_amplitude=1.0, switch_probability=0.02, min_hold=20, noise_std=0.1,
                                           noise_pole=0.9)


@dataclasses.dataclass
class UndeclaredEffectRun:
    """One run: the plant, the controller's model, the log as an analysis reads it, and the simulation.

    Attributes
    ----------
    plant : PlantModel
        The true plant, with the undeclared channel as a measured disturbance column.
    model : PlantModel
        The controller's model (no such column).
    data : LoggedData
        The log: the model's channels, and in ``extra`` the undeclared channel and the decoys.
    log : ClosedLoopLog
        The simulation (its ``noise`` and ``disturbance``: the noise floor of the prediction error).
    effect : UndeclaredEffect
    """

    plant: PlantModel
    model: PlantModel
    data: LoggedData
    log: ClosedLoopLog
    effect: UndeclaredEffect

    @property
    def noise_floor(self) -> dict:
        """``{output: RMS of the injected disturbance plus noise}``: the smallest prediction error a
        model can reach."""
        v = self.log.disturbance + self.log.noise
        return {o: float(np.sqrt(np.mean((v[:, i] - v[:, i].mean()) ** 2))) for i, o in enumerate(self.log.outputs)}


def random_walk(n: int, step_std: float, rng: np.random.Generator) -> np.ndarray:
    """A Gaussian random walk from 0, shape (n,)."""
    return np.cumsum(rng.normal(0.0, step_std, n))


def filtered_noise(n: int, std: float, pole: float, rng: np.random.Generator) -> np.ndarray:
    """First-order filtered white noise of standard deviation ``std``, started stationary, shape (n,)."""
    e = rng.normal(0.0, std * np.sqrt(1.0 - pole ** 2), n)
    x = np.empty(n)
    prev = rng.normal(0.0, std)
    for k in range(n):
        prev = pole * prev + e[k]
        x[k] = prev
    return x


def undeclared_effect_run(n_samples: int = 3000, seed: int = 1, effect: UndeclaredEffect = UndeclaredEffect(),
                          loop_channel: bool = True, excitation=None) -> UndeclaredEffectRun:
    """Simulate the Shell loop with the undeclared channel (see the module docstring).

    Parameters
    ----------
    n_samples : int
    seed : int
        Seed of the loop (:func:`~mpm_monitor.sim.closed_loop.run_closed_loop`); the channels use
        generators spawned from it too.
    effect : UndeclaredEffect
        The undeclared element (gain 0: the channel is one more decoy).
    loop_channel : bool
        Also log ``u2_flow``, the response of an intermediate flow to ``u2`` (gain 1.5, 10 s lag,
        2 s dead time, plus white noise of 0.02).
    excitation : ExcitationOptions, optional
        The setpoints' excitation instead of the paper's (e.g. rare setpoint steps).

    Returns
    -------
    UndeclaredEffectRun
    """
    case = paper_case("3.1")
    model = case.model.replace(name="shell 3x3 model (no feed temperature)")
    base = case.plant
    i = base.outputs.index(effect.output)
    gain = np.zeros((base.n_outputs, 1))
    tau = np.zeros((base.n_outputs, 1))
    delay = np.zeros((base.n_outputs, 1))
    gain[i, 0], tau[i, 0], delay[i, 0] = effect.gain, effect.time_constant, effect.delay
    plant = base.replace(disturbances=(EFFECT_CHANNEL,), gain=np.hstack([base.gain, gain]),
                         time_constant=np.hstack([base.time_constant, tau]), delay=np.hstack([base.delay, delay]),
                         lead=None, time_constant2=None, integrating=None,
                         name=f"shell 3x3 with {EFFECT_CHANNEL} on {effect.output}")
    ss_channel, ss_walk, ss_noise, ss_loop = np.random.SeedSequence([seed, 20260]).spawn(4)
    dv = MeasuredDisturbanceGenerator(1, EFFECT_SIGNAL, np.random.default_rng(ss_channel)).generate(n_samples)
    log = run_closed_loop(plant, model, n_samples, seed=seed, mpc=case.mpc, excitation=case.excitation if excitation is None else excitation,
                          disturbance=case.disturbance, dv=dv)
    extra = {EFFECT_CHANNEL: dv[:, 0],
             RANDOM_WALK_CHANNEL: random_walk(n_samples, 0.05, np.random.default_rng(ss_walk)),
             FILTERED_NOISE_CHANNEL: filtered_noise(n_samples, 0.5, 0.98, np.random.default_rng(ss_noise))}
    if loop_channel:
        flow = sample_parametric(1.5, 10.0, 2, plant.sample_time).respond(log.u[:, 1] - log.u[0, 1])
        extra[LOOP_CHANNEL] = flow + np.random.default_rng(ss_loop).normal(0.0, 0.02, n_samples)
    data = LoggedData(t=log.t, r=log.r, u=log.u, y=log.y, inputs=log.inputs, outputs=log.outputs,
                      sample_time=log.sample_time, source=f"undeclared-effect loop (seed {seed})", extra=extra)
    return UndeclaredEffectRun(plant=plant, model=model, data=data, log=log, effect=effect)
