"""The whole-response element test: its F test against least squares and scipy, its level, its
Bonferroni combination with the lag-window test, and what it sees that the window does not."""

import numpy as np
import pytest
from scipy import stats
from scipy.signal import lfilter

import mpm_monitor.core.element_test as element_test
from bench.structures_mc import make_structures_scenario, simulate
from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.arx import SharedBlockRegression, lag_matrix, segment_lag_matrix, segment_rows
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.response_test import combined_p_value, row_response_tests

N_LAG, NA = 8, 2


def _reference(model, i, j, u_c, d_c, a, start, n_lag, na, testable, segments=None):
    """F statistic, dof and p of the response regressor by brute-force least squares (numpy, scipy.stats)."""
    y = segment_rows(d_c[:, i], start, segments)
    others = [segment_lag_matrix(u_c[:, k], range(1, n_lag + 1), start, segments) for k in testable if k != j]
    own = -segment_lag_matrix(d_c[:, i], range(1, na + 1), start, segments)
    W = np.hstack(others + [own])
    runs = [(0, u_c.shape[0])] if segments is None else segments
    x = np.zeros(u_c.shape[0])
    for lo, hi in runs:
        el = model.discrete_element(i, j)
        x[lo:hi] = lfilter(np.r_[1.0, a], [1.0], el.respond(u_c[lo:hi, j]))
    xt = segment_rows(x, start, segments)
    xt = xt - xt.mean()
    r0 = y - W @ np.linalg.lstsq(W, y, rcond=None)[0]
    W1 = np.column_stack([W, xt])
    r1 = y - W1 @ np.linalg.lstsq(W1, y, rcond=None)[0]
    dof = y.size - W1.shape[1]
    f = (r0 @ r0 - r1 @ r1) / (r1 @ r1 / dof)
    return f, dof, stats.f.sf(f, 1, dof)


