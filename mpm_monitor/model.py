"""The controller's plant model: a transfer matrix of first-order-plus-dead-time elements.

Each element (output i, input j) is ``K e^{-theta s} / (tau s + 1)`` in deviation variables, as in
CONTRACTS section 1.  This module loads, validates and saves the YAML model file; the discrete-time
form lives in :mod:`mpm_monitor.discretize`.
"""

from __future__ import annotations

import dataclasses
import math
import unicodedata
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from .errors import ModelFileError, read_text

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
        """The model as plain Python values in the schema of CONTRACTS section 1."""

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
    # Every channel must be its own column of the CSV log (CONTRACTS section 2).
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


def _matrix(data: Mapping, key: str, source: str) -> np.ndarray:
    if key not in data:
        raise ModelFileError(f"{source}: missing key '{key}': expected a list of rows (outputs x inputs)")
    val = data[key]
    if not isinstance(val, Sequence) or isinstance(val, (str, bytes)):
        raise ModelFileError(f"{source}: key '{key}': expected a list of rows (outputs x inputs), got {type(val).__name__}")
    rows = []
    for i, row in enumerate(val):
        if not isinstance(row, Sequence) or isinstance(row, (str, bytes)):
            raise ModelFileError(f"{source}: key '{key}': row {i + 1}: expected a list of numbers, got {row!r}")
        if rows and len(row) != len(rows[0]):
            raise ModelFileError(
                f"{source}: key '{key}': row {i + 1} has {len(row)} entries, row 1 has {len(rows[0])}")
        out_row = []
        for j, x in enumerate(row):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                raise ModelFileError(f"{source}: key '{key}': row {i + 1}, column {j + 1}: expected a number, got {x!r}")
            out_row.append(_float(x, f"{source}: key '{key}': row {i + 1}, column {j + 1}"))
        rows.append(out_row)
    if not rows:
        raise ModelFileError(f"{source}: key '{key}': expected at least one row")
    return np.array(rows, dtype=float)


def _vector(data: Mapping, key: str, source: str):
    if key not in data or data[key] is None:
        return None
    val = data[key]
    if not isinstance(val, Sequence) or isinstance(val, (str, bytes)):
        raise ModelFileError(f"{source}: key '{key}': expected a list of numbers, got {type(val).__name__}")
    for j, x in enumerate(val):
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise ModelFileError(f"{source}: key '{key}': entry {j + 1}: expected a number, got {x!r}")
    return np.array([_float(x, f"{source}: key '{key}': entry {j + 1}") for x in val], dtype=float)


def _float(x, where: str) -> float:
    """``float(x)``; an integer beyond the float range (YAML reads ``1`` followed by 400 zeros as
    an int) is refused like infinity instead of raising ``OverflowError``."""
    try:
        return float(x)
    except OverflowError:
        raise ModelFileError(f"{where}: expected a finite number, got an integer of {len(str(abs(x)))} digits") from None


def _names(data: Mapping, key: str, source: str) -> tuple:
    if key not in data:
        raise ModelFileError(f"{source}: missing key '{key}': expected a list of names")
    val = data[key]
    if not isinstance(val, Sequence) or isinstance(val, (str, bytes)):
        raise ModelFileError(f"{source}: key '{key}': expected a list of names, got {type(val).__name__}")
    for n in val:
        if not isinstance(n, str):
            raise ModelFileError(f"{source}: key '{key}': expected names as strings, got {n!r}")
    return tuple(val)


