"""Options described once: type, default, description and allowed range of each setting.

A :class:`ParamSpec` is what the command line turns into a flag and a ROS 2 node into a declared
parameter (:func:`mpm_monitor.nodes.ros_io.declare_parameters`), and its :meth:`ParamSpec.check` is the
one check both apply.  It knows nothing of argparse or rclpy.

The fields of an options dataclass (such as :class:`mpm_monitor.core.analysis.AnalysisOptions`) are
declared with :func:`option`, which writes each default once; :func:`option_specs` derives their
:class:`ParamSpec` (the kind from the field's type) and :func:`check_options` checks an instance
with them.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import numbers
import typing
from typing import Any, Optional

import numpy as np

from .errors import ConfigurationError


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """A node parameter: its type, default, description and allowed range.

    Attributes
    ----------
    name : str
    kind : str
        ``bool``, ``int``, ``double``, ``string``, ``double_array`` or ``string_array``.
    default : object
        Default value; None for an optional array (declared without a value).
    description : str
        One sentence with the unit.
    low, high : float or None
        Range of an ``int`` or ``double`` (of every element of a ``double_array``), inclusive unless
        ``open_low`` / ``open_high``.
    choices : tuple of str or None
        Allowed values of a ``string``.
    numbers_as_text : bool
        A ``string`` that may also be given as a number (``-p case:=3.2``): declared with dynamic
        typing and the number turned into its text (``"3.2"``).
    read_only : bool
        Settable only at start-up (params file or ``-p``); the parameter services refuse changes.
        Every parameter that is not ``live`` is declared so (a node reads it once, at start-up);
        this flag marks the ones whose description says why they must stay fixed.
    live : bool
        Applied while the node runs: a change through the parameter services is checked like a
        start-up value (refused with the reason when out of range) and takes effect at once.
    open_low, open_high : bool
        ``low`` (``high``) itself is outside the range.  A ROS 2 range is inclusive: a node
        declares ``[low, high]`` and :meth:`check` refuses the open end.
    length : int or None
        Number of elements of a ``double_array``.
    empty_is_none : bool
        A ``*_topic`` or ``*_service`` string whose ``''`` means none (no topic); any other such name must be one
        ROS 2 can use, ``''`` included.
    """

    name: str
    kind: str
    default: Any
    description: str
    low: Optional[float] = None
    high: Optional[float] = None
    choices: Optional[tuple] = None
    numbers_as_text: bool = False
    read_only: bool = False
    live: bool = False
    open_low: bool = False
    open_high: bool = False
    length: Optional[int] = None
    empty_is_none: bool = False

    def range_text(self) -> str:
        """The range as text, e.g. ``[0, 50]`` or ``(0, 0.5)``; empty without a range."""
        if self.low is None and self.high is None:
            return ""
        low = "-inf" if self.low is None else f"{self.low:g}"
        high = "inf" if self.high is None else f"{self.high:g}"
        return f"{'(' if self.open_low else '['}{low}, {high}{')' if self.open_high else ']'}"

    def _in_range(self, x: float) -> bool:
        if self.low is not None and (x <= self.low if self.open_low else x < self.low):
            return False
        return not (self.high is not None and (x >= self.high if self.open_high else x > self.high))

    def check(self, value):
        """Return ``value`` converted to the parameter's Python type or raise :class:`ConfigurationError`."""
        n = self.name
        if value is None:
            if self.default is None:
                return None
            raise ConfigurationError(f"parameter {n}: not set (expected {self.kind})")
        if self.kind == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise ConfigurationError(f"parameter {n}: expected true or false, got {value!r}")
            return bool(value)
        if self.kind in ("int", "double"):
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
                raise ConfigurationError(f"parameter {n}: expected a number, got {value!r}")
            if self.kind == "int" and int(value) != value:
                raise ConfigurationError(f"parameter {n}: expected an integer, got {value!r}")
            value = int(value) if self.kind == "int" else float(value)
            if not math.isfinite(value):
                raise ConfigurationError(f"parameter {n}: expected a finite number, got {value!r}")
            if not self._in_range(value):
                raise ConfigurationError(f"parameter {n}: expected a value in {self.range_text()}, got {value!r}")
            return value
        if self.kind == "string":
            if self.numbers_as_text and isinstance(value, (int, float)) and not isinstance(value, bool):
                value = format(value, "g")
            if not isinstance(value, str) or (self.choices is not None and value not in self.choices):
                wanted = "a string" if self.choices is None else f"one of {', '.join(repr(c) for c in self.choices)}"
                raise ConfigurationError(f"parameter {n}: expected {wanted}, got {value!r}")
            return value
        if self.kind == "double_array":
            try:
                arr = np.asarray(list(value), dtype=float)
            except (TypeError, ValueError):
                raise ConfigurationError(f"parameter {n}: expected a list of numbers, got {value!r}") from None
            if not np.all(np.isfinite(arr)):
                raise ConfigurationError(f"parameter {n}: expected finite numbers, got {list(value)!r}")
            if self.length is not None and arr.shape != (self.length,):
                raise ConfigurationError(f"parameter {n}: expected {self.length} numbers, got {list(value)!r}")
            if not all(self._in_range(x) for x in arr):
                raise ConfigurationError(f"parameter {n}: expected values in {self.range_text()}, got {list(value)!r}")
            return arr.tolist()
        if self.kind == "string_array":
            return [str(s) for s in value]
        raise ValueError(f"unknown parameter kind {self.kind!r}")


#: Key of an :func:`option` field's metadata.
_OPTION = "mpm_monitor.option"

#: ParamSpec kind of an option field's type.
_KINDS = {bool: "bool", int: "int", float: "double", str: "string", tuple: "double_array"}


def option(default, description: str, **limits):
    """A dataclass field with its default, its description and its range (a :class:`ParamSpec`).

    Parameters
    ----------
    default : object
        The field's default (a tuple for a ``double_array``; None for an optional value).
    description : str
        One sentence with the unit.
    **limits
        ``low``, ``high``, ``open_low``, ``open_high``, ``choices``, ``length`` of :class:`ParamSpec`.

    Returns
    -------
    dataclasses.Field
    """
    return dataclasses.field(default=default, metadata={_OPTION: dict(description=description, **limits)})


def _kind(tp) -> str:
    args = [a for a in typing.get_args(tp) if a is not type(None)]
    return _KINDS[args[0] if args else tp]


@functools.lru_cache(maxsize=None)
def option_specs(cls) -> tuple:
    """The :class:`ParamSpec` of every :func:`option` field of the dataclass ``cls``, in field order."""
    hints = typing.get_type_hints(cls)
    return tuple(ParamSpec(f.name, _kind(hints[f.name]), f.default, **f.metadata[_OPTION])
                 for f in dataclasses.fields(cls) if _OPTION in f.metadata)


def check_options(obj) -> dict:
    """Every :func:`option` field of ``obj`` checked by its :class:`ParamSpec` (:meth:`ParamSpec.check`).

    Returns
    -------
    dict
        Field name -> the value converted to the field's type (a ``double_array`` given as a tuple
        by its default comes back as a tuple).

    Raises
    ------
    ConfigurationError
        Naming the first field out of its range.
    """
    out = {}
    for spec in option_specs(type(obj)):
        value = spec.check(getattr(obj, spec.name))
        out[spec.name] = tuple(value) if isinstance(spec.default, tuple) and value is not None else value
    return out
