"""The least-squares problems of the two tests, by QR or from the Gram matrices of lagged signals.

Both tests are single-output ARX regressions over the same window (:class:`RegressionLayout`):

* S_Delta row test (:mod:`mpm_monitor.core.row_test`): for every output ``i``, ``z_i = eps_i - r_i``
  on the setpoints ``r_c(t - l)``, ``l = 0 .. n_lag_r - 1``, and its own lags ``z_i(t - l)``,
  ``l = 1 .. na``;
* Delta element test (:mod:`mpm_monitor.core.element_test`): for every output ``i``, the prediction
  error ``d_i`` on the model's columns ``u_j(t - l)``, ``l = 1 .. n_lag_u`` (the inputs, then the
  measured disturbances: every signal called ``u`` below has one column per model column), and its
  own lags.

Every row's regression shares its large block (lagged setpoints or lagged inputs) with the other
rows, so that block is factored once per window and each row adds its own columns by the
Frisch-Waugh-Lovell partition of :class:`~mpm_monitor.core.arx.SharedBlockRegression`.  Two
providers of these fits have the same methods (``row_regression``, ``row_fit``, ``row_fits``,
``input_regression``, ``element_fit``, ``short_arx``):

* :class:`QrRegressions` builds the lagged regressor matrices and factors them by QR: the
  reference path;
* :class:`GramRegressions` solves them from cross-product (Gram) matrices of the lagged signals
  (:class:`~mpm_monitor.core.lagged_gram.LaggedGram`), ``O(p^3)`` per analysis whatever the number
  of samples, and refits by QR every regression too ill-conditioned for the normal equations.  The
  batch analysis builds them for its window at once (:func:`window_regressions`); the sliding-window
  analyzer (:mod:`mpm_monitor.core.sliding`) keeps them up to date sample by sample.

The Gram matrices of lagged signals are built and updated in :mod:`mpm_monitor.core.lagged_gram`; the
fits solved from them, with their condition checks, are in :mod:`mpm_monitor.core.gram_fits`.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .arx import ArxFit, SharedBlockRegression, fit_arx, segment_lag_matrix, segment_rows
from .gram_fits import DEFAULT_MAX_CONDITION, GramBlockRegression, GramFit, IllConditioned, gram_arx
from .lagged_gram import LaggedGram, SampleBuffer
from .logged_data import moving_columns
from .model import PlantModel
from .segments import as_segments


# ----------------------------------------------------------------------------------------- layout
def _minimum_samples(n_params: int) -> int:
    return 3 * n_params + 50


@dataclasses.dataclass(frozen=True)
class RegressionLayout:
    """Lags and first usable sample of the tests, fixed by the model and the options.

    Attributes
    ----------
    max_delay : int
        Largest dead time searched (samples).
    n_lag_r : int
        Setpoint lags ``0 .. n_lag_r - 1`` of the row test.
    n_lag_u : int
        Column lags ``1 .. n_lag_u`` of the element test (inputs and measured disturbances).
    start : int
        First sample of the window used as a regression row (every lag is inside the window).
    min_samples : int
        Fewest samples the tests accept.
    """

    max_delay: int
    n_lag_r: int
    n_lag_u: int
    start: int
    min_samples: int


def regression_layout(model: PlantModel, options) -> RegressionLayout:
    """The :class:`RegressionLayout` of the tests for this model and these options.

    Parameters
    ----------
    model : PlantModel
    options : AnalysisOptions
        Its ``na``, ``nb`` and ``max_delay`` (:class:`mpm_monitor.core.analysis.AnalysisOptions`).

    Returns
    -------
    RegressionLayout
        ``max_delay`` defaults to the model's largest delay + 5 samples, at least 10.
    """
    ny, nu, na, nb = model.n_outputs, model.n_columns, options.na, options.nb
    dmax_model = int(model.delay_samples.max(initial=0))
    max_delay = options.max_delay if options.max_delay is not None else max(10, dmax_model + 5)
    n_lag_r = max_delay + nb + 1            # setpoint lags 0 .. max_delay + nb
    n_lag_u = max_delay + nb                # input lags 1 .. max_delay + nb
    n_params = max(ny * n_lag_r, nu * n_lag_u) + na
    return RegressionLayout(max_delay=max_delay, n_lag_r=n_lag_r, n_lag_u=n_lag_u,
                            start=max(n_lag_r - 1, n_lag_u, na), min_samples=_minimum_samples(n_params))


# ----------------------------------------------------------------------------------------- QR
class QrRegressions:
    """The least-squares problems of the tests, built from the window's signals and factored by QR.

    This is the reference path, and the fallback of the default one: the analysis solves the tests
    from the Gram matrices of the window (:func:`window_regressions`) and refits by this class every
    regression too ill-conditioned for the normal equations.  Pass an instance as
    ``analyze(..., regressions=...)`` (:func:`mpm_monitor.core.pipeline.analyze`) to factor every
    regression by QR.

    Parameters
    ----------
    r, z, d : ndarray, shape (n_samples, n_outputs)
        Setpoints, ``z = eps - r`` and prediction errors of the window.
    u : ndarray, shape (n_samples, n_columns)
        The model's columns: plant inputs, then measured disturbances.
    layout : RegressionLayout
    na, nb : int
        ARX orders.
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs of rows ``(first, end)`` of the signals, stacked one after
        the other; every run gives its own regression rows ``first + start .. end - 1``, so that no
        row's lags reach across a gap (docs/interfaces.md, "Gaps").  Default: one run.
    """

    def __init__(self, r, u, z, d, layout: RegressionLayout, na: int, nb: int, segments=None):
        self.r, self.u, self.z, self.d = r, u, z, d
        self.layout, self.na, self.nb = layout, na, nb
        self.segments = as_segments(segments)
        self._u_c = u - u.mean(axis=0)

    def _lags(self, x, lags) -> np.ndarray:
        return segment_lag_matrix(x, lags, self.layout.start, self.segments)

    @property
    def n_rows(self) -> int:
        """Regression rows (of every segment)."""
        start, n = self.layout.start, self.r.shape[0]
        return n - start if self.segments is None else sum(b - a - start for a, b in self.segments)

    def row_regression(self, r_moving: list) -> SharedBlockRegression:
        """Setpoint lags ``0 .. n_lag_r - 1`` of the moving setpoints (S_Delta row test)."""
        r, lay = self.r, self.layout
        r_c = r - r.mean(axis=0)
        Xr = self._lags(r_c[:, r_moving], range(0, lay.n_lag_r)) if r_moving else np.zeros((self.n_rows, 0))
        return SharedBlockRegression(Xr, [lay.n_lag_r] * len(r_moving))

    def row_fit(self, reg: SharedBlockRegression, i: int):
        """ARX of ``z_i`` on the setpoints (``reg``) and its own lags 1..na."""
        start = self.layout.start
        zi = self.z[:, i] - self.z[:, i].mean()
        own = -self._lags(zi, range(1, self.na + 1)) if self.na else None
        return reg.fit(segment_rows(zi, start, self.segments), own)

    def row_fits(self, reg: SharedBlockRegression, outputs) -> list:
        """:meth:`row_fit` of every output of ``outputs``."""
        return [self.row_fit(reg, i) for i in outputs]

    def input_regression(self, testable: list) -> SharedBlockRegression:
        """Input lags ``1 .. n_lag_u`` of the inputs ``testable`` (Delta element test)."""
        lay = self.layout
        X = self._lags(self._u_c[:, testable], range(1, lay.n_lag_u + 1)) if testable else \
            np.zeros((self.n_rows, 0))
        return SharedBlockRegression(X, [lay.n_lag_u] * len(testable))

    def element_fit(self, reg: SharedBlockRegression, i: int):
        """ARX of ``d_i`` on the input lags (``reg``) and its own lags 1..na."""
        start = self.layout.start
        di = self.d[:, i] - self.d[:, i].mean()
        own = -self._lags(di, range(1, self.na + 1)) if self.na else None
        return reg.fit(segment_rows(di, start, self.segments), own)

    def short_arx(self, i: int, nk: np.ndarray):
        """The short ARX of ``d_i`` at the delays ``nk`` (the paper's tables); an :class:`ArxFit`."""
        di = self.d[:, i] - self.d[:, i].mean()
        return fit_arx(di, self._u_c, self.na, self.nb, nk, segments=self.segments)


class GramRegressions:
    """The tests' least-squares problems solved from the Gram matrices of a window.

    Has the methods of :class:`QrRegressions`, for ``analyze(..., regressions=...)``.  A regression
    whose condition bound exceeds ``max_condition`` is refitted by that class from the window's
    signals.

    Parameters
    ----------
    row_gram, input_gram : LaggedGram
        Up to date over the window's regression rows.
    r, u, z, d : ndarray
        The window's signals (for the window means, the few rows of the short ARX outside the Gram
        rows, and the QR fallback).
    layout : RegressionLayout
    na, nb : int
    max_condition : float
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs of rows of the signals, as for :class:`QrRegressions`
        (the Gram matrices then sum the runs' regression rows).
    """

    def __init__(self, row_gram: LaggedGram, input_gram: LaggedGram, r, u, z, d, layout: RegressionLayout,
                 na: int, nb: int, max_condition: float = DEFAULT_MAX_CONDITION, segments=None):
        self.segments = as_segments(segments)
        self.row_gram, self._input_gram = row_gram, input_gram
        self._take_input_gram = None      # window_regressions: how to take the input Gram when first read
        self.r, self.u, self.z, self.d = r, u, z, d
        self.layout, self.na, self.nb = layout, na, nb
        self.max_condition = max_condition
        self.row_means = np.concatenate([r.mean(axis=0), z.mean(axis=0)])
        self.row_z = None             # the outputs whose z the row Gram holds (None: all; window_regressions)
        self._widen_row_gram = None   # window_regressions: the row Gram of every z, when a reduced one lacks a row
        self.input_means = np.concatenate([u.mean(axis=0), d.mean(axis=0)])
        self._inputs_move = bool(np.all(moving_columns(u)))     # as InputDesign.testable
        self._qr = None
        self._qr_regs = {}
        self.fallbacks = []          # names of the regressions refitted by QR
        self.batch = False           # built at once from the window's signals (window_regressions)
        self._row_regs = {}          # channels -> the row test's regression
        self._row_fits = {}          # (id of the regression, output) -> its row fit
        self._previous, self._same_rows = None, frozenset()

    @property
    def input_gram(self) -> LaggedGram:
        """The Gram of the input lags and the own lags (:func:`window_regressions` takes it when first read:
        a detection that tests no element needs none)."""
        if self._take_input_gram is not None:
            take, self._take_input_gram = self._take_input_gram, None
            take()
        return self._input_gram

    def row_test_part(self) -> "GramRegressions":
        """A copy with only what :meth:`reuse_rows_of` reads from it (the setpoints, ``z``, the row
        test's regressions and fits): kept for the detection after a repair without the Gram matrices."""
        out = object.__new__(GramRegressions)
        out.__dict__.update(batch=self.batch, layout=self.layout, na=self.na, nb=self.nb,
                            max_condition=self.max_condition, r=self.r, z=self.z, fallbacks=list(self.fallbacks),
                            _row_regs=dict(self._row_regs), _row_fits=dict(self._row_fits),
                            _previous=self._previous, _same_rows=self._same_rows, row_z=None, _widen_row_gram=None)
        return out

    def reuse_rows_of(self, other: "GramRegressions") -> None:
        """Take the S_Delta row test's regression and fits from ``other`` where they are the same numbers.

        ``other``: the regressions of the same window with another model (the detection before a
        repair).  Both must be built by :func:`window_regressions` with the same layout and orders
        from the same setpoints; then the setpoint block is the same, and so is the row fit of every
        output whose ``z`` column is the same.  Otherwise nothing is taken.
        """
        if not (isinstance(other, GramRegressions) and self.batch and other.batch
                and (self.layout, self.na, self.nb, self.max_condition)
                == (other.layout, other.na, other.nb, other.max_condition)
                and self.r.shape == other.r.shape and self.z.shape == other.z.shape
                and np.array_equal(self.r, other.r)):
            return
        self._previous = other
        self._same_rows = frozenset(i for i in range(self.z.shape[1]) if np.array_equal(self.z[:, i], other.z[:, i]))

    def rows_to_fit(self) -> Optional[list]:
        """The outputs whose row fit this window needs although it reuses another's (:meth:`reuse_rows_of`):
        those whose ``z`` differs, or that the other did not fit; None when nothing is reused."""
        if self._previous is None:
            return None
        fitted = {i for _, i in self._previous._row_fits}
        return [i for i in range(self.z.shape[1]) if i not in self._same_rows or i not in fitted]

    @property
    def row_gram_means(self) -> np.ndarray:
        """The window means of the row Gram's channels: the setpoints, then the ``z`` of :attr:`row_z`."""
        if self.row_z is None:
            return self.row_means
        ny = self.r.shape[1]
        return self.row_means[np.concatenate([np.arange(ny), ny + np.asarray(self.row_z, dtype=int)])]

    # -------------------------------------------------------------- helpers
    @property
    def qr(self) -> QrRegressions:
        if self._qr is None:
            self._qr = QrRegressions(self.r, self.u, self.z, self.d, self.layout, self.na, self.nb, self.segments)
        return self._qr

    def _qr_regression(self, kind: str, channels: tuple) -> SharedBlockRegression:
        key = (kind, channels)
        if key not in self._qr_regs:
            build = self.qr.row_regression if kind == "row" else self.qr.input_regression
            self._qr_regs[key] = build(list(channels))
        return self._qr_regs[key]

    def _own_columns(self, gram: LaggedGram, i: int):
        """Own columns ``-x_i(t-1) .. -x_i(t-na)`` and the target ``x_i(t)`` of output ``i``."""
        c = i if (gram is not self.row_gram or self.row_z is None) else self.row_z.index(i)
        own = [gram.column(1, c, lag) for lag in range(1, self.na + 1)]
        return own, [-1.0] * len(own), gram.column(1, c, 0)

    def _common(self, kind, channels):
        gram = self.row_gram if kind == "row" else self.input_gram
        lags = range(0, self.layout.n_lag_r) if kind == "row" else range(1, self.layout.n_lag_u + 1)
        return gram, [gram.column(0, c, lag) for c in channels for lag in lags]

    def _regression(self, kind: str, channels: list):
        gram, cols = self._common(kind, channels)
        means = self.row_gram_means if kind == "row" else self.input_means
        g, _ = gram.centred(cols, np.ones(len(cols)), cols, np.ones(len(cols)), means)
        n_lag = self.layout.n_lag_r if kind == "row" else self.layout.n_lag_u
        try:
            reg = GramBlockRegression(g, [n_lag] * len(channels), self.max_condition)
        except IllConditioned:
            self.fallbacks.append(f"{kind} regression")
            return self._qr_regression(kind, tuple(channels))
        reg.kind, reg.channels, reg.columns = kind, tuple(channels), cols
        return reg

    def _fit_arguments(self, kind: str, reg: GramBlockRegression, i: int) -> tuple:
        """The cross products of output ``i``'s fit in ``reg``: :class:`~mpm_monitor.core.gram_fits.GramFit`'s arguments
        ``(g_co, g_oo, g_cy, g_oy, g_yy, sum_y, n)``."""
        gram = self.row_gram if kind == "row" else self.input_gram
        means = self.row_gram_means if kind == "row" else self.input_means
        own, own_signs, target = self._own_columns(gram, i)
        cols_b = own + [target]
        signs_b = np.array(own_signs + [1.0])
        g_cb, _ = gram.centred(reg.columns, np.ones(len(reg.columns)), cols_b, signs_b, means)
        g_bb, sums_b = gram.centred(cols_b, signs_b, cols_b, signs_b, means)
        po = len(own)
        return (g_cb[:, :po], g_bb[:po, :po], g_cb[:, po], g_bb[:po, po], float(g_bb[po, po]), float(sums_b[po]),
                gram.n_rows)

    def _fits(self, kind: str, reg, outputs: list, together: bool = False) -> list:
        """The fits of the outputs in ``reg``; an ill-conditioned one refitted by QR.

        ``together``: their products with the shared block are solved at once
        (:meth:`~mpm_monitor.core.gram_fits.GramBlockRegression.projections`: a fit's numbers do not
        depend on the others solved with it); else by each :class:`~mpm_monitor.core.gram_fits.GramFit`
        (the element test's fits).
        """
        def qr_fit(qr_reg, i):
            return (self.qr.row_fit if kind == "row" else self.qr.element_fit)(qr_reg, i)
        if not isinstance(reg, GramBlockRegression):
            return [qr_fit(reg, i) for i in outputs]
        args = [self._fit_arguments(kind, reg, i) for i in outputs]
        common = [None] * len(outputs)
        if together and outputs:
            rhs = [GramFit.common_rhs(reg, g_co, g_oo, g_cy) for g_co, g_oo, g_cy, *_ in args]
            q, w = reg.projections(np.hstack(rhs))
            ends = np.cumsum([b.shape[1] for b in rhs])
            common = [(q[:, e - b.shape[1]:e], w[:, e - b.shape[1]:e]) for e, b in zip(ends, rhs)]
        fits = []
        for i, arg, solved in zip(outputs, args, common):
            try:
                fits.append(GramFit(reg, *arg, self.max_condition, common=solved))
            except IllConditioned:
                self.fallbacks.append(f"{kind} fit of output {i}")
                fits.append(qr_fit(self._qr_regression(kind, reg.channels), i))
        return fits

    # -------------------------------------------------------------- the QrRegressions interface
    @staticmethod
    def _row_key(r_moving) -> tuple:
        """The key of the row test's regression on the setpoints ``r_moving``."""
        return tuple(int(c) for c in r_moving)

    def row_regression(self, r_moving: list) -> SharedBlockRegression:
        """Setpoint lags of the moving setpoints (S_Delta row test)."""
        key = self._row_key(r_moving)
        if key not in self._row_regs:
            prev = self._previous
            if prev is not None and key in prev._row_regs:
                self._row_regs[key] = prev._row_regs[key]
                self.fallbacks += [f for f in prev.fallbacks if f == "row regression"]
            else:
                self._row_regs[key] = self._regression("row", list(key))
        return self._row_regs[key]

    def row_regression_pending(self, r_moving: list) -> bool:
        """Whether :meth:`row_regression` of these setpoints would factor its block now (not kept here, nor
        in the regressions it reuses)."""
        key = self._row_key(r_moving)
        prev = self._previous
        return key not in self._row_regs and not (prev is not None and key in prev._row_regs)

    def factored_row_regression(self, r_moving: list) -> Optional["GramBlockRegression"]:
        """:meth:`row_regression` of these setpoints when its block is well conditioned (its Gram
        factorisation), else None; for :meth:`keep_row_regression` in another process (a forked child
        computes it while this one goes on, :func:`~mpm_monitor.core.analysis.detect`)."""
        reg = self.row_regression(r_moving)
        return reg if isinstance(reg, GramBlockRegression) else None

    def keep_row_regression(self, r_moving: list, reg: "GramBlockRegression") -> None:
        """Keep ``reg``, :meth:`factored_row_regression` of these setpoints computed in another process (the
        same numbers), as their :meth:`row_regression`."""
        self._row_regs.setdefault(self._row_key(r_moving), reg)

    def row_fit(self, reg, i: int):
        """ARX of ``z_i`` on the setpoints and its own lags."""
        return self.row_fits(reg, [i])[0]

    def row_fits(self, reg, outputs) -> list:
        """:meth:`row_fit` of every output of ``outputs``; those not fitted yet are solved together
        (two triangular solves with the setpoint block for all, :meth:`_fits`)."""
        prev = self._previous
        fits = {}
        for i in outputs:
            key = (id(reg), int(i))
            if key in self._row_fits:
                fits[i] = self._row_fits[key][1]
            elif prev is not None and i in self._same_rows and key in prev._row_fits:
                fits[i] = prev._row_fits[key][1]
        new = [i for i in dict.fromkeys(outputs) if i not in fits]
        if self.row_z is not None and any(i not in self.row_z for i in new):
            self._widen_row_gram()        # a row whose z the reduced row Gram lacks: the Gram of every z
        for i, fit in zip(new, self._fits("row", reg, new, together=True)):
            if isinstance(fit, GramFit):
                # Kept for a detection of another model on this window (reuse_rows_of), without its
                # assembled inverse factor (p x p; the row test does not read it, rinv assembles it again).
                fit._rinv = None
                self._row_fits[(id(reg), int(i))] = (reg, fit)
            fits[i] = fit
        return [fits[i] for i in outputs]

    def input_regression(self, testable: list) -> SharedBlockRegression:
        """Input lags of the inputs ``testable`` (Delta element test)."""
        return self._regression("input", list(testable))

    def element_fit(self, reg, i: int):
        """ARX of ``d_i`` on the input lags and its own lags."""
        return self._fits("input", reg, [i])[0]

    def short_arx(self, i: int, nk: np.ndarray) -> ArxFit:
        """The short ARX of ``d_i`` at the delays ``nk`` (the paper's tables, which read its ``a``, ``b`` and
        fit: its ``condition_number`` is NaN, not computed, unless refitted by QR)."""
        na, nb = self.na, self.nb
        nk = np.asarray(nk, dtype=int)
        nu = self.u.shape[1]
        if (not self._inputs_move or np.any(nk < 1) or np.any(nk + nb - 1 > self.layout.n_lag_u)):
            self.fallbacks.append(f"short ARX of output {i}")
            return self.qr.short_arx(i, nk)
        gram = self.input_gram
        own, own_signs, target = self._own_columns(gram, i)
        cols = own + [gram.column(0, j, lag) for j in range(nu) for lag in range(nk[j], nk[j] + nb)] + [target]
        signs = np.array(own_signs + [1.0] * (nu * nb) + [1.0])
        g, sums = gram.centred(cols, signs, cols, signs, self.input_means)
        n = gram.n_rows
        # fit_arx starts at max(na, max(nk) + nb - 1) <= layout.start: add the rows before the Gram's.
        first = max(na, int(np.max(nk + nb - 1)) if nu else 0)
        start = self.layout.start
        if first < start:
            t = np.arange(first, start)[:, None] if self.segments is None else \
                np.concatenate([np.arange(a + first, a + start) for a, _ in self.segments])[:, None]
            d_mean = self.input_means[nu + i]
            lags = (nk[:, None] + np.arange(nb)).ravel()
            channels = np.repeat(np.arange(nu), nb)
            x = np.hstack([-(self.d[t - np.arange(1, na + 1), i] - d_mean),
                           self.u[t - lags, channels] - self.input_means[channels],
                           self.d[t, i] - d_mean])
            g = g + x.T @ x
            sums = sums + x.sum(axis=0)
            n += t.shape[0]
        try:
            return gram_arx(g, float(sums[-1]), n, na, nb, nk, self.max_condition, condition=False)
        except IllConditioned:
            self.fallbacks.append(f"short ARX of output {i}")
            return self.qr.short_arx(i, nk)


def window_regressions(r, u, z, d, layout: RegressionLayout, na: int, nb: int,
                       max_condition: float = DEFAULT_MAX_CONDITION, segments=None, jobs: int = 1,
                       previous: Optional[GramRegressions] = None) -> GramRegressions:
    """The tests' regressions on one window, from Gram matrices built at once (the batch analysis).

    Both Gram matrices are computed from the window's signals by
    :func:`~mpm_monitor.core.lagged_gram.lagged_cross_products`,
    centred by the window means as :class:`QrRegressions` centres its columns; every regression
    whose condition bound exceeds ``max_condition`` is refitted by QR (see the module docstring),
    so the results equal the QR path's to about ``max_condition^2 * 1e-16``.

    Parameters
    ----------
    r, z, d : ndarray, shape (n_samples, n_outputs)
        Setpoints, ``z = eps - r`` and prediction errors of the window.
    u : ndarray, shape (n_samples, n_columns)
        The model's columns (inputs, then measured disturbances).
    layout : RegressionLayout
    na, nb : int
    max_condition : float
    segments : sequence of (int, int), optional
        Data with gaps: the contiguous runs of rows ``(first, end)`` of the signals; each gives the
        regression rows ``first + start .. end - 1`` and the Gram matrices are their sums, so that no
        row's lags reach across a gap.  Default: one run.
    jobs : int
        Processes the Gram matrices' products are split over
        (:func:`~mpm_monitor.core.lagged_gram.lagged_cross_products`; one run only: with segments each is
        computed here).
    previous : GramRegressions, optional
        The regressions of the same window with another model (the detection before a repair): their
        row test's regression and fits are reused where they are the same numbers
        (:meth:`GramRegressions.reuse_rows_of`), and the row Gram then holds, besides the setpoints, only
        the ``z`` of the outputs still to fit (:meth:`GramRegressions.rows_to_fit`; after a repair
        of one row, 1 of 100 at 100x40: about a quarter of the products).  Each entry is the one the
        Gram of every ``z`` has.  Without segments only.

    Returns
    -------
    GramRegressions
    """
    n, ny = r.shape
    nu = u.shape[1]
    buf = SampleBuffer(3 * ny + nu, n, 0, fill=False)
    at = 0
    for part in (r, u, z, d):            # [r | u | z | d], each copied in once
        buf.data[:, at:at + part.shape[1]] = part
        at += part.shape[1]
    buf.count = n

    def signals(block):
        return {"r": block[:, :ny], "u": block[:, ny:ny + nu], "z": block[:, ny + nu:2 * ny + nu],
                "d": block[:, 2 * ny + nu:]}
    row_gram = LaggedGram([("r", ny, range(0, layout.n_lag_r)), ("z", ny, range(0, na + 1))], signals)
    input_gram = LaggedGram([("u", nu, range(1, layout.n_lag_u + 1)), ("d", ny, range(0, na + 1))], signals)
    regs = GramRegressions(row_gram, input_gram, r, u, z, d, layout, na, nb, max_condition, segments)
    if segments is None:
        regs.batch = True
        start = min(layout.start, n)
        if previous is not None:
            regs.reuse_rows_of(previous)
        to_fit = regs.rows_to_fit()
        if to_fit is not None and len(to_fit) < ny:
            z_at = ny + nu + np.asarray(to_fit, dtype=int)

            def some_z(block):
                return {"r": block[:, :ny], "z": block[:, z_at]}
            regs.row_z = tuple(to_fit)
            regs.row_gram = LaggedGram([("r", ny, range(0, layout.n_lag_r)), ("z", len(to_fit), range(0, na + 1))],
                                       some_z)

            def widen():
                regs.row_z, regs.row_gram = None, row_gram
                row_gram.rebuild(buf, start, n, regs.row_means, jobs)
            regs._widen_row_gram = widen
        regs.row_gram.rebuild(buf, start, n, regs.row_gram_means, jobs)
        regs._take_input_gram = lambda: input_gram.rebuild(buf, start, n, regs.input_means, jobs)
        return regs
    for gram, means in ((row_gram, regs.row_means), (input_gram, regs.input_means)):
        total, sums, rows = 0.0, 0.0, 0
        for a, b in regs.segments:
            gram.rebuild(buf, a + layout.start, b, means)
            total, sums, rows = total + gram.gram, sums + gram.sums, rows + gram.n_rows
        gram.gram, gram.sums, gram.lo, gram.hi, gram._full = total, sums, 0, rows, None
    return regs
