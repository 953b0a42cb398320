"""The whole-response element test: its F test against least squares and scipy, its level, its
Bonferroni combination with the lag-window test, and what it sees that the window does not."""

import numpy as np
import pytest
from scipy import stats
from scipy.signal import lfilter

import mpm_monitor.core.element_windows as element_windows
from bench.structures_mc import make_structures_scenario, simulate
from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.arx import SharedBlockRegression, lag_matrix, segment_lag_matrix, segment_rows
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.segments import GapSegments
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
    # Centred over each segment's rows, as the prediction error is (one record: over all rows).
    xt = np.concatenate([(r := x[lo + start:hi]) - r.mean() for lo, hi in runs])
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


@pytest.mark.parametrize("segments", [None, [(0, 700), (700, 1500)]])
def test_the_response_test_on_some_rows_equals_least_squares_on_those_rows(segments):
    """``rows``: the regressors on the rows the fit holds (the confirmation with tails on data with gaps),
    each centred over its segment's rows among them; against brute-force least squares on those rows."""
    model, u_c, d_c = _open_loop(4, gain_error=0.05)
    start, testable = max(N_LAG, NA), [0, 1]
    n_rows = segment_rows(d_c[:, 0], start, segments).size
    rows = np.random.default_rng(1).random(n_rows) > 0.3
    rows[:60] = False
    X = np.hstack([segment_lag_matrix(u_c[:, k], range(1, N_LAG + 1), start, segments) for k in testable])[rows]
    own = -segment_lag_matrix(d_c[:, 0], range(1, NA + 1), start, segments)[rows]
    y = segment_rows(d_c[:, 0], start, segments)[rows]
    fit = SharedBlockRegression(X, [N_LAG, N_LAG]).fit(y, own)
    tests = row_response_tests(model, 0, fit, testable, X, [N_LAG, N_LAG], u_c, d_c, start, NA, segments, rows=rows)
    a = fit.own_theta()
    seg_of = np.concatenate([np.full(b - lo - start, k) for k, (lo, b) in enumerate(segments or [(0, u_c.shape[0])])])[rows]
    for j, t in tests.items():
        x = np.concatenate([lfilter(np.r_[1.0, a], [1.0], model.discrete_element(0, j).respond(u_c[lo:hi, j]))[start:]
                            for lo, hi in (segments or [(0, u_c.shape[0])])])[rows]
        for k in np.unique(seg_of):
            x[seg_of == k] -= x[seg_of == k].mean()
        W = np.hstack([X[:, [c for c in range(2 * N_LAG) if c // N_LAG != j]], own])
        r0 = y - W @ np.linalg.lstsq(W, y, rcond=None)[0]
        W1 = np.column_stack([W, x])
        r1 = y - W1 @ np.linalg.lstsq(W1, y, rcond=None)[0]
        dof = y.size - W1.shape[1]
        f = (r0 @ r0 - r1 @ r1) / (r1 @ r1 / dof)
        assert t.df_den == dof and t.statistic == pytest.approx(f, rel=1e-8)
        assert t.p_value == pytest.approx(stats.f.sf(f, 1, dof), rel=1e-6, abs=1e-300)
    with pytest.raises(ValueError, match="common"):
        row_response_tests(model, 0, fit, testable, None, [N_LAG, N_LAG], u_c, d_c, start, NA, segments, rows=rows)


@pytest.mark.parametrize("integrating", [False, True])
def test_a_self_regulating_row_keeps_one_level_through_short_gaps(integrating):
    """Through the short gaps of a GapSegments (the model runs through them) a row without an integrating element
    keeps one level: the response regressor is centred over the run's rows, not each segment's; a row with one
    keeps a level per segment.  Against brute-force least squares (numpy, scipy.stats) with the response
    simulated on the sample grid, its columns held through the gaps."""
    model, u_c, d_c = _open_loop(6, gain_error=0.05)
    if integrating:
        model = model.with_element(0, 1, integrating=True, gain=0.01)
    grid = np.concatenate([np.arange(700), np.arange(701, 1101), np.arange(1103, 1503)])    # 1 and 2 samples missing
    segments = GapSegments([(0, 700), (700, 1100), (1100, 1500)], grid, 10)
    start, testable = max(N_LAG, NA), [0, 1]
    X = np.hstack([segment_lag_matrix(u_c[:, k], range(1, N_LAG + 1), start, segments) for k in testable])
    own = -segment_lag_matrix(d_c[:, 0], range(1, NA + 1), start, segments)
    y = segment_rows(d_c[:, 0], start, segments)
    fit = SharedBlockRegression(X, [N_LAG, N_LAG]).fit(y, own)
    tests = row_response_tests(model, 0, fit, testable, X, [N_LAG, N_LAG], u_c, d_c, start, NA, segments)
    a = fit.own_theta()
    held = np.searchsorted(grid, np.arange(grid[-1] + 1), side="right") - 1      # the last row at or before
    labels = np.repeat([0, 1, 2], [700 - start, 400 - start, 400 - start])
    j = 0                                        # the slow element; the reference is the one-regressor F test
    x = model.discrete_element(0, j).respond(u_c[held, j])[grid]
    xf = np.concatenate([lfilter(np.r_[1.0, a], [1.0], x[lo:hi])[start:] for lo, hi in segments])
    W = np.hstack([X[:, N_LAG:], own])
    r0 = y - W @ np.linalg.lstsq(W, y, rcond=None)[0]

    def p_value(levels):
        xt = xf.copy()
        for g in np.unique(levels):
            xt[levels == g] -= xt[levels == g].mean()
        W1 = np.column_stack([W, xt])
        r1 = y - W1 @ np.linalg.lstsq(W1, y, rcond=None)[0]
        dof = y.size - W1.shape[1]
        return (r0 @ r0 - r1 @ r1) / (r1 @ r1 / dof), stats.f.sf((r0 @ r0 - r1 @ r1) / (r1 @ r1 / dof), 1, dof)

    per_run, per_segment = p_value(np.zeros_like(labels)), p_value(labels)
    assert abs(per_run[1] / per_segment[1] - 1.0) > 1e-3          # the two centrings are told apart here
    f, p = per_segment if integrating else per_run
    assert tests[j].statistic == pytest.approx(f, rel=1e-8)
    assert tests[j].p_value == pytest.approx(p, rel=1e-6, abs=1e-300)


def _row_fit(u_c, d_c, start):
    """The element fit of row 0 on both columns' lags 1 .. N_LAG and its own lags 1 .. NA: ``(X, fit)``."""
    X = np.hstack([lag_matrix(u_c[:, k], range(1, N_LAG + 1), start) for k in (0, 1)])
    own = -lag_matrix(d_c[:, 0], range(1, NA + 1), start)
    return X, SharedBlockRegression(X, [N_LAG, N_LAG]).fit(d_c[start:, 0], own)


def _integrating_loop(seed, n=1500, tau_error=0.0):
    """Element (0, 0) integrating (gain per second); the plant's time constant of it off by ``tau_error``."""
    rng = np.random.default_rng(seed)
    model = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1",), gain=np.array([[0.05, -0.8]]),
                       time_constant=np.array([[8.0, 6.0]]), delay=np.array([[2.0, 1.0]]),
                       integrating=np.array([[True, False]]))
    plant = model.with_element(0, 0, time_constant=8.0 * (1.0 + tau_error))
    u = np.column_stack([np.repeat(rng.choice([-1.0, 1.0], n // 5 + 1), 5)[:n], rng.standard_normal(n)])
    u_c = u - u.mean(axis=0)
    noise = lfilter([1.0], [1.0, -0.7], 0.01 * rng.standard_normal(n))
    d = plant.discrete_element(0, 0).respond(u_c[:, 0]) - model.discrete_element(0, 0).respond(u_c[:, 0]) + noise
    return model, u_c, (d - d.mean())[:, None]


def _grouped_reference(model, u_c, d_c, a, start):
    """F, dof and p of ``[A x, A s / (tau s + 1) x]`` of integrating element (0, 0) by brute-force least
    squares (numpy, scipy.signal, scipy.stats)."""
    y = d_c[start:, 0]
    others = lag_matrix(u_c[:, 1], range(1, N_LAG + 1), start)
    own = -lag_matrix(d_c[:, 0], range(1, NA + 1), start)
    W = np.hstack([others, own])
    X = _sensitivity_pair(model, 0, u_c, a, start)
    X = X - X.mean(axis=0)
    r0 = y - W @ np.linalg.lstsq(W, y, rcond=None)[0]
    W1 = np.column_stack([W, X])
    r1 = y - W1 @ np.linalg.lstsq(W1, y, rcond=None)[0]
    dof = y.size - W1.shape[1]
    f = (r0 @ r0 - r1 @ r1) / 2 / (r1 @ r1 / dof)
    return f, dof, stats.f.sf(f, 2, dof)


def test_an_integrating_element_is_tested_with_its_time_constant_sensitivity_too():
    """For an integrating element the test has two regressors, the response and its sensitivity to the
    time constant (the response differenced and lagged once more): two numerator degrees of freedom,
    the F test of least squares; a time-constant error is seen by it and hardly by the response alone."""
    model, u_c, d_c = _integrating_loop(4, tau_error=0.5)
    start = max(N_LAG, NA)
    X, fit = _row_fit(u_c, d_c, start)
    t = row_response_tests(model, 0, fit, [0, 1], X, [N_LAG, N_LAG], u_c, d_c, start, NA)[0]
    f, dof, p = _grouped_reference(model, u_c, d_c, fit.own_theta(), start)
    assert t.df_num == 2 and t.df_den == dof
    assert t.statistic == pytest.approx(f, rel=1e-8)
    assert t.p_value == pytest.approx(p, rel=1e-6, abs=1e-300)
    assert p < 1e-6
    alone = _reference(model, 0, 0, u_c, d_c, fit.own_theta(), start, N_LAG, NA, [0, 1])[2]
    assert alone > 1e3 * p
    assert row_response_tests(model, 0, fit, [0, 1], X, [N_LAG, N_LAG], u_c, d_c, start, NA)[1].df_num == 1


def _two_integrators(seed, n=1500, gain_error=0.0):
    """Both elements integrating; the plant's gain of element (0, 1) off by ``gain_error``, (0, 0) right."""
    rng = np.random.default_rng(seed)
    model = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1",), gain=np.array([[0.05, -0.04]]),
                       time_constant=np.array([[8.0, 5.0]]), delay=np.array([[2.0, 1.0]]),
                       integrating=np.array([[True, True]]))
    plant = model.with_element(0, 1, gain=-0.04 * (1.0 + gain_error))
    u = np.column_stack([np.repeat(rng.choice([-1.0, 1.0], n // 5 + 1), 5)[:n], rng.standard_normal(n)])
    u = u + 0.5 * np.roll(u[:, ::-1], 3, axis=0)                  # the columns move partly together
    u_c = u - u.mean(axis=0)
    noise = lfilter([1.0], [1.0, -0.7], 0.01 * rng.standard_normal(n))
    d = plant.discrete_element(0, 1).respond(u_c[:, 1]) - model.discrete_element(0, 1).respond(u_c[:, 1]) + noise
    return model, u_c, (d - d.mean())[:, None]


def _sensitivity_pair(model, j, u_c, a, start):
    """``[A x, A s / (tau s + 1) x]`` of integrating element (0, j) on the regression rows."""
    x = model.discrete_element(0, j).respond(u_c[:, j])
    p = np.exp(-1.0 / model.time_constant[0, j])
    sens = lfilter([1.0 - p], [1.0, -p], np.r_[x[0], np.diff(x)])
    return np.column_stack([lfilter(np.r_[1.0, a], [1.0], v) for v in (x, sens)])[start:]


def _fit_with_the_other_response_free(model, u_c, d_c, start):
    """Row 0's element fit with integrating element (0, 1)'s response (lags 0 .. NA) free beside its own
    lags, as the confirmation of a row's located elements has it: ``(X, fit, extra)``."""
    X = np.hstack([lag_matrix(u_c[:, k], range(1, N_LAG + 1), start) for k in (0, 1)])
    extra = lag_matrix(model.discrete_element(0, 1).respond(u_c[:, 1]), range(NA + 1), start)
    own = np.hstack([-lag_matrix(d_c[:, 0], range(1, NA + 1), start), extra])
    return X, SharedBlockRegression(X, [N_LAG, N_LAG]).fit(d_c[start:, 0], own), extra


def _test_with_the_other_free(model, u_c, d_c, start):
    X, fit, extra = _fit_with_the_other_response_free(model, u_c, d_c, start)
    return row_response_tests(model, 0, fit, [0, 1], X, [N_LAG, N_LAG], u_c, d_c, start, NA, columns=[0],
                              a=fit.own_theta()[:NA], extra=extra)[0], fit, extra


def test_another_integrating_elements_response_can_stay_free():
    """Two integrating elements, (0, 1) with a 40 % gain error that no lags of u2 can carry.  With
    (0, 1)'s response free beside it (``extra``), the test of (0, 0) is least squares' F test of its
    two regressors, and keeps its level (200 draws); without, 199 of the 200 p-values are below 0.05.
    Its level without the gain error: :func:`test_the_integrating_elements_test_keeps_its_level_without_mismatch`."""
    start = max(N_LAG, NA)
    model, u_c, d_c = _two_integrators(7, gain_error=0.4)
    t, fit, extra = _test_with_the_other_free(model, u_c, d_c, start)
    y = d_c[start:, 0]
    base = np.hstack([lag_matrix(u_c[:, 1], range(1, N_LAG + 1), start), -lag_matrix(d_c[:, 0], range(1, NA + 1), start),
                      extra])
    pair = _sensitivity_pair(model, 0, u_c, fit.own_theta()[:NA], start)
    full = np.hstack([base, pair - pair.mean(axis=0)])
    r0 = y - base @ np.linalg.lstsq(base, y, rcond=None)[0]
    r1 = y - full @ np.linalg.lstsq(full, y, rcond=None)[0]
    dof = y.size - np.linalg.matrix_rank(full)      # (x's lags 0 .. NA and u2's lags share a direction)
    f = (r0 @ r0 - r1 @ r1) / 2 / (r1 @ r1 / dof)
    assert t.df_num == 2 and t.df_den == dof
    assert t.statistic == pytest.approx(f, rel=1e-6)
    ps = np.array([_test_with_the_other_free(*_two_integrators(seed, 800, gain_error=0.4), start)[0].p_value
                   for seed in range(900, 1100)])
    assert np.mean(ps < 0.05) < 0.09          # conservative here (none below 0.05): never liberal
    leaking = _null_p_values(lambda seed, n: _two_integrators(seed, n, gain_error=0.4), range(900, 1100), [0])
    assert np.mean(leaking < 0.05) > 0.9


def _null_p_values(loop, seeds, columns):
    """Response-test p-values of ``columns`` of row 0 over loops ``loop(seed, n=800)`` without a mismatch."""
    ps = []
    start = max(N_LAG, NA)
    for seed in seeds:
        model, u_c, d_c = loop(seed, n=800)
        X, fit = _row_fit(u_c, d_c, start)
        tests = row_response_tests(model, 0, fit, [0, 1], X, [N_LAG, N_LAG], u_c, d_c, start, NA)
        ps += [tests[j].p_value for j in columns]
    return np.array(ps)


def test_the_integrating_elements_test_keeps_its_level_without_mismatch():
    """Under "no mismatch" the two-regressor test's p-values are uniform (300 draws, Kolmogorov-Smirnov)."""
    ps = _null_p_values(_integrating_loop, range(500, 800), [0])
    assert stats.kstest(ps, "uniform").pvalue > 0.01
    assert np.mean(ps < 0.05) < 0.09


def test_response_test_keeps_its_level_without_mismatch():
    """Under "no mismatch" the p-values are uniform: 400 draws, Kolmogorov-Smirnov against U(0, 1)."""
    ps = _null_p_values(_open_loop, range(100, 300), [0, 1])
    assert stats.kstest(ps, "uniform").pvalue > 0.01
    assert np.mean(ps < 0.05) < 0.08


def test_a_slow_gain_error_is_seen_by_the_response_not_the_window():
    model, u_c, d_c = _open_loop(5, gain_error=0.1)
    start = max(N_LAG, NA)
    X, fit = _row_fit(u_c, d_c, start)
    window = fit.test_blocks_zero([0], element_windows.element_window(model, 0, 0, 4)).p_value
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


def test_regressors_are_centred_over_each_segments_rows():
    from mpm_monitor.core.response_test import centred_rows

    rng = np.random.default_rng(5)
    start, segments = 3, [(0, 10), (10, 12), (12, 30)]      # the second segment has no row (2 <= start)
    X = rng.standard_normal((7 + 15, 2)) + np.repeat([[5.0, -1.0], [-2.0, 4.0]], [7, 15], axis=0)
    out = centred_rows(X, start, segments)
    np.testing.assert_allclose(out[:7].mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(out[7:].mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(out[7:] - X[7:], -X[7:].mean(axis=0) * np.ones((15, 1)))
    assert np.array_equal(centred_rows(X, start, None), X - X.mean(axis=0))
    assert np.array_equal(centred_rows(X, start, [(0, 22 + start)]), X - X.mean(axis=0))
    assert out is not X and X[0, 0] != out[0, 0]
