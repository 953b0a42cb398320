"""ARX estimation, F/Wald tests, delay estimation and the shared-block regression.

References: numpy.linalg.lstsq (an independent SVD-based least-squares solver) for the fitted
parameters; exact recovery of known ARX parameters on noise-free data (an invariant); the F
distribution's false-alarm rate on independent data (statistical, with a binomial bound).
"""

import numpy as np
import pytest
from scipy import signal, stats

from mpm_monitor.core.arx import SharedBlockRegression, estimate_delays, fit_arx, lag_matrix
from mpm_monitor.core.statistics import f_test, holm_adjust


def _arx_data(rng, n=2000, noise=0.0):
    """y with A = 1 - 1.2 q^-1 + 0.35 q^-2, B1 = q^-2 (0.5 + 0.3 q^-1), B2 = q^-4 (-0.7 + 0.2 q^-1)."""
    u = rng.standard_normal((n, 2))
    e = noise * rng.standard_normal(n)
    a = [1.0, -1.2, 0.35]
    b1 = [0, 0, 0.5, 0.3]
    b2 = [0, 0, 0, 0, -0.7, 0.2]
    y = signal.lfilter(b1, a, u[:, 0]) + signal.lfilter(b2, a, u[:, 1]) + signal.lfilter([1.0], a, e)
    return y, u


def test_lag_matrix_layout():
    x = np.arange(10.0).reshape(5, 2)
    m = lag_matrix(x, [0, 2], start=2)
    # column c*len(lags)+l holds x[t - lag_l, c] for t = 2..4
    np.testing.assert_array_equal(m[:, 0], x[2:, 0])
    np.testing.assert_array_equal(m[:, 1], x[:3, 0])
    np.testing.assert_array_equal(m[:, 3], x[:3, 1])


def test_fit_arx_recovers_true_parameters_noise_free():
    y, u = _arx_data(np.random.default_rng(0))
    fit = fit_arx(y, u, na=2, nb=2, nk=[2, 4])
    np.testing.assert_allclose(fit.a, [-1.2, 0.35], atol=1e-10)
    np.testing.assert_allclose(fit.b[0], [0.5, 0.3], atol=1e-10)
    np.testing.assert_allclose(fit.b[1], [-0.7, 0.2], atol=1e-10)
    assert fit.fit_percent > 99.999


def test_fit_arx_equals_numpy_lstsq_with_noise():
    rng = np.random.default_rng(1)
    y, u = _arx_data(rng, noise=0.1)
    fit = fit_arx(y, u, na=3, nb=3, nk=[1, 3])
    start = 5
    X = np.hstack([-lag_matrix(y, [1, 2, 3], start), lag_matrix(u[:, 0], [1, 2, 3], start),
                   lag_matrix(u[:, 1], [3, 4, 5], start)])
    ref, *_ = np.linalg.lstsq(X, y[start:], rcond=None)
    np.testing.assert_allclose(fit.theta, ref, rtol=1e-9, atol=1e-12)
    # covariance sigma^2 (X'X)^-1
    resid = y[start:] - X @ ref
    s2 = resid @ resid / (X.shape[0] - X.shape[1])
    np.testing.assert_allclose(fit.covariance, s2 * np.linalg.inv(X.T @ X), rtol=1e-7)


def test_estimate_delays_exact_on_noise_free_data():
    y, u = _arx_data(np.random.default_rng(2))
    np.testing.assert_array_equal(estimate_delays(y, u, na=2, nb=2, max_delay=8), [2, 4])


def test_estimate_delays_with_noise():
    y, u = _arx_data(np.random.default_rng(3), n=3000, noise=0.2)
    np.testing.assert_array_equal(estimate_delays(y, u, na=2, nb=2, max_delay=8), [2, 4])


