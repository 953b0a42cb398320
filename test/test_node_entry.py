"""A Ctrl-C while a node starts ends it quietly: exit code 130 and one line on stderr, no traceback.

The console scripts of ``setup.py`` (what ``ros2 run`` and ``.venv/bin`` run) start in the light module
:mod:`mpm_monitor.nodes.entry`, which imports the node's module (rclpy, numpy: about 0.3 s) under a
``try``; :func:`~mpm_monitor.nodes.ros_io.run_node` catches a ``KeyboardInterrupt`` until its own signal
handlers are in place.  The Ctrl-C is simulated in process, without signals or timing: the import of the
node's module, the params-file check or ``rclpy.init`` raises ``KeyboardInterrupt``.
"""

import ast
import importlib
import importlib.abc
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NODES = ("plant_node", "mpc_node", "setpoint_node", "monitor_node", "recorder_node", "replay_node")
EXECUTABLES = NODES + ("suite_inprocess", "suite_processes", "monitor_only", "mpm_analyze")
#: What the script file stands for in ``sys.argv[0]`` (``ros2 run`` starts ``lib/mpm_monitor/<name>``).
SCRIPT_DIR = "/ws/install/mpm_monitor/lib/mpm_monitor"


def console_scripts() -> dict:
    """``{script name: "module:function"}`` of setup.py's ``console_scripts``."""
    tree = ast.parse((ROOT / "setup.py").read_text(encoding="utf-8"))
    points = next(kw.value for node in ast.walk(tree) if isinstance(node, ast.Call)
                  for kw in node.keywords if kw.arg == "entry_points")
    lines = ast.literal_eval(points)["console_scripts"]
    return {name.strip(): target.strip() for name, _, target in (line.partition("=") for line in lines)}


def run_console_script(target: str):
    """What the script setuptools writes does: ``from <module> import <function>``, then ``<function>()``;
    a ``KeyboardInterrupt`` that gets out of it is what would have printed a traceback."""
    module, _, function = target.partition(":")
    try:
        return getattr(importlib.import_module(module), function)()
    except KeyboardInterrupt:
        pytest.fail(f"{target}: KeyboardInterrupt got out (the process would end in a traceback)")


class CtrlCOnImport(importlib.abc.MetaPathFinder):
    """An import finder that raises ``KeyboardInterrupt`` when ``name`` is imported (a Ctrl-C during it)."""

    def __init__(self, name: str):
        self.name = name
        self.hits = 0

    def find_spec(self, fullname, path=None, target=None):
        if fullname == self.name:
            self.hits += 1
            raise KeyboardInterrupt
        return None


def test_every_console_script_resolves_to_a_callable():
    scripts = console_scripts()
    assert sorted(scripts) == sorted(EXECUTABLES)
    for name, target in scripts.items():
        module, _, function = target.partition(":")
        assert callable(getattr(importlib.import_module(module), function)), (name, target)


def test_the_node_console_scripts_import_neither_rclpy_nor_numpy_before_they_run():
    """What a node's script imports before its function runs is the standard library: no Ctrl-C lands
    in rclpy's or numpy's import with nothing to catch it."""
    targets = [console_scripts()[n] for n in NODES]
    code = ("import importlib, sys\n"
            "for t in sys.argv[1:]:\n"
            "    m, _, f = t.partition(':')\n"
            "    assert callable(getattr(importlib.import_module(m), f)), t\n"
            "print(sorted(n for n in ('rclpy', 'numpy', 'yaml') if n in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", code, *targets], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "[]\n", (targets, done.stdout)


@pytest.mark.parametrize("name", NODES)
def test_a_ctrl_c_while_the_node_module_imports_ends_with_130_and_one_line(name, monkeypatch, capsys):
    module = f"mpm_monitor.nodes.{name}"
    finder = CtrlCOnImport(module)
    monkeypatch.delitem(sys.modules, module, raising=False)
    monkeypatch.setattr(sys, "meta_path", [finder] + sys.meta_path)
    monkeypatch.setattr(sys, "argv", [f"{SCRIPT_DIR}/{name}"])
    code = run_console_script(console_scripts()[name])
    err = capsys.readouterr().err
    assert finder.hits == 1
    assert code == 130
    assert err == f"{name}: interrupted while starting\n"


