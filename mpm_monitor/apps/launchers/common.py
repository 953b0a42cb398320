"""Helpers shared by the plain-Python launchers (no ``launch``/``launch_ros`` needed).

The launchers are console scripts: under colcon they are installed beside the nodes in
``lib/mpm_monitor/`` (``ros2 run mpm_monitor suite_inprocess --case 3.2``), under ``pip install``
in the environment's ``bin/``; in the repository ``launch_scripts/<launcher>.py`` runs the same code.
Their default params files are found by :func:`config_dir`.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import yaml

PACKAGE = "mpm_monitor"
NODES = ("plant", "setpoint", "mpc", "monitor")


def config_dir() -> Path:
    """The directory of the params files.

    Run from a source tree (the repository, or ``pip install -e``), it is the repository's
    ``config/``.  Installed (a colcon workspace, or a wheel), it is ``share/mpm_monitor/config``
    under the prefix that the ament index gives for ``mpm_monitor`` (``AMENT_PREFIX_PATH``, set by
    sourcing the install's ``setup.bash``).

    Returns
    -------
    Path
        The directory; ``SystemExit`` with one line when neither exists.
    """
    root = Path(__file__).resolve().parents[3]  # <root>/mpm_monitor/apps/launchers/common.py
    if (root / "package.xml").is_file() and (root / "config").is_dir():
        return root / "config"
    try:
        from ament_index_python.packages import get_package_share_directory

        return Path(get_package_share_directory(PACKAGE)) / "config"
    except (ImportError, LookupError):  # no ament_index_python, or PackageNotFoundError
        raise SystemExit(f"error: cannot find the params files: {PACKAGE} runs from no source tree and is not in "
                         f"the ament index (AMENT_PREFIX_PATH={os.environ.get('AMENT_PREFIX_PATH', '')!r}); "
                         "source the install's setup.bash, or give --params") from None


def case_params_file(case: str) -> Path:
    """``config/case_<case>.yaml`` (e.g. case ``3.2`` -> ``case_3_2.yaml``), see :func:`config_dir`."""
    return config_dir() / f"case_{case.replace('.', '_')}.yaml"


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
    """Command line of one node process: ``python -m mpm_monitor.nodes.entry <node>_node --ros-args ...``.

    The process starts as the node's console script does (:mod:`mpm_monitor.nodes.entry`): a Ctrl-C while it
    imports the node (rclpy, numpy) ends it with exit code 130 and one line, not a traceback.

    Parameters
    ----------
    node : str
        One of :data:`NODES` (``plant``).
    params_file : path, optional
        Its ``--params-file``.
    namespace : str
        Its namespace (``__ns``), with or without the leading ``/``; "" = none.
    params : dict, optional
        ``-p name:=value`` overrides.

    Returns
    -------
    list of str
        The command, for :class:`subprocess.Popen`.
    """
    cmd = [sys.executable, "-m", "mpm_monitor.nodes.entry", f"{node}_node", "--ros-args", "-r", f"__node:={node}"]
    if namespace:
        cmd += ["-r", f"__ns:={namespace if namespace.startswith('/') else '/' + namespace}"]
    if params_file:
        cmd += ["--params-file", str(params_file)]
    for k, v in (params or {}).items():
        cmd += ["-p", f"{k}:={yaml_value(v)}"]
    return cmd
