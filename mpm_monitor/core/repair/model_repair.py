"""repair_model: set-up, the rows, the disturbance check and the result."""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
from scipy import stats

from ..errors import ConfigurationError, InputError
from ..logged_data import LoggedData
from ..model import FopdtModel
from ..signals import LoopSignals, compute_signals
from .classify import _repair_row
from .disturbance import unexplained_disturbance
from .fit import _TooShort
from .options import RepairOptions
from .refit import _refit_row
from .result import RepairResult, _unchanged_entry


def _project_out(x: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``x`` minus its least-squares fit on the columns ``cols``."""
    coef, *_ = np.linalg.lstsq(cols, x, rcond=None)
    return x - cols @ coef


def _rms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


def _fit_percent(y, yhat) -> float:
    den = np.linalg.norm(y - np.mean(y))
    if den == 0:
        return float("nan")
    return float(100.0 * (1.0 - np.linalg.norm(y - yhat) / den))


def _check_inputs(model: FopdtModel, data: LoggedData, located, signals):
    if tuple(data.inputs) != tuple(model.inputs) or tuple(data.outputs) != tuple(model.outputs):
        raise InputError("repair: the data's channels do not match the model's inputs/outputs "
                         f"(data {list(data.inputs)} -> {list(data.outputs)}, model {list(model.inputs)} -> "
                         f"{list(model.outputs)})")
    n = data.n_samples
    for key, arr, width in (("r", data.r, model.n_outputs), ("u", data.u, model.n_inputs),
                            ("y", data.y, model.n_outputs)):
        if np.shape(arr) != (n, width):
            raise InputError(f"repair: data.{key}: expected shape ({n}, {width}), got {np.shape(arr)}")
    out = []
    for item in located:
        try:
            i, j = (int(v) for v in item)
        except (TypeError, ValueError):
            raise InputError(f"repair: located element {item!r}: expected a pair (output index, input index)") from None
        if not (0 <= i < model.n_outputs and 0 <= j < model.n_inputs):
            raise InputError(f"repair: located element ({i}, {j}): expected 0 <= output < {model.n_outputs} "
                             f"and 0 <= input < {model.n_inputs}")
        if (i, j) not in out:
            out.append((i, j))
    if signals is not None:
        for key in ("yhat", "d"):
            if np.shape(getattr(signals, key)) != (n, model.n_outputs):
                raise InputError(f"repair: signals.{key}: expected shape ({n}, {model.n_outputs}), "
                                 f"got {np.shape(getattr(signals, key))}")
    return sorted(out)


def repair_model(model: FopdtModel, data: LoggedData, located: Sequence[tuple],
                 options: RepairOptions = RepairOptions(), signals: Optional[LoopSignals] = None) -> RepairResult:
    """Re-estimate the located elements, classify their mismatch, and validate the repair.

    Parameters
    ----------
    model : FopdtModel
        The controller's model ``Phat`` as given.
    data : LoggedData
        Closed-loop record (``r``, ``u``, ``y``), shapes (n_samples, n_outputs/n_inputs).
    located : sequence of (int, int)
        (output index, input index) of the elements located as mismatched.  No other element is
        ever changed.
    options : RepairOptions
    signals : LoopSignals, optional
        :func:`~mpm_monitor.core.signals.compute_signals` of ``model`` on ``data`` (computed when absent).

    Returns
    -------
    RepairResult
    """
    if not isinstance(options, RepairOptions):
        raise ConfigurationError(f"options: expected RepairOptions, got {type(options).__name__}")
    located = _check_inputs(model, data, located, signals)
    ts = model.sample_time
    ny, nu = model.n_outputs, model.n_inputs
    names_y, names_u = model.outputs, model.inputs
    u, y = np.asarray(data.u, float), np.asarray(data.y, float)
    n = data.n_samples
    warnings: list = []
    if signals is None:
        signals = compute_signals(model, data.r, u, y, initial_state=options.initial_state)
    d0 = np.asarray(signals.d, float)
    yhat0 = np.asarray(signals.yhat, float)
    n_hold = int(round(options.holdout_fraction * n))
    n_fit = n - n_hold
    alpha = 1.0 - options.confidence_level
    zcrit = float(stats.norm.isf(alpha / 2))
    chi_crit = float(stats.chi2.isf(alpha, 1))
    hold = slice(n_fit, n)

    error_before = {names_y[i]: _rms(d0[:, i]) for i in range(ny)}
    fit_before = {names_y[i]: _fit_percent(y[:, i], yhat0[:, i]) for i in range(ny)}
    holdout_before = {names_y[i]: _rms(d0[hold, i]) for i in range(ny)} if n_hold > 0 else {}
    holdout_after = {}

    rows = sorted({i for i, _ in located})
    changes, kinds = [], {}
    min_fit = max(200, 20 * (2 * nu + options.noise_order + 5))
    if located and n_fit < min_fit:
        warnings.append(f"Only {n_fit} samples are available for re-estimating the located elements "
                        f"(at least {min_fit} needed); no element was changed.")
        for (i, j) in located:
            kinds[(i, j)] = "unknown"
            changes.append(_unchanged_entry(model, i, j, "too few samples"))
        rows = []
    if located and options.holdout_fraction == 0:
        warnings.append("No held-out data (holdout_fraction = 0): the repair was not validated on data "
                        "outside the fit.")

    def process_row(i, extra):
        """Classify, fit, validate and (optionally) refit the located elements of row ``i``."""
        js = [j for (ii, j) in located if ii == i]
        try:
            row = _repair_row(model, u, y, i, js, n_fit, options, zcrit, chi_crit, alpha, extra)
        except _TooShort as exc:
            return {"elements": {j: {"kind": "unknown", "changed": [], "after": model.element(i, j), "interval": None,
                                     "evidence": {}, "confidence": 0.0, "apply": False, "reason": str(exc)}
                                 for j in js},
                    "warnings": [f"{names_y[i]}: {exc}; its elements were not re-estimated."], "holdout_after": None,
                    "holdout_before": None}
        row_warnings = list(row["warnings"])
        elements = row["elements"]
        h_after = h_before = None
        candidate = model
        for j, el in elements.items():
            if el["apply"]:
                candidate = candidate.with_element(i, j, **el["after"])
        accepted = any(el["apply"] for el in elements.values())
        if accepted and n_hold > 0:
            sig_c = compute_signals(candidate, data.r, u, y, initial_state=options.initial_state)
            h_after = _rms(sig_c.d[hold, i])
            h_before = holdout_before[names_y[i]]
            if extra is not None:
                # The unexplained disturbance is no model's job: compare without it (an offset and the
                # step or ramp fitted over the held-out part), since a wrong element can partly cancel it.
                cols = np.column_stack([np.ones(n_hold), extra[hold]])
                h_after = _rms(_project_out(sig_c.d[hold, i], cols))
                h_before = _rms(_project_out(d0[hold, i], cols))
            if not h_after < h_before * (1.0 - options.min_holdout_improvement):
                accepted = False
                row_warnings.append(
                    f"{names_y[i]}: the re-estimated element(s) {', '.join(names_u[j] for j in js)} did not "
                    f"predict the held-out last {100 * options.holdout_fraction:.0f}% of the record better (RMS "
                    f"error {h_after:.4g} vs {h_before:.4g} with the model as given); the elements are kept as "
                    f"they were.")
                for el in elements.values():
                    if el["apply"]:
                        el.update(apply=False, fitted_kind=el["kind"], kind="unknown", confidence=0.0,
                                  reason="rejected by held-out validation")
        if accepted and options.refit_on_all and n_hold > 0:
            keep = {j: el for j, el in elements.items() if el["apply"]}
            for j, upd in _refit_row(model, u, y, i, keep, n, options, zcrit, chi_crit, extra).items():
                keep[j]["after"] = upd["after"]
                keep[j]["interval"] = upd["interval"]
        if not accepted:
            for el in elements.values():
                el["apply"] = False
        return {"elements": elements, "warnings": row_warnings, "holdout_after": h_after, "holdout_before": h_before}

    def build(results):
        repaired = model
        for i, res in results.items():
            for j, el in res["elements"].items():
                if el["apply"]:
                    repaired = repaired.with_element(i, j, **el["after"])
        return repaired

    def residual(repaired):
        if repaired == model:
            return signals
        return compute_signals(repaired, data.r, u, y, initial_state=options.initial_state)

    def disturbance_tests(d):
        return {i: unexplained_disturbance(d[:, i], ts, options.disturbance_alpha, options.disturbance_trim,
                                           options.noise_order) for i in range(ny)}

    results = {i: process_row(i, None) for i in rows}
    new_model = build(results)
    sig_after = residual(new_model)
    tests = disturbance_tests(np.asarray(sig_after.d, float))
    # A step or drift on a repaired row would bias its elements: redo the row with the disturbance as a
    # nuisance regressor (it stays in the residual: the model has no place for it).
    redo = [i for i in rows if tests[i]["detected"]]
    for i in redo:
        t = tests[i]
        k = np.arange(n, dtype=float)
        col = (k >= round(t["time"] / ts)).astype(float) if t["kind"] == "step" else k / n
        results[i] = process_row(i, col[:, None])
        results[i]["warnings"].append(
            f"{names_y[i]}: the re-estimation of its elements allowed for the unexplained "
            f"{'step' if t['kind'] == 'step' else 'drift'} in the prediction error.")
    if redo:
        new_model = build(results)
        sig_after = residual(new_model)
        tests = disturbance_tests(np.asarray(sig_after.d, float))

    for i in rows:
        res = results[i]
        warnings.extend(res["warnings"])
        if res["holdout_after"] is not None:
            holdout_after[names_y[i]] = res["holdout_after"]
            holdout_before[names_y[i]] = res["holdout_before"]
        for j, el in res["elements"].items():
            kinds[(i, j)] = el["kind"]
            entry = {"output": names_y[i], "input": names_u[j], "kind": el["kind"],
                     "before": model.element(i, j),
                     "after": el["after"] if el["apply"] else model.element(i, j),
                     "estimate": el["after"], "confidence": el["confidence"],
                     "interval": el["interval"], "applied": bool(el["apply"]), "evidence": el["evidence"]}
            if "fitted_kind" in el:
                entry["fitted_kind"] = el["fitted_kind"]
            if el.get("reason"):
                entry["reason"] = el["reason"]
            changes.append(entry)

    d1 = np.asarray(sig_after.d, float)
    error_after = {names_y[i]: _rms(d1[:, i]) for i in range(ny)}
    fit_after = {names_y[i]: _fit_percent(y[:, i], sig_after.yhat[:, i]) for i in range(ny)}
    for i in range(ny):
        if n_hold > 0 and names_y[i] not in holdout_after:
            holdout_after[names_y[i]] = _rms(d1[hold, i])

    disturbances = []
    for i in range(ny):
        test = tests[i]
        if not test["detected"]:
            continue
        disturbances.append({"output": names_y[i], "kind": test["kind"], "size": test["size"],
                             "time": test["time"], "rate": test["rate"], "p_value": test["p_value"],
                             "statistic": test["statistic"]})
        if test["kind"] == "step":
            warnings.append(
                f"{names_y[i]}: the prediction error shifts by {test['size']:+.3g} at about t = {test['time']:.0f} s "
                f"(p = {test['p_value']:.2g}) and no input explains it: an unmeasured disturbance or a change "
                f"in the process, not an error of one model element; no element was changed for it.")
        else:
            warnings.append(
                f"{names_y[i]}: the prediction error drifts by {test['size']:+.3g} over the record "
                f"({test['rate']:+.3g} per second, p = {test['p_value']:.2g}) and no input explains it: an "
                f"unmeasured disturbance or a slow process change; no element was changed for it.")
    return RepairResult(model=new_model, changes=changes, kinds=kinds, error_before=error_before,
                        error_after=error_after, fit_before=fit_before, fit_after=fit_after,
                        holdout_error_before=holdout_before, holdout_error_after=holdout_after,
                        disturbances=disturbances, warnings=warnings, n_samples=n, n_fit=n_fit,
                        options=options)
