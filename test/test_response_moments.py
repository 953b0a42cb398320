"""The element responses' moments shared by the whole-response test and the detectability: the same
tests as the direct products, with gaps, integrating, second-order, lead and absent elements."""

import numpy as np
import pytest
from scipy.signal import lfilter

from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.arx import SharedBlockRegression, lag_matrix, segment_lag_matrix, segment_rows
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.response_moments import ResponseMoments
from mpm_monitor.core.response_test import element_responses, row_response_tests
from mpm_monitor.core.segments import GapSegments, through

N_LAG, NA = 7, 2
#: Segments of the 1,800 stacked samples of _window after gaps of 1, 2 and 40 samples: with max_gap 10 the
#: responses run through the first two gaps (one run of three segments) and start from rest after the third.
RUNS = GapSegments([(0, 600), (600, 640), (640, 1300), (1300, 1800)],
                   np.concatenate([np.arange(600), np.arange(601, 641), np.arange(643, 1303), np.arange(1343, 1843)]), 10)


def _window(seed, n=1800):
    """One output, four inputs: a second-order lag with a lead, an integrator, an element the model
    lacks, and a first-order lag; AR(2) noise and a gain error of the first element."""
    rng = np.random.default_rng(seed)
    model = PlantModel(sample_time=1.0, inputs=("u1", "u2", "u3", "u4"), outputs=("y1",),
                       gain=np.array([[1.5, 0.02, 0.0, -0.8]]), time_constant=np.array([[30.0, 5.0, 0.0, 6.0]]),
                       time_constant2=np.array([[10.0, 0.0, 0.0, 0.0]]), lead=np.array([[4.0, 0.0, 0.0, 0.0]]),
                       delay=np.array([[2.0, 1.0, 0.0, 3.0]]), integrating=np.array([[False, True, False, False]]))
    u = np.column_stack([np.repeat(rng.choice([-1.0, 1.0], n // 5 + 1), 5)[:n], rng.standard_normal((n, 3))])
    u[:, 1] = np.cumsum(rng.standard_normal(n)) * 0.05 + rng.standard_normal(n)
    noise = lfilter([1.0], [1.0, -0.7, 0.1], 0.05 * rng.standard_normal(n))
    d = 0.05 * model.discrete_element(0, 0).respond(u[:, 0] - u[:, 0].mean()) + noise + 3.0
    return model, u, d[:, None]


def _direct_and_shared(model, u, d, testable, segments):
    """Row 0's whole-response tests by the direct products and from the moments, and the moments."""
    start = max(N_LAG, NA)
    u_c = u - u.mean(axis=0)
    d_c = d - d.mean(axis=0)
    X = np.hstack([segment_lag_matrix(u_c[:, k], range(1, N_LAG + 1), start, segments) for k in testable])
    own = -segment_lag_matrix(d_c[:, 0], range(1, NA + 1), start, segments)
    fit = SharedBlockRegression(X, [N_LAG] * len(testable)).fit(segment_rows(d_c[:, 0], start, segments), own)
    sizes = [N_LAG] * len(testable)
    direct = row_response_tests(model, 0, fit, testable, X, sizes, u_c, d_c, start, NA, segments)
    moments = ResponseMoments(model, u, d, testable, N_LAG, start, NA, segments)
    shared = row_response_tests(model, 0, fit, testable, None, sizes, u_c, d_c, start, NA, segments, moments=moments)
    return direct, shared, moments


@pytest.mark.parametrize("segments, testable", [
    (None, [0, 1, 2, 3]),
    ([(0, 600), (600, 640), (640, 1300), (1300, 1800)], [0, 1, 2, 3]),   # gaps
    (RUNS, [0, 1, 2, 3]),                                                # the responses through short gaps
    (None, [0, 1, 3]),                                                   # a column that never moves
])
def test_the_response_tests_from_the_moments_equal_the_direct_products(segments, testable):
    model, u, d = _window(4)
    direct, shared, _ = _direct_and_shared(model, u, d, testable, segments)
    assert set(direct) == set(shared) == {j for j in testable if model.present[0, j]}
    assert direct[1].df_num == 2                    # the integrator: with its time-constant sensitivity
    for j, t in direct.items():
        s = shared[j]
        assert (s.df_num, s.df_den) == (t.df_num, t.df_den)
        assert s.statistic == pytest.approx(t.statistic, rel=1e-9)
        assert s.p_value == pytest.approx(t.p_value, rel=1e-7, abs=1e-300)
        assert s.information == pytest.approx(t.information, rel=1e-9)
    assert direct[0].p_value < 1e-3                 # the gain error is there to be found


@pytest.mark.parametrize("segments", [RUNS, [(0, 600), (600, 640), (640, 1300), (1300, 1800)]])
def test_a_self_regulating_rows_tests_from_the_moments_equal_the_direct_products(segments):
    """A row without an integrating element keeps one level through the short gaps of a GapSegments (its regressors
    centred over each run's rows, segments.level_groups); with plain segments, one per segment: the moments give
    the direct products' tests either way."""
    model, u, d = _window(4)
    model = model.with_element(0, 1, integrating=False, gain=0.4, time_constant=12.0)
    direct, shared, moments = _direct_and_shared(model, u, d, [0, 1, 2, 3], segments)
    assert list(moments.levels(0)) == (RUN_OF_RUNS if segments is RUNS else [0, 1, 2, 3])
    assert set(direct) == set(shared) == {0, 1, 3}
    for j, t in direct.items():
        s = shared[j]
        assert (s.df_num, s.df_den) == (t.df_num, t.df_den) == (1, t.df_den)
        assert s.statistic == pytest.approx(t.statistic, rel=1e-9)
        assert s.p_value == pytest.approx(t.p_value, rel=1e-7, abs=1e-300)


def test_the_row_moments_equal_the_products_of_the_lag_matrices():
    """Z' [x, X], u(t)' [x, X], O' [x, X], [x, X]' [x, X] (the last two along lag diagonals), the sums
    and the segment means, against the lag matrices of each segment's centred response."""
    model, u, d = _window(9)
    start, segs = max(N_LAG, NA), [(0, 900), (900, 1800)]
    moments = ResponseMoments(model, u, d, [0, 1, 2, 3], N_LAG, start, NA, segs)
    rm = moments.row(0, keep_samples=True)
    u_c = u - u.mean(axis=0)
    Z = np.vstack([lag_matrix(u_c[a:b], range(1, N_LAG + 1), start) for a, b in segs])
    U0 = np.vstack([u_c[a + start:b] for a, b in segs])
    O = np.vstack([lag_matrix(d[a:b, 0] - d[a:b, 0].mean(), range(1, NA + 1), start) for a, b in segs])
    np.testing.assert_allclose(moments.Z, Z)
    np.testing.assert_allclose(rm.zo, Z.T @ O, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(rm.oo, O.T @ O, rtol=1e-12)
    assert [f[0] for f in rm.found] == [0, 1, 2, 3]          # (0, 2) stands for the row's typical element
    for b, (j, element, _) in enumerate(rm.found):
        parts, mus = [], []
        for a0, b0 in segs:
            x = element.respond(u_c[a0:b0, j])
            mus.append(x.mean())
            parts.append(lag_matrix(x - x.mean(), range(0, NA + 1), start))
        XW = np.vstack(parts)
        np.testing.assert_allclose(rm.mu[:, b], mus, rtol=1e-12)
        np.testing.assert_allclose(rm.R[:, b], np.concatenate([element.respond(u_c[a0:b0, j]) - mu
                                                               for (a0, b0), mu in zip(segs, mus)]))
        np.testing.assert_allclose(rm.xsum[b], XW.sum(axis=0), atol=1e-9 * np.abs(XW).sum())
        for got, want in ((rm.zx[..., b].reshape(-1, NA + 1), Z.T @ XW), (rm.ww[b], XW.T @ XW),
                          (rm.uw[:, b * (NA + 1):(b + 1) * (NA + 1)], U0.T @ XW),
                          (rm.ow[:, b * (NA + 1):(b + 1) * (NA + 1)], O.T @ XW)):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-10 * np.abs(want).max())
    assert np.array_equal(rm.ww[:, 1, 2], rm.ww[:, 2, 1])
    moments.release(0)
    assert moments.row(0).R is None and moments.take(0) is rm


def test_moments_of_other_columns_are_not_used():
    """The element test takes the shared moments only when they are of its own columns and segments."""
    model, u, d = _window(2)
    moments = ResponseMoments(model, u, d, [0, 1, 2, 3], N_LAG, N_LAG, NA)
    assert moments.of(u) and moments.of(u.copy())
    assert not moments.of(u + 1e-9) and not moments.of(u, [(0, 900), (900, 1800)])


def test_a_model_without_elements_has_no_moments_to_share():
    """No element anywhere: the rows have no responses; the analysis says why no value is given."""
    rng = np.random.default_rng(0)
    n = 2000
    model = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1",), gain=np.zeros((1, 2)),
                       time_constant=np.zeros((1, 2)), delay=np.zeros((1, 2)))
    moments = ResponseMoments(model, rng.standard_normal((n, 2)), rng.standard_normal((n, 1)), [0, 1], N_LAG, N_LAG,
                              NA)
    rm = moments.row(0, keep_samples=True)
    assert rm.found == [] and rm.zx.shape == (2, N_LAG, NA + 1, 0) and rm.uw.shape == (2, 0)
    data = LoggedData(t=np.arange(n, dtype=float), r=np.zeros((n, 1)), u=rng.standard_normal((n, 2)),
                      y=0.1 * rng.standard_normal((n, 1)), inputs=("u1", "u2"), outputs=("y1",), sample_time=1.0)
    rep = detect(model, data, AnalysisOptions())
    assert [e.detectable_gain_change for e in rep.elements] == [None, None]
    assert any("the model has no element" in w for w in rep.warnings)


def _by_product(monkeypatch, make):
    """The moments built with every ``Z' x`` taken by a product over the rows (no recursion, no long Gram)."""
    with monkeypatch.context() as mp:
        mp.setattr(ResponseMoments, "_recursive", lambda self, element: False)
        mp.setattr(ResponseMoments, "_long_fir", lambda self, element: False)
        return make()


@pytest.mark.parametrize("na, n_lag, segments", [
    (2, N_LAG, None),
    (2, N_LAG, [(0, 500), (500, 530), (530, 1800)]),     # gaps, one segment without a regression row
    (1, N_LAG, [(0, 900), (900, 1800)]),                 # na 1: the second-order elements by a product
    (2, N_LAG, RUNS),                                    # the responses through short gaps
    (4, 3, None),                                        # few lags: the slow delays by a product
])
def test_the_recursion_in_the_lags_equals_the_product_over_the_rows(monkeypatch, na, n_lag, segments):
    """``Z' x`` of an element from its difference equation and the input Gram (``_fill_lags``)
    against ``Z' x`` by a product over the rows, every moment of the row, whichever elements qualify."""
    model, u, d = _window(11)
    start = max(n_lag, na)

    def make():
        return ResponseMoments(model, u, d, [0, 1, 2, 3], n_lag, start, na, segments).row(0)

    got, want = make(), _by_product(monkeypatch, make)
    moments = ResponseMoments(model, u, d, [0, 1, 2, 3], n_lag, start, na, segments)
    used = [moments._recursive(element) for _, element, _ in got.found]
    assert any(used) and (not all(used) or na == 2)         # both paths where the elements differ
    for name in ("zx", "uw", "zo", "ww", "ow", "xsum", "mu"):
        w = getattr(want, name)
        np.testing.assert_allclose(getattr(got, name), w, rtol=1e-10, atol=1e-12 * np.abs(w).max(), err_msg=name)


def test_a_step_response_model_by_the_recursion_and_by_products(monkeypatch):
    """Step-response elements (a finite impulse response; in a ramp row with an integrator): the same
    moments by the recursion (taps within the lags) as by products (more taps than lags)."""
    rng = np.random.default_rng(3)
    n, N, n_lag = 1500, 30, 12
    k = np.arange(1, N + 1)
    row = np.stack([1.2 * (1 - np.exp(-np.maximum(k - 2, 0) / 3.0)), -0.5 * (1 - np.exp(-np.maximum(k - 1, 0) / 12.0)),
                    0.02 * np.maximum(k - 3, 0)])
    u = rng.standard_normal((n, 3))
    d = rng.standard_normal((n, 2))
    for taps, by_recursion in ((N, False), (8, True)):
        model = PlantModel.from_step_response(1.0, ("u1", "u2", "u3"), ("y1", "y2"),
                                              np.stack([row[:, :taps], row[:, :taps]]), ramp=(False, True))

        def make(i):
            return ResponseMoments(model, u, d, [0, 1, 2], n_lag, n_lag, 2).row(i)

        moments = ResponseMoments(model, u, d, [0, 1, 2], n_lag, n_lag, 2)
        for i in (0, 1):
            got, want = make(i), _by_product(monkeypatch, lambda: make(i))
            assert [moments._recursive(e) for _, e, _ in got.found] == [by_recursion] * 3
            for name in ("zx", "uw", "ww"):
                w = getattr(want, name)
                np.testing.assert_allclose(getattr(got, name), w, rtol=1e-10, atol=1e-12 * np.abs(w).max(),
                                           err_msg=f"{name}, {taps} taps, row {i}")


@pytest.mark.parametrize("segments", [None, [(0, 700), (700, 720), (720, 1800)]])
def test_the_input_gram_along_lag_diagonals_equals_the_product_of_the_lag_matrices(segments):
    model, u, d = _window(5)
    moments = ResponseMoments(model, u, d, [0, 1, 3], N_LAG, N_LAG, NA, segments)
    u_c = u - u.mean(axis=0)
    u_c[:, 2] = 0.0                                   # the column that never moves
    W = segment_lag_matrix(u_c, range(0, N_LAG + 1), N_LAG, segments)     # column c (L + 1) + l
    want = (W.T @ W).reshape(4, N_LAG + 1, 4, N_LAG + 1)
    np.testing.assert_allclose(moments.gram, want, rtol=1e-11, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("na", [1, 2, 4])
@pytest.mark.parametrize("segments", [None, [(0, 500), (500, 530), (530, 1100), (1100, 1800)]])
def test_the_own_lags_moments_of_every_row_equal_the_product_of_the_lag_matrices(na, segments):
    """``Z' O`` of each row, along lag diagonals from one ``Z' D`` of all outputs, against ``Z'`` times
    each row's own lags (centred over each segment), with gaps (one segment too short for a row)."""
    model, u, d = _window(11)
    rng = np.random.default_rng(3)
    d3 = np.column_stack([d[:, 0], 2.0 + np.cumsum(rng.standard_normal(d.shape[0])) * 0.1,
                          lfilter([1.0], [1.0, -0.9], rng.standard_normal(d.shape[0]))])
    model3 = PlantModel(sample_time=1.0, inputs=model.inputs, outputs=("y1", "y2", "y3"),
                        gain=np.vstack([model.gain] * 3), time_constant=np.vstack([model.time_constant] * 3),
                        time_constant2=np.vstack([model.time_constant2] * 3), lead=np.vstack([model.lead] * 3),
                        delay=np.vstack([model.delay] * 3), integrating=np.vstack([model.integrating] * 3))
    start = max(N_LAG, na)
    moments = ResponseMoments(model3, u, d3, [0, 1, 3], N_LAG, start, na, segments)
    segs = [(0, d3.shape[0])] if segments is None else [(a, b) for a, b in segments if b - a > start]
    u_c = u - u.mean(axis=0)
    u_c[:, 2] = 0.0
    Z = np.vstack([lag_matrix(u_c[a:b], range(1, N_LAG + 1), start) for a, b in segs])
    for i in range(3):
        O = np.vstack([lag_matrix(d3[a:b, i] - d3[a:b, i].mean(), range(1, na + 1), start) for a, b in segs])
        rm = moments.row(i)
        assert rm.zo.shape == (4 * N_LAG, na)
        np.testing.assert_allclose(rm.zo, Z.T @ O, rtol=1e-10, atol=1e-9 * np.abs(Z.T @ O).max())


#: The runs of RUNS' segments: the gaps of 1 and 2 samples are short (the model runs through them), the gap of 40 long.
RUN_OF_RUNS = [0, 0, 0, 1]


def _centred_error(moments, i):
    """Row ``i``'s prediction error as the tests centre it: over each run of :data:`RUNS` for a row without an
    integrating element (one level through a short gap), otherwise over each segment."""
    d = moments.d[:, i].copy()
    segs = moments.segs
    groups = RUN_OF_RUNS if moments.segments is RUNS and not moments.model.integrating_outputs[i] else range(len(segs))
    for g in set(groups):
        at = np.concatenate([np.arange(a, b) for (a, b), h in zip(segs, groups) if h == g])
        d[at] -= d[at].mean()
    return d


def _lag_zero_products(moments, i, rm):
    """``u_c(t)' [x, X]`` and ``O' [x, X]`` of row ``i``'s elements by products of each segment's lag matrices (the
    responses from rest in each segment, or through the runs of GapSegments)."""
    u_c, start, na = moments.u_c, moments.start, moments.na
    segs = moments.segs
    U0 = np.vstack([u_c[a + start:b] for a, b in segs])
    O = np.vstack([lag_matrix(d_i[a:b], range(1, na + 1), start) for d_i in [_centred_error(moments, i)] for a, b in segs])
    uw, ow = [], []
    for b, (j, element, _) in enumerate(rm.found):
        x = through(u_c[:, j], element.respond, moments.segments)     # from rest per segment, or through runs
        XW = np.vstack([lag_matrix(x[a0:b0] - rm.mu[s, b], range(0, na + 1), start) for s, (a0, b0) in enumerate(segs)])
        uw.append(U0.T @ XW)
        ow.append(O.T @ XW)
    return np.hstack(uw), np.hstack(ow)


@pytest.mark.parametrize("na, segments", [(3, None), (3, [(0, 600), (600, 620), (620, 1800)]), (1, None), (3, RUNS)])
def test_the_lag_zero_moments_by_the_difference_equation_equal_the_products(na, segments):
    """``u_c(t)' x(t - k)`` and ``O' x(t - k)`` from the elements' difference equations (``_lag_zero``):
    every lag of a finite impulse response, all but the last ``order`` lags of the others, none of an
    element whose numerator reaches beyond the lags; against the products of the lag matrices."""
    model, u, d = _window(7)
    rng = np.random.default_rng(8)
    k = np.arange(1, 5)
    fir = PlantModel.from_step_response(1.0, model.inputs, ("y1",), np.stack([np.stack([
        1.2 * (1 - np.exp(-np.maximum(k - 2, 0) / 2.0)), 0.3 * (1 - np.exp(-k / 3.0)), np.zeros(4),
        -0.5 * (1 - np.exp(-np.maximum(k - 1, 0) / 1.5))])]))
    slow = PlantModel(sample_time=1.0, inputs=model.inputs, outputs=("y1",), gain=np.array([[1.0, 0.5, 0.0, 2.0]]),
                      time_constant=np.array([[8.0, 3.0, 0.0, 4.0]]), delay=np.array([[2.0, 6.0, 0.0, 14.0]]))
    d2 = d + 0.1 * rng.standard_normal(d.shape)
    seen = set()
    for m in (model, fir, slow):
        moments = ResponseMoments(m, u, d2, [0, 1, 2, 3], N_LAG, N_LAG, na, segments)
        rm = moments.row(0)
        rec = [moments._recursive_lags(e) for _, e, _ in rm.found]
        seen.update("all" if r == na else "none" if r < 0 else "some" for r in rec)
        uw, ow = _lag_zero_products(moments, 0, rm)
        for name, got, want in (("uw", rm.uw, uw), ("ow", rm.ow, ow)):
            np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12 * np.abs(want).max(), err_msg=name)
    assert seen == {"all", "some", "none"}


def _long_step_response_window(seed, n=1500, N=40):
    """Two outputs, three inputs of a step-response model of ``N`` coefficients (more than the lags): two
    first-order responses after dead times and one that grows; row y2 a ramp row (integrating: its elements
    have a pole)."""
    rng = np.random.default_rng(seed)
    k = np.arange(1, N + 1)
    row = np.stack([1.2 * (1 - np.exp(-np.maximum(k - 2, 0) / 6.0)), -0.5 * (1 - np.exp(-np.maximum(k - 4, 0) / 9.0)),
                    0.02 * np.maximum(k - 3, 0)])
    model = PlantModel.from_step_response(1.0, ("u1", "u2", "u3"), ("y1", "y2"), np.stack([row, row]),
                                          ramp=(False, True))
    u = rng.standard_normal((n, 3))
    u[:, 0] = np.repeat(rng.choice([-1.0, 1.0], n // 4 + 1), 4)[:n]
    d = lfilter([1.0], [1.0, -0.6], rng.standard_normal((n, 2)), axis=0) + 1.5
    return model, u, d


@pytest.mark.parametrize("segments", [None, [(0, 500), (500, 540), (540, 560), (560, 1500)]])
def test_the_long_gram_equals_the_products_of_lag_matrices_from_rest_in_each_segment(segments):
    """``E[j, s, c, l] = sum_t u_j(t - s) u_c(t - l)`` out to the longest response, with ``u_j`` 0 before each
    segment's start, along lag diagonals, against the product of each segment's zero-padded lag matrices
    (a segment shorter than the response, one without a regression row)."""
    model, u, d = _long_step_response_window(2)
    n_lag, na = 9, 3
    moments = ResponseMoments(model, u, d, [0, 1, 2], n_lag, n_lag, na, segments)
    S = moments.fir_span
    elements = [model.discrete_element(0, j) for j in range(3)]
    assert [e.order for e in elements] == [0, 0, 0] and all(model.discrete_element(1, j).order == 1 for j in range(3))
    assert S == max(e.delay + e.num.size - 1 for e in elements) + na
    u_c = u - u.mean(axis=0)
    segs = [(0, u.shape[0])] if segments is None else [(a, b) for a, b in segments if b - a > n_lag]
    want = np.zeros((3, S + 1, 3, n_lag + 1))
    for a, b in segs:
        padded = np.vstack([np.zeros((S, 3)), u_c[a:b]])
        long = lag_matrix(padded, range(0, S + 1), S + n_lag)             # column j (S + 1) + s
        short = lag_matrix(u_c[a:b], range(0, n_lag + 1), n_lag)          # column c (L + 1) + l
        want += (long.T @ short).reshape(3, S + 1, 3, n_lag + 1)
    np.testing.assert_allclose(moments.fir_gram, want, rtol=1e-11, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("na, segments", [(2, None), (3, [(0, 500), (500, 540), (540, 1500)]),
                                          (1, [(0, 750), (750, 1500)])])
def test_a_long_step_response_by_the_long_gram_and_by_products(monkeypatch, na, segments):
    """A step-response model's elements longer than the lags (finite impulse responses): every moment of the
    row from their taps and the long Gram, against the products over the rows; the ramp row's elements (a
    pole) by products in either."""
    model, u, d = _long_step_response_window(5)
    n_lag = 8
    start = max(n_lag, na)

    def make(i):
        return ResponseMoments(model, u, d, [0, 1, 2], n_lag, start, na, segments).row(i)

    moments = ResponseMoments(model, u, d, [0, 1, 2], n_lag, start, na, segments)
    for i in (0, 1):
        got, want = make(i), _by_product(monkeypatch, lambda: make(i))
        fir = [moments._long_fir(e) for _, e, _ in got.found]
        assert fir == [i == 0] * 3                         # row y2 is a ramp row
        for name in ("zx", "uw", "zo", "ww", "ow", "xsum", "mu"):
            w = getattr(want, name)
            np.testing.assert_allclose(getattr(got, name), w, rtol=1e-10, atol=1e-12 * np.abs(w).max(),
                                       err_msg=f"{name}, row {i}")


def test_a_long_gram_above_its_memory_cap_is_not_built(monkeypatch):
    """Beyond FIR_GRAM_MAX_BYTES the long responses' moments are products over the rows (no long Gram)."""
    from mpm_monitor.core import response_moments

    model, u, d = _long_step_response_window(5)
    moments = ResponseMoments(model, u, d, [0, 1, 2], 8, 8, 2)
    nbytes = 3 * 3 * (moments.fir_span + 1) * 9 * 8
    monkeypatch.setattr(response_moments, "FIR_GRAM_MAX_BYTES", nbytes)
    assert all(moments._long_fir(e) for _, e, _ in moments.row(0).found)
    monkeypatch.setattr(response_moments, "FIR_GRAM_MAX_BYTES", nbytes - 1)
    moments = ResponseMoments(model, u, d, [0, 1, 2], 8, 8, 2)
    assert not any(moments._long_fir(e) for _, e, _ in moments.row(0).found)
    assert moments._fir_gram is None


def test_a_step_response_models_detection_by_the_long_gram_and_by_products(monkeypatch):
    """End to end: case 3.2's loop analysed with its model as step responses (300 coefficients, more than the
    lags): the report through the long Gram is the report through products over the rows, to rounding (the
    element tests, the detectable gain changes, the located elements)."""
    import warnings

    from mpm_monitor.apps.reproduce import simulate_case

    case, data, _ = simulate_case("3.2", 3000, 3)
    m = case.model
    coefs = [[m.discrete_element(i, j).step_response(301)[1:] for j in range(m.n_columns)] for i in range(m.n_outputs)]
    model = PlantModel.from_step_response(m.sample_time, m.inputs, m.outputs, coefs)
    calls = []
    taps = ResponseMoments._fir_moments

    def counted(self, *args):
        calls.append(args[0][0])
        return taps(self, *args)

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        monkeypatch.setattr(ResponseMoments, "_fir_moments", counted)
        got = detect(model, data, AnalysisOptions()).to_dict()
        assert len(calls) >= model.n_outputs * model.n_columns             # every row's elements took it
        monkeypatch.setattr(ResponseMoments, "_long_fir", lambda self, element: False)
        want = detect(model, data, AnalysisOptions()).to_dict()
    assert got["located"] == want["located"] and got["located"]
    assert len(got["elements"]) == len(want["elements"]) == 9
    for g, w in zip(got["elements"], want["elements"]):
        assert g.keys() == w.keys()
        for key, value in w.items():
            if isinstance(value, float):
                assert g[key] == pytest.approx(value, rel=1e-8, abs=1e-300), (g["output"], g["input"], key)
            else:
                assert g[key] == value, (key, g[key], value)


def test_the_row_moments_of_responses_through_short_gaps_equal_the_products_of_the_lag_matrices():
    """With the responses run through the short gaps (GapSegments): the responses are those of
    element_responses over the runs, each segment's centred on its own, and the moments their products."""
    model, u, d = _window(9)
    start = max(N_LAG, NA)
    assert RUNS.joined
    moments = ResponseMoments(model, u, d, [0, 1, 2, 3], N_LAG, start, NA, RUNS)
    assert moments.of(u, RUNS) and not moments.of(u, list(RUNS))
    rm = moments.row(0, keep_samples=True)
    u_c = u - u.mean(axis=0)
    Z = np.vstack([lag_matrix(u_c[a:b], range(1, N_LAG + 1), start) for a, b in RUNS])
    for b, (j, element, _) in enumerate(rm.found):
        if not model.present[0, j]:
            continue
        x = element_responses(model, 0, [j], u_c, RUNS)[j]
        assert np.abs(x[600:660] - element.respond(u_c[600:660, j])).max() > 0    # not from rest after the gap
        mus = [x[a:c].mean() for a, c in RUNS]
        XW = np.vstack([lag_matrix(x[a:c] - mu, range(0, NA + 1), start) for (a, c), mu in zip(RUNS, mus)])
        np.testing.assert_allclose(rm.mu[:, b], mus, rtol=1e-12)
        np.testing.assert_allclose(moments.responses(rm, [j])[j], x, rtol=1e-12, atol=1e-12)
        for got, want in ((rm.zx[..., b].reshape(-1, NA + 1), Z.T @ XW), (rm.ww[b], XW.T @ XW)):
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-10 * np.abs(want).max())


def test_a_long_step_response_through_short_gaps_by_the_long_gram_and_by_products(monkeypatch):
    """The long Gram with the responses through the short gaps: the columns read on each run's grid (held in
    its gaps), every moment equal to the products over the rows of the responses element_responses gives."""
    model, u, d = _long_step_response_window(5)
    runs = GapSegments([(0, 500), (500, 540), (540, 1100), (1100, 1500)],
                       np.concatenate([np.arange(500), np.arange(501, 541), np.arange(543, 1103),
                                       np.arange(1150, 1550)]), 10)
    assert [(a, b) for a, b, _ in runs.runs] == [(0, 1100), (1100, 1500)]

    def make(i):
        return ResponseMoments(model, u, d, [0, 1, 2], 8, 8, 3, runs).row(i, keep_samples=True)

    moments = ResponseMoments(model, u, d, [0, 1, 2], 8, 8, 3, runs)
    u_c = moments.u_c
    for i in (0, 1):
        got, want = make(i), _by_product(monkeypatch, lambda: make(i))
        assert [moments._long_fir(e) for _, e, _ in got.found] == [i == 0] * 3      # row y2 is a ramp row
        for b, (j, element, _) in enumerate(got.found):
            x = element_responses(model, i, [j], u_c, runs)[j]
            np.testing.assert_allclose(moments.responses(got, [j])[j], x, rtol=1e-12, atol=1e-12)
        for name in ("zx", "uw", "zo", "ww", "ow", "xsum", "mu"):
            w = getattr(want, name)
            np.testing.assert_allclose(getattr(got, name), w, rtol=1e-10, atol=1e-12 * np.abs(w).max(),
                                       err_msg=f"{name}, row {i}")


@pytest.mark.parametrize("testable", [[0, 1, 2], [0, 2]])
def test_the_moments_through_gaps_with_known_columns_run_on_them(monkeypatch, testable):
    """Known columns inside the short gaps (a segment left out, a spike: GapSegments' ``columns``): the moments
    centre them as their own columns (a column not tested 0) and the responses, the long Gram's windows and
    every moment run on them, equal to element_responses through the same filled segments and to the products
    over the rows; a response moves with them."""
    model, u, d = _long_step_response_window(7)
    grid = np.concatenate([np.arange(500), np.arange(501, 541), np.arange(543, 1103), np.arange(1150, 1550)])
    known = np.array([500, 541, 1120])                       # 542 stays unknown; 1120 lies in the long gap
    columns = np.random.default_rng(3).standard_normal((3, 3)) * 4.0
    runs = GapSegments([(0, 500), (500, 540), (540, 1100), (1100, 1500)], grid, 10, known, columns)

    def make(i):
        return ResponseMoments(model, u, d, testable, 8, 8, 3, runs).row(i, keep_samples=True)

    moments = ResponseMoments(model, u, d, testable, 8, 8, 3, runs)
    want_values = columns - u.mean(axis=0)
    want_values[:, [j for j in range(3) if j not in testable]] = 0.0
    np.testing.assert_array_equal(moments.segments.values, want_values)
    assert runs.values is None and moments.of(u, runs)
    held = ResponseMoments(model, u, d, testable, 8, 8, 3,
                           GapSegments([(0, 500), (500, 540), (540, 1100), (1100, 1500)], grid, 10, known))
    for i in (0, 1):
        got, want = make(i), _by_product(monkeypatch, lambda: make(i))
        for j in testable:                       # a column not tested has no response (its u_c is 0)
            x = element_responses(model, i, [j], moments.u_c, moments.segments)[j]
            np.testing.assert_allclose(moments.responses(got, [j])[j], x, rtol=1e-12, atol=1e-12)
            before = held.responses(held.row(i, keep_samples=True), [j])[j]
            assert np.abs(x[500:560] - before[500:560]).max() > 1e-3
        for name in ("zx", "uw", "zo", "ww", "ow", "xsum", "mu"):
            w = getattr(want, name)
            np.testing.assert_allclose(getattr(got, name), w, rtol=1e-10, atol=1e-12 * np.abs(w).max(),
                                       err_msg=f"{name}, row {i}")


@pytest.mark.parametrize("segments", [None, [(0, 150), (150, 200), (200, 400)], "runs"])
def test_a_step_response_longer_than_the_window_takes_a_gram_cut_where_no_sample_reaches(monkeypatch, segments):
    """A step-response model of 2,000 coefficients on a window of 400 samples: the long Gram stops at the last lag a
    sample still reaches (the longest segment, or run's grid, less one), not at the response's end, and every
    moment of the rows from it equals the products over the rows of the responses simulated to their full length."""
    model, u, d = _long_step_response_window(7, n=400, N=2000)
    if segments == "runs":          # the responses run through the short gaps of 1 and 2 samples: one run of 403
        segments = GapSegments([(0, 150), (150, 200), (200, 400)],
                               np.concatenate([np.arange(150), np.arange(151, 201), np.arange(203, 403)]), 10)
        reach = 402
    else:
        reach = 399 if segments is None else 199
    n_lag, na = 8, 3

    def make(i):
        return ResponseMoments(model, u, d, [0, 1, 2], n_lag, n_lag, na, segments).row(i)

    moments = ResponseMoments(model, u, d, [0, 1, 2], n_lag, n_lag, na, segments)
    assert moments.fir_reach == reach and moments.fir_span == reach
    assert moments.fir_gram.shape == (3, reach + 1, 3, n_lag + 1)
    got, want = make(0), _by_product(monkeypatch, lambda: make(0))
    assert [moments._long_fir(e) for _, e, _ in got.found] == [True] * 3
    for name in ("zx", "uw", "zo", "ww", "ow", "xsum", "mu"):
        w = getattr(want, name)
        np.testing.assert_allclose(getattr(got, name), w, rtol=1e-10, atol=1e-12 * np.abs(w).max(), err_msg=name)


def test_the_long_grams_lag_zero_taken_a_few_lags_at_a_time_is_the_same(monkeypatch):
    """FIR_COPY_BYTES bounds the copy of the lagged windows the long Gram's lag 0 is a product of: taken 7 lags at a
    time it equals the one product (a long response over a long window copied rows x lags: gigabytes)."""
    from mpm_monitor.core import response_moments

    model, u, d = _long_step_response_window(3)
    whole = ResponseMoments(model, u, d, [0, 1, 2], 8, 8, 2).fir_gram
    monkeypatch.setattr(response_moments, "FIR_COPY_BYTES", 8 * (1500 - 8) * 7)
    parts = ResponseMoments(model, u, d, [0, 1, 2], 8, 8, 2).fir_gram
    assert whole.shape[1] > 7
    np.testing.assert_allclose(parts, whole, rtol=1e-12, atol=1e-13 * np.abs(whole).max())
