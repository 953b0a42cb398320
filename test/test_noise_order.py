"""The noise-order check (mpm_monitor.core.noise_order): the Ljung-Box statistic, the element test's
residuals from its coefficients, and ``analyze`` raising ``na`` under a slow drift."""

import dataclasses

import numpy as np
import pytest
from scipy import stats

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.arx import segment_lag_matrix, segment_rows
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.noise_order import (WHITENESS_LAGS, coloured_rows, ljung_box, next_order, row_residuals,
                                          segment_lengths)
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.regressions import GramRegressions, QrRegressions, RegressionLayout, window_regressions
from mpm_monitor.sim.closed_loop import ExcitationOptions, run_closed_loop
from mpm_monitor.sim.excitation import PrbsOptions
from mpm_monitor.sim.mpc import MpcOptions
from mpm_monitor.sim.plant import DisturbanceOptions

WOOD_BERRY = PlantModel(sample_time=1.0, inputs=("reflux", "steam"), outputs=("xd", "xb"),
                        gain=np.array([[12.8, -18.9], [6.6, -19.4]]),
                        time_constant=np.array([[16.7, 21.0], [10.9, 14.4]]),
                        delay=np.array([[1.0, 3.0], [7.0, 3.0]]))
STEPS = ExcitationOptions(setpoint=PrbsOptions(amplitude=1.0, switch_probability=0.005, min_hold=150))
MPC = MpcOptions(prediction_horizon=90, control_horizon=10, input_rate_weight=20.0)


def _reference_ljung_box(e, lags, fitted):
    """The textbook statistic of one contiguous residual (numpy.correlate), its p-value from scipy.stats."""
    e = e - e.mean()
    n = e.size
    full = np.correlate(e, e, mode="full")[n - 1:]
    r = full[1:lags + 1] / full[0]
    q = n * (n + 2) * np.sum(r ** 2 / (n - np.arange(1, lags + 1)))
    return q, stats.chi2.sf(q, lags - fitted)


def test_ljung_box_equals_the_textbook_statistic_and_its_chi2_tail():
    rng = np.random.default_rng(3)
    for e in (rng.standard_normal(500), np.convolve(rng.standard_normal(800), [1, 0.5, 0.2])[:800]):
        q, dof, p = ljung_box(e, [e.size], 24, 4)
        q_ref, p_ref = _reference_ljung_box(e, 24, 4)
        assert dof == 20
        assert q == pytest.approx(q_ref, rel=1e-12)
        assert p == pytest.approx(p_ref, rel=1e-9, abs=1e-300)


def test_ljung_box_pairs_samples_of_one_segment_only():
    rng = np.random.default_rng(4)
    a, b = rng.standard_normal(300), rng.standard_normal(200)
    e = np.concatenate([a, b])
    q, _, _ = ljung_box(e, [300, 200], 5)
    e_c = e - e.mean()
    acf = [sum(float(s[k:] @ s[:-k]) for s in (e_c[:300], e_c[300:])) for k in range(1, 6)]
    r = np.array(acf) / float(e_c @ e_c)
    assert q == pytest.approx(500 * 502 * np.sum(r ** 2 / (500 - np.arange(1, 6))), rel=1e-12)
    # A residual without spread is white.
    assert ljung_box(np.zeros(100), [100], 10) == (0.0, 10, 1.0)


def test_white_noise_keeps_its_level_and_an_ar_residual_is_coloured():
    rng = np.random.default_rng(5)
    p_white = [ljung_box(rng.standard_normal(2000), [2000], WHITENESS_LAGS)[2] for _ in range(300)]
    assert 0.0 <= np.mean(np.array(p_white) < 0.05) <= 0.09
    x = np.zeros(2000)
    e = rng.standard_normal(2000)
    for k in range(1, 2000):
        x[k] = 0.3 * x[k - 1] + e[k]
    assert ljung_box(x, [2000], WHITENESS_LAGS)[2] < 1e-10


def test_coloured_rows_and_next_order():
    assert coloured_rows({0: 0.004, 1: 0.2}) == [0]          # 0.004 x 2 < 0.01
    assert coloured_rows({0: 0.006, 1: 0.2}) == []           # 0.012 > 0.01
    assert [next_order(4, 16), next_order(8, 16), next_order(16, 16), next_order(4, 4), next_order(0, 3),
            next_order(4, 6)] == [8, 16, None, None, 1, 6]


