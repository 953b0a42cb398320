"""``python -m mpm_monitor.nodes.<node>``: a Ctrl-C while the node starts ends it quietly, as its console script.

Run so, the node's module is ``__main__``: it used to import rclpy, the message packages and numpy (about
0.3 s) before any of the package's code could catch a ``KeyboardInterrupt``, and a Ctrl-C then ended the
process in a traceback (killed by SIGINT, exit -2).  Each node module now hands over at its very top to
:func:`mpm_monitor.nodes.entry.run_module`, which imports it under its own name inside a ``try``: exit code
130 and one line on stderr, ``<node>: interrupted while starting`` (test/test_node_entry.py for the console
scripts).

The SIGINT is a real one, sent by the node process to itself at the start of its first heavy import (numpy,
rclpy or yaml): a ``sitecustomize`` on the child's ``PYTHONPATH`` puts a finder first on ``sys.meta_path`` that
does it (no timing to race: before, this process sent it once ``-X importtime`` showed a heavy import).  The
child starts with SIGINT's default disposition, whatever this process's (an ignored one is inherited).  ``-X importtime`` still
lists what was imported before.  The node processes never reach ROS: discovery is off
(``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``).
"""

import ast
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parent.parent
NODES = ("plant_node", "mpc_node", "setpoint_node", "monitor_node", "recorder_node", "replay_node")
#: The heavy imports: the first ``-X importtime`` line of one of these says the node process is inside them.
HEAVY = ("numpy", "rclpy", "yaml")


#: The child's ``sitecustomize``: a SIGINT to itself as the first heavy import starts.
INTERRUPTER = f"""
import os, signal, sys


class _InterruptAtHeavyImport:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {HEAVY!r}:
            sys.meta_path.remove(self)
            os.kill(os.getpid(), signal.SIGINT)
        return None


sys.meta_path.insert(0, _InterruptAtHeavyImport())
"""


def _env(site_dir: Path = None) -> dict:
    from mpm_monitor.apps.launchers.common import ros_env

    env = ros_env(private=True)
    if site_dir is None:
        return env
    env["PYTHONPATH"] = os.pathsep.join([str(site_dir), str(ROOT)] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH")
                                                                       else []))
    return env


def _default_sigint() -> None:
    """In the child before it runs Python: SIGINT's default disposition."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _imported(line: str) -> str:
    """The module an ``-X importtime`` line names ('' for any other line)."""
    if not line.startswith("import time:") or "|" not in line:
        return ""
    return line.rsplit("|", 1)[1].strip()


def _interrupt_during_imports(name: str, site_dir: Path) -> tuple:
    """Run ``python -X importtime -m mpm_monitor.nodes.<name>`` with :data:`INTERRUPTER` as its ``sitecustomize``;
    its exit code, the modules imported before the signal and its stderr without the ``import time`` lines."""
    (site_dir / "sitecustomize.py").write_text(INTERRUPTER, encoding="utf-8")
    # A Ctrl-C reaches a process whose SIGINT is not ignored: an ignored disposition is inherited through exec
    # (pytest started in the background of a non-interactive shell has one), and Python then installs no handler.
    proc = subprocess.run([sys.executable, "-X", "importtime", "-m", f"mpm_monitor.nodes.{name}"], cwd=ROOT,
                          env=_env(site_dir), stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=60,
                          preexec_fn=_default_sigint)
    lines = proc.stderr.splitlines(keepends=True)
    before = [_imported(line) for line in lines if _imported(line)]
    # Interrupted at the first heavy import: only its own failed chain's lines (``rclpy``, ``rclpy.clock``) show.
    heavy = {m.split(".")[0] for m in before if m.split(".")[0] in HEAVY}
    assert len(heavy) <= 1, heavy
    return proc.returncode, before, "".join(line for line in lines if not _imported(line))


@pytest.mark.parametrize("name", NODES)
def test_a_ctrl_c_while_python_m_imports_the_node_ends_with_130_and_one_line(name, tmp_path):
    code, before, err = _interrupt_during_imports(name, tmp_path)
    assert "Traceback" not in err, err
    assert "KeyboardInterrupt" not in err, err
    assert code == 130, (code, err)
    assert err == f"{name}: interrupted while starting\n"
    assert "mpm_monitor.nodes.entry" in before          # the light start ran before the heavy imports


def test_each_node_module_hands_over_to_the_light_start_before_any_import():
    """The guard is the module's first statement after its docstring (and ``from __future__``): nothing
    else of the module runs as ``__main__``; it names its own module."""
    for name in NODES:
        tree = ast.parse((ROOT / "mpm_monitor" / "nodes" / f"{name}.py").read_text(encoding="utf-8"))
        body = [s for s in tree.body[1:]
                if not (isinstance(s, ast.ImportFrom) and s.module == "__future__")]
        guard = body[0]
        assert isinstance(guard, ast.If) and ast.unparse(guard.test) == "__name__ == '__main__'", name
        assert ast.unparse(guard.body[-1]) == f"run_module('{name}')", name
        imports = [ast.unparse(s) for s in guard.body[:-1]]
        assert imports == ["from .entry import run_module"], (name, imports)


def test_python_m_of_a_node_still_reads_its_ros_args_and_ends_with_its_own_code():
    """A normal start: the node reads the ``--ros-args`` of ``python -m`` (here a case it does not know) and ends
    with 2 and its one line, as before."""
    done = subprocess.run([sys.executable, "-m", "mpm_monitor.nodes.mpc_node", "--ros-args", "-p", "case:=9.9"],
                          cwd=ROOT, env=_env(), stdin=subprocess.DEVNULL, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 2, done.stderr
    assert done.stderr == "error: parameter case: expected one of '', '3.1', '3.2', '3.3', 'level', got '9.9'\n"

