"""The fast paths of the batch analysis equal the reference paths they replace (issue 8).

``analyze(model, data, options)`` now simulates the model element by element
(:func:`mpm_monitor.core.discretize.simulate_elements`) and solves the tests from Gram matrices built at
once from the window (:func:`mpm_monitor.core.regressions.window_regressions`, with their shift structure:
:func:`~mpm_monitor.core.lagged_gram.lagged_cross_products`), refitting by QR any regression whose
conditioning is poor.  The references are the previous paths: the dense simulation of
:func:`~mpm_monitor.core.discretize.state_space` (``scipy.signal.dlsim``) and
:class:`~mpm_monitor.core.regressions.QrRegressions`.

Tolerances: simulations 1e-12 of the largest output; cross products 1e-13 of the largest entry;
the analysis as in test_incremental.py -- decisions (flagged rows, located / ambiguous elements,
delays, collinear groups, warnings) identical, p-values to 1e-8 on their logarithm, F statistics,
RSI, fits and coefficients to 1e-8 relative (coefficients relative to the largest of their vector).
No timings here: bench/perf.py measures them.
"""

import dataclasses

import numpy as np
import pytest
import scipy.linalg as sla
from scipy import signal as sps

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.arx import SharedBlockRegression, lag_matrix
from mpm_monitor.core.discretize import simulate_elements, simulate_state_space, state_space
from mpm_monitor.core.gram_fits import GramBlockRegression, GramFit, IllConditioned
from mpm_monitor.core.input_design import InputDesign
from mpm_monitor.core.lagged_gram import LaggedGram, SampleBuffer, lagged_cross_products
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.regressions import QrRegressions, RegressionLayout, regression_layout, window_regressions
from mpm_monitor.core.signals import LoopSignals, compute_signals, initial_transient
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import ExcitationOptions, run_closed_loop
from mpm_monitor.sim.excitation import PrbsOptions

FAST = AnalysisOptions(repair=False)


# ------------------------------------------------------------------------------------ references
def dense_signals(model, r, u, y, initial_state="estimate"):
    """compute_signals as it was: the dense state-space simulation, then the same transient estimate."""
    yhat = simulate_state_space(state_space(model), u)
    transient = np.zeros_like(yhat)
    if initial_state == "estimate" and u.shape[0] > 1:
        transient = initial_transient(model, y - yhat)
        yhat = yhat + transient
    d = y - yhat
    return LoopSignals(yhat=yhat, d=d, eps=r - d, transient=transient)


def qr_analyze(model, data, options, signals=None):
    """The reference analysis: dense signals (unless given) and every regression by QR."""
    sig = signals if signals is not None else dense_signals(model, data.r, data.u, data.y, options.initial_state)
    regs = QrRegressions(data.r, data.u, sig.eps - data.r, sig.d, regression_layout(model, options),
                         options.na, options.nb)
    return analyze(model, data, options, signals=sig, regressions=regs)


from report_checks import _close, _close_vec, assert_reports_match  # noqa: E402


# ------------------------------------------------------------------------------------ simulation
def _random_model(ny, nu, rng, ts=1.0):
    """Every kind of element: lags with delays, tau = 0 with and without delay, gain 0."""
    gain = rng.uniform(0.3, 4.0, (ny, nu)) * rng.choice([-1.0, 1.0], (ny, nu))
    gain[rng.random((ny, nu)) < 0.2] = 0.0
    tau = rng.uniform(0.2, 60.0, (ny, nu))
    tau[rng.random((ny, nu)) < 0.25] = 0.0
    delay = rng.integers(0, 9, (ny, nu)) * ts
    return PlantModel(ts, [f"u{j + 1}" for j in range(nu)], [f"y{i + 1}" for i in range(ny)],
                      gain=gain, time_constant=tau, delay=delay)


@pytest.mark.parametrize("seed,ny,nu,ts", [(0, 1, 1, 1.0), (1, 3, 2, 1.0), (2, 5, 7, 0.5), (3, 8, 8, 2.0),
                                           (4, 20, 20, 1.0)])
