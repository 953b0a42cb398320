"""``python -m mpm_monitor``'s exit (:func:`mpm_monitor.__main__._leave`): the exit code, the exit functions
and the standard streams are as with an ordinary exit, without the interpreter's teardown."""

import subprocess
import sys


def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)


def test_the_exit_code_the_exit_functions_and_the_buffered_output_survive():
    done = _run("import atexit, sys\n"
                "from mpm_monitor.__main__ import _leave\n"
                "atexit.register(lambda: print('exit function ran'))\n"
                "print('report ' * 20000, end='')\n"                # buffered, larger than a pipe holds
                "print('to stderr', file=sys.stderr, end='')\n"
                "_leave(3)\n"
                "print('not reached')\n")
    assert done.returncode == 3
    assert done.stdout == "report " * 20000 + "exit function ran\n"
    assert done.stderr == "to stderr"


def test_with_another_thread_running_the_ordinary_exit_waits_for_it():
    done = _run("import threading, time\n"
                "from mpm_monitor.__main__ import _leave\n"
                "threading.Thread(target=lambda: (time.sleep(0.3), print('thread finished'))).start()\n"
                "_leave(0)\n")
    assert done.returncode == 0
    assert done.stdout == "thread finished\n"
