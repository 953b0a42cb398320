"""What the analysis and the repair compute once instead of again gives the same numbers (issue 15).

- ``compute_signals(..., like=(other model, its signals))`` takes the rows where the models agree from
  the other model's signals and computes the rest: exactly equal to computing every row, and every
  row is computed when the other signals cannot be reused (another initial state, signals from
  elsewhere, another memory of the model).
- ``PlantModel.with_element`` keeps the sampled forms of the other elements.
- The repair's row problem keeps its free responses, unit responses and the row without its located
  elements: its fits equal those of a problem built afresh.
- The model file is parsed by libyaml when present: the same values as the pure-Python parser.

No timings here: bench/perf.py and bench/repair_mc.py measure them.
"""

import dataclasses

import numpy as np
import pytest
import yaml
from scipy import signal as sps

from mpm_monitor.core.discretize import discretize, simulate_elements
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.repair.fit import _ElementSpec, _RowProblem
from mpm_monitor.core.repair.forms import _Form
from mpm_monitor.core.repair.options import RepairOptions
from mpm_monitor.core.repair.row import _estimate_row, _held_row, _RowData
from mpm_monitor.core.signals import LoopSignals, changed_rows, compute_signals
from mpm_monitor.io.model_file import _parse_yaml, dump_model, load_model

KEYS = ("yhat", "d", "eps", "transient")


def _model(ny=3, nu=3, seed=0):
    rng = np.random.default_rng(seed)
    return PlantModel(1.0, [f"u{j + 1}" for j in range(nu)], [f"y{i + 1}" for i in range(ny)],
                      gain=rng.uniform(0.5, 2.0, (ny, nu)), time_constant=rng.uniform(5.0, 20.0, (ny, nu)),
                      delay=rng.integers(0, 4, (ny, nu)).astype(float))


def _record(plant, n=1500, hold=300, seed=1):
    """Inputs held at 3 for ``hold`` samples before the record (a transient to estimate), noisy outputs."""
    rng = np.random.default_rng(seed)
    u = np.vstack([np.full((hold, plant.n_inputs), 3.0),
                   sps.lfilter([1.0], [1.0, -0.7], rng.standard_normal((n, plant.n_inputs)), axis=0)])
    y = simulate_elements(plant, u) + 0.05 * rng.standard_normal((hold + n, plant.n_outputs))
    return np.zeros((n, plant.n_outputs)), u[hold:], y[hold:]


def _equal(a: LoopSignals, b: LoopSignals):
    for key in KEYS:
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)


@pytest.mark.parametrize("change", [
    {"gain": 2.5},                                   # the row's gain
    {"time_constant": 40.0},                         # the row's settling time (the longest of the model)
    {"delay": 6.0},                                  # the model's memory grows: every row is computed
])
def test_signals_reused_on_unchanged_rows_equal_every_row_computed(change):
    model = _model()
    r, u, y = _record(model.with_element(1, 2, gain=1.7))
    sig = compute_signals(model, r, u, y)
    other = model.with_element(1, 2, **change)
    fresh = compute_signals(other, r, u, y)
    assert np.any(fresh.transient != 0)                       # the transient is estimated
    _equal(compute_signals(other, r, u, y, like=(model, sig)), fresh)
    assert changed_rows(other, model) == [1]


def test_signals_of_other_origin_are_not_reused():
    """Signals not computed by compute_signals from the data (or with another initial state) are never
    taken as they are: every row is computed."""
    model = _model()
    r, u, y = _record(model)
    other = model.with_element(0, 0, gain=3.0)
    fresh = compute_signals(other, r, u, y)
    garbage = LoopSignals(*(np.full_like(y, 7.0) for _ in KEYS))
    _equal(compute_signals(other, r, u, y, like=(model, garbage)), fresh)
    zero = compute_signals(model, r, u, y, initial_state="zero")
    _equal(compute_signals(other, r, u, y, like=(model, zero)), fresh)
    # The same signals marked as computed from the data are reused on the unchanged rows.
    marked = LoopSignals(*(np.full_like(y, 7.0) for _ in KEYS), initial_state="estimate")
    mixed = compute_signals(other, r, u, y, like=(model, marked))
    np.testing.assert_array_equal(mixed.d[:, 0], fresh.d[:, 0])
    assert np.all(mixed.d[:, 1:] == 7.0)


