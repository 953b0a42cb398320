"""Sliding-window analysis from sufficient statistics equals the batch QR analysis of the same window.

"Same window" (mpm_monitor/core/sliding.py): the last W samples of r, u, y, with yhat, d and eps from
the controller's model run from rest at the first pushed sample -- i.e. compute_signals(...,
initial_state="zero") over every pushed sample, cut to the window, passed to analyze(signals=...)
with the QR regressions (regressions.QrRegressions: the reference, not the default Gram path).
Tolerance 1e-8 on log p-values, F statistics, RSI and coefficients (coefficients relative to the
largest of their vector); the decisions (flagged rows, located and ambiguous elements) must be equal.

The analyzer's own model run (sample-wise recursion) and compute_signals (one filter per element)
agree to ~1e-16 relative; on ill-conditioned data (collinear inputs, a step of the operating point inside
the window) even that difference is amplified beyond 1e-8 by the batch QR itself, so those tests give
the batch path the analyzer's signals (SlidingWindowAnalyzer.window_data), as the live monitor does.
"""


import numpy as np
import pytest
from scipy import signal as sps

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.arx import SharedBlockRegression, lag_matrix
from mpm_monitor.core.discretize import ModelPredictor
from mpm_monitor.core.errors import ConfigurationError, DataFileError
from mpm_monitor.core.gram_fits import GramBlockRegression, GramFit
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.regressions import QrRegressions, regression_layout
from mpm_monitor.core.signals import LoopSignals, compute_signals
from mpm_monitor.core.sliding import SlidingWindowAnalyzer
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import ExcitationOptions, run_closed_loop

FAST = AnalysisOptions(repair=False, test_all_rows=True)


# ------------------------------------------------------------------------------------ helpers
def _case_log(name, n, seed, excitation=None):
    case = paper_case(name)
    log = run_closed_loop(case.plant, case.model, n, seed=seed, mpc=case.mpc,
                          excitation=excitation or case.excitation, disturbance=case.disturbance)
    return case, log


def _qr_analyze(model, data, options, sig):
    """The batch QR path (every regression factored by QR from the window's signals)."""
    regs = QrRegressions(data.r, data.u, sig.eps - data.r, sig.d, regression_layout(model, options),
                         options.na, options.nb)
    return analyze(model, data, options, signals=sig, regressions=regs)


def _batch_same_signals(an, options):
    """The batch reference on the analyzer's window and signals."""
    data, sig = an.window_data()
    return _qr_analyze(an.model, data, options, sig)


def _batch_of_window(model, r, u, y, window, options):
    """The batch reference: model run from rest over everything, cut to the last ``window`` samples."""
    sig = compute_signals(model, r, u, y, "zero")
    w = slice(max(0, r.shape[0] - window), r.shape[0])
    data = LoggedData(t=np.arange(r.shape[0])[w] * model.sample_time, r=r[w], u=u[w], y=y[w],
                      inputs=model.inputs, outputs=model.outputs, sample_time=model.sample_time)
    return _qr_analyze(model, data, options, LoopSignals(sig.yhat[w], sig.d[w], sig.eps[w], sig.transient[w]))


from report_checks import _close, _close_vec, assert_reports_match  # noqa: E402


def _offset_open_loop(n, seed, model, plant):
    """Open-loop data far from zero (r ~ 100, u ~ 30, y ~ 50): stresses the centring of the statistics."""
    rng = np.random.default_rng(seed)
    ny, nu = model.n_outputs, model.n_inputs
    r = 100.0 + np.where(rng.random((n, ny)) < 0.5, 1.0, -1.0)
    u = 30.0 + sps.lfilter([1.0], [1.0, -0.7], rng.standard_normal((n, nu)), axis=0)
    y = 50.0 + ModelPredictor(plant).run(u - 30.0) + 0.05 * rng.standard_normal((n, ny))
    y = y - 0.3 * (r - 100.0)          # the row test sees r in d: every row flagged
    return r, u, y


# ------------------------------------------------------------------------------------ the model
def _model_with_every_element_kind():
    return PlantModel(1.0, ["u1", "u2", "u3"], ["y1", "y2"],
                      gain=[[2.0, 0.0, -1.5], [0.5, 3.0, 1.0]],
                      time_constant=[[20.0, 10.0, 0.0], [5.0, 0.0, 40.0]],
                      delay=[[3.0, 0.0, 2.0], [0.0, 0.0, 7.0]])       # (y2, u2): static feed-through


