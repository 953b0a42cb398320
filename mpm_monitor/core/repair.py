"""Trace the prediction error to the effect the model lacks, re-estimate it, and show the gain.

After the analysis has located mismatched elements (paper section 2.2), this module answers the
control engineer's next questions (paper section 4, "type and severity" of each mismatch):

1. **Residual.**  ``d = y - Phat u`` of the model as given (paper eq. 9: ``d = Delta u + v``).
2. **Re-estimate.**  For each output row ``i`` with located elements ``J``, the elements
   ``(K_ij, tau_ij, theta_ij), j in J`` are fitted jointly to
   ``z_i = y_i - sum_{j not in J} Phat_ij u_j`` (the rest of the row held fixed) by a
   prediction-error method with an AR noise model (Ljung, *System Identification*, 2nd ed., 1999,
   sections 7.2 and 13.4)::

       e(k) = A(q) [ z_i(k) - sum_{j in J} G_j(q; K_j, a_j, L_j) u_j(k) - c' phi(k) ]
       G_j  = K_j (1 - a_j) q^{-L_j} / (1 - a_j q^{-1}),   a_j = exp(-T / tau_j)

   ``A(q) = 1 + alpha_1 q^-1 + ... + alpha_p q^-p`` whitens the coloured disturbance (the paper's
   ``v = w / (1 - 0.95 q^-1)`` plus white measurement noise), which makes the estimate consistent
   in closed loop where ``u`` is correlated with ``v`` (Ljung section 13.4, the "direct approach").
   ``phi`` holds the free responses of the row's states (the data may start mid-operation) and an
   offset.  The gains and ``c`` enter linearly and are eliminated by variable projection (Golub and
   Pereyra, 1973); the poles ``a_j`` are found by ``scipy.optimize.least_squares`` with ``A(q)``
   held, alternating with a least-squares fit of ``A(q)`` to the output error (generalized least
   squares, Ljung section 10.2); the input lag ``L_j`` (delay plus one sample for a lagged
   element) by a coordinate search on the integer grid around the model's value.
3. **Kind.**  On the whole record, every parameter of a located element is tested against the
   model's value by a likelihood-ratio test: the row is refitted with that parameter held and
   ``n ln(SSR_held / SSR_free)`` compared with chi-square(1) (Ljung section 16.5); the delay by
   its profile over the lag grid.  A parameter changed when the test rejects at
   ``1 - confidence_level`` *and* the change exceeds ``min_relative_change``.  The kind follows:
   one changed parameter -> gain, time_constant or delay; several -> mixed; a model gain of 0 with
   a significant fitted gain -> missing; nothing -> unknown (the element is kept).  The likelihood
   ratio, unlike a Wald test on the Jacobian, does not depend on the parametrization, which
   matters along the ridge where gain and time constant trade off (inputs that move together).
   The verdict's ``confidence`` is ``min over the tests of 1 - min(p/alpha, alpha/p)``: 0 when a
   p-value sits on the threshold, near 1 when every test is clear.
4. **Repair and validation.**  Only the changed parameters are refitted (all three for a missing
   element), on the first ``1 - holdout_fraction`` of the record; intervals at
   ``confidence_level`` come from the Jacobian of the full residual (``cov = s^2 (J'J)^-1``) for
   gain and time constant, from the profile statistic for the delay.  The repair is accepted only
   when the row's RMS prediction error on the held-out last part is lower than with the model as
   given; then it is refitted on the whole record.
5. **Unexplained disturbances.**  On every output, the (repaired) residual is tested for a level
   shift (sup-Wald test over the break date, Andrews 1993, p-values from the approximation of
   Estrella 2003) and for a linear drift (Wald test), each in a regression with AR(p) terms that
   absorb the coloured noise.  These are reported and never turned into element changes; when one
   shows on a repaired row, that row is re-estimated with the step (ramp) as a nuisance regressor
   so that it does not bias the elements.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional, Sequence

import numpy as np
from scipy import optimize, signal, stats

from .discretize import discretize
from .errors import ConfigurationError, InputError
from .logged_data import LoggedData
from .model import FopdtModel
from .signals import INITIAL_STATE_CHOICES, LoopSignals, compute_signals

KINDS = ("gain", "time_constant", "delay", "missing", "mixed", "unknown")

#: Bounds of a lag element's discrete pole ``a = exp(-T / tau)`` during the fit.
_POLE_MIN, _POLE_MAX = 1e-4, 0.9995


@dataclasses.dataclass(frozen=True)
class RepairOptions:
    """Options of :func:`repair_model`.

    Attributes
    ----------
    holdout_fraction : float
        Fraction of the record at its end kept out of the fit and used to validate the repair,
        in [0, 0.5].  0 disables the validation (with a warning).
    max_delay_shift : int
        Samples searched on either side of a located element's model delay (>= 0).  For an
        element the model does not have (gain 0) the search runs from 0 to the row's largest
        delay plus this many samples.
    noise_order : int
        Order ``p`` of the AR noise model ``A(q)`` of the prediction-error fit (0 = output error).
    confidence_level : float
        Level of the reported intervals and of the "significant change" decisions, in (0.5, 1): a
        parameter changed when the model's value lies outside its interval.  The default 0.999 is
        strict because the gain and the time constant of an element trade off against each other
        when inputs move together, which in a few thousand samples biases them by a fraction of a
        standard error; real mismatches worth a repair lie far outside.
    min_relative_change : float
        Smallest relative change of a gain or time constant that counts as a change, in [0, 1).
    refit_on_all : bool
        After a successful validation, refit the accepted elements on the whole record (delays
        searched again within a few samples of the validated ones).
    disturbance_alpha : float
        False-alarm probability per output of the unexplained-disturbance check (split equally
        between the step and the drift test), in (0, 0.5).
    disturbance_trim : float
        Fraction of the record at each end where a step is not searched (sup-Wald trimming), in
        [0.05, 0.3].
    min_holdout_improvement : float
        Relative reduction of the held-out RMS error that a row repair must achieve, in [0, 1).
    initial_state : {"estimate", "zero"}
        How the model's state at the first sample is treated (as in
        :func:`mpm_monitor.core.signals.compute_signals`); with "estimate" the fit also estimates the
        free response of the row.
    max_sweeps : int
        Coordinate sweeps of the delay search over the elements of a row (>= 1).
    """

    holdout_fraction: float = 0.25
    max_delay_shift: int = 10
    noise_order: int = 4
    confidence_level: float = 0.999
    min_relative_change: float = 0.05
    refit_on_all: bool = True
    disturbance_alpha: float = 0.01
    disturbance_trim: float = 0.15
    min_holdout_improvement: float = 0.0
    initial_state: str = "estimate"
    max_sweeps: int = 3

    def __post_init__(self):
        check_repair_options(self)


def check_repair_options(opts: RepairOptions) -> None:
    """Raise :class:`ConfigurationError` naming the first option outside its range."""

    def is_int(x):
        return isinstance(x, (int, np.integer)) and not isinstance(x, bool)

    def is_num(x):
        return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)

    if not (is_num(opts.holdout_fraction) and 0.0 <= opts.holdout_fraction <= 0.5):
        raise ConfigurationError(f"holdout_fraction: expected a number in [0, 0.5], got {opts.holdout_fraction!r}")
    if not (is_int(opts.max_delay_shift) and 0 <= opts.max_delay_shift <= 1000):
        raise ConfigurationError(f"max_delay_shift: expected an integer number of samples in [0, 1000], "
                                 f"got {opts.max_delay_shift!r}")
    if not (is_int(opts.noise_order) and 0 <= opts.noise_order <= 50):
        raise ConfigurationError(f"noise_order: expected an integer in [0, 50], got {opts.noise_order!r}")
    if not (is_num(opts.confidence_level) and 0.5 < opts.confidence_level < 1.0):
        raise ConfigurationError(f"confidence_level: expected a number in (0.5, 1), got {opts.confidence_level!r}")
    if not (is_num(opts.min_relative_change) and 0.0 <= opts.min_relative_change < 1.0):
        raise ConfigurationError(f"min_relative_change: expected a number in [0, 1), got {opts.min_relative_change!r}")
    if not isinstance(opts.refit_on_all, bool):
        raise ConfigurationError(f"refit_on_all: expected true or false, got {opts.refit_on_all!r}")
    if not (is_num(opts.disturbance_alpha) and 0.0 < opts.disturbance_alpha < 0.5):
        raise ConfigurationError(f"disturbance_alpha: expected a number in (0, 0.5), got {opts.disturbance_alpha!r}")
    if not (is_num(opts.disturbance_trim) and 0.05 <= opts.disturbance_trim <= 0.3):
        raise ConfigurationError(f"disturbance_trim: expected a number in [0.05, 0.3], got {opts.disturbance_trim!r}")
    if not (is_num(opts.min_holdout_improvement) and 0.0 <= opts.min_holdout_improvement < 1.0):
        raise ConfigurationError(f"min_holdout_improvement: expected a number in [0, 1), "
                                 f"got {opts.min_holdout_improvement!r}")
    if opts.initial_state not in INITIAL_STATE_CHOICES:
        raise ConfigurationError(f"initial_state: expected one of {', '.join(INITIAL_STATE_CHOICES)}, "
                                 f"got {opts.initial_state!r}")
    if not (is_int(opts.max_sweeps) and 1 <= opts.max_sweeps <= 20):
        raise ConfigurationError(f"max_sweeps: expected an integer in [1, 20], got {opts.max_sweeps!r}")


@dataclasses.dataclass
class RepairResult:
    """What :func:`repair_model` found and changed.

    Attributes
    ----------
    model : FopdtModel
        The repaired model: the input model with only accepted located elements changed.
    changes : list of dict
        One entry per located element: ``output``, ``input`` (names), ``kind``, ``before`` and
        ``after`` (``gain``, ``time_constant`` s, ``delay`` s; ``after`` equals ``before`` when not
        applied), ``estimate`` (the fitted parameters, also when not applied), ``confidence`` in
        [0, 1], ``interval`` (``[lo, hi]`` per parameter at ``confidence_level``), ``applied``,
        ``evidence`` (``p_gain``, ``p_time_constant``, ``p_delay``: likelihood-ratio p-values of
        "unchanged"; ``p_unchanged_jointly``; ``condition_number`` of the row fit; ``samples``;
        ``noise_model`` ``[alpha_1 .. alpha_p]``), and when not applied ``reason`` (and
        ``fitted_kind`` when the held-out validation rejected it).
    kinds : dict
        ``{(i, j): kind}`` for every located element (indices).
    error_before, error_after : dict
        ``{output name: RMS of d}`` over the whole record with the model as given / as repaired.
    fit_before, fit_after : dict
        ``{output name: fit %}``, ``100 (1 - ||y - yhat|| / ||y - mean y||)``.
    holdout_error_before, holdout_error_after : dict
        ``{output name: RMS of d}`` over the held-out last part, with the model as given / with the
        candidate fitted on the first part only (empty when ``holdout_fraction`` is 0).  On a row
        re-estimated with an unexplained step or drift, both are taken with that disturbance
        projected out.
    disturbances : list of dict
        Outputs whose residual holds a step or drift no input explains (``output``, ``kind``
        "step"/"drift", ``size`` in output units, ``time`` in seconds, ``p_value``, ``statistic``).
    warnings : list of str
        What limits the conclusions, in words.
    n_samples, n_fit : int
        Samples in the record and in the fit part.
    """

    model: FopdtModel
    changes: list
    kinds: dict
    error_before: dict
    error_after: dict
    fit_before: dict
    fit_after: dict
    holdout_error_before: dict
    holdout_error_after: dict
    disturbances: list
    warnings: list
    n_samples: int = 0
    n_fit: int = 0
    options: RepairOptions = RepairOptions()

    def to_dict(self) -> dict:
        """The ``repair`` object of the analysis report (CONTRACTS section 3), plain JSON values."""
        return _jsonable({
            "model": self.model.to_dict(),
            "changes": self.changes,
            "error_before": self.error_before,
            "error_after": self.error_after,
            "fit_before": self.fit_before,
            "fit_after": self.fit_after,
            "holdout_error_before": self.holdout_error_before,
            "holdout_error_after": self.holdout_error_after,
            "disturbances": self.disturbances,
            "warnings": list(self.warnings),
            "samples": self.n_samples,
            "fit_samples": self.n_fit,
            "holdout_fraction": self.options.holdout_fraction,
            "confidence_level": self.options.confidence_level,
        })


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    return x


# --------------------------------------------------------------------------------------------
# Row fit
# --------------------------------------------------------------------------------------------

def _element_lag(tau: float, delay_samples: int) -> int:
    """Input lag ``L`` of an element: ``n_d + 1`` with a lag, ``n_d`` without (see discretize)."""
    return int(delay_samples) + 1 if tau > 0 else int(delay_samples)


def _pole_of(tau: float, ts: float) -> float:
    """Discrete pole ``exp(-T / tau)`` (the lower pole bound for ``tau = 0``)."""
    return min(max(math.exp(-ts / tau), _POLE_MIN), _POLE_MAX) if tau > 0 else _POLE_MIN


def _element_params(gain: float, pole: float, lag: int, ts: float):
    """(gain, time constant in s, delay in s) of a fitted element; a vanishing pole means no lag."""
    if pole <= 2 * _POLE_MIN:
        return float(gain), 0.0, float(lag) * ts
    return float(gain), float(-ts / math.log(pole)), float(max(lag - 1, 0)) * ts


class _TooShort(Exception):
    """The fit window is too short for the lags searched (turned into a warning)."""


@dataclasses.dataclass
class _ElementSpec:
    """Which parameters of a located element the fit may move.

    ``gain``/``pole`` are the held values (or the start values when free); ``window`` is the
    inclusive range of input lags searched (``lo == hi`` holds the lag).
    """

    gain_free: bool
    pole_free: bool
    gain: float
    pole: float
    window: tuple

    @property
    def lag_free(self) -> bool:
        return self.window[0] != self.window[1]


@dataclasses.dataclass
class _Fit:
    """One converged fit of a row for given lags and noise model."""

    lags: tuple
    poles: np.ndarray   # (n_located,)
    gains: np.ndarray   # (n_located,)
    nuisance: np.ndarray
    ssr: float
    n_resid: int


class _RowProblem:
    """The prediction-error fit of the located elements of one row (see the module docstring).

    Parameters
    ----------
    z : ndarray, shape (n_samples,)
        Output minus the response of the row's fixed elements (from rest).
    u : ndarray, shape (n_samples, n_located)
        The inputs of the located elements.
    specs : list of _ElementSpec
        One per located element.
    n_fit : int
        Samples ``0 .. n_fit - 1`` are used.
    skip : int
        Samples at the start left out of the cost: the largest input lag of the row, since the
        inputs before the record are unknown.
    fixed_poles : sequence of float
        Poles of the row's fixed lag elements, whose free responses are estimated.
    free_response : bool
        Estimate the free responses (the initial state) of the row.
    noise_order : int
        ``p`` of ``A(q)``.
    extra : ndarray, shape (n_samples, n_extra), optional
        Nuisance regressors for an unmeasured disturbance (a step, a ramp), filtered by ``A(q)``
        like the output, so that the disturbance is never absorbed by an element.

    Notes
    -----
    Filtering commutes, so ``A(q) G(q) u = G(q) (A(q) u)``: the inputs are prefiltered once per
    noise model.  For ``k >= p``, ``A(q) a^k = A(1/a) a^k``: a free response stays a free response
    with another (free) coefficient, and the cost window starts at ``skip + p``.
    """

    def __init__(self, z, u, specs, n_fit, skip, fixed_poles, free_response, noise_order, extra=None):
        self.z = np.asarray(z, float)[:n_fit]
        self.extra = None if extra is None else np.asarray(extra, float).reshape(len(z), -1)[:n_fit]
        self.u = np.asarray(u, float)[:n_fit]
        self.specs = list(specs)
        self.n_fit = int(n_fit)
        self.p = int(noise_order)
        self.free = bool(free_response)
        self.start = int(skip) + self.p
        needed = max(150, 20 * (3 * len(self.specs) + self.p + 3))
        if self.n_fit - self.start < needed:
            raise _TooShort(f"{self.n_fit} samples are too few for input lags up to {skip} samples "
                            f"(at least {needed} beyond them needed)")
        self.kw = np.arange(self.start, self.n_fit, dtype=float)
        cols = [np.ones_like(self.kw)]
        if self.free:
            for a in sorted(set(np.round(np.asarray(fixed_poles, float), 12))):
                if 0 < a < 1 and a ** self.start > 1e-12:
                    cols.append(a ** self.kw)
        self.fixed_cols = np.column_stack(cols)
        self.pole_free_idx = [m for m, s in enumerate(self.specs) if s.pole_free]
        self.gain_free_idx = [m for m, s in enumerate(self.specs) if s.gain_free]
        self.set_ar(np.zeros(self.p))

    @property
    def n_located(self) -> int:
        return len(self.specs)

    def set_ar(self, ar) -> None:
        """Use the noise model ``A(q) = 1 + ar_1 q^-1 + ... + ar_p q^-p``."""
        self.ar = np.asarray(ar, float).copy()
        if self.p:
            num = np.concatenate([[1.0], self.ar])
            self.zf = signal.lfilter(num, [1.0], self.z)
            self.uf = signal.lfilter(num, [1.0], self.u, axis=0)
        else:
            self.zf, self.uf = self.z, self.u
        self.xf = None if self.extra is None else self._filtered_extra(self.ar)

    def _filtered_extra(self, ar):
        if self.p == 0:
            return self.extra[self.start:]
        return signal.lfilter(np.concatenate([[1.0], ar]), [1.0], self.extra, axis=0)[self.start:]

    def poles_from(self, x):
        poles = np.array([s.pole for s in self.specs], float)
        poles[self.pole_free_idx] = x
        return poles

    def _unit(self, src, m, pole, lag):
        """Window of the unit-gain response of element ``m`` to ``src[:, m]``."""
        base = signal.lfilter([1.0 - pole], [1.0, -pole], src[:self.n_fit - lag, m])
        return base[self.start - lag:]

    def _design(self, poles, lags, src, filtered=True):
        known = np.zeros(self.kw.shape[0])
        gcols = []
        for m, spec in enumerate(self.specs):
            col = self._unit(src, m, poles[m], lags[m])
            if spec.gain_free:
                gcols.append(col)
            else:
                known += spec.gain * col
        cols = gcols + [self.fixed_cols]
        if self.free:
            cols.append(np.column_stack([poles[m] ** self.kw for m in range(self.n_located)]))
        if self.extra is not None:
            cols.append(self.xf if filtered else self.extra[self.start:])
        return known, np.column_stack(cols)

    @staticmethod
    def _solve(phi, target):
        scale = np.sqrt(np.einsum("ij,ij->j", phi, phi))
        scale[scale == 0] = 1.0
        ps = phi / scale
        gram = ps.T @ ps
        beta = np.linalg.pinv(gram, rcond=1e-12, hermitian=True) @ (ps.T @ target)
        return beta / scale

    def projected(self, poles, lags):
        """Prefiltered residual with the linear parameters eliminated, and those parameters."""
        known, phi = self._design(poles, lags, self.uf)
        target = self.zf[self.start:] - known
        beta = self._solve(phi, target)
        return target - phi @ beta, beta

    def _make_fit(self, poles, lags, resid, beta):
        gains = np.array([s.gain for s in self.specs], float)
        ng = len(self.gain_free_idx)
        gains[self.gain_free_idx] = beta[:ng]
        return _Fit(lags=tuple(int(v) for v in lags), poles=np.asarray(poles, float).copy(), gains=gains,
                    nuisance=beta[ng:], ssr=float(resid @ resid), n_resid=resid.shape[0])

    def evaluate(self, poles, lags) -> _Fit:
        """Fit with the poles held (linear parameters re-estimated)."""
        resid, beta = self.projected(poles, lags)
        return self._make_fit(poles, lags, resid, beta)

    def fit(self, lags, poles0) -> _Fit:
        """Least-squares fit of the free poles for the given lags and the current noise model."""
        poles0 = np.clip(np.asarray(poles0, float), _POLE_MIN, _POLE_MAX)
        if not self.pole_free_idx:
            return self.evaluate(poles0, lags)
        x0 = poles0[self.pole_free_idx]

        def fun(x):
            return self.projected(self.poles_from(x), lags)[0]

        sol = optimize.least_squares(fun, x0, bounds=(_POLE_MIN, _POLE_MAX), method="trf",
                                     xtol=1e-9, ftol=1e-9, gtol=1e-9, max_nfev=60, diff_step=1e-6)
        return self.evaluate(self.poles_from(sol.x), lags)

    def update_ar(self, fit: _Fit) -> None:
        """Re-estimate ``A(q)`` by least squares on the unfiltered output error of ``fit``."""
        if self.p == 0:
            return
        known, phi = self._design(fit.poles, fit.lags, self.u, filtered=False)
        ng = len(self.gain_free_idx)
        r = self.z[self.start:] - known - phi[:, :ng] @ fit.gains[self.gain_free_idx]
        nuis = phi[:, ng:]
        r = r - nuis @ self._solve(nuis, r)
        target, lags = _ar_design(r, self.p)
        coef, *_ = np.linalg.lstsq(lags, target, rcond=None)
        self.set_ar(-coef)

    def full_residual(self, theta, lags):
        """Prefiltered residual as a function of ``[free gains, free poles, ar, nuisance]``."""
        ng, npf = len(self.gain_free_idx), len(self.pole_free_idx)
        gains = np.array([s.gain for s in self.specs], float)
        gains[self.gain_free_idx] = theta[:ng]
        poles = self.poles_from(theta[ng:ng + npf])
        ar = theta[ng + npf:ng + npf + self.p]
        nuis = theta[ng + npf + self.p:]
        num = np.concatenate([[1.0], ar])
        zf = signal.lfilter(num, [1.0], self.z)[self.start:]
        uf = signal.lfilter(num, [1.0], self.u, axis=0)
        out = zf.copy()
        for m in range(self.n_located):
            out -= gains[m] * self._unit(uf, m, poles[m], lags[m])
        cols = [self.fixed_cols]
        if self.free:
            cols.append(np.column_stack([poles[m] ** self.kw for m in range(self.n_located)]))
        if self.extra is not None:
            cols.append(self._filtered_extra(ar))
        return out - np.column_stack(cols) @ nuis

    def covariance(self, fit: _Fit):
        """Covariance of the free gains and poles from the Jacobian of the full residual.

        Returns
        -------
        cov_gain, cov_pole : ndarray, shape (n_located,)
            Variances (0 for held parameters).
        cond : float
            Condition number of the column-scaled Jacobian block of the free gains and poles.
        """
        ng, npf = len(self.gain_free_idx), len(self.pole_free_idx)
        theta = np.concatenate([fit.gains[self.gain_free_idx], fit.poles[self.pole_free_idx], self.ar,
                                fit.nuisance])
        r0 = self.full_residual(theta, fit.lags)
        jac = np.empty((r0.shape[0], theta.shape[0]))
        for m in range(theta.shape[0]):
            h = 1e-6 * max(1e-2, abs(theta[m]))
            if ng <= m < ng + npf:
                h = min(1e-6, 0.5 * (1.0 - theta[m]))
            tp, tm = theta.copy(), theta.copy()
            tp[m] += h
            tm[m] -= h
            jac[:, m] = (self.full_residual(tp, fit.lags) - self.full_residual(tm, fit.lags)) / (2 * h)
        dof = max(r0.shape[0] - theta.shape[0], 1)
        s2 = float(r0 @ r0) / dof
        scale = np.sqrt(np.sum(jac ** 2, axis=0))
        scale[scale == 0] = 1.0
        js = jac / scale
        cov = s2 * np.linalg.pinv(js.T @ js, rcond=1e-13, hermitian=True) / np.outer(scale, scale)
        var = np.diag(cov)
        var_gain = np.zeros(self.n_located)
        var_pole = np.zeros(self.n_located)
        var_gain[self.gain_free_idx] = var[:ng]
        var_pole[self.pole_free_idx] = var[ng:ng + npf]
        if ng + npf:
            sv = np.linalg.svd(js[:, :ng + npf], compute_uv=False)
            cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
        else:
            cond = 1.0
        return np.maximum(var_gain, 0.0), np.maximum(var_pole, 0.0), cond


@dataclasses.dataclass
class _RowEstimate:
    """Result of the search of one row: the fit, the lag profiles and the parameter variances."""

    fit: _Fit
    profiles: list      # per located element: {lag: ssr} with the other lags at their optimum
    var_gain: np.ndarray
    var_pole: np.ndarray
    cond: float
    edge: list          # per element: True when the best lag is at the edge of its window
    ar: np.ndarray


_TAU_GRID = (0.5, 0.7, 1.0, 1.4, 2.0)


def _search_row(problem: _RowProblem, lags0, max_sweeps: int, ar_iterations: int = 3,
                need_cov: bool = True) -> _RowEstimate:
    """Lags on the integer grid by coordinate search; poles by least squares; then the noise model.

    Phase 1 (output error, ``A = 1``): for each element with a free lag, a quick scan of (lag, pole)
    with the other parameters held picks candidates, which are fitted; sweeps repeat until no lag
    moves.  Phase 2: the noise model and the fit are alternately re-estimated.  Phase 3: each lag
    is moved by one sample while that lowers the cost, and its profile is recorded.
    """
    n = problem.n_located
    specs = problem.specs
    cache = {}

    def full(lg, poles_start):
        key = tuple(int(v) for v in lg)
        if key not in cache:
            cache[key] = problem.fit(key, poles_start)
        return cache[key]

    lags = [int(v) for v in lags0]
    best = full(lags, [s.pole for s in specs])
    for _ in range(max_sweeps):
        moved = False
        for m in range(n):
            spec = specs[m]
            if not spec.lag_free:
                continue
            base_tau = -1.0 / math.log(min(max(best.poles[m], _POLE_MIN), _POLE_MAX))
            grid = _TAU_GRID if spec.pole_free else (1.0,)
            cand = []
            for lag in range(spec.window[0], spec.window[1] + 1):
                lg = list(lags)
                lg[m] = lag
                for f in grid:
                    poles = best.poles.copy()
                    poles[m] = min(max(math.exp(-1.0 / (base_tau * f)), _POLE_MIN), _POLE_MAX)
                    cand.append((problem.evaluate(poles, lg).ssr, lag, poles))
            cand.sort(key=lambda c: c[0])
            tried = set()
            for _, lag, poles in cand:
                if lag in tried:
                    continue
                if len(tried) >= 3:
                    break
                tried.add(lag)
                lg = list(lags)
                lg[m] = lag
                f = full(lg, poles)
                if f.ssr < best.ssr * (1 - 1e-12):
                    moved = moved or lag != lags[m]
                    best, lags = f, lg
        if not moved:
            break
    # Phase 2: the noise model.
    for _ in range(ar_iterations if problem.p else 0):
        problem.update_ar(best)
        cache.clear()
        best = full(lags, best.poles)
    # Phase 3: local moves and profiles.
    improved = True
    while improved:
        improved = False
        for m in range(n):
            if not specs[m].lag_free:
                continue
            for step in (-1, 1):
                lag = lags[m] + step
                if specs[m].window[0] <= lag <= specs[m].window[1]:
                    lg = list(lags)
                    lg[m] = lag
                    f = full(lg, best.poles)
                    if f.ssr < best.ssr * (1 - 1e-12):
                        best, lags, improved = f, lg, True
    if need_cov:
        var_gain, var_pole, cond = problem.covariance(best)
    else:
        var_gain, var_pole, cond = np.zeros(n), np.zeros(n), float("nan")
    profiles = []
    for m in range(n):
        prof = {}
        for key, f in cache.items():
            if all(key[q] == lags[q] for q in range(n) if q != m):
                prof[key[m]] = f.ssr
        profiles.append(prof)
    edge = [specs[m].lag_free and lags[m] in specs[m].window for m in range(n)]
    est = _RowEstimate(fit=best, profiles=profiles, var_gain=var_gain, var_pole=var_pole, cond=cond, edge=edge,
                       ar=problem.ar.copy())
    est._full = full  # noqa: SLF001  (used by the profile intervals)
    return est


def _lag_lr(est: _RowEstimate, m: int, lag: int, specs) -> float:
    """Profile likelihood-ratio statistic ``n ln(SSR_lag / SSR_best)`` of element ``m`` at ``lag``."""
    fit = est.fit
    if lag not in est.profiles[m]:
        lg = list(fit.lags)
        lg[m] = lag
        est.profiles[m][lag] = est._full(lg, fit.poles).ssr
    return fit.n_resid * math.log(max(est.profiles[m][lag], 1e-300) / max(fit.ssr, 1e-300))


def _lag_interval(est: _RowEstimate, m: int, specs, threshold: float):
    """Contiguous lags of element ``m`` whose profile statistic stays below ``threshold``."""
    lo = hi = est.fit.lags[m]
    w = specs[m].window
    while lo - 1 >= w[0] and _lag_lr(est, m, lo - 1, specs) <= threshold:
        lo -= 1
    while hi + 1 <= w[1] and _lag_lr(est, m, hi + 1, specs) <= threshold:
        hi += 1
    return lo, hi


# --------------------------------------------------------------------------------------------
# Unexplained disturbance (step or drift) test
# --------------------------------------------------------------------------------------------

def sup_wald_p_value(statistic: float, trim: float) -> float:
    """Approximate p-value of the sup-Wald statistic of one break in the mean.

    Parameters
    ----------
    statistic : float
        ``sup_pi W(pi)`` over break fractions ``pi`` in ``[trim, 1 - trim]``.
    trim : float
        Trimming fraction.

    Notes
    -----
    Asymptotically ``W(pi) -> B(pi)^2 / (pi (1 - pi))`` with ``B`` a Brownian bridge (Andrews,
    *Econometrica* 61, 1993).  The tail ``P(sup > c)`` is approximated by
    ``sqrt(c) e^{-c/2} / sqrt(2 pi) [(1 - 1/c) ln(lambda) + 4/c]`` with
    ``lambda = (1 - trim)^2 / trim^2`` (Estrella, *Econometric Theory* 19, 2003).  The
    approximation is slightly conservative: 0.054 at Andrews' 5 % value 8.68, 0.011 at the 1 %
    value 12.16 for ``trim = 0.15``.
    """
    c = float(statistic)
    if not math.isfinite(c):
        return 0.0
    if c <= 1.0:
        return 1.0
    lam = (1.0 - trim) ** 2 / trim ** 2
    p = math.sqrt(c) * math.exp(-c / 2.0) / math.sqrt(2.0 * math.pi) * ((1.0 - 1.0 / c) * math.log(lam) + 4.0 / c)
    return float(min(1.0, max(0.0, p)))


def _ar_design(x: np.ndarray, p: int):
    """Rows ``k = p .. n-1``: target ``x(k)`` and lag columns ``x(k-1) .. x(k-p)``."""
    n = x.shape[0]
    lagcols = [x[p - l:n - l] for l in range(1, p + 1)]
    return x[p:], (np.column_stack(lagcols) if lagcols else np.zeros((n - p, 0)))


def unexplained_disturbance(d: np.ndarray, sample_time: float = 1.0, alpha: float = 0.01, trim: float = 0.15,
                            noise_order: int = 4) -> dict:
    """Test one residual for a step or a linear drift on top of AR(p)-coloured noise.

    Parameters
    ----------
    d : ndarray, shape (n_samples,)
        The prediction error of one output (output units).
    sample_time : float
        Seconds per sample, for the reported time and rate.
    alpha : float
        False-alarm probability of the combined test; each of the two tests runs at ``alpha / 2``.
    trim : float
        Fraction of the record at each end where no step is searched.
    noise_order : int
        Order ``p`` of the AR terms.

    Returns
    -------
    dict
        ``detected`` (bool), ``kind`` ("step", "drift" or None), ``size`` (output units: the step
        height, or the drift over the whole record), ``time`` (s, the step instant or None),
        ``rate`` (output units per second, drift only), ``p_value`` (the smaller of the two tests,
        Bonferroni-adjusted), ``p_step``, ``p_drift``, ``statistic`` (of the reported kind).

    Notes
    -----
    Step: in ``d(k) = c0 + c1 1(k >= k_b) + sum_l a_l d(k-l) + e(k)`` the Wald statistic of
    ``c1 = 0`` is computed for every break ``k_b`` at once (Frisch-Waugh with cumulative sums)
    and its supremum tested with :func:`sup_wald_p_value`.  Drift: the Wald statistic of ``c1`` in
    ``d(k) = c0 + c1 k + sum_l a_l d(k-l) + e(k)`` against chi-square(1).  The AR terms absorb the
    coloured disturbance, so a slowly wandering but stationary disturbance is not reported.
    """
    d = np.asarray(d, float).ravel()
    p = int(noise_order)
    n_all = d.shape[0]
    out = {"detected": False, "kind": None, "size": 0.0, "time": None, "rate": None, "p_value": 1.0,
           "p_step": 1.0, "p_drift": 1.0, "statistic": 0.0}
    if n_all < max(50, 10 * (p + 3)) or not np.all(np.isfinite(d)):
        return out
    yv, lags = _ar_design(d, p)
    n = yv.shape[0]
    X = np.column_stack([np.ones(n), lags])
    xtx_inv = np.linalg.pinv(X.T @ X)
    beta = xtx_inv @ (X.T @ yv)
    e = yv - X @ beta
    ssr0 = float(e @ e)
    # Step: for every break k, regressor s_k = 1(row >= k).
    q = np.cumsum(X[::-1], axis=0)[::-1]            # q[k] = sum_{t>=k} X[t]
    se = np.cumsum(e[::-1])[::-1]                    # sum_{t>=k} e[t]
    cnt = n - np.arange(n, dtype=float)
    denom = cnt - np.einsum("ij,jk,ik->i", q, xtx_inv, q)
    k_lo, k_hi = int(math.ceil(trim * n)), int(math.floor((1 - trim) * n))
    ks = np.arange(max(k_lo, 1), max(k_hi, k_lo + 1))
    ok = denom[ks] > 1e-9 * cnt[ks]
    ks = ks[ok]
    if ks.size == 0:
        return out
    num = se[ks] ** 2 / denom[ks]
    dof = n - X.shape[1] - 1
    s2 = (ssr0 - num) / dof
    wald = num / np.maximum(s2, 1e-300)
    best = int(np.argmax(wald))
    w_step, k_step = float(wald[best]), int(ks[best])
    p_step = min(1.0, 2.0 * sup_wald_p_value(w_step, trim))
    ssr_step = ssr0 - float(num[best])
    # Drift: linear trend regressor.
    tcol = np.arange(n, dtype=float) / n
    X2 = np.column_stack([X, tcol])
    beta2, *_ = np.linalg.lstsq(X2, yv, rcond=None)
    e2 = yv - X2 @ beta2
    ssr_drift = float(e2 @ e2)
    cov2 = np.linalg.pinv(X2.T @ X2) * ssr_drift / (n - X2.shape[1])
    w_drift = float(beta2[-1] ** 2 / cov2[-1, -1]) if cov2[-1, -1] > 0 else 0.0
    p_drift = min(1.0, 2.0 * float(stats.chi2.sf(w_drift, 1)))
    out.update(p_step=p_step, p_drift=p_drift, p_value=min(p_step, p_drift))
    step_hit, drift_hit = p_step < alpha, p_drift < alpha
    if not (step_hit or drift_hit):
        return out
    kb = k_step + p  # index into d
    if step_hit and (not drift_hit or ssr_step <= ssr_drift):
        size = float(np.mean(d[kb:]) - np.mean(d[:kb]))
        out.update(detected=True, kind="step", size=size, time=kb * sample_time, p_value=p_step,
                   statistic=w_step)
    else:
        # Size from an ordinary straight line through d: what an engineer would draw.
        slope = float(np.polyfit(np.arange(n_all, dtype=float), d, 1)[0])
        out.update(detected=True, kind="drift", size=slope * n_all, rate=slope / sample_time,
                   p_value=p_drift, statistic=w_drift)
    return out


# --------------------------------------------------------------------------------------------
# Main entry
# --------------------------------------------------------------------------------------------

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


def _p_from_z(zv):
    return float(2.0 * stats.norm.sf(abs(zv)))


def _margin(p, alpha):
    """How clearly a p-value lies on its side of ``alpha``: 0 at the threshold, 1 far from it."""
    if p <= 0:
        return 1.0
    return float(1.0 - min(p / alpha, alpha / p))


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


def _unchanged_entry(model, i, j, reason):
    return {"output": model.outputs[i], "input": model.inputs[j], "kind": "unknown",
            "before": model.element(i, j), "after": model.element(i, j), "estimate": None,
            "confidence": 0.0, "interval": None, "applied": False, "evidence": {}, "reason": reason}


def _row_response(model: FopdtModel, u: np.ndarray, i: int) -> np.ndarray:
    """Response of row ``i`` of ``model`` to ``u`` from rest, element by element (as
    :func:`mpm_monitor.core.discretize.simulate`).

    ``s(k+1) = a s(k) + b u_j(k - m)`` contributes ``s(k)``, i.e. ``b q^-(m+1) / (1 - a q^-1)``;
    a static element without delay is a feed-through (see :mod:`mpm_monitor.core.discretize`).
    """
    disc = discretize(model)
    out = np.zeros(u.shape[0])
    for j in range(model.n_inputs):
        if disc.active[i, j]:
            m = int(disc.input_lag[i, j]) + 1
            if m < u.shape[0]:
                a = disc.pole[i, j]
                out[m:] += signal.lfilter([disc.numerator[i, j]], [1.0, -a], u[:-m, j])
        if disc.feedthrough[i, j] != 0:
            out += disc.feedthrough[i, j] * u[:, j]
    return out


def _estimate_row(model, u, y, i, specs: dict, n_fit, options, lags0: dict, max_sweeps, skip=None, extra=None,
                  ar0=None, need_cov=True):
    """Fit the located elements ``specs`` (``{input index: _ElementSpec}``) of row ``i``.

    The row's other elements are held at the model's values.  ``skip`` (samples left out at the
    start) defaults to the largest lag searched; fits whose costs are compared must share it.
    Returns the problem and estimate.
    """
    js = sorted(specs)
    held = model
    for j in js:
        held = held.with_element(i, j, gain=0.0)
    z = y[:, i] - _row_response(held, u, i)
    disc = discretize(held)
    fixed_poles = [disc.pole[i, j] for j in range(model.n_inputs) if disc.active[i, j]]
    row_lags = [_element_lag(model.time_constant[i, j], model.delay_samples[i, j])
                for j in range(model.n_inputs) if held.gain[i, j] != 0]
    if skip is None:
        skip = max([specs[j].window[1] for j in js] + row_lags + [1])
    problem = _RowProblem(z, u[:, js], [specs[j] for j in js], n_fit, skip, fixed_poles,
                          options.initial_state == "estimate", options.noise_order, extra)
    if ar0 is not None:
        problem.set_ar(ar0)
    est = _search_row(problem, [lags0[j] for j in js], max_sweeps, ar_iterations=3 if ar0 is None else 1,
                      need_cov=need_cov)
    return problem, est


def _element_summary(problem, est, m, ts, zcrit, chi_crit):
    """Fitted parameters (seconds) and their intervals of element ``m`` of an estimate."""
    fit = est.fit
    k_hat, a_hat, lag_hat = float(fit.gains[m]), float(fit.poles[m]), int(fit.lags[m])
    se_k, se_a = math.sqrt(est.var_gain[m]), math.sqrt(est.var_pole[m])
    after = dict(zip(("gain", "time_constant", "delay"), _element_params(k_hat, a_hat, lag_hat, ts)))
    lo_lag, hi_lag = _lag_interval(est, m, problem.specs, chi_crit)
    a_lo = min(max(a_hat - zcrit * se_a, 1e-12), a_hat)
    a_hi = max(min(a_hat + zcrit * se_a, 1.0 - 1e-12), a_hat)
    lagged = after["time_constant"] > 0
    tau_iv = [-ts / math.log(a_lo), -ts / math.log(a_hi)] if lagged else [0.0, 0.0]
    shift = 1 if lagged else 0
    interval = {"gain": [k_hat - zcrit * se_k, k_hat + zcrit * se_k], "time_constant": tau_iv,
                "delay": [max(lo_lag - shift, 0) * ts, max(hi_lag - shift, 0) * ts]}
    return after, interval, (k_hat, se_k, a_hat, se_a)


def _lr_hold(model, u, y, i, specs, est, holds: dict, lag_orig: dict, n_use, options, skip, extra=None):
    """Likelihood-ratio statistic of holding parameters of located elements at the model's values.

    The row is refitted with, for each element index ``m`` in ``holds``, the parameters named in
    ``holds[m]`` ("gain", "pole", "lag", or "absent": no effect at all) held at the model's values,
    the other lags at their optimum and everything else free; the statistic is
    ``n ln(SSR_held / SSR_free)``, chi-square with as many degrees of freedom as parameters held
    when they did not change (Ljung 1999, section 16.5).  Unlike a Wald test on the Jacobian it
    does not depend on the parametrization, which matters along the ridge where gain and time
    constant trade off.
    """
    js = sorted(specs)
    held, lags = {}, {}
    for m, j in enumerate(js):
        sp = specs[j]
        lag = est.fit.lags[m]
        what = holds.get(m, set())
        if "lag" in what:
            lag = lag_orig[j]
        sp_new = _ElementSpec(sp.gain_free, sp.pole_free, float(est.fit.gains[m]), float(est.fit.poles[m]),
                              (lag, lag))
        if "gain" in what:
            sp_new.gain_free, sp_new.gain = False, float(model.gain[i, j])
        if "pole" in what:
            sp_new.pole_free, sp_new.pole = False, _pole_of(model.time_constant[i, j], model.sample_time)
        if "absent" in what:
            sp_new.gain_free, sp_new.gain, sp_new.pole_free = False, 0.0, False
        held[j] = sp_new
        lags[j] = lag
    _, est_h = _estimate_row(model, u, y, i, held, n_use, options, lags, 1, skip=skip, extra=extra, ar0=est.ar,
                             need_cov=False)
    return max(est_h.fit.n_resid * math.log(max(est_h.fit.ssr, 1e-300) / max(est.fit.ssr, 1e-300)), 0.0)


_PARAM_OF_TEST = {"gain": "gain", "time_constant": "pole", "delay": "lag", "missing": "absent"}


def _repair_row(model, u, y, i, js, n_fit, options, zcrit, chi_crit, alpha, extra=None):
    """Classify the located elements ``js`` of row ``i`` and fit their repair on samples ``0 .. n_fit-1``.

    Stage 1 (whole record, the most evidence) frees gain, time constant and delay of every located
    element and tests each against the model's value by a likelihood-ratio test.  Parameters
    judged unchanged are then held *together* and that joint hypothesis tested as well: gain and
    time constant (or two elements on inputs that move together) can each stand in for the other,
    so that each alone looks unchanged while holding both does not fit; while the joint test
    rejects, the held parameter with the strongest evidence of change is freed.  Stage 2 (first
    ``n_fit`` samples, so that the rest validates it) refits only what changed (everything for a
    missing element) with the rest held at the model's values; elements without a change are held
    entirely.  Fewer free parameters give tighter, less biased estimates when inputs move together.

    Returns
    -------
    dict
        ``elements``: ``{j: verdict}``, ``warnings``: list of str.
    """
    ts = model.sample_time
    n_all = u.shape[0]
    names_y, names_u = model.outputs, model.inputs
    gain, tau, nd = model.gain, model.time_constant, model.delay_samples
    row_nonzero = gain[i] != 0
    row_taus = tau[i][row_nonzero & (tau[i] > 0)]
    base_tau = float(np.median(row_taus)) if row_taus.size else 10.0 * ts
    max_row_lag = max([_element_lag(tau[i, j], nd[i, j]) for j in range(model.n_inputs) if row_nonzero[j]],
                      default=1)
    s = options.max_delay_shift
    warnings = []
    specs, lags0, lag_orig = {}, {}, {}
    for j in js:
        if gain[i, j] != 0:
            lag = max(1, _element_lag(tau[i, j], nd[i, j]))
            pole = _pole_of(tau[i, j], ts) if tau[i, j] > 0 else _pole_of(base_tau, ts)
            specs[j] = _ElementSpec(True, True, gain[i, j], pole, (max(1, lag - s), lag + s))
        else:
            lag = max_row_lag
            specs[j] = _ElementSpec(True, True, 0.0, _pole_of(base_tau, ts), (1, max_row_lag + s))
        lags0[j] = lag
        lag_orig[j] = _element_lag(tau[i, j], nd[i, j])
    problem, est = _estimate_row(model, u, y, i, specs, n_all, options, lags0, options.max_sweeps, extra=extra)
    skip1 = problem.start - problem.p

    def lr(holds):
        return _lr_hold(model, u, y, i, specs, est, holds, lag_orig, n_all, options, skip1, extra)

    # Individual tests.
    summaries, tests = {}, {}
    for m, j in enumerate(js):
        after, interval, _ = _element_summary(problem, est, m, ts, zcrit, chi_crit)
        summaries[j] = (after, interval)
        before = model.element(i, j)
        t = {}
        if before["gain"] == 0:
            t["missing"] = [float(stats.chi2.sf(lr({m: {"absent"}}), 1)), True]
        else:
            t["gain"] = [float(stats.chi2.sf(lr({m: {"gain"}}), 1)),
                         abs(after["gain"] - before["gain"]) > options.min_relative_change * abs(before["gain"])]
            tau0 = before["time_constant"]
            t["time_constant"] = [float(stats.chi2.sf(lr({m: {"pole"}}), 1)),
                                  abs(after["time_constant"] - tau0) > options.min_relative_change * max(tau0, ts)]
            w = specs[j].window
            p_d = float(stats.chi2.sf(_lag_lr(est, m, lag_orig[j], problem.specs), 1)) \
                if w[0] <= lag_orig[j] <= w[1] else 0.0
            t["delay"] = [p_d, after["delay"] != before["delay"]]
        tests[j] = t
    changed = {j: {k for k, (p, big) in tests[j].items() if p < alpha and big} for j in js}
    margins = {j: {k: _margin(p, alpha) for k, (p, _) in tests[j].items()} for j in js}
    # Joint test of everything held.
    joint_p = None
    while True:
        holds = {m: {_PARAM_OF_TEST[k] for k in tests[j] if k not in changed[j]} for m, j in enumerate(js)}
        n_held = sum(len(h) for h in holds.values())
        if n_held == 0:
            break
        joint_p = float(stats.chi2.sf(lr(holds), n_held))
        if joint_p >= alpha:
            break
        j_free, k_free = min(((j, k) for j in js for k in tests[j] if k not in changed[j]),
                             key=lambda jk: tests[jk[0]][jk[1]][0])
        changed[j_free].add(k_free)
        margins[j_free][k_free] = _margin(joint_p, alpha)
        warnings.append(f"{names_y[i]}/{names_u[j_free]}: its {k_free.replace('_', ' ')} alone does not show a "
                        f"significant change, but holding it together with the other unchanged parameters of the "
                        f"row does not fit the data (p = {joint_p:.2g}); it is re-estimated too.")
    verdicts = {}
    for m, j in enumerate(js):
        after, interval = summaries[j]
        hits = sorted(changed[j], key=["missing", "gain", "time_constant", "delay"].index)
        if "missing" in hits:
            kind = "missing"
        elif not hits:
            kind = "unknown"
        else:
            kind = hits[0] if len(hits) == 1 else "mixed"
        confidence = min(margins[j].values())
        if joint_p is not None and any(k not in changed[j] for k in tests[j]):
            confidence = min(confidence, _margin(joint_p, alpha))
        evidence = {"p_gain": tests[j].get("gain", tests[j].get("missing"))[0],
                    "p_time_constant": tests[j]["time_constant"][0] if "time_constant" in tests[j] else None,
                    "p_delay": tests[j]["delay"][0] if "delay" in tests[j] else None,
                    "p_unchanged_jointly": joint_p, "condition_number": est.cond, "samples": est.fit.n_resid,
                    "noise_model": [float(v) for v in est.ar]}
        verdicts[j] = {"kind": kind, "changed": hits, "after": after, "interval": interval,
                       "evidence": evidence, "confidence": confidence, "apply": kind != "unknown"}
        if est.edge[m]:
            warnings.append(f"{names_y[i]}/{names_u[j]}: the best delay lies at the edge of the searched range; "
                            f"the true delay may lie outside it (raise max_delay_shift).")
        if kind == "unknown":
            warnings.append(
                f"{names_y[i]}/{names_u[j]}: located as mismatched, but no parameter of the element differs "
                f"significantly from the model (at {100 * (1 - alpha):.4g}% confidence); the element is kept. "
                f"The mismatch may be too small for these data or not of first-order-plus-dead-time form.")
    if est.cond > 1e3 and len(js) > 1:
        warnings.append(
            f"{names_y[i]}: the inputs {', '.join(names_u[j] for j in js)} move together in these data "
            f"(condition number {est.cond:.3g}); their elements are hard to tell apart. More independent "
            f"excitation of these inputs (dither) would help.")
    # Stage 2: only what changed is free; fitted on the first n_fit samples.
    specs2, lags2 = {}, {}
    for m, j in enumerate(js):
        v = verdicts[j]
        if v["kind"] == "unknown":
            continue
        missing = v["kind"] == "missing"
        free_k = missing or "gain" in v["changed"]
        free_t = missing or "time_constant" in v["changed"]
        free_d = missing or "delay" in v["changed"]
        specs2[j] = _ElementSpec(free_k, free_t, est.fit.gains[m] if free_k else gain[i, j],
                                 est.fit.poles[m] if free_t else _pole_of(tau[i, j], ts),
                                 specs[j].window if free_d else (lag_orig[j], lag_orig[j]))
        lags2[j] = est.fit.lags[m] if free_d else lag_orig[j]
    if specs2:
        problem2, est2 = _estimate_row(model, u, y, i, specs2, n_fit, options, lags2, 1, extra=extra)
        for m, j in enumerate(sorted(specs2)):
            after2, interval2, _ = _element_summary(problem2, est2, m, ts, zcrit, chi_crit)
            sp = specs2[j]
            v = verdicts[j]
            after = {"gain": float(after2["gain"] if sp.gain_free else gain[i, j]),
                     "time_constant": float(after2["time_constant"] if sp.pole_free else tau[i, j]),
                     "delay": float(after2["delay"] if sp.lag_free else model.delay[i, j])}
            if not sp.lag_free and sp.pole_free and after2["time_constant"] == 0.0:
                after["delay"] = after2["delay"]  # a vanished lag moves the sample into the delay
            for key, free in (("gain", sp.gain_free), ("time_constant", sp.pole_free), ("delay", sp.lag_free)):
                if free:
                    v["interval"][key] = interval2[key]
            v["after"] = after
            v["evidence"]["condition_number_repair"] = est2.cond
    return {"elements": verdicts, "warnings": warnings}


def _refit_row(model, u, y, i, verdicts: dict, n, options, zcrit, chi_crit, extra=None):
    """Refit accepted elements on the whole record with the validated structure (lags +-3 samples)."""
    ts = model.sample_time
    specs, lags0 = {}, {}
    for j, v in verdicts.items():
        changed = set(v["changed"]) | ({"gain", "time_constant", "delay"} if v["kind"] == "missing" else set())
        a = v["after"]
        lag = _element_lag(a["time_constant"], int(round(a["delay"] / ts)))
        window = (max(1, lag - 3), lag + 3) if "delay" in changed else (lag, lag)
        specs[j] = _ElementSpec("gain" in changed, "time_constant" in changed, a["gain"],
                                _pole_of(a["time_constant"], ts), window)
        lags0[j] = lag
    problem, est = _estimate_row(model, u, y, i, specs, n, options, lags0, 1, extra=extra)
    out = {}
    for m, j in enumerate(sorted(specs)):
        after, interval, _ = _element_summary(problem, est, m, ts, zcrit, chi_crit)
        sp = specs[j]
        old = verdicts[j]["after"]
        new = {"gain": after["gain"] if sp.gain_free else old["gain"],
               "time_constant": after["time_constant"] if sp.pole_free else old["time_constant"],
               "delay": after["delay"] if (sp.lag_free or after["time_constant"] == 0.0) else old["delay"]}
        iv = dict(verdicts[j]["interval"])
        for key, free in (("gain", sp.gain_free), ("time_constant", sp.pole_free), ("delay", sp.lag_free)):
            if free:
                iv[key] = interval[key]
        out[j] = {"after": new, "interval": iv, "edge": est.edge[m]}
    return out
