"""The simulation cases: the three of the paper "A Novel Algorithm for Model-Plant Mismatch Detection for
Model Predictive Controllers" (Tsai, Gopaluni, Marshman and Chmelyk, IFAC ADCHEM 2015), and a level
case with an integrating output and a measured disturbance.

Each case gives the true plant, the controller's model, the expected located rows and elements,
the MPC tuning and the excitation.  Case 3.3 uses the input dither of the paper's second
experiment, since its plant is rank one and setpoint excitation alone drives the inputs
collinearly.  The level case (:func:`level_case`) is a 2x2 unit whose level integrates and whose
measured inflow feeds both outputs.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from ..core.model import PlantModel
from .closed_loop import ExcitationOptions
from .excitation import MeasuredDisturbanceOptions, PrbsOptions
from .mpc import MpcOptions
from .plant import DisturbanceOptions

#: The paper's cases.
CASE_NAMES = ("3.1", "3.2", "3.3")
#: Every simulation case: the paper's, then the level case (:func:`level_case`).
DEMO_CASES = CASE_NAMES + ("level",)

_SHELL_GAIN = [[4.05, 1.77, 5.88], [5.39, 5.72, 6.90], [4.38, 4.42, 7.20]]
_SHELL_TAU = [[50, 60, 50], [50, 60, 40], [33, 44, 19]]
_SHELL_DELAY = [[6, 7, 6], [4, 3, 3], [5, 5, 0]]


@dataclasses.dataclass(frozen=True)
class PaperCase:
    """A simulation case (a paper case, or the level case).

    Attributes
    ----------
    name : str
        "3.1", "3.2", "3.3" or "level".
    plant : PlantModel
        The true plant.
    model : PlantModel
        The controller's model.
    mismatched_rows : tuple of str
        Outputs whose rows are expected to be flagged.
    mismatched_elements : tuple of (str, str)
        (output, column) pairs expected to be located (the column an input or a measured disturbance).
    mpc : MpcOptions
    excitation : ExcitationOptions
    disturbance : DisturbanceOptions
    description : str
    measured_disturbance : MeasuredDisturbanceOptions or None
        The signal of the plant's measured disturbances (None: the plant has none).
    """

    name: str
    plant: PlantModel
    model: PlantModel
    mismatched_rows: tuple
    mismatched_elements: tuple
    mpc: MpcOptions
    excitation: ExcitationOptions
    disturbance: DisturbanceOptions
    description: str
    measured_disturbance: Optional[MeasuredDisturbanceOptions] = None


def _names(n, prefix):
    return tuple(f"{prefix}{k + 1}" for k in range(n))


def shell_plant() -> PlantModel:
    """The 3x3 Shell heavy-oil-fractionator plant with reduced delays (paper eq. 13)."""
    return PlantModel(sample_time=1.0, inputs=_names(3, "u"), outputs=_names(3, "y"), gain=_SHELL_GAIN,
                      time_constant=_SHELL_TAU, delay=_SHELL_DELAY, name="shell 3x3 (paper eq. 13)")


def paper_case(name: str) -> PaperCase:
    """The paper case ``name`` ("3.1", "3.2" or "3.3")."""
    mpc = MpcOptions(prediction_horizon=100, control_horizon=30, output_weight=1.0, input_weight=1.0,
                     input_rate_weight=0.1)
    dist = DisturbanceOptions(disturbance_std=7.5e-3, disturbance_pole=0.95, noise_std=5.0e-3)
    setpoint = PrbsOptions(amplitude=1.0, switch_probability=0.5)
    if name == "3.1":
        plant = shell_plant()
        return PaperCase("3.1", plant, plant.replace(name="shell 3x3 model, no mismatch"), (), (), mpc,
                         ExcitationOptions(setpoint=setpoint), dist, "3x3, no mismatch (plant = model)")
    if name == "3.2":
        plant = shell_plant()
        model = (plant.with_element(0, 1, time_constant=45, delay=4)
                 .with_element(0, 2, gain=3.5)
                 .with_element(1, 0, time_constant=70)
                 .replace(name="shell 3x3 model, sparse mismatch (paper eq. 14)"))
        return PaperCase("3.2", plant, model, ("y1", "y2"), (("y1", "u2"), ("y1", "u3"), ("y2", "u1")), mpc,
                         ExcitationOptions(setpoint=setpoint), dist, "3x3, sparse mismatch")
    if name == "3.3":
        ones = np.ones((5, 5))
        plant = PlantModel(sample_time=1.0, inputs=_names(5, "u"), outputs=_names(5, "y"), gain=5 * ones,
                           time_constant=50 * ones, delay=5 * ones, name="5x5 rank-one plant (paper 3.3)")
        model = (plant.with_element(0, 0, delay=8)
                 .with_element(1, 0, gain=4, time_constant=60)
                 .with_element(1, 2, time_constant=80)
                 .with_element(3, 1, gain=3.5)
                 .with_element(3, 4, gain=3.5)
                 .replace(name="5x5 model, sparse mismatch (paper 3.3, reconstructed)"))
        excitation = ExcitationOptions(setpoint=setpoint,
                                       dither=PrbsOptions(amplitude=0.1, switch_probability=0.5))
        return PaperCase("3.3", plant, model, ("y1", "y2", "y4"),
                         (("y1", "u1"), ("y2", "u1"), ("y2", "u3"), ("y4", "u2"), ("y4", "u5")), mpc,
                         excitation, dist, "5x5, sparse mismatch, with input dither")
    raise ValueError(f"unknown case {name!r}: expected one of {', '.join(CASE_NAMES)}")


def level_plant() -> PlantModel:
    """A 2x2 unit with a measured inflow: a temperature and an integrating level.

    The temperature answers the steam (first order, 30 s, 3 s dead time), a little the outflow
    and, cooling, the inflow; the level integrates the outflow (-0.05 per second, 5 s lag) and the
    inflow (+0.05 per second, 3 s lag), and the steam does not act on it.
    """
    return PlantModel(sample_time=1.0, inputs=("steam", "outflow"), outputs=("temperature", "level"),
                      disturbances=("inflow",),
                      gain=[[2.0, 0.3, -1.0], [0.0, -0.05, 0.05]],
                      time_constant=[[30.0, 20.0, 25.0], [0.0, 5.0, 3.0]],
                      delay=[[3.0, 2.0, 2.0], [0.0, 1.0, 1.0]],
                      integrating=[[False, False, False], [False, True, True]],
                      name="2x2 unit with an integrating level and a measured inflow")


def level_case() -> PaperCase:
    """The level case: the controller's model has a wrong gain of the measured inflow on the
    temperature (-0.6 for -1.0) and a wrong integrator gain of the outflow on the level (-0.035 per
    second for -0.05), the two elements to locate; the inflow steps between random levels."""
    plant = level_plant()
    model = (plant.with_element(0, 2, gain=-0.6)
             .with_element(1, 1, gain=-0.035)
             .replace(name="level unit model: wrong inflow gain on the temperature, wrong outflow integrator gain"))
    mpc = MpcOptions(prediction_horizon=100, control_horizon=30, output_weight=1.0, input_weight=1.0,
                     input_rate_weight=0.1)
    dist = DisturbanceOptions(disturbance_std=7.5e-3, disturbance_pole=0.95, noise_std=5.0e-3)
    excitation = ExcitationOptions(setpoint=PrbsOptions(amplitude=1.0, switch_probability=0.5))
    inflow = MeasuredDisturbanceOptions(step_amplitude=1.0, switch_probability=0.02, min_hold=20, noise_std=0.1,
                                        noise_pole=0.9)
    return PaperCase("level", plant, model, ("temperature", "level"), (("temperature", "inflow"), ("level", "outflow")),
                     mpc, excitation, dist, "2x2 with an integrating level and a measured inflow; wrong inflow gain "
                     "and wrong outflow integrator gain", measured_disturbance=inflow)


def simulation_case(name: str) -> PaperCase:
    """The case ``name``: a paper case ("3.1", "3.2", "3.3") or "level"."""
    if name == "level":
        return level_case()
    if name not in CASE_NAMES:
        raise ValueError(f"unknown case {name!r}: expected one of {', '.join(DEMO_CASES)}")
    return paper_case(name)
