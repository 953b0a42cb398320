"""The analysis of the live monitor's window, away from the subscription callbacks.

An :class:`AnalysisJob` is a copy of the window's data; :func:`run_analysis` turns it into an
:class:`AnalysisOutcome` (a report or a one-line error, never an exception).  :class:`AnalysisWorker`
runs the jobs one at a time in a background thread, so that no callback waits for an analysis, and
:class:`ProcessAnalyzer` moves the analysis itself into a child process, so that it does not even
compete with the callbacks for the Python interpreter.
:class:`~mpm_monitor.monitor.monitor_core.MonitorCore` makes the jobs and takes the outcomes.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import signal
import threading
import time
import traceback
from typing import Any, Callable, Optional

from ..core.errors import DataFileError, TooFewSamples
from ..core.logged_data import NUMERICAL_ERRORS, check_scale
from ..core.model import PlantModel
from ..core.parallel import fork_safe


@dataclasses.dataclass(frozen=True)
class AnalysisJob:
    """One analysis to run: the window's data and where it lies in the stream."""

    seq: int
    data: Any               # LoggedData
    first_stamp: float      # seconds
    last_stamp: float       # seconds
    completed: int          # samples completed in the stream when the job was taken
    candidates: Any = None  # "all": test the data's extra channels as candidates (None: none)
    keep: bool = False      # never replaced by a later job while it waits (the analysis of an experiment)


@dataclasses.dataclass(frozen=True)
class AnalysisOutcome:
    """The result of an :class:`AnalysisJob`: a report, an error message, or why the window is still too short
    for the tests (``too_few``: it holds fewer samples, or fewer regression rows between its gaps, than they need;
    not an error: the monitor waits for more)."""

    job: AnalysisJob
    report: Any = None
    error: Optional[str] = None
    seconds: float = 0.0
    too_few: Optional[str] = None


def run_analysis(analyze: Callable, model: PlantModel, options, job: AnalysisJob,
                 clock: Callable[[], float] = time.perf_counter) -> AnalysisOutcome:
    """Run ``analyze(model, job.data, options)`` (with ``candidates=job.candidates`` when the job has
    candidates) and wrap its report or its error."""
    t0 = clock()
    try:
        check_scale(model, job.data)  # a sentinel like 1e308 would give a silent all-clear
        if job.candidates is None:
            report = analyze(model, job.data, options)
        else:
            report = analyze(model, job.data, options, candidates=job.candidates)
    except TooFewSamples as exc:   # a window the tests cannot use yet (gaps cost it rows): waited on, not an error
        return AnalysisOutcome(job, too_few=str(exc).splitlines()[0], seconds=clock() - t0)
    except Exception as exc:  # the monitor reports any failure as ERROR and keeps running
        if isinstance(exc, DataFileError) and isinstance(exc.__cause__, NUMERICAL_ERRORS):  # numerical_breakdown
            exc = exc.__cause__  # reported as before: 'LinAlgError: ...'
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return AnalysisOutcome(job, error=f"analysis failed: {type(exc).__name__}: {msg}", seconds=clock() - t0)
    return AnalysisOutcome(job, report=report, seconds=clock() - t0)


class AnalysisWorker:
    """Runs analysis jobs one at a time in a background thread.

    Parameters
    ----------
    run : callable
        ``run(job) -> AnalysisOutcome``.
    on_done : callable, optional
        Called (in the worker thread) after each outcome is queued, e.g. to wake an executor.
    threaded : bool
        False runs each job inside :meth:`submit` (for deterministic unit tests).

    Notes
    -----
    At most one job waits: a job submitted while another waits replaces it (the newer window
    contains the newer samples), so a slow analysis never builds a backlog.  The one exception is a
    job with ``keep`` (the window that holds a whole experiment, which a later window no longer
    holds): it waits until it runs, and the newest other job waits behind it.  Outcomes are taken
    with :meth:`take_outcomes` in the thread that publishes.
    """

    def __init__(self, run: Callable[[AnalysisJob], AnalysisOutcome], on_done: Optional[Callable[[], None]] = None,
                 threaded: bool = True):
        self._run = run
        self._on_done = on_done
        self._threaded = threaded
        self._lock = threading.Condition()
        self._waiting: collections.deque = collections.deque()   # oldest first; at most one without keep
        self._busy = False
        self._closed = False
        self._outcomes: collections.deque = collections.deque()
        self.replaced = 0
        self._thread = None
        if threaded:
            self._thread = threading.Thread(target=self._loop, name="mpm_monitor analysis", daemon=True)
            self._thread.start()

    def submit(self, job: AnalysisJob) -> None:
        """Queue ``job`` (replacing a job that is still waiting, unless that one has ``keep``)."""
        if not self._threaded:
            self._outcomes.append(self._run(job))
            if self._on_done:
                self._on_done()
            return
        with self._lock:
            kept = [j for j in self._waiting if j.keep]
            self.replaced += len(self._waiting) - len(kept)
            self._waiting = collections.deque(kept + [job])
            self._lock.notify()

    @property
    def idle(self) -> bool:
        """True when no job runs or waits."""
        with self._lock:
            return not self._waiting and not self._busy

    def take_outcomes(self) -> list:
        """Outcomes finished since the last call, oldest first."""
        out = []
        while self._outcomes:
            out.append(self._outcomes.popleft())
        return out

    def _loop(self) -> None:
        while True:
            with self._lock:
                while not self._waiting and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                job = self._waiting.popleft()
                self._busy = True
            try:
                outcome = self._run(job)
            except BaseException:  # run() wraps analysis errors; a last resort (a KeyboardInterrupt too): the
                # thread never dies, or no later window would be analysed
                outcome = AnalysisOutcome(job, error="analysis failed: " + traceback.format_exc().splitlines()[-1])
            self._outcomes.append(outcome)
            with self._lock:
                self._busy = False
            if self._on_done:
                try:
                    self._on_done()
                except Exception:
                    pass

    def close(self, timeout: float = 5.0) -> None:
        """Stop the thread (a running analysis finishes first, up to ``timeout`` seconds)."""
        if self._thread is None:
            return
        with self._lock:
            self._closed = True
            self._lock.notify()
        self._thread.join(timeout)


