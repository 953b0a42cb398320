"""The model file (YAML): read, validate and write a :class:`~mpm_monitor.core.model.PlantModel`.

The schema is described in ``docs/interfaces.md``.  Files are loaded with PyYAML's safe loader
(libyaml's parser when present): a Python tag is refused, never run.  Numbers are read as YAML 1.2
(and JSON) write them, not by YAML 1.1's wider rules, which would silently turn a file into another
model: ``5e-05`` is a number (1.1: a string), ``010`` is ten (1.1: octal eight), ``1:30`` is not
a number (1.1: ninety, base 60), ``1_0`` is not a number.  Booleans too: ``true`` and ``false`` only
(1.1 also ``yes``, ``no``, ``on``, ``off``: an output named ``NO`` was ``False``).  A key given twice is
refused (1.1: the last one wins).  The writer quotes a name the loader would read otherwise.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import yaml

from ..core.errors import ModelFileError
from ..core.model import NOMINAL_KEYS, PlantModel, element_where
from .files import read_text, write_text_replacing
from .yaml_nesting import nests_deeper


def _matrix(data: Mapping, key: str, source: str, names: Optional[tuple] = None) -> np.ndarray:
    if key not in data:
        raise ModelFileError(f"{source}: missing key '{key}': expected a list of rows (outputs x columns)")
    val = data[key]
    if not isinstance(val, Sequence) or isinstance(val, (str, bytes)):
        raise ModelFileError(f"{source}: key '{key}': expected a list of rows (outputs x inputs), got {type(val).__name__}")
    rows = _rows(val, key, source, "numbers", _number, names)
    return np.array(rows, dtype=float)


def _cell(names: Optional[tuple], i: int, j: int) -> str:
    """``row 1 (y1), column 2 (u2)`` of a matrix entry (:func:`~mpm_monitor.core.model.element_where`), the names
    from ``names`` = (outputs, columns); ``row 1, column 2`` without them."""
    return f"row {i + 1}, column {j + 1}" if names is None else element_where(*names, i, j)


def _rows(val: Sequence, key: str, source: str, what: str, entry, names: Optional[tuple] = None) -> list:
    """The rows of a list-of-rows value, each entry through ``entry(x, where)``: rows of equal length,
    at least one, else a :class:`ModelFileError` naming the key, the row and the column (with their channel
    names, from ``names`` = (outputs, columns), when given)."""
    rows = []
    for i, row in enumerate(val):
        if not isinstance(row, Sequence) or isinstance(row, (str, bytes)):
            raise ModelFileError(f"{source}: key '{key}': row {i + 1}: expected a list of {what}, got {row!r}")
        if rows and len(row) != len(rows[0]):
            raise ModelFileError(f"{source}: key '{key}': row {i + 1} has {len(row)} entries, row 1 has {len(rows[0])}")
        rows.append([entry(x, f"{source}: key '{key}': {_cell(names, i, j)}") for j, x in enumerate(row)])
    if not rows:
        raise ModelFileError(f"{source}: key '{key}': expected at least one row")
    return rows


def _number(x, where: str) -> float:
    """A model file's number (not a boolean) as a float."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise ModelFileError(f"{where}: expected a number, got {x!r}")
    return _float(x, where)


def _flag(x, where: str) -> bool:
    """A model file's true/false entry."""
    if not isinstance(x, bool):
        raise ModelFileError(f"{where}: expected true or false, got {x!r}")
    return x


def _vector(data: Mapping, key: str, source: str):
    if key not in data or data[key] is None:
        return None
    val = data[key]
    if not isinstance(val, Sequence) or isinstance(val, (str, bytes)):
        raise ModelFileError(f"{source}: key '{key}': expected a list of numbers, got {type(val).__name__}")
    return np.array([_number(x, f"{source}: key '{key}': entry {j + 1}") for j, x in enumerate(val)], dtype=float)


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
            hint = " (a name that reads as a number or a boolean is written in quotes: '1e3')" \
                if isinstance(n, (int, float)) else ""
            raise ModelFileError(f"{source}: key '{key}': expected names as strings, got {n!r}{hint}")
    return tuple(val)


