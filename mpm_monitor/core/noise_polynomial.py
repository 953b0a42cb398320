"""The noise polynomial of an element-test row: what the row's fit says of its noise.

:func:`noise_filter` takes the element fit's own coefficients as the row's ``A(q)``, unless the window
leaves them undetermined (:data:`MAX_NOISE_FILTER_SE`), and :class:`RowNoise` keeps it with the
residual variance for the whole-response test and the detectability
(:mod:`mpm_monitor.core.detectability`); :func:`undetermined_noise_warnings` names the rows whose
polynomial came from the prediction error's own lags alone.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .model import PlantModel


@dataclasses.dataclass(frozen=True)
class RowNoise:
    """What the element test of one row estimated about its noise.

    Attributes
    ----------
    sigma2 : float
        Residual (equation-error) variance of the row's ARX, output units squared.
    dof : int
        Its residual degrees of freedom.
    a : ndarray, shape (na,)
        ``a_1 .. a_na`` of the row's noise polynomial ``A(q) = 1 + a_1 q^-1 + ... + a_na q^-na``
        (:func:`noise_filter`): the ARX's own coefficients, or, where the window leaves them
        undetermined, those of the prediction error's own lags alone.
    exact : bool
        The fit is exact (:attr:`~mpm_monitor.core.arx.SharedFit.exact`): its residual is rounding, not
        noise (a log without noise).
    undetermined : float or None
        The largest standard error of the ARX's own coefficients where it exceeds
        :data:`MAX_NOISE_FILTER_SE` (``a`` then comes from the own lags alone); None otherwise.
    """

    sigma2: float
    dof: int
    a: np.ndarray
    exact: bool = False
    undetermined: Optional[float] = None


#: Largest standard error of the element fit's own coefficients ``a_k`` (dimensionless filter taps) for
#: which they are the row's noise polynomial.  In a loop whose inputs move only with the controller's
#: feedback (no setpoint move, no dither) the input lags and the own lags can be nearly collinear (the
#: controller's law ties them; in a square loop always): the fit then splits the prediction error between
#: them arbitrarily, and its ``a_k`` come out as 1e4 to 1e11 with standard errors as large, where 0.02 to
#: 0.1 is usual.  Such an ``A(q)`` is no noise model: filtering an element's response by it made the
#: whole-response test's regressor meaningless and the detectable gain changes
#: (:mod:`mpm_monitor.core.detectability`) 1e-5 where 30 % went unseen.  Over the 194 rows of 40 such
#: loops of the Monte-Carlo's plants (``bench.scenarios``, setpoints held, no dither) the largest standard
#: error was either below 3.4 or above 2.8e4; over 118 rows of excited loops with noise, below 0.03.  A mismatched
#: row of a log without noise exceeds it too: its prediction error is then an exact function of the inputs.
MAX_NOISE_FILTER_SE = 1.0


def noise_filter(fit, na: Optional[int] = None) -> tuple:
    """The row's noise polynomial from an element-test fit.

    Parameters
    ----------
    fit : SharedFit or GramFit
        The row's element fit: ``d_i`` on the lag blocks and ``-d_i`` at lags ``1 .. na`` (then any
        further free columns).
    na : int, optional
        Own lags of the polynomial (default: every own column of ``fit``).

    Returns
    -------
    a : ndarray, shape (na,)
        ``a_1 .. a_na`` (dimensionless): the fit's first ``na`` own coefficients, unless their largest
        standard error exceeds :data:`MAX_NOISE_FILTER_SE`; then the first ``na`` coefficients of the fit
        of the prediction error on its own columns alone (under "no mismatch" the prediction error is
        the disturbance, so these whiten it).
    undetermined : float or None
        That largest standard error where it exceeds the bound; None otherwise.
    """
    own = np.array(fit.own_theta(), dtype=float)
    na = own.size if na is None else int(na)
    if not na:
        return own[:0], None
    with np.errstate(invalid="ignore"):
        se = float(np.max(fit.own_standard_errors()[:na]))
    if np.isfinite(se) and se > MAX_NOISE_FILTER_SE:
        return np.array(fit.own_only_theta(), dtype=float)[:na], se
    return own[:na], None


def undetermined_rows(noise: dict) -> list:
    """The rows of ``noise`` (output index -> :class:`RowNoise`), in order, whose noise polynomial came from the
    own lags alone (:func:`noise_filter`): inputs that move only with the controller's feedback, or a
    prediction error without noise."""
    return [i for i in sorted(noise) if getattr(noise[i], "undetermined", None) is not None]


def undetermined_noise_warnings(model: PlantModel, noise: dict) -> list:
    """One warning naming the rows whose noise polynomial came from the own lags alone (:func:`undetermined_rows`)."""
    rows = undetermined_rows(noise)
    if not rows:
        return []
    worst = max(noise[i].undetermined for i in rows)
    return [f"row{'s' if len(rows) > 1 else ''} {', '.join(model.outputs[i] for i in rows)}: the input lags and the "
            f"prediction error's own lags are nearly collinear here (the element fit's noise polynomial has standard "
            f"errors up to {worst:.2g}: inputs that move only with the controller's feedback, or a prediction error "
            f"without noise), so these data give no noise model of {'these rows' if len(rows) > 1 else 'the row'}: no "
            f"detectable gain change is computed for {'their' if len(rows) > 1 else 'its'} elements "
            "(detectable_gain_change null), and the whole-response test filters by the noise polynomial of the "
            "prediction error alone"]


def row_noise(fit) -> RowNoise:
    """The :class:`RowNoise` of an element-test fit (``sigma2``, ``dof``, its noise polynomial
    :func:`noise_filter`, ``exact``)."""
    a, undetermined = noise_filter(fit)
    return RowNoise(sigma2=float(fit.sigma2), dof=int(fit.dof), a=a, exact=bool(fit.exact), undetermined=undetermined)