def _start_analysis_process(parent_pid: int, niceness: int) -> None:
    """The analysis process's set-up: SIGINT ignored, its niceness raised by ``niceness``
    (:class:`ProcessAnalyzer`), and :func:`_exit_with_parent`.

    A terminal's Ctrl-C goes to its whole process group, the analysis process with it: the monitor's
    own process stops it (its pool shut down), so an interrupt of the child would only print its
    traceback and, in the middle of an analysis, end that analysis with ``KeyboardInterrupt``.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if niceness > 0 and hasattr(os, "nice"):      # raising it needs no privilege (lowering would)
        os.nice(niceness)
    _exit_with_parent(parent_pid)


def _exit_with_parent(parent_pid: int, period: float = 0.5) -> None:
    """In the analysis process: leave as soon as the monitor's process is gone (a pool worker
    otherwise outlives a parent killed by SIGKILL, waiting forever for work)."""

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(period)
        os._exit(0)

    # It only sleeps and polls: the analysis may still fork its second process (AnalysisOptions.jobs).
    fork_safe(threading.Thread(target=watch, name="exit with parent", daemon=True)).start()


class ProcessAnalyzer:
    """``analyze(model, data, options)`` run in one child process instead of the calling thread.

    A thread of the monitor's own process shares the Python interpreter lock with the subscription
    callbacks: under load (measured: 3x3 at 1 kHz on two busy cores) the callbacks then fall more
    than the topics' queue depth behind and samples are lost.  In a child process the analysis
    only costs the callbacks the pickling of the window.  The child is started (``spawn``, never
    ``fork`` in a process with DDS threads) at the first call and reused; if it dies, the call
    raises (the monitor reports ERROR) and the next call starts a new one.  The child leaves by
    itself within a second when the monitor's process dies, even by SIGKILL.

    Parameters
    ----------
    analyze : callable
        A picklable (module-level) function, e.g. :func:`mpm_monitor.core.pipeline.analyze`.
    niceness : int
        Added to the child's niceness (``os.nice``, 0 to 19; 0: the monitor's own priority).  Where the
        cores are busy, the scheduler then serves the monitor's callbacks, and the other processes on
        the machine such as the controller, before the analysis, which is only delayed (a later window
        replaces a job that waits: :class:`AnalysisWorker`).  Measured with ``bench.endurance`` (3x3 at
        1.5 kHz, beyond what the two cores of a slow machine hold, the publisher on the same machine;
        200,000 samples, two runs each, in turn): 20,133 and 18,351 samples lost at 0, 5,146 and 2,255
        at 10, 11,587 and 10,478 at 19.
    """

    def __init__(self, analyze: Callable, niceness: int = 0):
        self._analyze = analyze
        self._niceness = int(niceness)
        self._pool = None
        self._lock = threading.Lock()
        self._running = 0            # calls waiting for the child's result

    def __call__(self, model, data, options, **kwargs):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        from concurrent.futures.process import BrokenProcessPool

        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                 initializer=_start_analysis_process,
                                                 initargs=(os.getpid(), self._niceness))
            pool = self._pool
            self._running += 1
        try:
            return pool.submit(self._analyze, model, data, options, **kwargs).result()
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            raise RuntimeError("the analysis process died (out of memory or killed); a new one is started "
                               "for the next analysis") from None
        finally:
            with self._lock:
                self._running -= 1

    def close(self) -> None:
        """Stop the child process (a running analysis is abandoned: its process is ended) and wait until the
        pool has closed its pipes.

        A shutdown that did not wait left the pool's manager thread closing its wake-up pipe while the
        interpreter's exit (``concurrent.futures``' exit hook, which Python 3.11 does not lock against it)
        wrote to that pipe: about one stop of the monitor in five printed "Exception ignored ... OSError:
        [Errno 9] Bad file descriptor".  Ended first, a running analysis's process makes the wait short.
        """
        with self._lock:
            pool, self._pool = self._pool, None
            busy = self._running > 0
        if pool is None:
            return
        if busy:
            for process in list((getattr(pool, "_processes", None) or {}).values()):
                process.terminate()
        pool.shutdown(wait=True, cancel_futures=True)
