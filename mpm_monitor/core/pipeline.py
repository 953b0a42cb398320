"""The whole analysis of one window: detect, repair the located elements, detect again.

::

    detect(model, data)                 the S_Delta row test and the Delta element test
        -> repair_model(model, located) trace every located element to its kind, re-estimate it
        -> detect(repaired, data)       the row RSI and the flagged rows of the repaired model

:func:`analyze` is what the command line, the live monitor and the benchmarks run; its
:class:`~mpm_monitor.core.analysis.AnalysisReport` and JSON (``to_dict()``) are described in
docs/interfaces.md ("analyze and its JSON report").  With ``options.repair`` false it is
:func:`~mpm_monitor.core.analysis.detect` alone.
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

from .analysis import AnalysisOptions, AnalysisReport, Coloured, detect, detect_unless_coloured, light_jobs, row_jobs
from .analysis_report import settle_report
from .errors import DataFileError
from .logged_data import NUMERICAL_ERRORS, LoggedData, in_deviations, numerical_breakdown
from .model import PlantModel
from .repair import RepairOptions, explained_elements, repair_model
from .signals import LoopSignals
from .statistics import N_FAMILIES, holm_adjust


def analyze(model: PlantModel, data: LoggedData, options: AnalysisOptions = AnalysisOptions(), *,
            signals: Optional[LoopSignals] = None, regressions=None, candidates=None) -> AnalysisReport:
    """Locate the mismatched elements of ``model`` on logged closed-loop data and repair them.

    Parameters
    ----------
    model : PlantModel
        The controller's model ``Phat``.
    data : LoggedData
        Setpoints, inputs, measured disturbances and outputs on the grid of ``model.sample_time``; with
        gaps (``t`` skips samples) the detections and the repair run on the segments stacked, each
        segment a record of its own (:func:`repair_data`).
    options : AnalysisOptions
    signals : LoopSignals, optional
        Given to the first detection and to the repair (see
        :func:`~mpm_monitor.core.analysis.detect`).
    regressions : object, optional
        Given to the first detection (see :func:`~mpm_monitor.core.analysis.detect`).
    candidates : str, sequence of str or CandidateChannels, optional
        Logged channels tested as causes of the prediction error (see
        :func:`~mpm_monitor.core.analysis.detect`).  A located candidate is added to the model as a
        new measured disturbance column, its element fitted and validated on the held-out part like
        any missing element; one whose repair the validation rejects is left out of the repaired
        model.  The report's ``candidates.added`` names those added.

    With ``options.drop_spikes`` (and neither ``signals`` nor ``regressions`` given, which belong to
    the data as given) the samples of the log's spikes are left out first, as missing samples
    (:func:`mpm_monitor.core.spikes.without_spikes`); a warning names them.

    While a row's element-test residual is coloured, the detection runs again with ``na`` doubled, up
    to ``options.max_na`` (:func:`_raise_noise_order`, :mod:`mpm_monitor.core.noise_order`); the repair
    and the detection of the repaired model use the order the report was made with (the repair's AR noise
    model at least its default order, :func:`repair_noise_order`).

    Returns
    -------
    AnalysisReport
        With ``options.repair``: the ``repair`` of :func:`mpm_monitor.core.repair.repair_model` with,
        when the model changed, ``rsi_after`` (output -> RSI of the repaired model on the same data)
        and ``rows_flagged_after`` (the detection of the repaired model, every option kept but
        ``test_all_rows`` false, on the signals of the repaired model the repair computed); the kind of every
        located element; the repaired model.

    Raises
    ------
    DataFileError
        When the data do not fit the model, are too short for the tests or too large for them, or
        when the detection or the repair breaks down numerically on them (a loop that diverged:
        :func:`~mpm_monitor.core.logged_data.numerical_breakdown`, the numpy error as its ``__cause__``).
    """
    data = in_deviations(model, data)
    if options.drop_spikes and signals is None and regressions is None:
        from .spikes import without_spikes

        # Split over two processes on a window as large as the detection's lighter stages are split on.
        data, _ = without_spikes(data, jobs=light_jobs(options.jobs, data.n_samples, model))
    try:
        return _analyze(model, data, options, signals, regressions, candidates)
    except NUMERICAL_ERRORS as err:
        raise numerical_breakdown(model, data, err) from err


def _analyze(model: PlantModel, data: LoggedData, options: AnalysisOptions, signals: Optional[LoopSignals],
             regressions, candidates) -> AnalysisReport:
    """:func:`analyze` (same arguments), its numerical errors not yet turned into a ``DataFileError``."""
    kw = {} if candidates is None else {"candidates": candidates}
    # With two processes the detectable gain changes and the experiment are computed beside the repair and
    # the repaired model's detection (detect's settle): the report is settled before it is returned.
    ahead = _TestsAhead(model, data, options) if options.repair and candidates is None else None
    report, options = _detect_raising_na(model, data, options, signals, regressions,
                                         kw if ahead is None else {**kw, "beside": ahead.start})
    _check_quiet_rows(model, data, options, report, kw)
    try:
        return _repair_and_report(model, data, options, report, kw, ahead)
    except BaseException:
        if ahead is not None:     # not wanted either: its child stopped and reaped now
            ahead.close()
        try:                      # the second process's result is not wanted: only waited for
            settle_report(report)
        except BaseException:  # noqa: BLE001 - the error of the analysis is the one raised
            pass
        raise


def _check_quiet_rows(model: PlantModel, data: LoggedData, options: AnalysisOptions, report: AnalysisReport,
                      kw: dict) -> None:
    """Release the elements located in rows the S_Delta row test does not flag that the element test with
    ``max_na`` own lags does not confirm (``mismatch`` false, ``unlocated_at_na``, and the row no longer
    mismatched when no located element is left in it; with ``release_quiet_rows`` off they stay located), and
    say so in a warning per row.

    Confirmed is an element the detection with ``max_na`` own lags locates, or whose unadjusted p-value there,
    under Holm's procedure over the elements checked and times ``N_FAMILIES`` (as every element p-value), is
    below ``alpha``: the elements checked were selected by the detection with fewer own lags, and the test with
    ``max_na`` is the one whose level holds where the fewer own lags leave the noise coloured.  (Requiring the
    whole family at ``max_na`` released a true integrating element of ``bench.structures_mc`` seed 1 run 125
    with one sample dropped: p 5.8e-4 there, 0.022 after Holm over every element.)

    The row test regresses on the setpoints, which no disturbance moves: its level holds whatever colours the
    prediction error.  The element test regresses on the inputs, which the controller moves in answer to the
    prediction error: where a slow drift lies under measurement noise that is large against the loop's
    excitation, ``na`` own lags leave the noise coloured, the inputs' lags take its colour up (so that the
    whiteness check, on the residual of the fit with them, sees white noise) and the test locates elements of a
    model that matches the plant.  Measured on a 2x2 loop, plant = model (a drift of innovation 0.3 under noise of
    1.5, and 1.0 under 5.0; 20 seeds each): an element located in 20 of 20 runs each, in no row the row test flags,
    and in 0 of 20 with ``na`` 16.  A true mismatch the row test has too little power for (a small one, or one
    the setpoints do not excite) is confirmed at ``max_na`` too, as a rule, unless the noise dominates the loop's
    excitation (``bench.quiet_rows``: under the paper's noise nothing is released; under a drift below
    measurement noise of 1.5 and 5.0 the clean loops that alarm fall from 47 and 63 of 150 to 1 and 1, and the
    true elements located from 43 and 45 of 150 to 30 and 28).  The detection at ``max_na`` (no detectability)
    runs only where such an element is located.  A located candidate channel released comes
    off the candidates' located list too.  An element of such a row that the joint re-estimation released as
    explained by released elements only (``explained_by``), and that ``max_na`` does not locate either, is
    released with them (``explained_by`` emptied, ``unlocated_at_na`` set).
    """
    if options.na >= options.max_na:
        return
    quiet = {r.output: r.p_value_raw for r in report.rows if not r.p_value_raw < options.alpha}
    suspects = [e for e in report.elements if e.mismatch and e.output in quiet]
    if not suspects:
        return
    try:
        check = detect(model, data, dataclasses.replace(options, na=options.max_na), detectability=False, **kw)
    except DataFileError:        # too few samples or rows for the longer lags: nothing to compare
        return
    confirmation = _confirmation(check, [(e.output, e.input) for e in suspects])
    still = set(check.located_elements) | {k for k, p in confirmation.items() if p < options.alpha}
    release = options.release_quiet_rows
    for output in dict.fromkeys(e.output for e in suspects):
        gone = [e for e in suspects if e.output == output and (output, e.input) not in still]
        if not gone:
            continue
        names = ", ".join(e.input for e in gone)
        them = "it" if len(gone) == 1 else "them"
        # An element of the row released as explained by released ones alone (explained_by), which max_na does
        # not locate either, is not explained by a located element any more: it is released with them.
        freed = [e for e in report.elements if e.output == output and e.explained_by
                 and set(e.explained_by) <= {g.input for g in gone} and (output, e.input) not in still]
        if release:
            for e in gone:
                e.mismatch, e.unlocated_at_na = False, options.max_na
            for e in freed:
                e.explained_by, e.unlocated_at_na = (), options.max_na
            if report.candidates is not None:
                off = {(e.output, e.input) for e in gone}
                report.candidates.located = [k for k in report.candidates.located if k not in off]
            # The row counted as mismatched for its located elements only (its S_Delta test did not reject).
            if not any(e.mismatch for e in report.elements if e.output == output):
                report.rows = [dataclasses.replace(r, mismatch=False) if r.output == output else r
                               for r in report.rows]
        ps = ", ".join(f"{confirmation[(output, e.input)]:.2g}" for e in gone)
        head = (f"row {output}: the element test locates {names} where the S_Delta row test does not flag the row "
                f"(p = {quiet[output]:.2g}), and with na = {options.max_na} own lags it does not confirm {them} "
                f"(p = {ps}): a disturbance whose colour the inputs' lags take up (a slow drift under measurement "
                f"noise large against the loop's excitation) gives such false locations")
        also = (f", nor {', '.join(e.input for e in freed)}, which {'it' if len(gone) == 1 else 'they'} explained"
                if release and freed else "")
        report.warnings.append(f"{head}; {them} {'is' if len(gone) == 1 else 'are'} not reported as located{also}"
                               if release else f"{head}; analyze with na = {options.max_na} before acting on {them}")


def _confirmation(check: AnalysisReport, keys: list) -> dict:
    """``(output, column) -> p``: the confirmation's p-value of each checked element, its unadjusted p-value in
    ``check`` (the detection with ``max_na`` own lags) under Holm's procedure over ``keys`` and times
    ``N_FAMILIES``, as every element p-value (1 where ``check`` has none: an ambiguous element).  The checked
    elements were selected by the detection with fewer own lags; the test with ``max_na`` is the one whose level
    holds where those leave the noise coloured."""
    raw = {(e.output, e.input): e.p_value_raw for e in check.elements}
    given = [raw.get(k) for k in keys]
    adjusted = holm_adjust([1.0 if p is None or not np.isfinite(p) else p for p in given])
    return dict(zip(keys, np.minimum(1.0, N_FAMILIES * adjusted)))


class _TestsAhead:
    """The repair's disturbance tests of the model as given (:func:`~mpm_monitor.core.repair.disturbance_tests`),
    computed in a forked child while the detection's first stages run in this process.

    On a window that splits the element test row by row but not its lighter stages (20x20 x 10,000 samples),
    the second core is idle from the model's run to the element test; the repair tests every output's
    prediction error for an unexplained step or drift (about 30 ms at 20x20), and every output whose row it
    does not repair keeps the error of the model as given.  :meth:`start` is the detection's ``beside``;
    :meth:`result` is what :func:`~mpm_monitor.core.repair.repair_model` takes (its ``disturbance_tests``).
    """

    def __init__(self, model: PlantModel, data: LoggedData, options: AnalysisOptions):
        self.model, self.data, self.options = model, data, options
        self._job = None

    def start(self, signals: LoopSignals) -> None:
        """Fork the tests of ``signals.d`` (once)."""
        if self._job is None:
            from .parallel import Forked
            from .repair import disturbance_tests

            # The child's function holds no reference to this object (no cycle: dropped, the child is reaped at once).
            model, data, d = self.model, self.data, signals.d
            repair_options = RepairOptions(initial_state=self.options.initial_state)
            self._job = Forked(lambda: disturbance_tests(model, data, d, repair_options))

    def close(self) -> None:
        """Drop the tests unread: the child, if still running, is stopped, and reaped."""
        self._job = None

    def result(self):
        """The tests, or None when they were not started or failed (the repair then runs them itself)."""
        job, self._job = self._job, None
        if job is None:
            return None
        try:
            return job.result()
        except Exception:  # noqa: BLE001 - the repair computes them again, and meets the error there if it is real
            return None


def _repair_and_report(model: PlantModel, data: LoggedData, options: AnalysisOptions, report: AnalysisReport,
                       kw: dict, ahead: Optional[_TestsAhead] = None) -> AnalysisReport:
    """:func:`_analyze` after the detection: the joint classification, the repair and the detection of the
    repaired model; ``report`` settled (:func:`~mpm_monitor.core.analysis_report.settle_report`) after that detection
    (which reads only its regressions; at 100x40 it runs while the child still computes the detectability,
    about 0.3 s) and before its warnings are completed with the repair's and it is returned."""
    joint = options.release_explained and _shares_a_row(report)
    if not options.repair and not joint:
        return dataclasses.replace(settle_report(report), regressions=None)
    tried = report.candidates
    names = list(dict.fromkeys(name for _, name in tried.located)) if tried is not None else []
    wide, wide_data = (model, data) if not names else _with_candidates(model, data, names)
    columns = wide.columns
    mismatched = [e for e in report.elements if e.mismatch]
    located = [(wide.outputs.index(e.output), columns.index(e.input)) for e in mismatched]
    # The element test's estimate of where each mismatch acts: the repair's delay search reaches it.
    delays = {key: int(e.delay) for key, e in zip(located, mismatched) if e.delay is not None}
    span, note = repair_data(wide_data, report.gaps is not None, options, wide)
    max_gap = None if report.gaps is None else report.gaps["max_gap"]    # the model runs through the short gaps
    # The fits' noise model follows a raised na; the disturbance tests keep their 4 AR terms (repair_noise_order).
    repair_options = RepairOptions(initial_state=options.initial_state, max_gap=max_gap,
                                   noise_order=repair_noise_order(options.na, wide, span.n_samples),
                                   disturbance_noise_order=RepairOptions().noise_order)
    span_signals = report.signals if (span is wide_data or not names) else None
    classified = None
    if joint:
        classified = explained_elements(wide, span, located, repair_options, signals=span_signals, delays=delays)
        _release(report, classified.released, wide)
        located = [key for key in located if key not in classified.released]
    if not options.repair:
        return dataclasses.replace(settle_report(report), regressions=None)
    # The tests computed ahead (of the model as given, on data without gaps): repair_model takes only those that
    # fit its record, settings and prediction errors.
    jobs = row_jobs(options.jobs, span.n_samples, wide)      # the rows to repair, as the element test's
    result = repair_model(wide, span, located, repair_options, signals=span_signals, classified=classified,
                          disturbance_tests=None if ahead is None else ahead.result(), jobs=jobs, delays=delays)
    after_data, nominal = data, None
    if names:
        nominal = _candidate_operating_points(result, names)
        if nominal is not None:     # the repair again with the channels' operating points
            wide, wide_data = _with_candidates(model, data, names, nominal)
            span, note = repair_data(wide_data, report.gaps is not None, options, wide)
            result = repair_model(wide, span, located, repair_options, classified=classified, jobs=jobs,
                                  delays=delays)
        result, after_data = _keep_applied_candidates(model, data, result, tried, names, nominal)
    after_options = dataclasses.replace(options, repair=False, test_all_rows=False)

    def detect_repaired(result):
        return detect(result.model, after_data, after_options, signals=result.signals if span is wide_data else None,
                      previous=report, detectability=False, rows_only=True)
    after, named, again, refused = None, [], [], None
    if result.model != model:
        after = detect_repaired(result)
        named = located_after(report, after, result.changes, options.alpha)
        if options.repair_again and not names:
            again = _hidden(named, located, wide)
        if again:
            # A mismatch the located elements' larger one hid: the repair once more from the model as given, with it.
            keys = [key for key, _ in again]
            estimates = {(e.output, e.input): e.delay for e in after.elements if e.delay is not None}
            delays = {**delays, **{key: int(estimates[(x["output"], x["input"])]) for key, x in again
                                   if (x["output"], x["input"]) in estimates}}
            second = repair_model(wide, span, located + keys, repair_options, signals=span_signals,
                                  classified=classified, jobs=jobs, delays=delays)
            lost = _not_applied_again(result.changes, second.changes)
            if lost:         # the first repair stands
                refused = _second_round_refused(again, lost)
                again = []
            else:
                located, result = located + keys, second
                after = detect_repaired(result)
                named = located_after(report, after, result.changes, options.alpha)
    settle_report(report)
    warnings = report.warnings
    if note and located:
        warnings.append(note)
    warnings.extend(w for w in result.warnings if w not in warnings)
    doc = result.to_dict()
    if refused is not None:
        doc["warnings"].append(refused)
        warnings.append(refused)
    short = _short_noise_order(options.na, repair_options.noise_order, span.n_samples) if located else None
    if short is not None:
        doc["warnings"].append(short)
        warnings.append(short)
    if again:
        doc["second_round"] = [x for _, x in again]
        for o in dict.fromkeys(x["output"] for _, x in again):
            w = _second_round_warning(o, [x for _, x in again if x["output"] == o], located, wide)
            doc["warnings"].append(w)
            warnings.append(w)
    if after is not None:
        doc["rsi_after"] = {r.output: r.rsi for r in after.rows}
        doc["rows_flagged_after"] = after.flagged_rows
        doc["located_after"] = named
        for w in _still_flagged(report, doc["changes"], after.flagged_rows, doc["located_after"]):
            doc["warnings"].append(w)
            warnings.append(w)
    kinds = getattr(result, "kinds", {})
    for e in report.elements:
        if e.mismatch:
            e.kind = kinds.get((wide.outputs.index(e.output), columns.index(e.input)), "unknown")
    return dataclasses.replace(report, repair=doc, repaired_model=result.model, repair_result=result, regressions=None)


