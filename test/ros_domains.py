"""A ROS_DOMAIN_ID no other test process on this machine holds (for multi-process tests), and a
context of the test process on it."""

import contextlib
import fcntl
import os
import random
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
