"""The check of the ``--params-file`` arguments of a node's command line, before ``rclpy.init`` reads them.

``rclpy.init`` hands the ROS arguments to rcl, which parses every ``--params-file`` and, when one cannot be
read or is not a ROS params file, prints its own ``[ERROR] [...] [rcl]: Failed to parse global arguments``
line on stderr and raises.  :func:`params_file_problem` finds those files first, by the ``--ros-args``
grammar rcl uses (:func:`ros_params_files`), and says what is wrong with the first bad one in one line
(:func:`~mpm_monitor.nodes.ros_io.run_node` prints it as ``error: ...`` and exits 2 without calling
``rclpy.init``); a file it passes goes to rcl as before.

What is refused is what rcl's parser refuses (each case was tried on it):

- a file that cannot be read, is not UTF-8 text or not YAML, or holds an alias (``*name``);
- a top level that is not ``node_name: {ros__parameters: {...}}`` per node: a key holding a value, a list
  or nothing where a node name or namespace is expected, an empty key, a list or mapping as a key,
  ``ros__parameters`` with no node name above it or holding a value, a list of values or nothing;
- a node name or namespace that is not letters, digits and underscores (not starting with a digit), with
  ``/`` between namespace parts and the wildcards ``*`` and ``**`` (``/**/monitor``, ``/**``);
- a parameter with no value (``name:`` and nothing), and a list whose values are of different types
  (``[0, 0.5]``: an integer and a double) -- a value's type as rcl reads it (:func:`_rcl_type`), and only
  where it is certain.

And, as the check always did although rcl reads them, an empty file and a file of several YAML documents;
and, not tried on rcl, a file longer than :data:`MAX_PARAMS_FILE_BYTES` or nested deeper than PyYAML
composes (the check read such a file whole, or ended in a traceback).  A file it passes may still be
refused by rcl in a case it does not know (the order of a node's keys, for one); that file gets rcl's own
messages, as before.

Only the standard library and PyYAML (imported when a file is checked): no ``rclpy``.
"""

from __future__ import annotations

import functools
import re

#: Flags of a ``--ros-args`` section that take the next argument as their value (rcl/arguments.h).
ROS_FLAGS_WITH_VALUE = ("-r", "--remap", "-p", "--param", "--params-file", "-e", "--enclave", "--log-level",
                        "--log-file-name", "--log-config-file")

#: Longest params file read (bytes): a longer one is refused unread (a device such as ``/dev/zero`` never ends).
MAX_PARAMS_FILE_BYTES = 16 * 2**20

#: The key rcl takes as the start of a node's parameters (any key that begins with it).
PARAMS_KEY = "ros__parameters"

#: What a params file holds, for the messages.
PARAMS_FILE_FORM = ("a ROS params file, node_name: {ros__parameters: {name: value, ...}} per node "
                    "(node_name may be /**/name or /**)")

#: What a node name and each part of a namespace are, for the messages.
NAME_FORM = "letters, digits and underscores, not starting with a digit (or the wildcard * or **)"

#: A node name or a namespace part rcl takes (rmw's rule); ``*`` and ``**`` are the wildcards.
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_WILDCARDS = ("*", "**")

#: The plain scalars rcl reads as booleans (rcl_yaml_param_parser's get_value).
_RCL_BOOLS = frozenset("Y y yes Yes YES true True TRUE on On ON N n no No NO false False FALSE off Off OFF".split())
#: Plain scalars rcl reads as integers: strtol(value, 0) over the whole text (hex, octal, decimal).
_RCL_INT = re.compile(r"[+-]?(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)\Z")
#: Plain scalars rcl reads as doubles for certain: strtod over the whole text, the decimal forms.
_RCL_DOUBLE = re.compile(r"[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]+)?\Z")
_RCL_DOUBLE_WORDS = frozenset(".nan .NaN .NAN .inf .Inf .INF +.inf +.Inf +.INF -.inf -.Inf -.INF".split())
#: Plain scalars strtod may take in forms not sorted out here (inf, nan, hex floats, ...): type unknown.
_NUMBER_LIKE = re.compile(r"[+-]?([0-9.]|inf|nan)", re.IGNORECASE)


class _ParamsFileError(Exception):
    """What rcl refuses in a params file: ``line`` (1-based), what is there and what was expected."""

    def __init__(self, line: int, what: str, expected: str = PARAMS_FILE_FORM):
        super().__init__(what)
        self.line = line
        self.what = what
        self.expected = expected