def _hidden(named: list, located: Sequence, model: PlantModel) -> list:
    """The entries of ``named`` (:func:`located_after` of the repaired model's detection) that the repair did not
    re-estimate (not in ``located``): ``[((output index, column index), entry), ...]``, empty when none.

    Such an element is a mismatch the located elements' larger one hid from the first detection: every one of the
    ten named on ``bench.repair_mc`` and ``bench.structures_mc`` (4,300 loops at stop 80, 1,000 more at stop 83)
    was a drawn mismatch, and an analysis of the repaired model located each (docs/benchmarks.md, "Elements the
    repaired model's detection locates", "A second round of the repair").
    """
    keys = {(model.outputs[i], model.columns[j]) for i, j in located}
    return [((model.outputs.index(x["output"]), model.columns.index(x["input"])), x)
            for x in named if (x["output"], x["input"]) not in keys]


def _not_applied_again(first: list, second: list) -> list:
    """The changes ``(output, input)`` the first repair applied that the second round's does not (its held-out check
    refused the row's repair with the added elements): the second round is then not kept."""
    applied = {(c["output"], c["input"]) for c in second if c["applied"]}
    return [(c["output"], c["input"]) for c in first if c["applied"] and (c["output"], c["input"]) not in applied]


def _second_round_refused(named: list, lost: list) -> str:
    """The warning of a second round not kept (:func:`_not_applied_again`): ``named`` the ``(key, located_after
    entry)`` it added, ``lost`` the changes of the first repair it did not apply."""
    added = ", ".join(f"({x['output']}, {x['input']})" for _, x in named)
    dropped = ", ".join(f"({o}, {i})" for o, i in lost)
    return (f"the repair run again with {added}, which the repaired model's detection located and the first detection "
            f"did not, did not apply {dropped} again (the held-out check): the first repair stands")


