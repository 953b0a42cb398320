"""The repair's delay search reaches a plant's dead time far from the model's.

The repair searches a located element's delay within ``max_delay_shift`` samples of the model's.  A plant
whose dead time is far shorter than the model's (model 20 s, plant 2 s) was repaired at the model's delay
with the gain cut to a twenty-fifth, marked applied.  The element test sees the mismatch ``Delta`` act first at
the plant's lag; given that estimate (``delays``), the search reaches it.  A best lag at the end of the range,
or the fit's residual correlated with the input at a lag beyond it, widens the range too.
"""

import dataclasses

import pytest

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.errors import InputError
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.repair import RepairOptions, repair_model
from mpm_monitor.sim.cases import shell_plant
from mpm_monitor.sim.closed_loop import run_closed_loop

def _far_delay():
    """The Shell plant with (y2, u2) acting after 2 s and at gain 1.5 x the model's; the model says 20 s."""
    sh = shell_plant()
    plant = sh.with_element(1, 1, delay=2.0, gain=1.5 * float(sh.gain[1, 1]))
    model = sh.with_element(1, 1, delay=20.0)
    data = run_closed_loop(plant, model, 3000, seed=5).as_logged_data()
    return sh, plant, model, data

def test_a_delay_far_below_the_models_is_found_with_the_element_tests_estimate():
    from mpm_monitor.core.discretize import model_columns
    from mpm_monitor.core.repair.classify import _free_spec, _locate
    from mpm_monitor.core.repair.row import _RowData

    sh, plant, model, data = _far_delay()
    # The range searched: 10 samples either side of the model's input lag (21), reaching the estimate's 3.
    row = _RowData(model=model, u=model_columns(data.u, data.dv), y=data.y, i=1)
    assert _free_spec(row, _locate(row, 1), RepairOptions())[0].window == (11, 31)
    row = dataclasses.replace(row, delays={1: 3})
    assert _free_spec(row, _locate(row, 1), RepairOptions())[0].window == (1, 31)
    for delays in ({(1, 1): 3}, None):      # without the estimate, the residual's correlation with u2 finds it
        res = repair_model(model, data, [(1, 1)], delays=delays)
        assert res.model.delay[1, 1] == pytest.approx(2.0, abs=1.0)
        assert res.model.gain[1, 1] == pytest.approx(plant.gain[1, 1], rel=0.1)
        assert res.kinds[(1, 1)] == "mixed"
        assert res.error_after["y2"] < 0.1 * res.error_before["y2"]
        # Only the located element moves.
        for i in range(3):
            for j in range(3):
                if (i, j) != (1, 1):
                    assert res.model.element(i, j) == model.element(i, j)


def test_the_analysis_passes_its_delays_to_the_repair():
    _, plant, model, data = _far_delay()
    rep = analyze(model, data, AnalysisOptions())
    (el,) = [e for e in rep.elements if e.mismatch and (e.output, e.input) == ("y2", "u2")]
    assert abs(el.delay - 3) <= 2
    (change,) = [c for c in rep.repair["changes"] if (c["output"], c["input"]) == ("y2", "u2")]
    assert change["after"]["delay"] == pytest.approx(2.0, abs=1.0)
    assert change["applied"]

def test_no_hint_or_a_hint_inside_the_range_changes_nothing():
    sh = shell_plant()
    model = sh.with_element(1, 1, gain=1.5 * float(sh.gain[1, 1]))
    data = run_closed_loop(sh, model, 2000, seed=3).as_logged_data()
    base = repair_model(model, data, [(1, 1)])
    lag = int(model.delay_samples[1, 1]) + 1
    same = repair_model(model, data, [(1, 1)], delays={(1, 1): lag + 4, (0, 0): 40})   # (0, 0) is not located
    assert same.model == base.model and same.changes == base.changes
    # max_delay_shift 0 keeps the delay whatever the estimate.
    held = repair_model(model, data, [(1, 1)], RepairOptions(max_delay_shift=0), delays={(1, 1): 40})
    assert held.model.delay[1, 1] == model.delay[1, 1]

@pytest.mark.parametrize("delays, match", [
    ([((1, 1), 3)], "expected a mapping"),
    ({(1, 1): -1}, r"delays\[\(1, 1\)\]: expected an integer number of samples >= 0"),
    ({(1, 1): 2.5}, "expected an integer"),
    ({(1, 1): True}, "expected an integer"),
    ({"a": 3}, "expected a pair"),
])
def test_bad_delays_are_refused_in_one_line(delays, match):
    sh = shell_plant()
    data = run_closed_loop(sh, sh, 400, seed=1).as_logged_data()
    with pytest.raises(InputError, match=match) as err:
        repair_model(sh, data, [(1, 1)], delays=delays)
    assert "\n" not in str(err.value)