def test_changed_rows_of_step_response_models():
    sr = np.cumsum(np.random.default_rng(3).uniform(0.0, 0.2, (2, 2, 30)), axis=2)
    model = PlantModel.from_step_response(1.0, ["u1", "u2"], ["y1", "y2"], sr)
    assert changed_rows(model, model) == []
    assert changed_rows(model.with_element(1, 0, step_response=2 * sr[1, 0]), model) == [1]


def test_with_element_keeps_the_sampled_forms_of_the_other_elements():
    model = _model()
    disc = discretize(model)
    other = model.with_element(0, 1, gain=5.0, delay=2.0)
    for i in range(3):
        for j in range(3):
            if (i, j) != (0, 1):
                assert other.discrete_element(i, j) is disc.elements[i][j]
    ref = discretize(PlantModel(1.0, model.inputs, model.outputs, gain=other.gain,
                                time_constant=other.time_constant, delay=other.delay))
    new = discretize(other)
    assert new.elements[0][1] is not disc.elements[0][1]
    np.testing.assert_array_equal(new.input_lag, ref.input_lag)
    for i in range(3):
        for j in range(3):
            np.testing.assert_array_equal(new.numerators[i][j], ref.numerators[i][j])
            np.testing.assert_array_equal(new.denominators[i][j], ref.denominators[i][j])


def _row(seed=4):
    plant = _model(2, 3, seed)
    model = plant.with_element(0, 1, gain=plant.gain[0, 1] * 1.4)
    r, u, y = _record(plant, n=2000, hold=0, seed=seed)
    return _RowData(model=model, u=u, y=y, i=0)


def _spec(row, j, form=_Form()):
    lag = int(row.model.delay_samples[0, j]) + 1
    pole = float(np.exp(-1.0 / row.model.time_constant[0, j]))
    return _ElementSpec(gain_free=True, pole_free=True, gain=float(row.model.gain[0, j]),
                        poles=(pole,) * form.n_lags, window=(max(lag - 2, 1), lag + 2), form=form)


@pytest.mark.parametrize("form", [_Form(), _Form(n_lags=2, lead=True)])
def test_row_fits_with_kept_responses_equal_fits_from_scratch(form):
    """Two rows estimated one after the other share the row's kept arrays: the second's numbers equal
    those of the same estimate on a fresh row (nothing kept)."""
    row = _row()
    options = RepairOptions(noise_order=2)
    specs = {1: _spec(row, 1, form)}
    lags0 = {1: specs[1].window[0] + 2}
    _estimate_row(row, {1: _spec(row, 1), 2: _spec(row, 2)}, {1: lags0[1], 2: 2}, 2000, options)
    assert row.shared                                            # free responses and held rows kept
    kept_problem, kept = _estimate_row(row, specs, lags0, 2000, options)
    fresh_row = _RowData(model=row.model, u=row.u, y=row.y, i=0)
    fresh_problem, fresh = _estimate_row(fresh_row, specs, lags0, 2000, options)
    assert kept.fit.lags == fresh.fit.lags
    for key in ("poles", "coefs", "gains", "leads", "nuisance"):
        np.testing.assert_array_equal(getattr(kept.fit, key), getattr(fresh.fit, key), err_msg=key)
    assert kept.fit.ssr == fresh.fit.ssr
    np.testing.assert_array_equal(kept.cov, fresh.cov)
    np.testing.assert_array_equal(kept.ar, fresh.ar)
    assert kept.profiles == fresh.profiles