def _second_round_warning(output: str, named: list, located: Sequence, model: PlantModel) -> str:
    """The warning of a row repaired a second time (:func:`_hidden`): ``named`` its entries of ``located_after``
    from the first repair, ``located`` every element repaired the second time."""
    i = model.outputs.index(output)
    inputs = [x["input"] for x in named]
    others = [model.columns[j] for r, j in located if r == i and model.columns[j] not in inputs]
    one = len(inputs) == 1
    p = ", ".join(f"{x['p_value']:.2g}" for x in named)
    return (f"{output}: the detection of the repaired model located the element{'' if one else 's'} of "
            f"{', '.join(inputs)} (p = {p} at the first detection's level), which the first detection did not (the "
            f"larger mismatch of {', '.join(others)} hid {'it' if one else 'them'}); the repair ran again from the "
            f"model as given with {'it' if one else 'them'} (repair.second_round)")


def located_after(report: AnalysisReport, after: AnalysisReport, changes: list, alpha: float) -> list:
    """The elements the element test of the repaired model locates in the rows whose repair was applied, kept
    where they pass at the level of the first detection.

    The detection of the repaired model element-tests only the rows it flags, so its Holm family is smaller than
    the first detection's (every row's elements, by default): its adjusted p-values are not the first detection's.
    Here an element's raw p-value is adjusted by Bonferroni over as many elements as the first detection tested
    (with its factor for the two families), never less strict than the first detection's Holm procedure on
    those: an element of a row the repair did not change that passes here was located the first time.

    Parameters
    ----------
    report : AnalysisReport
        The detection of the model as given (``elements``).
    after : AnalysisReport
        The detection of the repaired model on the same data.
    changes : list of dict
        The repair's ``changes`` (``output``, ``applied``).
    alpha : float
        The analysis's false-alarm rate (the element test's level, as the first detection's).

    Returns
    -------
    list of dict
        ``output``, ``input``, ``p_value`` (the Bonferroni-adjusted p-value, below ``alpha``), in the order of
        ``after.elements``.
    """
    from .statistics import N_FAMILIES

    rows = {c["output"] for c in changes if c["applied"]}
    family = max(sum(e.p_value is not None for e in report.elements), 1)
    out = []
    for e in after.elements:
        if e.output not in rows or not e.mismatch or e.p_value_raw is None:
            continue
        p = min(1.0, N_FAMILIES * family * float(e.p_value_raw))
        if p < alpha:
            out.append({"output": e.output, "input": e.input, "p_value": p})
    return out


