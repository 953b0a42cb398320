"""The repair in words: what a control engineer reads in the summary, the statuses and the demo.

Every text about a suggested repair is made here from the ``repair`` dict of an analysis report
(``changes`` with ``before``/``after`` parameters, the held-out errors), so that the command line, the
monitor's statuses and the demo say the same thing the same way.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

#: Element parameters of a repair change, with their unit.
_CHANGE_PARAMS = (("gain", ""), ("time_constant", " s"), ("delay", " s"))

#: ``reason`` of a change the held-out validation refused (:func:`mpm_monitor.core.repair.repair_model`).
_REJECTED = "rejected by held-out validation"


def _short(x) -> str:
    """A parameter value with three significant digits (``60.0057`` -> ``60``, ``5.8773`` -> ``5.88``)."""
    return "nan" if x is None else f"{float(x):.3g}"


def describe_change(change: dict) -> str:
    """The parameters a repair change entry alters, in words: ``time_constant 45->60 s, delay 4->7 s``.

    Parameters
    ----------
    change : dict
        An entry of the report's ``repair["changes"]`` (``before`` and ``after`` with ``gain``,
        ``time_constant`` in seconds and ``delay`` in seconds).

    Returns
    -------
    str
        "" when ``after`` equals ``before``.
    """
    before, after = change.get("before") or {}, change.get("after") or {}
    parts = []
    for key, unit in _CHANGE_PARAMS:
        b, a = before.get(key), after.get(key)
        if a is None or b is None or float(a) == float(b):
            continue
        parts.append(f"{key} {_short(b)}->{_short(a)}{unit}")
    return ", ".join(parts)


def applied_changes(changes) -> list:
    """The changes of a repair that were applied and alter at least one parameter."""
    return [c for c in changes if c.get("applied") and describe_change(c)]


def repair_ran(report) -> bool:
    """True when ``report`` holds the result of the repair (the analysis ran with ``repair=True``)."""
    if getattr(report, "repair_result", None) is not None:
        return True
    doc = getattr(report, "repair", None)
    return isinstance(doc, dict) and "holdout_fraction" in doc


def row_repair_text(changes: Sequence[dict], output: str) -> str:
    """The suggested repair of one row: ``u2: time_constant 45->60 s, delay 4->7 s; u3: gain 3.5->5.88``.

    A located element left as it was says why: ``u1: kept (rejected by held-out validation)``.
    """
    parts = []
    for c in changes:
        if c.get("output") != output:
            continue
        what = describe_change(c) if c.get("applied") else ""
        if what:
            parts.append(f"{c.get('input')}: {what}")
        else:
            parts.append(f"{c.get('input')}: kept ({c.get('reason') or 'no parameter differs significantly'})")
    return "; ".join(parts)


@dataclasses.dataclass(frozen=True)
class RepairVerdict:
    """The held-out validation of a repair, summed up over the rows.

    Attributes
    ----------
    verdict : str
        ``passed`` (every row with a candidate repair predicted the held-out data better),
        ``rejected`` (none did: no change suggested), ``mixed``, ``not_validated`` (changes suggested
        without held-out data), ``not_run`` (located elements but no parameter to change), ``none``
        (nothing located) or ``off`` (the analysis ran without the repair).
    detail : str
        The same in words, with the held-out RMS errors before -> after per row.
    changes : int
        Number of suggested element changes.
    """

    verdict: str
    detail: str
    changes: int


def repair_verdict(report) -> RepairVerdict:
    """The :class:`RepairVerdict` of an analysis report (its ``repair`` dict, docs/interfaces.md)."""
    if not repair_ran(report):
        return RepairVerdict("off", "the analysis ran without the repair", 0)
    doc = report.repair
    changes = list(doc.get("changes") or [])
    n_applied = len(applied_changes(changes))
    rows = list(dict.fromkeys(c.get("output") for c in changes))
    if not rows:
        return RepairVerdict("none", "no element located, nothing to repair", 0)
    hb, ha = doc.get("holdout_error_before") or {}, doc.get("holdout_error_after") or {}
    frac = doc.get("holdout_fraction") or 0.0
    n_hold = int(doc.get("samples") or 0) - int(doc.get("fit_samples") or 0)
    passed, rejected, not_run = [], [], []
    for o in rows:
        cs = [c for c in changes if c.get("output") == o]
        errors = f"{o} ({_short(hb.get(o))}->{_short(ha.get(o))})" if o in hb else o
        if any(c.get("reason") == _REJECTED for c in cs):
            rejected.append(errors)
        elif any(c.get("applied") for c in cs):
            passed.append(errors)
        else:
            not_run.append(o)
    parts = []
    if passed and not frac:
        verdict = "not_validated"
        parts.append(f"changes suggested for {', '.join(passed)} without held-out data")
    else:
        verdict = ("mixed" if passed and rejected else "passed" if passed else "rejected" if rejected else "not_run")
        if passed:
            parts.append(f"passed for {', '.join(passed)}")
        if rejected:
            parts.append(f"rejected for {', '.join(rejected)}")
    if not_run:
        parts.append(f"nothing to re-estimate for {', '.join(not_run)}")
    detail = "; ".join(parts)
    if passed or rejected:
        if frac:
            detail += (f" (held-out RMS prediction error before->after, last {100 * frac:.0f}% of the window, "
                       f"{n_hold} samples)")
    return RepairVerdict(verdict, detail, n_applied)


def repair_summary_lines(repair: dict) -> list:
    """Text lines of a repair dict (docs/interfaces.md): the changes and the errors before/after."""
    lines = []
    changes = repair.get("changes", [])
    if changes:
        lines.append("repair (gain / time constant s / delay s, re-estimated from the same data):")
        for c in changes:
            b, a = c["before"], c["after"]
            lines.append(f"  ({c['output']}, {c['input']}) {c['kind']:<13} {b['gain']:g} / {b['time_constant']:g} / "
                         f"{b['delay']:g}  ->  {a['gain']:.4g} / {a['time_constant']:.4g} / {a['delay']:g}")
    eb, ea = repair.get("error_before", {}), repair.get("error_after", {})
    if eb:
        lines.append("prediction error RMS before -> after repair: "
                     + ", ".join(f"{k} {eb[k]:.4f} -> {ea.get(k, float('nan')):.4f}" for k in eb))
    if "rsi_after" in repair:
        lines.append("row RSI of the repaired model on the same data: "
                     + ", ".join(f"{k} {v:.3f}" for k, v in repair["rsi_after"].items()))
    return lines


def repair_text(report, model, plant=None) -> str:
    """The suggested repair of an analysis report in words: changes, held-out verdict, errors before/after.

    Parameters
    ----------
    report : AnalysisReport
    model : PlantModel
        The model analysed (for the element order).
    plant : PlantModel, optional
        The true plant (a simulation), whose element values are shown next to each change.

    Returns
    -------
    str
        Lines ending with a newline.
    """
    verdict = repair_verdict(report)
    if verdict.verdict == "off":
        return "suggested repair: none (the monitor ran without the repair)\n"
    doc = report.repair
    lines = [f"suggested repair: {verdict.changes} change{'s' if verdict.changes != 1 else ''}",
             f"held-out validation: {verdict.detail or verdict.verdict.replace('_', ' ')}"]
    for ch in doc.get("changes") or []:
        what = describe_change(ch) if ch.get("applied") else ""
        conf = ch.get("confidence")
        line = f"  ({ch['output']}, {ch['input']}) {ch.get('kind', 'unknown')}: "
        line += what if what else f"kept ({ch.get('reason') or 'no parameter differs significantly'})"
        if what and conf is not None:
            line += f"  (confidence {conf:.2f})"
        if plant is not None and ch["output"] in plant.outputs and ch["input"] in plant.columns:
            true = plant.element(plant.outputs.index(ch["output"]), plant.columns.index(ch["input"]))
            line += (f"  [plant: gain {true['gain']:.3g}, time_constant {true['time_constant']:.3g} s, "
                     f"delay {true['delay']:.3g} s]")
        lines.append(line)
    eb, ea = doc.get("error_before") or {}, doc.get("error_after") or {}
    if eb:
        lines.append("prediction error RMS before -> after: "
                     + ", ".join(f"{o} {eb[o]:.4f} -> {ea.get(o, float('nan')):.4f}" for o in model.outputs if o in eb))
    rsi_after = doc.get("rsi_after") or {}
    if rsi_after:
        lines.append("RSI of the repaired model on the same window: "
                     + ", ".join(f"{o} {rsi_after[o]:.3f}" for o in model.outputs if o in rsi_after))
    return "\n".join(lines) + "\n"
