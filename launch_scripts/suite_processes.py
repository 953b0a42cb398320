#!/usr/bin/env python3
"""The launcher ``suite_processes``, run from the repository: ``python launch_scripts/suite_processes.py ...``.

In a colcon workspace the same code is ``ros2 run mpm_monitor suite_processes ...``.  Its options:
``--help``, or :mod:`mpm_monitor.apps.launchers.suite_processes`.
"""

from mpm_monitor.apps.launchers.suite_processes import main

if __name__ == "__main__":
    raise SystemExit(main())
