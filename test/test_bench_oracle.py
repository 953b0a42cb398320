"""The oracle's measure of a mismatch's visibility (bench.oracle) against independent references."""

import numpy as np
import pytest
import scipy.linalg as sla

from bench.oracle import innovation_model, oracle_noncentrality, oracle_power
from mpm_monitor.sim.plant import DisturbanceOptions


@pytest.mark.parametrize("noise", [DisturbanceOptions(), DisturbanceOptions(2e-2, 0.7, 1e-2),
                                   DisturbanceOptions(1e-2, 0.0, 3e-3), DisturbanceOptions(1e-2, 0.9, 0.0)])
def test_the_innovation_model_factors_the_noise_spectrum(noise):
    c, s2 = innovation_model(noise)
    assert 0.0 <= c < 1.0
    w = np.linspace(0.0, np.pi, 2001)
    q = np.exp(-1j * w)
    p = noise.disturbance_pole
    spectrum = noise.disturbance_std ** 2 / np.abs(1 - p * q) ** 2 + noise.noise_std ** 2
    np.testing.assert_allclose(s2 * np.abs(1 - c * q) ** 2 / np.abs(1 - p * q) ** 2, spectrum, rtol=1e-12)
    # Kolmogorov-Szego: the innovation variance is the geometric mean of the spectrum over the circle.
    grid = np.exp(-1j * 2 * np.pi * np.arange(4096) / 4096)
    geo = np.exp(np.mean(np.log(noise.disturbance_std ** 2 / np.abs(1 - p * grid) ** 2 + noise.noise_std ** 2)))
    assert s2 == pytest.approx(geo, rel=1e-10)


def test_the_noncentrality_is_the_gls_one_of_the_exact_noise_covariance():
    noise = DisturbanceOptions()
    n, p = 1500, noise.disturbance_pole
    rng = np.random.default_rng(3)
    z = np.convolve(rng.standard_normal(n), 0.05 * 0.9 ** np.arange(60))[:n]
    k = np.arange(n)
    cov = sla.toeplitz(noise.disturbance_std ** 2 * p ** k / (1 - p * p)) + noise.noise_std ** 2 * np.eye(n)
    exact = float(z @ sla.cho_solve(sla.cho_factor(cov), z))
    # The whitening filter starts at rest where the stationary noise does not: a difference of order 1/n.
    assert oracle_noncentrality(z, noise) == pytest.approx(exact, rel=0.02)
    assert oracle_noncentrality(2 * z, noise) == pytest.approx(4 * oracle_noncentrality(z, noise), rel=1e-12)


def test_the_power_is_the_noncentral_chi_square_tail():
    from scipy import stats

    noise = DisturbanceOptions()
    z = 0.004 * np.sin(np.arange(800) / 7.0)
    lam = oracle_noncentrality(z, noise)
    for level in (0.05, 1e-3, 1e-5):
        ref = stats.ncx2.sf(stats.chi2.isf(level, 1), 1, lam)
        assert oracle_power(z, noise, level) == pytest.approx(ref, rel=1e-9)
    assert oracle_power(np.zeros(100), noise, 1e-3) == pytest.approx(1e-3, rel=1e-9)
    assert oracle_power(10 * z, noise, 1e-3) > 0.999