def test_model_predictor_equals_the_dense_state_space_simulation():
    model = _model_with_every_element_kind()
    u = np.random.default_rng(0).standard_normal((400, 3))
    ref = compute_signals(model, np.zeros((400, 2)), u, np.zeros((400, 2)), "zero").yhat
    one = ModelPredictor(model)
    stepped = np.array([one.step(u[k]) for k in range(400)])
    chunked = ModelPredictor(model)
    runs = np.vstack([chunked.run(u[a:a + 37]) for a in range(0, 400, 37)])
    np.testing.assert_allclose(stepped, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    np.testing.assert_allclose(runs, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


# ------------------------------------------------------------------------------------ Gram solve
def test_gram_regression_equals_the_qr_regression():
    """Frisch-Waugh-Lovell from cross products equals the QR fit (theta, RSS, block tests)."""
    rng = np.random.default_rng(1)
    x = sps.lfilter([1.0], [1.0, -0.5], rng.standard_normal((3000, 3)), axis=0)
    y = x[:, 0] * 0.5 + np.roll(x[:, 2], 2) * 0.3 + 0.1 * rng.standard_normal(3000)
    start = 6
    common = lag_matrix(x, range(1, 6), start)
    own = -lag_matrix(y, [1, 2], start)
    target = y[start:]
    qr = SharedBlockRegression(common, [5, 5, 5]).fit(target, own)
    reg = GramBlockRegression(common.T @ common, [5, 5, 5])
    fit = GramFit(reg, common.T @ own, own.T @ own, common.T @ target, own.T @ target, float(target @ target),
                  float(target.sum()), target.shape[0])
    _close_vec(fit.theta, qr.theta, "theta")
    _close(fit.rss, qr.rss, "rss")
    _close(fit.rss_own_only, qr.rss_own_only, "rss own only")
    for blocks in ([0], [1], [2], [0, 2]):
        _close(fit.test_blocks_zero(blocks).statistic, qr.test_blocks_zero(blocks).statistic, f"F {blocks}")
    _close(fit.test_all_common_zero().statistic, qr.test_all_common_zero().statistic, "F all")
    for b in range(3):
        _close_vec(fit.block_std(b), qr.block_std(b), f"std {b}")


# ------------------------------------------------------------------------------------ analysis
@pytest.mark.parametrize("name", ["3.2", "3.3"])
def test_sliding_window_equals_batch_on_the_paper_cases(name):
    case, log = _case_log(name, 3200, seed=21)
    window = 2500
    an = SlidingWindowAnalyzer(case.model, FAST, window)
    an.push_many(log.r[:3000], log.u[:3000], log.y[:3000])
    for k in range(3000, 3200):                 # the window slides 700 samples past its start
        an.push(log.r[k], log.u[k], log.y[k])
    inc = an.analyze()
    ref = _batch_of_window(case.model, log.r, log.u, log.y, window, FAST)
    assert_reports_match(inc, ref)
    assert an.last_fallbacks == []              # well-conditioned: solved from the statistics
    assert set(inc.located_elements) == set(case.mismatched_elements)


def test_every_periodic_analysis_equals_batch_while_the_window_fills_and_slides():
    case, log = _case_log("3.2", 2600, seed=22)
    window = 1200
    an = SlidingWindowAnalyzer(case.model, FAST, window, update_block=7)
    done = 0
    for stop in (700, 1200, 1571, 2600):       # growing, full, sliding by an odd amount, sliding far
        an.push_many(log.r[done:stop], log.u[done:stop], log.y[done:stop])
        done = stop
        assert an.n_samples == min(stop, window)
        assert_reports_match(an.analyze(), _batch_of_window(case.model, log.r[:stop], log.u[:stop],
                                                            log.y[:stop], window, FAST))


def test_push_one_by_one_and_in_blocks_give_the_same_report():
    case, log = _case_log("3.2", 1800, seed=23)
    a = SlidingWindowAnalyzer(case.model, FAST, 1000, update_block=1)
    b = SlidingWindowAnalyzer(case.model, FAST, 1000, update_block=64)
    for k in range(1800):
        a.push(log.r[k], log.u[k], log.y[k])
    b.push_many(log.r, log.u, log.y)
    assert_reports_match(a.analyze(), b.analyze())


def test_long_run_drift_stays_below_1e_8():
    """50,000 pushes, each entering and leaving the statistics, with and without periodic rebuilds."""
    case = paper_case("3.2")
    model = case.model
    r, u, y = _offset_open_loop(50_000, 3, model, case.plant)
    window = 400
    opts = AnalysisOptions(repair=False, test_all_rows=True, max_delay=6)
    no_rebuild = SlidingWindowAnalyzer(model, opts, window, update_block=4, refresh_interval=0)
    periodic = SlidingWindowAnalyzer(model, opts, window, update_block=4)
    for k in range(50_000):
        no_rebuild.push(r[k], u[k], y[k])
        periodic.push(r[k], u[k], y[k])
    assert no_rebuild.rebuilds < 10            # only while the window fills (cheaper than updating)
    assert periodic.rebuilds > 100
    for an in (no_rebuild, periodic):
        assert an.gram_drift() < 1e-8
        assert_reports_match(an.analyze(), _batch_of_window(model, r, u, y, window, opts))


def test_a_jump_of_the_operating_point_is_absorbed():
    """A step of 1000 standard deviations in every signal re-centres the statistics (no loss of digits)."""
    case = paper_case("3.2")
    r, u, y = _offset_open_loop(4000, 4, case.model, case.plant)
    for x in (r, u, y):
        x[1500:] += 1e3
    an = SlidingWindowAnalyzer(case.model, FAST, 1200, refresh_interval=0)
    an.push_many(r[:1400], u[:1400], y[:1400])
    an.analyze()
    rebuilds = an.rebuilds
    for k in range(1400, 3000):                # the window ends up wholly after the step
        an.push(r[k], u[k], y[k])
    inc = an.analyze()
    assert an.rebuilds == rebuilds + 1         # forced by the drift of the means, not by the schedule
    assert an.last_fallbacks == []
    assert_reports_match(inc, _batch_same_signals(an, FAST))
    assert_reports_match(inc, _batch_of_window(case.model, r[:3000], u[:3000], y[:3000], 1200, FAST))


def test_collinear_inputs_fall_back_to_qr_and_still_equal_batch():
    """Case 3.3 without dither drives inputs together: too ill-conditioned for the normal equations."""
    case, log = _case_log("3.3", 2200, seed=5, excitation=ExcitationOptions())
    an = SlidingWindowAnalyzer(case.model, FAST, 2000)
    an.push_many(log.r, log.u, log.y)
    inc = an.analyze()
    assert "input regression" in an.last_fallbacks      # refitted by QR
    assert_reports_match(inc, _batch_same_signals(an, FAST))
    assert inc.ambiguous_elements


def test_a_constant_setpoint_and_the_default_options():
    case, log = _case_log("3.2", 2000, seed=6)
    r = log.r.copy()
    r[:, 2] = 0.5                             # y3's setpoint never moves
    an = SlidingWindowAnalyzer(case.model, AnalysisOptions(), 1500)
    an.push_many(r, log.u, log.y)
    inc = an.analyze()
    assert any("never move" in w for w in inc.warnings)
    assert_reports_match(inc, _batch_of_window(case.model, r, log.u, log.y, 1500, AnalysisOptions()))


# ------------------------------------------------------------------------------------ memory
def test_window_memory_is_linear_in_the_window_and_the_channels():
    case = paper_case("3.2")
    small = SlidingWindowAnalyzer(case.model, FAST, 2000).memory_bytes()
    large = SlidingWindowAnalyzer(case.model, FAST, 8000).memory_bytes()
    assert large["gram"] == small["gram"]                          # statistics do not grow with W
    assert large["buffer"] == pytest.approx(4 * small["buffer"], rel=1e-12)
    channels = 3 * case.model.n_outputs + case.model.n_inputs
    assert large["buffer"] == (8000 + 8000 // 4) * channels * 8    # window + slack rows of float64


# ------------------------------------------------------------------------------------ errors
def test_bad_configuration_is_refused():
    model = paper_case("3.2").model
    need = regression_layout(model, FAST).min_samples
    with pytest.raises(ConfigurationError, match=rf"window: expected an integer >= {need} samples"):
        SlidingWindowAnalyzer(model, FAST, need - 1)
    with pytest.raises(ConfigurationError, match="update_block"):
        SlidingWindowAnalyzer(model, FAST, 2000, update_block=0)
    with pytest.raises(ConfigurationError, match="refresh_interval"):
        SlidingWindowAnalyzer(model, FAST, 2000, refresh_interval=-5)
    with pytest.raises(ConfigurationError, match="max_condition"):
        SlidingWindowAnalyzer(model, FAST, 2000, max_condition=0.5)


def test_bad_samples_are_refused_and_too_few_samples_is_a_clear_error():
    model = paper_case("3.2").model
    an = SlidingWindowAnalyzer(model, FAST, 2000)
    with pytest.raises(DataFileError, match=r"input: expected shape \(3,\), got \(2,\)"):
        an.push([0, 0, 0], [0, 0], [0, 0, 0])
    with pytest.raises(DataFileError, match="output: values contain NaN"):
        an.push([0, 0, 0], [0, 0, 0], [0, np.nan, 0])
    with pytest.raises(DataFileError, match=r"setpoint: expected shape \(5, 3\)"):
        an.push_many(np.zeros((5, 2)), np.zeros((5, 3)), np.zeros((5, 3)))
    assert an.total_samples == 0              # nothing half-pushed
    an.push_many(np.zeros((10, 3)), np.zeros((10, 3)), np.zeros((10, 3)))
    assert not an.ready
    with pytest.raises(DataFileError, match=r"10 samples; the tests need at least \d+ samples"):
        an.analyze()