def _still_flagged(report: AnalysisReport, changes: list, flagged_after: list, located_after: Sequence = ()) -> list:
    """Warnings for the rows whose repair was applied and that the repaired model's detection still flags.  Where
    the row holds elements the data cannot tell apart (``ambiguous``, not located), the mismatch those may hold is
    not repaired, and the repaired elements, fitted with them held as the model has them, may have taken part of
    it.  Otherwise the repaired elements, in their structure, do not explain the row's mismatch (a plant's lead
    that a first-order element cannot take was fitted with its gain cut to a quarter, at confidence 1).

    Parameters
    ----------
    report : AnalysisReport
        The detection of the model as given.
    changes : list of dict
        The repair's ``changes`` (``output``, ``input``, ``applied``).
    flagged_after : list of str
        The outputs whose row the detection of the repaired model flags.
    located_after : sequence of dict
        The elements (``output``, ``input``) the element test of the repaired model locates in the rows whose
        repair was applied (:func:`located_after`).  Where it locates one that was not located, the warning
        names it: the first detection missed it, often because the located elements' larger mismatch hid it
        (docs/benchmarks.md, "Elements the repaired model's detection locates"); where it locates a repaired
        one again, the warning says so.

    Returns
    -------
    list of str
    """
    out = []
    applied = [c for c in changes if c["applied"]]
    for o in dict.fromkeys(c["output"] for c in applied if c["output"] in flagged_after):
        ambiguous = [e.input for e in report.elements if e.output == o and e.ambiguous and not e.mismatch]
        repaired = [c["input"] for c in applied if c["output"] == o]
        first = [e.input for e in report.elements if e.output == o and e.mismatch]
        again = [x["input"] for x in located_after if x["output"] == o and (x["input"] in repaired
                                                                             or x["input"] not in first)]
        if not ambiguous and again:
            out.append(f"{o}: still flagged after the repair of {', '.join(repaired)}; "
                       f"{_located_again(again, repaired)}")
            continue
        if not ambiguous:
            what = ("elements, each in the structure the model gives it, do not explain the row's mismatch whole: the "
                    "plant's elements may have a shape their structure lacks" if len(repaired) > 1 else
                    "element, in the structure the model gives it, does not explain the row's mismatch whole: the "
                    "plant's element may have a shape that structure lacks")
            out.append(f"{o}: still flagged after the repair of {', '.join(repaired)}; the re-estimated {what} (a lead, "
                       f"a second lag; a step-response element would take it), or another element of the row is "
                       f"mismatched and was not located; check the repair before using it")
            continue
        one = len(ambiguous) == 1
        tail = f"; {_located_again(again, repaired, beside_ambiguous=True)}" if again else ""
        out.append(f"{o}: still flagged after the repair of {', '.join(repaired)}; "
                   f"{'the element' if one else 'the elements'} of {', '.join(ambiguous)} cannot be told apart from "
                   f"these data (ambiguous) and {'was' if one else 'were'} held as the model has "
                   f"{'it' if one else 'them'}: a mismatch there is not repaired, and the re-estimated "
                   f"{'element' if len(repaired) == 1 else 'elements'} of {', '.join(repaired)} may have taken part "
                   f"of it; a dither that separates the inputs (the report's experiment) would decide{tail}")
    return out


