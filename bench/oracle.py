"""What an oracle could detect: a test-independent measure of how visible a mismatch is in a window.

The benchmarks score the element test's recall.  A miss may be the test's fault, or the data's: a
mismatch whose effect on the output is small against the noise cannot be found by any test.  The
report's own ``detectable_gain_change`` answers this with the element test itself (and for gain
errors only).  The measure here does not use the analysis at all.

The **oracle** knows the mismatch's exact contribution to the output, ``z = (P_ij - Phat_ij) u_j``
(the plant's minus the model's element response to the logged column), and the exact model of the
unmeasured disturbance ``v``.  Its test of ``d = delta z + v``, ``delta = 0`` against ``delta != 0``,
whitens both by the noise model and has one degree of freedom: its statistic is chi-square with
noncentrality ``lambda = ||W z||^2 / sigma_e^2`` (``W`` the whitening filter, ``sigma_e^2`` the
innovation variance).  No test that must also find the shape, the element or the noise model can
do better; one that does not know the size in advance (as every real test) does worse.  Its level
is the Bonferroni level of one element in the analysis's element family, ``alpha / (N_FAMILIES m)``
with ``m`` the elements tested (the level of the first step of the analysis's Holm procedure).

The oracle ignores the feedback (in closed loop ``u`` depends on past ``v``): it measures the signal
against the noise, not a bias.

The noise is the simulator's (:class:`~mpm_monitor.sim.plant.DisturbanceOptions`): white ``w`` (std
``sigma_w``) through ``1 / (1 - p q^-1)`` plus white measurement noise (std ``sigma_n``), an ARMA(1, 1)
``v = (1 - c q^-1) / (1 - p q^-1) e`` by spectral factorisation (:func:`innovation_model`).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.special as sc

from mpm_monitor.core.filters import lfilter
from mpm_monitor.sim.plant import DisturbanceOptions


def innovation_model(noise: DisturbanceOptions) -> tuple:
    """The innovation form of the simulator's output noise.

    Parameters
    ----------
    noise : DisturbanceOptions

    Returns
    -------
    c : float
        Zero of ``v = (1 - c q^-1) / (1 - p q^-1) e``, ``0 <= c < 1``.
    sigma2_e : float
        Variance of the innovation ``e`` (output units squared).

    Notes
    -----
    The spectrum ``sigma_w^2 / |1 - p z^-1|^2 + sigma_n^2`` has the numerator ``sigma_w^2 +
    sigma_n^2 (1 + p^2) - sigma_n^2 p (z + z^-1)`` over ``|1 - p z^-1|^2``; matching it with
    ``sigma_e^2 |1 - c z^-1|^2`` gives ``sigma_e^2 c = sigma_n^2 p`` and ``sigma_e^2 (1 + c^2) = sigma_w^2
    + sigma_n^2 (1 + p^2)``, whose root ``|c| < 1`` is taken.
    """
    p, sw2, sn2 = noise.disturbance_pole, noise.disturbance_std ** 2, noise.noise_std ** 2
    s0 = sw2 + sn2 * (1.0 + p * p)
    b = sn2 * p
    if b <= 0.0:
        return 0.0, s0
    c = (s0 - math.sqrt(max(s0 * s0 - 4.0 * b * b, 0.0))) / (2.0 * b)
    return c, b / c


def oracle_noncentrality(z: np.ndarray, noise: DisturbanceOptions) -> float:
    """``lambda = ||W z||^2 / sigma_e^2`` of the oracle's test (module docstring).

    Parameters
    ----------
    z : ndarray, shape (n_samples,)
        The mismatch's contribution to the output over the window (output units).
    noise : DisturbanceOptions

    Returns
    -------
    float
        The noncentrality (dimensionless).
    """
    c, sigma2_e = innovation_model(noise)
    if sigma2_e <= 0.0:
        return math.inf
    white = lfilter([1.0, -noise.disturbance_pole], [1.0, -c], np.asarray(z, dtype=float))
    return float(white @ white) / sigma2_e


def oracle_power(z: np.ndarray, noise: DisturbanceOptions, level: float) -> float:
    """Probability that the oracle's test at ``level`` detects the contribution ``z``.

    Parameters
    ----------
    z : ndarray, shape (n_samples,)
        The mismatch's contribution to the output (output units).
    noise : DisturbanceOptions
    level : float
        The test's false-alarm probability, in (0, 1).

    Returns
    -------
    float
        ``P(chi2_1(lambda) > chi2_1^-1(1 - level))``, in [level, 1].
    """
    lam = oracle_noncentrality(z, noise)
    if not math.isfinite(lam):
        return 1.0
    critical = float(sc.chdtri(1.0, level))
    return float(1.0 - sc.chndtr(critical, 1.0, lam))
