"""Figures of an analysis report (matplotlib, Agg backend, PNG).

- :func:`plot_sdelta` -- the overall and per-row singular values of the identified ``S_Delta(omega)``
  with the identity line (paper, Figs. 3 to 5): a row without mismatch stays at 1 over the band.
- :func:`plot_element_map` -- the located elements as a picture of the transfer matrix.
- :func:`plot_step_responses` -- for each located element, the step response of the model's
  element, of the repaired element and of the element identified from the data
  (``Phat_ij + Delta_ij``, ``Delta_ij = q^-nk B_ij(q) / A(q)`` from the row's ARX table).
- :func:`plot_residuals` -- the prediction error ``d = y - Phat u`` per output with the model as
  given and as repaired.

Each function writes one PNG and returns its path (or None when there is nothing to draw).  They
read an :class:`~mpm_monitor.core.analysis.AnalysisReport` through the attributes listed in
``docs/DESIGN.md`` only, so any object with those attributes will do.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

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
    """State of every element as a string array of shape (n_outputs, n_inputs).

    ``located`` (mismatch located), ``ambiguous`` (cannot be told apart from another input),
    ``clean`` (tested, no mismatch) or ``untested`` (its row was not flagged, so not tested).
    """
    states = np.full((model.n_outputs, model.n_inputs), "untested", dtype=object)
    for e in report.elements:
        i, j = model.outputs.index(e.output), model.inputs.index(e.input)
        states[i, j] = "located" if e.mismatch else ("ambiguous" if getattr(e, "ambiguous", False) else "clean")
    return states


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
    ny, nu = model.n_outputs, model.n_inputs
    states = element_states(report, model)
    rgb = np.array([[to_rgb(_COLORS[s]) for s in row] for row in states])
    fig, ax = plt.subplots(figsize=(1.2 * nu + 2.6, 0.9 * ny + 1.6))
    ax.imshow(rgb, aspect="auto")
    by_key = {(e.output, e.input): e for e in report.elements}
    for i, out in enumerate(model.outputs):
        for j, inp in enumerate(model.inputs):
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
    ax.set_xticks(range(nu), model.inputs)
    ax.set_yticks(range(ny), [f"{o}  (RSI {rsi[o].rsi:.2f}{', flagged' if rsi[o].mismatch else ''})"
                              if o in rsi else o for o in model.outputs])
    ax.set_xticks(np.arange(-0.5, nu), minor=True)
    ax.set_yticks(np.arange(-0.5, ny), minor=True)
    ax.grid(which="minor", color="white", lw=2)
    ax.tick_params(which="minor", length=0)
    ax.xaxis.tick_top()
    ax.set_title("model elements: located mismatch", fontsize=10, pad=22)
    handles = [Patch(color=_COLORS[k], label=label) for k, label in
               (("located", "mismatch located"), ("ambiguous", "ambiguous (inputs move together)"),
                ("clean", "tested, no mismatch"), ("untested", "row not flagged"))]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=2, fontsize=7, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------
# Step responses


def element_step(model: PlantModel, i: int, j: int, n: int) -> np.ndarray:
    """Unit-step response of element (i, j) of the discretized model, samples ``0 .. n-1``.

    ``y(k)`` answers a unit step of input ``j`` applied from sample 0 (so ``y(0) = 0``: the
    output depends on inputs up to ``k - 1``, see docs/DESIGN.md).
    """
    from ..core.discretize import simulate_elements

    el = PlantModel(sample_time=model.sample_time, inputs=(model.inputs[j],), outputs=(model.outputs[i],),
                    gain=[[model.gain[i, j]]], time_constant=[[model.time_constant[i, j]]],
                    delay=[[model.delay[i, j]]])
    return simulate_elements(el, np.ones((n, 1)))[:, 0]


def arx_step(a, b, delay: int, n: int) -> np.ndarray:
    """Unit-step response of ``q^-delay (b_0 + b_1 q^-1 + ...) / (1 + a_1 q^-1 + ...)``.

    Parameters
    ----------
    a : sequence of float
        ``a_1 .. a_na``.
    b : sequence of float
        ``b_0 .. b_{nb-1}``.
    delay : int
        Samples.
    n : int

    Returns
    -------
    ndarray, shape (n,)
    """
    from ..core.filters import lfilter

    num = np.concatenate([np.zeros(int(delay)), np.asarray(b, dtype=float)])
    den = np.concatenate([[1.0], np.asarray(a, dtype=float)])
    return lfilter(num, den, np.ones(n))


def _step_horizon(models, pairs) -> int:
    longest = 0.0
    for m in models:
        for i, j in pairs:
            longest = max(longest, m.delay[i, j] + 5.0 * m.time_constant[i, j])
    ts = models[0].sample_time
    return int(min(max(20, np.ceil(longest / ts) + 5), 5000))


def identified_step(report, model: PlantModel, i: int, j: int, n: int) -> Optional[np.ndarray]:
    """Step response of the element as identified from the data, ``Phat_ij + Delta_ij``, or None.

    ``Delta_ij`` is the row's ARX (``report.arx_tables``: ``a``, ``b[input]``, ``delay[input]``) of
    the prediction error on the inputs, paper eq. (10).
    """
    for table in getattr(report, "arx_tables", None) or ():
        if table.output == model.outputs[i] and model.inputs[j] in table.b:
            delta = arx_step(table.a, table.b[model.inputs[j]], table.delay[model.inputs[j]], n)
            return element_step(model, i, j, n) + delta
    return None


def plot_step_responses(report, model: PlantModel, path) -> Optional[Path]:
    """Step responses of every located element: model, repaired model and identified element.

    Parameters
    ----------
    report : AnalysisReport
        Uses ``elements``, ``repaired_model`` and ``arx_tables`` (optional).
    model : PlantModel
    path : str or Path

    Returns
    -------
    Path or None
        None when no element is located.
    """
    pairs = [(model.outputs.index(o), model.inputs.index(u)) for o, u in
             [(e.output, e.input) for e in report.elements if e.mismatch]]
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
        ax.step(t, element_step(model, i, j, n), where="post", color="k", lw=1.4, label="model")
        ax.step(t, element_step(repaired, i, j, n), where="post", color=_COLORS["clean"], lw=1.4, ls="--",
                label="repaired model")
        ident = identified_step(report, model, i, j, n)
        if ident is not None:
            ax.step(t, ident, where="post", color=_COLORS["located"], lw=1.0, alpha=0.8,
                    label="identified (model + ARX Delta)")
        ax.set_title(f"({model.outputs[i]}, {model.inputs[j]})", fontsize=9)
        ax.set_xlabel("time (s)", fontsize=8)
        ax.grid(True, alpha=0.3)
        ax.tick_params(labelsize=8)
    for ax in axes.flat[len(pairs):]:
        ax.set_visible(False)
    for ax in axes[:, 0]:
        ax.set_ylabel("unit-step response", fontsize=8)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle("located elements: step responses", fontsize=10)
    fig.tight_layout()
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------
# Residuals


def prediction_errors(model: PlantModel, data, initial_state: str = "estimate") -> np.ndarray:
    """``d = y - Phat u`` of shape (n_samples, n_outputs) (:func:`~mpm_monitor.core.signals.compute_signals`)."""
    from ..core.signals import compute_signals

    return compute_signals(model, data.r, data.u, data.y, initial_state=initial_state).d


def plot_residuals(model: PlantModel, repaired: Optional[PlantModel], data, path,
                   initial_state: str = "estimate") -> Path:
    """Prediction error per output with the model as given and (if any) as repaired.

    Parameters
    ----------
    model : PlantModel
    repaired : PlantModel or None
        None or equal to ``model``: only the "before" curve is drawn.
    data : LoggedData
    path : str or Path
    initial_state : {"estimate", "zero"}

    Returns
    -------
    Path
    """
    plt = _pyplot()
    before = prediction_errors(model, data, initial_state)
    after = prediction_errors(repaired, data, initial_state) if repaired is not None and repaired != model else None
    t = np.asarray(data.t, dtype=float)
    stride = max(1, int(np.ceil(t.size / MAX_POINTS)))
    ny = model.n_outputs
    fig, axes = plt.subplots(ny, 1, figsize=(9.0, 1.9 * ny + 0.6), sharex=True, squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        rms_b = float(np.sqrt(np.mean(before[:, k] ** 2)))
        ax.plot(t[::stride], before[::stride, k], color=_COLORS["located"], lw=0.7,
                label=f"model as given (RMS {rms_b:.4g})")
        if after is not None:
            rms_a = float(np.sqrt(np.mean(after[:, k] ** 2)))
            ax.plot(t[::stride], after[::stride, k], color=_COLORS["clean"], lw=0.7, alpha=0.9,
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