def ros_params_files(args) -> list:
    """The ``--params-file`` paths of the ROS arguments in ``args``, in order (None for a ``--params-file``
    that ends the command line without a path).

    Only the ``--ros-args`` sections count (each ended by ``--`` or by the end of the command line), and the
    value of a flag that takes one (:data:`ROS_FLAGS_WITH_VALUE`: ``-p --params-file`` is a parameter rule) is
    never a flag itself, as rcl reads them.

    Parameters
    ----------
    args : sequence of str or None
        A command line (``sys.argv``, with or without the program's name first).

    Returns
    -------
    list of str or None
    """
    args = [str(a) for a in (args or ())]
    files: list = []
    in_ros, k = False, 0
    while k < len(args):
        arg = args[k]
        if not in_ros:
            in_ros = arg == "--ros-args"
        elif arg == "--":
            in_ros = False
        elif arg in ROS_FLAGS_WITH_VALUE:
            if arg == "--params-file":
                files.append(args[k + 1] if k + 1 < len(args) else None)
            k += 1
        k += 1
    return files


def params_file_problem(args) -> str:
    """Why a ``--params-file`` of the ROS arguments ``args`` cannot be given to rcl ('' when every one can):
    ``--params-file PATH: ...``, one line, saying what was expected.

    Parameters
    ----------
    args : sequence of str or None
        A command line (see :func:`ros_params_files`).

    Returns
    -------
    str
        The problem of the first bad file, or ''.
    """
    for path in ros_params_files(args):
        if path is None:
            return "--params-file: expected the path of a params file after it (it ends the command line)"
        problem = params_text_problem(path)
        if problem:
            return f"--params-file {path}: {problem}"
    return ""


def params_text_problem(path) -> str:
    """Why the file ``path`` is no params file rcl reads ('' when it is one; see the module docstring).

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    str
        ``cannot read it: ...``, ``not valid YAML at line 2, column 3: ...; expected ...``, ``empty ...``,
        ``line 4: ...: expected ...``; '' when the file is fine.
    """
    import yaml

    try:
        with open(path, "rb") as fh:
            raw = fh.read(MAX_PARAMS_FILE_BYTES + 1)        # a device such as /dev/zero never ends
    except OSError as exc:
        return f"cannot read it: {exc.strerror or exc}"
    if len(raw) > MAX_PARAMS_FILE_BYTES:
        return f"longer than {MAX_PARAMS_FILE_BYTES:,} bytes: expected {PARAMS_FILE_FORM}"
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        return f"not UTF-8 text (byte 0x{raw[exc.start]:02x} at offset {exc.start}): expected {PARAMS_FILE_FORM}"
    try:
        doc = yaml.compose(text, Loader=_loader())
        if doc is None:
            return f"empty (no YAML document): expected {PARAMS_FILE_FORM}"
        _check_names_level(doc, ())
    except _ParamsFileError as exc:
        return f"line {exc.line}: {exc.what}: expected {exc.expected}"
    except yaml.YAMLError as exc:
        return f"not valid YAML{_yaml_error_text(exc)}; expected {PARAMS_FILE_FORM}"
    except RecursionError:
        return f"lists or mappings nested too deeply: expected {PARAMS_FILE_FORM}"
    return ""