def _free_problem(model, data, i, j):
    """The free fit of element (i, j) alone, as the repair's classification starts it."""
    from mpm_monitor.core.discretize import model_columns
    from mpm_monitor.core.repair.classify import _free_spec, _locate
    from mpm_monitor.core.repair.row import _estimate_row, _RowData

    options = RepairOptions()
    row = _RowData(model=model, u=model_columns(data.u, data.dv), y=data.y, i=i)
    spec, lag0 = _free_spec(row, _locate(row, j), options)
    return _estimate_row(row, {j: spec}, {j: lag0}, data.n_samples, options, options.max_sweeps)


def test_the_residuals_correlation_with_the_input_is_normal_where_the_fit_holds_and_peaks_where_the_input_acts():
    import math

    import numpy as np

    sh = shell_plant()
    model = sh.with_element(1, 1, gain=1.5 * float(sh.gain[1, 1]))
    data = run_closed_loop(sh, model, 3000, seed=4).as_logged_data()
    problem, est = _free_problem(model, data, 1, 1)
    z = problem.input_correlation(est.fit, 0, 60)
    # The same numbers written out: the residual against the prefiltered input tau samples before it.
    resid, _ = problem.projected(est.fit.poles, est.fit.lags)
    k = np.arange(problem.start, problem.n_fit)
    for tau in (1, 17, 60):
        ok = k - tau >= 0                # only inputs inside the record
        e, v = resid[ok], problem.uf[k[ok] - tau, 0]
        assert z[tau - 1] == pytest.approx(math.sqrt(len(e)) * abs(e @ v) / math.sqrt((e @ e) * (v @ v)), rel=1e-12)
    # The fit holds the plant: about N(0, 1) at every lag (a mean square near 1, nothing beyond 4.5).
    assert 0.3 < float(np.mean(z ** 2)) < 3.0 and z.max() < 4.5
    # A plant whose (y2, u2) acts 22 samples later than the model says: the fit within the model's range
    # leaves the input's effect in the residual, largest near the plant's input lag (26).
    late = sh.with_element(1, 1, delay=25.0)
    data = run_closed_loop(late, sh, 3000, seed=4).as_logged_data()
    problem, est = _free_problem(sh, data, 1, 1)
    assert est.fit.lags[0] <= 14                        # the range searched: input lags 1 to 14
    z = problem.input_correlation(est.fit, 0, 60)
    assert abs(int(np.argmax(z)) + 1 - 26) <= 3 and z.max() > 6.0


def test_a_delay_far_beyond_the_models_is_found():
    """(y2, u2) acting 22 samples later than the model's 3 s: outside the range searched at first."""
    sh = shell_plant()
    late = sh.with_element(1, 1, delay=25.0)
    data = run_closed_loop(late, sh, 3000, seed=4).as_logged_data()
    res = repair_model(sh, data, [(1, 1)])
    assert res.model.delay[1, 1] == pytest.approx(25.0, abs=1.0)
    assert res.kinds[(1, 1)] == "delay" and res.changes[0]["applied"]
    assert not [w for w in res.warnings if "edge of the searched range" in w]


def test_the_refits_in_another_form_keep_the_widened_range():
    """An element the model lacks, whose plant acts 40 s after its input: first order at first, the two-lag
    form is tried against it by a refit, which keeps the range the free fit had to widen."""
    from mpm_monitor.core.discretize import model_columns
    from mpm_monitor.core.repair.classify import _fit_free, _locate, _refit_element
    from mpm_monitor.core.repair.forms import _missing_ladder
    from mpm_monitor.core.repair.options import _TestSettings
    from mpm_monitor.core.repair.row import _RowData

    sh = shell_plant()
    plant = sh.with_element(0, 1, delay=40.0)
    model = sh.with_element(0, 1, gain=0, time_constant=0, delay=0)
    data = run_closed_loop(plant, model, 3000, seed=2).as_logged_data()
    row = _RowData(model=model, u=model_columns(data.u, data.dv), y=data.y, i=0)
    settings = _TestSettings.of(RepairOptions())
    free = _fit_free(row, [1], settings)
    (lo, hi), = free.widened.values()
    assert lo <= 41 <= hi and hi > 7 + 1 + 10           # beyond the row's longest input lag plus 10
    assert abs(free.est.fit.lags[0] - 41) <= 1
    larger = _refit_element(free, 1, _locate(row, 1, _missing_ladder(model, 0)[1]), None, settings)
    assert larger.specs[1].window[0] <= 41 <= larger.specs[1].window[1] and larger.widened == free.widened
    res = repair_model(model, data, [(0, 1)])
    assert res.kinds[(0, 1)] == "missing" and res.model.delay[0, 1] == pytest.approx(40.0, abs=1.0)
