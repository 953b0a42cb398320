"""The model file (YAML): read, validate and write a :class:`~mpm_monitor.core.model.FopdtModel`.

The schema is described in ``docs/interfaces.md``.  Files are loaded with ``yaml.safe_load``: a
Python tag is refused, never run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml

from ..core.errors import ModelFileError
from ..core.model import FopdtModel
from .files import read_text


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
        Keys of the model file (docs/interfaces.md, "Model file").
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
    """Load and validate a YAML model file (docs/interfaces.md, "Model file").

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
