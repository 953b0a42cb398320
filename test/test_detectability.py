"""Detectability and the experiment: the noncentral-F formula, its moments, the experiment's choice, the outputs.

The calibration by simulation (an error of the reported size is detected about 90 % of the time) is
bench/detectability.py; the recall the experiments bring is bench/experiment_mc.py.
"""

import dataclasses
import itertools
import json
import types

import numpy as np
import pytest
from scipy import stats

from mpm_monitor.core import detectability as det
from mpm_monitor.core import experiment as exm
from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.arx import lag_matrix
from mpm_monitor.core.filters import lfilter
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.noise_polynomial import RowNoise
from mpm_monitor.core.regressions import regression_layout
from mpm_monitor.core.statistics import detection_noncentrality
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.mpc import MpcOptions

FAST = AnalysisOptions(repair=False)
#: A fat plant (2 outputs, 4 inputs): its controller moves the inputs in 2 directions only.
FAT_PLANT = PlantModel(sample_time=1.0, inputs=("u1", "u2", "u3", "u4"), outputs=("y1", "y2"),
                       gain=[[1.0, 0.6, 0.8, 0.5], [0.4, 1.2, 0.5, 0.9]],
                       time_constant=[[10, 15, 12, 20], [14, 10, 18, 12]], delay=[[1, 2, 1, 3], [2, 1, 2, 1]])
FAT_MODEL = FAT_PLANT.replace(gain=[[1.0, 0.6, 0.8, 0.8], [0.4, 1.2, 0.5, 0.9]])


# ------------------------------------------------------------------------------ the noncentral F
@pytest.mark.parametrize("k, dof, level", [(1, 50, 0.05), (4, 200, 0.01), (12, 2900, 0.01 / 24), (20, 800, 1e-4)])
def test_detection_noncentrality_gives_the_power_of_the_noncentral_f(k, dof, level):
    """The noncentrality from scipy.special's ncfdtrinc is detected with probability 0.9 (scipy.stats.ncf)."""
    lam = detection_noncentrality(k, dof, level, 0.9)
    f_crit = stats.f.isf(level, k, dof)
    assert stats.ncf.sf(f_crit, k, dof, lam) == pytest.approx(0.9, abs=2e-5)   # ncfdtrinc solves to ~5e-6
    assert stats.ncf.sf(f_crit, k, dof, 0.8 * lam) < 0.9 < stats.ncf.sf(f_crit, k, dof, 1.2 * lam)


def test_detection_noncentrality_by_numerical_integration():
    """Independent reference: P(F' > c) as the Poisson mixture of central F tails, integrated numerically."""
    k, dof, level = 3, 120, 0.005
    lam = detection_noncentrality(k, dof, level, 0.9)
    c = stats.f.isf(level, k, dof)
    x = np.linspace(c, c + 400.0, 400_001)
    j = np.arange(0, 200)
    weights = stats.poisson.pmf(j, lam / 2)
    # the density of the noncentral F: sum_j w_j * density of (k + 2j) chi2 / k over chi2(dof) / dof
    dens = sum(w * stats.f.pdf(x * k / (k + 2 * jj), k + 2 * jj, dof) * k / (k + 2 * jj)
               for jj, w in zip(j, weights) if w > 1e-14)
    assert np.trapezoid(dens, x) == pytest.approx(0.9, abs=2e-4)


def _window(seed=0, n=2000, na=2):
    """A 2x3 model, white inputs, an AR noise on the prediction error of row 0."""
    model = PlantModel(sample_time=1.0, inputs=("u1", "u2", "u3"), outputs=("y1", "y2"),
                       gain=[[1.5, 0.0, -0.7], [0.3, 1.0, 0.5]], time_constant=[[8, 0, 5], [3, 6, 9]],
                       delay=[[2, 0, 1], [1, 3, 0]])
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 3)) @ np.array([[1.0, 0.3, 0.0], [0.0, 1.0, 0.4], [0.0, 0.0, 1.0]])
    e = 0.1 * rng.standard_normal((n, 2))
    d = lfilter([1.0], [1.0, -0.6, 0.1], e, axis=0)
    noise = {0: RowNoise(sigma2=0.01, dof=n - 40, a=np.array([-0.6, 0.1][:na]))}
    return model, u, d, noise


def test_the_drop_equals_the_least_squares_reference():
    """q_ij / n from the moments equals the RSS drop of A(q) x_ij on the input and own lags, by lstsq."""
    model, u, d, noise = _window()
    L, start = 8, 8
    windows = {(0, 0): 5, (0, 1): None, (0, 2): 3}
    info = det.WindowInformation(model, u, d, [0, 1, 2], L, start, noise, windows)
    drops = info.drops([(0, 0), (0, 1), (0, 2)], det.moment_inverse(info.G))
    u_c = u - u.mean(axis=0)
    d_c = d[:, 0] - d[:, 0].mean()
    Z = lag_matrix(u_c, range(1, L + 1), start)
    O = lag_matrix(d_c, range(1, 3), start)
    for (i, j), k in windows.items():
        element, _ = det.target_element(model, i, j)        # (0, 1): the row's typical element
        x = element.respond(u_c[:, j])
        x -= x.mean()
        xf = lfilter(np.r_[1.0, noise[0].a], [1.0], x)[start:]
        k = L if k is None else k
        keep = [c for c in range(Z.shape[1]) if not (j * L <= c < j * L + k)]
        full = np.column_stack([Z, O])
        reduced = np.column_stack([Z[:, keep], O])
        rss = [np.sum((xf - m @ np.linalg.lstsq(m, xf, rcond=None)[0]) ** 2) for m in (reduced, full)]
        assert drops[(i, j)] == pytest.approx((rss[0] - rss[1]) / Z.shape[0], rel=1e-6)