#: Every key a model file may hold.  Any other key is refused: a misspelt key (``time_constant_2``)
#: read as absent would silently turn the model into another one.
KNOWN_KEYS = ("sample_time", "inputs", "outputs", "disturbances", "gain", "time_constant", "delay", "lead",
              "time_constant2", "integrating", "step_response", "ramp", "input_nominal", "output_nominal",
              "disturbance_nominal", "name")
#: Other names a control engineer gives a key (lower case, ``_`` for spaces and dashes) -> the model file's key,
#: for the hint of an unknown key (``dead_time`` is closer in spelling to ``sample_time`` than to ``delay``).
KEY_SYNONYMS = {"dead_time": "delay", "deadtime": "delay", "time_delay": "delay", "theta": "delay",
                "lag": "time_constant", "tau": "time_constant", "time_constants": "time_constant", "k": "gain",
                "gains": "gain", "kp": "gain", "tau2": "time_constant2", "second_time_constant": "time_constant2",
                "integrator": "integrating", "integrators": "integrating", "ts": "sample_time", "dt": "sample_time",
                "sampling_time": "sample_time", "mvs": "inputs", "cvs": "outputs", "dvs": "disturbances",
                "step_responses": "step_response", "delays": "delay", "leads": "lead"}
#: Keys of the parametric form, which a step-response model (key ``step_response``) replaces.
PARAMETRIC_ONLY = ("gain", "time_constant", "delay", "lead", "time_constant2", "integrating")
#: The keys a model may leave out: given as null, each is read as absent.
OPTIONAL_KEYS = ("disturbances", "lead", "time_constant2", "integrating", "ramp", "input_nominal", "output_nominal",
                 "disturbance_nominal")


def _check_keys(data: Mapping, source: str) -> None:
    """Refuse a key the model file does not know, naming it, the nearest known key and the known keys."""
    import difflib

    for key in data:
        if key in KNOWN_KEYS:
            continue
        if key is None:             # `~:` or `null:` in the file
            raise ModelFileError(f"{source}: a key that is null (~ or null): a model file holds only the keys "
                                 f"{', '.join(KNOWN_KEYS)}")
        text = str(key)
        meant = KEY_SYNONYMS.get(text.lower().replace("-", "_").replace(" ", "_"))
        near = [meant] if meant else difflib.get_close_matches(text, KNOWN_KEYS, n=1, cutoff=0.6)
        hint = f" (did you mean '{near[0]}'?)" if near else ""
        raise ModelFileError(f"{source}: unknown key {text!r}{hint}: a model file holds only the keys "
                             f"{', '.join(KNOWN_KEYS)}")


def _bool_matrix(data: Mapping, key: str, source: str, names: Optional[tuple] = None):
    if key not in data or data[key] is None:
        return None
    val = data[key]
    if not isinstance(val, Sequence) or isinstance(val, (str, bytes)):
        raise ModelFileError(f"{source}: key '{key}': expected a list of rows of true/false (outputs x columns), "
                             f"got {type(val).__name__}")
    rows = _rows(val, key, source, "true/false", _flag, names)
    return np.array(rows, dtype=bool)


def _bool_vector(data: Mapping, key: str, source: str):
    if key not in data or data[key] is None:
        return None
    val = data[key]
    if not isinstance(val, Sequence) or isinstance(val, (str, bytes)):
        raise ModelFileError(f"{source}: key '{key}': expected a list of true/false (one per output), "
                             f"got {type(val).__name__}")
    for j, x in enumerate(val):
        if not isinstance(x, bool):
            raise ModelFileError(f"{source}: key '{key}': entry {j + 1}: expected true or false, got {x!r}")
    return tuple(val)


def _plain_numbers(values: Sequence):
    """``values`` as a float array when every entry is an ``int`` or a ``float`` (not a boolean) within the
    float range: the same numbers as ``float(x)`` each, in one pass; otherwise None (the caller then looks
    at each entry, to name the one that is not a number)."""
    if not set(map(type, values)) <= {int, float}:
        return None
    try:
        return np.array(values, dtype=float)
    except OverflowError:               # an integer beyond the float range
        return None