def _refuse_factory(**kwargs):
    raise AssertionError("the node was built after a Ctrl-C")


def test_a_ctrl_c_in_run_node_before_rclpy_init_ends_with_130_and_one_line(monkeypatch, capsys):
    from mpm_monitor.nodes import ros_io

    def interrupted_check(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(ros_io, "params_file_problem", interrupted_check)
    monkeypatch.setattr(sys, "argv", [f"{SCRIPT_DIR}/plant_node"])
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        code = ros_io.run_node(_refuse_factory, ["plant_node"])
    except KeyboardInterrupt:
        pytest.fail("run_node let the KeyboardInterrupt out (the process would end in a traceback)")
    assert code == 130
    assert capsys.readouterr().err == "plant_node: interrupted while starting\n"
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_a_ctrl_c_during_rclpy_init_shuts_the_context_down_and_ends_with_130(monkeypatch, capsys):
    pytest.importorskip("rclpy")
    import rclpy

    from mpm_monitor.nodes import ros_io

    contexts = []
    real_init = rclpy.init

    def init_then_ctrl_c(**kwargs):
        real_init(**kwargs)                 # the Ctrl-C lands as rcl's init returns
        contexts.append(kwargs["context"])
        raise KeyboardInterrupt

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")
    monkeypatch.setattr(rclpy, "init", init_then_ctrl_c)
    monkeypatch.setattr(sys, "argv", [f"{SCRIPT_DIR}/monitor_node"])
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        code = ros_io.run_node(_refuse_factory, ["monitor_node"])
    except KeyboardInterrupt:
        pytest.fail("run_node let the KeyboardInterrupt out (the process would end in a traceback)")
    finally:
        for ctx in contexts:
            ctx.try_shutdown()
    assert code == 130
    assert capsys.readouterr().err == "monitor_node: interrupted while starting\n"
    assert len(contexts) == 1 and not contexts[0].ok()
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_a_ctrl_c_that_gets_out_of_main_still_ends_with_130_and_one_line(monkeypatch, capsys):
    """After the node's handlers are given back (at its very end, once its context is shut down): no traceback
    either."""
    pytest.importorskip("rclpy")
    from mpm_monitor.nodes import entry, plant_node

    def interrupted_main(args=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(plant_node, "main", interrupted_main)
    try:
        code = entry.plant_node()
    except KeyboardInterrupt:
        pytest.fail("entry.plant_node let the KeyboardInterrupt out")
    assert code == 130
    assert capsys.readouterr().err == "plant_node: interrupted\n"


# ------------------------------------------------------------------ python -m mpm_monitor.nodes.entry <node>
def test_the_launchers_start_their_node_processes_through_the_entry_module(tmp_path):
    """``suite_processes``'s node processes start as the console scripts do (``python -m mpm_monitor.nodes.entry
    <node>``), not as ``python -m mpm_monitor.nodes.<node>``, which imports the node before any of its code runs;
    the ``--ros-args`` part is the same."""
    from mpm_monitor.apps.launchers.common import NODES as LAUNCHED, node_command

    f = tmp_path / "plant.yaml"
    for node in LAUNCHED:
        cmd = node_command(node, f, "unit1", {"seed": 3})
        assert cmd[:4] == [sys.executable, "-m", "mpm_monitor.nodes.entry", f"{node}_node"], cmd
        assert f"mpm_monitor.nodes.{node}_node" not in cmd
        assert cmd[4:] == ["--ros-args", "-r", f"__node:={node}", "-r", "__ns:=/unit1", "--params-file", str(f),
                           "-p", "seed:=3"]


@pytest.mark.parametrize("name", NODES)
def test_the_entry_module_runs_the_named_node_with_its_ros_args_as_before(name, monkeypatch):
    """``python -m mpm_monitor.nodes.entry <node> --ros-args ...``: the node's ``main`` sees the ``sys.argv`` that
    ``python -m mpm_monitor.nodes.<node> --ros-args ...`` gave it (the module's file, then the ROS arguments)."""
    from mpm_monitor.nodes import entry

    module = importlib.import_module(f"mpm_monitor.nodes.{name}")
    seen = []

    def fake_main(args=None):
        seen.append((args, list(sys.argv), entry.program_name()))
        return 7

    monkeypatch.setattr(module, "main", fake_main)
    monkeypatch.setattr(sys, "argv", ["/nowhere/entry.py"])
    ros_args = ["--ros-args", "-r", "__node:=x", "--params-file", "/tmp/p.yaml", "-p", "a:=1"]
    assert entry.main([str(ROOT / "mpm_monitor" / "nodes" / "entry.py"), name, *ros_args]) == 7
    assert seen == [(None, [module.__file__, *ros_args], name)]


@pytest.mark.parametrize("argv, said", [
    (["entry.py", "plant"], "unknown node 'plant'"),
    (["entry.py", "--ros-args"], "unknown node '--ros-args'"),
    (["entry.py"], "no node named"),
])
def test_the_entry_module_refuses_an_unknown_node_with_2_and_one_line(argv, said, monkeypatch, capsys):
    from mpm_monitor.nodes import entry

    monkeypatch.setattr(sys, "argv", list(argv))
    assert entry.main() == 2
    assert sys.argv == argv
    assert capsys.readouterr().err == (
        f"error: {said} (expected python -m mpm_monitor.nodes.entry <node> [--ros-args ...], <node> one of "
        f"{', '.join(NODES)})\n")


def test_a_ctrl_c_while_the_entry_module_imports_the_node_ends_with_130_and_one_line(monkeypatch, capsys):
    from mpm_monitor.nodes import entry

    module = "mpm_monitor.nodes.mpc_node"
    finder = CtrlCOnImport(module)
    monkeypatch.delitem(sys.modules, module, raising=False)
    monkeypatch.setattr(sys, "meta_path", [finder] + sys.meta_path)
    monkeypatch.setattr(sys, "argv", ["entry.py"])
    try:
        code = entry.main(["entry.py", "mpc_node", "--ros-args"])
    except KeyboardInterrupt:
        pytest.fail("entry.main let the KeyboardInterrupt out (the process would end in a traceback)")
    assert finder.hits == 1 and code == 130
    assert capsys.readouterr().err == "mpc_node: interrupted while starting\n"


def test_the_entry_module_imports_neither_rclpy_nor_numpy_before_it_picks_the_node():
    """What ``python -m mpm_monitor.nodes.entry`` imports before the node's own import (under its ``try``): the
    standard library (``-X importtime`` lists every import; an unknown node ends before any node import)."""
    done = subprocess.run([sys.executable, "-X", "importtime", "-m", "mpm_monitor.nodes.entry", "no_such_node"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    imported = {line.rsplit("|", 1)[1].strip().split(".")[0] for line in done.stderr.splitlines()
                if line.startswith("import time:") and "|" in line}
    assert "mpm_monitor" in imported                     # the listing is there
    assert not imported & {"rclpy", "numpy", "yaml"}, sorted(imported & {"rclpy", "numpy", "yaml"})
    assert done.stderr.splitlines()[-1].startswith("error: unknown node 'no_such_node'")


def test_a_node_process_of_the_launchers_starts_and_refuses_a_bad_parameter_in_one_line(tmp_path):
    """The command :func:`~mpm_monitor.apps.launchers.common.node_command` builds runs the node for real: the
    node reads its ``--ros-args`` (here a case it does not know) and ends with 2 and its one line."""
    from mpm_monitor.apps.launchers.common import node_command, ros_env

    cmd = node_command("mpc", params={"case": "9.9"})
    done = subprocess.run(cmd, cwd=tmp_path, env=ros_env(private=True), capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr == "error: parameter case: expected one of '', '3.1', '3.2', '3.3', 'level', got '9.9'\n"
