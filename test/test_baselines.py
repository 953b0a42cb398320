"""Tests of the baseline element tests (mpm_monitor.core.baselines): size, power, shapes, error paths.

Synthetic signals only (no MPC), so the whole file runs in a few seconds.  Size tests use
binomial bounds: with ``R`` independent draws and true rate ``a`` the observed rate lies within
``a +- 4 sqrt(a (1 - a) / R)`` with probability > 0.9999.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy import signal

from mpm_monitor.core.baselines import (
    ElementTestResult,
    cross_correlation_test,
    fit_ar,
    input_separability,
    partial_correlation_test,
)
from mpm_monitor.core.errors import ConfigurationError, InputError
from mpm_monitor.core.statistics import holm_adjust, holm_reject

TESTS = (cross_correlation_test, partial_correlation_test)


def ar1(rng, n, pole, cols=1, std=1.0):
    """First-order filtered white noise ``x = w / (1 - pole q^-1)``, shape (n, cols)."""
    w = rng.standard_normal((n + 200, cols)) * std
    return signal.lfilter([1.0], [1.0, -pole], w, axis=0)[200:]


def fopdt(u, gain, pole, delay):
    """Discrete first-order-plus-delay response ``gain (1 - pole) q^-(delay+1) / (1 - pole q^-1)`` of ``u``."""
    num = np.zeros(delay + 2)
    num[delay + 1] = gain * (1.0 - pole)
    return signal.lfilter(num, [1.0, -pole], u)


def binomial_bounds(rate, runs, z=4.0):
    half = z * math.sqrt(rate * (1.0 - rate) / runs)
    return max(0.0, rate - half), rate + half


# --------------------------------------------------------------------------- Holm and AR helpers
def test_holm_adjust_matches_hand_computation():
    # Holm (1979): sorted p (0.005, 0.01, 0.03, 0.04) times (4, 3, 2, 1) = (0.02, 0.03, 0.06, 0.04),
    # running maximum (0.02, 0.03, 0.06, 0.06), back in the original order.
    p = np.array([[0.01, 0.04], [0.03, 0.005]])
    np.testing.assert_allclose(holm_adjust(p), [[0.03, 0.06], [0.06, 0.02]], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(holm_reject(p, 0.05), [[True, False], [False, True]])


def test_holm_ignores_nan_and_caps_at_one():
    adj = holm_adjust([0.5, np.nan, 0.6])
    assert np.isnan(adj[1])
    np.testing.assert_allclose(adj[[0, 2]], [1.0, 1.0])
    assert not holm_reject([np.nan], 0.5)[0]


def test_fit_ar_recovers_coefficients():
    rng = np.random.default_rng(1)
    a_true = np.array([1.2, -0.5])
    x = signal.lfilter([1.0], np.concatenate([[1.0], -a_true]), rng.standard_normal(20000))
    a = fit_ar(x - x.mean(), max_order=8)
    assert a.size == 2  # BIC picks the true order on long data
    np.testing.assert_allclose(a, a_true, atol=0.03)


def test_fit_ar_white_noise_has_order_zero():
    rng = np.random.default_rng(2)
    assert fit_ar(rng.standard_normal(5000)).size == 0


# --------------------------------------------------------------------------- size (false alarms)
@pytest.mark.parametrize("test", TESTS, ids=lambda f: f.__name__)
def test_size_on_independent_coloured_signals(test):
    """No relation between d and u: raw p-values are uniform and Holm keeps the family-wise rate <= alpha."""
    rng = np.random.default_rng(123)
    runs, alpha, n = 200, 0.05, 400
    family_alarms, raw_p = 0, []
    for _ in range(runs):
        d = ar1(rng, n, 0.8, cols=2)
        u = ar1(rng, n, 0.6, cols=2)
        res = test(d, u, alpha=alpha, max_lag=5)
        family_alarms += bool(res.mismatch.any())
        raw_p.append(res.p_values.ravel())
    raw_p = np.concatenate(raw_p)
    lo, hi = binomial_bounds(alpha, raw_p.size)
    assert lo <= np.mean(raw_p < alpha) <= hi
    _, hi_family = binomial_bounds(alpha, runs)
    assert family_alarms / runs <= hi_family


@pytest.mark.parametrize("test", TESTS, ids=lambda f: f.__name__)
def test_size_under_feedback(test):
    """Delta = 0 but u reacts to the coloured d (as an MPC does): lag-0 feedback must not raise alarms.

    ``d = v`` (AR(1), pole 0.95) and ``u(k) = r(k) - 0.5 d(k) - 0.3 d(k - 1)``: the raw correlation
    of ``d(k)`` with ``u(k - l)`` is far from zero at every lag, so a test that does not whiten ``d``
    fails here.
    """
    rng = np.random.default_rng(7)
    runs, alpha, n = 100, 0.05, 600
    alarms = 0
    for _ in range(runs):
        v = ar1(rng, n, 0.95, cols=2, std=0.1)
        r = np.where(rng.random((n, 2)) < 0.5, -1.0, 1.0)
        u = r - 0.5 * v - 0.3 * np.vstack([np.zeros((1, 2)), v[:-1]])
        u = u @ np.array([[1.0, 0.4], [0.2, 1.0]])
        alarms += bool(test(v, u, alpha=alpha, max_lag=6).mismatch.any())
    _, hi = binomial_bounds(alpha, runs)
    assert alarms / runs <= hi


# --------------------------------------------------------------------------- power
@pytest.mark.parametrize("test", TESTS, ids=lambda f: f.__name__)
def test_power_on_open_loop_delta(test):
    """Known Delta_12 (30 % of a unit FOPDT gain, delay 3) in open loop: exactly that element is located."""
    rng = np.random.default_rng(11)
    n = 2000
    u = ar1(rng, n, 0.5, cols=3)
    d = ar1(rng, n, 0.9, cols=2, std=0.05)
    d[:, 0] += fopdt(u[:, 1], 0.3, 0.9, 3)
    res = test(d, u, alpha=0.01)
    expected = np.zeros((2, 3), dtype=bool)
    expected[0, 1] = True
    np.testing.assert_array_equal(res.mismatch, expected)
    assert res.p_values[0, 1] < 1e-10


def test_partial_correlation_separates_correlated_inputs():
    """Inputs correlated with each other: pcorr removes the other inputs and still locates only (0, 1)."""
    rng = np.random.default_rng(5)
    n = 3000
    base = ar1(rng, n, 0.7, cols=3)
    u = base @ np.array([[1.0, 0.8, 0.3], [0.0, 0.6, 0.5], [0.0, 0.0, 0.8]])
    d = ar1(rng, n, 0.9, cols=2, std=0.05)
    d[:, 0] += fopdt(u[:, 1], 0.5, 0.85, 2)
    res = partial_correlation_test(d, u, alpha=0.01)
    expected = np.zeros((2, 3), dtype=bool)
    expected[0, 1] = True
    np.testing.assert_array_equal(res.mismatch, expected)
    assert not res.ambiguous.any()


def test_partial_correlation_reports_collinear_inputs_ambiguous():
    """u3 = u1 + u2 exactly: the three inputs cannot be separated -> ambiguous, never a located element."""
    rng = np.random.default_rng(6)
    n = 2000
    u12 = ar1(rng, n, 0.5, cols=2)
    u = np.column_stack([u12, u12.sum(axis=1)])
    d = ar1(rng, n, 0.9, cols=2, std=0.05)
    d[:, 1] += fopdt(u[:, 2], 0.5, 0.8, 1)
    res = partial_correlation_test(d, u, alpha=0.01)
    assert not res.mismatch.any()
    assert res.ambiguous.all()
    np.testing.assert_array_equal(res.p_values, np.ones((2, 3)))
    assert any("collinear" in w for w in res.warnings)
    np.testing.assert_allclose(res.separability, 0.0, atol=1e-6)


def test_input_separability_independent_inputs_near_one():
    rng = np.random.default_rng(8)
    sep = input_separability(ar1(rng, 3000, 0.5, cols=3), 10)
    assert np.all(sep > 0.95)


# --------------------------------------------------------------------------- shapes and results
@pytest.mark.parametrize("test", TESTS, ids=lambda f: f.__name__)
def test_result_shapes_and_fields(test):
    rng = np.random.default_rng(3)
    d, u = rng.standard_normal((500, 4)), rng.standard_normal((500, 2))
    res = test(d, u, alpha=0.01, max_lag=4)
    assert isinstance(res, ElementTestResult)
    for arr in (res.p_values, res.mismatch, res.statistic, res.adjusted_p_values):
        assert arr.shape == (4, 2)
    assert res.mismatch.dtype == bool
    assert res.method == ("xcorr" if test is cross_correlation_test else "pcorr")
    assert res.max_lag == 4 and res.alpha == 0.01
    assert np.all((res.p_values >= 0) & (res.p_values <= 1))
    assert np.all(res.adjusted_p_values >= res.p_values)
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.method = "other"


@pytest.mark.parametrize("test", TESTS, ids=lambda f: f.__name__)
def test_one_dimensional_signals_are_single_columns(test):
    rng = np.random.default_rng(4)
    res = test(rng.standard_normal(400), rng.standard_normal(400), max_lag=3)
    assert res.p_values.shape == (1, 1)


@pytest.mark.parametrize("test", TESTS, ids=lambda f: f.__name__)
def test_constant_input_is_not_tested(test):
    rng = np.random.default_rng(9)
    u = np.column_stack([rng.standard_normal(600), np.full(600, 2.5)])
    res = test(rng.standard_normal((600, 2)), u, max_lag=3)
    np.testing.assert_array_equal(res.p_values[:, 1], [1.0, 1.0])
    assert not res.mismatch[:, 1].any()
    assert any("constant" in w for w in res.warnings)


def test_default_max_lag_is_reported():
    rng = np.random.default_rng(10)
    res = cross_correlation_test(rng.standard_normal((1000, 1)), rng.standard_normal((1000, 1)))
    assert res.max_lag == 20


# --------------------------------------------------------------------------- error paths
@pytest.mark.parametrize("test", TESTS, ids=lambda f: f.__name__)
def test_error_paths(test):
    rng = np.random.default_rng(0)
    d, u = rng.standard_normal((500, 2)), rng.standard_normal((500, 3))
    with pytest.raises(InputError, match=r"same number of samples.*\(500, 2\).*\(499, 3\)"):
        test(d, u[:-1])
    with pytest.raises(InputError, match=r"u: expected shape \(n_samples, n_inputs\), got shape \(500, 3, 1\)"):
        test(d, u[:, :, None])
    with pytest.raises(InputError, match=r"d: expected shape \(n_samples, n_outputs\), got shape \(500, 0\)"):
        test(d[:, :0], u)
    bad = d.copy()
    bad[7, 1] = np.nan
    with pytest.raises(InputError, match="d: expected finite numbers, got nan at sample 7, column 1"):
        test(bad, u)
    with pytest.raises(InputError, match="u: expected a numeric array"):
        test(d, [["a"] * 3] * 500)
    for alpha in (0.0, 1.0, -0.1, "x"):
        with pytest.raises(ConfigurationError, match=r"alpha: expected a number in \(0, 1\)"):
            test(d, u, alpha=alpha)
    for lag in (0, -2, 1.5, True):
        with pytest.raises(ConfigurationError, match="max_lag: expected an integer >= 1"):
            test(d, u, max_lag=lag)
    with pytest.raises(InputError, match="needs at least .* samples, got 500"):
        test(d, u, max_lag=100)


def test_partial_correlation_option_errors():
    rng = np.random.default_rng(0)
    d, u = rng.standard_normal((500, 2)), rng.standard_normal((500, 2))
    with pytest.raises(ConfigurationError, match="own_lags: expected an integer >= 0"):
        partial_correlation_test(d, u, own_lags=-1)
    with pytest.raises(ConfigurationError, match=r"separability_threshold: expected a number in \[0, 1\)"):
        partial_correlation_test(d, u, separability_threshold=1.0)


@pytest.mark.parametrize("test", TESTS, ids=lambda f: f.__name__)
def test_default_max_lag_shrinks_on_short_data(test):
    """The default L = 20 does not fit 150 samples of 2 inputs: fewer lags are tested, with a warning."""
    rng = np.random.default_rng(12)
    res = test(rng.standard_normal((150, 2)), rng.standard_normal((150, 2)))
    assert 5 <= res.max_lag < 20
    assert any("only 150 samples" in w for w in res.warnings)
    with pytest.raises(InputError, match="needs at least"):
        test(rng.standard_normal((30, 2)), rng.standard_normal((30, 2)))
