"""Work shared with a second process: a fork, its result back through a pipe.

The analysis holds Python's global interpreter lock almost throughout (many numpy calls on arrays of
a few thousand numbers, row after row), so threads cannot put a second core to use; a forked process
can.  A fork copies nothing up front (the child reads the parent's arrays through copy-on-write
pages), and the child sends back only its result, pickled.  What it computes is the same code on the
same numbers as in the parent, so a split computation gives the same result bit for bit as the
computation in one process.

:class:`Forked` runs one function in a child; :func:`split_map` runs a function over items, part of
them in a child.  Both run everything in the calling process when ``jobs`` is 1, when the platform
has no ``fork``, or when the calling process runs other threads (a fork copies only the calling
thread, and a lock another thread held at that moment stays locked in the child: the ROS nodes'
executors and DDS threads), but for threads marked :func:`fork_safe` (the live monitor's analysis
process, started with ``spawn``, runs only such a watchdog beside the analysis).

Errors: an exception raised in the child is raised again in the parent (the original type when it
pickles, otherwise a :class:`ChildProcessError` naming it).  A child that dies without a result (killed,
out of memory) costs time only: the parent computes what it was to compute itself.
"""

from __future__ import annotations

import os
import pickle
import signal
import struct
import threading
import weakref
from typing import Callable, Optional, Sequence

#: Items below which :func:`split_map` does not fork (the fork and the pickling cost more).
MIN_SPLIT = 2


