"""Test-wide set-up: one BLAS thread (as the entry points ask), before any test module loads numpy."""

import mpm_monitor

mpm_monitor.limit_blas_threads()


def pytest_configure(config):
    """lark (pinned by the ROS message packages) imports the standard library's deprecated ``sre_parse`` and
    ``sre_constants``: its two DeprecationWarnings are not this package's, and are left out of the summary."""
    for module in ("sre_parse", "sre_constants"):
        config.addinivalue_line("filterwarnings", f"ignore:module '{module}' is deprecated:DeprecationWarning")