def _located_again(again: list, repaired: list, beside_ambiguous: bool = False) -> str:
    """The part of a still-flagged row's warning that names what the repaired model's element test locates in it:
    ``again`` (inputs, at least one), of which those in ``repaired`` were re-estimated and the others were not
    located by the first detection.  ``beside_ambiguous``: the row holds ambiguous elements held as the model has
    them, whose mismatch a repaired element located again may be showing (``bench.structures_mc --lost-lag`` seed
    0: in all 5 elements located again, 4 of them false positives, the mismatch was an ambiguous element's).
    Otherwise the repaired element's structure may lack the plant's shape, or a mismatched element the test does
    not locate took part of it (``bench.repair_mc --dither-fat`` seed 4 run 123: a missing element fitted with a
    second lag and 3 s less dead time beside a missed element of the same row whose dead time grew 5 s)."""
    new = [i for i in again if i not in repaired]
    old = [i for i in again if i in repaired]
    parts = []
    if new:
        one = len(new) == 1
        whose = "element's" if len(repaired) == 1 else "elements'"
        parts.append(f"the detection of the repaired model locates {'the element' if one else 'the elements'} of "
                     f"{', '.join(new)}, which the first detection did not: a mismatch there is likely, which the "
                     f"located {whose} larger mismatch hid (analyze the "
                     f"repaired model, written with --repair-out, on these data to locate and repair "
                     f"{'it' if one else 'them'})")
    if old:
        one = len(old) == 1
        head = (f"{'it' if new else 'the detection of the repaired model'} locates "
                f"{'the element' if one else 'the elements'} of {', '.join(old)} again: ")
        if beside_ambiguous:
            parts.append(head + "a mismatch of the ambiguous elements, held as the model has them, may be what it sees")
        else:
            parts.append(head + f"the re-estimated {'element' if one else 'elements'}, in the structure the model "
                         f"gives {'it' if one else 'them'}, {'does' if one else 'do'} not explain the row's mismatch "
                         f"whole (the plant's {'element' if one else 'elements'} may have a shape that structure "
                         f"lacks: a lead, a second lag; a step-response element would take it), or another element "
                         f"of the row is mismatched and was not located, and the re-estimated "
                         f"{'element' if one else 'elements'} took part of its mismatch")
    return "; ".join(parts) + "; check the repair before using it"


