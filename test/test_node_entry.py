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
    """After the node's handlers are restored (a second Ctrl-C while the node closes): no traceback either."""
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
