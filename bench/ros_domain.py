"""A ROS_DOMAIN_ID of one's own on this machine, for runs of node processes beside other runs.

:func:`held_domain` takes an id in 1..101 that no other process holds: an exclusive ``flock`` on
``<tmp>/mpm_monitor_domain_<id>.lock`` for as long as the ``with`` block runs (the multi-process
tests take the same locks, through ``test/ros_domains.py``).  :func:`domain_context` is an rclpy
context of this process on that domain with discovery limited to this host, as the node processes
are started (``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST``).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import random
import tempfile
from pathlib import Path


class NoFreeDomain(RuntimeError):
    """Every ROS_DOMAIN_ID in 1..101 is held by another process."""


@contextlib.contextmanager
def held_domain(salt: int = 0):
    """Yield a ROS_DOMAIN_ID in 1..101 locked against other processes (see the module docstring)."""
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
    raise NoFreeDomain("no free ROS_DOMAIN_ID in 1..101")


def domain_env(domain_id: int) -> dict:
    """The environment variables of a node process on ``domain_id``, discovery on this host only."""
    return {"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(domain_id)}


def domain_context(domain_id: int):
    """An initialised rclpy context of this process on ``domain_id`` (see :func:`domain_env`)."""
    import rclpy
    from rclpy.context import Context

    from mpm_monitor.apps.demo import _env

    ctx = Context()
    with _env(domain_env(domain_id)):
        rclpy.init(args=[], context=ctx, domain_id=domain_id)
    return ctx


def stop_process(proc, timeout: float = 10.0) -> None:
    """Stop a node or launcher process as Ctrl-C would (SIGINT); SIGKILL it after ``timeout`` seconds."""
    import signal
    import subprocess

    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def close_nodes(executor, context, *nodes) -> None:
    """Tear down nodes of this process (each removed from ``executor``, then destroyed), then the
    executor and the context."""
    for node in nodes:
        executor.remove_node(node)
        node.destroy_node()
    executor.shutdown()
    context.try_shutdown()


def close_listener(executor, node, context) -> None:
    """Tear down a node of this process, its executor and its context."""
    close_nodes(executor, context, node)
