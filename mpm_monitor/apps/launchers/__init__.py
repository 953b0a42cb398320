"""The plain-Python launchers (console scripts ``suite_inprocess``, ``suite_processes``, ``monitor_only``).

They start the nodes without ``launch``/``launch_ros``; ``launch_scripts/`` in the repository holds
a thin script for each.
"""
