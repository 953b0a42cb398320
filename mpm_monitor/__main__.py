"""``python -m mpm_monitor <command>``: see :mod:`mpm_monitor.cli`."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
