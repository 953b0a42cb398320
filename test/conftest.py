"""Test-wide set-up: one BLAS thread (as the entry points ask), before any test module loads numpy; and
which modules run in the serial pass of ``make test``."""

from pathlib import Path

import pytest

import mpm_monitor

mpm_monitor.limit_blas_threads()

# ``make test`` runs the suite in two passes: the computational modules spread over the machine's
# cores (pytest-xdist, one module per worker at a time), then, one at a time, every module that runs
# ROS nodes, ROS contexts or node processes, or forks: those wait on timers, discovery and other
# processes, and forking a worker that holds threads is not safe.  A module is serial when its text
# names one of these.
SERIAL_WORDS = ("rclpy", "ros_domains", "mpm_monitor.nodes", "launchers", "multiprocessing", "fork")


def pytest_configure(config):
    """lark (pinned by the ROS message packages) imports the standard library's deprecated ``sre_parse`` and
    ``sre_constants``: its two DeprecationWarnings are not this package's, and are left out of the summary."""
    for module in ("sre_parse", "sre_constants"):
        config.addinivalue_line("filterwarnings", f"ignore:module '{module}' is deprecated:DeprecationWarning")
    config.addinivalue_line("markers", "serial: runs in make test's serial pass (ROS, node processes, forks)")


def _is_serial(path: Path, cache: dict) -> bool:
    if path not in cache:
        text = path.read_text(encoding="utf-8")
        cache[path] = any(word in text for word in SERIAL_WORDS)
    return cache[path]


def pytest_collection_modifyitems(config, items):
    """Mark the items of serial modules (see :data:`SERIAL_WORDS`)."""
    cache: dict = {}
    for item in items:
        if _is_serial(Path(str(item.path)), cache):
            item.add_marker(pytest.mark.serial)