def _step_response(data: Mapping, source: str, names: Optional[tuple] = None) -> np.ndarray:
    """``step_response: {length: N, coefficients: [[[N values] per column] per output]}`` as an array (an entry's
    message names its channels from ``names`` = (outputs, columns) when given)."""
    val = data["step_response"]
    key = "step_response"
    if not isinstance(val, Mapping):
        raise ModelFileError(f"{source}: key '{key}': expected a mapping with 'length' and 'coefficients', "
                             f"got {type(val).__name__}")
    for k in val:
        if k not in ("length", "coefficients"):
            raise ModelFileError(f"{source}: key '{key}': unknown key {str(k)!r}: expected 'length' and 'coefficients'")
    for k in ("length", "coefficients"):
        if k not in val:
            raise ModelFileError(f"{source}: key '{key}': missing '{k}'")
    n = val["length"]
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ModelFileError(f"{source}: key '{key}': 'length': expected a whole number of samples >= 1, got {n!r}")
    coef = val["coefficients"]
    if not isinstance(coef, Sequence) or isinstance(coef, (str, bytes)) or not coef:
        raise ModelFileError(f"{source}: key '{key}': 'coefficients': expected a list of rows (one per output), "
                             f"each a list of {n} values per column")
    rows = []
    for i, row in enumerate(coef):
        if not isinstance(row, Sequence) or isinstance(row, (str, bytes)):
            raise ModelFileError(f"{source}: key '{key}': row {i + 1}: expected a list of columns, got {row!r}")
        if rows and len(row) != len(rows[0]):
            raise ModelFileError(f"{source}: key '{key}': row {i + 1} has {len(row)} columns, row 1 has {len(rows[0])}")
        out_row = []
        for j, el in enumerate(row):
            where = f"{source}: key '{key}': {_cell(names, i, j)}"
            if not isinstance(el, Sequence) or isinstance(el, (str, bytes)):
                raise ModelFileError(f"{where}: expected a list of {n} coefficients, got {el!r}")
            if len(el) != n:
                raise ModelFileError(f"{where}: expected {n} coefficients (length), got {len(el)}")
            vals = _plain_numbers(el)
            if vals is not None:
                out_row.append(vals)
                continue
            vals = []
            for k, x in enumerate(el):
                if isinstance(x, bool) or not isinstance(x, (int, float)):
                    raise ModelFileError(f"{where}, coefficient {k + 1}: expected a number, got {x!r}")
                vals.append(_float(x, f"{where}, coefficient {k + 1}"))
            out_row.append(vals)
        rows.append(out_row)
    return np.array(rows, dtype=float)


def model_from_dict(data: Any, source: str = "model") -> PlantModel:
    """Build and validate a model from parsed YAML/JSON data.

    Parameters
    ----------
    data : mapping
        Keys as in ``docs/interfaces.md`` ("Model file", "Richer elements", "Measured disturbances").
    source : str
        Name used as the prefix of error messages (usually the file path).

    Raises
    ------
    ModelFileError
        With one line naming the key (and the element) and what was expected; an unknown key is
        refused, never ignored.
    """
    if not isinstance(data, Mapping):
        raise ModelFileError(f"{source}: expected a YAML mapping with keys sample_time, inputs, outputs, gain, "
                             f"time_constant, delay; got {type(data).__name__}")
    _check_keys(data, source)
    if "sample_time" not in data:
        raise ModelFileError(f"{source}: missing key 'sample_time': expected a positive number of seconds")
    ts = data["sample_time"]
    if isinstance(ts, bool) or not isinstance(ts, (int, float)):
        raise ModelFileError(f"{source}: key 'sample_time': expected a positive number of seconds, got {ts!r}")
    inputs = _names(data, "inputs", source)
    outputs = _names(data, "outputs", source)
    for key, names in (("inputs", inputs), ("outputs", outputs)):
        if not names:       # named before the matrices, which would be refused as empty rows
            raise ModelFileError(f"{source}: key '{key}': expected a non-empty list of names")
    disturbances = _names(data, "disturbances", source) if data.get("disturbances") is not None else ()
    name = data.get("name", "")
    if not isinstance(name, str):
        raise ModelFileError(f"{source}: key 'name': expected a string, got {name!r}")
    common = dict(sample_time=_float(ts, f"{source}: key 'sample_time'"), inputs=inputs, outputs=outputs,
                  disturbances=disturbances, input_nominal=_vector(data, "input_nominal", source),
                  output_nominal=_vector(data, "output_nominal", source),
                  disturbance_nominal=_vector(data, "disturbance_nominal", source), name=name)
    cells = (outputs, inputs + disturbances)           # a matrix entry's message names its channels
    try:
        if "step_response" in data:
            for key in PARAMETRIC_ONLY:
                # an optional key given as null is absent (it was refused here, against the file's rule)
                if key in data and not (key in OPTIONAL_KEYS and data[key] is None):
                    raise ModelFileError(
                        f"{source}: key '{key}': a step-response model (key 'step_response') has no {key}: give "
                        f"either the step responses or the parametric elements")
            return PlantModel.from_step_response(coefficients=_step_response(data, source, cells),
                                                 ramp=_bool_vector(data, "ramp", source), **common)
        if data.get("ramp") is not None:
            raise ModelFileError(f"{source}: key 'ramp': only a step-response model (key 'step_response') takes a "
                                 f"ramp; an integrating parametric element is marked in 'integrating'")
        return PlantModel(
            gain=_matrix(data, "gain", source, cells), time_constant=_matrix(data, "time_constant", source, cells),
            delay=_matrix(data, "delay", source, cells),
            lead=_matrix(data, "lead", source, cells) if data.get("lead") is not None else None,
            time_constant2=(_matrix(data, "time_constant2", source, cells)
                            if data.get("time_constant2") is not None else None),
            integrating=_bool_matrix(data, "integrating", source, cells), **common)
    except ModelFileError as exc:
        # __post_init__ validates with the generic prefix; re-raise with the file name.
        msg = str(exc)
        if msg.startswith("model: "):
            msg = f"{source}: " + msg[len("model: "):]
        raise ModelFileError(msg) from None


