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
from typing import Optional

from .analysis import AnalysisOptions, AnalysisReport, detect
from .logged_data import LoggedData
from .model import PlantModel
from .repair import RepairOptions, repair_model
from .signals import LoopSignals


def analyze(model: PlantModel, data: LoggedData, options: AnalysisOptions = AnalysisOptions(), *,
            signals: Optional[LoopSignals] = None, regressions=None) -> AnalysisReport:
    """Locate the mismatched elements of ``model`` on logged closed-loop data and repair them.

    Parameters
    ----------
    model : PlantModel
        The controller's model ``Phat``.
    data : LoggedData
        Setpoints, inputs, measured disturbances and outputs on the grid of ``model.sample_time``; with
        gaps (``t`` skips samples) the detections run on the segments stacked and the repair on the
        longest segment (:func:`repair_data`).
    options : AnalysisOptions
    signals : LoopSignals, optional
        Given to the first detection and to the repair (see
        :func:`~mpm_monitor.core.analysis.detect`).
    regressions : object, optional
        Given to the first detection (see :func:`~mpm_monitor.core.analysis.detect`).

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
        When the data do not fit the model or are too short for the tests.
    """
    report = detect(model, data, options, signals=signals, regressions=regressions)
    if not options.repair:
        return report
    columns = model.columns
    located = [(model.outputs.index(e.output), columns.index(e.input)) for e in report.elements if e.mismatch]
    span, note = repair_data(data, report.gaps is not None)
    result = repair_model(model, span, located, RepairOptions(initial_state=options.initial_state),
                          signals=report.signals if span is data else None)
    warnings = report.warnings
    if note and located:
        warnings.append(note)
    warnings.extend(w for w in result.warnings if w not in warnings)
    doc = result.to_dict()
    if result.model != model:
        after = detect(result.model, data, dataclasses.replace(options, repair=False, test_all_rows=False),
                       signals=result.signals if span is data else None)
        doc["rsi_after"] = {r.output: r.rsi for r in after.rows}
        doc["rows_flagged_after"] = after.flagged_rows
    kinds = getattr(result, "kinds", {})
    for e in report.elements:
        if e.mismatch:
            e.kind = kinds.get((model.outputs.index(e.output), columns.index(e.input)), "unknown")
    return dataclasses.replace(report, repair=doc, repaired_model=result.model, repair_result=result)


def repair_data(data: LoggedData, gappy: bool) -> tuple:
    """The data the repair fits: all of ``data``, or with gaps its longest segment.

    The repair's fits and its held-out validation need one contiguous record (their free responses
    and the held-out split are per record), so on data with gaps it runs on the longest span
    without a gap; its ``error_before`` / ``error_after`` are then that span's.

    Returns
    -------
    (LoggedData, str)
        The data and, for a segment, the warning that says so ('' for all of ``data``).
    """
    if not gappy:
        return data, ""
    a, b = max(data.segments, key=lambda s: s[1] - s[0])
    note = (f"the repair was fitted and validated on the longest span without a gap (t = {float(data.t[a]):g} .. "
            f"{float(data.t[b - 1]):g} s, {b - a} of {data.n_samples} samples); its prediction errors are that span's")
    return data.slice(a, b), note
