"""Figures of an analysis report (matplotlib, Agg backend, PNG).

- :func:`plot_sdelta` -- the overall and per-row singular values of the identified ``S_Delta(omega)``
  with the identity line (paper, Figs. 3 to 5): a row without mismatch stays at 1 over the band.
- :func:`plot_element_map` -- the located elements as a picture of the transfer matrix.
- :func:`plot_detectability_map` -- the detectable gain change of every tested element, the same
  picture.
- :func:`plot_step_responses` -- for each located element, the step response of the model's
  element and of the repaired element (and of the repair's estimate where it was not applied),
  each from the element's own sampled form, whatever its structure.
- :func:`plot_residuals` -- the prediction error ``d = y - Phat u`` per output with the model as
  given and as repaired.

Each function writes one PNG and returns its path (or None when there is nothing to draw).  They
read an :class:`~mpm_monitor.core.analysis.AnalysisReport` through the attributes listed in
``docs/DESIGN.md`` only, so any object with those attributes will do.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.analysis_report import detectable_text
from ..core.model import PlantModel

#: Largest number of points drawn per time-series curve (longer records are decimated for drawing).
MAX_POINTS = 20_000
#: Figure resolution, dots per inch.
DPI = 100

_COLORS = {"located": "#d62728", "ambiguous": "#ff7f0e", "clean": "#2ca02c", "untested": "#d9d9d9"}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    _pyplot().close(fig)
    return path


# ----------------------------------------------------------------------------------------------------
# S_Delta singular values (paper Figs. 3-5)


def plot_sdelta(report, path, title: str = "") -> Path:
    """Overall and per-row singular values of ``S_Delta(omega)`` with the identity line.

    Parameters
    ----------
    report : AnalysisReport
        Uses ``frequencies`` (rad/sample, shape (n_freq,)), ``sigma_max`` (n_freq,), ``row_gains``
        (n_outputs, n_freq) and ``rows`` (``output``, ``rsi``, ``mismatch``).
    path : str or Path
        PNG file to write.
    title : str

    Returns
    -------
    Path
    """
    plt = _pyplot()
    w = np.asarray(report.frequencies, dtype=float)
    keep = w > 0  # log axis: the point at omega = 0 cannot be drawn
    w = w[keep]
    gains = np.atleast_2d(np.asarray(report.row_gains, dtype=float))[:, keep]
    sigma = np.asarray(report.sigma_max, dtype=float)[keep]
    panels = [("overall (largest singular value)", sigma, float(np.max(sigma, initial=1.0)), None)]
    panels += [(f"row {row.output}", gains[k], float(row.rsi), bool(row.mismatch))
               for k, row in enumerate(report.rows)]
    ncol = min(len(panels), 4)
    nrow = int(np.ceil(len(panels) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.3 * ncol, 2.9 * nrow), sharey=True, squeeze=False)
    top = max(1.5, 1.1 * max(float(np.nanmax(g)) if g.size and np.isfinite(g).any() else 1.0 for _, g, _, _ in panels))
    for ax, (name, g, rsi, flagged) in zip(axes.flat, panels):
        color = "C0" if flagged is None else (_COLORS["located"] if flagged else _COLORS["clean"])
        ax.semilogx(w, g, color=color, lw=1.6, label="identified S_Delta")
        ax.axhline(1.0, color="k", ls="--", lw=0.9, label="identity (no mismatch)")
        verdict = "" if flagged is None else (": MISMATCH" if flagged else ": no mismatch")
        ax.set_title(f"{name}{verdict}\nRSI {rsi:.3f}", fontsize=9)
        ax.set_xlabel("frequency (rad/sample)", fontsize=8)
        ax.set_ylim(0.0, top)
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=8)
    for ax in axes.flat[len(panels):]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("singular value", fontsize=8)
    axes.flat[0].legend(fontsize=7, loc="lower left")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------
# Located elements as a matrix picture


def format_p_value(p) -> str:
    """``p=3.2e-04``; values below double precision's resolution as ``p<1e-16``."""
    return "p<1e-16" if p < 1e-16 else f"p={p:.1e}"


def element_states(report, model: PlantModel) -> np.ndarray:
    """State of every element as a string array of shape (n_outputs, n_columns) (inputs, then measured disturbances).

    ``located`` (mismatch located), ``ambiguous`` (cannot be told apart from another input),
    ``clean`` (tested, no mismatch) or ``untested`` (its row was not flagged, so not tested).
    """
    states = np.full((model.n_outputs, model.n_columns), "untested", dtype=object)
    for e in report.elements:
        i, j = model.outputs.index(e.output), model.columns.index(e.input)
        states[i, j] = "located" if e.mismatch else ("ambiguous" if getattr(e, "ambiguous", False) else "clean")
    return states


