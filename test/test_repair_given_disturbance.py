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


def test_a_redo_whose_disturbance_the_repaired_model_does_not_show_says_so():
    """An outside check: a 2x2 loop with a measured disturbance and an integrating output, the gain of (y1, u1)
    doubled in the plant and no step anywhere.  The model as given's prediction error shows a step (the gain
    error's), the row was re-estimated allowing for it, and the repaired model's error showed none: the report
    listed no disturbance, while its warning said the elements "allowed for the unexplained step" (33 of 41 such
    reports).  The warning now says where the step was seen and that none is reported; a row that keeps its
    disturbance keeps the old words (the test above)."""
    from mpm_monitor.core.model import PlantModel

    kw = dict(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1", "y2"), disturbances=("dv1",),
              time_constant=[[20, 15, 10], [12, 5, 8]], time_constant2=[[0, 0, 0], [6, 0, 0]],
              lead=[[8, 0, 0], [0, 0, 0]], delay=[[2, 3, 4], [1, 2, 3]],
              integrating=[[False, False, False], [False, True, True]])
    model = PlantModel(gain=[[1.5, 0.5, 0.8], [0.3, 0.02, 0.01]], **kw)
    plant = PlantModel(gain=[[3.0, 0.5, 0.8], [0.3, 0.02, 0.01]], **kw)
    # Seed 24: since stop 96 the disturbance tests' confirmation also simulates a longer AR of the error, which
    # holds the gain error's colour, and the error as given shows a step in 2 of seeds 1 to 24 only (seed 1, this
    # test's before, none).
    data = run_closed_loop(plant, model, 5000, seed=24).as_logged_data()
    res = repair_model(model, data, [(0, 0)], RepairOptions())
    (change,) = res.changes
    assert change["kind"] == "gain" and abs(change["after"]["gain"] / 3.0 - 1.0) < 0.05
    reported = {x["output"] for x in res.disturbances}
    redone = [w for w in res.warnings if "allowing for one" in w or "allowed for the unexplained" in w]
    assert redone, res.warnings          # the row was redone (else this test checks nothing)
    for w in redone:
        output = w.split(":")[0]
        assert ("allowed for the unexplained" in w) == (output in reported), (w, reported)
    assert any(w.startswith("y1: the prediction error of the model as given showed an unexplained step (p = ")
               and w.endswith("shows none at the disturbance tests' level, and none is reported.") for w in redone), redone