def model_from_dict(data: Any, source: str = "model") -> FopdtModel:
    """Build and validate a model from parsed YAML/JSON data.

    Parameters
    ----------
    data : mapping
        Keys as in CONTRACTS section 1.
    source : str
        Name used as the prefix of error messages (usually the file path).

    Raises
    ------
    ModelFileError
        With one line naming the key and what was expected.
    """
    if not isinstance(data, Mapping):
        raise ModelFileError(f"{source}: expected a YAML mapping with keys sample_time, inputs, outputs, gain, "
                             f"time_constant, delay; got {type(data).__name__}")
    if "sample_time" not in data:
        raise ModelFileError(f"{source}: missing key 'sample_time': expected a positive number of seconds")
    ts = data["sample_time"]
    if isinstance(ts, bool) or not isinstance(ts, (int, float)):
        raise ModelFileError(f"{source}: key 'sample_time': expected a positive number of seconds, got {ts!r}")
    inputs = _names(data, "inputs", source)
    outputs = _names(data, "outputs", source)
    gain = _matrix(data, "gain", source)
    tau = _matrix(data, "time_constant", source)
    delay = _matrix(data, "delay", source)
    name = data.get("name", "")
    if not isinstance(name, str):
        raise ModelFileError(f"{source}: key 'name': expected a string, got {name!r}")
    try:
        return FopdtModel(
            sample_time=_float(ts, f"{source}: key 'sample_time'"), inputs=inputs, outputs=outputs, gain=gain, time_constant=tau,
            delay=delay, input_nominal=_vector(data, "input_nominal", source),
            output_nominal=_vector(data, "output_nominal", source), name=name)
    except ModelFileError as exc:
        # __post_init__ validates with the generic prefix; re-raise with the file name.
        msg = str(exc)
        if msg.startswith("model: "):
            msg = f"{source}: " + msg[len("model: "):]
        raise ModelFileError(msg) from None


def load_model(path) -> FopdtModel:
    """Load and validate a YAML model file (CONTRACTS section 1).

    Parameters
    ----------
    path : str or Path
        The file.

    Raises
    ------
    ModelFileError
        When the file cannot be read, is not YAML, or fails validation; the one-line message names
        the file and the key.
    """
    path = Path(path)
    text = read_text(path, ModelFileError, "model file", "a YAML model file")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        if isinstance(exc, yaml.reader.ReaderError):  # a control character: no mark, a position
            where = f" at character {exc.position + 1}"
        problem = getattr(exc, "problem", None) or getattr(exc, "reason", None) or "invalid YAML"
        raise ModelFileError(f"{path}: not valid YAML{where}: {problem}") from None
    except RecursionError:
        raise ModelFileError(f"{path}: not a model file: lists or mappings nested too deeply") from None
    if data is None:
        raise ModelFileError(f"{path}: empty file: expected a YAML model with sample_time, inputs, outputs, gain, "
                             f"time_constant, delay")
    return model_from_dict(data, source=str(path))


def save_model(model: FopdtModel, path) -> None:
    """Write a model to a YAML file that :func:`load_model` reads back identically."""
    text = dump_model(model)
    Path(path).write_text(text, encoding="utf-8")


def yaml_number(v) -> str:
    """``repr`` of a number in a form YAML 1.1 (PyYAML) reads back as a number.

    PyYAML resolves a float only with a decimal point, so ``1e-05`` would load as a string; write
    ``1.0e-05`` instead.
    """
    text = repr(v)
    mantissa, e, exponent = text.partition("e")
    if e and "." not in mantissa:
        text = f"{mantissa}.0e{exponent}"
    return text


def dump_model(model: FopdtModel) -> str:
    """The model as YAML text, one matrix row per line."""
    d = model.to_dict()
    lines = []
    if "name" in d:
        lines.append(f"name: {yaml.safe_dump(d['name'], default_flow_style=True).strip().removesuffix('...').strip()}")
    lines.append(f"sample_time: {yaml_number(d['sample_time'])}")
    lines.append(f"inputs: {yaml.safe_dump(d['inputs'], default_flow_style=True).strip()}")
    lines.append(f"outputs: {yaml.safe_dump(d['outputs'], default_flow_style=True).strip()}")
    for key in ("gain", "time_constant", "delay"):
        rows = ", ".join("[" + ", ".join(yaml_number(v) for v in row) + "]" for row in d[key])
        lines.append(f"{key}: [{rows}]")
    for key in ("input_nominal", "output_nominal"):
        if key in d:
            lines.append(f"{key}: [{', '.join(yaml_number(v) for v in d[key])}]")
    return "\n".join(lines) + "\n"