@pytest.mark.parametrize("L, start, testable", [(8, 8, [0, 1, 2]), (6, 11, [0, 2])])
def test_the_moments_equal_the_direct_products(L, start, testable):
    """Z' x_f, Z' X (summed along lag diagonals), O' x_f, O' X, X' X and X' x_f equal the products of the
    lag matrices themselves, for every element."""
    model, u, d, noise = _window(seed=3)
    info = det.WindowInformation(model, u, d, testable, L, start, noise, {})
    u_c = u - u.mean(axis=0)
    u_c[:, [j for j in range(3) if j not in testable]] = 0.0
    Z = lag_matrix(u_c, range(1, L + 1), start)
    O = lag_matrix(d[:, 0] - d[:, 0].mean(), range(1, 3), start)
    n = Z.shape[0]
    assert sorted(info.targets) == [(0, 0), (0, 1), (0, 2)]
    for (i, j), t in info.targets.items():
        element, _ = det.target_element(model, i, j)
        x = element.respond(u_c[:, j])
        x -= x.mean()
        xf = lfilter(np.r_[1.0, noise[0].a], [1.0], x)[start:]
        X = lag_matrix(x, range(1, 3), start)
        for got, want in ((t.c, Z.T @ xf), (t.zx, Z.T @ X), (t.c_own, O.T @ xf), (t.ox, O.T @ X),
                          (t.xx, X.T @ X), (t.xxf, X.T @ xf)):
            np.testing.assert_allclose(got, want / n, rtol=1e-10, atol=1e-12 * np.abs(want / n).max())


def test_with_gaps_the_moments_are_the_sums_of_the_segments_own():
    """Data with gaps: every moment is the sum over the segments of the products of each segment's
    lag matrices (its responses from rest, its x and d centred on their own), the diagonal sums
    corrected at both ends of every segment."""
    model, u, d, noise = _window(seed=5)
    L = start = 6
    segs = [(0, 400), (400, 410), (410, 1100), (1100, u.shape[0])]      # the second too short: left out
    info = det.WindowInformation(model, u, d, [0, 1, 2], L, start, noise, {}, segments=segs)
    used = [(a, b) for a, b in segs if b - a > start]
    assert info.segments == used
    u_c = u - u.mean(axis=0)
    Z = np.vstack([lag_matrix(u_c[a:b], range(1, L + 1), start) for a, b in used])
    O = np.vstack([lag_matrix(d[a:b, 0] - d[a:b, 0].mean(), range(1, 3), start) for a, b in used])
    n = Z.shape[0]
    assert info.n_rows == n == sum(b - a - start for a, b in used)
    np.testing.assert_allclose(info.G, Z.T @ Z / n, rtol=1e-12)
    for (i, j), t in info.targets.items():
        element, _ = det.target_element(model, i, j)
        xs = []
        for a, b in used:
            x = element.respond(u_c[a:b, j])
            xs.append(x - x.mean())
        xf = np.concatenate([lfilter(np.r_[1.0, noise[0].a], [1.0], x)[start:] for x in xs])
        X = np.vstack([lag_matrix(x, range(1, 3), start) for x in xs])
        for got, want in ((t.c, Z.T @ xf), (t.zx, Z.T @ X), (t.c_own, O.T @ xf), (t.ox, O.T @ X),
                          (t.xx, X.T @ X), (t.xxf, X.T @ xf)):
            np.testing.assert_allclose(got, want / n, rtol=1e-10, atol=1e-12 * np.abs(want / n).max())


def test_without_detectability_the_tests_are_the_same_and_nothing_is_estimated():
    model, _, _, _ = _window()
    plant = model.with_element(0, 0, gain=2.0)
    data = run_closed_loop(plant, model, 1500, seed=4).as_logged_data()
    full, bare = detect(model, data), detect(model, data, detectability=False)
    assert [(e.output, e.input, e.p_value, e.mismatch) for e in full.elements] == \
        [(e.output, e.input, e.p_value, e.mismatch) for e in bare.elements]
    assert [r.p_value for r in full.rows] == [r.p_value for r in bare.rows]
    assert any(e.detectable_gain_change is not None for e in full.elements)
    assert all(e.detectable_gain_change is None for e in bare.elements) and bare.experiment is None