def test_element_simulation_equals_the_dense_state_space(seed, ny, nu, ts):
    rng = np.random.default_rng(seed)
    model = _random_model(ny, nu, rng, ts)
    model = model.with_element(0, 0, gain=1.5, time_constant=0.0, delay=0.0)     # a feed-through
    model = model.with_element(ny - 1, nu - 1, gain=-2.0, time_constant=0.0, delay=3 * ts)
    u = rng.standard_normal((700, nu)).cumsum(axis=0)
    ref = simulate_state_space(state_space(model), u)
    new = simulate_elements(model, u)
    np.testing.assert_allclose(new, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    for n in (0, 1, 2, 5):               # shorter than the delays
        np.testing.assert_allclose(simulate_elements(model, u[:n]), simulate_state_space(state_space(model), u[:n]),
                                   rtol=0, atol=1e-12 * max(np.abs(ref).max(), 1.0))


def test_element_simulation_of_a_model_without_lag_states():
    model = PlantModel(1.0, ["u1", "u2"], ["y1"], gain=[[2.0, 0.0]], time_constant=[[0.0, 5.0]], delay=[[0.0, 1.0]])
    u = np.random.default_rng(5).standard_normal((50, 2))
    np.testing.assert_array_equal(simulate_elements(model, u), 2.0 * u[:, :1])


def test_compute_signals_equals_the_dense_reference_with_and_without_a_transient():
    """A log that starts after a long hold of the inputs at 5: the model's state is far from rest."""
    case = paper_case("3.2")
    rng = np.random.default_rng(9)
    u = np.vstack([np.full((600, 3), 5.0), sps.lfilter([1.0], [1.0, -0.8], rng.standard_normal((2000, 3)), axis=0)])
    y = simulate_elements(case.plant, u) + 0.05 * rng.standard_normal((2600, 3))
    r = np.zeros_like(y)
    for a, state in ((600, "estimate"), (0, "estimate"), (600, "zero")):
        new, ref = (f(case.model, r[a:], u[a:], y[a:], state) for f in (compute_signals, dense_signals))
        for name in ("yhat", "d", "eps", "transient"):
            scale = np.abs(ref.yhat).max()
            np.testing.assert_allclose(getattr(new, name), getattr(ref, name), rtol=0, atol=1e-12 * scale,
                                       err_msg=f"{name} from {a}, {state}")
        if a:      # the transient is found and subtracted, or not looked for
            assert (np.abs(new.transient).max() > 1.0) == (state == "estimate")


# ------------------------------------------------------------------------------------ cross products
def _check_lagged_cross_products(rng, channel, lag, n, spare_channels):
    """Random signals (``spare_channels`` unused ones beside), their lagged Gram and sums against the
    direct product of the lag matrix; returns the signals and the largest lag."""
    max_lag = int(lag.max())
    x = rng.standard_normal((n + max_lag, channel.max() + 1 + spare_channels)) + 3.0
    phi = x[max_lag + np.arange(n)[:, None] - lag[None, :], channel[None, :]]
    gram, sums = lagged_cross_products(x, channel, lag, max_lag)
    ref = phi.T @ phi
    np.testing.assert_allclose(gram, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
    np.testing.assert_array_equal(gram, gram.T)
    np.testing.assert_allclose(sums, phi.sum(axis=0), rtol=0, atol=1e-13 * np.abs(phi).sum(axis=0).max())
    return x, max_lag


@pytest.mark.parametrize("groups,n", [
    ([(3, range(0, 5)), (2, range(0, 3))], 200),
    ([(2, range(1, 6)), (3, range(0, 3))], 7),                    # fewer rows than the largest lag
    ([(2, [0]), (1, [2, 5])], 1),                                 # lags that are not consecutive
    ([(2, range(1, 9))], 3),                                      # no lag 0
    ([(4, range(0, 12)), (4, range(0, 5))], 3000),
])
def test_lagged_cross_products_equal_the_direct_product(groups, n):
    rng = np.random.default_rng(n)
    channel, lag = [], []
    for g, (n_ch, lags) in enumerate(groups):
        for c in range(n_ch):
            channel += [len(set(channel))] * len(lags)
            lag += list(lags)
    x, max_lag = _check_lagged_cross_products(rng, np.array(channel), np.array(lag), n, spare_channels=0)
    empty, empty_sums = lagged_cross_products(x[:max_lag], channel, lag, max_lag)
    assert not empty.any() and not empty_sums.any()


@pytest.mark.parametrize("channel,lag,n", [
    ([0] * 7, range(0, 7), 40),                                   # a single channel
    ([0, 1, 2], [0, 0, 0], 30),                                   # max_lag 0
    ([2, 2, 0, 0, 0, 1, 2], [3, 1, 0, 4, 2, 1, 0], 50),          # lags out of order, a channel in two runs
    ([0, 0, 3, 3, 1, 0], [1, 1, 5, 2, 0, 3], 2),                  # a column twice, channels out of order
    ([4, 4, 1, 1, 2, 2], [6, 7, 0, 1, 0, 1], 60),                 # unused channels
    ([0, 0, 1, 1, 2, 2, 3, 3, 3], [2, 3, 2, 3, 0, 1, 0, 1, 2], 25),  # runs of channels sharing lags
])
def test_lagged_cross_products_of_any_column_layout(channel, lag, n):
    # The Gram matrix is filled block by block over runs of channels sharing a lag sequence, then
    # mirrored below the lag diagonal: any order of the columns gives the direct product.
    _check_lagged_cross_products(np.random.default_rng(n), np.array(channel), np.array(list(lag)), n,
                                 spare_channels=1)


def test_lagged_gram_symmetric_after_rebuild_and_update():
    # A rebuilt matrix is its own full matrix; an update (of its lower triangle) drops that.
    rng = np.random.default_rng(5)
    buf = SampleBuffer(3, 400, 0)
    buf.append(rng.standard_normal((400, 3)))
    gram = LaggedGram([("x", 2, range(0, 4)), ("y", 1, range(1, 3))],
                      lambda block: {"x": block[:, :2], "y": block[:, 2:]})

    def direct(a, b):
        phi = gram.rows(buf, a, b)
        return phi.T @ phi

    gram.rebuild(buf, 10, 300, np.zeros(3))
    np.testing.assert_allclose(gram.symmetric(), direct(10, 300), rtol=0, atol=1e-12 * np.abs(direct(10, 300)).max())
    for add, remove in (((300, 350), (10, 60)), ((350, 380), (60, 65))):       # as many rows as leave, or not
        gram.update(buf, add, remove)
        ref = direct(remove[1], add[1])
        np.testing.assert_allclose(gram.symmetric(), ref, rtol=0, atol=1e-12 * np.abs(ref).max())
    # What symmetric() handed out after a rebuild (the matrix itself) stays as it was through an update
    # or a clear of the Gram (both write in place).
    for change in (lambda: gram.update(buf, (380, 390), (65, 70)), gram.clear):
        gram.rebuild(buf, 100, 300, np.zeros(3))
        held = gram.symmetric()
        kept = held.copy()
        change()
        np.testing.assert_array_equal(held, kept)


def test_row_fits_solved_together_equal_each_alone_and_qr():
    # row_fits solves every row's products with the setpoint block at once (two triangular solves);
    # a row fitted alone has the same numbers, GramFit's own products by R1^-1 the same to rounding,
    # and the QR path the same fit.
    rng = np.random.default_rng(7)
    n, ny, na = 1500, 4, 2
    r = np.repeat(rng.standard_normal((n // 10, ny)), 10, axis=0)
    z = sps.lfilter([0.0, 0.3], [1.0, -0.6], r, axis=0) @ rng.standard_normal((ny, ny)) \
        + 0.1 * rng.standard_normal((n, ny))
    u, d = rng.standard_normal((n, 2)), rng.standard_normal((n, ny))
    layout = RegressionLayout(max_delay=3, n_lag_r=6, n_lag_u=5, start=6, min_samples=0)
    together = window_regressions(r, u, z, d, layout, na, 2)
    reg = together.row_regression(list(range(ny)))
    fits = together.row_fits(reg, range(ny))
    alone = window_regressions(r, u, z, d, layout, na, 2)
    reg_alone = alone.row_regression(list(range(ny)))
    qr = QrRegressions(r, u, z, d, layout, na, 2)
    reg_qr = qr.row_regression(list(range(ny)))
    assert not together.fallbacks and not alone.fallbacks
    for i, fit in enumerate(fits):
        single = alone.row_fit(reg_alone, i)
        own = GramFit(reg_alone, *alone._fit_arguments("row", reg_alone, i), alone.max_condition)
        ref = qr.row_fit(reg_qr, i)
        assert isinstance(fit, GramFit) and isinstance(single, GramFit)
        for other in (single, own):
            np.testing.assert_allclose(fit.theta, other.theta, rtol=1e-12, atol=1e-13 * np.abs(other.theta).max())
            np.testing.assert_allclose(fit.common_variances(), other.common_variances(), rtol=1e-12)
            assert fit.rss == pytest.approx(other.rss, rel=1e-12)
            assert fit.test_all_common_zero().statistic == pytest.approx(other.test_all_common_zero().statistic,
                                                                          rel=1e-12)
        np.testing.assert_allclose(fit.theta, ref.theta, rtol=1e-7, atol=1e-9)
        assert fit.rss == pytest.approx(ref.rss, rel=1e-8)
        assert together.row_fit(reg, i) is fit


def test_the_short_arx_from_the_gram_equals_the_qr_one_without_its_condition_number():
    # The paper's table reads a short ARX's a, b and fit; from the Gram its condition number (an SVD of the
    # factor per row) is not computed; the QR path (fit_arx) still gives it.
    rng = np.random.default_rng(3)
    n, ny, nu, na, nb = 2000, 2, 3, 2, 3
    r = np.repeat(rng.standard_normal((n // 20, ny)), 20, axis=0)
    u = sps.lfilter([1.0], [1.0, -0.7], rng.standard_normal((n, nu)), axis=0)
    d = u[:, :ny] * 0.4 + 0.1 * rng.standard_normal((n, ny))
    layout = RegressionLayout(max_delay=4, n_lag_r=6, n_lag_u=7, start=8, min_samples=0)
    gram, qr = window_regressions(r, u, -d, d, layout, na, nb), QrRegressions(r, u, -d, d, layout, na, nb)
    nk = np.array([1, 2, 3])
    fast, ref = gram.short_arx(1, nk), qr.short_arx(1, nk)
    assert not gram.fallbacks
    np.testing.assert_allclose(fast.theta, ref.theta, rtol=1e-7, atol=1e-9)
    assert fast.fit_percent == pytest.approx(ref.fit_percent, rel=1e-8)
    assert np.isnan(fast.condition_number) and np.isfinite(ref.condition_number) and ref.condition_number >= 1


# ------------------------------------------------------------------------------------ batched fits
def _fits():
    rng = np.random.default_rng(1)
    x = sps.lfilter([1.0], [1.0, -0.5], rng.standard_normal((3000, 4)), axis=0)
    x[:, 3] = 0.7 * x[:, 2] + 1e-7 * rng.standard_normal(3000)        # one near-collinear block
    y = x[:, 0] * 0.5 + np.roll(x[:, 2], 2) * 0.3 + 0.1 * rng.standard_normal(3000)
    start = 6
    common = lag_matrix(x, range(1, 6), start)
    own = -lag_matrix(y, [1, 2], start)
    target = y[start:]
    qr = SharedBlockRegression(common, [5] * 4).fit(target, own)
    good = common[:, :15]
    reg = GramBlockRegression(good.T @ good, [5] * 3)
    gram = GramFit(reg, good.T @ own, own.T @ own, good.T @ target, own.T @ target, float(target @ target),
                   float(target.sum()), target.shape[0])
    return qr, gram


@pytest.mark.parametrize("which", ["qr", "gram"])
def test_the_batched_block_tests_equal_one_test_per_block(which):
    fit = dict(zip(("qr", "gram"), _fits()))[which]
    n_blocks = len(fit.reg.block_sizes)
    windows = [None, 3, 9, 0][:n_blocks]
    for b, (t, std) in enumerate(zip(fit.test_each_block_zero(windows), fit.block_stds())):
        one = fit.test_blocks_zero([b], n_first=windows[b])
        assert (t.df_num, t.df_den) == (one.df_num, one.df_den)
        _close(t.statistic, one.statistic, f"F {b}", tol=1e-12)
        _close(t.p_value, one.p_value, f"p {b}", tol=1e-12)
        _close_vec(std, fit.block_std(b), f"std {b}", tol=1e-12)


def test_gram_fit_covariance_blocks_equal_the_assembled_inverse():
    _, fit = _fits()
    full = fit.rinv @ fit.rinv.T
    idx = np.array([[0, 1, 2], [5, 9, 14], [3, 4, 16]])         # the last row reaches an own column
    for row, block in zip(idx, fit.covariance_blocks(idx)):
        _close_vec(block, full[np.ix_(row, row)], f"block {row}", tol=1e-12)
    _close_vec(fit.common_variances(), np.diag(full)[:fit.n_common], "variances", tol=1e-12)


def _vif_block_by_block(reg, n_lag):
    """The variance-inflation factors as InputDesign computed them, one lag block at a time."""
    R = reg.R
    p = R.shape[1]
    rinv = np.linalg.pinv(R) if not reg.full_rank else sla.solve_triangular(R, np.eye(p))
    inv = rinv @ rinv.T
    out = []
    for b in range(p // n_lag):
        sl = slice(b * n_lag, (b + 1) * n_lag)
        ev = np.linalg.eigvals((R[:, sl].T @ R[:, sl]) @ inv[sl, sl]).real
        vif = float(ev.max()) if np.all(np.isfinite(ev)) else float("inf")
        if not reg.full_rank:
            sub = R[:, [c for c in range(p) if c < sl.start or c >= sl.stop]]
            if np.linalg.matrix_rank(np.hstack([sub, R[:, sl]])) < np.linalg.matrix_rank(sub) + n_lag:
                vif = float("inf")
        out.append(vif)
    return out


@pytest.mark.parametrize("dither", [True, False])
def test_input_design_equals_the_block_by_block_variance_inflation(dither):
    """With dither (case 3.3) and without (two inputs move together: a rank-deficient lag matrix)."""
    case, data = _run("3.3", 5, excitation=None if dither else ExcitationOptions())
    lay = regression_layout(case.model, FAST)
    design = InputDesign(case.model, data.u, lay.n_lag_u, lay.start, FAST.collinearity_threshold)
    ref = _vif_block_by_block(design.regression, lay.n_lag_u)
    assert design.regression.full_rank == dither
    for j, v in zip(design.testable, ref):
        _close(design.vif[case.model.inputs[j]], v, f"VIF {case.model.inputs[j]}", tol=1e-10)
    assert (max(ref) < 100) == dither


# ------------------------------------------------------------------------------------ analysis
def _run(name, seed, samples=3000, excitation=None):
    case = paper_case(name)
    log = run_closed_loop(case.plant, case.model, samples, seed=seed, mpc=case.mpc,
                          excitation=excitation or case.excitation, disturbance=case.disturbance)
    return case, log.as_logged_data()


def _non_square(ny, nu, dither):
    """test_analysis.test_non_square_plants."""
    rng = np.random.default_rng(ny * 10 + nu)
    plant = PlantModel(1.0, [f"u{j + 1}" for j in range(nu)], [f"y{i + 1}" for i in range(ny)],
                       gain=rng.uniform(0.5, 3, (ny, nu)) * rng.choice([-1, 1], (ny, nu)),
                       time_constant=rng.uniform(10, 60, (ny, nu)), delay=rng.integers(1, 6, (ny, nu)).astype(float))
    i2 = min(4, ny - 1)
    model = plant.with_element(1, 0, gain=plant.gain[1, 0] * 1.5).with_element(
        i2, 2, time_constant=plant.time_constant[i2, 2] * 2)
    exc = ExcitationOptions(dither=None if dither is None else PrbsOptions(amplitude=dither))
    return model, run_closed_loop(plant, model, 4000, seed=1, excitation=exc).as_logged_data()


def _large(n, samples, seed=0):
    """A random n x n plant as in bench/perf.py, the model's (y1, u2) gain 30 % off."""
    rng = np.random.default_rng(seed + n)
    shape = (n, n)
    plant = PlantModel(1.0, [f"u{j + 1}" for j in range(n)], [f"y{i + 1}" for i in range(n)],
                       gain=np.exp(rng.uniform(np.log(0.5), np.log(5.0), shape)) * rng.choice([-1.0, 1.0], shape),
                       time_constant=rng.uniform(10.0, 80.0, shape), delay=rng.integers(0, 9, shape).astype(float))
    model = plant.with_element(0, 1, gain=plant.gain[0, 1] * 1.3)
    return model, run_closed_loop(plant, model, samples, seed=seed + 100 + n).as_logged_data()


def _case(key):
    if key.startswith("paper"):
        _, name, seed = key.split("-")
        case, data = _run(name, int(seed))
        return case.model, data
    if key == "mid-operation":
        case = paper_case("3.2")
        log = run_closed_loop(case.plant, case.model, 3600, seed=9, mpc=case.mpc, excitation=case.excitation,
                              disturbance=case.disturbance)
        return case.model, log.as_logged_data().slice(600, 3600)
    if key == "constant-setpoint":
        case, data = _run("3.2", 6, 2000)
        r = data.r.copy()
        r[:, 2] = 0.5
        return case.model, dataclasses.replace(data, r=r)
    if key == "7x3":
        return _non_square(7, 3, None)
    if key == "3x7":
        return _non_square(3, 7, 0.3)
    if key == "20x20":
        return _large(20, 3000)
    raise KeyError(key)


CASES = ["paper-3.1-11", "paper-3.2-11", "paper-3.3-11", "paper-3.1-12", "paper-3.2-3", "mid-operation",
         "constant-setpoint", "7x3", "3x7", "20x20"]


@pytest.mark.parametrize("key", CASES)
def test_analyze_equals_the_dense_and_qr_reference(key):
    model, data = _case(key)
    new = analyze(model, data, FAST)
    assert_reports_match(new, qr_analyze(model, data, FAST))
    regs = window_regressions(data.r, data.u, new.signals.eps - data.r, new.signals.d,
                              regression_layout(model, FAST), FAST.na, FAST.nb)
    analyze(model, data, FAST, signals=new.signals, regressions=regs)
    assert regs.fallbacks == []              # well-conditioned closed-loop data: all from the Gram matrices


@pytest.mark.parametrize("options", [
    AnalysisOptions(repair=False, test_all_rows=False, element_window="full"),
    AnalysisOptions(repair=False, initial_state="zero", na=2, nb=3, max_delay=6, band=(0.01, 1.0), n_freq=64),
    AnalysisOptions(repair=False, method="xcorr"),
    AnalysisOptions(),                                                   # with the repair
], ids=["paper-order", "other-orders", "xcorr", "repair"])
def test_analyze_equals_the_reference_with_other_options(options):
    case, data = _run("3.2", 12)
    new, ref = analyze(case.model, data, options), qr_analyze(case.model, data, options)
    assert_reports_match(new, ref)
    if options.repair:
        assert [c["output"] + c["input"] for c in new.repair["changes"]] == \
            [c["output"] + c["input"] for c in ref.repair["changes"]]


def test_collinear_inputs_fall_back_to_qr():
    """Case 3.3 without dither: the input lags are too ill-conditioned for the normal equations.

    On such data the QR path itself amplifies rounding differences of the signals beyond 1e-8, so
    both paths get the same signals (the comparison is of the regressions, not of the simulation).
    """
    case, data = _run("3.3", 5, excitation=ExcitationOptions())
    sig = compute_signals(case.model, data.r, data.u, data.y)
    regs = window_regressions(data.r, data.u, sig.eps - data.r, sig.d, regression_layout(case.model, FAST),
                              FAST.na, FAST.nb)
    new = analyze(case.model, data, FAST, signals=sig, regressions=regs)
    assert "input regression" in regs.fallbacks
    assert new.ambiguous_elements
    assert_reports_match(new, qr_analyze(case.model, data, FAST, signals=sig))
    assert_reports_match(analyze(case.model, data, FAST, signals=sig), new)


def test_noise_free_rows_fall_back_to_qr():
    """Without noise (1e-9) a mismatched row's prediction error is explained almost exactly by the input
    lags: ``y'y - |Q'y|^2`` would lose every digit of the residual, so that fit is refitted by QR."""
    case = paper_case("3.2")
    rng = np.random.default_rng(3)
    n = 2500
    u = sps.lfilter([1.0], [1.0, -0.6], rng.standard_normal((n, 3)), axis=0)
    y = simulate_elements(case.plant, u) + 1e-9 * rng.standard_normal((n, 3))   # open loop, no disturbance
    r = np.where(rng.random((n, 3)) < 0.5, 1.0, -1.0)
    data = LoggedData(t=np.arange(n) * 1.0, r=r, u=u, y=y, inputs=case.model.inputs, outputs=case.model.outputs,
                      sample_time=1.0)
    opts = AnalysisOptions(repair=False, initial_state="zero")
    sig = compute_signals(case.model, r, u, y, "zero")
    regs = window_regressions(r, u, sig.eps - r, sig.d, regression_layout(case.model, opts), opts.na, opts.nb)
    new = analyze(case.model, data, opts, signals=sig, regressions=regs)
    assert any(f.startswith("input fit of output") for f in regs.fallbacks)
    assert_reports_match(new, qr_analyze(case.model, data, opts, signals=sig))
    assert set(new.located_elements) == set(case.mismatched_elements)


def test_a_fit_checks_its_condition_from_its_shared_blocks_norms(monkeypatch):
    # 1,100 common columns: the Frobenius bound (about 1,300) exceeds 1e3 although the condition number
    # is about 3, so each fit needs the finer check.  The shared block's 2-norms are estimated once for
    # all its fits; each fit adds its own columns' exact Frobenius norms, which bounds its condition
    # number from above (||[A B]||_2^2 <= ||A||_2^2 + ||B||_F^2).
    import mpm_monitor.core.gram_fits as gram_fits

    calls = []
    estimate = gram_fits._norm2_estimate
    monkeypatch.setattr(gram_fits, "_norm2_estimate", lambda a, *k: calls.append(1) or estimate(a, *k))
    rng = np.random.default_rng(3)
    n, p = 4000, 1100
    X = rng.standard_normal((n, p))
    reg = GramBlockRegression(X.T @ X, [p])
    assert reg.frobenius_R * reg.frobenius_rinv > 1e3
    fits = []
    for k in range(3):
        own = rng.standard_normal((n, 2))
        y = X[:, k] + own @ [0.5, -0.2] + rng.standard_normal(n)
        fits.append(GramFit(reg, X.T @ own, own.T @ own, X.T @ y, own.T @ y, float(y @ y), float(y.sum()), n))
    assert len(calls) == 2                       # ||R1||_2 and ||R1^-1||_2, once for the three fits
    for fit in fits:
        R = np.block([[reg.R, fit._qo], [np.zeros((2, p)), fit._R2]])
        kappa = np.linalg.cond(R)
        assert 0.98 * kappa <= fit.condition_bound <= 2.0 * kappa
    # An own column nearly collinear with the common ones: the bound exceeds the limit and the whole
    # factor's estimate decides (and rejects).
    own = np.column_stack([X[:, 0] + 1e-6 * rng.standard_normal(n), rng.standard_normal(n)])
    y = rng.standard_normal(n)
    with pytest.raises(IllConditioned):
        GramFit(reg, X.T @ own, own.T @ own, X.T @ y, own.T @ y, float(y @ y), float(y.sum()), n)
    assert len(calls) == 4