def _yaml_error_text(exc) -> str:
    """`` at line 2, column 20: expected ',' or ']', but got '<stream end>'`` (as a model file's message says
    it), `` at character 12: ...`` for a character YAML does not allow."""
    import yaml

    mark = getattr(exc, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    if isinstance(exc, yaml.reader.ReaderError):       # a control character: no mark, a position
        where = f" at character {exc.position + 1}"
    problem = getattr(exc, "problem", None) or getattr(exc, "reason", None) or "invalid YAML"
    return f"{where}: {' '.join(str(problem).split())[:200]}"


@functools.lru_cache(maxsize=None)
def _loader():
    """A PyYAML loader that composes the nodes (no Python objects are made of the values, so no tag or
    date can fail there) and raises :class:`_ParamsFileError` at an alias, which rcl refuses."""
    import yaml

    class NoAliasLoader(yaml.SafeLoader):
        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                event = self.peek_event()
                raise _ParamsFileError(event.start_mark.line + 1, f"an alias (*{event.anchor})",
                                       "the value written out (rcl takes no aliases)")
            return super().compose_node(parent, index)

    return NoAliasLoader


def _line(node) -> int:
    return node.start_mark.line + 1


def _shown(node) -> str:
    """A node for a message: a scalar's text (quoted, cut to 40 characters; ``nothing`` for a null), or
    ``a list``, ``a mapping``."""
    import yaml

    if isinstance(node, yaml.ScalarNode):
        if node.tag == "tag:yaml.org,2002:null" and node.value in ("", "~", "null", "Null", "NULL"):
            return "nothing"
        return repr(node.value if len(node.value) <= 40 else node.value[:40] + "...")
    return "a list" if isinstance(node, yaml.SequenceNode) else "a mapping"


def _check_names_level(node, names: tuple) -> None:
    """Check a mapping above ``ros__parameters``: the top level when ``names`` is empty, else the value of the
    node name or namespace keys ``names`` (each ``(text, line)``); raise :class:`_ParamsFileError` at the first
    thing rcl refuses."""
    import yaml

    if not isinstance(node, yaml.MappingNode):       # only the top level: the levels below are checked first
        raise _ParamsFileError(_line(node), f"{_shown(node)} at the top level")
    for key, value in node.value:
        if not isinstance(key, yaml.ScalarNode):
            raise _ParamsFileError(_line(key), f"{_shown(key)} as a key")
        if key.value == "":
            raise _ParamsFileError(_line(key), "an empty key")
        if key.value.startswith(PARAMS_KEY):
            _check_node_name(key, names)
            if isinstance(value, yaml.ScalarNode) or (isinstance(value, yaml.SequenceNode) and any(
                    isinstance(v, yaml.ScalarNode) for v in value.value)):
                raise _ParamsFileError(_line(key), f"{key.value} of {'/'.join(t for t, _ in names)} holds "
                                                   f"{_shown(value)}, not a mapping of parameter names to values")
            if isinstance(value, yaml.MappingNode):
                _check_parameters(value, ())
        elif isinstance(value, yaml.MappingNode):
            _check_names_level(value, names + ((key.value, _line(key)),))
        else:
            raise _ParamsFileError(_line(key), f"key {_shown(key)} holds {_shown(value)} outside any node's "
                                               f"{PARAMS_KEY}")


def _check_node_name(key, names: tuple) -> None:
    """Check the node name (with its namespace) that the keys ``names`` make, above the ``ros__parameters``
    key ``key``, as rcl does: ``ns/sub/node``, ``/**/node``, ``/**``."""
    if not names:
        raise _ParamsFileError(_line(key), f"{key.value} with no node name above it")
    full, line = "/".join(t for t, _ in names), names[-1][1]
    if full == "/**":
        return
    if "//" in full:
        raise _ParamsFileError(line, f"node name {full!r} (a repeated /)", NAME_FORM + ", parts separated by one /")
    namespace, _, node_name = full.rpartition("/")
    if node_name not in _WILDCARDS and not _NAME.match(node_name):
        raise _ParamsFileError(line, f"node name {node_name!r} of {full!r}", f"a node name of {NAME_FORM}")
    parts = namespace[1:] if namespace.startswith("/") else namespace
    for part in parts.split("/") if parts else ():
        if part not in _WILDCARDS and not _NAME.match(part):
            raise _ParamsFileError(line, f"namespace part {part!r} of {full!r}", f"namespace parts of {NAME_FORM}")


def _check_parameters(node, prefix: tuple) -> None:
    """Check the parameters in the mapping ``node`` (under the parameter namespaces ``prefix``): no parameter
    without a value, no list of values of different types."""
    import yaml

    for key, value in node.value:
        if not isinstance(key, yaml.ScalarNode):
            continue                      # left to rcl
        name = ".".join(prefix + (key.value,))
        if isinstance(value, yaml.MappingNode):
            _check_parameters(value, prefix + (key.value,))
        elif isinstance(value, yaml.ScalarNode):
            if value.value == "" and value.style is None:
                raise _ParamsFileError(_line(key), f"parameter {name} has no value",
                                       "a value after the colon ('' for an empty string)")
        elif isinstance(value, yaml.SequenceNode) and all(isinstance(v, yaml.ScalarNode) for v in value.value):
            known = [(t, v) for v in value.value for t in [_rcl_type(v)] if t is not None]
            other = next(((t, v) for t, v in known if t != known[0][0]), None)
            if other is not None:
                first, second = known[0], other
                raise _ParamsFileError(
                    _line(second[1]), f"the list of parameter {name} mixes {first[0]} {first[1].value!r} and "
                                      f"{second[0]} {second[1].value!r}",
                    "values of one type (in a list of doubles write 0.0, not 0; quote a string that reads as a "
                    "number or a boolean)")


def _rcl_type(node) -> "str | None":
    """The type rcl gives a scalar of a list (``bool``, ``integer``, ``double``, ``string``), or None where it
    is not certain here (``inf``, ``nan``, hex floats, an integer beyond 64 bits: strtod's other forms)."""
    text = node.value
    if node.style in ("'", '"'):
        return "string"
    if text in _RCL_BOOLS:
        return "bool"
    if _RCL_INT.match(text):
        digits = text.lstrip("+-")
        if digits[:2] in ("0x", "0X"):
            value = int(digits, 16)
        else:
            value = int(digits, 8) if digits.startswith("0") and len(digits) > 1 else int(digits)
        value = -value if text.startswith("-") else value
        return "integer" if -2**63 <= value < 2**63 else None
    if text in _RCL_DOUBLE_WORDS or _RCL_DOUBLE.match(text):
        return "double"
    if text == "" or _NUMBER_LIKE.match(text):
        return None
    return "string"