def test_the_detectable_change_is_the_formula(monkeypatch):
    """Without the own-lag fixed point: sqrt(c lambda_90 sigma^2 / q), lambda_90 at Holm's first step alpha / (2 m)."""
    monkeypatch.setattr(det, "FIXED_POINT_STEPS", 0)
    model, u, d, noise = _window()
    info = det.WindowInformation(model, u, d, [0, 1, 2], 8, 8, noise, {})
    values = info.detectable([(0, 0), (0, 2)], alpha=0.01, family_size=3)
    q = info.drops([(0, 0), (0, 2)], det.moment_inverse(info.G))
    n = info.n_rows
    dof = n - 24 - 2
    f_crit = stats.f.isf(0.01 / 6, 8, dof)
    lo, hi = 0.0, 500.0        # the power equation solved by bisection on scipy.stats.ncf
    for _ in range(100):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if stats.ncf.sf(f_crit, 8, dof, mid) < 0.9 else (lo, mid)
    for key in values:
        assert values[key] == pytest.approx(np.sqrt(det.CALIBRATION * lo * 0.01 / (q[key] * n)), rel=1e-5)


# ------------------------------------------------------------------------------ closed loops
@pytest.fixture(scope="module")
def fat():
    """The fat loop without dither (1500 samples) and its analysis: ambiguous, no element located."""
    log = run_closed_loop(FAT_PLANT, FAT_MODEL, 1500, seed=3, mpc=MpcOptions(prediction_horizon=60,
                                                                              control_horizon=15))
    data = log.as_logged_data("fat loop")
    return data, detect(FAT_MODEL, data, FAST)


def test_a_fat_plant_gets_the_fewest_inputs_then_the_smallest_experiment(fat):
    data, rep = fat
    assert rep.located_elements == [] and rep.ambiguous_elements
    exp = rep.experiment
    assert exp is not None
    # fewest inputs: the controller moves 4 inputs in 2 directions, so 2 must be dithered (1 cannot separate them)
    assert len(exp.dither) == 2
    std = data.u.std(axis=0)
    for name, a in exp.dither.items():
        assert 0 < a <= 0.5 * std[FAT_MODEL.inputs.index(name)] * (1 + 1e-3)
    assert exp.expected_detectable_gain_change <= exm.GOAL + 1e-9
    assert exp.samples % exm.SAMPLES_STEP == 0 and exp.samples <= exm.MAX_SAMPLES
    assert exp.why.startswith("the closed loop moves u1, u2, u3, u4 together")
    assert "smallest experiment" in exp.why
    # the smallest amplitude x samples: no other pair of inputs does it cheaper at full amplitude
    info, pred, caps, chosen = _predictor(data, rep)
    cost = min(exm._trial(pred, chosen, caps, f, info.G.shape[0]).cost for f in exm.AMPLITUDE_FRACTIONS)
    for pair in itertools.combinations(range(4), 2):
        t = exm._trial(pred, pair, caps, 1.0, info.G.shape[0])
        assert not t.separated or t.cost >= cost - 1e-9
    for one in range(4):
        assert not exm._trial(pred, (one,), caps, 1.0, info.G.shape[0]).separated


def test_the_experiment_is_long_enough_for_the_repair_of_what_it_locates():
    """A 1 x 2 loop (one output, two inputs the controller moves together): the design of 250 samples located the
    element and left 188 samples to the repair's fit part, fewer than the 260 it needs: "unknown", no change, on
    every such run of an outside check.  The experiment now lasts at least what the repair needs, and its log
    repairs the element."""
    from mpm_monitor.core.pipeline import analyze
    from mpm_monitor.core.repair import RepairOptions
    from mpm_monitor.core.repair.record import samples_for_repair

    plant = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1",), gain=[[1.0, 0.7]],
                       time_constant=[[10, 15]], delay=[[1, 2]])
    model = plant.replace(gain=[[1.0, 1.0]])
    need = samples_for_repair(model, RepairOptions())
    assert need == 346                                   # a fit part of 260 once the held-out quarter is apart
    log = run_closed_loop(plant, model, 3000, seed=0)
    exp = detect(model, log.as_logged_data(), FAST).experiment
    assert exp is not None and exp.samples >= need
    from mpm_monitor.sim.closed_loop import ExcitationOptions
    from mpm_monitor.sim.excitation import PrbsOptions

    amplitudes = tuple(exp.dither.get(name, 0.0) for name in model.inputs)
    dither = ExcitationOptions(dither=PrbsOptions(amplitude=1.0, switch_probability=0.5), dither_amplitudes=amplitudes)
    dithered = run_closed_loop(plant, model, exp.samples, seed=10000, mpc=MpcOptions(), excitation=dither)
    rep = analyze(model, dithered.as_logged_data(), AnalysisOptions())
    assert rep.located_elements == [("y1", "u2")]
    assert rep.repaired_model.gain[0, 1] == pytest.approx(0.7, rel=0.05)