def test_shared_block_regression_equals_direct_least_squares():
    rng = np.random.default_rng(4)
    y, u = _arx_data(rng, noise=0.1)
    start = 6
    common = lag_matrix(u, range(1, 7), start)
    own = -lag_matrix(y, [1, 2], start)
    fit = SharedBlockRegression(common, [6, 6]).fit(y[start:], own)
    X = np.hstack([common, own])
    ref, *_ = np.linalg.lstsq(X, y[start:], rcond=None)
    np.testing.assert_allclose(fit.theta, ref, rtol=1e-8, atol=1e-12)
    rss = float(np.sum((y[start:] - X @ ref) ** 2))
    assert fit.rss == pytest.approx(rss, rel=1e-9)
    # Wald test of a block equals the nested F test of dropping its columns.
    Xr = np.hstack([common[:, 6:], own])
    refr, *_ = np.linalg.lstsq(Xr, y[start:], rcond=None)
    rss_r = float(np.sum((y[start:] - Xr @ refr) ** 2))
    f_ref, p_ref = f_test(rss_r, rss, 6, X.shape[0] - X.shape[1])
    t = fit.test_blocks_zero([0])
    assert t.statistic == pytest.approx(f_ref, rel=1e-7)
    assert t.p_value == pytest.approx(p_ref, rel=1e-6, abs=1e-300)
    # All common coefficients zero: regress on own columns only.
    ref0, *_ = np.linalg.lstsq(own, y[start:], rcond=None)
    rss0 = float(np.sum((y[start:] - own @ ref0) ** 2))
    t_all = fit.test_all_common_zero()
    assert t_all.statistic == pytest.approx(f_test(rss0, rss, 12, X.shape[0] - 14)[0], rel=1e-7)


def test_f_test_false_alarm_rate_on_independent_data():
    """Under H0 (target independent of the block) the p-values are uniform: P(p < 0.05) ~ 0.05."""
    rng = np.random.default_rng(5)
    hits = 0
    n_trials = 400
    for _ in range(n_trials):
        x = rng.standard_normal((300, 2))
        common = lag_matrix(x, [0, 1, 2], 2)
        target = rng.standard_normal(common.shape[0])
        p = SharedBlockRegression(common, [3, 3]).fit(target, None).test_blocks_zero([0]).p_value
        hits += p < 0.05
    # binomial(400, 0.05): mean 20, sd 4.4; a 4-sigma band
    assert 20 - 18 <= hits <= 20 + 18


def test_collinear_block_has_no_degrees_of_freedom():
    rng = np.random.default_rng(6)
    x = rng.standard_normal((500, 1))
    u = np.hstack([x, 2 * x])            # two identical inputs (up to scale)
    common = lag_matrix(u, [1, 2], 2)
    target = rng.standard_normal(common.shape[0])
    reg = SharedBlockRegression(common, [2, 2])
    assert not reg.full_rank
    t = reg.fit(target, None).test_blocks_zero([0, 1])
    assert t.df_num == 2                  # only the identifiable combination is tested


def test_holm_adjust_against_hand_computation():
    p = np.array([0.01, 0.04, 0.03, np.nan, 0.005])
    # sorted: 0.005*4=0.02, 0.01*3=0.03, 0.03*2=0.06, 0.04*1=0.04 -> running max 0.06
    np.testing.assert_allclose(holm_adjust(p), [0.03, 0.06, 0.06, np.nan, 0.02])


def test_holm_adjust_leaves_every_non_finite_entry_out_of_the_family():
    # An infinity is no p-value: like NaN it is not counted in m and stays NaN (hand computation:
    # m = 2, sorted 0.02 * 2 = 0.04, 0.3 * 1 = 0.3).
    p = np.array([[0.3, np.inf], [-np.inf, 0.02]])
    np.testing.assert_allclose(holm_adjust(p), [[0.3, np.nan], [np.nan, 0.04]])
    assert np.all(np.isnan(holm_adjust([np.nan, np.inf])))


def test_f_test_p_value_matches_scipy():
    f, p = f_test(12.0, 10.0, 4, 100)
    assert f == pytest.approx((2.0 / 4) / (10.0 / 100))
    assert p == pytest.approx(stats.f.sf(f, 4, 100))


def test_f_test_of_an_exact_fit_is_decided_outright():
    # A full fit at or below the floor (rounding, not noise): the restriction is rejected outright when
    # the restricted fit leaves more than the floor, and there is nothing to test when it does not.
    assert f_test(1.0, 1e-30, 3, 100, floor=1e-20) == (float("inf"), 0.0)
    assert f_test(1e-25, 1e-30, 3, 100, floor=1e-20) == (0.0, 1.0)
    assert f_test(1.0, 0.0, 3, 100) == (float("inf"), 0.0)        # floor 0: only an exact 0 is exact
    assert f_test(0.0, 0.0, 3, 100) == (0.0, 1.0)
    f, p = f_test(12.0, 10.0, 4, 100, floor=1e-20)                 # above the floor: the ordinary F test
    assert (f, p) == f_test(12.0, 10.0, 4, 100)


