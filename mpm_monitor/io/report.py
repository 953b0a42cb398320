"""The analysis report a control engineer reads: one self-contained HTML file plus its figures.

:func:`write_report` writes into a directory

- ``report.html`` -- self-contained (figures embedded as base64 PNG): what was analysed, the row
  test (RSI per output), the located elements, the repair (parameters before and after, prediction
  error before and after) and the warnings, with the figures of :mod:`mpm_monitor.io.plots`;
- the same figures as PNG files (``sdelta.png``, ``elements.png``, ``steps.png``,
  ``residuals.png``) for slides and tickets.

It reads the :class:`~mpm_monitor.core.analysis.AnalysisReport` attributes listed in docs/DESIGN.md:
``rows``, ``elements``, ``frequencies``, ``row_gains``, ``sigma_max``, ``repair``,
``repaired_model``, ``warnings`` (and ``overall_rsi``, ``arx_tables``, ``candidates`` when present).
"""

from __future__ import annotations

import base64
import datetime
import html
import math
from pathlib import Path

from ..core.errors import InputError
from ..core.model import PlantModel
from . import plots

REPORT_FILE = "report.html"
#: The figures :func:`write_report` writes beside it (or removes, stale, where this report has none of them).
REPORT_FIGURES = ("sdelta.png", "elements.png", "detectability.png", "steps.png", "residuals.png")
#: Every file a report writes into its directory.
REPORT_FILES = (REPORT_FILE,) + REPORT_FIGURES

_CSS = """
body { font-family: sans-serif; margin: 2em auto; max-width: 70em; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #f2f2f2; } td.name { text-align: left; }
tr.flag td { background: #fde0dc; } tr.amb td { background: #fff0d9; }
.warn { background: #fff6d6; border-left: 4px solid #e0a800; padding: 0.4em 0.8em; margin: 0.3em 0; }
.ok { color: #2a7d2a; } .bad { color: #b22222; font-weight: bold; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { font-size: 0.85em; color: #555; }
"""


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _num(x, fmt: str = ".4g") -> str:
    if x is None:
        return "&ndash;"
    try:
        v = float(x)
    except (TypeError, ValueError):
        return _e(x)
    return "&ndash;" if not math.isfinite(v) else format(v, fmt)


def _p(x) -> str:
    if x is None or not math.isfinite(float(x)):
        return "&ndash;"
    return "&lt;1e-16" if float(x) < 1e-16 else format(float(x), ".2e")