def usable_cpus() -> int:
    """The cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):
        return max(os.cpu_count() or 1, 1)


def default_jobs() -> int:
    """Processes an analysis started from the command line uses: 2 where two cores are usable, else 1."""
    return min(usable_cpus(), 2)


#: Threads that hold no lock a child could need (they only sleep and poll): :func:`can_fork` allows them.
_FORK_SAFE = weakref.WeakSet()


def fork_safe(thread: threading.Thread) -> threading.Thread:
    """Mark ``thread`` as one that never holds a lock (a watchdog that sleeps and polls), so that a process
    running it may still fork (:func:`can_fork`); the child does not run it.  Returns ``thread``."""
    _FORK_SAFE.add(thread)
    return thread


def can_fork() -> bool:
    """Whether :class:`Forked` may fork here: the platform has ``fork`` and this process runs no other
    thread than the calling one and those marked :func:`fork_safe`."""
    if not hasattr(os, "fork"):
        return False
    me = threading.current_thread()
    return all(t is me or t in _FORK_SAFE for t in threading.enumerate())


class Forked:
    """``fn()`` computed in a forked child process; :meth:`result` waits for it.

    Parameters
    ----------
    fn : callable
        Called without arguments in the child; its return value must pickle.
    inline : bool
        Compute ``fn()`` here, at construction (no child), as when the process cannot fork.
    """

    def __init__(self, fn: Callable[[], object], inline: bool = False):
        self._pid = None
        self._value = None
        self._fn = fn
        #: Whether ``fn`` ran in a child (else here: at construction, or in :meth:`result` after the child died
        #: without a result; its side effects are then here).
        self.forked = not inline and can_fork()
        if not self.forked:
            self._value = _outcome(fn)
            return
        read_end, write_end = os.pipe()
        spool = _spool_file()
        self._owner = os.getpid()
        pid = os.fork()
        if pid == 0:                       # the child: compute, send, leave without running any cleanup
            try:
                os.close(read_end)
                _send(write_end, _outcome(fn), spool)
            finally:
                os._exit(0)
        os.close(write_end)
        self._pid, self._read, self._spool = pid, read_end, spool

    def __del__(self):
        # Dropped without result(): stop the child and reap it, so that no process is left behind (only in the
        # process that forked it: a later fork's child that drops its copy of this object leaves it alone).
        if getattr(self, "_pid", None) is not None and getattr(self, "_owner", None) == os.getpid():
            try:
                os.close(self._read)
                os.kill(self._pid, signal.SIGKILL)
                os.waitpid(self._pid, 0)
            except OSError:
                pass
            self._pid = None
            _close_spool(self._spool)

    def result(self):
        """The value of ``fn()``, or its exception raised again; computed here if the child died without a result."""
        if self._pid is not None:
            try:
                self._value = _receive(self._read, self._spool)
            except (EOFError, OSError, pickle.UnpicklingError, ValueError):
                self._value = None          # the child died: below, fn() in this process
            finally:
                os.close(self._read)
                _close_spool(self._spool)
                os.waitpid(self._pid, 0)
                self._pid = None
            if self._value is None:
                self.forked = False
                self._value = _outcome(self._fn)
        self._fn = None
        ok, value = self._value
        if ok:
            return value
        raise value


def _outcome(fn):
    """``(True, fn())`` or ``(False, the exception)``."""
    try:
        return True, fn()
    except BaseException as exc:  # noqa: BLE001 - raised again in the parent
        return False, exc


#: Bytes of the header of a message: the pickle's length, the number of its buffers, and whether they are in
#: the spool (1) or follow in the pipe (0).
_HEADER = struct.Struct("<QQQ")
#: A result whose arrays take at least this many bytes has them written to the spool (:func:`_spool_file`).
SPOOL_MIN_BYTES = 1 << 20
#: Each array in the spool starts at a multiple of this many bytes.
_SPOOL_ALIGN = 64


def _spool_file() -> Optional[int]:
    """A file in memory (Linux ``memfd_create``) the child writes the arrays of a large result into, made before
    the fork so that both hold it; None where there is none (the arrays then go through the pipe).

    The parent maps it once the child is done (privately: the arrays are writable, a write copies its page)
    and the arrays are built on the mapping, without a copy: the transfer is then the child's own copy into
    the file, and the parent neither reads the bytes through the pipe nor allocates them (at 100x40 the
    element test's child sends about 72 MB of moments)."""
    try:
        return os.memfd_create("mpm_monitor-result", os.MFD_CLOEXEC)
    except (AttributeError, OSError):
        return None


def _close_spool(spool: Optional[int]) -> None:
    if spool is not None:
        try:
            os.close(spool)
        except OSError:
            pass


def _pickled(outcome) -> tuple:
    """``(pickle, buffers)`` of ``outcome``: protocol 5, the arrays' data left out of band (sent as they are,
    without a copy into the pickle); an exception that does not pickle becomes a ChildProcessError naming it."""
    buffers = []
    try:
        return pickle.dumps(outcome, protocol=5, buffer_callback=buffers.append), buffers
    except Exception as exc:  # noqa: BLE001
        ok, value = outcome
        what = f"{type(value).__name__}: {value}" if not ok else f"a result that does not pickle ({exc})"
        return pickle.dumps((False, ChildProcessError(f"the analysis's second process: {what}"))), []


def _send(fd: int, outcome, spool: Optional[int] = None) -> None:
    """Write ``outcome`` to the pipe ``fd``: a header, the pickle, the sizes of its buffers, then the buffers;
    or, when they take at least :data:`SPOOL_MIN_BYTES` and there is a ``spool``, the buffers into the spool
    (each at a multiple of :data:`_SPOOL_ALIGN` bytes) and their offsets into the pipe."""
    data, buffers = _pickled(outcome)
    views = [b.raw() for b in buffers]
    sizes = [v.nbytes for v in views]
    spooled = spool is not None and sum(sizes) >= SPOOL_MIN_BYTES
    offsets = []
    if spooled:
        at = 0
        for v in views:
            at = -(-at // _SPOOL_ALIGN) * _SPOOL_ALIGN
            offsets.append(at)
            _pwrite_all(spool, v, at)
            at += v.nbytes
    _widen(fd)
    _write_all(fd, _HEADER.pack(len(data), len(views), int(spooled)) + data
               + struct.pack(f"<{len(views) + len(offsets)}Q", *sizes, *offsets))
    if not spooled:
        for v in views:
            _write_all(fd, v)


def _receive(fd: int, spool: Optional[int] = None):
    """Read what :func:`_send` wrote to the pipe ``fd`` (and the ``spool``); the arrays are built on the bytes
    read, or on the spool's private mapping, without a copy."""
    _widen(fd)
    size, count, spooled = _HEADER.unpack(_read_exactly(fd, _HEADER.size))
    data = _read_exactly(fd, size)
    if not spooled:
        sizes = struct.unpack(f"<{count}Q", _read_exactly(fd, 8 * count))
        return pickle.loads(data, buffers=[_read_exactly(fd, n) for n in sizes])
    numbers = struct.unpack(f"<{2 * count}Q", _read_exactly(fd, 16 * count))
    sizes, offsets = numbers[:count], numbers[count:]
    if spool is None:
        raise ValueError("a result in a spool this process does not hold")
    import mmap

    whole = memoryview(mmap.mmap(spool, os.fstat(spool).st_size, flags=mmap.MAP_PRIVATE,
                                 prot=mmap.PROT_READ | mmap.PROT_WRITE))
    return pickle.loads(data, buffers=[whole[a:a + n] for a, n in zip(offsets, sizes)])


def _pwrite_all(fd: int, data, offset: int) -> None:
    view = memoryview(data).cast("B")
    while view.nbytes:
        k = os.pwrite(fd, view, offset)
        view, offset = view[k:], offset + k


def _widen(fd: int) -> None:
    """Ask for a pipe buffer of 1 MiB (Linux; fewer switches between the processes), if allowed."""
    try:
        import fcntl

        fcntl.fcntl(fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), 1 << 20)
    except (ImportError, OSError):
        pass


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view.nbytes:
        view = view[os.write(fd, view):]


def _read_exactly(fd: int, n: int) -> bytearray:
    """``n`` bytes from ``fd``; EOFError when the pipe closes before."""
    out = bytearray(n)
    view, got = memoryview(out), 0
    while got < n:
        k = os.readv(fd, [view[got:]])
        if k == 0:
            raise EOFError(f"the pipe closed after {got} of {n} bytes")
        got += k
    return out


def split_map(fn: Callable[[object], object], items: Sequence, jobs: int = 1,
              meanwhile: Optional[Callable[[], None]] = None) -> list:
    """``[fn(x) for x in items]``, part of ``items`` computed in a forked child when ``jobs`` > 1.

    The parent and the child take the items one at a time, each the next one not taken yet (their
    indices wait in a pipe, and a read of a few bytes from a pipe is atomic), so that neither waits
    long for the other however the items' costs and the two processes' speeds differ (the child pays
    for the pages it writes, :mod:`mpm_monitor.core.parallel`).  The results come back in the order of
    ``items``; each is computed by the same code on the same numbers as in one process, whichever
    process takes it.  Side effects of ``fn`` in the child (caches, dicts it fills) stay in the child:
    ``fn`` must return all that the caller needs, and the caller must not rely on the order in which
    the parent's calls happen.

    Parameters
    ----------
    fn : callable
        One item -> its result (which must pickle).
    items : sequence
    jobs : int
        Processes to use (at most 2 are used).
    meanwhile : callable, optional
        Other work of the caller, called without arguments in this process before it takes any item: after
        the fork, so that the child takes items meanwhile (with one process, first).  It must not depend on
        the items' results, nor they on its side effects.

    Returns
    -------
    list
    """
    items = list(items)
    n = len(items)
    if jobs <= 1 or n < MIN_SPLIT or not can_fork():
        if meanwhile is not None:
            meanwhile()
        return [fn(x) for x in items]
    # The queue: runs of consecutive items (one item each, up to _QUEUE_LENGTH items).
    bounds = [k * n // min(n, _QUEUE_LENGTH) for k in range(min(n, _QUEUE_LENGTH) + 1)]
    read_end, write_end = os.pipe()
    try:
        _write_all(write_end, b"".join(_INDEX.pack(k) for k in range(len(bounds) - 1)))
    finally:
        os.close(write_end)          # the queue is complete: an empty pipe now reads as its end

    def take_all() -> list:
        """``(index, fn(item))`` of every item this process takes, until none is left."""
        out = []
        while True:
            got = os.read(read_end, _INDEX.size)
            if not got:
                return out
            run = _INDEX.unpack(got)[0]
            out.extend((k, fn(items[k])) for k in range(bounds[run], bounds[run + 1]))

    try:
        child = Forked(take_all)
        try:
            if meanwhile is not None:
                meanwhile()
            mine = take_all()
        except BaseException:
            try:
                child.result()            # reap the child; the parent's own error is the one raised
            except BaseException:  # noqa: BLE001
                pass
            raise
        theirs = child.result()
    finally:
        os.close(read_end)
    results = [None] * n
    done = [False] * n
    for k, value in mine + theirs:
        results[k], done[k] = value, True
    for k in range(n):               # taken by a child that died without a result: computed here
        if not done[k]:
            results[k] = fn(items[k])
    return results


#: The index of a run of items in :func:`split_map`'s queue.
_INDEX = struct.Struct("<I")
#: Runs in :func:`split_map`'s queue, at most: their indices (4 KiB) fit in the smallest pipe buffer
#: Linux gives, so that the queue is written whole before the fork.
_QUEUE_LENGTH = 1024
