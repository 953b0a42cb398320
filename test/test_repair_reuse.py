"""What the repair computes once instead of again gives the same numbers.

- The disturbance test of an output whose prediction error an earlier evaluation of the repair
  tested as it is (a row not repaired, or not repaired again) is taken over: the tests equal those
  of every output tested afresh, and only the changed outputs are tested again.
- The disturbance tests of the model as given, computed ahead (``disturbance_tests``, which ``analyze``
  computes in its second process while that one is idle), are taken by the repair for the outputs it
  does not repair: the same result; ignored when taken with other settings.
- The step test's quadratic forms of the cumulative regressors equal ``np.einsum`` term by term.
- A row estimate's covariance is computed when first read, its condition number alone from the
  Jacobian columns of the free parameters: the same numbers as the whole covariance's.
- A pole fit takes its solution's cost and linear parameters from the solver's evaluation there:
  the same as evaluating the solution again.
- The intervals of the repair fit on the first part of the record are taken only when the refit on
  the whole record does not replace them: every reported number equals taking them at once.

No timings here: bench/stages.py and bench/repair_mc.py measure them.
"""

import dataclasses
import json

import numpy as np
import pytest

from mpm_monitor.core.repair import (RepairOptions, disturbance_tests, model_repair, repair_model, residual_tests,
                                     unexplained_disturbance)
from mpm_monitor.core.signals import compute_signals
from mpm_monitor.core.repair import refit as repair_refit
from mpm_monitor.core.repair.disturbance import _row_quadratic_forms
from mpm_monitor.core.repair.fit import _ElementSpec, _RowProblem
from mpm_monitor.core.repair.forms import _Form
from mpm_monitor.core.repair.row import _estimate_row, _RowData
from mpm_monitor.sim.cases import shell_plant
from mpm_monitor.sim.closed_loop import run_closed_loop

N_SAMPLES = 4000


