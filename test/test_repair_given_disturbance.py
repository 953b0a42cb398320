"""A repair that would take up an unexplained drift: the row is re-estimated with the drift as a nuisance.

On bench.perf's 20x20 loop (the gain of (y1, u2) 30 % off in the model) with a slow drift on every output,
the controller ramps its inputs against the drifts; fitted on its own, the located element became a slow
element of a large gain (-10.9 against the plant's -0.577) that ramps with u2 and so explains y1's drift, and
the repaired residual showed no drift left to allow for.  The drift is in the prediction error of the model
as given, so the row is processed again with it as a nuisance regressor, as when the repaired residual keeps it.
"""

import numpy as np

from bench.perf import industrial_case
from mpm_monitor.core.repair import RepairOptions, repair_model
from mpm_monitor.sim.closed_loop import run_closed_loop


def drifting_loop(samples: int = 10000):
    plant, model, clean = industrial_case(20, 20, samples, 0, mismatches=1)
    size = np.std(np.asarray(clean.y), axis=0)
    signs = np.random.default_rng(100).choice([-1, 1], 20)
    drifts = np.outer(np.arange(samples) / samples, size * signs)      # one standard deviation over the log
    return plant, model, run_closed_loop(plant, model, samples, seed=7, output_disturbance=drifts).as_logged_data()


def test_a_drift_the_first_repair_takes_up_is_allowed_for():
    plant, model, data = drifting_loop()
    res = repair_model(model, data, [(0, 1)], RepairOptions(disturbance_draws=0))
    (change,) = res.changes
    assert change["applied"] and change["kind"] == "gain"
    assert abs(change["after"]["gain"] / plant.gain[0, 1] - 1.0) < 0.02
    assert abs(change["after"]["time_constant"] / plant.time_constant[0, 1] - 1.0) < 0.02
    assert any(w == "y1: the re-estimation of its elements allowed for the unexplained drift in the prediction error."
               for w in res.warnings)
    assert "y1" in [x["output"] for x in res.disturbances]          # the drift stays in the residual, reported


def test_a_loop_without_a_disturbance_is_repaired_as_before():
    # The same loop without the drifts: the model as given shows no disturbance, nothing is redone.
    plant, model, _ = drifting_loop(samples=200)
    data = run_closed_loop(plant, model, 10000, seed=7).as_logged_data()
    res = repair_model(model, data, [(0, 1)], RepairOptions(disturbance_draws=0))
    assert not res.disturbances and not any("allowed for" in w for w in res.warnings)
    assert abs(res.changes[0]["after"]["gain"] / plant.gain[0, 1] - 1.0) < 0.02
