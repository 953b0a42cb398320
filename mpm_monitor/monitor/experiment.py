"""The live monitor's experiments: when to ask the controller for a dither, and what to say about it.

When the data cannot tell some inputs apart, the analysis recommends an experiment (the report's
``experiment``: a PRBS dither per input and a number of samples; docs/interfaces.md, "Detectability
and experiment").  With ``auto_experiment`` the monitor node asks the MPC node's ``~/start_dither``
service for it; :class:`ExperimentTracker` decides when (never while a call or an experiment is
under way, and then not before ``experiment_cooldown`` samples), follows the experiment on the
``dither`` topic, asks for the analysis of the window that includes it once it has ended, and gives
the summary status its words.  It holds no ROS object and reads no clock: the node passes it the
window's sample counts and stamps, the service's answers and the dither messages.

The life of an experiment (:attr:`ExperimentTracker.phase`)::

    idle --call--> requested --accepted--> running --zero dither vector, or samples + END_MARGIN
    samples completed--> ended --a job of a window holding its last sample--> analysing --that
    job's outcome--> done

A refused or failed call goes to ``refused`` / ``failed``.  After ``done``, ``refused`` or
``failed`` the next call waits until ``experiment_cooldown`` samples have completed since, so one
recommendation that the experiment did not settle (or that the service refuses) is not requested
again and again.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Mapping, Optional, Sequence

import numpy as np

from ..core.errors import ConfigurationError
from .window import NS_PER_S, seconds_text

#: Samples after the expected end of an experiment at which it counts as ended even though no zero
#: dither vector came (a lost message, or a stack whose dither topic the monitor does not see).
END_MARGIN = 10

IDLE, REQUESTED, RUNNING, ENDED, ANALYSING, DONE, REFUSED, FAILED = (
    "idle", "requested", "running", "ended", "analysing", "done", "refused", "failed")
#: Phases during which no other experiment is requested.
BUSY = (REQUESTED, RUNNING, ENDED, ANALYSING)


@dataclasses.dataclass(frozen=True)
class ExperimentOptions:
    """What the monitor does with a recommended experiment.

    Attributes
    ----------
    auto : bool
        Ask ``service`` for the experiment (``auto_experiment``); false: only report it.
    service : str
        The dither service, as named in messages (the node gives its resolved name).
    cooldown : int
        Samples after an experiment's analysis (or a refused or failed call) before the next call
        (``experiment_cooldown``, >= 0).
    """

    auto: bool = False
    service: str = "mpc/start_dither"
    cooldown: int = 10000

    def __post_init__(self):
        if int(self.cooldown) != self.cooldown or not 0 <= self.cooldown <= 10**9:
            raise ConfigurationError(f"experiment_cooldown: expected an integer in [0, 1000000000] samples, "
                                     f"got {self.cooldown!r}")


@dataclasses.dataclass(frozen=True)
class Recommendation:
    """An experiment as the monitor requests it.

    Attributes
    ----------
    dither : tuple of (str, float)
        (input, PRBS amplitude in input units), in the model's input order.
    samples : int
        Samples to request: the recommendation's, capped at the window less :data:`END_MARGIN`
        (the window analysed when the experiment ends is taken up to that many samples after its
        last dithered sample, and must still hold its first).
    recommended_samples : int
        The samples the analysis recommended.
    expected_detectable_gain_change : float
        The analysis's prediction (relative gain error detected with 90 % probability after it).
    why : str
    """

    dither: tuple
    samples: int
    recommended_samples: int
    expected_detectable_gain_change: float = float("nan")
    why: str = ""

    @property
    def capped(self) -> bool:
        """True when the request is shorter than the recommendation (capped to fit the window)."""
        return self.samples < self.recommended_samples

    @property
    def inputs(self) -> tuple:
        return tuple(name for name, _ in self.dither)

    def amplitudes_text(self) -> str:
        """``amplitudes 0.08, 0.08`` (``amplitude 0.08`` for one input)."""
        word = "amplitude" if len(self.dither) == 1 else "amplitudes"
        return f"{word} {', '.join(f'{a:g}' for _, a in self.dither)}"

    def dither_value(self) -> str:
        """``u4=0.08,u5=0.08`` (a diagnostic value)."""
        return ",".join(f"{name}={a!r}" for name, a in self.dither)

    def cap_text(self, window_samples: int) -> str:
        """Why the request is shorter than the recommendation ('' when it is not)."""
        if not self.capped:
            return ""
        return (f"capped at {self.samples} samples to fit the window of {window_samples}; "
                f"{self.recommended_samples} recommended")


def _field(obj, name: str):
    return obj.get(name) if isinstance(obj, Mapping) else getattr(obj, name, None)


def recommendation_of(report, inputs: Sequence[str], window_samples: int) -> Optional[Recommendation]:
    """The experiment a report recommends, as the monitor would request it (None: none, or unusable).

    Parameters
    ----------
    report : AnalysisReport or None
        Its ``experiment`` is None or has ``dither`` (input name -> amplitude, input units),
        ``samples``, ``expected_detectable_gain_change`` and ``why`` (an object or a mapping, as in
        the JSON report).
    inputs : sequence of str
        The model's inputs (the order of the dither).
    window_samples : int
        The monitor's window: a longer experiment is requested for ``window_samples - END_MARGIN``
        samples only (at least 1), so that the window analysed after it holds it.
    """
    exp = None if report is None else getattr(report, "experiment", None)
    if exp is None:
        return None
    dither = dict(_field(exp, "dither") or {})
    try:
        samples = int(_field(exp, "samples"))
        amps = {name: float(a) for name, a in dither.items()}
    except (TypeError, ValueError):
        return None
    amps = {name: a for name, a in amps.items() if math.isfinite(a) and a > 0}
    if samples < 1 or not amps or any(name not in inputs for name in amps):
        return None
    gain = _field(exp, "expected_detectable_gain_change")
    return Recommendation(dither=tuple((name, amps[name]) for name in inputs if name in amps),
                          samples=min(samples, max(1, int(window_samples) - END_MARGIN)), recommended_samples=samples,
                          expected_detectable_gain_change=float("nan") if gain is None else float(gain),
                          why=str(_field(exp, "why") or ""))


class ExperimentTracker:
    """When the monitor asks for an experiment, how it follows it, and the summary's words about it.

    Parameters
    ----------
    inputs : sequence of str
        The model's inputs.
    window_samples : int
        The monitor's window (the cap of a request).
    options : ExperimentOptions

    Notes
    -----
    Sample counts are the window's completed samples (:attr:`SampleWindow.n_completed`), stamps
    integer nanoseconds; the node calls :meth:`on_samples` as samples complete,
    :meth:`on_outcome` for every accepted analysis outcome, :meth:`next_request` after it, then
    :meth:`on_requested`, :meth:`on_response` or :meth:`on_call_failed` for the service call, and
    :meth:`on_dither` for every dither vector.
    """

    def __init__(self, inputs: Sequence[str], window_samples: int, options: ExperimentOptions = ExperimentOptions()):
        self.inputs = tuple(inputs)
        self.window_samples = int(window_samples)
        self.options = options
        self.phase = IDLE
        #: The latest analysis's recommendation (None: none).
        self.recommendation: Optional[Recommendation] = None
        #: The experiment requested, running or last run.
        self.current: Optional[Recommendation] = None
        #: The service's answer, or why the call failed (one line).
        self.detail = ""
        #: Experiments the service accepted.
        self.started = 0
        self.service_ready: Optional[bool] = None
        self._next_allowed = 0
        self._start_completed = 0
        self._seen = 0
        self._first_stamp: Optional[int] = None
        self._last_stamp: Optional[int] = None
        self._analysis_seq: Optional[int] = None
        self._analysed_job = None

    # ------------------------------------------------------------------------------ decisions
    def on_outcome(self, outcome) -> None:
        """An accepted analysis outcome: its recommendation, and the end of an experiment's analysis."""
        if outcome.report is not None and outcome.error is None:
            self.recommendation = recommendation_of(outcome.report, self.inputs, self.window_samples)
        if self.phase == ANALYSING and outcome.job.seq >= self._analysis_seq:
            self.phase = DONE
            self._analysed_job = outcome.job
            self._next_allowed = outcome.job.completed + self.options.cooldown

    def next_request(self, completed: int, service_ready: bool) -> Optional[Recommendation]:
        """The experiment to request now, or None.

        Parameters
        ----------
        completed : int
            Samples completed so far.
        service_ready : bool
            The dither service answers (a call now would reach it).
        """
        if not self.options.auto or self.phase in BUSY or self.recommendation is None:
            return None
        if completed < self._next_allowed:
            return None
        self.service_ready = bool(service_ready)
        return self.recommendation if service_ready else None

    def on_requested(self, request: Recommendation) -> None:
        """The call for ``request`` was sent."""
        self.phase = REQUESTED
        self.current = request
        self.detail = ""
        self._seen = 0
        self._first_stamp = self._last_stamp = None

    def on_response(self, successful: bool, reason: str, completed: int) -> None:
        """The service answered the call."""
        self.detail = " ".join(str(reason).split())
        if successful:
            self.phase = RUNNING
            self.started += 1
            self._start_completed = int(completed)
        else:
            self.phase = REFUSED
            self._next_allowed = int(completed) + self.options.cooldown

    def on_call_failed(self, reason: str, completed: int) -> None:
        """The call did not get an answer (no service any more, a timeout, an error)."""
        self.phase = FAILED
        self.detail = " ".join(str(reason).split())
        self._next_allowed = int(completed) + self.options.cooldown

    # ----------------------------------------------------------------------------- following
    def on_dither(self, stamp_ns: int, values) -> None:
        """A dither vector (model input order) arrived; the zero vector ends the running experiment.

        Vectors that come while the call is under way count too: the dither starts with the
        controller's next sample, which may come before the node has taken the answer.
        """
        if self.phase not in (REQUESTED, RUNNING):
            return
        if np.any(np.asarray(values) != 0):
            self._seen += 1
            if self._first_stamp is None:
                self._first_stamp = int(stamp_ns)
            self._last_stamp = int(stamp_ns)
        elif self.phase == RUNNING:
            self.phase = ENDED

    def on_samples(self, completed: int) -> None:
        """Samples completed: a running experiment whose zero vector never came ends by its count."""
        if self.phase == RUNNING and completed - self._start_completed >= self.current.samples + END_MARGIN:
            self.phase = ENDED

    def analysis_wanted(self, last_sample_stamp_ns: Optional[int]) -> bool:
        """True when the experiment has ended and the window holds its last dithered sample."""
        if self.phase != ENDED:
            return False
        return self._last_stamp is None or (last_sample_stamp_ns is not None
                                            and last_sample_stamp_ns >= self._last_stamp)

    def job_taken(self, job) -> None:
        """A job of the window was taken: the experiment's analysis when it is the job that holds the
        experiment (``job.keep``, set from :meth:`analysis_wanted` when the job was made)."""
        if job.keep:
            self.phase = ANALYSING
            self._analysis_seq = job.seq

    def samples_left(self, completed: int) -> int:
        """Samples of the running experiment still to come (from the dither topic, else from the count)."""
        if self.current is None or self.phase != RUNNING:
            return 0
        done = self._seen if self._seen else completed - self._start_completed
        return max(0, self.current.samples - done)

    # -------------------------------------------------------------------------------- words
    def _span(self) -> str:
        if self._first_stamp is None:
            return ""
        return f" (t = {seconds_text(self._first_stamp)}-{seconds_text(self._last_stamp)} s)"

    def _not_started(self, completed: int) -> str:
        """Why the recommendation is only reported."""
        service = self.options.service
        if not self.options.auto:
            return "auto_experiment is false"
        if completed < self._next_allowed:
            again = f"not before sample {self._next_allowed} (experiment_cooldown)"
            if self.phase == REFUSED:
                reason = self.detail[len("refused: "):] if self.detail.startswith("refused: ") else self.detail
                return f"refused by {service}: {reason}; {again}"
            if self.phase == FAILED:
                return f"the call to {service} failed: {self.detail}; {again}"
            return again
        if self.service_ready is False:
            return f"no dither service at {service}"
        return f"calling {service}"

    def text(self, completed: int, outcome=None) -> str:
        """The summary's words about experiments ('' when there is nothing to say).

        Parameters
        ----------
        completed : int
            Samples completed so far.
        outcome : AnalysisOutcome, optional
            The latest outcome (says whether its window holds the last experiment).
        """
        parts = []
        cur = self.current
        if self.phase == REQUESTED:
            parts.append(f"experiment requested: dither on {', '.join(cur.inputs)} for {cur.samples} samples "
                         f"({cur.amplitudes_text()}) from {self.options.service}")
        elif self.phase == RUNNING:
            parts.append(f"experiment running: dither on {', '.join(cur.inputs)} ({cur.amplitudes_text()}; "
                         f"{self.samples_left(completed)} samples left)")
        elif self.phase in (ENDED, ANALYSING):
            parts.append(f"experiment ended: dither on {', '.join(cur.inputs)} for {cur.samples} samples"
                         f"{self._span()}; analysing the window that includes it")
        elif self.phase == DONE and outcome is not None and self._first_stamp is not None \
                and outcome.job.first_stamp <= float(self._first_stamp) / NS_PER_S:
            parts.append(f"this analysis includes the experiment: dither on {', '.join(cur.inputs)} for "
                         f"{cur.samples} samples{self._span()}")
        rec = self.recommendation
        if rec is not None and self.phase not in BUSY:
            notes = [rec.amplitudes_text(), rec.cap_text(self.window_samples), self._not_started(completed)]
            parts.append(f"experiment recommended: dither on {', '.join(rec.inputs)} for {rec.samples} samples "
                         f"({'; '.join(n for n in notes if n)})")
        return "; ".join(parts)

    def state(self) -> str:
        """``none``, ``recommended`` or the phase of the latest experiment (a diagnostic value)."""
        if self.phase in BUSY:
            return self.phase
        if self.recommendation is not None:
            return "recommended"
        return "none" if self.phase == IDLE else self.phase

    def values(self, completed: int) -> list:
        """The summary's experiment values, as (key, value) pairs (none before the first recommendation)."""
        if self.phase == IDLE and self.recommendation is None:
            return []
        shown = self.current if self.phase in BUSY or self.recommendation is None else self.recommendation
        gain = "nan" if shown is None or not math.isfinite(shown.expected_detectable_gain_change) \
            else repr(shown.expected_detectable_gain_change)
        return [("experiment", self.state()),
                ("experiment_dither", "" if shown is None else shown.dither_value()),
                ("experiment_samples", "" if shown is None else str(shown.samples)),
                ("experiment_samples_left", str(self.samples_left(completed))),
                ("experiment_expected_detectable_gain_change", gain),
                ("experiment_why", "" if shown is None else shown.why),
                ("experiment_detail", self.detail),
                ("experiments", str(self.started))]
