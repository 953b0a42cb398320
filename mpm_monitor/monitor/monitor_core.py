"""The live monitor without ROS: the sliding window, the analysis schedule and the latest outcome.

:class:`MonitorCore` receives decoded vectors (stamp in nanoseconds, values in model order) and the
wall-clock time of their arrival, keeps a :class:`~mpm_monitor.monitor.window.SampleWindow`, says when
an analysis is due and on which data (an :class:`~mpm_monitor.monitor.worker.AnalysisJob`), keeps the
latest :class:`~mpm_monitor.monitor.worker.AnalysisOutcome` and the data problems, and gives the
diagnostic statuses computed from them by :mod:`mpm_monitor.monitor.statuses` (STALE when the data
stop).  The analysis itself runs elsewhere (:mod:`mpm_monitor.monitor.worker`), and the ROS node
(:mod:`mpm_monitor.nodes.monitor_node`) only converts messages and publishes what this module returns.

:meth:`MonitorCore.write_repaired_model` writes the repaired model of the latest analysis
atomically.  :attr:`MonitorCore.experiment` (:class:`~mpm_monitor.monitor.experiment.ExperimentTracker`)
follows the experiments the analyses recommend; the summary status carries its words.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..core.errors import ConfigurationError
from ..core.model import PlantModel
from ..core.wording import applied_changes, describe_change, repair_ran, repair_verdict
from ..io.files import replace_file, same_file
from ..io.model_file import dump_model
from .candidate_window import CandidateWindow
from .experiment import ExperimentOptions, ExperimentTracker
from .statuses import (
    mark_stale,
    row_statuses,
    stale_reason,
    summary_status,
    waiting_message,
    window_values,
    with_experiment,
)
from .window import ERROR_KINDS, SampleWindow, WindowOptions
from .worker import AnalysisJob, AnalysisOutcome


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
    experiment : ExperimentOptions
        What to do with a recommended experiment (:mod:`mpm_monitor.monitor.experiment`).
    candidates : bool
        Take candidate channels (:meth:`MonitorCore.add_candidates`) and test every one of them in each
        analysis (docs/interfaces.md, "Candidate channels"); default false.
    """

    window: WindowOptions = WindowOptions()
    analysis_period: int = 500
    min_samples: int = 1000
    stale_timeout: float = 5.0
    hardware_id: str = "mpm_monitor"
    experiment: ExperimentOptions = ExperimentOptions()
    candidates: bool = False

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


def write_model_atomically(model: PlantModel, path) -> Path:
    """Write ``model`` (YAML, :func:`mpm_monitor.io.model_file.dump_model`) to ``path`` through a temporary file,
    flushed to disk and renamed over it (:func:`mpm_monitor.io.files.replace_file`: a reader sees the old file or
    the whole new one; the mode of an existing file is kept).  Returns the absolute path written; raises
    ``OSError`` (no such directory, not writable, ``path`` a directory, ...)."""
    return replace_file(path, lambda tmp: Path(tmp).write_text(dump_model(model), encoding="utf-8"), fsync=True)


