"""Test-wide set-up: one BLAS thread (as the entry points ask), before any test module loads numpy."""

import mpm_monitor

mpm_monitor.limit_blas_threads()
