#!/usr/bin/env python3
"""The launcher ``monitor_only``, run from the repository: ``python launch_scripts/monitor_only.py ...``.

In a colcon workspace the same code is ``ros2 run mpm_monitor monitor_only ...``.  Its options:
``--help``, or :mod:`mpm_monitor.apps.launchers.monitor_only`.
"""

from mpm_monitor.apps.launchers.monitor_only import main

if __name__ == "__main__":
    raise SystemExit(main())