@pytest.mark.parametrize("gaps", [False, True])
def test_row_residuals_from_the_coefficients_are_the_fits_residuals(gaps):
    """The residual rebuilt from a fit's coefficients equals the QR fit's own residual (less its mean),
    from the QR fit's coefficients and from the Gram fit's (which keeps no residual)."""
    rng = np.random.default_rng(6)
    n, nu, ny, na, n_lag = 900, 2, 2, 3, 6
    u = np.cumsum(rng.standard_normal((n, nu)), axis=0) * 0.1 + rng.standard_normal((n, nu))
    d = np.zeros((n, ny))
    e = rng.standard_normal((n, ny))
    for k in range(2, n):
        d[k] = 0.6 * d[k - 1] - 0.1 * d[k - 2] + 0.4 * u[k - 1, ::-1] + 0.2 * u[k - 2] + e[k]
    r = rng.standard_normal((n, ny))
    layout = RegressionLayout(max_delay=n_lag - 2, n_lag_r=n_lag + 1, n_lag_u=n_lag, start=n_lag, min_samples=100)
    segments = [(0, 400), (400, 900)] if gaps else None
    qr = QrRegressions(r, u, -d, d, layout, na, 2, segments=segments)
    reg = qr.input_regression([0, 1])
    blocks, own, fits = {}, {}, {}
    for i in range(ny):
        fit = qr.element_fit(reg, i)
        fits[i] = fit
        blocks[i] = np.array([fit.block_theta(b) for b in range(nu)])
        own[i] = fit.theta[fit.n_common:]
    res = row_residuals(u, d, [0, 1], [0, 1], n_lag, n_lag, blocks, own, segments)
    for i in range(ny):
        ref = fits[i].residuals - fits[i].residuals.mean()
        np.testing.assert_allclose(res[i], ref, atol=1e-9 * np.abs(ref).max())
    assert sum(segment_lengths(n, n_lag, segments)) == res[0].size
    gram = window_regressions(r, u, -d, d, layout, na, 2, segments=segments)
    assert isinstance(gram, GramRegressions)
    g_reg = gram.input_regression([0, 1])
    for i in range(ny):
        fit = gram.element_fit(g_reg, i)
        assert fit.residuals is None                     # a Gram fit has only its coefficients and RSS
        rr = row_residuals(u, d, [i], [0, 1], n_lag, n_lag, {i: np.array([fit.block_theta(b) for b in range(nu)])},
                           {i: fit.theta[fit.n_common:]}, segments)[i]
        # The Gram fit is the QR fit (its columns centred by the window means, as the QR's): the same
        # coefficients, so the same residual less its mean.
        assert fit.rss == pytest.approx(fits[i].rss, rel=1e-8)
        ref = fits[i].residuals - fits[i].residuals.mean()
        np.testing.assert_allclose(rr, ref, atol=1e-7 * np.abs(ref).max())
    # The lag matrix the fits use, for the record: the rows are the segments' rows after their start.
    assert segment_lag_matrix(u, range(1, n_lag + 1), n_lag, segments).shape[0] == segment_rows(d, n_lag, segments).shape[0]


def _drift_loop(seed: int, drift: float, n: int = 4000):
    rng = np.random.default_rng([seed, 77])
    v = np.zeros((n, 2))
    e = rng.standard_normal((n, 2))
    for k in range(1, n):
        v[k] = 0.98 * v[k - 1] + drift * e[k]
    # White measurement noise 0.02 and the drift alone (no other disturbance).
    return run_closed_loop(WOOD_BERRY, WOOD_BERRY, n, seed=seed, mpc=MPC, excitation=STEPS,
                           disturbance=DisturbanceOptions(disturbance_std=0.0, noise_std=0.02),
                           output_disturbance=v).as_logged_data(f"drift seed {seed}")


def test_a_slow_drift_raises_na_and_keeps_the_false_alarm_away():
    data = _drift_loop(6, 0.005)   # with max_na = 4, (xd, reflux) is located (a false alarm)
    rep = analyze(WOOD_BERRY, data, AnalysisOptions(repair=False))
    order = rep.noise_order
    assert order["requested"] == 4 and order["na"] > 4 and order["coloured"] == []
    assert any("residual was not white with na = 4" in w and f"ran with na = {order['na']}" in w for w in rep.warnings)
    assert rep.located_elements == []
    assert rep.to_dict()["noise_order"]["na"] == order["na"]
    # max_na = na: never raised, and said so.
    kept = analyze(WOOD_BERRY, data, AnalysisOptions(repair=False, max_na=4))
    assert kept.noise_order["na"] == 4 and kept.noise_order["coloured"]
    assert any("na was not raised (max_na 4)" in w for w in kept.warnings)
    # Both rows' level is at risk; in xd the located element (here the false alarm itself) may be the colour.
    assert set(kept.noise_order["coloured"]) == {"xd", "xb"} and kept.located_elements == [("xd", "reflux")]
    assert any("the tests' false-alarm rate may exceed alpha in xd, xb (a located mismatch in xd may be what colours "
               "the residual, or a false alarm the colour caused)" in w for w in kept.warnings)
    assert any("which whitens them" in w for w in rep.warnings)      # two rows were coloured at na = 4


def test_white_noise_keeps_na_and_the_report():
    data = _drift_loop(2, 0.0)
    rep = analyze(WOOD_BERRY, data, AnalysisOptions(repair=False))
    assert rep.noise_order["na"] == 4 and rep.noise_order["coloured"] == []
    same = analyze(WOOD_BERRY, data, AnalysisOptions(repair=False, max_na=4))
    assert rep.to_dict() == same.to_dict() | {"noise_order": rep.to_dict()["noise_order"]}