def _figure(path: Path, caption: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return (f'<figure><img alt="{_e(caption)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{_e(caption)} (also <code>{_e(path.name)}</code>)</figcaption></figure>")


def _table(headers, rows, classes=None) -> str:
    out = ["<table><tr>" + "".join(f"<th>{h}</th>" for h in headers) + "</tr>"]
    for k, row in enumerate(rows):
        cls = f' class="{classes[k]}"' if classes and classes[k] else ""
        cells = "".join(f'<td class="name">{c}</td>' if n == 0 else f"<td>{c}</td>" for n, c in enumerate(row))
        out.append(f"<tr{cls}>{cells}</tr>")
    out.append("</table>")
    return "\n".join(out)


def _params(p, ramp: bool = False) -> str:
    """An element of a ``changes`` entry in a table cell: ``K 4.05, tau 30 s, tau2 15 s, lead 12 s,
    theta 6 s`` (``K`` per second for an integrating element), or a step response's length, final
    value (its final slope per second on a ramp output, ``ramp``) and dead time."""
    if not isinstance(p, dict):
        return "&ndash;"
    if "step_response" in p:
        final = f"final slope {_num(p.get('gain'))} per s" if ramp else f"final value {_num(p.get('gain'))}"
        return f"step response of {len(p['step_response'])} samples: {final}, dead time {_num(p.get('delay'))} s"
    text = f"K {_num(p.get('gain'))}{' per s (integrating)' if p.get('integrating') else ''}, "
    text += f"&tau; {_num(p.get('time_constant'))} s"
    if "time_constant2" in p:
        text += f", &tau;<sub>2</sub> {_num(p.get('time_constant2'))} s"
    if "lead" in p:
        text += f", lead {_num(p.get('lead'))} s"
    return text + f", &theta; {_num(p.get('delay'))} s"


def _rows_section(report) -> str:
    rows, classes = [], []
    for r in report.rows:
        rows.append([_e(r.output), _num(r.rsi, ".3f"), _p(r.p_value),
                     '<span class="bad">mismatch</span>' if r.mismatch else '<span class="ok">no mismatch</span>'])
        classes.append("flag" if r.mismatch else "")
    overall = getattr(report, "overall_rsi", None)
    lead = (f"<p>Overall RSI (largest singular value of S<sub>&Delta;</sub> over the band): "
            f"<b>{_num(overall, '.3f')}</b>. A row whose S<sub>&Delta;</sub> stays at the identity (RSI near 1) "
            f"has no model-plant mismatch; the decision is the row test's p-value.</p>") if overall is not None else ""
    return lead + _table(["output", "RSI", "p-value", "row test"], rows, classes)


def _elements_section(report) -> str:
    located = [e for e in report.elements if e.mismatch]
    ambiguous = [e for e in report.elements if getattr(e, "ambiguous", False)]
    if not report.elements:
        return "<p>No element was tested (no row flagged).</p>"
    if not located and not ambiguous:
        return "<p>No element located: every tested element is consistent with the model.</p>"
    rows, classes = [], []
    for e in located + [e for e in ambiguous if not e.mismatch]:
        with_ = ", ".join(getattr(e, "ambiguous_with", ()) or ())
        label = f"{e.input} (candidate)" if getattr(e, "role", "input") == "candidate" else e.input
        rows.append([_e(f"({e.output}, {label})"),
                     _e(e.kind or "") if e.mismatch else "ambiguous" + (f" with {_e(with_)}" if with_ else ""),
                     _p(e.p_value), _num(getattr(e, "delay", None), ".0f")])
        classes.append("flag" if e.mismatch else "amb")
    return _table(["element (output, input)", "kind", "p-value", "delay of &Delta; (samples)"], rows, classes)


def _detectability_section(report) -> str:
    values = [e for e in report.elements if getattr(e, "detectable_gain_change", None) is not None
              and math.isfinite(e.detectable_gain_change)]
    parts = []
    if values:
        best = min(values, key=lambda e: e.detectable_gain_change)
        worst = max(values, key=lambda e: e.detectable_gain_change)
        parts.append(f"<p>Each tested element's <i>detectable gain change</i> is the smallest relative error of its "
                     f"gain (|&Delta;K| / |K|) this window would detect with probability 0.9 at the analysis's "
                     f"false-alarm rate, from the data's own noise and excitation. Here it ranges from "
                     f"{_num(100 * best.detectable_gain_change, '.0f')}% ({_e(best.output)}, {_e(best.input)}) to "
                     f"{_num(100 * worst.detectable_gain_change, '.0f')}% ({_e(worst.output)}, {_e(worst.input)}). "
                     f"An element without a located mismatch may still be off by less than its value.</p>")
    elif report.elements:
        parts.append("<p>The detectable gain change could not be computed for these elements (see the warnings).</p>")
    else:
        parts.append("<p>No element was tested, so no detectable gain change.</p>")
    exp = getattr(report, "experiment", None)
    if exp is None:
        parts.append("<p>No experiment recommended.</p>")
    else:
        rows = [[_e(k), _num(v)] for k, v in exp.dither.items()]
        parts.append(f"<p><b>Recommended experiment:</b> a PRBS dither (&plusmn;amplitude, switching with probability "
                     f"1/2 every sample) added to these inputs for <b>{int(exp.samples)}</b> samples; expected "
                     f"detectable gain change afterwards {_num(exp.expected_detectable_gain_change, '.2f')}.</p>")
        parts.append(_table(["input", "amplitude (input units)"], rows))
        parts.append(f"<p>{_e(exp.why)}</p>")
    return "\n".join(parts)


def _repair_section(report) -> str:
    rep = report.repair or {}
    parts = []
    changes = rep.get("changes") or []
    if changes:
        rows = []
        for c in changes:
            applied, ramp = c.get("applied", True), bool(c.get("ramp"))
            rows.append([_e(f"({c.get('output')}, {c.get('input')})"), _e(c.get("kind", "")),
                         _params(c.get("before"), ramp), _params(c.get("after"), ramp),
                         _num(c.get("confidence"), ".2f"), "yes" if applied else "no"])
        parts.append(_table(["element", "kind", "model as given", "repaired", "confidence", "applied"], rows))
    else:
        parts.append("<p>No element was changed.</p>")
    eb, ea = rep.get("error_before") or {}, rep.get("error_after") or {}
    if eb:
        rows = []
        for out, before in eb.items():
            after = ea.get(out)
            ratio = (after / before) if (after is not None and before) else None
            rows.append([_e(out), _num(before), _num(after), _num(ratio, ".3f")])
        parts.append("<p>Root-mean-square one-step prediction error d = y &minus; &#375; per output:</p>")
        parts.append(_table(["output", "model as given", "repaired", "ratio"], rows))
    return "\n".join(parts)


def _explained_candidates(report) -> dict:
    """Candidate -> the elements that explain it, for a candidate whose test rejected in a row but that the row's
    other located elements explain (released, ``explained_by``)."""
    explained: dict = {}
    for e in getattr(report, "elements", ()):
        if getattr(e, "role", "") == "candidate":
            names = explained.setdefault(e.input, [])
            names += [x for x in (getattr(e, "explained_by", None) or ()) if x not in names]
    return {k: v for k, v in explained.items() if v}


def _unlocated_candidates(report) -> dict:
    """Candidate -> the ``na`` with which the element test no longer locates it, for a candidate located in a row
    the S_Delta row test does not flag and released (``unlocated_at_na``)."""
    return {e.input: e.unlocated_at_na for e in getattr(report, "elements", ())
            if getattr(e, "role", "") == "candidate" and getattr(e, "unlocated_at_na", None) is not None}


def _candidates_section(report, explained: dict, unlocated: dict) -> str:
    """Which channels were tried, the p-value of each in each row, which were unusable or not
    exogenous, which were explained by the row's located elements (``explained``:
    :func:`_explained_candidates` of the report as analysed; such a channel read "no effect found" beside its
    p-value below 1e-16) or released by the test with more own lags (``unlocated``: :func:`_unlocated_candidates`
    of the report as analysed), and which were added to the repaired model."""
    cands = report.candidates
    if not cands.tried:
        return "<p>No candidate channel was given.</p>"
    outputs = [r.output for r in report.rows]
    located = set(cands.located)
    rows, classes = [], []
    for name in cands.tried:
        if name in cands.p_values:
            ps = cands.p_values[name]
            verdict = "added to the model" if name in cands.added else (
                "located, not added (see the warnings)" if any(c == name for _, c in located) else
                f"flagged, explained by {', '.join(explained[name])} (see the warnings)" if name in explained else
                f"flagged, not with na = {unlocated[name]} own lags (see the warnings)" if name in unlocated else
                "no effect found")
            rows.append([_e(name)] + [_p(ps.get(o)) for o in outputs] + [_e(verdict)])
            classes.append("flag" if any(c == name for _, c in located) else "")
        else:
            why = cands.not_exogenous.get(name) or f"unusable: {cands.unusable.get(name, '')}"
            rows.append([_e(name)] + ["&ndash;"] * len(outputs) + [_e(why)])
            classes.append("amb")
    lead = ("<p>Logged channels the model does not use, tested as causes of each output's prediction error "
            "jointly with the model's columns (p-values adjusted in the element tests' family). A channel that "
            "moves with the inputs is an effect of the loop and is not tested; a located one is added to the "
            "repaired model as a measured disturbance when it predicts the held-out data better.</p>")
    added = f"<p>Added: <b>{_e(', '.join(cands.added))}</b>.</p>" if cands.added else "<p>Added: none.</p>"
    return lead + _table(["channel"] + [f"p-value {_e(o)}" for o in outputs] + ["verdict"], rows, classes) + added


def _plotted(model: PlantModel, data, report):
    """The model, data and report the figures read: with the located candidates as measured disturbance
    columns (the added ones first, as in the repaired model), so that every located element has a column."""
    import dataclasses

    cands = getattr(report, "candidates", None)
    if cands is None:
        return model, data, report
    if not cands.located:
        elements = [e for e in report.elements if getattr(e, "role", "input") != "candidate"]
        return model, data, dataclasses.replace(report, elements=elements)

    from ..core.candidates import with_candidate_columns

    names = list(cands.added) + [n for n in dict.fromkeys(c for _, c in cands.located) if n not in cands.added]
    wide, wide_data = with_candidate_columns(model, data, names)
    repaired = getattr(report, "repaired_model", None) or model
    repaired, _ = with_candidate_columns(repaired, data, [n for n in names if n not in cands.added])
    elements = [e for e in report.elements if getattr(e, "role", "input") != "candidate" or e.input in names]
    return wide, wide_data, dataclasses.replace(report, repaired_model=repaired, elements=elements)


def _warnings_section(report) -> str:
    if not report.warnings:
        return "<p>None.</p>"
    return "\n".join(f'<div class="warn">{_e(w)}</div>' for w in report.warnings)


def _remove_stale(path: Path) -> None:
    """Remove a figure an earlier report wrote into the same directory and this one has none of (so a
    reused directory never shows, say, the step responses of elements this analysis did not locate)."""
    path.unlink(missing_ok=True)


def write_report(directory, model: PlantModel, data, report) -> Path:
    """Write the HTML report and its figures into ``directory`` (created if needed).

    Parameters
    ----------
    directory : str or Path
    model : PlantModel
        The controller's model as given.
    data : LoggedData
        The analysed samples (for the residual plot).
    report : AnalysisReport

    Returns
    -------
    Path
        The HTML file.

    Raises
    ------
    InputError
        The directory cannot be created or written.
    """
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"{directory}: cannot create report directory: {exc.strerror or exc}") from None
    model_as_given = model
    explained, unlocated = _explained_candidates(report), _unlocated_candidates(report)
    model, data, report = _plotted(model, data, report)
    repaired = getattr(report, "repaired_model", None)
    try:
        figs = [(plots.plot_sdelta(report, directory / "sdelta.png", title="S_Delta singular values"),
                 "Overall and per-row singular values of the identified S_Delta with the identity line "
                 "(paper Figs. 3-5): a row without mismatch stays at 1.")]
        figs.append((plots.plot_element_map(report, model, directory / "elements.png"),
                     "Model elements coloured by the element test's verdict."))
        detect_map = plots.plot_detectability_map(report, model, directory / "detectability.png")
        if detect_map is None:
            _remove_stale(directory / "detectability.png")
        else:
            figs.append((detect_map, "Detectable gain change of every tested element: the smallest relative gain "
                                      "error this window detects with probability 0.9 at the analysis's alpha."))
        steps = plots.plot_step_responses(report, model, directory / "steps.png")
        if steps is None:
            _remove_stale(directory / "steps.png")
        else:
            figs.append((steps, "Unit-step responses of each located element, each from the element's own "
                                "sampled form: model as given, repaired model (and the repair's estimate where it "
                                "was not applied)."))
        max_gap = report.gaps.get("max_gap") if getattr(report, "gaps", None) else None
        figs.append((plots.plot_residuals(model, repaired, data, directory / "residuals.png", max_gap=max_gap),
                     "Prediction error d = y - model output per output, with the model as given and as repaired."))
    except OSError as exc:
        raise InputError(f"{directory}: cannot write figures: {exc.strerror or exc}") from None
    fig_html = {p.stem: _figure(p, cap) for p, cap in figs}
    source = getattr(data, "source", "") or "data"
    n = getattr(data, "n_samples", None)
    n = n if n is not None else len(data.t)
    model = model_as_given
    title = f"Model-plant mismatch report: {model.name}" if model.name else "Model-plant mismatch report"
    flagged = [r.output for r in report.rows if r.mismatch]
    located = [f"({e.output}, {e.input})" for e in report.elements if e.mismatch]
    verdict = ("No model-plant mismatch found." if not flagged else
               f"Mismatch in row{'s' if len(flagged) > 1 else ''} {', '.join(flagged)}; "
               f"located element{'s' if len(located) != 1 else ''}: {', '.join(located) or 'none'}.")
    columns = f"{model.n_inputs} inputs ({_e(', '.join(model.inputs))})"
    if model.n_disturbances:
        columns += (f" and {model.n_disturbances} measured disturbance{'s' if model.n_disturbances > 1 else ''} "
                    f"({_e(', '.join(model.disturbances))})")
    body = [
        f"<h1>{_e(title)}</h1>",
        f"<p><b>{_e(verdict)}</b></p>",
        f"<p>Data: <code>{_e(source)}</code>, {n} samples at {_num(model.sample_time)} s "
        f"({_num(n * model.sample_time)} s); model: {model.n_outputs} outputs "
        f"({_e(', '.join(model.outputs))}) &times; {columns}. "
        f"Written {_e(datetime.datetime.now().isoformat(timespec='seconds'))}.</p>",
        "<h2>Warnings</h2>", _warnings_section(report),
        "<h2>Row test: S<sub>&Delta;</sub></h2>", _rows_section(report), fig_html.get("sdelta", ""),
        "<h2>Element test: located mismatch</h2>", _elements_section(report), fig_html.get("elements", ""),
        fig_html.get("steps", ""),
        "<h2>Detectability and experiment</h2>", _detectability_section(report), fig_html.get("detectability", ""),
    ]
    if getattr(report, "candidates", None) is not None:
        body += ["<h2>Candidate channels</h2>", _candidates_section(report, explained, unlocated)]
    body += [
        "<h2>Repair</h2>", _repair_section(report), fig_html.get("residuals", ""),
    ]
    doc = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{_e(title)}</title>'
           f"<style>{_CSS}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
    out = directory / REPORT_FILE
    try:
        out.write_text(doc, encoding="utf-8")
    except OSError as exc:
        raise InputError(f"{out}: cannot write report: {exc.strerror or exc}") from None
    return out