def _predictor(data, rep):
    """The window's information and the experiment's predictor, rebuilt as detect() builds them."""
    from mpm_monitor.core.input_design import InputDesign
    from mpm_monitor.core.noise_polynomial import row_noise
    from mpm_monitor.core.regressions import window_regressions
    from mpm_monitor.core.signals import compute_signals

    model, options = FAT_MODEL, FAST
    layout = regression_layout(model, options)
    sig = compute_signals(model, data.r, data.u, data.y, options.initial_state, dv=data.dv)
    regs = window_regressions(data.r, data.u, sig.eps - data.r, sig.d, layout, options.na, options.nb)
    design = InputDesign(model, data.u, layout.n_lag_u, layout.start, options.collinearity_threshold,
                         regs.input_regression)
    noise = {i: row_noise(regs.element_fit(design.regression, i)) for i in range(model.n_outputs)}
    info, _, _ = det.element_detectability(model, data.u, sig.d, design, noise, layout, options)
    targets = sorted((model.outputs.index(o), model.inputs.index(i)) for o, i in rep.ambiguous_elements)
    pred = exm._Predictor(info, targets, options.alpha, options.collinearity_threshold, layout, info.testable)
    caps, _ = exm._caps(info, model, [0, 1, 2, 3])
    chosen = tuple(sorted(model.inputs.index(k) for k in rep.experiment.dither))
    return info, pred, caps, chosen


def test_an_input_that_did_not_move_is_named_and_its_amplitude_is_not_bounded_by_a_spread(fat):
    data, _ = fat
    u = data.u.copy()
    u[:, 3] = 0.25                       # u4 never moved in this window
    frozen = dataclasses.replace(data, u=u)
    rep = detect(FAT_MODEL, frozen, FAST)
    assert all(e.detectable_gain_change is None for e in rep.elements if e.input == "u4")
    assert any("u4 never move" in w and "detectable_gain_change null" in w for w in rep.warnings)
    exp = rep.experiment
    assert exp is not None and "u4" in exp.dither and exp.dither["u4"] > 0
    assert "u4 did not move at all in this window" in exp.why and "u4 did not move, so its amplitude" in exp.why
    # It said "matches the other inputs' dithers", also where no other input is dithered.
    assert "its effect on the outputs matches the effect on the outputs of a dither of half the standard " \
           "deviation of the inputs that moved" in exp.why and "the other inputs' dithers" not in exp.why
    # The summary says why its elements were not tested (it listed them as "ambiguous (inputs move together)").
    text = rep.summary_text()
    assert "not testable (their column never moves): (y1, u4), (y2, u4)" in text and "u4 n/a (never moves)" in text
    assert not any("u4" in line for line in text.splitlines() if line.startswith("ambiguous ("))


def test_no_experiment_when_nothing_is_ambiguous_and_elements_are_decidable():
    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 3000, seed=11, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    rep = detect(case.model, log.as_logged_data(), FAST)
    assert rep.located_elements and not rep.ambiguous_elements
    values = [e.detectable_gain_change for e in rep.elements]
    assert all(v is not None and 0 < v < 1 for v in values) and min(values) <= 0.2
    assert rep.experiment is None
    assert rep.to_dict()["experiment"] is None


def test_experiment_choice_rules_on_a_stub_window():
    """Not decidable at 20 % and nothing ambiguous: the experiment is for every unlocated element."""
    model, u, d, noise = _window(n=800)
    info = det.WindowInformation(model, u, d, [0, 1, 2], 8, 8, noise, {})
    layout = types.SimpleNamespace(start=8, min_samples=200)

    def el(j, x, ambiguous=False, mismatch=False):
        return types.SimpleNamespace(output="y1", input=model.inputs[j], mismatch=mismatch, ambiguous=ambiguous,
                                     ambiguous_with=(), detectable_gain_change=x)

    # decidable (one element at 20 % or better) and nothing ambiguous: no experiment
    assert exm.design_experiment(model, info, [el(0, 0.1), el(1, 0.5), el(2, 0.9)], FAST, layout) is None
    # nothing decidable: an experiment, the dither on as few inputs as reach the goal
    exp = exm.design_experiment(model, info, [el(0, 0.5), el(1, 0.6), el(2, 0.9)], FAST, layout)
    assert exp is not None and 1 <= len(exp.dither) <= 3
    assert "no element is decidable at the 20% level in this window" in exp.why
    # With ambiguous elements, whose values are not calibrated (and printed beside the why), the text says
    # the others: "no element is decidable" read as a contradiction of an ambiguous value of 13 %.
    exp = exm.design_experiment(model, info, [el(0, 0.13, ambiguous=True), el(1, 0.6), el(2, 0.9)], FAST, layout)
    assert "no element that these data tell apart is decidable at the 20% level in this window (the smallest " \
           "detectable gain change is 0.6)" in exp.why
    assert all(a <= 0.5 * u[:, model.inputs.index(k)].std() * 1.001 for k, a in exp.dither.items())
    # a located element is not a target: with the others decidable, nothing to do
    assert exm.design_experiment(model, info, [el(0, 0.5, mismatch=True), el(1, 0.1), el(2, 0.15)], FAST,
                                 layout) is None