def test_a_row_without_a_testable_column_is_still_checked():
    """Inputs that never move leave no lag block: the residual is the row's own ARX's."""
    from mpm_monitor.core.logged_data import LoggedData

    model = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1",), gain=np.array([[2.0]]),
                       time_constant=np.array([[10.0]]), delay=np.array([[1.0]]))
    n = 2000
    rng = np.random.default_rng(0)
    r = np.zeros((n, 1))
    r[500:] = 1.0
    y = np.zeros((n, 1))
    e = rng.standard_normal(n) * 0.1
    for k in range(1, n):                    # an AR(1) noise, which na = 4 whitens
        y[k, 0] = 0.5 * y[k - 1, 0] + e[k]
    data = LoggedData(t=np.arange(n) * 1.0, r=r, u=np.ones((n, 1)), y=y, inputs=("u1",), outputs=("y1",),
                      sample_time=1.0)
    rep = analyze(model, data, AnalysisOptions(repair=False))
    assert any("never move" in w for w in rep.warnings)
    assert rep.noise_order["na"] == 4 and 0.0 < rep.noise_order["p_values"]["y1"] <= 1.0
    res = row_residuals(np.ones((n, 1)), y, [0], [], 5, 5, {0: np.zeros((0, 5))}, {0: np.array([-0.5])})[0]
    np.testing.assert_allclose(res, (y[5:, 0] - 0.5 * y[4:-1, 0]) - np.mean(y[5:, 0] - 0.5 * y[4:-1, 0]))


def _ma_log(n: int):
    """A clean loop under an MA(1) noise (zero at -0.95) that four or eight own lags cannot whiten."""
    rng = np.random.default_rng(1)
    e = rng.standard_normal((n + 1, 2)) * 0.05
    return run_closed_loop(WOOD_BERRY, WOOD_BERRY, n, seed=1, mpc=MPC,
                           disturbance=DisturbanceOptions(disturbance_std=0.0, noise_std=0.0),
                           output_disturbance=e[1:] + 0.95 * e[:-1]).as_logged_data("ma")


def test_a_log_too_short_for_the_raised_order_keeps_the_last_one_and_says_why():
    # 400 samples with max_delay 51: the tests need 398 at na = 4 and 410 at na = 8: the raise is
    # refused by the data, not the run.
    rep = analyze(WOOD_BERRY, _ma_log(400), AnalysisOptions(repair=False, max_delay=51))
    assert rep.noise_order["na"] == 4 and rep.noise_order["coloured"]
    assert any("the tests ran with na = 4: na = 8 needs more data" in w and "need at least 410 samples" in w
               for w in rep.warnings)


@pytest.mark.parametrize("all_rows", [True, False])
@pytest.mark.parametrize("na", [4, 8, 16])
def test_detect_unless_coloured_stops_at_the_fits_or_gives_the_detection(all_rows, na):
    """Coloured: the detection's noise order, signals and gaps without its tests; white: its very report."""
    from mpm_monitor.core.analysis import Coloured, detect, detect_unless_coloured

    data = _drift_loop(6, 0.005, n=2500)
    keep = np.ones(data.n_samples, bool)
    keep[[700, 701, 1500, 1900]] = False
    seen = set()
    for log in (data, data.take(np.flatnonzero(keep))):           # with gaps: the same segments and rows
        options = AnalysisOptions(repair=False, na=na, test_all_rows=all_rows)
        full = detect(WOOD_BERRY, log, options)
        got = detect_unless_coloured(WOOD_BERRY, log, options)
        assert got.noise_order == full.noise_order
        seen.add(bool(full.noise_order["coloured"]))
        if full.noise_order["coloured"]:
            assert isinstance(got, Coloured) and got.gaps == full.gaps
            np.testing.assert_array_equal(got.signals.d, full.signals.d)
        else:
            assert got.to_dict() == full.to_dict()
    if na != 8:                                                   # both kinds are exercised
        assert seen == {na == 4}


def test_an_order_only_probed_is_detected_when_the_next_needs_more_data():
    # As the test above with 420 samples: na = 8 fits (410 needed) and stays coloured, na = 16 does not fit.
    log = _ma_log(420)
    rep = analyze(WOOD_BERRY, log, AnalysisOptions(repair=False, max_delay=51))
    assert rep.noise_order["na"] == 8 and rep.noise_order["coloured"] and rep.noise_order["requested"] == 4
    assert any("the tests ran with na = 8: na = 16 needs more data" in w for w in rep.warnings)
    # The detection at na = 8, as a run that starts there.
    at8 = analyze(WOOD_BERRY, log, AnalysisOptions(repair=False, max_delay=51, na=8, max_na=8))
    assert [dataclasses.asdict(e) for e in rep.elements] == [dataclasses.asdict(e) for e in at8.elements]
    assert [r.p_value for r in rep.rows] == [r.p_value for r in at8.rows]
