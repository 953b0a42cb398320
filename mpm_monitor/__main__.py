"""``python -m mpm_monitor <command>``: see :mod:`mpm_monitor.apps.cli`."""

import sys

from . import limit_blas_threads

if __name__ == "__main__":
    limit_blas_threads()
    from .apps.cli import main

    sys.exit(main())