# ------------------------------------------------------------------------------ the outputs
def test_json_summary_statuses_and_report_carry_it(fat, tmp_path):
    from mpm_monitor.io.report import write_report
    from mpm_monitor.monitor.statuses import row_statuses
    from mpm_monitor.monitor.worker import AnalysisJob, AnalysisOutcome

    data, rep = fat
    doc = json.loads(json.dumps(rep.to_dict()))
    assert all("detectable_gain_change" in e for e in doc["elements"])
    assert all(e["detectable_gain_change"] is None or e["detectable_gain_change"] > 0 for e in doc["elements"])
    e = doc["experiment"]
    assert set(e) == {"dither", "samples", "expected_detectable_gain_change", "why"}
    assert e["samples"] == rep.experiment.samples and e["dither"] == rep.experiment.dither

    text = rep.summary_text()
    assert "detectable gain change (smallest relative gain error detected with probability 0.9):" in text
    assert "  y1: u1 " in text and "(ambiguous)" in text
    assert f"experiment recommended: PRBS dither on {', '.join(f'{k} {v:g}' for k, v in e['dither'].items())}" \
           f" (input units) for {e['samples']} samples" in text

    job = AnalysisJob(seq=1, data=data, first_stamp=0.0, last_stamp=1499.0, completed=1500)
    rows = row_statuses(FAT_MODEL.outputs, AnalysisOutcome(job, report=rep), None, "waiting", "test")
    value = rows[0].value("detectable_gain_change")
    parts = dict(p.split("=") for p in value.split(","))
    assert list(parts) == ["u1", "u2", "u3", "u4"]
    by_input = {x.input: x.detectable_gain_change for x in rep.elements if x.output == "y1"}
    assert all(float(v) == pytest.approx(by_input[k]) for k, v in parts.items())

    out = write_report(tmp_path / "rep", FAT_MODEL, data, rep)
    html = out.read_text()
    assert "<h2>Detectability and experiment</h2>" in html and "Recommended experiment:" in html
    assert (tmp_path / "rep" / "detectability.png").is_file()