@pytest.mark.parametrize("form", [_Form(), _Form(n_lags=2, lead=True)])
def test_the_kept_free_responses_are_bounded_and_the_fits_the_same(monkeypatch, form):
    """The free responses a row's fits keep take at most POWER_CACHE_BYTES (at least POWER_CACHE_MIN of them, the
    least recently used dropped: every solver evaluation tries new poles, and on a record of 100,000 samples the
    unbounded store grew past 6 GB); with room for only two, the fits are those with room for all."""
    from mpm_monitor.core.repair import fit as fit_module

    options = RepairOptions(noise_order=2)

    def estimate():
        row = _row()
        specs = {1: _spec(row, 1, form), 2: _spec(row, 2)}
        lags = {1: specs[1].window[0] + 2, 2: 2}
        return row, _estimate_row(row, specs, lags, 2000, options)[1]

    row, roomy = estimate()
    kept = [len(v) for k, v in row.shared.items() if isinstance(k, tuple) and k[0] == "powers"]
    assert kept and max(kept) > 2
    monkeypatch.setattr(fit_module, "POWER_CACHE_BYTES", 0)
    monkeypatch.setattr(fit_module, "POWER_CACHE_MIN", 2)
    row, tight = estimate()
    kept = [len(v) for k, v in row.shared.items() if isinstance(k, tuple) and k[0] == "powers"]
    assert kept and max(kept) == 2
    assert tight.fit.lags == roomy.fit.lags
    for key in ("poles", "coefs", "gains", "leads", "nuisance"):
        np.testing.assert_array_equal(getattr(tight.fit, key), getattr(roomy.fit, key), err_msg=key)
    assert tight.fit.ssr == roomy.fit.ssr
    np.testing.assert_array_equal(tight.cov, roomy.cov)


def test_unit_responses_follow_the_noise_model():
    """A unit response kept under one noise model is not used under another."""
    row = _row()
    spec = _spec(row, 1)
    z = _held_row(row, (1,)).z
    lags = [spec.window[0] + 1]
    problem = _RowProblem(z, row.u[:, [1]], [spec], 2000, 8, {}, True, 2, shared={})
    poles = problem.start_poles()
    problem.evaluate(poles, lags)                              # kept under A = 1
    problem.set_ar([-0.5, 0.1])
    fresh = _RowProblem(z, row.u[:, [1]], [spec], 2000, 8, {}, True, 2)
    fresh.set_ar([-0.5, 0.1])
    a, b = problem.evaluate(poles, lags), fresh.evaluate(poles, lags)
    assert a.ssr == b.ssr
    np.testing.assert_array_equal(a.coefs, b.coefs)


def _whole_design(problem, poles, lags):
    """The residual and coefficients of the design solved as one (the original formula)."""
    known, phi = problem._design(poles, lags)
    target = problem._cost(problem.zf) - known
    beta = problem._solve(phi, target)
    return target - phi @ beta, beta


@pytest.mark.parametrize("case", ["plain", "fixed_poles", "extra", "segments", "lead_form"])
def test_projection_with_the_constant_columns_kept_equals_the_whole_design(case):
    """The fit's cost with the cross products of the constant columns kept once per noise model equals
    the design solved as one: the same residual and the same coefficients (well-determined problems)."""
    row = _row()
    form = _Form(n_lags=2, lead=True) if case == "lead_form" else _Form()
    spec = _spec(row, 1, form)
    z = _held_row(row, (1,)).z
    kwargs = {}
    fixed = {0.8: 1, 0.6: 1} if case == "fixed_poles" else {}
    if case == "extra":
        kwargs["extra"] = np.column_stack([(np.arange(2000) >= 900).astype(float), np.arange(2000) / 2000.0])
    if case == "segments":
        kwargs["segments"] = [(0, 1100), (1100, 2000)]
    problem = _RowProblem(z, row.u[:, [1]], [spec], 2000, 8, fixed, True, 2, **kwargs)
    lags = [spec.window[0] + 1]
    for ar in ([0.0, 0.0], [-0.5, 0.1]):
        problem.set_ar(ar)
        for scale in (1.0, 0.97):
            poles = np.clip(problem.start_poles() * scale, 0.0, 0.999)
            resid, beta = problem.projected(poles, lags)
            ref_resid, ref_beta = _whole_design(problem, poles, lags)
            np.testing.assert_allclose(resid, ref_resid, rtol=0, atol=1e-9 * np.abs(ref_resid).max())
            np.testing.assert_allclose(beta, ref_beta, rtol=1e-7, atol=1e-9 * np.abs(ref_beta).max())