def _matrix_axes(ax, model: PlantModel, row_labels: list, title: str) -> None:
    """Ticks, cell grid and title of a transfer-matrix picture (columns on top, one cell per element)."""
    ny, nu = model.n_outputs, model.n_columns
    ax.set_xticks(range(nu), [c if model.role(j) == "input" else f"{c}\n(disturbance)"
                              for j, c in enumerate(model.columns)])
    ax.set_yticks(range(ny), row_labels)
    ax.set_xticks(np.arange(-0.5, nu), minor=True)
    ax.set_yticks(np.arange(-0.5, ny), minor=True)
    ax.grid(which="minor", color="white", lw=2)
    ax.tick_params(which="minor", length=0)
    ax.xaxis.tick_top()
    ax.set_title(title, fontsize=10, pad=22)


def plot_element_map(report, model: PlantModel, path) -> Path:
    """The transfer matrix with each element coloured by its verdict and labelled with its kind.

    Parameters
    ----------
    report : AnalysisReport
        Uses ``rows`` and ``elements`` (``output``, ``input``, ``mismatch``, ``p_value``, ``kind``,
        ``ambiguous``).
    model : PlantModel
    path : str or Path

    Returns
    -------
    Path
    """
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    plt = _pyplot()
    ny, nu = model.n_outputs, model.n_columns
    states = element_states(report, model)
    rgb = np.array([[to_rgb(_COLORS[s]) for s in row] for row in states])
    fig, ax = plt.subplots(figsize=(1.2 * nu + 2.6, 0.9 * ny + 1.6))
    ax.imshow(rgb, aspect="auto")
    by_key = {(e.output, e.input): e for e in report.elements}
    for i, out in enumerate(model.outputs):
        for j, inp in enumerate(model.columns):
            e = by_key.get((out, inp))
            lines = []
            if e is not None and e.mismatch:
                lines.append(str(e.kind or "located").replace("_", " "))
            elif states[i, j] == "ambiguous":
                lines.append("ambiguous")
            if e is not None and e.p_value is not None and states[i, j] != "untested":
                lines.append(format_p_value(e.p_value))
            ax.text(j, i, "\n".join(lines), ha="center", va="center", fontsize=7)
    rsi = {r.output: r for r in report.rows}
    _matrix_axes(ax, model, [f"{o}  (RSI {rsi[o].rsi:.2f}{', flagged' if rsi[o].mismatch else ''})"
                             if o in rsi else o for o in model.outputs], "model elements: located mismatch")
    handles = [Patch(color=_COLORS[k], label=label) for k, label in
               (("located", "mismatch located"), ("ambiguous", "ambiguous (inputs move together)"),
                ("clean", "tested, no mismatch"), ("untested", "row not flagged"))]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=2, fontsize=7, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------
# Detectability as a matrix picture

#: Classes of the detectable gain change: (upper bound, colour, legend label).
DETECTABILITY_CLASSES = ((0.2, "#1a9850", "detects 20% or less"), (0.5, "#fee08b", "20-50%"),
                         (1.0, "#fc8d59", "50-100%"), (math.inf, "#d73027", "above 100%"))


def detectability_class(x) -> Optional[int]:
    """Index into :data:`DETECTABILITY_CLASSES` of a detectable gain change (None: not computed)."""
    if x is None or not math.isfinite(x):
        return None
    return next(k for k, (bound, _, _) in enumerate(DETECTABILITY_CLASSES) if x <= bound)


def plot_detectability_map(report, model: PlantModel, path) -> Optional[Path]:
    """The transfer matrix with each tested element coloured by its ``detectable_gain_change``.

    The smallest relative gain error of the element the window detects with probability 0.9, in
    classes (:data:`DETECTABILITY_CLASSES`); ambiguous elements say so; an element whose value could
    not be computed is grey (``n/a``), an element not tested light grey.

    Parameters
    ----------
    report : AnalysisReport
        Uses ``elements`` (``output``, ``input``, ``detectable_gain_change``, ``mismatch``,
        ``ambiguous``) and ``rows``.
    model : PlantModel
    path : str or Path

    Returns
    -------
    Path or None
        None when no element was tested.
    """
    from matplotlib.colors import to_rgb
    from matplotlib.patches import Patch

    if not report.elements:
        return None
    plt = _pyplot()
    ny, nu = model.n_outputs, model.n_columns
    by_key = {(e.output, e.input): e for e in report.elements}
    rgb = np.empty((ny, nu, 3))
    fig, ax = plt.subplots(figsize=(1.2 * nu + 2.6, 0.9 * ny + 1.8))
    for i, out in enumerate(model.outputs):
        for j, col in enumerate(model.columns):
            e = by_key.get((out, col))
            x = None if e is None else getattr(e, "detectable_gain_change", None)
            k = detectability_class(x)
            rgb[i, j] = to_rgb(_COLORS["untested"] if e is None else ("#969696" if k is None
                                                                        else DETECTABILITY_CLASSES[k][1]))
            if e is None:
                continue
            lines = [detectable_text(x)]
            if e.mismatch:
                lines.append("located")
            elif getattr(e, "ambiguous", False):
                lines.append("ambiguous")
            ax.text(j, i, "\n".join(lines), ha="center", va="center", fontsize=7)
    ax.imshow(rgb, aspect="auto")
    _matrix_axes(ax, model, list(model.outputs), "detectable gain change (90% probability)")
    handles = [Patch(color=c, label=label) for _, c, label in DETECTABILITY_CLASSES]
    handles += [Patch(color="#969696", label="not computable"), Patch(color=_COLORS["untested"], label="not tested")]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=3, fontsize=7, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------
