"""Candidate channels: logged variables the model does not use, tested as causes of the prediction error.

A log often holds more than the model's columns: a feed temperature, an ambient condition, another
unit's flow.  When one of them drives an output and the model leaves it out, its effect sits in the
prediction error ``d = y - Phat u`` (see :mod:`mpm_monitor.core.element_test`).  The user names such
channels (``--candidates``, docs/interfaces.md "Candidate channels"); each is examined in three
steps:

1. **Usability.**  A channel that is not numeric, partly missing (the reader's
   :attr:`~mpm_monitor.core.logged_data.LoggedData.unusable`), constant, non-finite or not as long
   as the log is reported as unusable with the reason, never used.
2. **Exogeneity.**  A logged variable inside the loop (an intermediate flow or temperature) moves
   because the controller moves the inputs: it is an effect of the loop, and a regression of the
   output on it would credit it with what the inputs did.  The candidate ``c`` is regressed on its
   own lags ``1 .. CANDIDATE_AR_ORDER`` and the lags ``1 .. n_lag`` of every moving manipulated
   input (a Granger-causality test; Granger, 1969)::

       c(k) = sum_l phi_l c(k-l) + sum_j sum_l beta_jl u_j(k-l) + e(k)

   An exogenous channel, even one the loop reacts to through the outputs, has ``beta = 0``: its own
   past holds everything its past has to say about it.  ``beta = 0`` is rejected when both the F
   test and its heteroskedasticity-robust score version (Wooldridge, 1991) reject: a channel that
   moves in a few steps leaves its own-lag residual as a few spikes, and one that falls a few
   samples after a setpoint step, which moves the inputs sharply, is fitted by their lags and
   trips the F test alone far beyond its level.  A rejection (Holm's procedure over the
   candidates, at the analysis's ``alpha``, on the larger of the two p-values) marks the channel as
   "moves with u2: may be an effect of the loop, not a cause", named after the inputs whose blocks
   reject alone.  It is never tested as a cause, never added.  The test is on lags of the levels
   with the candidate's own lags in the regression, so a wandering candidate (a random walk) keeps
   it valid: the tested coefficients belong to stationary regressors (Sims, Stock and Watson, 1990).
3. **Cause.**  For each output ``i`` and exogenous candidate ``c``, the candidate's lags join the
   regression of the Delta element test::

       d_i(k) = sum_l a_l d_i(k-l) + sum_j sum_l b_jl u_j(k-l) + sum_l g_l w(k-l) + e(k)

   The candidate's lags are ``1 .. CANDIDATE_DELAY_FACTOR * max_delay + nb`` (the columns' ``1 ..
   max_delay + nb``): a channel the model does not declare has no dead time to start from, and a
   transport delay longer than the model's own is common (a feed's temperature reaching a column
   tray); with the columns' lags alone an effect of 0.8 (16 times the noise) with a dead time of 14
   samples on a model whose longest is 7 came out p = 1, silently (an outside check).
   ``w`` is the candidate whitened by its own least-squares AR(``CANDIDATE_AR_ORDER``) filter:
   most process variables wander, and the lags of a random walk in levels would give the spurious
   regression of Granger and Newbold (1974) -- the F test of ``g = 0`` then rejects far more often
   than it should.  The whitened channel is (close to) white noise, so the test keeps its level
   even where the ARX noise model of ``d_i`` is imperfect, and an effect ``G(q) c`` of the
   candidate still shows as ``G(q) H(q) w`` (``H`` the candidate's own filter, the ARX's ``A(q)``
   absorbing its poles).  The p-values of ``g = 0`` join the element tests' family: Holm's
   procedure over every element and every (output, candidate) pair at ``alpha / N_FAMILIES``
   (:mod:`mpm_monitor.core.statistics`), so the analysis's false-alarm rate stays ``alpha`` whatever
   the number of candidates tried.  A model element keeps at least its p-value without the
   candidates (the family only grows, and the confirmation of a row's located elements with the
   others' tails, :mod:`mpm_monitor.core.element_test`, is not undone).

A located candidate is an element the model lacks (kind ``missing``, role ``candidate``).  The
repair (:func:`mpm_monitor.core.pipeline.analyze`) adds it to the model as a new measured
disturbance column (:func:`with_candidate_columns`), fits its element like any missing element
and validates it on the held-out part; a candidate whose fit the validation rejects is dropped
again (:func:`without_columns`).

References
----------
- Granger, C. W. J. (1969). Investigating causal relations by econometric models and
  cross-spectral methods. *Econometrica* 37(3), 424-438.
- Granger, C. W. J. and Newbold, P. (1974). Spurious regressions in econometrics. *Journal of
  Econometrics* 2(2), 111-120.
- Wooldridge, J. M. (1991). On the application of robust, regression-based diagnostics to models
  of conditional means and conditional variances. *Journal of Econometrics* 47(1), 5-46.
- Sims, C. A., Stock, J. H. and Watson, M. W. (1990). Inference in linear time series models with
  some unit roots. *Econometrica* 58(1), 113-144.
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence

import numpy as np

from .arx import segment_lag_matrix, segment_rows
from .errors import ConfigurationError
from .logged_data import MAX_ANALYSIS_SCALE, MIN_ANALYSIS_SCALE, LoggedData, moving_columns
from .model import PARAMETRIC_KEYS, PlantModel, name_problem
from .statistics import chi2_tail, f_test

#: Own lags of a candidate in its exogeneity test and the order of its whitening filter.
CANDIDATE_AR_ORDER = 8
#: A candidate's effect is searched for dead times up to this many times the analysis's ``max_delay`` (module
#: docstring, step 3).
CANDIDATE_DELAY_FACTOR = 3
#: The word of ``--candidates`` that selects every numeric channel the model does not use.
ALL_CANDIDATES = "all"
#: A candidate that ``a x + b`` fits, ``x`` one of the log's other channels, to within this fraction of its
#: own spread (root mean square about its mean) is a copy of ``x``: the same tag logged twice, in other units,
#: with an offset, or stored with fewer digits (a 32-bit float of a value far from 0 keeps about 1e-5 of its
#: spread).  A second sensor of the same quantity differs by its own noise, far more than this.
COPY_TOLERANCE = 1e-4


@dataclasses.dataclass(frozen=True)
class CandidateChannels:
    """The channels selected as candidates, split into those that can be used and those that cannot.

    Attributes
    ----------
    names : tuple of str
        The usable channels, in the order asked for.
    values : ndarray, shape (n_samples, n_candidates)
        Their samples.
    unusable : dict
        ``name -> reason`` of the selected channels that cannot be used.
    """

    names: tuple
    values: np.ndarray
    unusable: dict

    @property
    def tried(self) -> tuple:
        """Every channel selected: the usable ones, then the unusable ones."""
        return self.names + tuple(n for n in self.unusable if n not in self.names)


def parse_candidate_spec(spec) -> object:
    """``"all"``, or the tuple of names of a ``NAME[,NAME...]`` string or a sequence of names.

    Raises
    ------
    ConfigurationError
        An empty list or an empty name.
    """
    if isinstance(spec, str):
        if spec.strip() == ALL_CANDIDATES:
            return ALL_CANDIDATES
        names = [s.strip() for s in spec.split(",")]
    else:
        names = [str(s).strip() for s in spec]
    if not names or any(not s for s in names):
        raise ConfigurationError(f"candidates: expected 'all' or NAME[,NAME...] of logged channels, got {spec!r}")
    return tuple(dict.fromkeys(names))


def channel_problem(values, n_samples: int) -> Optional[str]:
    """Why a channel cannot be a candidate (None when it can).

    Parameters
    ----------
    values : array_like, shape (n_samples,)
    n_samples : int
        Samples of the log.

    Returns
    -------
    str or None
        "not numeric", "N samples, the log has M", "holds NaN or infinity", too large, too small (its largest
        |value| below :data:`~mpm_monitor.core.logged_data.MIN_ANALYSIS_SCALE`, whose moves would square to zero),
        or "constant".
    """
    try:
        x = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        return "not numeric"
    if x.ndim != 1 or x.shape[0] != n_samples:
        return f"{x.shape[0] if x.ndim == 1 else x.size} samples, the log has {n_samples}"
    if not np.isfinite(x).all():
        return "holds NaN or infinity"
    peak = float(np.abs(x).max(initial=0.0))
    if peak > MAX_ANALYSIS_SCALE:
        return f"values up to {peak:.3g}: too large for the analysis (at most {MAX_ANALYSIS_SCALE:g}); rescale"
    if 0.0 < peak < MIN_ANALYSIS_SCALE:   # its moves square to zero (underflow): it would read as constant
        return f"values up to {peak:.3g}: too small for the analysis (at least {MIN_ANALYSIS_SCALE:g}); rescale"
    if not moving_columns(x):            # relative to its own size: a channel in small units moves too
        return "constant: it never moves"
    return None


def select_candidates(data: LoggedData, spec, model: Optional[PlantModel] = None) -> CandidateChannels:
    """The candidate channels ``spec`` names among the data's other channels.

    Parameters
    ----------
    data : LoggedData
        Its :attr:`~mpm_monitor.core.logged_data.LoggedData.extra` (numeric channels the model does not
        use) and :attr:`~mpm_monitor.core.logged_data.LoggedData.unusable` (name -> reason).
    spec : str or sequence of str
        ``"all"`` (every channel of ``extra`` and ``unusable``) or names (a ``NAME[,NAME...]``
        string or a sequence).  A string that is itself the name of a channel (one whose name holds a
        comma) names that channel.
    model : PlantModel, optional
        A name that is one of the model's channels is refused.

    Returns
    -------
    CandidateChannels

    Raises
    ------
    ConfigurationError
        A name that is no channel of the data (listing the available ones), or one of the model's.
    """
    wanted = parse_candidate_spec(spec)
    available = list(data.extra) + [n for n in data.unusable if n not in data.extra]
    if isinstance(spec, str) and spec.strip() in available and spec.strip() not in wanted:
        wanted = (spec.strip(),)       # a channel whose own name holds a comma ("a,b", quoted in the CSV)
    if wanted == ALL_CANDIDATES:
        wanted = tuple(available)
    used = set(model.columns + model.outputs) if model is not None else set()
    setpoints = {f"r_{o}" for o in data.outputs}
    for name in wanted:
        if name in used:
            raise ConfigurationError(f"candidates: '{name}' is a channel of the model, not a candidate")
        if name == "t" or name in setpoints:
            what = "the log's time" if name == "t" else "a setpoint of the log"
            raise ConfigurationError(f"candidates: '{name}' is {what}, not a candidate")
        if name not in available:
            raise ConfigurationError(f"candidates: no column '{name}' in {data.source or 'the data'}; the channels "
                                     f"the model does not use are: {', '.join(available) or 'none'}")
    n = data.n_samples
    names, cols, unusable = [], [], {}
    copies = _Copies(data)
    for name in wanted:
        if name in data.unusable:
            unusable[name] = data.unusable[name]
            continue
        bad_name = name_problem(name)
        if bad_name:        # the repair would add it to the model as a measured disturbance by this name
            unusable[name] = f"its name {bad_name}, which a model's channel name cannot: rename the column to test it"
            continue
        why = channel_problem(data.extra[name], n)
        x = np.asarray(data.extra[name], dtype=float) if why is None else None
        why = why or copies.of(x)
        if why:
            unusable[name] = why
            continue
        names.append(name)
        cols.append(x)
        copies.add(x, f"candidate {name}", f"it is examined as {name}")
    values = np.column_stack(cols) if cols else np.zeros((n, 0))
    return CandidateChannels(names=tuple(names), values=values, unusable=unusable)


class _Copies:
    """The log's channels a candidate may be a copy of (:data:`COPY_TOLERANCE`): the model's inputs and measured
    disturbances, the outputs, the setpoints, then the candidates taken so far, each with what a copy of it is."""

    def __init__(self, data: LoggedData):
        self.labels, self.values, self._stacked = [], [], None
        dv = data.dv if data.dv is not None else np.zeros((data.n_samples, 0))
        known = ([(f"input {n}", "the model has it already") for n in data.inputs]
                 + [(f"measured disturbance {n}", "the model has it already") for n in data.disturbances]
                 + [(f"output {n}", "the output itself, not a cause") for n in data.outputs]
                 + [(f"setpoint r_{n}", "a setpoint acts through the inputs, not beside them") for n in data.outputs])
        values = [data.u[:, j] for j in range(data.u.shape[1])] + [dv[:, j] for j in range(dv.shape[1])] \
            + [data.y[:, j] for j in range(data.y.shape[1])] + [data.r[:, j] for j in range(data.r.shape[1])]
        for (label, why), x in zip(known, values):
            self.add(np.asarray(x, dtype=float), label, why)

    def add(self, x: np.ndarray, label: str, why: str) -> None:
        """Take ``x`` (shape (n_samples,)) as a channel later candidates are compared with (not when it never
        moves or is not finite: no candidate copies it)."""
        if x.ndim != 1 or not np.isfinite(x).all() or not moving_columns(x):
            return
        self.labels.append((label, why))
        self.values.append(x)
        self._stacked = None

    def of(self, c: np.ndarray) -> Optional[str]:
        """What ``c`` (shape (n_samples,), finite, moving) is a copy of, in words, or None."""
        if not self.values:
            return None
        cc = c - c.mean()
        spread = float(np.sqrt(np.mean(cc * cc)))
        if self._stacked is None:       # the channels, centred, and their norms: once per channel added
            X = np.column_stack(self.values)
            Xc = X - X.mean(axis=0)
            self._stacked = X, Xc, np.sqrt(np.einsum("ij,ij->j", Xc, Xc))
        X, Xc, norms = self._stacked
        corr = np.abs(Xc.T @ cc) / (norms * np.sqrt(float(cc @ cc)))
        for k in np.flatnonzero(corr > 1.0 - 1e-6):     # a screen; the residual itself decides
            scale = float(Xc[:, k] @ cc) / float(norms[k] ** 2)
            rest = cc - scale * Xc[:, k]
            if float(np.sqrt(np.mean(rest * rest))) <= COPY_TOLERANCE * spread:
                (label, why), offset = self.labels[k], float(c.mean() - scale * X[:, k].mean())
                if np.array_equal(c, X[:, k]):
                    return f"an exact copy of {label}: {why}"
                # A scale or offset within what tells a copy (the tolerance of the spread) is not said.
                how = (f" times {scale:.6g}" if abs(scale - 1.0) > COPY_TOLERANCE else "") + \
                    (f" {'plus' if offset > 0 else 'minus'} {abs(offset):.6g}"
                     if abs(offset) > COPY_TOLERANCE * spread else "")
                return f"a copy of {label}{how}: {why}"
        return None


# ------------------------------------------------------------------------------------ least squares
def _lags(x: np.ndarray, n_lag: int, start: int, segments=None) -> np.ndarray:
    """Lags ``1 .. n_lag`` of every column of ``x`` (shape (n, m)) for the regression rows, channel by
    channel (:func:`~mpm_monitor.core.arx.segment_lag_matrix`): the rows ``start ..``, or with gaps the
    rows at least ``start`` samples into their segment (:func:`_long_segments`)."""
    return segment_lag_matrix(x, range(1, n_lag + 1), start, _long_segments(segments, start))


def _rows(x: np.ndarray, start: int, segments=None) -> np.ndarray:
    """``x`` at the regression rows of :func:`_lags` (:func:`~mpm_monitor.core.arx.segment_rows`)."""
    return segment_rows(x, start, _long_segments(segments, start))


def _long_segments(segments, start: int):
    """The segments that give a regression row from their ``start``-th sample; None without gaps."""
    if segments is None or len(segments) <= 1:
        return None
    return [(a, b) for a, b in segments if b - a > start]


def _row_count(n: int, start: int, segments=None) -> int:
    """Regression rows of :func:`_rows` over ``n`` samples: ``n - start``, or with gaps those of the segments
    longer than ``start`` (at least 0)."""
    long = _long_segments(segments, start)
    if long is None:
        return max(n - start, 0)
    return sum(b - a - start for a, b in long)


def _rss(X: np.ndarray, y: np.ndarray):
    """Residual sum of squares of the least-squares fit of ``y`` on ``X``, the rank of ``X``, the
    coefficients and their unscaled variances ``diag((X'X)^-1)`` (one QR; ``lstsq`` and the
    pseudo-inverse when ``X`` is rank-deficient).

    The columns are scaled to unit norm first, so that the rank does not depend on their units: a
    candidate logged in units of 1e-14 has lags 1e-14 the size of the mean's column of ones, which an
    unscaled rank test took for zero (and then found the inputs' lags explaining it)."""
    if X.shape[1] == 0:
        return float(y @ y), 0, np.zeros(0), np.zeros(0)
    norms = np.sqrt(np.einsum("ij,ij->j", X, X))
    norms[norms == 0] = 1.0
    q, r = np.linalg.qr(X / norms)
    diag = np.abs(np.diag(r))
    if diag.min() > 1e-10 * max(float(diag.max()), 1e-300):
        rinv = np.linalg.inv(r)
        qty = q.T @ y
        coef = (rinv @ qty) / norms
        res = y - q @ qty
        return float(res @ res), X.shape[1], coef, np.sum(rinv ** 2, axis=1) / norms ** 2
    coef, _, rank, _ = np.linalg.lstsq(X / norms, y, rcond=None)
    res = y - (X / norms) @ coef
    return float(res @ res), int(rank), coef / norms, np.sum(np.linalg.pinv(r) ** 2, axis=1) / norms ** 2


def whiten(c: np.ndarray, order: int = CANDIDATE_AR_ORDER, segments=None) -> np.ndarray:
    """The innovations of a candidate under its own least-squares AR(``order``) filter (with a mean).

    Parameters
    ----------
    c : ndarray, shape (n_samples,)
    order : int
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs of samples; no lag reaches across a gap (the first
        ``order`` samples of every run are 0).

    Returns
    -------
    ndarray, shape (n_samples,)
        ``w(k) = c(k) - m - sum_l phi_l c(k-l)`` for ``k >= order``, zero before.  A random walk gives
        (about) its increments, a first-order filtered noise its white input.
    """
    x = np.asarray(c, dtype=float)
    x = x - x.mean()
    if order == 0:
        return x
    # In units of its own spread (the filter does not depend on them; a least-squares rank test does).
    scale = float(np.abs(x).max(initial=0.0))
    if scale > 0:
        return scale * _whiten(x / scale, order, segments)
    return _whiten(x, order, segments)


def _whiten(x: np.ndarray, order: int, segments) -> np.ndarray:
    """:func:`whiten` of the centred ``x``, ``order`` >= 1."""
    w = np.zeros_like(x)
    if _long_segments(segments, order) is None:
        X = np.column_stack([np.ones(x.shape[0] - order), _lags(x[:, None], order, order)])
        coef, *_ = np.linalg.lstsq(X, x[order:], rcond=None)
        w[order:] = x[order:] - X @ coef
        return w
    # With gaps: a mean per segment (a channel's level may move while the log is down).
    means = np.zeros((x.shape[0], len(segments)))
    for k, (a, b) in enumerate(segments):
        means[a:b, k] = 1.0
    X = np.column_stack([_rows(means, order, segments), _lags(x[:, None], order, order, segments)])
    target = _rows(x, order, segments)
    coef, *_ = np.linalg.lstsq(X, target, rcond=None)
    w[_rows(np.arange(x.shape[0]), order, segments)] = target - X @ coef
    return w


@dataclasses.dataclass(frozen=True)
class ExogeneityTest:
    """The Granger test of whether a candidate moves with the manipulated inputs.

    Attributes
    ----------
    p_value : float
        Unadjusted p-value of "no input lag helps predict the candidate": the larger of
        ``p_value_f`` and ``p_value_robust`` (1 when untestable).
    statistic : float
        The F statistic.
    inputs : tuple of str
        The inputs whose lag block alone rejects at ``alpha`` (the strongest one when none does).
    p_value_f : float
        The classical F test's p-value (NaN when untestable).
    p_value_robust : float
        The heteroskedasticity-robust score test's p-value (:func:`robust_score_test`; NaN when
        untestable).
    """

    p_value: float
    statistic: float
    inputs: tuple
    p_value_f: float = float("nan")
    p_value_robust: float = float("nan")


def exogeneity_test(c: np.ndarray, u: np.ndarray, input_names: Sequence[str], n_lag: int, alpha: float,
                    order: int = CANDIDATE_AR_ORDER, segments=None) -> ExogeneityTest:
    """Regress the candidate on its own lags and the inputs' lags; test the input lags (module docstring).

    The input lags count only when both the classical F test and the heteroskedasticity-robust score
    test (:func:`robust_score_test`) reject: the p-value is the larger of the two.  The F test alone
    assumes residuals of one size throughout; a channel that moves in a few steps (a feed changed by
    hand) leaves its own-lag residual as a few spikes, and when one falls a few samples after a sharp
    move of the inputs (a setpoint step) the input lags fit that spike and the F test rejects at
    many times its level.  The robust test weighs each sample by its own residual, so a few
    coincidences count as a few observations.

    Parameters
    ----------
    c : ndarray, shape (n_samples,)
        The candidate.
    u : ndarray, shape (n_samples, n_inputs)
        The manipulated inputs.
    input_names : sequence of str
    n_lag : int
        Input lags ``1 .. n_lag`` (the element test's).
    alpha : float
        Level at which an input's own block is named.
    order : int
        Own lags of the candidate.
    segments : sequence of (int, int), optional
        Data with gaps: only the rows whose lags stay inside their segment are regressed.
    """
    c = np.asarray(c, float)
    c = c - c.mean()
    moving = np.flatnonzero(moving_columns(u)).tolist()
    start = max(order, n_lag)
    if not moving or _row_count(c.shape[0], start, segments) < 3 * (order + n_lag * len(moving)) + 10:
        return ExogeneityTest(1.0, float("nan"), ())
    y = _rows(c, start, segments)
    own = _lags(c[:, None], order, start, segments)
    U = _lags(u[:, moving] - u[:, moving].mean(axis=0), n_lag, start, segments)
    base = np.column_stack([np.ones(y.shape[0]), own])
    rss_r, *_ = _rss(base, y)
    full = np.hstack([base, U])
    rss_f, rank_f, *_ = _rss(full, y)
    df_den = y.shape[0] - rank_f
    stat, p_f = f_test(rss_r, rss_f, n_lag * len(moving), df_den)
    _, p_robust = robust_score_test(base, U, y)
    p = max(p_f, p_robust)
    per_input = []
    for b, j in enumerate(moving):
        others = np.hstack([base, np.delete(U, np.s_[b * n_lag:(b + 1) * n_lag], axis=1)])
        rss_o, *_ = _rss(others, y)
        per_input.append((f_test(rss_o, rss_f, n_lag, df_den)[1], input_names[j]))
    named = tuple(name for pj, name in per_input if pj < alpha) or (min(per_input)[1],)
    return ExogeneityTest(float(p), float(stat), named, float(p_f), float(p_robust))


def robust_score_test(base: np.ndarray, tested: np.ndarray, y: np.ndarray):
    """Heteroskedasticity-robust score (LM) test of adding ``tested`` to the regression of ``y`` on ``base``.

    ``e`` is the residual of ``y`` on ``base``, ``R`` the columns of ``tested`` with ``base``
    partialled out, and ``z_k = e_k R_k`` the score of row ``k``; the statistic is
    ``s' (Z'Z)^+ s`` with ``s = sum_k z_k``, computed as ``n`` minus the residual sum of squares of a
    column of ones regressed on ``Z`` (Wooldridge 1991; Wooldridge, *Econometric Analysis of Cross
    Section and Panel Data*, 2010, section 4.2.3), and ``chi2(q)`` under the null, ``q`` the number
    of tested columns.  Its variance is the scores' own, so it needs no common residual size: a
    single large residual fitted by the tested columns adds about 1 to the statistic, where it can
    add hundreds to an F statistic.

    Parameters
    ----------
    base : ndarray, shape (n_rows, n_base)
        The restricted regression's columns.
    tested : ndarray, shape (n_rows, q)
        The columns whose coefficients are tested for zero.
    y : ndarray, shape (n_rows,)
        The regressand.

    Returns
    -------
    statistic : float
    p_value : float
        ``P(chi2(q) > statistic)``; (nan, 1.0) without tested columns or rows.
    """
    n, q = tested.shape
    if q == 0 or n == 0:
        return float("nan"), 1.0
    norms = np.sqrt(np.einsum("ij,ij->j", base, base))
    norms[norms == 0] = 1.0
    basis, _ = np.linalg.qr(base / norms)
    e = y - basis @ (basis.T @ y)
    R = tested - basis @ (basis.T @ tested)
    rss, *_ = _rss(e[:, None] * R, np.ones(n))
    stat = max(n - rss, 0.0)
    return float(stat), float(chi2_tail(stat, q))


@dataclasses.dataclass(frozen=True)
class CauseTest:
    """The test of one candidate's lags in one output row's element regression.

    Attributes
    ----------
    p_value : float
        Unadjusted p-value of "no lag of the whitened candidate helps".
    statistic : float
    delay : int
        First lag (samples) of its effect, as the element test reports it for an input: the start of
        the window of ``nb`` lags with the largest squared t-statistics (a dead time of ``theta``
        samples shows from lag ``theta + 1``).
    b : list of float
        The ``nb`` coefficients there (of the whitened candidate).
    """

    p_value: float
    statistic: float
    delay: int
    b: list


def cause_tests(d: np.ndarray, columns: np.ndarray, w: np.ndarray, na: int, nb: int, n_lag: int,
                start: int, output_spread: Optional[float] = None, segments=None,
                n_cand: Optional[int] = None) -> list:
    """The test of every candidate (whitened) as a cause of one output's prediction error.

    Parameters
    ----------
    d : ndarray, shape (n_samples,)
        The row's prediction error.
    columns : ndarray, shape (n_samples, n_moving)
        The model's moving columns (inputs and measured disturbances).
    w : ndarray, shape (n_samples, n_candidates)
        The whitened candidates (:func:`whiten`).
    na, nb : int
        ARX orders of the element test.
    n_lag : int
        Lags ``1 .. n_lag`` of the columns.
    start : int
        First regression row (every lag inside the record and past the whitening's start).
    output_spread : float, optional
        Standard deviation of the row's output, output units: a fit that leaves at most
        :data:`~mpm_monitor.core.statistics.EXACT_FIT` of it is exact (a log without noise) and its
        test is decided outright (:func:`~mpm_monitor.core.statistics.exact_fit_statistic`).  Default:
        only a residual of exactly 0.
    segments : sequence of (int, int), optional
        Data with gaps: only the rows at least ``start`` samples into their segment are regressed.
    n_cand : int, optional
        Lags ``1 .. n_cand`` of each candidate (default ``n_lag``; :data:`CANDIDATE_DELAY_FACTOR`).

    Returns
    -------
    list of CauseTest
        One per candidate.
    """
    from .arx import estimate_delay_from_lags
    from .statistics import exact_sigma2

    dc = d - d.mean()
    y = _rows(dc, start, segments)
    parts = [np.ones((y.shape[0], 1))]
    if na:
        parts.append(_lags(dc[:, None], na, start, segments))
    if columns.shape[1]:
        parts.append(_lags(columns - columns.mean(axis=0), n_lag, start, segments))
    base = np.hstack(parts)
    rss_r, *_ = _rss(base, y)
    out = []
    n_cand = n_lag if n_cand is None else int(n_cand)
    for k in range(w.shape[1]):
        W = _lags(w[:, k:k + 1], n_cand, start, segments)
        full = np.hstack([base, W])
        rss_f, rank_f, coef, var = _rss(full, y)
        df_den = y.shape[0] - rank_f
        floor = 0.0 if output_spread is None else max(df_den, 0) * exact_sigma2(output_spread)
        stat, p = f_test(rss_r, rss_f, n_cand, df_den, floor)
        g = coef[-n_cand:]
        s2 = rss_f / max(df_den, 1)
        std = np.sqrt(np.maximum(var[-n_cand:] * s2, 0.0))
        lag0 = estimate_delay_from_lags(g, std, nb, first_lag=1)
        out.append(CauseTest(float(p), float(stat), int(lag0), g[lag0 - 1:lag0 - 1 + nb].tolist()))
    return out


# ------------------------------------------------------------------------------------ the analysis
@dataclasses.dataclass
class CandidateReport:
    """What the candidate channels gave; :meth:`to_dict` is the report's ``candidates`` object.

    Attributes
    ----------
    tried : list of str
        Every channel selected.
    p_values : dict
        ``{name: {output: p}}``: the adjusted p-value (as an element's) of each exogenous usable
        candidate in each output row.
    unusable : dict
        ``{name: reason}``.
    not_exogenous : dict
        ``{name: "moves with u2: may be an effect of the loop, not a cause"}``.
    exogeneity_p_values : dict
        ``{name: p}``: Holm-adjusted p-value of the exogeneity test of each usable candidate.
    located : list of tuple of str
        ``(output, name)`` of the located candidate effects.
    added : list of str
        The candidates the repair added to the model (filled in by the repair).
    gaps : int
        Gaps in the record (missing samples); no regression row of the candidate tests reaches
        across one (each row's lags stay inside its segment).
    exogeneity_tests : dict
        ``{name: ExogeneityTest}``: each usable candidate's test before Holm's adjustment, with the F
        and robust p-values apart (not in the report's JSON).
    max_delay : int or None
        The longest dead time (samples) of an effect the cause tests search (their lags ``1 .. max_delay +
        nb``, :func:`candidate_lags`); None when none ran.
    """

    tried: list
    p_values: dict
    unusable: dict
    not_exogenous: dict
    exogeneity_p_values: dict
    located: list
    added: list = dataclasses.field(default_factory=list)
    gaps: int = 0
    exogeneity_tests: dict = dataclasses.field(default_factory=dict, repr=False)
    max_delay: Optional[int] = None

    def to_dict(self) -> dict:
        return {"tried": list(self.tried), "p_values": {k: dict(v) for k, v in self.p_values.items()},
                "unusable": dict(self.unusable), "not_exogenous": dict(self.not_exogenous),
                "exogeneity_p_values": dict(self.exogeneity_p_values),
                "located": [{"output": o, "candidate": c} for o, c in self.located], "added": list(self.added),
                "max_delay": self.max_delay}

    def warnings(self) -> list:
        """The unusable and the not-exogenous channels, in words."""
        out = [f"candidate {name} is unusable ({why}); it was not tested" for name, why in self.unusable.items()]
        out += [f"candidate {name} {why}; it was not tested as a cause" for name, why in self.not_exogenous.items()]
        return out

    def summary_lines(self) -> list:
        """Lines of the text summary."""
        lines = [f"candidate channels tried: {', '.join(self.tried) or 'none'}"]
        if self.p_values and self.max_delay is not None:
            lines[0] += (f" (effects searched for dead times up to {self.max_delay} samples, "
                         f"{CANDIDATE_DELAY_FACTOR} x --max-delay)")
        for name, ps in self.p_values.items():
            lines.append(f"  {name}: p = " + ", ".join(f"{o} {p:.2g}" for o, p in ps.items()))
        for name, why in self.not_exogenous.items():
            lines.append(f"  {name}: {why}")
        for name, why in self.unusable.items():
            lines.append(f"  {name}: unusable ({why})")
        added = ", ".join(self.added) if self.added else "none"
        lines.append(f"candidates added to the model as measured disturbances: {added}")
        return lines


@dataclasses.dataclass
class CandidateTest:
    """The element results with the candidates joined: the elements (their p-values adjusted in the
    larger family), the candidate entries, and the :class:`CandidateReport`."""

    elements: list
    candidate_elements: list
    report: CandidateReport


def candidate_lags(layout, options) -> int:
    """The lags ``1 .. n`` of a candidate in its cause test: dead times up to :data:`CANDIDATE_DELAY_FACTOR` times
    the layout's ``max_delay`` (samples), and ``nb`` more."""
    return CANDIDATE_DELAY_FACTOR * int(layout.max_delay) + int(options.nb)


def run_candidate_tests(model: PlantModel, data: LoggedData, chosen: CandidateChannels, columns: np.ndarray,
                    d: np.ndarray, elements: list, layout, options,
                    output_spread: Optional[np.ndarray] = None, still_outputs=()) -> CandidateTest:
    """Run the exogeneity and cause tests of the chosen candidates and adjust the element family.

    Parameters
    ----------
    model : PlantModel
    data : LoggedData
    chosen : CandidateChannels
    columns : ndarray, shape (n_samples, n_columns)
        The model's columns (inputs, then measured disturbances).
    d : ndarray, shape (n_samples, n_outputs)
        Prediction error of the model.
    elements : list of ElementResult
        The Delta element test's results; those with a p-value (not ambiguous) are the family the
        candidates join.
    layout : RegressionLayout
        Its ``n_lag_u`` and ``start``.
    options : AnalysisOptions
        Its ``alpha``, ``na`` and ``nb``.
    output_spread : ndarray, shape (n_outputs,), optional
        The outputs' standard deviations (output units) against which a cause test's fit is exact
        (:func:`cause_tests`); 0 for an output only a residual of exactly 0 fits exactly.  Default: that
        for every output.
    still_outputs : sequence of int
        Outputs that never move in the window (a stuck sensor): no candidate is tested on their rows.

    Returns
    -------
    CandidateTest
    """
    from .element_test import ElementResult
    from .statistics import N_FAMILIES, holm_adjust

    alpha, n_lag = options.alpha, layout.n_lag_u
    n_cand = candidate_lags(layout, options)
    u = np.asarray(data.u, dtype=float)
    segments = data.segments if len(data.segments) > 1 else None   # no regression row reaches across a gap
    moving = np.flatnonzero(moving_columns(columns)).tolist()
    start = max(layout.start, CANDIDATE_AR_ORDER + n_cand)
    # The cause test regresses an output's error on its own lags, the moving columns' and the candidate's: data
    # whose spans between gaps are shorter than its lags give it too few rows, or none (the tests broke down).
    rows, n_params = _row_count(d.shape[0], start, segments), 1 + options.na + len(moving) * n_lag + n_cand
    if chosen.names and rows < 3 * n_params + 10:
        where = "the spans between gaps give" if segments is not None else "the window gives"
        why = (f"{where} {rows} regression rows for its test (a row needs the {start} samples before it"
               f"{' in its span' if segments is not None else ''}), at least {3 * n_params + 10} needed")
        chosen = dataclasses.replace(chosen, names=(), values=np.zeros((d.shape[0], 0)),
                                     unusable={**{name: why for name in chosen.names}, **chosen.unusable})
    exo = {name: exogeneity_test(chosen.values[:, k], u, model.inputs, n_lag, alpha, segments=segments)
           for k, name in enumerate(chosen.names)}
    names = list(chosen.names)
    exo_adj = dict(zip(names, holm_adjust([exo[n].p_value for n in names]))) if names else {}
    not_exogenous = {n: f"moves with {', '.join(exo[n].inputs)}: may be an effect of the loop, not a cause"
                     for n in names if np.isfinite(exo_adj[n]) and exo_adj[n] < alpha}
    causes = [n for n in names if n not in not_exogenous]
    idx = [names.index(n) for n in causes]
    w = np.column_stack([whiten(chosen.values[:, k], segments=segments) for k in idx]) if idx else \
        np.zeros((d.shape[0], 0))
    tests = {}
    for i in range(model.n_outputs if causes else 0):
        if i in still_outputs:
            continue
        spread = None if output_spread is None else float(output_spread[i])
        for name, t in zip(causes, cause_tests(d[:, i], columns[:, moving], w, options.na, options.nb, n_lag, start,
                                               output_spread=spread, segments=segments, n_cand=n_cand)):
            tests[(i, name)] = t
    # One family: every element with a p-value and every (output, candidate) pair.
    family = [e for e in elements if e.p_value is not None and not e.ambiguous]
    raw = [e.p_value_raw if e.p_value_raw is not None else np.nan for e in family]
    raw += [tests[k].p_value for k in tests]
    adj = holm_adjust(np.array(raw, dtype=float)) if raw else np.zeros(0)
    p_of = [min(1.0, N_FAMILIES * a) if np.isfinite(a) else 1.0 for a in adj]
    new_elements, by_id = [], {id(e): p for e, p in zip(family, p_of)}
    for e in elements:
        if id(e) in by_id:
            # Holm's adjusted p-values only grow when hypotheses join the family, so the element's
            # own adjusted p-value is at most this one; what it holds above that is the confirmation
            # with the other located columns' tails (confirmation._confirm_with_tails), which a
            # larger family must not undo.
            p = max(by_id[id(e)], e.p_value)
            e = dataclasses.replace(e, p_value=float(p), mismatch=bool(p < alpha))
        new_elements.append(e)
    cand_p = dict(zip(tests, p_of[len(family):]))
    cand_elements, p_values, located = [], {n: {} for n in causes}, []
    for (i, name), t in tests.items():
        p = cand_p[(i, name)]
        out = model.outputs[i]
        hit = bool(p < alpha)
        p_values[name][out] = float(p)
        if hit:
            located.append((out, name))
        cand_elements.append(ElementResult(output=out, input=name, mismatch=hit, p_value=float(p),
                                           p_value_raw=t.p_value, statistic=t.statistic,
                                           kind="missing" if hit else None, delay=t.delay, b=t.b, role="candidate"))
    cand_elements.sort(key=lambda e: (model.outputs.index(e.output), causes.index(e.input)))
    located.sort(key=lambda k: (model.outputs.index(k[0]), causes.index(k[1])))
    report = CandidateReport(tried=list(chosen.tried), p_values=p_values, unusable=dict(chosen.unusable),
                             not_exogenous=not_exogenous, exogeneity_p_values={n: float(exo_adj[n]) for n in names},
                             located=located, gaps=max(len(data.segments) - 1, 0), exogeneity_tests=exo,
                             max_delay=n_cand - int(options.nb) if tests else None)
    return CandidateTest(elements=new_elements, candidate_elements=cand_elements, report=report)


# ------------------------------------------------------------------------------------ the repair's model
#: A channel whose mean is within this many standard deviations of 0 is taken as logged in deviations.
DEVIATION_SPREADS = 3.0


def default_operating_point(x: np.ndarray) -> float:
    """The operating point a candidate channel is added at before its repair (:func:`with_candidate_columns`).

    A channel that swings around 0 (its mean within :data:`DEVIATION_SPREADS` standard deviations of 0)
    is taken as logged in deviations: 0.  One that sits away from 0 is logged in its units (a feed
    temperature at 350 +- 2): its mean over the data, which
    :func:`~mpm_monitor.core.pipeline.analyze` then moves to centre the prediction error of the rows
    its repaired elements act on.

    Parameters
    ----------
    x : ndarray, shape (n_samples,)
        The channel, its logged units.

    Returns
    -------
    float
    """
    x = np.asarray(x, float)
    mean, std = float(np.mean(x)), float(np.std(x))
    return 0.0 if abs(mean) <= DEVIATION_SPREADS * std else mean


def with_candidate_columns(model: PlantModel, data: LoggedData, names: Sequence[str], nominal: Optional[dict] = None):
    """The model and the data with the candidates ``names`` as new measured disturbance columns.

    The new columns' elements are absent (gain 0; a zero step response), so the model's output and
    prediction error are those of ``model``; the data's ``dv`` gains the channels' samples (taken
    out of ``extra``).  A channel's operating point (``disturbance_nominal``) is ``nominal[name]``,
    by default :func:`default_operating_point`: 0 for a channel logged in deviations, its mean for one
    logged in its units (a feed temperature at 350 acts through its element as its deviation from
    there), so the repaired model predicts the logged outputs from the logged channel (in the
    deviations of data already converted, :attr:`~mpm_monitor.core.logged_data.LoggedData.deviations`,
    the column is that deviation).

    Returns
    -------
    (PlantModel, LoggedData)
    """
    names = [n for n in names if n not in model.disturbances]
    if not names:
        return model, data
    ny, k = model.n_outputs, len(names)
    values = [np.asarray(data.extra[n], float) for n in names]
    given = nominal or {}
    nominal = np.concatenate([np.asarray(model.disturbance_nominal, float),
                              [float(given[n]) if n in given else default_operating_point(x) for n, x in zip(names, values)]])
    if model.is_step_response:
        sr = np.concatenate([model.step_response, np.zeros((ny, k, model.step_length))], axis=1)
        new = model.replace(disturbances=model.disturbances + tuple(names), step_response=sr, lead=None,
                            time_constant2=None, integrating=None, disturbance_nominal=nominal)
    else:
        arrays = {key: np.hstack([np.asarray(getattr(model, key)),
                                  np.zeros((ny, k), dtype=np.asarray(getattr(model, key)).dtype)])
                  for key in PARAMETRIC_KEYS}
        new = model.replace(disturbances=model.disturbances + tuple(names), disturbance_nominal=nominal, **arrays)
    if data.deviations:
        values = [x - x0 for x, x0 in zip(values, nominal[model.n_disturbances:])]
    dv = np.column_stack([np.asarray(data.dv, float)] + values)
    extra = {key: v for key, v in data.extra.items() if key not in names}
    return new, dataclasses.replace(data, dv=dv, disturbances=tuple(data.disturbances) + tuple(names), extra=extra)


def without_columns(model: PlantModel, names: Sequence[str]) -> PlantModel:
    """``model`` without the measured disturbance columns ``names``."""
    drop = [model.n_inputs + model.disturbances.index(n) for n in names if n in model.disturbances]
    if not drop:
        return model
    keep = [j for j in range(model.n_columns) if j not in drop]
    dist = tuple(n for n in model.disturbances if n not in names)
    nominal = np.asarray(model.disturbance_nominal)[[j - model.n_inputs for j in keep if j >= model.n_inputs]]
    if model.is_step_response:
        return model.replace(disturbances=dist, step_response=np.asarray(model.step_response)[:, keep], lead=None,
                             time_constant2=None, integrating=None, disturbance_nominal=nominal)
    arrays = {key: np.asarray(getattr(model, key))[:, keep] for key in PARAMETRIC_KEYS}
    return model.replace(disturbances=dist, disturbance_nominal=nominal, **arrays)