@pytest.mark.parametrize("case", ["plain", "extra", "segments"])
def test_reused_buffers_and_nuisance_columns_give_the_numbers_of_fresh_ones(case):
    """The fit's moving columns are written into a buffer kept for the next evaluation, and the covariance's
    finite differences share one nuisance matrix across their noise models when none of its columns depends
    on it: the same numbers, bit for bit, as fresh arrays."""
    row = _row()
    spec = _spec(row, 1)
    z = _held_row(row, (1,)).z
    kwargs = {}
    if case == "extra":
        kwargs["extra"] = np.column_stack([(np.arange(2000) >= 900).astype(float), np.arange(2000) / 2000.0])
    if case == "segments":
        kwargs["segments"] = [(0, 1100), (1100, 2000)]
    problem = _RowProblem(z, row.u[:, [1]], [spec], 2000, 8, {0.8: 1}, True, 2, **kwargs)
    lags = [spec.window[0] + 1]
    poles = problem.start_poles()
    problem.projected(np.clip(poles * 0.9, 0.0, 0.999), [spec.window[0]])    # the buffer holds other columns
    resid, beta = problem.projected(poles, lags)
    fresh = _RowProblem(z, row.u[:, [1]], [spec], 2000, 8, {0.8: 1}, True, 2, **kwargs)
    fresh_resid, fresh_beta = fresh.projected(poles, lags)
    assert resid.tobytes() == fresh_resid.tobytes() and beta.tobytes() == fresh_beta.tobytes()
    problem.set_ar([-0.5, 0.1])
    fit = problem.evaluate(poles, lags)
    theta = np.concatenate([fit.coefs, fit.poles[problem.pole_free_idx], problem.ar, fit.nuisance])
    memo = {}
    for k in range(theta.size):
        for step in (1e-6, -1e-6):
            moved = theta.copy()
            moved[k] += step
            shared = problem.full_residual(moved, fit.lags, memo)
            assert shared.tobytes() == problem.full_residual(moved, fit.lags).tobytes(), k


def test_held_row_is_the_output_minus_the_other_elements():
    row = _row()
    held = _held_row(row, (1,))
    assert _held_row(row, (1,)) is held
    without = row.model.with_element(0, 1, gain=0.0)
    np.testing.assert_array_equal(held.z, row.y[:, 0] - simulate_elements(without, row.u, rows=[0])[:, 0])
    assert held.lag_poles == discretize(without).lag_poles(0)


def test_model_file_values_equal_the_pure_python_parser(tmp_path):
    model = _model(4, 3, seed=8).with_element(2, 1, time_constant2=3.0, lead=1.5)
    text = dump_model(model)
    assert _parse_yaml(text) == yaml.safe_load(text)
    path = tmp_path / "m.yaml"
    path.write_text(text, encoding="utf-8")
    assert load_model(path) == model


def _loop(seed=2):
    from mpm_monitor.sim.closed_loop import run_closed_loop

    plant = _model(4, 4, seed)
    model = plant.with_element(0, 1, gain=plant.gain[0, 1] * 1.3)
    return plant, model, run_closed_loop(plant, model, 3000, seed=seed).as_logged_data()


