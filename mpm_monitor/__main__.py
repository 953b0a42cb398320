"""``python -m mpm_monitor <command>``: see :mod:`mpm_monitor.apps.cli`."""

import sys

from . import limit_blas_threads


def _leave(code: int) -> None:
    """Exit with ``code`` without tearing the interpreter down, when that loses nothing.

    A command has written and closed its files when :func:`~mpm_monitor.apps.cli.main` returns; what
    an ordinary exit adds is the exit functions (run here), the flush of the standard streams (done
    here) and the release of every module and object, which takes about 0.05 s after an analysis and
    is skipped.  With another thread still running, or a stream that cannot be flushed (a closed
    pipe), the ordinary exit runs instead, with its usual messages.
    """
    import atexit
    import os
    import threading

    if threading.active_count() == 1:
        atexit._run_exitfuncs()
        try:
            for stream in (sys.stdout, sys.stderr):     # None: started with the stream closed (>&-)
                if stream is not None:
                    stream.flush()
        except (OSError, ValueError):
            pass
        else:
            os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    limit_blas_threads()
    from .apps.cli import main

    code = main()
    _leave(0 if code is None else int(code))