class MonitorCore:
    """Window, analysis schedule and diagnostic statuses of one monitored controller.

    Parameters
    ----------
    model : PlantModel
        The controller's model (channel names and sample time).
    options : MonitorOptions
    """

    def __init__(self, model: PlantModel, options: MonitorOptions = MonitorOptions()):
        self.model = model
        self.options = options
        self.window = SampleWindow(model.outputs, model.inputs, model.sample_time, options.window,
                                   disturbances=model.disturbances)
        self._seq = 0
        self._last_job_completed = None
        self._results = 0
        self._latest: Optional[AnalysisOutcome] = None
        self._analysis_error: Optional[str] = None
        #: Why the latest window was too short for the tests (fewer samples, or regression rows between its
        #: gaps, than they need): waited on, not an error; None once an analysis has run.
        self._too_few: Optional[str] = None
        self._data_error: Optional[str] = None
        self._data_error_until = 0
        self._recent_warnings: collections.deque = collections.deque(maxlen=5)
        self._last_arrival: dict = {channel: None for channel in self.window.channels}
        self._last_complete_wall: Optional[float] = None
        self._started_wall: Optional[float] = None
        #: Number of data errors (bad values, conflicts, off-grid stamps) seen so far.
        self.data_errors = 0
        #: The experiments: recommended, requested, running, analysed.
        self.experiment = ExperimentTracker(model.inputs, options.window.window_samples, options.experiment)
        #: The candidate channels (None unless ``options.candidates``).
        self.candidates = (CandidateWindow(model.sample_time, options.window.window_samples + 64,
                                           options.window.stamp_tolerance, reserved=model.columns + model.outputs,
                                           late_samples=options.window.reorder_samples)
                           if options.candidates else None)

    # --------------------------------------------------------------------------------- input
    def add(self, channel: str, stamp_ns: int, values, now: float) -> int:
        """Add a decoded vector received at wall-clock time ``now`` (seconds); returns samples completed."""
        if self._started_wall is None:
            self._started_wall = now
        self._last_arrival[channel] = now
        n = self.window.add(channel, stamp_ns, values, int(now * 1e9))
        if n:
            self._last_complete_wall = now
            self.experiment.on_samples(self.window.n_completed)
        self._collect_problems()
        return n

    def add_candidates(self, stamp_ns: int, names: Sequence[str], values, now: float) -> Optional[str]:
        """Keep a vector of candidate channels received at wall-clock time ``now`` (seconds); a refused one
        is a bad message of the channel ``candidate``.  Ignored unless ``options.candidates``.

        Returns
        -------
        str or None
            Why the vector was refused (:meth:`~mpm_monitor.monitor.candidate_window.CandidateWindow.add`, one
            line, as recorded by :meth:`bad_message`), for the caller to log; None when it was kept or ignored.
        """
        if self.candidates is None:
            return None
        problem = self.candidates.add(stamp_ns, names, values)
        if problem is not None:
            self.bad_message("candidate", problem, now)
        return problem

    def bad_message(self, channel: str, message: str, now: float) -> None:
        """Record a message refused by the converter (wrong names, lengths, non-finite values)."""
        if self._started_wall is None:
            self._started_wall = now
        if channel in self._last_arrival:
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
        a run, so that the last samples are analysed).  An experiment that has ended makes an
        analysis due as soon as the window holds its last sample.
        """
        w = self.window
        if w.n_window < self.options.min_samples:
            return False
        if self._last_job_completed is None or self.experiment.analysis_wanted(w.last_sample_stamp_ns):
            return True
        new = w.n_completed - self._last_job_completed
        return new >= (1 if force else self.options.analysis_period)

    def take_job(self) -> AnalysisJob:
        """The window's data as the next :class:`AnalysisJob` (a copy; cheap)."""
        data = self.window.data(source="the window")
        if self.candidates is not None:
            data = self.candidates.attach(data)
        self._seq += 1
        self._last_job_completed = self.window.n_completed
        job = AnalysisJob(seq=self._seq, data=data, first_stamp=float(data.t[0]), last_stamp=float(data.t[-1]),
                          completed=self.window.n_completed, candidates="all" if self.candidates is not None else None,
                          keep=self.experiment.analysis_wanted(self.window.last_sample_stamp_ns))
        self.experiment.job_taken(job)
        return job

    def accept(self, outcome: AnalysisOutcome) -> None:
        """Take the outcome of a job (in the thread that publishes)."""
        if self._latest is not None and outcome.job.seq < self._latest.job.seq:
            return  # an older job finishing late
        if outcome.too_few is not None:      # no analysis: the latest result (or the waiting) stands, with why
            self._too_few = outcome.too_few
            self._analysis_error = None
            w = self.window
            if w.n_window >= self.options.window.window_samples and w.window_gaps()[1] == 0:
                # A full window without gaps: waiting cannot help (a window_samples below what the model's tests need).
                self._analysis_error = (f"window_samples {self.options.window.window_samples} is too short for the "
                                        f"tests even when the window is full ({outcome.too_few}): raise window_samples")
            return
        self._too_few = None
        self._results += 1
        self.experiment.on_outcome(outcome)
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
        window = f"the analysis of {job.data.n_samples} samples up to t = {job.last_stamp:.15g} s"
        applied = applied_changes(rep.repair.get("changes") or [])
        if not applied or rep.repaired_model == self.model:
            verdict = repair_verdict(rep)
            return False, (f"no change to write: {window} suggests no change to the model "
                           f"(held-out validation {verdict.verdict.replace('_', ' ')}"
                           + (f": {verdict.detail})" if verdict.detail else ")"))
        target = Path(path).expanduser().absolute()
        for other in protected:
            if other and same_file(other, target):
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
        """The current statuses: one per row then the summary (list of :class:`.statuses.StatusData`).

        Parameters
        ----------
        now : float
            Wall-clock time, seconds (same clock as the ``now`` given to :meth:`add`).
        """
        hw = self.options.hardware_id
        waiting = self._waiting_message()
        rows = row_statuses(self.model.outputs, self._latest, self._analysis_error, waiting, hw)
        summary = summary_status(self._latest, self._results, self._analysis_error, waiting,
                                 window_values(self.window.health(), self.window.n_window, self.window.window_gaps()),
                                 self._active_data_error(),
                                 self._recent_warnings[-1] if self._recent_warnings else None, hw)
        completed = self.window.n_completed
        summary = with_experiment(summary, self.experiment.text(completed, self._latest),
                                  self.experiment.values(completed))
        if self._too_few is not None and self._latest is not None:
            summary = dataclasses.replace(summary, values=summary.values + (("last_analysis_skipped", self._too_few),))
        reason = stale_reason(now, self.options.stale_timeout, self._last_complete_wall, self._started_wall,
                              self._last_arrival)
        return mark_stale(rows + [summary], reason)

    def _waiting_message(self) -> str:
        if self._too_few is not None:
            return f"no analysis yet: the window is still too short for the tests ({self._too_few})"
        return waiting_message(self.window.n_window, self.options.min_samples, self.window.oldest_incomplete())

    def _active_data_error(self) -> Optional[str]:
        """The latest bad-data problem while it counts (``analysis_period`` samples after it), else None."""
        if self._data_error is not None and self.window.n_completed >= self._data_error_until:
            self._data_error = None
        return self._data_error