# Step responses


def element_step(model: PlantModel, i: int, j: int, n: int) -> np.ndarray:
    """Unit-step response of element (i, j) (column ``j``: an input or a measured disturbance), samples ``0 .. n-1``.

    ``y(k)`` answers a unit step of column ``j`` applied from sample 0 (so ``y(0) = 0`` unless the
    element feeds through: the output depends on inputs up to ``k - 1``, see docs/DESIGN.md), from
    the element's own sampled form (:meth:`PlantModel.discrete_element`), whatever its structure: an
    integrating element's step response is a ramp, a step-response element's its coefficients.
    """
    return model.discrete_element(i, j).step_response(n)


def _step_horizon(models, pairs) -> int:
    """Samples drawn: the longest delay plus five lags (both lags of a second-order element), or the
    length of a step response, over the elements drawn; at least 20, at most 5000."""
    longest = 0.0
    for m in models:
        for i, j in pairs:
            if m.is_step_response:
                longest = max(longest, (m.step_length + 5) * m.sample_time)
            else:
                longest = max(longest, m.delay[i, j] + 5.0 * (m.time_constant[i, j] + m.time_constant2[i, j]))
    ts = models[0].sample_time
    return int(min(max(20, np.ceil(longest / ts) + 5), 5000))


def _with_element(model: PlantModel, i: int, j: int, element: dict) -> PlantModel:
    """``model`` with element (i, j) as a report's ``changes`` entry gives it (:meth:`PlantModel.element` keys)."""
    if "step_response" in element:
        return model.with_element(i, j, step_response=element["step_response"])
    return model.with_element(i, j, gain=element["gain"], time_constant=element["time_constant"],
                              delay=element["delay"], lead=element.get("lead", 0.0),
                              time_constant2=element.get("time_constant2", 0.0),
                              integrating=bool(element.get("integrating", False)))


def step_curves(report, model: PlantModel, i: int, j: int, n: int) -> dict:
    """The step responses drawn for element (i, j): ``{label: ndarray of shape (n,)}``.

    ``model`` (as given) and ``repaired model``, and where the repair re-estimated the element but
    did not apply the estimate (the held-out validation rejected it, or no parameter differed
    significantly), ``re-estimated (not applied)``.  Every curve is a model's element sampled as the
    model samples it; nothing is drawn that the repair does not stand behind.
    """
    repaired = getattr(report, "repaired_model", None) or model
    curves = {"model": element_step(model, i, j, n), "repaired model": element_step(repaired, i, j, n)}
    repair = getattr(report, "repair", None) or {}
    for c in repair.get("changes") or ():
        if (c.get("output"), c.get("input")) != (model.outputs[i], model.columns[j]):
            continue
        if not c.get("applied") and c.get("estimate"):
            try:
                curves["re-estimated (not applied)"] = element_step(_with_element(model, i, j, c["estimate"]), i, j, n)
            except (KeyError, ValueError):
                pass        # an estimate the model cannot hold is not drawn
    return curves


_CURVE_STYLE = {"model": dict(color="k", lw=1.4),
                "repaired model": dict(color=_COLORS["clean"], lw=1.4, ls="--"),
                "re-estimated (not applied)": dict(color=_COLORS["ambiguous"], lw=1.0, ls=":")}


