"""The controller's plant model: a transfer matrix of first-order-plus-dead-time elements.

Each element (output i, input j) is ``K e^{-theta s} / (tau s + 1)`` in deviation variables, as in
the model file (docs/interfaces.md, "Model file").  This module holds and validates the model; the
YAML file is read and written by :mod:`mpm_monitor.io.model_file`, and the discrete-time form lives
in :mod:`mpm_monitor.core.discretize`.
"""

from __future__ import annotations

import dataclasses
import math
import unicodedata

import numpy as np

from .errors import ModelFileError

#: Relative tolerance with which a delay must be a multiple of the sample time.
DELAY_GRID_TOLERANCE = 1e-6
#: Largest dead time in samples (beyond it the sample count no longer fits the integer arithmetic
#: of the analysis, and no window could hold it anyway).
MAX_DELAY_SAMPLES = 2**31 - 1


def _unprintable(name: str) -> bool:
    """Whether a name holds a control character or a line/paragraph separator (it would split a
    one-line message or a CSV header)."""
    return any(unicodedata.category(c) in ("Cc", "Cs", "Zl", "Zp") for c in name)


@dataclasses.dataclass(frozen=True)
class FopdtModel:
    """A MIMO transfer matrix of first-order-plus-dead-time elements.

    Parameters
    ----------
    sample_time : float
        Seconds per sample, > 0.
    inputs : tuple of str
        Names of the manipulated variables, in column order (length ``n_inputs``).
    outputs : tuple of str
        Names of the controlled variables, in row order (length ``n_outputs``).
    gain : ndarray, shape (n_outputs, n_inputs)
        Steady-state gains ``K`` (output units per input unit); 0 means "no such effect".
    time_constant : ndarray, shape (n_outputs, n_inputs)
        Time constants ``tau`` in seconds, >= 0 (0 = no lag).
    delay : ndarray, shape (n_outputs, n_inputs)
        Dead times ``theta`` in seconds, >= 0 and a multiple of ``sample_time``.
    input_nominal : ndarray, shape (n_inputs,)
        Operating point of the inputs (default zeros).
    output_nominal : ndarray, shape (n_outputs,)
        Operating point of the outputs (default zeros).
    name : str
        Free-text name.
    """

    sample_time: float
    inputs: tuple
    outputs: tuple
    gain: np.ndarray
    time_constant: np.ndarray
    delay: np.ndarray
    input_nominal: np.ndarray = None
    output_nominal: np.ndarray = None
    name: str = ""

    def __post_init__(self):
        ny, nu = len(self.outputs), len(self.inputs)
        for key in ("gain", "time_constant", "delay"):
            arr = np.array(getattr(self, key), dtype=float, copy=True)
            arr.setflags(write=False)
            object.__setattr__(self, key, arr)
        object.__setattr__(self, "inputs", tuple(self.inputs))
        object.__setattr__(self, "outputs", tuple(self.outputs))
        for key, n in (("input_nominal", nu), ("output_nominal", ny)):
            val = getattr(self, key)
            arr = np.zeros(n) if val is None else np.array(val, dtype=float, copy=True)
            arr.setflags(write=False)
            object.__setattr__(self, key, arr)
        validate_model(self)

    @property
    def n_inputs(self) -> int:
        """Number of inputs (columns)."""
        return len(self.inputs)

    @property
    def n_outputs(self) -> int:
        """Number of outputs (rows)."""
        return len(self.outputs)

    @property
    def delay_samples(self) -> np.ndarray:
        """Dead times in samples, integer array of shape (n_outputs, n_inputs)."""
        return np.rint(self.delay / self.sample_time).astype(int)

    def element(self, i: int, j: int) -> dict:
        """Parameters of element (output ``i``, input ``j``) as a dict (seconds)."""
        return {
            "gain": float(self.gain[i, j]),
            "time_constant": float(self.time_constant[i, j]),
            "delay": float(self.delay[i, j]),
        }

    def replace(self, **changes) -> "FopdtModel":
        """Return a copy with some fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)

    def with_element(self, i: int, j: int, gain=None, time_constant=None, delay=None) -> "FopdtModel":
        """Return a copy in which element (i, j) has new parameters (None keeps the old one)."""
        g, t, d = (np.array(self.gain), np.array(self.time_constant), np.array(self.delay))
        if gain is not None:
            g[i, j] = gain
        if time_constant is not None:
            t[i, j] = time_constant
        if delay is not None:
            d[i, j] = delay
        return self.replace(gain=g, time_constant=t, delay=d)

    def to_dict(self) -> dict:
        """The model as plain Python values in the schema of the model file (docs/interfaces.md, "Model file")."""

        def num(x):
            x = float(x)
            return int(x) if x.is_integer() and abs(x) < 2**53 else x

        out = {
            "sample_time": num(self.sample_time),
            "inputs": list(self.inputs),
            "outputs": list(self.outputs),
            "gain": [[num(v) for v in row] for row in self.gain],
            "time_constant": [[num(v) for v in row] for row in self.time_constant],
            "delay": [[num(v) for v in row] for row in self.delay],
        }
        if np.any(self.input_nominal != 0):
            out["input_nominal"] = [num(v) for v in self.input_nominal]
        if np.any(self.output_nominal != 0):
            out["output_nominal"] = [num(v) for v in self.output_nominal]
        if self.name:
            out["name"] = self.name
        return out

    def __eq__(self, other):
        if not isinstance(other, FopdtModel):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None


def validate_model(model: FopdtModel, source: str = "model") -> None:
    """Check a model's shapes and values; raise :class:`ModelFileError` naming the key.

    Parameters
    ----------
    model : FopdtModel
        The model to check.
    source : str
        Name of the file or object, used as the message prefix.
    """
    ts = model.sample_time
    if not isinstance(ts, (int, float, np.floating)) or not math.isfinite(ts) or ts <= 0:
        raise ModelFileError(f"{source}: key 'sample_time': expected a positive finite number of seconds, got {ts!r}")
    ny, nu = len(model.outputs), len(model.inputs)
    for key, names in (("inputs", model.inputs), ("outputs", model.outputs)):
        if len(names) == 0:
            raise ModelFileError(f"{source}: key '{key}': expected a non-empty list of names")
        for n in names:
            if not isinstance(n, str) or not n or "," in n or n != n.strip() or _unprintable(n):
                raise ModelFileError(
                    f"{source}: key '{key}': expected names as non-empty strings without commas, "
                    f"control characters or surrounding spaces, got {n!r}")
        if len(set(names)) != len(names):
            dup = sorted({n for n in names if list(names).count(n) > 1})
            raise ModelFileError(f"{source}: key '{key}': names must be unique, repeated: {', '.join(dup)}")
    overlap = set(model.inputs) & set(model.outputs)
    if overlap:
        raise ModelFileError(
            f"{source}: keys 'inputs' and 'outputs': a name cannot be both, found {', '.join(sorted(overlap))}")
    # Every channel must be its own column of the CSV log (docs/interfaces.md, "Logged data (CSV)").
    columns = ["t"] + [f"r_{o}" for o in model.outputs] + list(model.inputs) + list(model.outputs)
    clash = sorted({c for c in columns if columns.count(c) > 1})
    if clash:
        raise ModelFileError(
            f"{source}: keys 'inputs' and 'outputs': name {clash[0]!r} would be two columns of the CSV log "
            f"(t, r_<output>, <input>, <output>): rename the channel")
    for key in ("gain", "time_constant", "delay"):
        arr = getattr(model, key)
        if arr.shape != (ny, nu):
            raise ModelFileError(
                f"{source}: key '{key}': expected {ny} rows x {nu} columns (outputs x inputs), got shape "
                f"{'x'.join(str(s) for s in arr.shape) or 'scalar'}")
        if not np.all(np.isfinite(arr)):
            i, j = np.argwhere(~np.isfinite(arr))[0]
            raise ModelFileError(f"{source}: key '{key}': row {i + 1}, column {j + 1}: expected a finite number, got {arr[i, j]}")
    for key in ("time_constant", "delay"):
        arr = getattr(model, key)
        if np.any(arr < 0):
            i, j = np.argwhere(arr < 0)[0]
            raise ModelFileError(
                f"{source}: key '{key}': row {i + 1} ({model.outputs[i]}), column {j + 1} ({model.inputs[j]}): "
                f"expected >= 0 seconds, got {arr[i, j]:g}")
    with np.errstate(over="ignore"):
        ratio = model.delay / ts
    if np.any(ratio > MAX_DELAY_SAMPLES):
        i, j = np.argwhere(ratio > MAX_DELAY_SAMPLES)[0]
        raise ModelFileError(
            f"{source}: key 'delay': row {i + 1} ({model.outputs[i]}), column {j + 1} ({model.inputs[j]}): "
            f"expected at most {MAX_DELAY_SAMPLES} samples of sample_time {ts:g} s, got {model.delay[i, j]:g} s")
    off = np.abs(ratio - np.rint(ratio)) > DELAY_GRID_TOLERANCE * np.maximum(1.0, np.abs(ratio))
    if np.any(off):
        i, j = np.argwhere(off)[0]
        raise ModelFileError(
            f"{source}: key 'delay': row {i + 1} ({model.outputs[i]}), column {j + 1} ({model.inputs[j]}): "
            f"expected a multiple of sample_time {ts:g} s, got {model.delay[i, j]:g} s")
    for key, arr, n in (("input_nominal", model.input_nominal, nu), ("output_nominal", model.output_nominal, ny)):
        if arr.shape != (n,):
            raise ModelFileError(f"{source}: key '{key}': expected a list of {n} numbers, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ModelFileError(f"{source}: key '{key}': expected finite numbers")