def _open_loop(seed, n=1500, gain_error=0.0, segments=None):
    """Two inputs (white and slow PRBS-like), one output with AR(1) noise; element (0, 0) is slow."""
    rng = np.random.default_rng(seed)
    model = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1",), gain=np.array([[1.5, -0.8]]),
                       time_constant=np.array([[40.0, 6.0]]), time_constant2=np.array([[15.0, 0.0]]),
                       delay=np.array([[2.0, 1.0]]))
    u = np.column_stack([np.repeat(rng.choice([-1.0, 1.0], n // 5 + 1), 5)[:n], rng.standard_normal(n)])
    u_c = u - u.mean(axis=0)
    noise = lfilter([1.0], [1.0, -0.7], 0.05 * rng.standard_normal(n))
    d = gain_error * model.discrete_element(0, 0).respond(u_c[:, 0]) + noise
    return model, u_c, (d - d.mean())[:, None]


@pytest.mark.parametrize("segments", [None, [(0, 700), (700, 1500)]])
def test_response_test_equals_least_squares_and_scipy(segments):
    model, u_c, d_c = _open_loop(3, gain_error=0.05)
    start = max(N_LAG, NA)
    testable = [0, 1]
    X = np.hstack([segment_lag_matrix(u_c[:, k], range(1, N_LAG + 1), start, segments) for k in testable])
    own = -segment_lag_matrix(d_c[:, 0], range(1, NA + 1), start, segments)
    fit = SharedBlockRegression(X, [N_LAG, N_LAG]).fit(segment_rows(d_c[:, 0], start, segments), own)
    tests = row_response_tests(model, 0, fit, testable, X, [N_LAG, N_LAG], u_c, d_c, start, NA, segments)
    assert set(tests) == {0, 1}
    for j, t in tests.items():
        f, dof, p = _reference(model, 0, j, u_c, d_c, fit.own_theta(), start, N_LAG, NA, testable, segments)
        assert t.df_num == 1 and t.df_den == dof
        assert t.statistic == pytest.approx(f, rel=1e-8)
        assert t.p_value == pytest.approx(p, rel=1e-6, abs=1e-300)


def test_response_test_keeps_its_level_without_mismatch():
    """Under "no mismatch" the p-values are uniform: 400 draws, Kolmogorov-Smirnov against U(0, 1)."""
    ps = []
    start = max(N_LAG, NA)
    for seed in range(200):
        model, u_c, d_c = _open_loop(100 + seed, n=800)
        X = np.hstack([lag_matrix(u_c[:, k], range(1, N_LAG + 1), start) for k in (0, 1)])
        own = -lag_matrix(d_c[:, 0], range(1, NA + 1), start)
        fit = SharedBlockRegression(X, [N_LAG, N_LAG]).fit(d_c[start:, 0], own)
        ps += [t.p_value for t in row_response_tests(model, 0, fit, [0, 1], X, [N_LAG, N_LAG], u_c, d_c, start,
                                                     NA).values()]
    ps = np.array(ps)
    assert stats.kstest(ps, "uniform").pvalue > 0.01
    assert np.mean(ps < 0.05) < 0.08


def test_a_slow_gain_error_is_seen_by_the_response_not_the_window():
    model, u_c, d_c = _open_loop(5, gain_error=0.1)
    start = max(N_LAG, NA)
    X = np.hstack([lag_matrix(u_c[:, k], range(1, N_LAG + 1), start) for k in (0, 1)])
    own = -lag_matrix(d_c[:, 0], range(1, NA + 1), start)
    fit = SharedBlockRegression(X, [N_LAG, N_LAG]).fit(d_c[start:, 0], own)
    window = fit.test_blocks_zero([0], element_test.element_window(model, 0, 0, 4)).p_value
    response = row_response_tests(model, 0, fit, [0, 1], X, [N_LAG, N_LAG], u_c, d_c, start, NA)[0].p_value
    assert response < 1e-6 and window > 0.1


def test_combined_p_value_is_bonferroni_over_the_two_tests():
    assert combined_p_value(0.3, None) == 0.3
    assert combined_p_value(0.3, 0.01) == pytest.approx(0.02)
    assert combined_p_value(0.002, 0.4) == pytest.approx(0.004)
    assert combined_p_value(0.7, 0.6) == 1.0


@pytest.fixture(scope="module")
def structures_run():
    sc = make_structures_scenario(0, 2)
    return sc, simulate(sc, 3000).as_logged_data("run 2")


def test_the_report_carries_both_p_values_and_their_combination(structures_run):
    sc, data = structures_run
    report = detect(sc.model, data, AnalysisOptions(repair=False))
    tested = [e for e in report.elements if e.p_value_window is not None]
    assert tested
    for e in tested:
        present = sc.model.present[sc.model.outputs.index(e.output), sc.model.columns.index(e.input)]
        assert (e.p_value_response is not None) == bool(present)
        assert e.p_value_raw == pytest.approx(combined_p_value(e.p_value_window, e.p_value_response))
    off = detect(sc.model, data, AnalysisOptions(repair=False, element_response=False))
    assert all(e.p_value_response is None and e.p_value_raw == e.p_value_window
               for e in off.elements if e.p_value_window is not None)


def test_gram_and_qr_paths_give_the_same_response_tests(structures_run):
    from mpm_monitor.core.regressions import QrRegressions, regression_layout
    from mpm_monitor.core.signals import compute_signals

    sc, data = structures_run
    options = AnalysisOptions(repair=False)
    gram = detect(sc.model, data, options)
    layout = regression_layout(sc.model, options)
    cols = np.column_stack([data.u, data.dv]) if data.dv.size else np.asarray(data.u)
    sig = compute_signals(sc.model, data.r, data.u, data.y, options.initial_state, dv=data.dv if data.dv.size else None)
    qr = detect(sc.model, data, options,
                regressions=QrRegressions(data.r, cols, sig.eps - data.r, sig.d, layout, options.na, options.nb))
    for a, b in zip(gram.elements, qr.elements):
        assert (a.p_value_response is None) == (b.p_value_response is None)
        if a.p_value_response is not None:
            assert a.p_value_response == pytest.approx(b.p_value_response, rel=1e-6, abs=1e-12)
