"""Logged closed-loop data in memory: setpoints, inputs and outputs on a regular time grid.

The CSV file is read and written by :mod:`mpm_monitor.io.csv_log`, bags by :mod:`mpm_monitor.io.bags`,
and the live monitor builds the same object from its window (:mod:`mpm_monitor.monitor.window`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .errors import DataFileError
from .model import FopdtModel

#: Largest |value| x max(1, |gain|) the analysis takes: its least-squares fits square the signals and
#: float64 overflows near 1e308 (the results are scale-invariant up to about 1e150).
MAX_ANALYSIS_SCALE = 1e150


@dataclasses.dataclass
class LoggedData:
    """Setpoints, inputs and outputs of a closed-loop run.

    Attributes
    ----------
    t : ndarray, shape (n_samples,)
        Time in seconds, equally spaced by ``sample_time``.
    r : ndarray, shape (n_samples, n_outputs)
        Setpoints, columns in the model's output order.
    u : ndarray, shape (n_samples, n_inputs)
        Plant inputs, columns in the model's input order.
    y : ndarray, shape (n_samples, n_outputs)
        Measured outputs, columns in the model's output order.
    inputs, outputs : tuple of str
        Channel names.
    sample_time : float
        Seconds per sample.
    source : str
        Where the data came from (file name), for messages.
    """

    t: np.ndarray
    r: np.ndarray
    u: np.ndarray
    y: np.ndarray
    inputs: tuple
    outputs: tuple
    sample_time: float
    source: str = ""

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])

    def slice(self, start: int, stop: int) -> "LoggedData":
        """Samples ``start:stop`` as a new object."""
        return dataclasses.replace(self, t=self.t[start:stop], r=self.r[start:stop], u=self.u[start:stop],
                                   y=self.y[start:stop])


def check_scale(model: FopdtModel, data: LoggedData, model_source: str = "the model") -> None:
    """Refuse data (or model gains) so large that the squares in the analysis overflow float64.

    Beyond :data:`MAX_ANALYSIS_SCALE` the fits break down (a ``LinAlgError``) or, worse, return a
    confident all-clear; a sensor's "bad value" sentinel such as 1e308 gets there.

    Raises
    ------
    DataFileError
        Naming the source, the channel and the time of the largest value.
    """
    gain = float(np.max(np.abs(model.gain))) if model.gain.size else 0.0
    for name, arr, names in (("setpoint", data.r, model.outputs), ("input", data.u, model.inputs),
                             ("output", data.y, model.outputs)):
        arr = np.abs(np.asarray(arr, dtype=float))
        if arr.size == 0:
            continue
        k, j = np.unravel_index(int(np.argmax(arr)), arr.shape)
        peak = float(arr[k, j])
        if not peak * max(1.0, gain) <= MAX_ANALYSIS_SCALE:
            why = "" if peak > MAX_ANALYSIS_SCALE else f" with gains up to {gain:.3g} in {model_source}"
            raise DataFileError(f"{data.source or 'data'}: {name} '{names[j]}' at t = {float(data.t[k]):g} s is "
                                f"{peak:.3g}{why}: too large for the analysis (|value| x max(1, |gain|) at most "
                                f"{MAX_ANALYSIS_SCALE:g}); rescale the units")
