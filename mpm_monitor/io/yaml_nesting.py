"""How deep the lists and mappings of a YAML text nest, found without recursing.

The YAML loaders recurse once per level of nesting: the pure-Python one reaches Python's recursion limit after
seconds, and libyaml's C composer overflows the stack (a segmentation fault, no message).  The model file reader
(:mod:`mpm_monitor.io.model_file`) and the bag reader's check of ``metadata.yaml``
(:mod:`mpm_monitor.io.bags.common`) ask :func:`nests_deeper` first and refuse a text nested beyond their limit in
one line.
"""

from __future__ import annotations

import re

import yaml

#: The run of blanks and block indicators ("- ", "? ", ": ") that starts a line (any YAML line break).
_LINE_PREFIX = re.compile(r"(?:\A|[\r\n\x85\u2028\u2029])[ \t?:-]*")


def nesting_bound(text: str) -> int:
    """An upper bound of the nesting of the lists and mappings of a YAML text, in one pass.

    A flow collection opens with ``[`` or ``{`` (those in strings only raise the bound).  A block
    collection is deeper than its parent by its indentation or by an indicator on the same line, and a
    mapping's sequence may share the mapping's indentation: twice the longest blank-and-indicator run
    that starts a line, plus two.

    Parameters
    ----------
    text : str

    Returns
    -------
    int
        At least the depth of the deepest list or mapping.
    """
    prefix = max((len(m.group()) for m in _LINE_PREFIX.finditer(text)), default=0)
    return text.count("[") + text.count("{") + 2 * prefix + 2


def nests_deeper(text: str, limit: int, loader=None) -> bool:
    """Whether the lists and mappings of ``text`` nest more than ``limit`` deep.

    :func:`nesting_bound` first; only when that bound is above ``limit``, PyYAML's event parser (not recursive),
    read until the answer is known.

    Parameters
    ----------
    text : str
    limit : int
        Deepest nesting allowed.
    loader : type, optional
        The loader class whose parser reads the events (default libyaml's ``CSafeLoader`` when PyYAML has it,
        else ``SafeLoader``).

    Returns
    -------
    bool
        False also for a text the parser refuses (the loaders then name its error).
    """
    if nesting_bound(text) <= limit:
        return False
    depth = 0
    try:
        for event in yaml.parse(text, Loader=loader or getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
            if isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
                depth += 1
                if depth > limit:
                    return True
            elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
                depth -= 1
    except Exception:  # noqa: BLE001 - YAMLError, ValueError, ...: the loaders name it
        return False
    return False
