"""The repair in words: what a control engineer reads in the summary, the statuses and the demo.

Every text about a suggested repair is made here from the ``repair`` dict of an analysis report
(``changes`` with ``before``/``after`` parameters, the held-out errors), so that the command line, the
monitor's statuses and the demo say the same thing the same way: a parameter by its key
(``time_constant2 25->40 s``, ``lead 12->8 s``), a step-response element by its final value and dead
time (``step response of (y1, u2) re-estimated: final value 1.2->1.6, dead time 3->5 s``).
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

#: Element parameters of a repair change, with their unit, in the order they are named.
_CHANGE_PARAMS = (("gain", ""), ("time_constant", " s"), ("time_constant2", " s"), ("lead", " s"), ("delay", " s"))

#: ``reason`` of a change the held-out validation refused (:func:`mpm_monitor.core.repair.repair_model`).
_REJECTED = "rejected by held-out validation"


def _short(x) -> str:
    """A parameter value with three significant digits (``60.0057`` -> ``60``, ``5.8773`` -> ``5.88``)."""
    return "nan" if x is None else f"{float(x):.3g}"


def _pair(b, a) -> tuple:
    """``b`` and ``a`` as :func:`_short` words them, with as many more digits (up to six) as it takes to tell them
    apart when they differ: a gain 1.9992 -> 2.0033 read "2 -> 2", or was taken for no change at all."""
    if b is None or a is None or float(a) == float(b):
        return _short(b), _short(a)
    for digits in range(3, 7):
        bs, as_ = f"{float(b):.{digits}g}", f"{float(a):.{digits}g}"
        if bs != as_:
            return bs, as_
    return bs, as_


def _step_change(change: dict, element: bool) -> str:
    """A step-response element's change: ``step response re-estimated: final value 1.2->1.6, dead time 3->5 s``.

    The final value is the last slope (per second) on a ramp output (``change["ramp"]``); a value
    is named when it changed in its first six significant digits (with as many as tell it apart, three at
    least), and when neither did, the response's shape alone changed.
    """
    before, after = change.get("before") or {}, change.get("after") or {}
    if before.get("step_response") == after.get("step_response"):
        return ""
    final = "final slope" if change.get("ramp") else "final value"
    unit = " per s" if change.get("ramp") else ""
    parts = []
    for key, name, u in (("gain", final, unit), ("delay", "dead time", " s")):
        b, a = _pair(before.get(key), after.get(key))
        if b != a:
            parts.append(f"{name} {b}->{a}{u}")
    # The shape's change as its parametric reading says it (a time-constant change read "final value 1.2->1.18
    # (time_constant)", the lag's 12 -> 36.7 s only in the JSON's evidence).
    evidence = change.get("evidence") or {}
    p_before, p_after = evidence.get("parametric_before") or {}, evidence.get("parametric_after") or {}
    shape = []
    for key, name in (("time_constant", "time constant"), ("time_constant2", "second time constant"),
                      ("lead", "lead")):
        if key in p_before and key in p_after:
            b, a = _pair(p_before.get(key), p_after.get(key))
            if b != a:
                shape.append(f"{name} {b}->{a} s")
    if not parts:
        parts.append(f"shape only ({final} {_short(after.get('gain'))}{unit}, dead time {_short(after.get('delay'))} s)")
    if shape:
        parts.append("read as " + ", ".join(shape))
    what = f"of ({change.get('output')}, {change.get('input')}) " if element else ""
    return f"step response {what}re-estimated: " + ", ".join(parts)


def _element_words(element: dict) -> str:
    """An element in words: ``gain 4.05, time_constant 30 s, time_constant2 15 s, delay 6 s`` (a
    step-response element: ``final value 1.5, dead time 3 s``)."""
    if "step_response" in element:
        return f"final value {_short(element['gain'])}, dead time {_short(element['delay'])} s"
    return ", ".join(f"{key} {_short(element[key])}{unit}" for key, unit in _CHANGE_PARAMS if key in element)


def describe_change(change: dict, element: bool = False) -> str:
    """The parameters a repair change entry alters, in words: ``time_constant 45->60 s, delay 4->7 s``.

    Parameters
    ----------
    change : dict
        An entry of the report's ``repair["changes"]`` (``before`` and ``after`` with the element's
        keys: ``gain``, ``time_constant`` and ``delay`` in seconds, ``time_constant2`` and ``lead``
        where the element has them, or ``step_response``).
    element : bool
        Name the element in a step-response element's text (``step response of (y1, u2)
        re-estimated: final value 1.2->1.6, dead time 3->5 s``).

    Returns
    -------
    str
        "" when ``after`` equals ``before``.
    """
    before, after = change.get("before") or {}, change.get("after") or {}
    if "step_response" in after or "step_response" in before:
        return _step_change(change, element)
    parts = []
    for key, unit in _CHANGE_PARAMS:
        b, a = before.get(key), after.get(key)
        if key in ("time_constant2", "lead") and (a is not None or b is not None):
            b, a = b or 0.0, a or 0.0                        # an absent lead or second lag is 0
        if a is None or b is None or float(a) == float(b):
            continue
        parts.append("{} {}->{}{}".format(key, *_pair(b, a), unit))
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
    """The suggested repair of one row: ``u2: time_constant 45->60 s, delay 4->7 s; u3: gain 3.5->5.88``
    (``u1: lead 12->8 s``, ``u2: step response re-estimated: final value 1.2->1.6, dead time 3->5 s``).

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
    ob, oa = doc.get("holdout_one_step_error_before") or {}, doc.get("holdout_one_step_error_after") or {}
    frac = doc.get("holdout_fraction") or 0.0
    n_hold = int(doc.get("samples") or 0) - int(doc.get("fit_samples") or 0)
    passed, rejected, not_run = [], [], []
    for o in rows:
        cs = [c for c in changes if c.get("output") == o]
        errors = f"{o} ({_short(hb.get(o))}->{_short(ha.get(o))})" if o in hb else o
        if any(c.get("reason") == _REJECTED for c in cs):
            rejected.append(errors)
        elif any(c.get("applied") for c in cs):
            if o in hb and o in ob and o in oa and ha.get(o) is not None and hb[o] is not None and ha[o] >= hb[o]:
                # passed one step ahead, its simulation error not significantly larger (repair_model)
                errors = f"{errors[:-1]}; one step ahead {_short(ob[o])}->{_short(oa[o])})"
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
            if "step_response" in b:
                what = describe_change(c, element=True) or f"step response of ({c['output']}, {c['input']}) kept"
                lines.append(f"  {what} ({c['kind']})")
                continue
            line = (f"  ({c['output']}, {c['input']}) {c['kind']:<13} {b['gain']:g} / {b['time_constant']:g} / "
                    f"{b['delay']:g}  ->  {a['gain']:.4g} / {a['time_constant']:.4g} / {a['delay']:g}")
            extra = [f"{key} {b.get(key, 0.0):g} -> {a.get(key, 0.0):.4g} s" for key in ("time_constant2", "lead")
                     if key in b or key in a]
            if b.get("integrating"):
                extra.append("integrating: gain per second")
            lines.append(line + (f"  ({'; '.join(extra)})" if extra else ""))
    eb, ea = repair.get("error_before", {}), repair.get("error_after", {})

    def rms(v) -> str:          # null in the JSON (not finite) is "n/a"
        return "n/a" if v is None else f"{v:.4f}"

    if eb and not changes and all(ea.get(k) == v for k, v in eb.items()):     # --no-repair, or nothing to repair
        lines.append("prediction error RMS (nothing repaired): " + ", ".join(f"{k} {rms(eb[k])}" for k in eb))
    elif eb:
        lines.append("prediction error RMS before -> after repair: "
                     + ", ".join(f"{k} {rms(eb[k])} -> {rms(ea.get(k))}" for k in eb))
    if "rsi_after" in repair:
        lines.append("row RSI of the repaired model on the same data: "
                     + ", ".join(f"{k} {v:.3f}" for k, v in repair["rsi_after"].items()))
    if repair.get("second_round"):
        lines.append("repaired again with the elements the first repair's detection located: "
                     + ", ".join(f"({x['output']}, {x['input']})" for x in repair["second_round"]))
    if repair.get("located_after"):
        lines.append("elements the repaired model's detection locates: "
                     + ", ".join(f"({x['output']}, {x['input']})" for x in repair["located_after"]))
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
            line += f"  [plant: {_element_words(true)}]"
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
