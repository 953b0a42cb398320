"""JSON text of a report, indented, faster than :func:`json.dumps` with ``indent`` and the same.

Python's :mod:`json` writes indented text with its pure-Python encoder (its C encoder serves only
``indent=None``): at 100 outputs x 40 inputs a report's 3.5 MB took about 0.16 s.  :func:`dumps_indented`
gives the same text for the values a report holds (dicts with string keys, lists, tuples, strings,
integers, floats, booleans and None), writing a list of plain floats, or of plain integers and floats,
at once; anything else (another key type, a subclass, a value :mod:`json` would refuse or convert by
``default``) is handed to :func:`json.dumps` whole, so the result is always the text :func:`json.dumps`
gives.
"""

from __future__ import annotations

import json
from json.encoder import encode_basestring_ascii as _quoted

_float_repr = float.__repr__
_int_repr = int.__repr__
#: The types of a list written by json's C encoder at once (exactly these: not bool, nor numpy's scalars).
_NUMBERS = frozenset((int, float))


class _Unusual(Exception):
    """A value the fast path does not write: :func:`json.dumps` writes the whole document."""


def dumps_indented(obj, indent: int = 2) -> str:
    """``json.dumps(obj, indent=indent)``, the same text.

    Parameters
    ----------
    obj : dict, list or scalar
        JSON-ready data (e.g. :meth:`~mpm_monitor.core.analysis.AnalysisReport.to_dict`).
    indent : int
        Spaces per level.

    Returns
    -------
    str
        The text, without a final newline (as :func:`json.dumps`).
    """
    parts: list = []
    try:
        _write(obj, "\n", " " * indent, parts)
    except (_Unusual, RecursionError):
        return json.dumps(obj, indent=indent)
    return "".join(parts)


def _scalar(o) -> str:
    t = type(o)
    if t is str:
        return _quoted(o)
    if t is float:
        if o != o or o in (float("inf"), float("-inf")):
            return "NaN" if o != o else ("Infinity" if o > 0 else "-Infinity")
        return _float_repr(o)
    if t is int:
        return _int_repr(o)
    if o is None:
        return "null"
    if o is True:
        return "true"
    if o is False:
        return "false"
    raise _Unusual


def _write(o, newline: str, step: str, out: list) -> None:
    """Append the text of ``o`` to ``out``; ``newline`` is a newline and the current indentation."""
    append = out.append
    t = type(o)
    if t is dict:
        if not o:
            append("{}")
            return
        inner = newline + step
        sep = "{" + inner
        for key, value in o.items():
            if type(key) is not str:
                raise _Unusual
            vt = type(value)
            if vt is float:
                text = _float_repr(value)
                append(sep + _quoted(key) + ": " + (text if "n" not in text else _scalar(value)))
            elif vt is str:
                append(sep + _quoted(key) + ": " + _quoted(value))
            elif vt is dict or vt is list or vt is tuple:
                append(sep + _quoted(key) + ": ")
                _write(value, inner, step, out)
            else:
                append(sep + _quoted(key) + ": " + _scalar(value))
            sep = "," + inner
        append(newline + "}")
    elif t is list or t is tuple:
        if not o:
            append("[]")
            return
        inner = newline + step
        try:       # a list of plain floats (the report's series) at once
            text = ("," + inner).join(map(_float_repr, o))
        except TypeError:
            text = None
        if text is not None and "n" not in text:      # nan and inf are written by _scalar
            append("[" + inner + text + newline + "]")
            return
        if text is None and set(map(type, o)) <= _NUMBERS:
            # Plain ints and floats (a model's numbers, integral ones as ints): json's C encoder writes each
            # as _scalar does (repr, NaN, Infinity), separated by ", ", which no number holds.
            append("[" + inner + ("," + inner).join(json.dumps(o)[1:-1].split(", ")) + newline + "]")
            return
        sep = "[" + inner
        for value in o:
            vt = type(value)
            if vt is dict or vt is list or vt is tuple:
                append(sep)
                _write(value, inner, step, out)
            else:
                append(sep + _scalar(value))
            sep = "," + inner
        append(newline + "]")
    else:
        append(_scalar(o))