_INT_TAG, _FLOAT_TAG = "tag:yaml.org,2002:int", "tag:yaml.org,2002:float"
_INT = re.compile(r"^[-+]?[0-9]+$")
_FLOAT = re.compile(r"^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?"
                    r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$")


def _construct_float(loader, node) -> float:
    text = loader.construct_scalar(node).lower()
    if text.endswith(".inf"):
        return float("-inf") if text.startswith("-") else float("inf")
    if text == ".nan":
        return float("nan")
    return float(text)


_BOOL_TAG, _MERGE_TAG = "tag:yaml.org,2002:bool", "tag:yaml.org,2002:merge"
_TIMESTAMP_TAG = "tag:yaml.org,2002:timestamp"
_BOOL = re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$")


def _strict_resolvers(cls, timestamps: bool = True) -> None:
    """Give ``cls`` (a PyYAML loader or dumper class) YAML 1.2's numbers and booleans in place of YAML 1.1's;
    ``timestamps`` False: no timestamps either (YAML 1.2 has none: the loaders read a name ``2001-12-14`` as a
    date and refused it as not a string; the dumper keeps them, so that it quotes such a name for YAML 1.1
    readers)."""
    dropped = (_INT_TAG, _FLOAT_TAG, _BOOL_TAG) + (() if timestamps else (_TIMESTAMP_TAG,))
    cls.yaml_implicit_resolvers = {first: [(tag, rx) for tag, rx in resolvers if tag not in dropped]
                                   for first, resolvers in cls.yaml_implicit_resolvers.items()}
    cls.add_implicit_resolver(_INT_TAG, _INT, list("-+0123456789"))
    cls.add_implicit_resolver(_FLOAT_TAG, _FLOAT, list("-+0123456789."))
    cls.add_implicit_resolver(_BOOL_TAG, _BOOL, list("tTfF"))


#: What a constructor raises on a value its tag does not fit (``!!int 1.5``, ``!!bool maybe``, ``!!map`` on a list).
_CONSTRUCTOR_ERRORS = (ValueError, TypeError, KeyError, AttributeError, OverflowError, IndexError)


def _short_tag(tag) -> str:
    """``!!int`` for ``tag:yaml.org,2002:int`` (as written in a file)."""
    return str(tag).replace("tag:yaml.org,2002:", "!!")


def _strict_loader(base):
    """``base`` (PyYAML's SafeLoader or CSafeLoader) with YAML 1.2's numbers and booleans and unique keys
    (module docstring); a value an explicit tag's constructor refuses (``!!int 1.5``) and a merge key are
    errors with their line and column."""

    class Loader(base):
        def construct_object(self, node, deep=False):
            try:
                return super().construct_object(node, deep=deep)
            except yaml.YAMLError:
                raise
            except _CONSTRUCTOR_ERRORS as exc:
                what = repr(node.value)[:40] if isinstance(node, yaml.ScalarNode) else f"this {node.id}"
                raise yaml.constructor.ConstructorError(
                    None, None, f"{what} cannot be read as {_short_tag(node.tag)} ({type(exc).__name__}: {exc})"[:200],
                    node.start_mark) from None

        def construct_document(self, node):
            try:
                return super().construct_document(node)
            except yaml.YAMLError:
                raise
            except _CONSTRUCTOR_ERRORS as exc:
                # A constructor that runs late (the lists and mappings are filled after their nodes).
                raise yaml.constructor.ConstructorError(
                    None, None, f"a value its tag does not fit ({type(exc).__name__}: {exc})"[:200], None) from None

        def construct_mapping(self, node, deep=False):
            if not isinstance(node, yaml.MappingNode):      # an explicit !!map on a list or a scalar
                raise yaml.constructor.ConstructorError(
                    None, None, f"expected a mapping for {_short_tag(node.tag)}, "
                    f"got a {node.id}", node.start_mark)
            seen = set()
            for key_node, _ in node.value:
                if key_node.tag == _MERGE_TAG:
                    raise yaml.constructor.ConstructorError(
                        None, None, "a merge key (<<) is not read in a model file: write its keys out",
                        key_node.start_mark)
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                except TypeError:          # an unhashable key: the base constructor refuses it
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError("while constructing a mapping", node.start_mark,
                                                            f"found duplicate key {key!r}", key_node.start_mark)
                seen.add(key)
            return super().construct_mapping(node, deep=deep)

    _strict_resolvers(Loader, timestamps=False)
    Loader.add_constructor(_INT_TAG, lambda loader, node: int(loader.construct_scalar(node)))
    Loader.add_constructor(_FLOAT_TAG, _construct_float)
    return Loader


_LOADER = _strict_loader(yaml.SafeLoader)
_C_LOADER = _strict_loader(yaml.CSafeLoader) if hasattr(yaml, "CSafeLoader") else None


class _Dumper(yaml.SafeDumper):
    """PyYAML's safe dumper with the loader's YAML 1.2 numbers and booleans: a string that the loader would read
    as a number or a boolean (a name ``2e3`` or ``NO``... ``2e3`` is a plain string to YAML 1.1) is quoted."""


_strict_resolvers(_Dumper)


#: A flow list of plain numbers, ``[0, -0.18, 1e-3, .inf]`` (spaces and line breaks only around the
#: commas, a trailing comma allowed): the bulk of a step-response model.  The numbers are YAML 1.2's
#: (:data:`_INT`, :data:`_FLOAT`), so the list holds exactly what the loader would construct.
_NUMBER = r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN)"
_SPACE = r"[ \r\n]*"
_NUMBER_LIST = re.compile(rf"{_SPACE}(?:{_NUMBER}){_SPACE}(?:,{_SPACE}(?:{_NUMBER}){_SPACE})*(?:,{_SPACE})?")
_FLOW_LIST = re.compile(r"\[([^\[\]{}#\"'\t]*)\]")
#: The local tag that stands for one such list while the rest of the text is parsed.
_LIST_TAG = "!mpm_monitor_numbers"
_NOT_PARSED = object()


