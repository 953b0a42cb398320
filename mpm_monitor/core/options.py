"""Options described once: type, default, description and allowed range of each setting.

A :class:`ParamSpec` is what the command line turns into a flag and a ROS 2 node into a declared
parameter (:func:`mpm_monitor.nodes.ros_io.declare_parameters`), and its :meth:`ParamSpec.check` is the
one check both apply.  It knows nothing of argparse or rclpy.
"""

from __future__ import annotations

import dataclasses
import math
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
        Inclusive range of an ``int`` or ``double``.
    choices : tuple of str or None
        Allowed values of a ``string``.
    numbers_as_text : bool
        A ``string`` that may also be given as a number (``-p case:=3.2``): declared with dynamic
        typing and the number turned into its text (``"3.2"``).
    read_only : bool
        Settable only at start-up (params file or ``-p``); the parameter services refuse changes.
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

    def check(self, value):
        """Return ``value`` converted to the parameter's Python type or raise :class:`ConfigurationError`."""
        n = self.name
        if value is None:
            if self.default is None:
                return None
            raise ConfigurationError(f"parameter {n}: not set (expected {self.kind})")
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise ConfigurationError(f"parameter {n}: expected true or false, got {value!r}")
            return value
        if self.kind in ("int", "double"):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigurationError(f"parameter {n}: expected a number, got {value!r}")
            if self.kind == "int" and int(value) != value:
                raise ConfigurationError(f"parameter {n}: expected an integer, got {value!r}")
            value = int(value) if self.kind == "int" else float(value)
            if not math.isfinite(value):
                raise ConfigurationError(f"parameter {n}: expected a finite number, got {value!r}")
            if (self.low is not None and value < self.low) or (self.high is not None and value > self.high):
                raise ConfigurationError(f"parameter {n}: expected a value in [{self.low:g}, {self.high:g}], "
                                         f"got {value!r}")
            return value
        if self.kind == "string":
            if self.numbers_as_text and isinstance(value, (int, float)) and not isinstance(value, bool):
                value = format(value, "g")
            if not isinstance(value, str):
                raise ConfigurationError(f"parameter {n}: expected a string, got {value!r}")
            if self.choices is not None and value not in self.choices:
                raise ConfigurationError(f"parameter {n}: expected one of {', '.join(repr(c) for c in self.choices)}, "
                                         f"got {value!r}")
            return value
        if self.kind == "double_array":
            arr = np.asarray(list(value), dtype=float)
            if not np.all(np.isfinite(arr)):
                raise ConfigurationError(f"parameter {n}: expected finite numbers, got {list(value)!r}")
            return arr.tolist()
        if self.kind == "string_array":
            return [str(s) for s in value]
        raise ValueError(f"unknown parameter kind {self.kind!r}")
