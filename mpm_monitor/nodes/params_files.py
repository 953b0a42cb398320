"""The params files ``config/<node>.yaml``, generated from the nodes' declared parameters.

Every node declares its parameters in a ``PARAMS`` tuple of :class:`~mpm_monitor.core.options.ParamSpec`
(type, default, description, range; declared by :func:`mpm_monitor.nodes.ros_io.declare_parameters`);
the files in ``config/`` are written from those tuples so that the documentation of a parameter can
never drift from the code (a test compares them).  A file is named after the node's default name,
which is also its key in the file.

Run ``python -m mpm_monitor.nodes.params_files [--check] [--dir config]``; ``--markdown`` prints
the README's parameter tables.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import textwrap
from pathlib import Path

from ..io.model_file import yaml_number

#: default node name -> (module, title)
NODES = {
    "plant": ("plant_node", "Plant simulator node"),
    "mpc": ("mpc_node", "MPC controller node"),
    "setpoint": ("setpoint_node", "Setpoint generator node"),
    "monitor": ("monitor_node", "Live mismatch monitor node"),
    "mpm_recorder": ("recorder_node", "Recorder node"),
    "mpm_replay": ("replay_node", "Replay node"),
}

WIDTH = 100


def _value(spec) -> str:
    v = spec.default
    if spec.kind == "bool":
        return "true" if v else "false"
    if spec.kind == "string":
        return "'" + str(v).replace("'", "''") + "'"
    if spec.kind == "double":
        return yaml_number(float(v))
    if spec.kind == "double_array":
        return "[" + ", ".join(yaml_number(float(x)) for x in v) + "]"
    if spec.kind == "string_array":
        return "[" + ", ".join("'" + str(x).replace("'", "''") + "'" for x in v) + "]"
    return str(v)


def _comment(spec) -> str:
    text = spec.description
    if spec.low is not None and spec.kind in ("int", "double"):
        text += f" Range {spec.range_text()}."
    if spec.choices:
        text += " One of: " + ", ".join(f"'{c}'" for c in spec.choices) + "."
    if getattr(spec, "live", False):
        text += " Changeable while the node runs."
    return text + f" ({spec.kind})"


def render(node: str) -> str:
    """The text of ``config/<node>.yaml``."""
    module, title = NODES[node]
    params = importlib.import_module(f"mpm_monitor.nodes.{module}").PARAMS
    lines = [f"# {title}: every parameter with its default (ROS 2 params file).",
             f"# Use: ros2 run mpm_monitor {module} --ros-args --params-file config/{node}.yaml",
             f"#  or: python -m mpm_monitor.nodes.{module} --ros-args --params-file config/{node}.yaml",
             "# Ranges are enforced when the node starts (a value out of range is refused with its name).",
             "# Every parameter is read at start-up and read-only afterwards (the parameter services refuse a",
             "# change), except those marked 'Changeable while the node runs'.",
             "# Generated from the node's declared parameters: python -m mpm_monitor.nodes.params_files",
             f"/**/{node}:", "  ros__parameters:"]
    for spec in params:
        lines += textwrap.wrap(_comment(spec), WIDTH, initial_indent="    # ", subsequent_indent="    # ")
        if spec.default is None:  # an optional array: an empty list cannot be declared, so leave it unset
            lines.append(f"    # {spec.name}: []   # optional, unset by default")
        else:
            lines.append(f"    {spec.name}: {_value(spec)}")
    return "\n".join(lines) + "\n"


def markdown(node: str) -> str:
    """The parameters of one node as a Markdown table (for the README)."""
    module, _ = NODES[node]
    params = importlib.import_module(f"mpm_monitor.nodes.{module}").PARAMS
    lines = [f"**{node} node** (`config/{node}.yaml`)", "",
             "| parameter | default | type, range | meaning |", "| --- | --- | --- | --- |"]
    for spec in params:
        kind = spec.kind
        if spec.low is not None and spec.kind in ("int", "double"):
            kind += f", Range {spec.range_text()}"
        if spec.choices:
            kind += ", One of: " + ", ".join(f"'{c}'" for c in spec.choices)
        if getattr(spec, "live", False):
            kind += ", live"
        default = "unset" if spec.default is None else f"`{_value(spec)}`"
        lines.append(f"| `{spec.name}` | {default} | {kind} | {spec.description.replace('|', chr(92) + '|')} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mpm_monitor.nodes.params_files", description=__doc__.split("\n\n")[0])
    p.add_argument("--dir", default="config", help="folder of the params files (default config)")
    p.add_argument("--check", action="store_true", help="only report files that differ (exit 1)")
    p.add_argument("--markdown", action="store_true", help="print the README's parameter tables instead")
    args = p.parse_args(argv)
    if args.markdown:
        print("\n\n".join(markdown(node) for node in NODES))
        return 0
    stale = []
    for node in NODES:
        path = Path(args.dir) / f"{node}.yaml"
        text = render(node)
        if args.check:
            if not path.exists() or path.read_text(encoding="utf-8") != text:
                stale.append(str(path))
        else:
            path.write_text(text, encoding="utf-8")
            print(f"wrote {path}")
    if stale:
        print("out of date: " + ", ".join(stale), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