def _number_value(token: str):
    """What the strict loader constructs for the plain scalar ``token`` (one of :data:`_NUMBER_LIST`'s)."""
    if _INT.match(token):
        return int(token)
    low = token.lower()
    if low.endswith(".inf"):
        return float("-inf") if low.startswith("-") else float("inf")
    return float("nan") if low == ".nan" else float(token)


def _token_values(tokens: list, text: str) -> list:
    """The numbers of ``tokens`` (each one of :data:`_NUMBER`'s forms; ``text`` holds them all)."""
    if "n" in text or "N" in text:          # .inf or .nan
        return [_number_value(t) for t in tokens]
    return [float(t) if "." in t or "e" in t or "E" in t else int(t) for t in tokens]   # else _INT's


#: A run of block sequence items at one indentation, each a plain number alone on its line.
_BLOCK_RUN = re.compile(rf"^( *)- (?:{_NUMBER}) *\r?\n(?:\1- (?:{_NUMBER}) *\r?\n)*", re.MULTILINE)
#: The start of the line before such a run when the run's first item is on it: the parents' ``- `` markers.
_MARKERS = re.compile(r"(?: |- )*")
_ITEM = re.compile(rf"- ({_NUMBER}) *\r?")


def _replace_block_lists(text: str, lists: list) -> str:
    """``text`` with every block sequence of plain numbers replaced by ``!mpm_monitor_numbers k`` (its
    numbers appended to ``lists``), as ``yaml.safe_dump`` writes a step response::

        coefficients:            coefficients:
        - - - 0                  - - !mpm_monitor_numbers 0
            - 0.18               ...
            - 0.33

    A run of lines ``- number`` at one indentation ``c`` is the whole sequence when the sequence
    starts there and ends there: it starts either on the line before, whose text before column ``c``
    is only its parents' ``- `` markers and whose rest is its first item (as above), or after a line
    ``key:`` indented at most ``c``; and the next line that is not blank or a comment is indented less
    than ``c``, or at ``c`` without a ``-``.  Any other run is left as written (to YAML, always safe);
    :func:`_parse_number_lists` then checks that every replacement was read as a value.  A text with a
    flow collection anywhere (a ``[``, ``]``, ``{`` or ``}``) is left as written: a run inside one is not
    a block sequence.
    """
    if any(c in text for c in "[]{}"):
        return text
    edits = []
    for run in _BLOCK_RUN.finditer(text):
        a, b, c = run.start(), run.end(), len(run.group(1))
        if not _ends_at(text, b, c):
            continue
        line = text.rfind("\n", 0, a - 1) + 1 if a > 0 else a
        prev = text[line:max(a - 1, line)].rstrip("\r")
        tokens = [m.group(1) for m in _ITEM.finditer(run.group(0))]
        first = _ITEM.fullmatch(prev, c) if a > 0 and len(prev) > c else None
        if first is not None and _MARKERS.fullmatch(prev, 0, c) and prev[c - 2:c] == "- ":
            tokens.insert(0, first.group(1))
            start, lead = line + c, ""
        elif a > 0 and prev.rstrip().endswith(":") and "#" not in prev and len(prev) - len(prev.lstrip(" ")) <= c:
            start, lead = a, " " * (c + 1)
        else:
            continue
        lists.append(_token_values(tokens, " ".join(tokens)))
        edits.append((start, b, f"{lead}{_LIST_TAG} {len(lists) - 1}\n"))
    if not edits:
        return text
    parts, at = [], 0
    for start, end, new in edits:
        parts += [text[at:start], new]
        at = end
    parts.append(text[at:])
    return "".join(parts)