def _detect_raising_na(model: PlantModel, data: LoggedData, options: AnalysisOptions,
                       signals: Optional[LoopSignals], regressions, kw: dict) -> tuple:
    """The detection, with ``na`` doubled while a row's element-test residual is coloured.

    :mod:`mpm_monitor.core.noise_order`: each row's residual of the element test's unrestricted fit is
    checked for whiteness (Ljung-Box, Bonferroni over the rows); while some row's is coloured and ``na`` is
    below ``options.max_na``, ``na`` doubles and the detection runs again on the same data (its
    regressions built for the new ``na``, whatever regressions the first detection was given; the first
    detection's model signals reused on data without gaps, where they are the same).  Below ``max_na``
    each order runs :func:`~mpm_monitor.core.analysis.detect_unless_coloured`: the unrestricted fits
    first, and the tests only when their residuals are white, since a detection whose rows stay
    coloured would be discarded; an order whose successor needs more data than the log holds is
    detected after all.  The report kept is the detection of the last order, with a warning saying why
    and with what ``na``; its ``noise_order`` has the order ``requested``.

    Returns
    -------
    (AnalysisReport, AnalysisOptions)
        The report and the options it was made with (``na`` raised or not).
    """
    from .noise_order import next_order

    def run(opts, **given):
        """The detection at ``opts.na``, or a :class:`Coloured` where a larger ``na`` may follow (a report
        not settled: the only one made is the one returned)."""
        if next_order(opts.na, opts.max_na) is not None:
            return detect_unless_coloured(model, data, opts, **given, **kw, settle=False)
        return detect(model, data, opts, **given, **kw, settle=False)

    report = run(options, signals=signals, regressions=regressions)
    order = report.noise_order
    if order is None or not order["coloured"]:
        return report, options
    first, first_options, refused = order, options, None
    if signals is None and report.gaps is None:
        signals = report.signals        # the model's run does not depend on na: computed once
    detected = (None, None) if isinstance(report, Coloured) else (report, options)    # the last detection
    while order["coloured"]:
        na = next_order(options.na, options.max_na)
        if na is None:
            break
        raised = dataclasses.replace(options, na=na)
        try:
            report = run(raised, signals=signals)
        except DataFileError as err:         # too few samples or rows for the longer lags: keep the last order
            refused = (na, str(err))
            break
        options, order = raised, report.noise_order
        if not isinstance(report, Coloured):
            detected = (report, options)
    if detected[1] is not options:
        # The last order ran only its fits (the next needs more data than the log holds): its detection.
        try:
            report = detect(model, data, options, signals=signals,
                            regressions=regressions if options is first_options else None, **kw, settle=False)
        except DataFileError as err:
            if detected[0] is None:
                raise
            refused = (options.na, str(err))
            report, options = detected
        order = report.noise_order
    order["requested"] = first["requested"]
    rows = ", ".join(first["coloured"])
    p_min = min(first["p_values"][x] for x in first["coloured"])
    what = (f"{'row' if len(first['coloured']) == 1 else 'rows'} {rows}: the element test's residual was not white "
            f"with na = {first['na']} (Ljung-Box p = {p_min:.2g}; a slow drift or coloured disturbance, under "
            f"which the tests give false alarms, or the row's own mismatch)")
    several = len(first["coloured"]) > 1
    coloured = order["coloured"]
    located = [x for x in coloured if any(e.mismatch for e in report.elements if e.output == x)]
    risk = ""
    if coloured:
        where = "there" if located == coloured else f"in {', '.join(located)}"
        risk = (f"; the tests' false-alarm rate may exceed alpha in {', '.join(coloured)}"
                + (f" (a located mismatch {where} may be what colours the residual, or a false alarm the colour "
                   f"caused)" if located else ""))
    if refused is not None:
        report.warnings.append(f"{what}; the tests ran with na = {order['na']}: na = {refused[0]} needs more data "
                               f"({refused[1]}){risk}")
    elif order["na"] == first["na"]:
        report.warnings.append(f"{what}; na was not raised (max_na {options.max_na}){risk}")
    elif coloured:
        report.warnings.append(f"{what}; the tests ran with na = {order['na']} (max_na), where "
                               f"{', '.join(coloured)} {'is' if len(coloured) == 1 else 'are'} still not white{risk}")
    else:
        report.warnings.append(f"{what}; the tests ran with na = {order['na']}, which whitens "
                               f"{'them' if several else 'it'}")
    return report, options


