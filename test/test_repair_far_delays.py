"""The repair's delay search reaches the element test's estimate of where a mismatch acts.

The repair searches a located element's delay within ``max_delay_shift`` samples of the model's.  A plant
whose dead time is far shorter than the model's (model 20 s, plant 2 s) was repaired at the model's delay
with the gain cut to a twenty-fifth, marked applied.  The element test sees the mismatch ``Delta`` act first at
the plant's lag; given that estimate (``delays``), the search reaches it.
"""

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
    sh, plant, model, data = _far_delay()
    without = repair_model(model, data, [(1, 1)])
    # Within the model's range (10 to 30 s) the fit cannot reach the plant's 2 s: the gain is bent instead.
    assert without.model.delay[1, 1] >= 10.0
    with_hint = repair_model(model, data, [(1, 1)], delays={(1, 1): 3})
    assert with_hint.model.delay[1, 1] == pytest.approx(2.0, abs=1.0)
    assert with_hint.model.gain[1, 1] == pytest.approx(plant.gain[1, 1], rel=0.1)
    assert with_hint.kinds[(1, 1)] == "mixed"
    assert with_hint.error_after["y2"] < 0.5 * without.error_after["y2"]
    # Only the located element moves.
    for i in range(3):
        for j in range(3):
            if (i, j) != (1, 1):
                assert with_hint.model.element(i, j) == model.element(i, j)

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