def _ends_at(text: str, at: int, indent: int) -> bool:
    """Whether a block sequence at ``indent`` ends before offset ``at`` (a line start): the next line that
    is not blank or a comment is indented less, or as much without a ``-`` (or there is none)."""
    while at < len(text):
        end = text.find("\n", at)
        end = len(text) if end < 0 else end
        body = text[at:end].rstrip("\r")
        stripped = body.lstrip(" ")
        if stripped and not stripped.startswith("#"):
            level = len(body) - len(stripped)
            return level < indent or (level == indent and not stripped.startswith("-"))
        at = end + 1
    return True


def _parse_number_lists(text: str):
    """The text parsed with every flow list of plain numbers read in one pass (its tokens split and
    converted here) instead of as a YAML node per number, which takes about 5 us a number: a 100 x 40
    step-response model of 120 coefficients holds 480,000 of them.  A list may run over several lines,
    as PyYAML's ``dump`` wraps it (a flow list's lines need no indentation, to PyYAML and libyaml alike).

    A block sequence of numbers, one ``- number`` per line (``yaml.safe_dump``'s style), is read so too
    (:func:`_replace_block_lists`).

    Each such list that starts before any ``#`` on its line is replaced by the scalar
    ``!mpm_monitor_numbers k`` before the text is parsed.  The result is used only when every
    replacement was constructed exactly once as that tagged scalar: a list written inside a quoted or
    block string or a longer plain scalar is not, and neither is one a YAML error surrounds.  Otherwise
    (and when the text already holds the tag, or a number will not convert) the result is
    :data:`_NOT_PARSED`, and the caller parses the text as written: its values, and its errors with
    their lines, are then the YAML parser's.
    """
    if _LIST_TAG in text:
        return _NOT_PARSED
    lists: list = []

    first_hash: dict = {}                      # line start -> its first '#' (-1: none)

    def replace(match):
        content, at = match.group(1), match.start()
        line = text.rfind("\n", 0, at) + 1
        sign = first_hash.get(line)
        if sign is None:
            end = text.find("\n", line)
            sign = first_hash[line] = text.find("#", line, len(text) if end < 0 else end)
        if 0 <= sign < at or not _NUMBER_LIST.fullmatch(content):
            return match.group(0)             # in a comment (or after a quoted '#'), or not only numbers
        tokens = [t.strip() for t in content.split(",")]
        if not tokens[-1]:
            tokens.pop()                       # a trailing comma
        lists.append(_token_values(tokens, content))
        return f"{_LIST_TAG} {len(lists) - 1}"

    try:
        text = _replace_block_lists(text, lists)
        # A list after a '#' on its line is left as written (a comment's, or a quoted string's: not replacing
        # is always safe).
        replaced = _FLOW_LIST.sub(replace, text)
    except (ValueError, OverflowError):     # a number Python will not convert (an int of 5,000 digits)
        return _NOT_PARSED
    if not lists:
        return _NOT_PARSED
    base = _C_LOADER if _C_LOADER is not None else _LOADER
    seen: set = set()

    def construct(loader, node):
        plain = isinstance(node, yaml.ScalarNode) and not node.style      # libyaml's plain style is '', PyYAML's None
        value = node.value if plain else ""
        k = int(value) if value.isascii() and value.isdigit() and str(int(value)) == value else -1
        if not 0 <= k < len(lists) or k in seen:
            raise ValueError("not a list this parse replaced")
        seen.add(k)
        return lists[k]

    if base is _C_LOADER and nests_deeper(replaced, _C_MAX_NESTING, _C_LOADER):
        # libyaml's composer would overflow the stack (a segmentation fault) before any error: the caller
        # checks the nesting of the text as written and refuses it in one line.
        return _NOT_PARSED
    loader = base(replaced)
    loader.yaml_constructors = {**base.yaml_constructors, _LIST_TAG: construct}   # this loader's only
    try:
        data = loader.get_single_data()
    except (yaml.YAMLError, RecursionError, ValueError, TypeError):
        return _NOT_PARSED
    finally:
        loader.dispose()
    if len(seen) != len(lists) or not _depth_within(data, _MAX_DEPTH):
        return _NOT_PARSED
    return data