def _shares_a_row(report: AnalysisReport) -> bool:
    """Whether two located elements of ``report`` share an output row."""
    rows = [e.output for e in report.elements if e.mismatch]
    return len(set(rows)) < len(rows)


def _release(report: AnalysisReport, released: dict, model: PlantModel) -> None:
    """Mark the located elements ``released`` (:func:`~mpm_monitor.core.repair.explained_elements`:
    ``{(i, j): [k, ...]}`` in ``model``'s indices) as not located, each with the columns that
    explain it (``explained_by``), and say so in a warning per row; a candidate's comes off the
    candidates' located list too."""
    if not released:
        return
    columns, outputs = model.columns, model.outputs
    by_row = {}
    for e in report.elements:
        key = (outputs.index(e.output), columns.index(e.input)) if e.input in columns else None
        if e.mismatch and key in released:
            e.mismatch = False
            e.explained_by = tuple(columns[k] for k in released[key])
            by_row.setdefault(e.output, []).append(e)
    if report.candidates is not None:   # a candidate released is no longer among the candidates located
        gone = {(e.output, e.input) for elements in by_row.values() for e in elements}
        report.candidates.located = [k for k in report.candidates.located if k not in gone]
    for output, elements in by_row.items():
        by = list(dict.fromkeys(k for e in elements for k in e.explained_by))
        report.warnings.append(
            f"{output}: the element test also flagged {', '.join(e.input for e in elements)}, but re-estimated "
            f"together with {', '.join(by)} {'it does' if len(elements) == 1 else 'they do'} not differ "
            f"significantly from the model: {', '.join(by)} explain{'s' if len(by) == 1 else ''} the row's "
            f"mismatch, and {'it is' if len(elements) == 1 else 'they are'} not reported as located.")


def repair_noise_order(na: int, model: PlantModel, n_samples: int) -> int:
    """The order of the AR noise model of the repair's fits and held-out check: the tests' ARX order ``na`` where
    it is above the repair's default (:attr:`RepairOptions.noise_order`, 4), as far as a record of ``n_samples``
    allows.  (The repair's disturbance tests keep 4 AR terms, :attr:`RepairOptions.disturbance_noise_order`.)

    ``na`` is raised above 4 where the element test's residuals are coloured (:mod:`mpm_monitor.core.noise_order`),
    most often by a slow drift under white measurement noise, an ARMA(1, 1) whose inverse needs 15 or more lags.
    The repair's fit is a prediction-error fit in closed loop: with a noise model that leaves such colour its
    intervals are too narrow and its likelihood-ratio tests too liberal (an outside check's PI and LQ loops under a
    drift: 99.9 % intervals missed the true gain in 30 of 240 repairs with 4 lags, none with 16; docs/benchmarks.md,
    "The repair's noise order under a drift").  The order is lowered (not below the default) until the record holds
    the fit part the repair needs (:func:`~mpm_monitor.core.repair.record.samples_for_repair`), so that a short
    record is repaired as before.

    Parameters
    ----------
    na : int
        The ARX order the detection ran with (raised or not).
    model : PlantModel
        The model repaired (its columns count in the samples needed).
    n_samples : int
        Samples of the record the repair fits.

    Returns
    -------
    int
    """
    from .repair.record import samples_for_repair

    base = RepairOptions().noise_order
    order = max(base, int(na))
    while order > base and samples_for_repair(model, RepairOptions(noise_order=order)) > n_samples:
        order -= 1
    return order


def _short_noise_order(na: int, order: int, n_samples: int) -> Optional[str]:
    """The warning of a repair whose noise order :func:`repair_noise_order` lowered below the tests' ``na`` (the
    record too short for more), or None."""
    if order >= int(na):
        return None
    return (f"The repair's noise model has {order} lags where the tests ran with na = {na}: the record ({n_samples} "
            f"samples) is too short for more; where a slow drift or coloured disturbance is what raised na, the "
            f"repair's intervals may be too narrow and its kinds too ready to call a parameter changed")


