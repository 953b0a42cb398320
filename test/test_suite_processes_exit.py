"""The exit code of the ``suite_processes`` launcher: 130 after SIGINT, 143 after SIGTERM, whatever its nodes end with.

A Ctrl-C in a terminal reaches the launcher's whole process group, so its nodes stop by the same signal and end as
they can (0, 130 while they start, killed); the launcher ended with 0, 1 or 254 depending on which of them it saw
end first.  In process, the node processes are fakes and the Ctrl-C is raised in the launcher's first wait; one
test runs the real launcher and nodes in a process group of their own.
"""

import os
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import pytest

from mpm_monitor.apps.launchers import suite_processes
from mpm_monitor.apps.launchers.suite_processes import exit_code

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize("failed, signum, code", [
    ([], None, 0),
    ([], signal.SIGINT, 130),
    ([], signal.SIGTERM, 143),
    ([("mpc", 1)], None, 1),
    ([("monitor", 0)], None, 1),                     # a node that is not the plant should not end
    ([("mpc", -signal.SIGKILL)], None, 137),         # killed: 128 + 9, not 256 - 9
    ([("plant", 1), ("mpc", 2)], signal.SIGINT, 1),  # the first failure, also when a Ctrl-C followed it
])
def test_exit_code(failed, signum, code):
    assert exit_code(failed, signum) == code


class FakeNode:
    """A node process that ends with ``code`` once the signal reached the group (``group["signalled"]``), or at
    once when ``on_its_own``; it ends with 0 at the launcher's SIGINT."""

    def __init__(self, code, group, on_its_own=False):
        self.code, self.group, self.on_its_own = code, group, on_its_own
        self.returncode = None
        self.signals = []

    def poll(self):
        if self.returncode is None and (self.on_its_own or self.group["signalled"]):
            self.returncode = self.code
        return self.returncode

    def send_signal(self, sig):
        self.signals.append(sig)
        self.returncode = 0 if self.returncode is None else self.returncode

    def wait(self, timeout=None):
        return self.poll()

    def kill(self):
        self.returncode = -signal.SIGKILL


def run_launcher(monkeypatch, codes, signum=None, on_its_own=()):
    """``suite_processes.main`` with fake node processes (``codes``: node name -> its code at the signal); the
    launcher's first wait raises ``signum`` (None: no signal).  Returns the exit code, the fakes and whether the
    SIGINT and SIGTERM handlers are the ones from before."""
    group = {"signalled": False}
    fakes = {}

    def popen(cmd, env=None):
        name = cmd[3].removesuffix("_node")
        fakes[name] = FakeNode(codes[name], group, name in on_its_own)
        return fakes[name]

    def sleep(seconds):
        if signum is not None and not group["signalled"]:
            group["signalled"] = True
            signal.raise_signal(signum)    # the launcher's handler runs here, as within time.sleep

    monkeypatch.setattr(suite_processes.subprocess, "Popen", popen)
    monkeypatch.setattr(suite_processes.time, "sleep", sleep)
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    try:
        code = suite_processes.main(["--case", "3.2", "--linger", "0"])
    finally:
        restored = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
        signal.signal(signal.SIGINT, before[0])
        signal.signal(signal.SIGTERM, before[1])
    return code, fakes, restored


@pytest.mark.parametrize("signum, expected", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
@pytest.mark.parametrize("codes", [
    {"plant": 0, "setpoint": 0, "mpc": 0, "monitor": 0},                       # all stopped in order
    {"plant": 130, "setpoint": 130, "mpc": 130, "monitor": 130},               # all interrupted while starting
    {"plant": -signal.SIGABRT, "setpoint": 0, "mpc": 130, "monitor": 0},       # one aborted
], ids=["orderly", "starting", "aborted"])
def test_a_signal_to_the_group_ends_the_launcher_with_128_plus_its_number(monkeypatch, capsys, codes, signum,
                                                                          expected):
    code, _, restored = run_launcher(monkeypatch, codes, signum)
    assert code == expected
    assert "exited with" not in capsys.readouterr().err
    assert restored     # main gives the caller its handlers back


def test_a_node_that_ends_on_its_own_is_reported_and_stops_the_suite(monkeypatch, capsys):
    codes = {"plant": 0, "setpoint": 0, "mpc": 1, "monitor": 0}
    code, fakes, _ = run_launcher(monkeypatch, codes, on_its_own={"mpc"})
    assert code == 1
    assert capsys.readouterr().err == "suite: mpc exited with 1\n"
    assert [name for name, fake in fakes.items() if fake.signals] == ["plant", "setpoint", "monitor"]


def test_a_plant_that_fails_on_its_own_is_reported_and_its_code_kept(monkeypatch, capsys):
    codes = {"plant": 1, "setpoint": 0, "mpc": 0, "monitor": 0}
    code, _, _ = run_launcher(monkeypatch, codes, on_its_own={"plant"})
    assert code == 1
    assert capsys.readouterr().err == "suite: plant exited with 1\n"


def test_a_plant_done_with_0_and_the_linger_over_ends_the_launcher_with_0(monkeypatch, capsys):
    codes = {"plant": 0, "setpoint": 0, "mpc": 0, "monitor": 0}
    assert run_launcher(monkeypatch, codes, on_its_own={"plant"})[0] == 0
    assert capsys.readouterr().err == ""


# ------------------------------------------------------------------ the real launcher and nodes
def test_a_ctrl_c_to_the_running_suite_ends_the_launcher_with_130():
    """Ctrl-C as a terminal sends it: SIGINT to the launcher's process group, once its four nodes have started
    (their first log lines, written after their signal handlers are in place)."""
    pytest.importorskip("rclpy")
    from ros_domains import unique_domain

    with unique_domain(3) as domain:
        cmd = [sys.executable, str(ROOT / "launch_scripts" / "suite_processes.py"), "--case", "3.2", "--domain-id",
               str(domain), "--localhost", "--namespace", f"/ctrlc{os.getpid()}"]
        env = dict(os.environ, PYTHONUNBUFFERED="1", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        env.pop("ROS_LOCALHOST_ONLY", None)
        log = tempfile.TemporaryFile()
        launcher = subprocess.Popen(cmd, env=env, cwd=str(ROOT), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    start_new_session=True)
        started = set()
        up = threading.Event()

        def read():
            for line in launcher.stdout:
                log.write(line)
                text = line.decode(errors="replace")
                started.update(n for n in ("plant", "setpoint", "mpc", "monitor") if f".{n}]: " in text)
                if len(started) == 4:
                    up.set()

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        try:
            assert up.wait(120.0), f"the nodes did not start (started: {sorted(started)})"
            os.killpg(launcher.pid, signal.SIGINT)
            code = launcher.wait(60.0)
        finally:
            if launcher.poll() is None:
                os.killpg(launcher.pid, signal.SIGKILL)
                launcher.wait()
            reader.join(10.0)
        log.seek(0)
        out = log.read().decode(errors="replace")
        log.close()
        assert code == 130, out[-3000:]
        assert "exited with" not in out, out[-3000:]
