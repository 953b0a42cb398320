"""The S_Delta row test: which rows of the sensitivity ``S_Delta`` differ from the identity.

For a plant under MPC in internal-model structure ("A Novel Algorithm for Model-Plant Mismatch
Detection for Model Predictive Controllers", Fig. 1), with ``d = y - Phat u`` and ``eps = r - d``::

    eps = S_Delta (r - v),   S_Delta = (I + Delta C)^-1            (paper eq. 1)

Row ``i`` of ``S_Delta - I`` equals ``-Delta_i C S_Delta``, so it is zero exactly when row ``i`` of
``Delta`` is zero.  With ``z_i = eps_i - r_i`` the ARX

    A(q) z_i(t) = sum_j C_j(q) r_j(t) + e(t)

has ``C = 0`` under "no mismatch in row i", and since the setpoints are exogenous (independent of
the disturbance) the F test of ``C = 0`` has a known false-alarm rate whatever the disturbance
colour.  The same fit gives the paper's identified row ``S_i = e_i + C/A`` (an ARX of ``eps_i`` on
``r``), whose H-infinity norm over the band is the row's relative sensitivity index (RSI, paper
eq. 8).  Rows are decided with Holm's step-down procedure at family-wise level
``alpha / N_FAMILIES`` (:mod:`mpm_monitor.core.statistics`).

The regressions come from a provider with the methods of
:class:`~mpm_monitor.core.regressions.QrRegressions` (``row_regression``, ``row_fits``); on data with
gaps its ``segments`` say which rows are regression rows (docs/interfaces.md, "Gaps").
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from .arx import segment_rows
from .logged_data import moving_columns
from .model import PlantModel
from .parallel import split_map
from .statistics import N_FAMILIES, holm_adjust


@dataclasses.dataclass
class RowResult:
    """S_Delta row test of one output.

    Attributes
    ----------
    output : str
    rsi : float
        Row H-infinity norm of the identified S_Delta over the band.
    mismatch : bool
        The row differs from the identity row (Holm-adjusted p < alpha).
    p_value : float
        Holm-adjusted p-value of "row equals the identity row".
    p_value_raw : float
        Unadjusted p-value.
    statistic : float
        F statistic.
    df : tuple of int
        Degrees of freedom (numerator, denominator).
    fit_percent : float
        One-step fit of the row's ARX.
    """

    output: str
    rsi: float
    mismatch: bool
    p_value: float
    p_value_raw: float
    statistic: float
    df: tuple
    fit_percent: float


@dataclasses.dataclass
class RowTest:
    """The S_Delta row test of every output and the identified ``S_Delta``.

    Attributes
    ----------
    rows : list of RowResult
        One per output, in the model's order.
    frequencies : ndarray, shape (n_freq,)
        The band's frequency grid, rad/sample (:func:`frequency_grid`).
    response : ndarray of complex, shape (n_freq, n_outputs, n_outputs)
        The identified ``S_Delta(e^{j omega})``.
    row_gains : ndarray, shape (n_outputs, n_freq)
        2-norm of every row of ``response``.
    sigma_max : ndarray, shape (n_freq,)
        Largest singular value of ``response``.
    warnings : list of str
        Setpoints that never move (their columns of ``S_Delta`` cannot be identified).
    """

    rows: list
    frequencies: np.ndarray
    response: np.ndarray
    row_gains: np.ndarray
    sigma_max: np.ndarray
    warnings: list


def frequency_grid(band: tuple, n: int) -> np.ndarray:
    """Frequencies (rad/sample) in the band: 0 if included, then log-spaced to the top."""
    lo, hi = band
    lo_log = max(lo, hi * 1e-3)
    grid = np.logspace(np.log10(lo_log), np.log10(hi), n - (1 if lo == 0 else 0))
    if lo == 0:
        grid = np.concatenate([[0.0], grid])
    return grid


def moving_setpoints(r: np.ndarray) -> list:
    """The setpoints that move over the window (:func:`~mpm_monitor.core.logged_data.moving_columns`): the row
    test's columns.

    Parameters
    ----------
    r : ndarray, shape (n_samples, n_outputs)

    Returns
    -------
    list of int
    """
    # Not a standard deviation above 0: a setpoint held at 0.1 has one of about 1e-17 (the rounding of its mean),
    # and its column of S_Delta then came out as rounding (an RSI of 1e11).
    moves = moving_columns(r)
    return [j for j in range(r.shape[1]) if moves[j]]


def sdelta_row_test(model: PlantModel, r: np.ndarray, eps: np.ndarray, regressions, layout, options,
                    output_spread: Optional[np.ndarray] = None, singular_values: bool = True,
                    jobs: Optional[int] = None) -> RowTest:
    """The S_Delta row test of every output (see the module docstring).

    Parameters
    ----------
    model : PlantModel
        The controller's model (its output names).
    r, eps : ndarray, shape (n_samples, n_outputs)
        Setpoints and controller inputs ``eps = r - d`` of the window.
    regressions : QrRegressions or GramRegressions
        The window's least-squares problems (:mod:`mpm_monitor.core.regressions`).
    layout : RegressionLayout
        Setpoint lags ``0 .. n_lag_r - 1`` and first regression row ``start``.
    options : AnalysisOptions
        Its ``na``, ``alpha``, ``band`` and ``n_freq``.
    output_spread : ndarray, shape (n_outputs,), optional
        Standard deviation of every output over the window, output units.  A row whose fit leaves at
        most :data:`~mpm_monitor.core.statistics.EXACT_FIT` of it is fitted exactly (a log without
        noise): its test is decided outright, not on the rounding of its residual
        (:meth:`~mpm_monitor.core.arx.SharedFit.set_output_spread`).  Default: only a residual of exactly 0.
    singular_values : bool
        False: ``sigma_max`` is not computed (NaN; the rows' tests and RSI do not need it).
    jobs : int, optional
        With 2 a forked child computes the singular values of one of two halves of the frequencies
        (:func:`~mpm_monitor.core.parallel.split_map`; the same numbers); default ``options.jobs``.

    Returns
    -------
    RowTest
    """
    ny, na, n_lag_r, start = model.n_outputs, options.na, layout.n_lag_r, layout.start
    warnings = []
    r_moving = moving_setpoints(r)
    if len(r_moving) < ny:
        still = [model.outputs[j] for j in range(ny) if j not in r_moving]
        warnings.append(f"setpoints of {', '.join(still)} never move: their columns of S_Delta cannot be identified "
                        f"and a mismatch that shows only through them goes unseen")
    reg_r = regressions.row_regression(r_moving)
    omega = frequency_grid(options.band, options.n_freq)
    z1 = np.exp(-1j * omega)
    z_pow = z1[:, None] ** np.arange(max(n_lag_r, na + 1))     # z^-l, shape (n_freq, lags)
    S = np.zeros((omega.size, ny, ny), dtype=complex)
    row_raw_p = np.full(ny, np.nan)
    row_stat, row_df, row_fit = np.full(ny, np.nan), [(0, 0)] * ny, np.zeros(ny)
    row_gains = np.zeros((ny, omega.size))                        # (ny, n_freq)
    for i, fit in enumerate(regressions.row_fits(reg_r, range(ny))):
        if output_spread is not None:
            fit.set_output_spread(output_spread[i])
        test = fit.test_all_common_zero()
        row_raw_p[i], row_stat[i], row_df[i] = test.p_value, test.statistic, (test.df_num, test.df_den)
        a = fit.own_theta()
        a_poly = 1.0 + z_pow[:, 1:na + 1] @ a
        S[:, i, i] = 1.0
        # The common coefficients: every moving setpoint's lags 0 .. n_lag_r - 1, one block after the other.
        c = fit.theta[:fit.n_common].reshape(len(r_moving), n_lag_r)
        S[:, i, r_moving] += (z_pow[:, :n_lag_r] @ c.T) / a_poly[:, None]
        # The row's 2-norm at every frequency (numpy's norm along the row, without its temporaries of all of S).
        row = S[:, i, :]
        row_gains[i] = np.sqrt(np.add.reduce((row.conj() * row).real, axis=1))
        # Fit of the paper's ARX of eps_i on r (same model, target eps_i).
        e_i = segment_rows(eps[:, i], start, getattr(regressions, "segments", None))
        e_i = e_i - e_i.mean()
        row_fit[i] = 100.0 * (1.0 - math.sqrt(fit.rss) / max(np.linalg.norm(e_i), 1e-300))
    if singular_values:
        half = (omega.size + 1) // 2
        sigma_max = np.concatenate(split_map(lambda part: np.linalg.svd(S[part], compute_uv=False)[:, 0],
                                             [slice(0, half), slice(half, omega.size)],
                                             getattr(options, "jobs", 1) if jobs is None else jobs))
    else:
        sigma_max = np.full(omega.size, np.nan)
    row_p = np.minimum(1.0, N_FAMILIES * holm_adjust(row_raw_p))
    rows = []
    for i in range(ny):
        p = row_p[i]
        rows.append(RowResult(output=model.outputs[i], rsi=float(row_gains[i].max()),
                              mismatch=bool(np.isfinite(p) and p < options.alpha),
                              p_value=float(p) if np.isfinite(p) else 1.0, p_value_raw=float(row_raw_p[i]),
                              statistic=float(row_stat[i]), df=tuple(row_df[i]), fit_percent=float(row_fit[i])))
    warnings += near_instability_warnings(rows, omega, row_gains, model.sample_time, model.integrating_outputs)
    return RowTest(rows=rows, frequencies=omega, response=S, row_gains=row_gains, sigma_max=sigma_max,
                   warnings=warnings)


#: A flagged row whose RSI exceeds this is named as a loop near instability
#: (:func:`near_instability_warnings`).  ``S_Delta`` is the ratio of the loop's real sensitivity to the
#: one its model predicts; the usual bound on a sensitivity's peak is 2, so a mismatch that triples it
#: at some frequency has taken the loop well past its design margins.
RSI_NEAR_INSTABILITY = 3.0


def near_instability_warnings(rows: list, frequencies: np.ndarray, row_gains: np.ndarray, sample_time: float,
                              integrating: Optional[tuple] = None, limit: float = RSI_NEAR_INSTABILITY) -> list:
    """One warning per flagged row whose RSI exceeds ``limit``: where the mismatch amplifies the loop.

    An integrating output's row is named only for a peak above frequency 0: there its identified
    ``S_Delta`` carries the ARX's root near 1 (the level's drift under an integrator error), whose gain
    at frequency 0 is not the loop's.

    Parameters
    ----------
    rows : list of RowResult
    frequencies : ndarray, shape (n_freq,)
        rad/sample.
    row_gains : ndarray, shape (n_outputs, n_freq)
        2-norm of every row of the identified ``S_Delta``.
    sample_time : float
        Seconds per sample.
    integrating : tuple of bool, optional
        Per output, whether it integrates (:attr:`~mpm_monitor.core.model.PlantModel.integrating_outputs`).
    limit : float

    Returns
    -------
    list of str
        ``row y2: RSI 50.1, the mismatch amplifies the loop's response 50.1 times the model's at
        0.063 rad/sample (period 100 s): ...``; a peak at frequency 0 is named as the steady state.
    """
    out = []
    for i, row in enumerate(rows):
        if not (row.mismatch and row.rsi > limit):
            continue
        w = float(frequencies[int(np.argmax(row_gains[i]))])
        if w == 0 and integrating is not None and integrating[i]:
            continue
        where = (f"at {w:.3g} rad/sample (period {2 * math.pi / w * sample_time:.3g} s): the loop runs close to "
                 f"instability and oscillates near that period" if w > 0 else
                 "in steady state (frequency 0): the controller's corrections are far off there, and its "
                 "inputs move far more than the model expects")
        out.append(f"row {row.output}: RSI {row.rsi:.3g}, the mismatch amplifies the loop's response {row.rsi:.3g} "
                   f"times what the model predicts {where}; the model needs repairing before the loop is tuned "
                   f"tighter")
    return out
