"""Helpers shared by the plain-Python launchers (no ``launch``/``launch_ros`` needed).

The launchers live in ``launch_scripts/`` in the repository and in ``share/mpm_monitor/launch`` once
installed; the params files are in ``config/`` beside them (``share/mpm_monitor/config``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import yaml

CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
NODES = ("plant", "setpoint", "mpc", "monitor")


def case_params_file(case: str) -> Path:
    """``config/case_<case>.yaml`` (e.g. case ``3.2`` -> ``case_3_2.yaml``)."""
    return CONFIG_DIR / f"case_{case.replace('.', '_')}.yaml"


def load_params_file(path) -> dict:
    """A ROS 2 params file as ``{node_name: {parameter: value}}``.

    Keys such as ``/**/plant``, ``/ns/plant`` or ``plant`` all give ``plant``.
    """
    with open(path, encoding="utf-8") as fh:
        doc = yaml.safe_load(fh) or {}
    out = {}
    for key, body in doc.items():
        name = str(key).rstrip("/").split("/")[-1]
        params = (body or {}).get("ros__parameters", {})
        out.setdefault(name, {}).update(params)
    return out


def parse_overrides(items) -> dict:
    """``node.param:=value`` strings as ``{node: {param: value}}`` (values parsed as YAML)."""
    out = {}
    for item in items or []:
        if ":=" not in item or "." not in item.split(":=")[0]:
            raise SystemExit(f"error: -p {item!r}: expected node.parameter:=value (e.g. monitor.alpha:=0.05)")
        lhs, value = item.split(":=", 1)
        node, param = lhs.split(".", 1)
        if node not in NODES:
            raise SystemExit(f"error: -p {item!r}: node must be one of {', '.join(NODES)}")
        out.setdefault(node, {})[param] = yaml.safe_load(value)
    return out


def merge(base: dict, extra: dict) -> dict:
    """``base`` updated node by node with ``extra``."""
    out = {k: dict(v) for k, v in base.items()}
    for node, params in extra.items():
        out.setdefault(node, {}).update(params)
    return out


def ros_env(domain_id=None, localhost: bool = False, private: bool = False) -> dict:
    """The environment for node processes: ``ROS_DOMAIN_ID`` and the discovery range."""
    env = dict(os.environ)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(int(domain_id))
    if private:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
    elif localhost:
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return env


def yaml_value(v) -> str:
    """A parameter value as a ``-p name:=value`` string."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return v if v else "''"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(yaml_value(x) for x in v) + "]"
    return repr(v)


def node_command(node: str, params_file=None, namespace: str = "", params: dict = None) -> list:
    """Command line of one node process: ``python -m mpm_monitor.nodes.<node>_node --ros-args ...``."""
    cmd = [sys.executable, "-m", f"mpm_monitor.nodes.{node}_node", "--ros-args", "-r", f"__node:={node}"]
    if namespace:
        cmd += ["-r", f"__ns:={namespace if namespace.startswith('/') else '/' + namespace}"]
    if params_file:
        cmd += ["--params-file", str(params_file)]
    for k, v in (params or {}).items():
        cmd += ["-p", f"{k}:={yaml_value(v)}"]
    return cmd
