"""For multi-process tests: a ROS_DOMAIN_ID no other test process on this machine holds, a context
of the test process on it, and the tear-down of node processes and of the test's own listener."""

import contextlib
import fcntl
import os
import random
import signal
import subprocess
import tempfile
from pathlib import Path

import pytest


@contextlib.contextmanager
def unique_domain(salt: int = 0):
    """Yield a ROS_DOMAIN_ID in 1..101 locked (``flock`` on ``<tmp>/mpm_monitor_domain_<id>.lock``)
    against other test processes; skip the test when every id is taken."""
    ids = list(range(1, 102))
    random.Random(os.getpid() + salt).shuffle(ids)
    for d in ids:
        fh = open(Path(tempfile.gettempdir()) / f"mpm_monitor_domain_{d}.lock", "w")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        try:
            yield d
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)
            fh.close()
        return
    pytest.skip("no free ROS_DOMAIN_ID")


def domain_context(domain_id):
    """A context on ``domain_id`` with discovery limited to this host (as the node processes)."""
    import rclpy
    from rclpy.context import Context

    from mpm_monitor.apps.demo import _env

    ctx = Context()
    with _env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(domain_id)}):
        rclpy.init(args=[], context=ctx, domain_id=domain_id)
    return ctx


def stop_process(proc, timeout: float = 10.0) -> None:
    """Stop a node or launcher process as Ctrl-C would (SIGINT); SIGKILL it after ``timeout`` seconds."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def close_listener(executor, node, context) -> None:
    """Tear down the test's own node, its executor and its context."""
    executor.remove_node(node)
    node.destroy_node()
    executor.shutdown()
    context.try_shutdown()