@pytest.mark.parametrize("rounding", [0.0, 1e-14, 1e-12])
def test_the_block_tests_of_an_exact_fit_are_decided_outright(rounding):
    # y is an exact ARX of u1 and u2; u3 has no part in it.  With the output's spread set, a residual of
    # at most 1e-10 of it is rounding: the blocks of u1 and u2 are rejected outright (p 0) and u3's has
    # nothing to test (p 1), whatever the rounding is.  Without it, u3's F divides rounding by rounding.
    rng = np.random.default_rng(11)
    y, u = _arx_data(rng)
    u = np.column_stack([u, rng.standard_normal(u.shape[0])])
    y = y + rounding * np.std(y) * rng.standard_normal(y.shape[0])
    start = 6
    fit = SharedBlockRegression(lag_matrix(u, range(1, 7), start), [6, 6, 6]).fit(y[start:], -lag_matrix(y, [1, 2], start))
    fit.set_output_spread(np.std(y))
    assert fit.exact
    tests = fit.test_each_block_zero([None, None, None])
    assert [t.p_value for t in tests] == [0.0, 0.0, 1.0]
    assert [t.statistic for t in tests] == [np.inf, np.inf, 0.0]
    assert fit.test_all_common_zero().p_value == 0.0
    assert fit.test_blocks_zero([2]).p_value == 1.0


def test_a_fit_with_noise_is_not_exact_and_its_tests_are_the_ordinary_ones():
    rng = np.random.default_rng(12)
    y, u = _arx_data(rng, noise=1e-6)
    start = 6
    common, own = lag_matrix(u, range(1, 7), start), -lag_matrix(y, [1, 2], start)
    plain = SharedBlockRegression(common, [6, 6]).fit(y[start:], own)
    spread = SharedBlockRegression(common, [6, 6]).fit(y[start:], own)
    spread.set_output_spread(np.std(y))
    assert not spread.exact
    for a, b in zip(plain.test_each_block_zero([None, None]), spread.test_each_block_zero([None, None])):
        assert (a.statistic, a.p_value) == (b.statistic, b.p_value)


def test_a_large_regression_is_factored_in_place_with_one_copy_and_the_same_fits(monkeypatch):
    # From QR_IN_PLACE_BYTES on, the scaled copy becomes Q (a long window's confirmation holds 200 MB of regressors;
    # numpy.linalg.qr took five copies besides them).  The fits are numpy's to rounding.
    import tracemalloc

    from mpm_monitor.core import arx

    rng = np.random.default_rng(3)
    X = rng.standard_normal((200_000, 12)) * 10.0 ** (np.arange(12) % 4 - 1)     # 19 MB, columns of unlike sizes
    X[:, 5] += 0.5 * X[:, 4]
    y = X @ rng.standard_normal(12) + rng.standard_normal(200_000)
    own = np.column_stack([np.roll(y, 1), np.roll(y, 2)])
    small = SharedBlockRegression(X, [4, 4, 4]).fit(y, own)           # below the bound: numpy's
    monkeypatch.setattr(arx, "QR_IN_PLACE_BYTES", X.nbytes)
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        Q, R, scale, rank, _ = arx._scaled_qr(X)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 1.5 * X.nbytes                # the scaled copy (Q) and a column's worth of work: no second copy
    assert Q.shape == X.shape and R.shape == (12, 12) and rank == 12
    np.testing.assert_allclose(Q @ R, X / scale, atol=1e-12)
    np.testing.assert_allclose(Q.T @ Q, np.eye(12), atol=1e-12)
    large = SharedBlockRegression(X, [4, 4, 4]).fit(y, own)
    np.testing.assert_allclose(large.theta, small.theta, rtol=1e-9)
    for blocks in ([0], [1, 2]):
        assert large.test_blocks_zero(blocks).p_value == pytest.approx(small.test_blocks_zero(blocks).p_value,
                                                                      rel=1e-9, abs=1e-300)
