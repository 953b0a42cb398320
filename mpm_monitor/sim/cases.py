"""The three simulation cases of the paper "A Novel Algorithm for Model-Plant Mismatch Detection for Model
Predictive Controllers" (Tsai, Gopaluni, Marshman and Chmelyk, IFAC ADCHEM 2015).

Each case gives the true plant, the controller's model, the expected located rows and elements,
the MPC tuning and the excitation.  Case 3.3 uses the input dither of the paper's second
experiment, since its plant is rank one and setpoint excitation alone drives the inputs
collinearly.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.model import PlantModel
from .closed_loop import ExcitationOptions
from .excitation import PrbsOptions
from .mpc import MpcOptions
from .plant import DisturbanceOptions

CASE_NAMES = ("3.1", "3.2", "3.3")

_SHELL_GAIN = [[4.05, 1.77, 5.88], [5.39, 5.72, 6.90], [4.38, 4.42, 7.20]]
_SHELL_TAU = [[50, 60, 50], [50, 60, 40], [33, 44, 19]]
_SHELL_DELAY = [[6, 7, 6], [4, 3, 3], [5, 5, 0]]


@dataclasses.dataclass(frozen=True)
class PaperCase:
    """A paper case.

    Attributes
    ----------
    name : str
        "3.1", "3.2" or "3.3".
    plant : PlantModel
        The true plant.
    model : PlantModel
        The controller's model.
    mismatched_rows : tuple of str
        Outputs whose rows are expected to be flagged.
    mismatched_elements : tuple of (str, str)
        (output, input) pairs expected to be located.
    mpc : MpcOptions
    excitation : ExcitationOptions
    disturbance : DisturbanceOptions
    description : str
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