def test_every_element_of_a_well_excited_square_loop_gets_a_value():
    case = paper_case("3.1")
    log = run_closed_loop(case.plant, case.model, 2000, seed=5, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    rep = detect(case.model, log.as_logged_data(), dataclasses.replace(FAST, test_all_rows=True))
    assert len(rep.elements) == 9
    assert all(np.isfinite(e.detectable_gain_change) for e in rep.elements)


def _kept_information(monkeypatch):
    """detect()'s WindowInformation objects, kept as they are made."""
    made = []

    class Keep(det.WindowInformation):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            made.append(self)

    monkeypatch.setattr(det, "WindowInformation", Keep)
    return made


def test_the_experiment_counts_the_whole_response_test_and_a_dithers_share_of_it(fat, monkeypatch):
    """The prediction takes, per target, the better of the window test and the whole-response test,
    whose information a dither on the element's input raises by a^2 sum h^2 / sigma^2 per sample
    (checked against python-control's ZOH of the element driven by a PRBS, filtered by A_i)."""
    import control

    data, _ = fat
    made = _kept_information(monkeypatch)
    given = []
    element_detectability = det.element_detectability

    def keep_responses(*args, **kwargs):
        given.append(kwargs.get("responses") or {})
        return element_detectability(*args, **kwargs)

    monkeypatch.setattr(det, "element_detectability", keep_responses)
    rep = detect(FAT_MODEL, data, FAST)
    info = made[-1]
    targets = sorted((FAT_MODEL.outputs.index(o), FAT_MODEL.inputs.index(i)) for o, i in rep.ambiguous_elements)
    # Every element of the fat model whose whole-response test could be formed has its information kept.  The
    # inputs move exactly together here (variance inflation inf), so whether an element's regressor keeps a
    # direction above the rank cut is decided at rounding level: on some BLAS kernels one of the eight has none.
    formed = {k for k, t in given[-1].items() if t.df_num > 0 and 0 < t.information < np.inf}
    assert set(info.responses) == formed & set(targets)
    assert len(info.responses) >= len(targets) - 1
    pred = exm._Predictor(info, targets, FAST.alpha, FAST.collinearity_threshold, regression_layout(FAT_MODEL, FAST),
                          info.testable)
    key = (1, 2) if (1, 2) in info.responses else (1, 3)       # (y2, u3), else (y2, u4)
    other = 3 if key[1] == 2 else 2
    a = 0.3
    own = pred.response_rate(key, {})
    assert own == info.responses[key][0]
    added = pred.response_rate(key, {key[1]: a}) - own
    assert pred.response_rate(key, {other: a}) == own          # a dither on another input adds nothing here
    # Reference: the element as python-control samples it (ZOH, then the dead time), a +-a PRBS through it,
    # A_i(q) applied, its mean square over the row's noise variance.
    gain, tau, delay = FAT_MODEL.gain[key], FAT_MODEL.time_constant[key], int(FAT_MODEL.delay[key])
    sysd = control.sample_system(control.tf([gain], [tau, 1.0]), FAT_MODEL.sample_time, method="zoh")
    rng = np.random.default_rng(5)
    n = 400_000
    dither = a * np.where(rng.random(n) < 0.5, -1.0, 1.0)
    x = np.asarray(control.forced_response(sysd, T=np.arange(n) * FAT_MODEL.sample_time, U=dither).outputs)
    x = np.concatenate([np.zeros(delay), x[:n - delay]])
    nz = info.noise[key[0]]
    xf = lfilter(np.concatenate([[1.0], nz.a]), [1.0], x)[1000:]
    assert added == pytest.approx(np.mean(xf ** 2) / nz.sigma2, rel=0.02)
    # Each target needs the smaller of its two tests' rows, so the experiment is never longer than
    # the window test alone would ask; with u3 and u4 dithered it is shorter where every target has both tests.
    p = info.G.shape[0]
    sep, drops, fam = pred.evaluate({2: 0.186, 3: 0.198})
    alone = {k: (q, 0.0) for k, (q, _) in drops.items()}
    for k, (q, rate) in drops.items():
        both = pred._need(k, q, rate, fam, 3000, p)
        assert both == min(pred._need(k, q, 0.0, fam, 3000, p), pred._need(k, 0.0, rate, fam, 3000, p))
    with_dither, without = pred.samples_needed(drops, fam, p), pred.samples_needed(alone, fam, p)
    assert sep and with_dither <= without
    assert pred.worst_at(drops, fam, 2400, p) <= pred.worst_at(alone, fam, 2400, p)
    if set(info.responses) == set(targets):    # every target has both tests (see above): the dither shortens it
        assert with_dither < 0.9 * without
        assert pred.worst_at(drops, fam, 2400, p) < pred.worst_at(alone, fam, 2400, p)
    assert rep.experiment.samples <= pred.samples_needed(drops, fam, p) + exm.SAMPLES_STEP


def test_an_element_the_model_lacks_is_valued_at_the_full_level(monkeypatch):
    """Only an element with the whole-response test shares its window test's level with it: the
    element the model lacks (window test alone) is valued at alpha / (2 m), the others at alpha / (4 m)."""
    case = paper_case("3.1")
    model = case.model.with_element(0, 1, gain=0.0)
    log = run_closed_loop(model, model, 2000, seed=5, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    made = _kept_information(monkeypatch)
    rep = detect(model, log.as_logged_data(), dataclasses.replace(FAST, test_all_rows=True))
    info, = made
    assert info.split == 2
    got = {(model.outputs.index(e.output), model.columns.index(e.input)): e for e in rep.elements}
    assert got[(0, 1)].p_value_response is None and got[(0, 0)].p_value_response is not None
    family = 9
    full = info.detectable([(0, 1)], 0.01, family, split=1)[(0, 1)]
    half = info.detectable([(0, 1)], 0.01, family)[(0, 1)]
    assert got[(0, 1)].detectable_gain_change == full < half
    # An element with both tests: the smaller of its window test's value at half the level and its
    # response test's.
    window = info.detectable([(0, 0)], 0.01, family)[(0, 0)]
    assert got[(0, 0)].detectable_gain_change <= window
    # The experiment's prediction takes the same levels: the full one for the element the model lacks.
    assert (info.split_of((0, 1)), info.split_of((0, 0))) == (1, 2)
    layout = regression_layout(model, FAST)
    pred = exm._Predictor(info, [(0, 1), (0, 0)], 0.01, FAST.collinearity_threshold, layout, [0, 1, 2])
    separated, drops, fam = pred.evaluate({})
    assert separated and pred._level((0, 1), fam) == 2 * pred._level((0, 0), fam) == info.level(fam, 0.01, 1)
    lone = {(0, 1): drops[(0, 1)]}
    at_full = pred.worst_at(lone, fam, 2000, info.G.shape[0])
    monkeypatch.setattr(det.WindowInformation, "split_of", lambda self, key: 2)
    assert at_full < pred.worst_at(lone, fam, 2000, info.G.shape[0])


def test_no_values_for_the_baselines():
    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 1500, seed=11, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    rep = detect(case.model, log.as_logged_data(), dataclasses.replace(FAST, method="xcorr"))
    assert all(e.detectable_gain_change is None for e in rep.elements) and rep.experiment is None
    assert "method xcorr: the smallest gain change this window detects is computed for the arx element test only " \
           "(detectable_gain_change null)" in rep.warnings



def test_simulate_takes_the_dither_of_a_reports_experiment(tmp_path):
    from mpm_monitor.apps.cli import _experiment_dither
    from mpm_monitor.core.errors import InputError

    path = tmp_path / "report.json"
    path.write_text(json.dumps({"experiment": {"dither": {"u4": 0.2, "u2": 0.1}, "samples": 100}}))
    assert _experiment_dither(str(path), FAT_MODEL) == (0.0, 0.1, 0.0, 0.2)
    path.write_text(json.dumps({"experiment": None}))
    with pytest.raises(InputError, match="key 'experiment': expected an object with a 'dither'"):
        _experiment_dither(str(path), FAT_MODEL)
    path.write_text(json.dumps({"experiment": {"dither": {"u9": 0.2}}}))
    with pytest.raises(InputError, match="unknown input"):
        _experiment_dither(str(path), FAT_MODEL)
    # A boolean was read as 1.0; an integer of 401 digits, and nesting json cannot follow, ended in tracebacks
    for text, match in (('{"experiment": {"dither": {"u2": true}}}', r"expected finite amplitudes >= 0, got u2=True"),
                        ('{"experiment": {"dither": {"u2": Infinity}}}', r"got u2=inf"),
                        ('{"experiment": {"dither": {"u2": 1' + "0" * 400 + '}}}', r"got u2=1000+\.\.\.$"),
                        ("[" * 100000 + "]" * 100000, r"cannot read the report: arrays or objects nested too deeply"),
                        # an outside check: 1e300 was taken, and the log it wrote every reader refused
                        ('{"experiment": {"dither": {"u2": 1e300}}}',
                         r"key 'experiment.dither': expected amplitudes of at most 1e\+40 \(input units: a log "
                         r"dithered beyond it cannot be analysed\), got u2=1e\+300$")):
        path.write_text(text)
        with pytest.raises(InputError, match=match) as refused:
            _experiment_dither(str(path), FAT_MODEL)
        assert str(refused.value).startswith(f"{path}: ") and "\n" not in str(refused.value)


def test_a_still_measured_disturbance_is_named_as_one():
    """The warning that the detectable change of a still column's elements cannot be computed calls a
    measured disturbance a measured disturbance (it said "inputs inflow never move")."""
    from mpm_monitor.apps.reproduce import simulate_case

    case, data, _ = simulate_case("level", 1500, 3)
    still = dataclasses.replace(data, dv=np.full_like(data.dv, 0.4))
    rep = detect(case.model, still, AnalysisOptions(repair=False))
    said = [w for w in rep.warnings if "never move: the smallest gain change" in w]
    assert said and said[0].startswith(f"measured disturbances {case.model.disturbances[0]} never move"), said


def test_the_summary_prints_a_value_above_one_as_more_than_100_percent():
    """Above 1 the first-order value says only that this window does not reliably detect an error as large
    as the element (bench.detectability --still --first-order); the JSON keeps the number."""
    from mpm_monitor.core.analysis_report import detectable_text

    assert [detectable_text(x) for x in (0.35, 0.999, 1.0, 1.0001, 353.5, None, float("inf"))] == \
        ["35%", "100%", "100%", ">100%", ">100%", "n/a", "n/a"]
    # Below half a percent it said "0%", which reads as an error of none detected for sure.
    assert [detectable_text(x) for x in (0.0049, 0.001, 0.0, 0.0051, 0.0149)] == ["<1%", "<1%", "<1%", "1%", "1%"]


def test_beyond_the_cap_the_smallest_multiple_that_reaches_the_goal_is_found_by_bisection(monkeypatch):
    """A stub predictor needing 4e6 / f^2 samples at f times the largest amplitudes: the smallest multiple of
    BEYOND_CAP within MAX_SAMPLES is the one reported (15: 17,778 samples; 10 would need 40,000), found in at
    most five evaluations; none when even the last multiple is not enough."""
    calls = []

    def trial(pred, inputs, caps, fraction, p):
        calls.append(fraction)
        need = pred / fraction ** 2
        return exm._Trial(inputs, fraction, need, exm.GOAL, True)

    monkeypatch.setattr(exm, "_trial", trial)
    found = exm._beyond_cap(4e6, (0, 1), {0: 0.1, 1: 0.2}, 10)
    assert found.fraction == 15.0 and found.samples == pytest.approx(4e6 / 225)
    expected = min(f for f in exm.BEYOND_CAP if 4e6 / f ** 2 <= exm.MAX_SAMPLES)
    assert found.fraction == expected and len(calls) <= 5
    calls.clear()
    assert exm._beyond_cap(1e9, (0,), {0: 0.1}, 10) is None and len(calls) == 1


def test_a_dither_at_its_cap_is_never_rounded_above_it():
    """Three significant digits rounded to the nearest put an amplitude at the cap (half the input's standard
    deviation, 0.37465) at 0.375, above it; it is rounded down there, to the nearest elsewhere."""
    model = types.SimpleNamespace(inputs=("u1", "u2", "u3"))
    trial = exm._Trial(inputs=(0, 2), fraction=1.0, samples=1000.0, worst=0.2, separated=True)
    assert exm._dither(model, trial, {0: 0.37465, 2: 0.12345}) == {"u1": 0.374, "u3": 0.123}
    half = dataclasses.replace(trial, fraction=0.5)
    assert exm._dither(model, half, {0: 0.37465, 2: 0.2469}) == {"u1": 0.187, "u3": 0.123}
    assert exm._dither(model, trial, {0: 0.37449, 2: 1.0}) == {"u1": 0.374, "u3": 1.0}
    beyond = dataclasses.replace(trial, fraction=2.0)            # a multiple beyond the caps: to the nearest
    assert exm._dither(model, beyond, {0: 0.18733, 2: 1.0}) == {"u1": 0.375, "u3": 2.0}


def test_the_why_quotes_the_dither_as_recommended():
    """At its cap a dither is rounded down (0.185 for a cap of 0.18567); the ``why`` quoted the amplitude rounded to
    the nearest (0.186), so the two disagreed in the third digit."""
    model = types.SimpleNamespace(inputs=("u1", "u2"), columns=("u1", "u2"), outputs=("y1",))
    info = types.SimpleNamespace(noise={}, std=np.array([0.37134, 0.5]))
    trial = exm._Trial(inputs=(0,), fraction=1.0, samples=1000.0, worst=0.2, separated=True)
    caps = {0: 0.18567, 1: 0.25}
    dither = exm._dither(model, trial, caps)
    assert dither == {"u1": 0.185}
    why = exm._why(model, info, trial, dither, [], [(0, 0)], True, [0.3], [(0, 0)], 1000, 0.19, True)
    assert "on u1 (0.185, 0.5 of its standard deviation 0.371)" in why and "0.186" not in why


def test_the_experiment_search_tries_a_bounded_number_of_input_subsets(monkeypatch):
    """A 12-input window where no subset reaches the goal (random logged values: nothing decidable) made the
    design try all 4,095 subsets of the inputs (a minute; 40 inputs never finished).  At most
    MAX_SUBSET_TRIALS subsets are tried now (plus the refinements of the best few), all the inputs at once
    always among them."""
    from mpm_monitor.core.logged_data import LoggedData

    n = 12
    model = PlantModel(sample_time=1.0, inputs=tuple(f"u{k}" for k in range(n)),
                       outputs=tuple(f"y{k}" for k in range(n)), gain=0.1 + 0.9 * np.eye(n),
                       time_constant=np.full((n, n), 5.0), delay=np.ones((n, n)))
    rng = np.random.default_rng(3)
    T = 1200
    data = LoggedData(t=np.arange(T, dtype=float), r=rng.normal(size=(T, n)), u=rng.normal(size=(T, n)),
                      y=rng.normal(size=(T, n)), inputs=model.inputs, outputs=model.outputs, sample_time=1.0)
    tried = []
    real = exm._trial
    monkeypatch.setattr(exm, "_trial", lambda pred, chosen, *a: tried.append(chosen) or real(pred, chosen, *a))
    report = detect(model, data, FAST)
    assert report.experiment is not None and report.experiment.expected_detectable_gain_change > exm.GOAL
    assert tuple(range(n)) in tried
    assert len(tried) <= exm.MAX_SUBSET_TRIALS + exm.REFINED_SUBSETS * len(exm.AMPLITUDE_FRACTIONS)


def test_the_targets_are_views_of_the_rows_moments_divided_in_place():
    # A row's Z' X (the largest of its moments: 353 MiB over 100 rows at 100x40 with 16 own lags) becomes the
    # targets' zx divided in place, no copy: in the detectability's child process the pages stay the parent's.
    from mpm_monitor.core.response_moments import ResponseMoments

    model, u, d, noise = _window()
    L, start = 8, 8
    moments = ResponseMoments(model, u, d, [0, 1, 2], L, start, 2)
    rm = moments.row(0)
    assert rm.zx.flags.c_contiguous
    expected = rm.zx / (u.shape[0] - start)
    before = dict(rm.__dict__)
    info = det.WindowInformation(model, u, d, [0, 1, 2], L, start, noise, {}, moments=moments)
    assert moments.kept(0) is None                              # taken: the window's no longer
    for b, (j, _, _) in enumerate(before["found"]):
        t = info.targets[(0, j)]
        assert np.shares_memory(t.zx, before["zx"])
        np.testing.assert_array_equal(t.zx, expected[..., b].reshape(-1, 3)[:, 1:])
    fresh = det.WindowInformation(model, u, d, [0, 1, 2], L, start, noise, {})   # its own moments, the same numbers
    for key, t in fresh.targets.items():
        np.testing.assert_array_equal(t.zx, info.targets[key].zx)
        np.testing.assert_array_equal(t.c, info.targets[key].c)


def test_read_only_moments_are_copied_not_changed():
    from mpm_monitor.core.response_moments import ResponseMoments

    model, u, d, noise = _window()
    moments = ResponseMoments(model, u, d, [0, 1, 2], 8, 8, 2)
    rm = moments.row(0)
    zx = rm.zx
    zx.flags.writeable = False
    kept = zx.copy()
    info = det.WindowInformation(model, u, d, [0, 1, 2], 8, 8, noise, {}, moments=moments)
    np.testing.assert_array_equal(zx, kept)                     # not divided in place
    fresh = det.WindowInformation(model, u, d, [0, 1, 2], 8, 8, noise, {})
    for key, t in fresh.targets.items():
        np.testing.assert_array_equal(t.zx, info.targets[key].zx)
        assert not np.shares_memory(info.targets[key].zx, zx)