def plot_step_responses(report, model: PlantModel, path) -> Optional[Path]:
    """Step responses of every located element: the model's and the repaired model's (:func:`step_curves`).

    Parameters
    ----------
    report : AnalysisReport
        Uses ``elements``, ``repaired_model`` and ``repair`` (its ``changes``).
    model : PlantModel
    path : str or Path

    Returns
    -------
    Path or None
        None when no element is located.
    """
    pairs = [(model.outputs.index(e.output), model.columns.index(e.input)) for e in report.elements if e.mismatch]
    if not pairs:
        return None
    plt = _pyplot()
    repaired = getattr(report, "repaired_model", None) or model
    n = _step_horizon([model, repaired], pairs)
    t = np.arange(n) * model.sample_time
    ncol = min(len(pairs), 3)
    nrow = int(np.ceil(len(pairs) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.6 * ncol, 2.9 * nrow), squeeze=False)
    for ax, (i, j) in zip(axes.flat, pairs):
        for label, y in step_curves(report, model, i, j, n).items():
            ax.step(t, y, where="post", label=label, **_CURVE_STYLE[label])
        role = " (measured disturbance)" if model.role(j) == "disturbance" else ""
        ax.set_title(f"({model.outputs[i]}, {model.columns[j]}){role}", fontsize=9)
        ax.set_xlabel("time (s)", fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=8)
        ax.legend(fontsize=7)
    for ax in axes.flat[len(pairs):]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("unit-step response", fontsize=8)
    fig.suptitle("located elements: step responses", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------
# Residuals


def prediction_errors(model: PlantModel, data, initial_state: str = "estimate", max_gap: Optional[int] = None) -> np.ndarray:
    """``d = y - Phat [u | dv]`` of shape (n_samples, n_outputs) (:func:`~mpm_monitor.core.signals.compute_signals`).

    On data with gaps, as the analysis runs the model (:func:`~mpm_monitor.core.signals.segment_signals`): through
    a gap of at most ``max_gap`` samples, restarted after a longer one (``max_gap`` None: after every gap), never
    as if the rows on either side of a gap were consecutive samples.
    """
    from ..core.logged_data import in_deviations
    from ..core.signals import compute_signals, segment_signals

    data = in_deviations(model, data)
    dv = getattr(data, "dv", None) if model.n_disturbances else None
    segments = data.segments
    if len(segments) > 1:
        grid = {} if max_gap is None else {"grid": data.grid_index, "max_gap": int(max_gap),
                                           "fill": data.fill_on_grid()}
        return segment_signals(model, data.r, data.u, data.y, segments, initial_state, dv=dv, **grid).d
    return compute_signals(model, data.r, data.u, data.y, initial_state=initial_state, dv=dv).d


def _broken_at_gaps(t: np.ndarray, d: np.ndarray, segments: list, stride: int) -> tuple:
    """``(t, d)`` every ``stride``-th sample of each segment, a NaN between segments: a line plot is not drawn
    across a gap (it would look like values where none were logged)."""
    if len(segments) <= 1:
        return t[::stride], d[::stride]
    ts, ds = [], []
    for a, b in segments:
        ts += [t[a:b:stride], [np.nan]]
        ds += [d[a:b:stride], np.full((1,) + d.shape[1:], np.nan)]
    return np.concatenate(ts[:-1]), np.concatenate(ds[:-1])


def plot_residuals(model: PlantModel, repaired: Optional[PlantModel], data, path,
                   initial_state: str = "estimate", max_gap: Optional[int] = None) -> Path:
    """Prediction error per output with the model as given and (if any) as repaired.

    Parameters
    ----------
    model : PlantModel
    repaired : PlantModel or None
        None or equal to ``model``: only the "before" curve is drawn.
    data : LoggedData
    path : str or Path
    initial_state : {"estimate", "zero"}
    max_gap : int, optional
        Data with gaps: the longest gap the model runs through (the analysis's, ``report.gaps["max_gap"]``);
        the lines break at every gap.

    Returns
    -------
    Path
    """
    plt = _pyplot()
    before = prediction_errors(model, data, initial_state, max_gap)
    after = prediction_errors(repaired, data, initial_state, max_gap) \
        if repaired is not None and repaired != model else None
    t = np.asarray(data.t, dtype=float)
    stride = max(1, int(np.ceil(t.size / MAX_POINTS)))
    segments = data.segments
    ny = model.n_outputs
    fig, axes = plt.subplots(ny, 1, figsize=(9.0, 1.9 * ny + 0.6), sharex=True, squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        rms_b = float(np.sqrt(np.mean(before[:, k] ** 2)))
        ax.plot(*_broken_at_gaps(t, before[:, k], segments, stride), color=_COLORS["located"], lw=0.7,
                label=f"model as given (RMS {rms_b:.4g})")
        if after is not None:
            rms_a = float(np.sqrt(np.mean(after[:, k] ** 2)))
            ax.plot(*_broken_at_gaps(t, after[:, k], segments, stride), color=_COLORS["clean"], lw=0.7, alpha=0.9,
                    label=f"repaired model (RMS {rms_a:.4g})")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_ylabel(f"d of {model.outputs[k]}", fontsize=8)
        ax.legend(fontsize=7, loc="upper right")
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=8)
    axes[-1, 0].set_xlabel("time (s)", fontsize=8)
    fig.suptitle("prediction error d = y - model output, before and after repair", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)