def repair_data(data: LoggedData, gappy: bool, options: AnalysisOptions, model: PlantModel) -> tuple:
    """The data the repair fits: all of ``data``, or with gaps the segments the detection used.

    On data with gaps the repair (:func:`~mpm_monitor.core.repair.repair_model`) fits every segment
    as a record of its own: simulated from rest at its first sample, with its own offset and free
    responses, its first samples (the longest lag) left out of the fits; nothing is interpolated.
    Its prediction errors (before, after, held out) are those of the model run through the short
    gaps, as the detection's (``RepairOptions.max_gap``).
    The segments too short for a regression row of the tests (:func:`~mpm_monitor.core.gaps.plan_gaps`)
    are left out, as the detection leaves them out.

    Parameters
    ----------
    data : LoggedData
    gappy : bool
        Whether ``data`` has gaps (the detection's report has a ``gaps`` object).
    options : AnalysisOptions
        Its ``na``, ``nb``, ``max_delay`` and ``max_gap`` (the tests' longest lag and the gaps' plan).
    model : PlantModel
        The model repaired.

    Returns
    -------
    (LoggedData, str)
        The data and, with gaps, the warning that says what the repair used ('' for all of ``data``).
    """
    if not gappy:
        return data, ""
    from .gaps import plan_gaps
    from .regressions import regression_layout

    plan = plan_gaps(data, regression_layout(model, options).start, options.max_gap)
    if plan is None:                   # said to have gaps, but no sample is missing
        return data, ""
    used = plan.used
    rows = np.concatenate([np.arange(a, b) for a, b in used])
    short = bool(np.any(plan.gap_lengths <= plan.max_gap))
    through = "the model run through the short gaps" if short else "the model restarted after each gap"
    spans = f"the {len(used)} spans between the gaps, each from its own start" if len(used) > 1 else \
        "the one span between the gaps long enough for it"
    note = (f"the repair was fitted on {spans} ({rows.size} of {data.n_samples} samples), and validated with "
            f"{through}; no fit reaches across a gap")
    return (data if rows.size == data.n_samples else data.take(rows)), note


def _with_candidates(model: PlantModel, data: LoggedData, names: list, nominal: Optional[dict] = None):
    """The model and data with the located candidates ``names`` as new measured disturbance columns
    (:func:`~mpm_monitor.core.candidates.with_candidate_columns`, at the operating points ``nominal``,
    by default their means), which the repair fits like any element the model lacks."""
    from .candidates import with_candidate_columns

    return with_candidate_columns(model, data, names, nominal)


def _candidate_operating_points(result, names: list) -> Optional[dict]:
    """The operating points of the candidate columns logged in their units that centre the prediction
    error of the rows their repaired elements act on, or None when none moves.

    The repair added each candidate at :func:`~mpm_monitor.core.candidates.default_operating_point`:
    0 for a channel logged in deviations, kept; its mean for one logged in its units, which this moves.
    A channel's operating point moves the level of its self-regulating elements' response, which the
    data cannot tell from an offset of the output: the point chosen is the one that leaves no such
    offset, by least squares over the self-regulating rows where a candidate's element was applied,
    ``mean(d_i) + sum_c K_ic delta_c = 0`` with ``K`` the elements' gains.  (An integrating element's
    operating point sets the slope of its response, which the repair cannot tell from a ramp of the
    output either; it stays at the mean.)
    """
    m = result.model
    cols = [m.columns.index(n) for n in names if n in m.disturbances]
    cols = [j for j in cols if m.disturbance_nominal[j - m.n_inputs] != 0]         # logged in their units
    level = m.integrating_outputs
    rows = [i for i in range(m.n_outputs) if not level[i] and any(m.present[i, j] for j in cols)]
    if not rows or result.signals is None:
        return None
    K = np.where(m.present[np.ix_(rows, cols)], m.gain[np.ix_(rows, cols)], 0.0)
    mean = np.asarray(result.signals.d, float)[:, rows].mean(axis=0)
    delta = np.linalg.lstsq(K, -mean, rcond=None)[0]
    if not np.all(np.isfinite(delta)) or np.max(np.abs(K @ delta)) <= 1e-9 * (1.0 + np.max(np.abs(mean))):
        return None
    x0 = np.asarray(m.disturbance_nominal, float)[[j - m.n_inputs for j in cols]]
    return {m.columns[j]: float(a + e) for j, a, e in zip(cols, x0, delta)}


def _keep_applied_candidates(model: PlantModel, data: LoggedData, result, tried, names: list,
                             nominal: Optional[dict] = None):
    """The repair's result without the candidate columns none of whose elements it applied (their
    ``changes`` entries stay), the data with the candidates kept (at the operating points ``nominal``),
    and ``tried.added`` set."""
    from .candidates import with_candidate_columns, without_columns

    added = [n for n in names if any(c["input"] == n and c["applied"] for c in result.changes)]
    result = dataclasses.replace(result, model=without_columns(result.model, [n for n in names if n not in added]))
    tried.added = added
    return result, with_candidate_columns(model, data, added, nominal)[1]