def _repaired_loop():
    """``(data, options, first, repaired, sig)``: :func:`_loop`'s detection, its model with (y1, u2) repaired
    and the repaired model's signals (its row y1 changed only)."""
    from mpm_monitor.core.analysis import AnalysisOptions, detect

    plant, model, data = _loop()
    options = AnalysisOptions(repair=False, test_all_rows=False)
    first = detect(model, data, options)
    repaired = model.with_element(0, 1, gain=plant.gain[0, 1])
    sig = compute_signals(repaired, data.r, data.u, data.y, like=(model, first.signals))
    return data, options, first, repaired, sig


def test_detection_after_a_repair_reuses_the_unchanged_rows_and_gives_the_same_report():
    from mpm_monitor.core.analysis import detect

    data, options, first, repaired, sig = _repaired_loop()
    fresh = detect(repaired, data, options, signals=sig)
    reused = detect(repaired, data, options, signals=sig, previous=first)
    assert reused.to_dict() == fresh.to_dict()
    # To rounding: the reused rows' products are the first detection's, the fresh ones are taken over a
    # Gram of other width, and some BLAS kernels (OpenBLAS's Zen) then move the last bit.
    for key in ("row_gains", "sigma_max", "sdelta_response"):
        np.testing.assert_allclose(getattr(reused, key), getattr(fresh, key), rtol=1e-12, atol=0)
    # The setpoint block and the fits of rows y2..y4 are the first detection's own objects; y1's is new.
    regs, prev = reused.regressions, first.regressions
    assert list(regs._row_regs.values()) == list(prev._row_regs.values())
    (reg,) = prev._row_regs.values()
    assert {i for (_, i) in regs._row_fits} == {0}
    assert regs.row_fit(reg, 2) is prev.row_fit(reg, 2)
    assert regs.row_fit(reg, 0) is not prev.row_fit(reg, 0)


def test_row_fits_are_not_reused_across_other_setpoints():
    from mpm_monitor.core.analysis import AnalysisOptions, detect

    _, model, data = _loop()
    options = AnalysisOptions(repair=False)
    first = detect(model, data, options)
    shifted = dataclasses.replace(data, r=data.r + 1e-3 * np.arange(data.n_samples)[:, None] % 2)
    again = detect(model, shifted, options, previous=first)
    assert again.to_dict() == detect(model, shifted, options).to_dict()
    assert not again.regressions._same_rows and again.regressions._previous is None


def test_after_a_repair_the_row_gram_holds_the_rows_to_fit_only_and_gives_their_fits_to_rounding():
    from mpm_monitor.core.regressions import regression_layout, window_regressions

    data, options, first, repaired, sig = _repaired_loop()
    layout = regression_layout(repaired, options)
    z = sig.eps - data.r
    full = window_regressions(data.r, data.u, z, sig.d, layout, options.na, options.nb)
    reduced = window_regressions(data.r, data.u, z, sig.d, layout, options.na, options.nb, previous=first.regressions)
    assert full.row_z is None and reduced.row_z == (0,)
    assert reduced.row_gram.n_columns == full.row_gram.n_columns - 3 * (options.na + 1)
    (reg,) = first.regressions._row_regs.values()
    a, b = reduced.row_fit(reg, 0), full.row_fit(reg, 0)
    # The reduced Gram's products are taken over fewer columns: equal to rounding (bit for bit with some
    # BLAS kernels, not with OpenBLAS's Zen kernels).
    np.testing.assert_allclose(a.theta, b.theta, rtol=1e-10, atol=1e-12 * np.max(np.abs(b.theta)))
    assert a.rss == pytest.approx(b.rss, rel=1e-12)
    # A row the reduced Gram lacks, asked for: the Gram of every z is built, and the fit is the full one's.
    reduced._same_rows = frozenset()
    c = reduced.row_fit(reg, 2)
    assert reduced.row_z is None and reduced.row_gram.n_columns == full.row_gram.n_columns
    np.testing.assert_array_equal(c.theta, full.row_fit(reg, 2).theta)