@pytest.fixture(scope="module")
def stepped_gain_log():
    """A gain error on y2/u2 and an unmeasured step on y2: the repair redoes row y2 with the step."""
    sh = shell_plant()
    model = sh.with_element(1, 1, gain=4.0)
    step = np.zeros((N_SAMPLES, 3))
    step[N_SAMPLES // 2:, 1] = 0.1
    return model, run_closed_loop(sh, model, N_SAMPLES, seed=11, output_disturbance=step).as_logged_data()


def test_disturbance_tests_of_unchanged_outputs_are_taken_over(stepped_gain_log, monkeypatch):
    model, data = stepped_gain_log
    calls = []

    confirmed = []

    def counted(d, *args, **kwargs):
        (confirmed if kwargs.get("calibrate") else calls).append(np.array(d, copy=True))
        return unexplained_disturbance(d, *args, **kwargs)

    monkeypatch.setattr(residual_tests, "unexplained_disturbance", counted)
    res = repair_model(model, data, [(1, 1)])
    assert any("allowed for the unexplained step" in w for w in res.warnings)      # two evaluations
    # Every output once, then the redone row only; the step each evaluation reports confirmed once.
    assert len(calls) == model.n_outputs + 1
    np.testing.assert_array_equal(calls[-1], res.signals.d[:, 1])
    assert len(confirmed) == 2
    np.testing.assert_array_equal(confirmed[-1], res.signals.d[:, 1])
    opts = res.options
    spread = np.std(np.asarray(data.y, float), axis=0)

    def fresh_test(i, calibrate=False):
        return unexplained_disturbance(res.signals.d[:, i], model.sample_time, opts.disturbance_alpha,
                                       opts.disturbance_trim, opts.noise_order, scale=float(spread[i]),
                                       calibrate=calibrate, draws=opts.disturbance_draws,
                                       rng=np.random.default_rng(opts.disturbance_seed))

    fresh = {i: fresh_test(i) for i in range(model.n_outputs)}
    residual_tests._one_family(fresh, opts.disturbance_alpha)             # the outputs' tests as one family
    fresh = {i: fresh_test(i, calibrate=t["detected"]) for i, t in fresh.items()}      # the reported confirmed
    residual_tests._one_family(fresh, opts.disturbance_alpha)
    expected = [{"output": model.outputs[i], "kind": t["kind"], "size": t["size"], "time": t["time"],
                 "rate": t["rate"], "p_value": t["p_value"], "p_value_raw": t["p_value_raw"],
                 "statistic": t["statistic"],
                 "null_scale": t["null_scale_step" if t["kind"] == "step" else "null_scale_drift"]}
                for i, t in fresh.items() if t["detected"]]
    assert res.disturbances == expected
    assert [d["output"] for d in res.disturbances] == ["y2"]


def _counted(monkeypatch) -> list:
    """The prediction errors the repair tests (the confirmations of a reported disturbance not counted)."""
    calls = []

    def counted(d, *args, **kwargs):
        if not kwargs.get("calibrate"):
            calls.append(np.array(d, copy=True))
        return unexplained_disturbance(d, *args, **kwargs)

    monkeypatch.setattr(residual_tests, "unexplained_disturbance", counted)
    return calls


@pytest.mark.parametrize("settings", ["same", "other level", "other scale"])
def test_disturbance_tests_computed_ahead_are_taken_for_the_outputs_not_repaired(stepped_gain_log, monkeypatch,
                                                                               settings):
    model, data = stepped_gain_log
    options = RepairOptions()
    plain = repair_model(model, data, [(1, 1)], options)
    sig = compute_signals(model, data.r, data.u, data.y, initial_state=options.initial_state)
    ahead = disturbance_tests(model, data, sig.d, options if settings != "other level" else
                              dataclasses.replace(options, disturbance_alpha=0.05))
    assert len(ahead.tests) == model.n_outputs
    if settings == "other scale":
        ahead.spread = ahead.spread * 2.0
    calls = _counted(monkeypatch)
    res = repair_model(model, data, [(1, 1)], options, disturbance_tests=ahead)
    assert json.dumps(res.to_dict(), sort_keys=True) == json.dumps(plain.to_dict(), sort_keys=True)
    assert res.disturbances == plain.disturbances and [d["output"] for d in res.disturbances] == ["y2"]
    # Row y2 is repaired, then redone with the step: with the tests given only its two tests run here.
    if settings == "same":
        assert len(calls) == 2 and not any(np.array_equal(c, sig.d[:, 1]) for c in calls)
    else:
        assert len(calls) == model.n_outputs + 1


@pytest.mark.parametrize("n, k", [(1, 1), (60, 5), (9000, 5), (20000, 7), (3000, 23)])
def test_row_quadratic_forms_equal_einsum(n, k):
    rng = np.random.default_rng(n + k)
    x = rng.standard_normal((n, k)) * 10.0 ** rng.uniform(-3, 3, k)
    x[:, 0] = 1.0
    q = np.cumsum(x[::-1], axis=0)[::-1]                 # as the step test builds it: a reversed view
    a = np.linalg.pinv(x.T @ x)
    np.testing.assert_array_equal(_row_quadratic_forms(q, a), np.einsum("ij,jk,ik->i", q, a, q))


@pytest.fixture(scope="module")
def gain_log():
    """A gain error on y2/u2 of the Shell loop."""
    sh = shell_plant()
    model = sh.with_element(1, 1, gain=4.0)
    return model, run_closed_loop(sh, model, 2500, seed=4).as_logged_data()


@pytest.mark.parametrize("gain_free, pole_free, form", [
    (True, False, _Form()),
    (False, True, _Form()),
    (True, True, _Form()),
    (True, True, _Form(n_lags=2, lead=True)),
])
def test_condition_alone_equals_the_covariance_one(gain_log, gain_free, pole_free, form):
    model, data = gain_log
    row = _RowData(model=model, u=np.asarray(data.u, float), y=np.asarray(data.y, float), i=1)
    lag = int(model.delay_samples[1, 1]) + 1
    pole = float(np.exp(-model.sample_time / model.time_constant[1, 1]))
    spec = _ElementSpec(gain_free, pole_free, 5.0, (pole,) * form.n_lags, (lag - 1, lag + 1), form=form)
    problem, est = _estimate_row(row, {1: spec}, {1: lag}, 2000, RepairOptions())
    assert est._cov is None                          # nothing computed before it is read
    cond = est.cond
    assert est._cov is None
    cov, cond_all = problem.covariance(est.fit)
    assert cond == cond_all
    np.testing.assert_array_equal(est.cov, cov)


@pytest.mark.parametrize("options", [RepairOptions(), RepairOptions(refit_on_all=False),
                                     RepairOptions(min_holdout_improvement=0.95)],
                         ids=["refit", "no refit", "rejected"])
def test_repair_intervals_taken_when_reported_equal_taken_at_once(gain_log, monkeypatch, options):
    model, data = gain_log
    covariances = []
    original_cov = _RowProblem.covariance

    def counted(self, fit):
        covariances.append(fit)
        return original_cov(self, fit)

    monkeypatch.setattr(_RowProblem, "covariance", counted)
    late = repair_model(model, data, [(1, 1)], options)
    # The classification's and, without the refit, the repair fit's; with it the refit's instead.
    assert len(covariances) == 2
    original_fit = repair_refit._fit_repair

    def at_once(free, verdicts, n_fit, settings):
        fit = original_fit(free, verdicts, n_fit, settings)
        if fit is not None:
            fit.put_intervals(verdicts, settings)
        return fit

    monkeypatch.setattr(model_repair, "_fit_repair", at_once)
    eager = repair_model(model, data, [(1, 1)], options)
    assert late.changes == eager.changes
    assert late.model == eager.model
    assert dataclasses.asdict(late.options) == dataclasses.asdict(eager.options)


@pytest.mark.parametrize("form", [_Form(), _Form(n_lags=2, lead=True)])
def test_pole_fit_takes_the_solution_from_the_solver_evaluations(gain_log, monkeypatch, form):
    model, data = gain_log
    row = _RowData(model=model, u=np.asarray(data.u, float), y=np.asarray(data.y, float), i=1)
    lag = int(model.delay_samples[1, 1]) + 1
    pole = float(np.exp(-model.sample_time / model.time_constant[1, 1]))
    spec = _ElementSpec(True, True, 5.0, (pole, 0.5 * pole)[:form.n_lags], (lag, lag), form=form)
    problem, _ = _estimate_row(row, {1: spec}, {1: lag}, 2000, RepairOptions())
    evaluated = []
    original = _RowProblem.evaluate
    monkeypatch.setattr(_RowProblem, "evaluate", lambda self, *a: evaluated.append(a) or original(self, *a))
    got = problem.fit([lag], problem.start_poles())
    assert not evaluated                             # the solution was among the last evaluations
    again = original(problem, got.poles, [lag])
    assert (got.ssr, got.n_resid, got.lags) == (again.ssr, again.n_resid, again.lags)
    for key in ("poles", "coefs", "gains", "leads", "nuisance"):
        np.testing.assert_array_equal(getattr(got, key), getattr(again, key), err_msg=key)