def _parse_yaml(text: str):
    """``yaml.safe_load(text)``, by libyaml's parser when PyYAML has it (the same safe constructor and
    resolver: the same values, many times faster on a large model); a text it refuses is parsed again
    by the pure-Python parser, whose error names the problem and its place as before.  The lists of
    numbers are read first in one pass (:func:`_parse_number_lists`), when that gives the same values."""
    data = _parse_number_lists(text)
    if data is not _NOT_PARSED:
        return data
    if _C_LOADER is not None:
        if nests_deeper(text, _C_MAX_NESTING, _C_LOADER):
            raise RecursionError(f"lists or mappings nested more than {_C_MAX_NESTING} deep")
        try:
            data = yaml.load(text, Loader=_C_LOADER)
        except (yaml.YAMLError, RecursionError, ValueError, TypeError):
            data = None
        else:
            if _depth_within(data, _MAX_DEPTH):
                return data
    return yaml.load(text, Loader=_LOADER)


#: Nesting beyond which a text is refused before libyaml composes it: its composer recurses in C once per level,
#: and near 25,000 levels (a 50 kB file) it overflows the process's stack (a segmentation fault, no message);
#: Python's recursion limit never sees it.  The pure-Python parser refuses far less (its recursion limit).
_C_MAX_NESTING = 1000


#: Values (numbers, strings, ...) a model file may hold once its aliases are expanded: a 100 x 40 step-response
#: model of 300 coefficients holds 1.2 million.  A few lines of nested aliases can expand to billions (a
#: "billion laughs"), which every reader of the lists would then walk.
MAX_VALUES = 20_000_000


def _nests(values: list) -> bool:
    """Whether ``values`` holds a list or a mapping (its entries' types looked at once each)."""
    return any(issubclass(kind, (list, dict)) for kind in set(map(type, values)))


