"""For multi-process tests: a ROS_DOMAIN_ID no other test process on this machine holds, a context
of the test process on it, and the tear-down of node processes and of the test's own listener
(the helpers of :mod:`bench.ros_domain`, which the endurance benchmark uses too)."""

import contextlib

import pytest

from bench.ros_domain import NoFreeDomain, close_listener, close_nodes, domain_context, held_domain, stop_process

__all__ = ["close_listener", "close_nodes", "domain_context", "stop_process", "unique_domain"]


@contextlib.contextmanager
def unique_domain(salt: int = 0):
    """Yield a ROS_DOMAIN_ID in 1..101 locked (``flock`` on ``<tmp>/mpm_monitor_domain_<id>.lock``)
    against other test processes; skip the test when every id is taken."""
    try:
        with held_domain(salt) as d:
            yield d
    except NoFreeDomain:
        pytest.skip("no free ROS_DOMAIN_ID")
