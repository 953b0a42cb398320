#!/usr/bin/env python3
"""The launcher ``suite_inprocess``, run from the repository: ``python launch_scripts/suite_inprocess.py ...``.

In a colcon workspace the same code is ``ros2 run mpm_monitor suite_inprocess ...``.  Its options:
``--help``, or :mod:`mpm_monitor.apps.launchers.suite_inprocess`.
"""

from mpm_monitor.apps.launchers.suite_inprocess import main

if __name__ == "__main__":
    raise SystemExit(main())