def _expanded_size(data) -> int:
    """The values ``data`` holds with its aliases expanded (a list or mapping reached twice counts twice),
    counted once per distinct list or mapping; stops counting past :data:`MAX_VALUES`."""
    sizes: dict = {}
    stack = [(data, False)]
    while stack:
        x, done = stack.pop()
        if not isinstance(x, (list, dict)) or (id(x) in sizes and not done):
            continue
        items = list(x.values()) + list(x.keys()) if isinstance(x, dict) else x
        if not done and isinstance(x, list) and not _nests(x):
            sizes[id(x)] = min(len(x), MAX_VALUES + 1)       # a list of plain values (numbers): its length
            continue
        if done:
            total = sum(sizes.get(id(v), 1) if isinstance(v, (list, dict)) else 1 for v in items)
            sizes[id(x)] = min(total, MAX_VALUES + 1)
            continue
        sizes[id(x)] = 0                       # on the stack (a cycle counts as nothing more)
        stack.append((x, True))
        stack.extend((v, False) for v in items if isinstance(v, (list, dict)) and id(v) not in sizes)
    return sizes.get(id(data), 1) if isinstance(data, (list, dict)) else 1


#: Nesting of lists and mappings beyond which a text is left to the pure-Python parser (a model file
#: nests 4 deep; that parser refuses a nesting its recursion cannot follow, see :func:`load_model`).
_MAX_DEPTH = 32


def _depth_within(data, limit: int) -> bool:
    """Whether the lists and mappings of ``data`` nest at most ``limit`` deep (each distinct one looked at
    once: the aliases of a file can repeat a list at every level)."""
    level, depth, seen = [data], 0, set()
    while level:
        depth += 1
        if depth > limit:
            return False
        nxt = []
        for x in level:
            if isinstance(x, dict):
                nxt.extend(v for v in x.values() if isinstance(v, (list, dict)))
            elif isinstance(x, list) and _nests(x):
                nxt.extend(v for v in x if isinstance(v, (list, dict)))
        level = [x for x in nxt if id(x) not in seen and not seen.add(id(x))]
    return True


def load_model(path) -> PlantModel:
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
    text = read_text(path, ModelFileError, "model file", "a YAML model file", max_bytes=MAX_MODEL_BYTES)
    try:
        data = _parse_yaml(text)
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
    if _expanded_size(data) > MAX_VALUES:
        raise ModelFileError(f"{path}: not a model file: its aliases expand to more than {MAX_VALUES:,} values "
                             f"(expected lists of the model's numbers)")
    return model_from_dict(data, source=str(path))


#: Largest model file read (bytes): a 100 x 40 step-response model of 300 coefficients is about 10 MB.  A larger
#: file, or a device that never ends (``/dev/zero``), is refused before it fills the memory.
MAX_MODEL_BYTES = 256 * 2 ** 20


def save_model(model: PlantModel, path) -> None:
    """Write a model to a YAML file that :func:`load_model` reads back identically."""
    text = dump_model(model)
    write_text_replacing(path, text)           # a reader of the file never sees half of it


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


def dump_model(model: PlantModel) -> str:
    """The model as YAML text, one matrix row per line (one line per output for step responses)."""
    d = model.to_dict()

    def flow(v):
        return yaml.dump(v, Dumper=_Dumper, default_flow_style=True).strip()

    def row(values):
        return "[" + ", ".join("true" if v is True else "false" if v is False else yaml_number(v) for v in values) + "]"

    lines = []
    if "name" in d:
        lines.append(f"name: {flow(d['name']).removesuffix('...').strip()}")
    lines.append(f"sample_time: {yaml_number(d['sample_time'])}")
    for key in ("inputs", "outputs", "disturbances"):
        if key in d:
            lines.append(f"{key}: {flow(d[key])}")
    for key in ("gain", "time_constant", "delay", "lead", "time_constant2", "integrating"):
        if key in d:
            lines.append(f"{key}: [{', '.join(row(r) for r in d[key])}]")
    if "step_response" in d:
        sr = d["step_response"]
        lines.append("step_response:")
        lines.append(f"  length: {sr['length']}")
        lines.append("  coefficients:")
        for name, r in zip(d["outputs"], sr["coefficients"]):
            lines.append(f"  - [{', '.join(row(el) for el in r)}]   # {name}")
        if "ramp" in d:
            lines.append(f"ramp: {row(d['ramp'])}")
    for key in NOMINAL_KEYS:
        if key in d:
            lines.append(f"{key}: {row(d[key])}")
    return "\n".join(lines) + "\n"
