"""The live monitor's diagnostic statuses, as plain data computed from what the monitor knows.

Every function here is pure: it turns the latest analysis outcome, the window's health and the
arrival times into :class:`StatusData`, and changes nothing.
:class:`~mpm_monitor.monitor.monitor_core.MonitorCore` keeps that state and calls them; the ROS
node (:mod:`mpm_monitor.nodes.monitor_node`) turns the result into
``diagnostic_msgs/DiagnosticStatus``.

Statuses (docs/interfaces.md, "ROS 2 topics and statuses"): one per output, named ``mpm_monitor:
row <output>``, with values ``rsi``, ``mismatch`` (``true``/``false``), ``flagged_inputs``
(comma-separated), ``p_value`` and more, and one ``mpm_monitor: summary``.  Levels: OK (no
mismatch), WARN (mismatch located), ERROR (bad input data or analysis failure), STALE (no fresh
data).  An output that never moves in the window (a stuck sensor or a held value: the report's
``still_outputs``) is bad input data: its row's status is ERROR, and so is the summary, whose value
``still_outputs`` names them.

When the analysis includes the repair (:mod:`mpm_monitor.core.repair`), the statuses carry the
suggested repair: per row ``repair`` (e.g. ``u2: time_constant 45->60 s, delay 4->7 s; u3: gain
3.5->5.88``), ``error_before`` / ``error_after`` (RMS of the one-step prediction error ``d = y -
yhat`` over the window with the model as given / as repaired), the held-out errors, ``rsi_after``,
``second_round`` (the inputs of the elements the repair ran again with: a first repair's detection located them,
the first detection did not), ``located_after`` (where the repaired model's detection still locates elements in
the row: their inputs, comma-separated) and per located element ``kind <input>`` and ``confidence <input>``; in the summary
``repair_changes`` (number of suggested element changes), ``repair_validation`` (the held-out
verdict: ``passed``, ``rejected``, ``mixed``, ``not_validated``, ``not_run``, ``none`` or ``off``)
and ``repair_validation_detail`` (the same in words).

Per row, ``detectable_gain_change`` lists for every tested element the smallest relative gain
error this window detects with probability 0.9 (``u1=0.12,u2=0.35,u3=nan``; ``nan`` where it cannot
be computed, :mod:`mpm_monitor.core.detectability`).

The summary also says what became of the experiment the analysis recommends (``experiment
recommended: ...``, ``experiment running: ...``; :mod:`mpm_monitor.monitor.experiment` words it,
:func:`with_experiment` adds it).
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import Mapping, Optional, Sequence

from ..core.wording import applied_changes, repair_ran, repair_verdict, row_repair_text
from .window import seconds_text

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


def _num(x) -> str:
    """A number as a diagnostic value: shortest exact repr, ``nan`` for missing."""
    if x is None:
        return "nan"
    x = float(x)
    return repr(x) if math.isfinite(x) else ("nan" if math.isnan(x) else ("inf" if x > 0 else "-inf"))


def _bool(b) -> str:
    return "true" if b else "false"


#: Values of a row status that has no analysis result.
_NO_ROW_RESULT = (("rsi", "nan"), ("mismatch", "false"), ("flagged_inputs", ""), ("p_value", "nan"),
                  ("analyzed", "false"))


# ------------------------------------------------------------------------------- the window
def waiting_message(n_window: int, min_samples: int, incomplete: Optional[tuple] = None) -> str:
    """Why there is no analysis result yet: samples still missing, or the first analysis running.

    ``incomplete`` is :meth:`~mpm_monitor.monitor.window.SampleWindow.oldest_incomplete` (the samples held
    incomplete, and what the oldest lacks), said when samples are still missing.
    """
    if n_window < min_samples:
        held = ""
        if incomplete is not None:
            stamp_ns, absent, n_held = incomplete
            lacks = f" (no {' and no '.join(absent)})" if absent else ""
            held = f"; {n_held} more held incomplete, from t = {seconds_text(stamp_ns)} s{lacks}"
        return f"no analysis yet: {n_window} of {min_samples} samples collected{held}"
    return f"no analysis yet: the first analysis is running ({n_window} samples collected)"


def window_values(health, n_window: int, window_gaps: tuple = (0, 0)) -> list:
    """The window's counters as summary values.

    Parameters
    ----------
    health : WindowHealth
        :meth:`mpm_monitor.monitor.window.SampleWindow.health`.
    n_window : int
        Samples in the window now.
    window_gaps : (int, int)
        Samples lost and gaps inside the window now (:meth:`~mpm_monitor.monitor.window.SampleWindow.window_gaps`).
    """
    h = health
    return [("completed_samples", str(h.completed)), ("window_samples", str(n_window)),
            ("window_lost_samples", str(window_gaps[0])), ("window_gaps", str(window_gaps[1])),
            ("missing_samples", str(h.missing_samples)), ("gaps", str(h.gaps)),
            ("bad_messages", str(h.bad_value)), ("off_grid", str(h.off_grid)), ("conflicts", str(h.conflict)),
            ("duplicates", str(h.duplicate)), ("late", str(h.late)), ("out_of_order", str(h.out_of_order)),
            ("restarts", str(h.restarts))]


def lost_text(data) -> str:
    """``", 12 lost in 7 gaps"`` for a window whose ``t`` skips samples ('' without a gap)."""
    segments = data.segments
    if len(segments) <= 1:
        return ""
    lost = int(data.grid_index[-1]) + 1 - data.n_samples
    return f", {lost} lost in {len(segments) - 1} gap{'s' if len(segments) > 2 else ''}"


def stale_reason(now: float, timeout: float, last_complete: Optional[float], started: Optional[float],
                 last_arrival: Mapping[str, Optional[float]]) -> Optional[str]:
    """Why the statuses are STALE at wall-clock time ``now``, or None while the data are fresh.

    Parameters
    ----------
    now, timeout : float
        Wall-clock time and the stale timeout, seconds.
    last_complete : float or None
        Wall-clock time the last sample completed (None: none yet).
    started : float or None
        Wall-clock time the monitor started (the reference before the first complete sample).
    last_arrival : mapping of str to float or None
        Wall-clock time of the last message of each channel (None: never).
    """
    ref = last_complete if last_complete is not None else started
    if ref is None or now - ref <= timeout:
        return None
    ages = [f"{ch} {'never' if t is None else f'{now - t:.1f} s ago'}" for ch, t in last_arrival.items()]
    what = "no complete sample" if last_complete is not None else "no complete sample yet"
    return f"{what} for {now - ref:.1f} s (last {', '.join(ages)})"


def mark_stale(statuses: Sequence[StatusData], reason: Optional[str]) -> list:
    """``statuses`` turned STALE with ``reason`` in front of their message (unchanged when ``reason`` is None)."""
    if reason is None:
        return list(statuses)
    return [s.with_level(STALE, f"{reason}; last result: {s.message}") for s in statuses]


# ------------------------------------------------------------------------------ the results
def row_statuses(outputs: Sequence[str], outcome, analysis_error: Optional[str], waiting: str,
                 hardware_id: str) -> list:
    """One status per output row.

    Parameters
    ----------
    outputs : sequence of str
        The model's outputs, in order.
    outcome : AnalysisOutcome or None
        The latest outcome (:class:`mpm_monitor.monitor.worker.AnalysisOutcome`); after a failed
        analysis it carries the failed job and the previous report.
    analysis_error : str or None
        The latest analysis failed with this message.
    waiting : str
        The message before the first report (:func:`waiting_message`).
    hardware_id : str
    """
    hw = hardware_id
    rep = None if outcome is None else outcome.report
    if rep is None:
        msg = analysis_error or waiting
        level = ERROR if analysis_error else OK
        return [StatusData(level, row_status_name(o), msg, hw, _NO_ROW_RESULT) for o in outputs]
    job = outcome.job
    rows = {r.output: r for r in rep.rows}
    elements = collections.defaultdict(list)
    for e in rep.elements:
        elements[e.output].append(e)
    repaired = repair_ran(rep)
    doc = rep.repair if repaired else {}
    changes = list(doc.get("changes") or [])
    confidence = {(c.get("output"), c.get("input")): c.get("confidence") for c in changes}
    still = set(getattr(rep, "still_outputs", ()) or ())
    out = []
    for o in outputs:
        r = rows.get(o)
        if r is None:
            out.append(StatusData(ERROR, row_status_name(o), f"the analysis has no row {o}", hw, _NO_ROW_RESULT))
            continue
        els = elements.get(o, [])
        candidates = [e.input for e in els if e.mismatch and getattr(e, "role", "input") == "candidate"]
        flagged = [e.input for e in els if e.mismatch and getattr(e, "role", "input") != "candidate"]
        ambiguous = [e.input for e in els if getattr(e, "ambiguous", False)]
        values = [("rsi", _num(r.rsi)), ("mismatch", _bool(r.mismatch)), ("flagged_inputs", ",".join(flagged)),
                  ("p_value", _num(r.p_value)), ("ambiguous_inputs", ",".join(ambiguous))]
        explained = [e.input for e in els if getattr(e, "explained_by", ())]
        if explained:
            values.append(("explained_inputs", ",".join(explained)))
        unlocated = [e.input for e in els if getattr(e, "unlocated_at_na", None) is not None]
        if unlocated:
            values.append(("unlocated_inputs", ",".join(unlocated)))
        detectable = [(e.input, getattr(e, "detectable_gain_change", None)) for e in els]
        if any(x is not None for _, x in detectable):
            values.append(("detectable_gain_change", ",".join(f"{i}={_num(x)}" for i, x in detectable)))
        if getattr(rep, "candidates", None) is not None:
            values.append(("candidate_effects", ",".join(candidates)))
        for e in els:
            if e.mismatch or getattr(e, "ambiguous", False):
                values.append((f"p_value {e.input}", _num(e.p_value)))
                values.append((f"kind {e.input}", str(getattr(e, "kind", None) or "unknown")))
                if (o, e.input) in confidence:
                    values.append((f"confidence {e.input}", _num(confidence[(o, e.input)])))
        if repaired:
            values.append(("repair", row_repair_text(changes, o)))
            values += [(key, _num(doc[key][o])) for key in ("error_before", "error_after", "holdout_error_before",
                                                            "holdout_error_after", "rsi_after")
                       if o in (doc.get(key) or {})]
            for key in ("second_round", "located_after"):
                named = [x["input"] for x in doc.get(key) or [] if x["output"] == o]
                if named:
                    values.append((key, ",".join(named)))
        values += [("samples", str(job.data.n_samples)), ("window_start", _num(job.first_stamp)),
                   ("window_end", _num(job.last_stamp)), ("analyzed", "true")]
        if o in still:
            level = ERROR
            msg = (f"output {o} never moves in this window (every value the same: a stuck sensor or a held value?): "
                   f"a fault of the measurement; the elements of row {o} are not tested (RSI {r.rsi:.3f})")
        elif r.mismatch:
            level = WARN
            if flagged:
                msg = f"mismatch in row {o}: elements " + ", ".join(f"({o}, {i})" for i in flagged)
            elif candidates:
                msg = f"mismatch in row {o}: an effect of candidate channel(s) {', '.join(candidates)} the model lacks"
            elif ambiguous:
                msg = f"mismatch in row {o}: inputs {', '.join(ambiguous)} cannot be told apart"
            else:
                msg = f"mismatch in row {o}: no single element located"
            if flagged and candidates:
                msg += f", and an effect of candidate channel(s) {', '.join(candidates)} the model lacks"
            msg += f" (RSI {r.rsi:.3f})"
            row_applied = [c for c in applied_changes(changes) if c.get("output") == o]
            if row_applied and o in (doc.get("error_before") or {}) and o in (doc.get("error_after") or {}):
                msg += (f"; suggested repair of {', '.join(c.get('input') for c in row_applied)} lowers the "
                        f"RMS prediction error {doc['error_before'][o]:.3g} -> {doc['error_after'][o]:.3g}")
        else:
            level = OK
            msg = f"no mismatch in row {o} (RSI {r.rsi:.3f})"
        if analysis_error:
            level, msg = ERROR, f"{analysis_error}; previous result: {msg}"
        out.append(StatusData(level, row_status_name(o), msg, hw, tuple(values)))
    return out


def summary_status(outcome, analyses: int, analysis_error: Optional[str], waiting: str, window: Sequence[tuple],
                   data_error: Optional[str], last_data_problem: Optional[str], hardware_id: str) -> StatusData:
    """The ``mpm_monitor: summary`` status.

    Parameters
    ----------
    outcome, analysis_error, waiting, hardware_id
        As for :func:`row_statuses`.
    analyses : int
        Analysis outcomes accepted so far.
    window : sequence of (str, str)
        The window's counters (:func:`window_values`).
    data_error : str or None
        A recent bad-data problem that makes the summary ERROR.
    last_data_problem : str or None
        The latest problem that costs samples but not correctness (value ``last_data_problem``).
    """
    rep = None if outcome is None else outcome.report
    values = []
    if rep is None:
        level = ERROR if analysis_error else OK
        msg = analysis_error or waiting
        values += [("flagged_rows", ""), ("located_elements", ""), ("overall_rsi", "nan"), ("analyses", "0")]
    else:
        job = outcome.job
        flagged = [r.output for r in rep.rows if r.mismatch]
        located = [(e.output, e.input) for e in rep.elements if e.mismatch]
        warnings = list(getattr(rep, "warnings", []) or [])
        values += [("flagged_rows", ",".join(flagged)),
                   ("located_elements", ",".join(f"{o}:{i}" for o, i in located)),
                   ("overall_rsi", _num(getattr(rep, "overall_rsi", None))),
                   ("analyses", str(analyses)), ("samples", str(job.data.n_samples)),
                   ("window_start", _num(job.first_stamp)), ("window_end", _num(job.last_stamp)),
                   ("analysis_seconds", f"{outcome.seconds:.3f}"),
                   ("warnings", " | ".join(warnings))]
        verdict = repair_verdict(rep)
        values += [("repair_changes", str(verdict.changes)), ("repair_validation", verdict.verdict),
                   ("repair_validation_detail", verdict.detail)]
        order = getattr(rep, "noise_order", None)
        if order is not None:          # the ARX order of the tests (raised from the option's while a residual is coloured)
            values += [("na", str(order["na"]))]
        cands = getattr(rep, "candidates", None)
        if cands is not None:
            values += [("candidates_tried", ",".join(cands.tried)), ("candidates_added", ",".join(cands.added)),
                       ("candidates_not_exogenous", ",".join(cands.not_exogenous)),
                       ("candidates_unusable", ",".join(cands.unusable))]
        if flagged:
            level = WARN
            msg = (f"mismatch in row(s) {', '.join(flagged)}; elements "
                   + (", ".join(f"({o}, {i})" for o, i in located) if located else "not located"))
            if verdict.verdict not in ("off", "none"):
                msg += (f"; suggested repair: {verdict.changes} change{'s' if verdict.changes != 1 else ''}, "
                        f"held-out validation {verdict.verdict.replace('_', ' ')}")
            if cands is not None and cands.added:
                msg += f"; candidate channel(s) {', '.join(cands.added)} added to the repaired model as measured " \
                       f"disturbance(s)"
        else:
            level = OK
            msg = "no model-plant mismatch detected"
        still = list(getattr(rep, "still_outputs", ()) or ())
        if still:
            level = ERROR
            values += [("still_outputs", ",".join(still))]
            several = len(still) > 1
            msg = (f"output{'s' if several else ''} {', '.join(still)} never move{'' if several else 's'} (a stuck "
                   f"sensor or a held value?); {msg}")
        msg += f" ({job.data.n_samples} samples up to t = {job.last_stamp:.15g} s{lost_text(job.data)})"
        if analysis_error:
            level, msg = ERROR, f"{analysis_error}; previous result: {msg}"
    values += list(window)
    if data_error is not None:
        level = ERROR
        msg = f"bad input data: {data_error}; {msg}"
    if last_data_problem is not None:
        values.append(("last_data_problem", last_data_problem))
    return StatusData(level, SUMMARY_NAME, msg, hardware_id, tuple(values))


def with_experiment(summary: StatusData, text: str, values: Sequence[tuple]) -> StatusData:
    """The summary with the experiment's words after its message and its values at the end.

    Parameters
    ----------
    summary : StatusData
        :func:`summary_status`.
    text : str
        :meth:`mpm_monitor.monitor.experiment.ExperimentTracker.text` ('' leaves the message as it is).
    values : sequence of (str, str)
        :meth:`mpm_monitor.monitor.experiment.ExperimentTracker.values`.
    """
    message = f"{summary.message}; {text}" if text else summary.message
    return dataclasses.replace(summary, message=message, values=tuple(summary.values) + tuple(values))
