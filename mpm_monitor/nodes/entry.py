"""The nodes' console scripts: a light start that ends quietly when Ctrl-C comes before the node spins.

``setup.py`` points the console scripts ``plant_node``, ``mpc_node``, ``setpoint_node``, ``monitor_node``,
``recorder_node`` and ``replay_node`` at the functions here rather than at the nodes' own ``main``.  A
node's module imports ``rclpy``, the message packages and numpy, about 0.3 s of start; a console script
that named the module itself imported all of it before any of the package's code ran, and a Ctrl-C in
that time ended the process in a ``KeyboardInterrupt`` traceback.  This module imports only the standard
library at its top; each function imports its node's module under a ``try`` and calls its ``main``, and
:func:`~mpm_monitor.nodes.ros_io.run_node` does the same until its own SIGINT and SIGTERM handlers are in
place.  Interrupted so, the process ends with exit code 130 (the shell's code of a process SIGINT ended)
and one line on stderr, ``plant_node: interrupted while starting``.

The same start without a console script (a process started from ``sys.executable``, as the
``suite_processes`` launcher starts its nodes): ``python -m mpm_monitor.nodes.entry plant_node --ros-args ...``
(:func:`main`).  ``python -m mpm_monitor.nodes.plant_node`` starts the same way: run so, the node's module is
``__main__``, and its first statement (after its docstring), before any of its imports, hands over to
:func:`run_module`, which imports the module under its own name inside the ``try`` of :func:`run_console_script`
and ends the process with its exit code; nothing else of the ``__main__`` copy runs.
"""

import importlib
import os
import sys

#: Exit code of a process a Ctrl-C (SIGINT) ended, the shell's 128 + 2.
INTERRUPTED = 130

#: The node modules of :mod:`mpm_monitor.nodes`, which are also their console scripts' names.
NODES = ("plant_node", "mpc_node", "setpoint_node", "monitor_node", "recorder_node", "replay_node")

#: How :func:`main` is called, for its error line.
USAGE = "python -m mpm_monitor.nodes.entry <node> [--ros-args ...]"


def program_name(default: str = "node") -> str:
    """The running program's name: the file name of ``sys.argv[0]`` without its suffix (``plant_node`` for
    ``lib/mpm_monitor/plant_node`` and for ``mpm_monitor/nodes/plant_node.py``), or ``default``."""
    argv0 = sys.argv[0] if sys.argv and sys.argv[0] else ""
    name = os.path.splitext(os.path.basename(argv0))[0]
    return name or default


def interrupted(name: str, when: str = "while starting") -> int:
    """Say in one line on stderr that ``name`` was interrupted (``plant_node: interrupted while starting``)
    and return :data:`INTERRUPTED`, the exit code."""
    try:
        print(f"{name}: interrupted{' ' + when if when else ''}", file=sys.stderr)
    except (OSError, ValueError):    # stderr closed or gone: the exit code says it
        pass
    return INTERRUPTED


def run_console_script(name: str, args=None) -> int:
    """Import the node module ``mpm_monitor.nodes.<name>`` and return its ``main(args)``.

    Parameters
    ----------
    name : str
        The node module's name, which is also its console script's (``plant_node``).
    args : list of str, optional
        Command-line arguments for ``main`` (default: ``sys.argv``).

    Returns
    -------
    int
        ``main``'s exit code, or :data:`INTERRUPTED` after one line on stderr when a ``KeyboardInterrupt``
        (Ctrl-C before the node's signal handlers are in place, or after it gave the previous ones back as it
        ended) ends it.
    """
    try:
        module = importlib.import_module(f"{__package__}.{name}")
    except KeyboardInterrupt:
        return interrupted(name, "while starting")
    try:
        return module.main(args)
    except KeyboardInterrupt:       # run_node handles the start itself; this is one left after it
        return interrupted(name, "")


def run_module(name: str):
    """``python -m mpm_monitor.nodes.<name>``: :func:`run_console_script`, then the end of the process.

    Each node module calls this at its very top, under ``if __name__ == "__main__":`` and before any of its
    own imports, so that ``python -m`` starts as the console script does: the node's module (rclpy, numpy) is
    imported under its own name inside a ``try``, and a Ctrl-C while it starts ends the process with
    :data:`INTERRUPTED` and one line, not a traceback.  ``sys.argv`` is left as ``python -m`` set it (the
    module's file, then the arguments), where ``main`` reads its ``--ros-args``.

    Parameters
    ----------
    name : str
        The node module's name (``plant_node``).

    Raises
    ------
    SystemExit
        Always, with the node's exit code (:func:`run_console_script`): the rest of the ``__main__`` module,
        its imports included, never runs.
    """
    sys.exit(run_console_script(name))


def plant_node(args=None) -> int:
    """Console script ``plant_node``: :func:`mpm_monitor.nodes.plant_node.main`."""
    return run_console_script("plant_node", args)


def mpc_node(args=None) -> int:
    """Console script ``mpc_node``: :func:`mpm_monitor.nodes.mpc_node.main`."""
    return run_console_script("mpc_node", args)


def setpoint_node(args=None) -> int:
    """Console script ``setpoint_node``: :func:`mpm_monitor.nodes.setpoint_node.main`."""
    return run_console_script("setpoint_node", args)


def monitor_node(args=None) -> int:
    """Console script ``monitor_node``: :func:`mpm_monitor.nodes.monitor_node.main`."""
    return run_console_script("monitor_node", args)


def recorder_node(args=None) -> int:
    """Console script ``recorder_node``: :func:`mpm_monitor.nodes.recorder_node.main`."""
    return run_console_script("recorder_node", args)


def replay_node(args=None) -> int:
    """Console script ``replay_node``: :func:`mpm_monitor.nodes.replay_node.main`."""
    return run_console_script("replay_node", args)


def main(argv=None) -> int:
    """``python -m mpm_monitor.nodes.entry <node> [--ros-args ...]``: run the node as its console script does.

    ``sys.argv`` becomes what ``python -m mpm_monitor.nodes.<node>`` gave: the node module's file, then the
    arguments after the node's name; ``rclpy`` and the node read their ``--ros-args`` there.

    Parameters
    ----------
    argv : list of str, optional
        The command line, program first (default: ``sys.argv``).

    Returns
    -------
    int
        The node's exit code (:func:`run_console_script`), or 2 with one line ``error: ...`` on stderr when no
        node or an unknown one is named.
    """
    argv = list(sys.argv if argv is None else argv)
    name = argv[1] if len(argv) > 1 else ""
    if name not in NODES:
        given = f"unknown node {name!r}" if name else "no node named"
        print(f"error: {given} (expected {USAGE}, <node> one of {', '.join(NODES)})", file=sys.stderr)
        return 2
    sys.argv = [os.path.join(os.path.dirname(os.path.abspath(__file__)), f"{name}.py")] + argv[2:]
    return run_console_script(name)


if __name__ == "__main__":
    sys.exit(main())
