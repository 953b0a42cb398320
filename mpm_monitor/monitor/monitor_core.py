"""The live monitor's logic, without ROS: sliding window -> analysis -> diagnostic statuses.

:class:`MonitorCore` receives decoded vectors (stamp in nanoseconds, values in model order) and the
wall-clock time of their arrival, keeps a :class:`~mpm_monitor.monitor.window.SampleWindow`, says when an
analysis is due and on which data, turns an :class:`~mpm_monitor.core.analysis.AnalysisReport` (or an
error) into diagnostic statuses as plain data, and ages them to STALE when the data stop.
:class:`AnalysisWorker` runs the analysis in a background thread so that the subscription callbacks
never wait for it.  The ROS node (:mod:`mpm_monitor.nodes.monitor_node`) only converts messages
and publishes what this module returns.

Statuses (CONTRACTS section 4): one per output, named ``mpm_monitor: row <output>``, with values
``rsi``, ``mismatch`` (``true``/``false``), ``flagged_inputs`` (comma-separated), ``p_value`` and
more, and one ``mpm_monitor: summary``.  Levels: OK (no mismatch), WARN (mismatch located), ERROR
(bad input data or analysis failure), STALE (no fresh data).

When the analysis includes the repair (:mod:`mpm_monitor.core.repair`, issue 5), the statuses carry the
suggested repair: per row ``repair`` (e.g. ``u2: time_constant 45->60 s, delay 4->7 s; u3: gain
3.5->5.88``), ``error_before`` / ``error_after`` (RMS of the one-step prediction error ``d = y -
yhat`` over the window with the model as given / as repaired), the held-out errors, ``rsi_after``
and per located element ``kind <input>`` and ``confidence <input>``; in the summary
``repair_changes`` (number of suggested element changes), ``repair_validation`` (the held-out
verdict: ``passed``, ``rejected``, ``mixed``, ``not_validated``, ``not_run``, ``none`` or ``off``)
and ``repair_validation_detail`` (the same in words).  :meth:`MonitorCore.write_repaired_model`
writes the latest repaired model file atomically.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import os
import tempfile
import threading
import time
import traceback
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from ..core.errors import ConfigurationError
from ..core.model import FopdtModel
from ..core.wording import applied_changes, describe_change, repair_ran, repair_verdict, row_repair_text
from ..io.model_file import save_model
from .window import ERROR_KINDS, SampleWindow, WindowOptions

OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}

STATUS_PREFIX = "mpm_monitor"
SUMMARY_NAME = f"{STATUS_PREFIX}: summary"


def row_status_name(output: str) -> str:
    """Name of the status of one output row: ``mpm_monitor: row <output>``."""
    return f"{STATUS_PREFIX}: row {output}"


@dataclasses.dataclass(frozen=True)
class StatusData:
    """A diagnostic status as plain data (the node turns it into ``diagnostic_msgs/DiagnosticStatus``).

    Attributes
    ----------
    level : int
        ``OK`` (0), ``WARN`` (1), ``ERROR`` (2) or ``STALE`` (3).
    name : str
    message : str
    hardware_id : str
    values : tuple of (str, str)
        Key/value pairs, in order.
    """

    level: int
    name: str
    message: str
    hardware_id: str
    values: tuple

    def value(self, key: str, default: Optional[str] = None) -> Optional[str]:
        """The value of ``key`` (or ``default``)."""
        for k, v in self.values:
            if k == key:
                return v
        return default

    def with_level(self, level: int, message: str) -> "StatusData":
        return dataclasses.replace(self, level=level, message=message)


@dataclasses.dataclass(frozen=True)
class MonitorOptions:
    """Options of the live monitor.

    Attributes
    ----------
    window : WindowOptions
        Length of the sliding window and alignment rules.
    analysis_period : int
        Samples between two analyses (>= 1).
    min_samples : int
        Samples needed in the window before the first analysis (>= 10, <= window length).
    stale_timeout : float
        Wall-clock seconds without a completed sample after which every status is STALE (> 0).
    hardware_id : str
        ``hardware_id`` of the statuses (e.g. the controller's name).
    """

    window: WindowOptions = WindowOptions()
    analysis_period: int = 500
    min_samples: int = 1000
    stale_timeout: float = 5.0
    hardware_id: str = "mpm_monitor"

    def __post_init__(self):
        check_monitor_options(self)


def check_monitor_options(o: MonitorOptions) -> None:
    """Raise :class:`ConfigurationError` naming the option outside its range."""
    if int(o.analysis_period) != o.analysis_period or not 1 <= o.analysis_period <= 10_000_000:
        raise ConfigurationError(f"analysis_period: expected an integer in [1, 10000000] samples, "
                                 f"got {o.analysis_period!r}")
    if int(o.min_samples) != o.min_samples or not 10 <= o.min_samples <= o.window.window_samples:
        raise ConfigurationError(f"min_samples: expected an integer in [10, window_samples="
                                 f"{o.window.window_samples}], got {o.min_samples!r}")
    if not (math.isfinite(o.stale_timeout) and o.stale_timeout > 0):
        raise ConfigurationError(f"stale_timeout: expected a number of seconds > 0, got {o.stale_timeout!r}")


@dataclasses.dataclass(frozen=True)
class AnalysisJob:
    """One analysis to run: the window's data and where it lies in the stream."""

    seq: int
    data: Any               # LoggedData
    first_stamp: float      # seconds
    last_stamp: float       # seconds
    completed: int          # samples completed in the stream when the job was taken


@dataclasses.dataclass(frozen=True)
class AnalysisOutcome:
    """The result of an :class:`AnalysisJob`: a report or an error message."""

    job: AnalysisJob
    report: Any = None
    error: Optional[str] = None
    seconds: float = 0.0


def _num(x) -> str:
    """A number as a diagnostic value: shortest exact repr, ``nan`` for missing."""
    if x is None:
        return "nan"
    x = float(x)
    return repr(x) if math.isfinite(x) else ("nan" if math.isnan(x) else ("inf" if x > 0 else "-inf"))


def _bool(b) -> str:
    return "true" if b else "false"


def write_model_atomically(model: FopdtModel, path) -> Path:
    """Write ``model`` (YAML, :func:`mpm_monitor.io.model_file.save_model`) to ``path`` through a temporary file.

    The file is written next to ``path``, flushed to disk and renamed over it, so a reader sees
    either the old file or the whole new one, never a partial one.  The mode of an existing file is
    kept (0644 for a new one).

    Returns
    -------
    Path
        The absolute path written.

    Raises
    ------
    OSError
        The directory does not exist, is not writable, ``path`` is a directory, ...
    """
    target = Path(path).expanduser().absolute()
    if target.is_dir():
        raise IsADirectoryError(21, "is a directory", str(target))
    mode = (target.stat().st_mode & 0o7777) if target.exists() else 0o644
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        os.close(fd)
        save_model(model, tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return target


def run_analysis(analyze: Callable, model: FopdtModel, options, job: AnalysisJob,
                 clock: Callable[[], float] = time.perf_counter) -> AnalysisOutcome:
    """Run ``analyze(model, job.data, options)`` and wrap its report or its error."""
    from ..core.logged_data import check_scale

    t0 = clock()
    try:
        check_scale(model, job.data)  # a sentinel like 1e308 would give a silent all-clear
        report = analyze(model, job.data, options)
    except Exception as exc:  # the monitor reports any failure as ERROR and keeps running
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return AnalysisOutcome(job, error=f"analysis failed: {type(exc).__name__}: {msg}", seconds=clock() - t0)
    return AnalysisOutcome(job, report=report, seconds=clock() - t0)


class MonitorCore:
    """Window, analysis schedule and diagnostic statuses of one monitored controller.

    Parameters
    ----------
    model : FopdtModel
        The controller's model (channel names and sample time).
    options : MonitorOptions
    """

    def __init__(self, model: FopdtModel, options: MonitorOptions = MonitorOptions()):
        self.model = model
        self.options = options
        self.window = SampleWindow(model.outputs, model.inputs, model.sample_time, options.window)
        self._seq = 0
        self._last_job_completed = None
        self._results = 0
        self._latest: Optional[AnalysisOutcome] = None
        self._analysis_error: Optional[str] = None
        self._data_error: Optional[str] = None
        self._data_error_until = 0
        self._recent_warnings: collections.deque = collections.deque(maxlen=5)
        self._last_arrival: dict = {"setpoint": None, "input": None, "output": None}
        self._last_complete_wall: Optional[float] = None
        self._started_wall: Optional[float] = None
        #: Number of data errors (bad values, conflicts, off-grid stamps) seen so far.
        self.data_errors = 0

    # --------------------------------------------------------------------------------- input
    def add(self, channel: str, stamp_ns: int, values, now: float) -> int:
        """Add a decoded vector received at wall-clock time ``now`` (seconds); returns samples completed."""
        if self._started_wall is None:
            self._started_wall = now
        self._last_arrival[channel] = now
        n = self.window.add(channel, stamp_ns, values)
        if n:
            self._last_complete_wall = now
        self._collect_problems()
        return n

    def bad_message(self, channel: str, message: str, now: float) -> None:
        """Record a message refused by the converter (wrong names, lengths, non-finite values)."""
        if self._started_wall is None:
            self._started_wall = now
        self._last_arrival[channel] = now
        self.window.report_bad(channel, None, message)
        self._collect_problems()

    def start(self, now: float) -> None:
        """Start the staleness clock (otherwise it starts with the first message)."""
        if self._started_wall is None:
            self._started_wall = now

    def _collect_problems(self) -> None:
        for p in self.window.take_problems():
            if p.kind in ERROR_KINDS:
                self.data_errors += 1
                self._data_error = p.message
                self._data_error_until = self.window.n_completed + self.options.analysis_period
            else:
                self._recent_warnings.append(p.message)

    # ------------------------------------------------------------------------------ analysis
    def analysis_due(self, force: bool = False) -> bool:
        """True when the window holds ``min_samples`` and ``analysis_period`` samples came since the last job.

        With ``force``, any new sample since the last job makes an analysis due (e.g. at the end of
        a run, so that the last samples are analysed).
        """
        w = self.window
        if w.n_window < self.options.min_samples:
            return False
        if self._last_job_completed is None:
            return True
        new = w.n_completed - self._last_job_completed
        return new >= (1 if force else self.options.analysis_period)

    def take_job(self) -> AnalysisJob:
        """The window's data as the next :class:`AnalysisJob` (a copy; cheap)."""
        data = self.window.data(source="ros")
        self._seq += 1
        self._last_job_completed = self.window.n_completed
        return AnalysisJob(seq=self._seq, data=data, first_stamp=float(data.t[0]), last_stamp=float(data.t[-1]),
                           completed=self.window.n_completed)

    def accept(self, outcome: AnalysisOutcome) -> None:
        """Take the outcome of a job (in the thread that publishes)."""
        if self._latest is not None and outcome.job.seq < self._latest.job.seq:
            return  # an older job finishing late
        self._results += 1
        if outcome.error is not None:
            self._analysis_error = outcome.error
            self._latest = dataclasses.replace(outcome, report=self._latest.report if self._latest else None)
            return
        self._analysis_error = None
        self._latest = outcome

    @property
    def results(self) -> int:
        """Number of analysis outcomes accepted so far."""
        return self._results

    @property
    def latest_report(self):
        """The latest report (None before the first)."""
        return None if self._latest is None else self._latest.report

    @property
    def latest_outcome(self) -> Optional[AnalysisOutcome]:
        return self._latest

    def write_repaired_model(self, path: str, protected: Sequence[str] = ()) -> tuple:
        """Write the repaired model of the latest analysis to ``path`` (YAML, atomically).

        Parameters
        ----------
        path : str
            The file to write (a node parameter, never taken from a message); "" refuses.
        protected : sequence of str
            Files never overwritten (the controller's model file).

        Returns
        -------
        (bool, str)
            Success and a one-line message: what was written where, or why nothing was (no
            analysis yet, the analysis ran without the repair, no change suggested, the write
            failed).  Never raises for these cases.
        """
        if not path:
            return False, "no file to write to: set the parameter repaired_model_file"
        rep = self.latest_report
        if rep is None:
            if self._analysis_error:
                return False, f"no analysis result yet: {self._analysis_error}"
            return False, self._waiting_message()
        if not repair_ran(rep) or getattr(rep, "repaired_model", None) is None:
            return False, "the latest analysis ran without the repair (parameter repair is false): nothing to write"
        job = self._latest.job
        window = f"the analysis of {job.data.n_samples} samples up to t = {job.last_stamp:g} s"
        applied = applied_changes(rep.repair.get("changes") or [])
        if not applied or rep.repaired_model == self.model:
            verdict = repair_verdict(rep)
            return False, (f"no change to write: {window} suggests no change to the model "
                           f"(held-out validation {verdict.verdict.replace('_', ' ')}"
                           + (f": {verdict.detail})" if verdict.detail else ")"))
        target = Path(path).expanduser().absolute()
        for other in protected:
            if other and Path(other).expanduser().absolute() == target:
                return False, f"refusing to overwrite the monitored model file {target}: set repaired_model_file " \
                              f"to another path"
        try:
            written = write_model_atomically(rep.repaired_model, target)
        except OSError as exc:
            return False, f"cannot write {target}: {exc.strerror or exc}"
        what = "; ".join(f"{c.get('output')}/{c.get('input')}: {describe_change(c)}" for c in applied)
        n = len(applied)
        return True, f"wrote the repaired model of {window} to {written} ({n} change{'s' if n != 1 else ''}: {what})"

    def rsi_vector(self) -> Optional[np.ndarray]:
        """Row RSI values in model output order, shape (n_outputs,), or None before the first report."""
        rep = self.latest_report
        if rep is None:
            return None
        by = {r.output: float(r.rsi) for r in rep.rows}
        return np.array([by.get(o, float("nan")) for o in self.model.outputs])

    # ------------------------------------------------------------------------------ statuses
    def statuses(self, now: float) -> list:
        """The current statuses: one per row then the summary (list of :class:`StatusData`).

        Parameters
        ----------
        now : float
            Wall-clock time, seconds (same clock as the ``now`` given to :meth:`add`).
        """
        rows = self._row_statuses()
        summary = self._summary_status()
        stale = self._stale_reason(now)
        if stale is not None:
            rows = [s.with_level(STALE, f"{stale}; last result: {s.message}") for s in rows]
            summary = summary.with_level(STALE, f"{stale}; last result: {summary.message}")
        return rows + [summary]

    def _stale_reason(self, now: float) -> Optional[str]:
        timeout = self.options.stale_timeout
        ref = self._last_complete_wall if self._last_complete_wall is not None else self._started_wall
        if ref is None or now - ref <= timeout:
            return None
        ages = []
        for ch, t in self._last_arrival.items():
            ages.append(f"{ch} {'never' if t is None else f'{now - t:.1f} s ago'}")
        what = "no complete sample" if self._last_complete_wall is not None else "no complete sample yet"
        return f"{what} for {now - ref:.1f} s (last {', '.join(ages)})"

    def _waiting_message(self) -> str:
        n, need = self.window.n_window, self.options.min_samples
        if n < need:
            return f"no analysis yet: {n} of {need} samples collected"
        return f"no analysis yet: the first analysis is running ({n} samples collected)"

    def _window_values(self) -> list:
        h = self.window.health()
        return [("completed_samples", str(h.completed)), ("window_samples", str(self.window.n_window)),
                ("missing_samples", str(h.missing_samples)), ("gaps", str(h.gaps)),
                ("bad_messages", str(h.bad_value)), ("off_grid", str(h.off_grid)), ("conflicts", str(h.conflict)),
                ("duplicates", str(h.duplicate)), ("late", str(h.late)), ("out_of_order", str(h.out_of_order)),
                ("restarts", str(h.restarts))]

    def _row_statuses(self) -> list:
        hw = self.options.hardware_id
        rep = self.latest_report
        out = []
        if rep is None:
            msg = self._analysis_error or self._waiting_message()
            level = ERROR if self._analysis_error else OK
            for o in self.model.outputs:
                out.append(StatusData(level, row_status_name(o), msg, hw,
                                      (("rsi", "nan"), ("mismatch", "false"), ("flagged_inputs", ""),
                                       ("p_value", "nan"), ("analyzed", "false"))))
            return out
        job = self._latest.job
        rows = {r.output: r for r in rep.rows}
        elements = collections.defaultdict(list)
        for e in rep.elements:
            elements[e.output].append(e)
        repaired = repair_ran(rep)
        doc = rep.repair if repaired else {}
        changes = list(doc.get("changes") or [])
        confidence = {(c.get("output"), c.get("input")): c.get("confidence") for c in changes}
        for o in self.model.outputs:
            r = rows.get(o)
            if r is None:
                out.append(StatusData(ERROR, row_status_name(o), f"the analysis has no row {o}", hw,
                                      (("rsi", "nan"), ("mismatch", "false"), ("flagged_inputs", ""),
                                       ("p_value", "nan"), ("analyzed", "false"))))
                continue
            els = elements.get(o, [])
            flagged = [e.input for e in els if e.mismatch]
            ambiguous = [e.input for e in els if getattr(e, "ambiguous", False)]
            values = [("rsi", _num(r.rsi)), ("mismatch", _bool(r.mismatch)), ("flagged_inputs", ",".join(flagged)),
                      ("p_value", _num(r.p_value)), ("ambiguous_inputs", ",".join(ambiguous))]
            for e in els:
                if e.mismatch or getattr(e, "ambiguous", False):
                    values.append((f"p_value {e.input}", _num(e.p_value)))
                    values.append((f"kind {e.input}", str(getattr(e, "kind", None) or "unknown")))
                    if (o, e.input) in confidence:
                        values.append((f"confidence {e.input}", _num(confidence[(o, e.input)])))
            row_repair = ""
            if repaired:
                row_repair = row_repair_text(changes, o)
                values.append(("repair", row_repair))
                values += [(key, _num(doc[key][o])) for key in ("error_before", "error_after", "holdout_error_before",
                                                                "holdout_error_after", "rsi_after")
                           if o in (doc.get(key) or {})]
            values += [("samples", str(job.data.n_samples)), ("window_start", _num(job.first_stamp)),
                       ("window_end", _num(job.last_stamp)), ("analyzed", "true")]
            if r.mismatch:
                level = WARN
                if flagged:
                    msg = f"mismatch in row {o}: elements " + ", ".join(f"({o}, {i})" for i in flagged)
                elif ambiguous:
                    msg = f"mismatch in row {o}: inputs {', '.join(ambiguous)} cannot be told apart"
                else:
                    msg = f"mismatch in row {o}: no single element located"
                msg += f" (RSI {r.rsi:.3f})"
                row_applied = [c for c in applied_changes(changes) if c.get("output") == o]
                if row_applied and o in (doc.get("error_before") or {}) and o in (doc.get("error_after") or {}):
                    msg += (f"; suggested repair of {', '.join(c.get('input') for c in row_applied)} lowers the "
                            f"RMS prediction error {doc['error_before'][o]:.3g} -> {doc['error_after'][o]:.3g}")
            else:
                level = OK
                msg = f"no mismatch in row {o} (RSI {r.rsi:.3f})"
            if self._analysis_error:
                level, msg = ERROR, f"{self._analysis_error}; previous result: {msg}"
            out.append(StatusData(level, row_status_name(o), msg, hw, tuple(values)))
        return out

    def _summary_status(self) -> StatusData:
        hw = self.options.hardware_id
        rep = self.latest_report
        values = []
        if rep is None:
            level = ERROR if self._analysis_error else OK
            msg = self._analysis_error or self._waiting_message()
            values += [("flagged_rows", ""), ("located_elements", ""), ("overall_rsi", "nan"), ("analyses", "0")]
        else:
            job = self._latest.job
            flagged = [r.output for r in rep.rows if r.mismatch]
            located = [(e.output, e.input) for e in rep.elements if e.mismatch]
            warnings = list(getattr(rep, "warnings", []) or [])
            values += [("flagged_rows", ",".join(flagged)),
                       ("located_elements", ",".join(f"{o}:{i}" for o, i in located)),
                       ("overall_rsi", _num(getattr(rep, "overall_rsi", None))),
                       ("analyses", str(self._results)), ("samples", str(job.data.n_samples)),
                       ("window_start", _num(job.first_stamp)), ("window_end", _num(job.last_stamp)),
                       ("analysis_seconds", f"{self._latest.seconds:.3f}"),
                       ("warnings", " | ".join(warnings))]
            verdict = repair_verdict(rep)
            values += [("repair_changes", str(verdict.changes)), ("repair_validation", verdict.verdict),
                       ("repair_validation_detail", verdict.detail)]
            if flagged:
                level = WARN
                msg = (f"mismatch in row(s) {', '.join(flagged)}; elements "
                       + (", ".join(f"({o}, {i})" for o, i in located) if located else "not located"))
                if verdict.verdict not in ("off", "none"):
                    msg += (f"; suggested repair: {verdict.changes} change{'s' if verdict.changes != 1 else ''}, "
                            f"held-out validation {verdict.verdict.replace('_', ' ')}")
            else:
                level = OK
                msg = "no model-plant mismatch detected"
            msg += f" ({job.data.n_samples} samples up to t = {job.last_stamp:g} s)"
            if self._analysis_error:
                level, msg = ERROR, f"{self._analysis_error}; previous result: {msg}"
        values += self._window_values()
        if self._data_error is not None:
            if self.window.n_completed < self._data_error_until:
                level = ERROR
                msg = f"bad input data: {self._data_error}; {msg}"
            else:
                self._data_error = None
        if self._recent_warnings:
            values.append(("last_data_problem", self._recent_warnings[-1]))
        return StatusData(level, SUMMARY_NAME, msg, hw, tuple(values))


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
    contains the newer samples), so a slow analysis never builds a backlog.  Outcomes are taken
    with :meth:`take_outcomes` in the thread that publishes.
    """

    def __init__(self, run: Callable[[AnalysisJob], AnalysisOutcome], on_done: Optional[Callable[[], None]] = None,
                 threaded: bool = True):
        self._run = run
        self._on_done = on_done
        self._threaded = threaded
        self._lock = threading.Condition()
        self._waiting: Optional[AnalysisJob] = None
        self._busy = False
        self._closed = False
        self._outcomes: collections.deque = collections.deque()
        self.replaced = 0
        self._thread = None
        if threaded:
            self._thread = threading.Thread(target=self._loop, name="mpm_monitor analysis", daemon=True)
            self._thread.start()

    def submit(self, job: AnalysisJob) -> None:
        """Queue ``job`` (replacing a job that is still waiting)."""
        if not self._threaded:
            self._outcomes.append(self._run(job))
            if self._on_done:
                self._on_done()
            return
        with self._lock:
            if self._waiting is not None:
                self.replaced += 1
            self._waiting = job
            self._lock.notify()

    @property
    def idle(self) -> bool:
        """True when no job runs or waits."""
        with self._lock:
            return self._waiting is None and not self._busy

    def take_outcomes(self) -> list:
        """Outcomes finished since the last call, oldest first."""
        out = []
        while self._outcomes:
            out.append(self._outcomes.popleft())
        return out

    def _loop(self) -> None:
        while True:
            with self._lock:
                while self._waiting is None and not self._closed:
                    self._lock.wait()
                if self._closed:
                    return
                job, self._waiting = self._waiting, None
                self._busy = True
            try:
                outcome = self._run(job)
            except Exception:  # run() already wraps analysis errors; this is a last resort
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


def _exit_with_parent(parent_pid: int, period: float = 0.5) -> None:
    """In the analysis process: leave as soon as the monitor's process is gone (a pool worker
    otherwise outlives a parent killed by SIGKILL, waiting forever for work)."""

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(period)
        os._exit(0)

    threading.Thread(target=watch, name="exit with parent", daemon=True).start()


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
        A picklable (module-level) function, e.g. :func:`mpm_monitor.core.analysis.analyze`.
    """

    def __init__(self, analyze: Callable):
        self._analyze = analyze
        self._pool = None
        self._lock = threading.Lock()

    def __call__(self, model, data, options):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor
        from concurrent.futures.process import BrokenProcessPool

        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                                 initializer=_exit_with_parent, initargs=(os.getpid(),))
            pool = self._pool
        try:
            return pool.submit(self._analyze, model, data, options).result()
        except BrokenProcessPool:
            with self._lock:
                if self._pool is pool:
                    self._pool = None
            raise RuntimeError("the analysis process died (out of memory or killed); a new one is started "
                               "for the next analysis") from None

    def close(self) -> None:
        """Stop the child process (a running analysis is abandoned)."""
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)
