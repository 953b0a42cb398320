"""The repair in the element's structure: one wrong element of each structure, restored in its keys.

For a second lag, a lead, an inverse response (closed loops of the paper's Shell plant given those
structures), an integrator, a step-response model (on a settling and on a ramp output) and a
measured-disturbance column (open-loop records: ``u`` and ``dv`` known, ``d = y - yhat``), the
controller's model differs from the plant in one element.  The analysis must locate it, name the
kind of the error, and repair it in its structure: the parameters within a few percent of the
plant's, the step response within 10% over 300 samples, every other element as it was, and the
repaired model file read back in the same structure.
"""

import dataclasses

import numpy as np
import pytest
from structure_models import first_order_model, rich_model, step_model
from test_detection_columns import open_loop

from mpm_monitor.core.elements import sample_parametric
from mpm_monitor.core.filters import lfilter
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.repair import RepairOptions, repair_model
from mpm_monitor.core.repair.forms import _basis, _Form, _step_reference, _tau_of
from mpm_monitor.io.model_file import load_model, save_model
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import run_closed_loop

#: Parametric keys compared within this relative tolerance.
REL = 0.03


def shell_structures():
    """The Shell plant of paper case 3.2 with a second lag on (y1, u1), a lead on (y2, u2) and an
    inverse response on (y3, u3)."""
    plant = paper_case("3.2").plant
    return (plant.with_element(0, 0, time_constant=30.0, time_constant2=15.0)
            .with_element(1, 1, lead=20.0)
            .with_element(2, 2, lead=-10.0, delay=1.0))


def closed_loop(plant, model, seed, samples=3000):
    case = paper_case("3.2")
    return run_closed_loop(plant, model, samples, seed=seed, mpc=case.mpc, excitation=case.excitation,
                           disturbance=case.disturbance).as_logged_data()


def assert_repaired_in_structure(report, model, plant, element, kind, tmp_path):
    """The located element's kind, its keys and step response, every other element unchanged, the file."""
    o, c = element
    i, j = model.outputs.index(o), model.columns.index(c)
    assert element in report.located_elements
    kinds = {(e.output, e.input): e.kind for e in report.elements if e.mismatch}
    assert kinds.pop(element) == kind
    assert set(kinds.values()) <= {"unknown"}            # an element located besides is kept as it is
    repaired = report.repaired_model
    change = next(c for c in report.repair["changes"] if (c["output"], c["input"]) == element)
    assert change["applied"] is True and change["kind"] == kind
    assert [c["applied"] for c in report.repair["changes"]].count(True) == 1
    assert change["after"] == repaired.element(i, j)
    assert set(change["after"]) == set(plant.element(i, j)) == set(change["before"])
    if not model.is_step_response:
        for key, true in plant.element(i, j).items():
            assert change["after"][key] == pytest.approx(true, rel=REL, abs=1e-9), key
    new = repaired.discrete_element(i, j).step_response(300)
    true = plant.discrete_element(i, j).step_response(300)
    assert np.max(np.abs(new - true)) <= 0.10 * np.max(np.abs(true))
    # No other element changed: putting the old element back gives the model as given.
    old = ({"step_response": model.step_response[i, j]} if model.is_step_response else
           {k: model.element(i, j).get(k, d) for k, d in (("gain", 0.0), ("time_constant", 0.0), ("delay", 0.0),
                                                          ("lead", 0.0), ("time_constant2", 0.0),
                                                          ("integrating", False))})
    assert repaired.with_element(i, j, **old) == model
    path = tmp_path / "repaired.yaml"
    save_model(repaired, path)
    back = load_model(path)
    assert back == repaired and back.is_step_response == model.is_step_response
    return change


# ----------------------------------------------------------------------------------------------------
# Closed loops: second lag, lead, inverse response


@pytest.mark.parametrize("element, change, kind", [
    (("y1", "u1"), {"time_constant2": 6.0}, "time_constant"),
    (("y1", "u1"), {"gain": 6.0}, "gain"),
    (("y2", "u2"), {"lead": 35.0}, "time_constant"),
    (("y3", "u3"), {"lead": -4.0}, "time_constant"),
    (("y3", "u3"), {"delay": 4.0}, "delay"),
], ids=["second-lag", "second-order-gain", "lead", "inverse-response", "inverse-response-delay"])
def test_closed_loop_structures_are_repaired_in_their_keys(element, change, kind, tmp_path):
    model = shell_structures()
    o, u = element
    i, j = model.outputs.index(o), model.inputs.index(u)
    plant = model.with_element(i, j, **change)
    report = analyze(model, closed_loop(plant, model, seed=31))
    entry = assert_repaired_in_structure(report, model, plant, element, kind, tmp_path)
    for key in change:
        assert entry["before"][key] != entry["after"][key]


@pytest.mark.parametrize("lead, seed", [(0.0, 31), (5.0, 31), (5.0, 33)],
                         ids=["two-lags", "two-lags-and-a-lead", "two-lags-and-a-lead-just-above-the-bound"])
def test_a_second_lag_the_plant_lost_is_repaired_away(lead, seed):
    """The plant lost the second lag of (y1, u1) (30 s and 15 s in the model, 30 s alone in the plant): the fit's
    pole stops at its bound, and the element was repaired with a second lag of 0.109 s (at T = 1 s), which kept
    the row mismatched (located again in the repaired model, its row in rows_flagged_after).  It is repaired
    with one lag now, time_constant2 0; with a lead, at the same dead time (the one-lag form with a lead acts
    at its dead time, the two-lag form a sample after it).  Its kind is a time constant: decided in the
    two-lag form, the lag of a tenth of a sample bent the gain or the dead time, and every one of these came
    out "mixed".  With seed 33 and a lead the fitted lag came to rest just above the bound (0.121 s) and was
    written, with a lead of 4.2 s for 5 s and a dead time one sample short."""
    model = shell_structures().with_element(0, 0, lead=lead)
    plant = model.with_element(0, 0, time_constant2=0.0)
    data = closed_loop(plant, model, seed=seed)
    report = analyze(model, data)
    assert ("y1", "u1") in report.located_elements
    change = next(c for c in report.repair["changes"] if (c["output"], c["input"]) == ("y1", "u1"))
    assert change["kind"] == "time_constant"
    after = report.repaired_model.element(0, 0)
    assert after.get("time_constant2", 0.0) == 0.0
    assert after["time_constant"] == pytest.approx(30.0, rel=REL) and after["delay"] == model.delay[0, 0]
    assert after["gain"] == pytest.approx(plant.gain[0, 0], rel=REL)
    assert after.get("lead", 0.0) == pytest.approx(lead, rel=REL, abs=0.1)
    assert "y1" not in report.repair["rows_flagged_after"]
    again = analyze(report.repaired_model, data)
    assert not [k for k in again.located_elements if k[0] == "y1"]


def test_a_lead_the_plant_lost_is_not_repaired_into_a_direct_feed_through():
    """An inverse response on (y1, u2) (lead -5 s, lag 15 s, dead time 1 s in the model; a pure gain with a dead
    time of 1 s in the plant): the repair searched the lead-lag element's input lag down to 0, found its best there and
    wrote a lead with no dead time, a direct feed-through that the package's own simulator and MPC refuse.  The
    input lag is 1 at least now."""
    from mpm_monitor.sim.plant import require_strictly_proper

    model = PlantModel(inputs=("u1", "u2"), outputs=("y1", "y2"), sample_time=1.0,
                       gain=np.array([[1.5, 0.5], [-0.6, 1.0]]), time_constant=np.array([[20.0, 15.0], [25.0, 12.0]]),
                       delay=np.array([[2.0, 1.0], [3.0, 1.0]]), lead=np.array([[0.0, -5.0], [10.0, 0.0]]))
    plant = model.with_element(0, 1, time_constant=0.0, lead=0.0)
    log = run_closed_loop(plant, model, 3000, seed=3)
    report = analyze(model, log.as_logged_data())
    assert ("y1", "u2") in report.located_elements
    require_strictly_proper(report.repaired_model, "repaired model")
    assert report.repaired_model.element(0, 1)["delay"] >= 1.0
    step = plant.discrete_element(0, 1).step_response(300)
    fitted = report.repaired_model.discrete_element(0, 1).step_response(300)
    assert np.max(np.abs(fitted - step)) < 0.1 * abs(plant.gain[0, 1])


@pytest.mark.parametrize("delay", [0.0, 1.0, 2.0])
def test_no_element_is_searched_at_an_input_lag_of_0(delay):
    """The input lags a lead-lag element (one lag and a lead, biproper) was searched over reached down to 0: a
    lead with no dead time, acting on y(k) through u(k).  A loop run by another controller (u(k) computed from
    y(k)) made that lag the best, and the repair wrote a direct feed-through that the package's simulator and
    MPC refuse.  Every element is searched from lag 1 up, but one the model itself gives a feed-through (no dead
    time, stop 75): that one from 0, its own lag, so that its dead time can be held
    (``test_a_model_element_with_a_feed_through_is_repaired_in_it``)."""
    from mpm_monitor.core.repair.classify import _free_spec, _locate
    from mpm_monitor.core.repair.row import _RowData

    model = PlantModel(inputs=("u1", "u2"), outputs=("y1",), sample_time=1.0, gain=np.array([[1.5, 0.5]]),
                       time_constant=np.array([[20.0, 15.0]]), delay=np.array([[2.0, delay]]),
                       lead=np.array([[0.0, -5.0]]))
    row = _RowData(model=model, u=np.zeros((50, 2)), y=np.zeros((50, 1)), i=0)
    spec, lag = _free_spec(row, _locate(row, 1), RepairOptions())
    floor = 0 if delay == 0 else 1                   # the model's own feed-through, and only that, from 0
    assert spec.window[0] == max(floor, lag - RepairOptions().max_delay_shift)
    assert spec.window[0] <= lag <= spec.window[1] and lag == int(delay)


def test_the_new_parameters_are_worded_with_their_keys():
    from mpm_monitor.core.wording import describe_change, repair_summary_lines, row_repair_text

    change = {"output": "y1", "input": "u1", "kind": "time_constant", "applied": True,
              "before": {"gain": 4.05, "time_constant": 30.0, "delay": 6.0, "time_constant2": 15.0},
              "after": {"gain": 4.05, "time_constant": 30.0, "delay": 6.0, "time_constant2": 25.0}}
    assert describe_change(change) == "time_constant2 15->25 s"
    change["before"]["lead"], change["after"]["lead"] = 12.0, 8.0
    assert describe_change(change) == "time_constant2 15->25 s, lead 12->8 s"
    assert row_repair_text([change], "y1") == "u1: time_constant2 15->25 s, lead 12->8 s"
    assert repair_summary_lines({"changes": [change]})[1].endswith("(time_constant2 15 -> 25 s; lead 12 -> 8 s)")
    step = {"output": "y1", "input": "u2", "kind": "mixed", "applied": True,
            "before": {"gain": 1.2, "time_constant": 0.0, "delay": 3.0, "step_response": [0.0, 0.5, 1.2]},
            "after": {"gain": 1.6, "time_constant": 0.0, "delay": 5.0, "step_response": [0.0, 0.0, 1.6]}}
    assert describe_change(step) == "step response re-estimated: final value 1.2->1.6, dead time 3->5 s"
    assert describe_change(step, element=True) == ("step response of (y1, u2) re-estimated: final value 1.2->1.6, "
                                                   "dead time 3->5 s")
    assert row_repair_text([step], "y1") == "u2: step response re-estimated: final value 1.2->1.6, dead time 3->5 s"
    assert repair_summary_lines({"changes": [step]})[1] == (
        "  step response of (y1, u2) re-estimated: final value 1.2->1.6, dead time 3->5 s (mixed)")
    step["after"] = dict(step["before"], step_response=[0.0, 0.7, 1.2])
    assert describe_change(step) == "step response re-estimated: shape only (final value 1.2, dead time 3 s)"
    # An outside check: a time-constant change read "final value 1.2->1.18 (time_constant)", the lag's change only
    # in the evidence's parametric readings, which the words now give.
    step["evidence"] = {"parametric_before": {"gain": 1.2, "time_constant": 12.0, "delay": 3.0},
                        "parametric_after": {"gain": 1.2, "time_constant": 36.7, "delay": 3.0}}
    assert describe_change(step) == ("step response re-estimated: shape only (final value 1.2, dead time 3 s), read as "
                                     "time constant 12->36.7 s")
    del step["evidence"]
    step["after"], step["ramp"] = dict(step["before"], gain=0.08, step_response=[0.0, 0.5, 1.3]), True
    assert describe_change(step) == "step response re-estimated: final slope 1.2->0.08 per s"


# ----------------------------------------------------------------------------------------------------
# Open loops: integrator, measured disturbance, step-response models


def test_an_integrator_gain_error_is_a_gain_and_keeps_the_integrator(tmp_path):
    model = rich_model()
    plant = model.with_element(1, 0, gain=0.08)
    report = analyze(model, open_loop(plant, model, 3000, seed=12, burn_in=300))
    entry = assert_repaired_in_structure(report, model, plant, ("y2", "u1"), "gain", tmp_path)
    assert entry["after"]["integrating"] is True


def test_a_pure_integrator_whose_plant_gained_a_lag_is_repaired_with_the_lag(tmp_path):
    """The model's integrator (y2, u1) has no lag; the plant's has one of 5 s.  Fitted in the model's form,
    only the dead time could move: the repair was the lag's worth of dead time (the same ramp, another
    transient, the row still mismatched) and the kind ``delay``.  Now the one-lag form, kept where the data
    call for it, gives the lag."""
    plant = rich_model()
    model = plant.with_element(1, 0, time_constant=0.0)
    report = analyze(model, open_loop(plant, model, 3000, seed=16, burn_in=300))
    entry = assert_repaired_in_structure(report, model, plant, ("y2", "u1"), "time_constant", tmp_path)
    assert entry["after"]["integrating"] is True and entry["after"]["delay"] == model.delay[1, 0]


@pytest.mark.parametrize("index", [80, 164, 178])
def test_two_pure_integrators_of_a_row_that_both_gained_a_lag_are_repaired_with_their_lags(index):
    """bench.structures_mc --gained-lag, seed 4 (runs never looked at before): a row of a closed loop holds two
    pure integrators whose plants both gained a lag (16.3 s and 2.6 s; 17.1 s and 16.4 s; 5.5 s and 3.5 s).
    Fitted in the model's form, the noise model took a unit root and the integrators' gains fell to a twentieth
    or less (a drift the noise model carries, in place of the ramps the inputs make).  Grown one at a time from
    that fit, the first element's lag did not fit better while the other was still a collapsed pure integrator
    (runs 80 and 164: only the second was grown), or neither did (run 178): both stayed ``unknown``, and the held-
    out check then kept the model.  Now a growth is retried on the others after one is taken, and the elements
    still left are grown together: both a ``time_constant`` change, each gain and lag the plant's."""
    from bench.structures_mc import StructuresOptions

    sc, report = structures_scenario_report(StructuresOptions(gained_lag=True), index, seed=4)
    changes = {(c["output"], c["input"]): c for c in report.repair["changes"]}
    assert len(sc.mismatches) == 2
    for m in sc.mismatches:
        assert m["kind"] == "integrator_gained_lag"
        i, j = m["output"], m["column"]
        change = changes[(sc.model.outputs[i], sc.model.columns[j])]
        assert change["kind"] == "time_constant" and change["applied"] is True
        assert change["after"]["integrating"] is True and change["after"]["delay"] == m["plant"]["delay"]
        assert change["after"]["gain"] == pytest.approx(m["plant"]["gain"], rel=0.02)
        assert change["after"]["time_constant"] == pytest.approx(m["plant"]["time_constant"], rel=0.1)


def test_a_pure_gain_whose_plant_gained_a_lag_is_a_time_constant(tmp_path):
    """The model's (y2, u2) is a pure gain with 3 s of dead time; the plant's has a lag of 9 s at the same dead
    time.  A first-order element acts one sample after a pure gain of the same dead time: the delay test held
    the pure gain's own lag (3) with the lag free, rejected, and the kind was ``mixed`` (177 of 177 in
    bench.structures_mc --gained-lag), though the dead time had not changed."""
    plant = first_order_model()
    model = plant.with_element(1, 1, time_constant=0.0)
    report = analyze(model, open_loop(plant, model, 3000, seed=21, burn_in=300))
    entry = assert_repaired_in_structure(report, model, plant, ("y2", "u2"), "time_constant", tmp_path)
    assert entry["after"]["delay"] == model.delay[1, 1] and entry["evidence"]["p_delay"] > 0.01


def test_a_pure_gains_gain_change_is_still_a_gain(tmp_path):
    """The same pure gain, the plant's 30 % larger and still without a lag: the kind is ``gain``, the lag and the
    dead time as they were (the delay test also holds the pure gain's own lag, where the fit puts it)."""
    pure = first_order_model().with_element(1, 1, time_constant=0.0)
    plant = pure.with_element(1, 1, gain=1.3 * pure.gain[1, 1])
    report = analyze(pure, open_loop(plant, pure, 3000, seed=22, burn_in=300))
    entry = assert_repaired_in_structure(report, pure, plant, ("y2", "u2"), "gain", tmp_path)
    assert entry["after"]["time_constant"] == 0.0 and entry["after"]["delay"] == pure.delay[1, 1]


def test_a_pure_gains_dead_time_change_of_a_sample_is_still_a_delay(tmp_path):
    """The same pure gain, the plant's a sample later and still without a lag: a ``delay`` change.  A pure gain a
    sample later is a first-order element with a vanishing lag at the reference's dead time: holding the later lag
    whenever the lag was free read such changes ``mixed`` (11 of 70 in bench.structures_mc --pure-gains)."""
    pure = first_order_model().with_element(1, 1, time_constant=0.0)
    plant = pure.with_element(1, 1, delay=pure.delay[1, 1] + 1.0)
    report = analyze(pure, open_loop(plant, pure, 3000, seed=23, burn_in=300))
    entry = assert_repaired_in_structure(report, pure, plant, ("y2", "u2"), "delay", tmp_path)
    assert entry["after"]["time_constant"] == 0.0


@pytest.mark.parametrize("seed", [21, 23, 35, 39])
def test_a_first_order_element_whose_plant_lost_its_lag_is_a_pure_gain_at_the_same_dead_time(tmp_path, seed):
    """The model's (y2, u2) has a lag of 9 s and 3 s of dead time; the plant's is a pure gain at the same dead time.
    The fit reads no lag; the delay test held the element's lag with the lag (a sample later) and the kind was
    ``mixed`` (44 of 44 in bench.structures_mc --pure-gains).  With seed 23 the repair also wrote the vanished lag
    as 0.12 s at the held dead time, a sample later than the lag it was fitted at.  With seeds 35 and 39 the fitted
    pole (3.2e-4 and 3.0e-4) lies above the pole's reading as no lag (2e-4, a lag of T / 8.5): read as a lag of
    T / 8 a sample earlier, the kind was ``mixed`` again (6 of 44 in --pure-gains); holding the pole at no lag
    does not fit worse, and that reading is now the fit's."""
    model = first_order_model()
    plant = model.with_element(1, 1, time_constant=0.0)
    report = analyze(model, open_loop(plant, model, 3000, seed=seed, burn_in=300))
    entry = assert_repaired_in_structure(report, model, plant, ("y2", "u2"), "time_constant", tmp_path)
    assert entry["after"]["time_constant"] == 0.0 and entry["after"]["delay"] == model.delay[1, 1]


def test_an_integrator_with_a_lead_whose_plant_gained_a_lag_keeps_its_lead():
    """(y2, u2) integrates with a lead of 4 s and no lag; the plant's has a lag of 6 s too.  The lag and the
    lead trade along a ridge (over seeds 16 to 18 the fit gave 5.8 to 6.7 s and 3.8 to 4.5 s), their
    difference and the step response do not."""
    model = rich_model()
    plant = model.with_element(1, 1, time_constant=6.0)
    report = analyze(model, open_loop(plant, model, 3000, seed=16, burn_in=300))
    assert ("y2", "u2") in report.located_elements
    change = next(c for c in report.repair["changes"] if (c["output"], c["input"]) == ("y2", "u2"))
    after = change["after"]
    assert change["kind"] == "time_constant" and change["applied"] is True
    assert after["integrating"] is True and after["delay"] == model.delay[1, 1] and after["lead"] > 0
    assert after["time_constant"] - after["lead"] == pytest.approx(2.0, abs=0.3)
    new = report.repaired_model.discrete_element(1, 1).step_response(300)
    true = plant.discrete_element(1, 1).step_response(300)
    assert np.max(np.abs(new - true)) <= 0.01 * np.max(np.abs(true))


def test_the_held_out_check_ignores_the_level_of_an_integrating_output():
    # The arbitrary level of an integrating output (here -30.8) is no element's to explain: the
    # held-out check takes it from the fit part, so the right repair passes at once (compared with
    # the level, it was first rejected, and accepted only when redone with a spurious step).
    model = rich_model()
    plant = model.with_element(1, 0, gain=0.08)
    res = repair_model(model, open_loop(plant, model, 3000, seed=12, burn_in=300, level=-30.8), [(1, 0)])
    assert res.changes[0]["applied"] is True and res.kinds[(1, 0)] == "gain"
    assert res.holdout_error_after["y2"] < 0.05 < 1.0 < res.holdout_error_before["y2"]
    assert not any(w.startswith("y2: the re-estimation of its elements allowed for") for w in res.warnings)
    assert not any("did not predict the held-out" in w for w in res.warnings)


def test_a_measured_disturbance_element_is_repaired_in_its_structure(tmp_path):
    # (y2, dv1): second order with a lead; the disturbance's gain is wrong.
    model = rich_model()
    plant = model.with_element(1, 2, gain=-0.8)
    report = analyze(model, open_loop(plant, model, 3000, seed=14, burn_in=300))
    entry = assert_repaired_in_structure(report, model, plant, ("y2", "dv1"), "gain", tmp_path)
    assert report.to_dict()["elements"][[(e.output, e.input) for e in report.elements].index(("y2", "dv1"))][
        "role"] == "disturbance"
    assert {"lead", "time_constant2"} <= set(entry["after"])


def test_a_disturbance_time_constant_is_repaired_with_its_lead_and_second_lag():
    model = rich_model()
    plant = model.with_element(1, 2, time_constant=20.0)
    res = repair_model(model, open_loop(plant, model, 3000, seed=15, burn_in=300), [(1, 2)])
    entry = res.changes[0]
    assert entry["kind"] == "time_constant" and entry["applied"] is True
    assert entry["after"]["time_constant"] == pytest.approx(20.0, rel=REL)
    # The shape is freed as a whole: the lead and the second lag are re-estimated too, near the plant's.
    assert entry["after"]["lead"] == pytest.approx(2.0, rel=0.15)
    assert entry["after"]["time_constant2"] == pytest.approx(3.0, rel=0.15)
    new = res.model.discrete_element(1, 2).step_response(300)
    true = plant.discrete_element(1, 2).step_response(300)
    assert np.max(np.abs(new - true)) <= 0.03 * np.max(np.abs(true))


def _step_plant(model, i, j, coefs):
    sr = np.array(model.step_response)
    sr[i, j] = coefs
    return model.replace(step_response=sr)


@pytest.mark.parametrize("what, kind", [("gain", "gain"), ("shape", "time_constant"), ("delay", "delay")])
def test_a_step_response_element_is_re_estimated_as_a_step_response(what, kind, tmp_path):
    model = step_model(60)
    k = np.arange(1, 61)
    true = {"gain": np.where(k > 3, 2.1 * (1 - np.exp(-(k - 3) / 6.0)), 0.0),
            "shape": np.where(k > 3, 1.5 * (1 - np.exp(-(k - 3) / 12.0)), 0.0),
            "delay": np.where(k > 6, 1.5 * (1 - np.exp(-(k - 6) / 6.0)), 0.0)}[what]
    plant = _step_plant(model, 0, 0, true)
    report = analyze(model, open_loop(plant, model, 3000, seed=16, burn_in=300))
    entry = assert_repaired_in_structure(report, model, plant, ("y1", "u1"), kind, tmp_path)
    assert len(entry["after"]["step_response"]) == 60
    assert "step response of (y1, u1) re-estimated: " in report.summary_text()
    assert set(entry["evidence"]["parametric_before"]) == {"gain", "time_constant", "delay"}
    new = np.asarray(entry["after"]["step_response"])
    assert np.max(np.abs(new - true)) <= 0.03 * np.max(np.abs(true))
    if what != "shape":
        # Only the final value or the dead time changed: the old response is kept, scaled or shifted.
        old = model.step_response[0, 0]
        if what == "gain":
            np.testing.assert_allclose(new, old * new[-1] / old[-1], rtol=1e-12)
        else:
            np.testing.assert_array_equal(new[:6], 0.0)
            np.testing.assert_allclose(new[6:], old[3:-3], rtol=1e-12)


def test_a_ramp_element_of_a_step_response_model_keeps_its_ramp(tmp_path):
    model = step_model(60)
    k = np.arange(1, 61)
    true = np.where(k > 2, 0.08 * (k - 2) - 0.32 * (1 - np.exp(-(k - 2) / 4.0)), 0.0)     # slope 0.05 -> 0.08
    plant = _step_plant(model, 1, 0, true)
    report = analyze(model, open_loop(plant, model, 3000, seed=17, burn_in=300))
    entry = assert_repaired_in_structure(report, model, plant, ("y2", "u1"), "gain", tmp_path)
    assert entry["after"]["gain"] == pytest.approx(0.08, rel=REL)          # the last slope, per second
    assert report.repaired_model.ramp == model.ramp


def test_an_element_a_step_response_model_lacks_on_a_ramp_row_is_fitted_integrating(tmp_path):
    # Outside hunt 3: fitted first order (a 2000 s lag), its error after the repair 20 times the noise.
    model = step_model(60)
    k = np.arange(1, 61)
    assert not model.present[1, 1] and model.ramp[1]
    plant = _step_plant(model, 1, 1, np.where(k > 2, 0.03 * (k - 2), 0.0))       # slope 0.03 per second
    report = analyze(model, open_loop(plant, model, 3000, seed=17, burn_in=300))
    entry = assert_repaired_in_structure(report, model, plant, ("y2", "u2"), "missing", tmp_path)
    assert entry["after"]["gain"] == pytest.approx(0.03, rel=REL)                # the last slope, per second
    assert entry["evidence"]["parametric_after"]["integrating"]
    assert report.repair["error_after"]["y2"] <= 1.1 * report.repair["error_after"]["y1"]


# ----------------------------------------------------------------------------------------------------
# The pieces


@pytest.mark.parametrize("form", [_Form(1, True), _Form(2), _Form(2, True), _Form(0, True, True),
                                  _Form(1, False, True), _Form(2, True, True)],
                         ids=lambda f: f.describe().replace(" ", "-"))
@pytest.mark.parametrize("poles", [(0.9, 0.6), (0.8, 0.8), (0.8, 0.8 + 1e-8)], ids=["distinct", "repeated", "near"])
def test_the_fit_basis_is_the_sampled_element(form, poles):
    ts = 2.0
    poles = poles[:form.n_lags]
    taus = [_tau_of(a, ts) for a in poles] + [0.0, 0.0]
    for lead in ((3.0, -5.0) if form.lead else (0.0,)):
        el = sample_parametric(1.0, taus[0], 0, ts, lead=lead, time_constant2=taus[1], integrating=form.integrating)
        num_a, num_b, den = _basis(form, poles, ts)
        num = num_a if num_b is None else num_a + lead * num_b
        np.testing.assert_allclose(den, el.den, atol=1e-12)
        np.testing.assert_allclose(num, el.num[form.offset:], rtol=1e-7, atol=1e-10 * np.max(np.abs(el.num)))


@pytest.mark.parametrize("form, params, n", [
    (_Form(), {"gain": 1.5, "time_constant": 6.0, "delay": 3.0}, 80),
    (_Form(2), {"gain": -0.7, "time_constant": 9.0, "time_constant2": 3.0, "delay": 1.0}, 80),
    (_Form(2, True), {"gain": 0.4, "time_constant": 9.0, "time_constant2": 3.0, "lead": -4.0, "delay": 2.0}, 80),
    (_Form(1, False, True), {"gain": 0.05, "time_constant": 4.0, "delay": 2.0, "integrating": True}, 80),
    # an integrator's inverse response over 12 time constants: its first time constant was tried from the ramp
    # (187 s), and the fit stopped at two lags of 43 s, a lead of 65 s and three samples of dead time, 12 % off
    (_Form(2, True, True), {"gain": -0.0354, "time_constant": 15.5, "time_constant2": 7.5, "lead": -4.0,
                            "delay": 0.0, "integrating": True}, 281),
])
def test_the_parametric_form_of_a_step_response_is_found_again(form, params, n):
    from mpm_monitor.core.repair.forms import _sampled

    full = {"lead": 0.0, "time_constant2": 0.0, "integrating": False, **params}
    coefs = _sampled(full, 1.0).step_response(n + 1)[1:]
    ref, lag, _, _ = _step_reference(coefs, form, 1.0)
    for key, value in full.items():
        assert ref[key] == pytest.approx(value, rel=1e-4, abs=1e-6), key
    assert lag == int(full["delay"]) + form.offset


def test_a_step_response_is_read_in_the_first_form_that_reads_it():
    """A first-order response starts first order; a two-lag one (7.9 s and 5.8 s, which one lag reads as a longer
    lag with more dead time, off by more than 1 %) starts in two lags; a first-order response with noise no form
    reads within 1 % is not read in a larger form for its noise (it must halve the error)."""
    from mpm_monitor.core.repair.forms import (
        STEP_READ_GAIN,
        STEP_READ_TOLERANCE,
        _LADDER_STEP_RAMP,
        _sampled,
        _step_ladder,
        _step_start_form,
    )

    model = step_model(60)
    ladder = _step_ladder(model, 0, 0)
    assert ladder[0] == _Form() and ladder[1] == _Form(2)

    def start(params, noise=0.0):
        full = {"lead": 0.0, "time_constant2": 0.0, "integrating": False, **params}
        coefs = _sampled(full, 1.0).step_response(81)[1:]
        coefs = coefs + noise * np.random.default_rng(3).standard_normal(coefs.size)
        errors = {form: _step_reference(coefs, form, 1.0)[3] for form in ladder}
        return _step_start_form(lambda form: errors[form], ladder), errors

    form, errors = start({"gain": 1.5, "time_constant": 6.0, "delay": 3.0})
    assert form == _Form() and errors[_Form()] < 1e-6
    form, errors = start({"gain": 2.0, "time_constant": 7.9, "time_constant2": 5.8, "delay": 3.0})
    assert form == _Form(2) and errors[_Form()] > STEP_READ_TOLERANCE > errors[_Form(2)]
    form, errors = start({"gain": 1.5, "time_constant": 6.0, "delay": 3.0}, noise=0.05)
    assert form == _Form() and errors[_Form()] > STEP_READ_TOLERANCE
    # An integrator with a lead: read in one lag 6.6 % off, in two lags no better, in two lags and a lead exactly.
    ladder = _LADDER_STEP_RAMP
    form, errors = start({"gain": -0.0939, "time_constant": 19.8, "time_constant2": 6.3, "lead": 14.4,
                          "integrating": True, "delay": 0.0})
    lag, two_lags = _Form(1, False, True), _Form(2, False, True)
    assert errors[two_lags] > STEP_READ_GAIN * errors[lag] > STEP_READ_GAIN * STEP_READ_TOLERANCE
    assert form == _Form(2, True, True) and errors[form] < 1e-6


@pytest.mark.parametrize("seed", [21, 22])
def test_a_two_lag_step_response_that_lost_a_lag_is_a_time_constant_change(seed):
    """The step-response form of (y1, u1) of the rich model, lags of 10 s and 4 s; the plant lost the 4 s lag.  Its
    old response was read in one lag (11.4 s and three samples more dead time) and the fit, one lag of 10 s and the
    declared dead time, read as changed in both: ``mixed``.  The old response now reads in two lags, and the fit that drops
    one holds that reading: ``time_constant``, the dead time kept.  A pure gain change stays ``gain``."""
    from bench.step_models import step_form

    model = rich_model()
    for plant, kind in ((model.with_element(0, 0, time_constant2=0.0), "time_constant"),
                        (model.with_element(0, 0, gain=2.6), "gain")):
        res = repair_model(step_form(model), open_loop(step_form(plant), step_form(model), 3000, seed=seed,
                                                       burn_in=300), [(0, 0)])
        (change,) = res.changes
        assert change["kind"] == kind and change["applied"] is True
        fitted = change["evidence"]["parametric_after"]
        assert fitted["delay"] == 2.0 and fitted["time_constant"] == pytest.approx(10.0, rel=0.01)
        assert fitted.get("time_constant2", 0.0) == pytest.approx(float(plant.time_constant2[0, 0]), rel=0.02)
        new = res.model.step_response[0, 0]
        true = step_form(plant).step_response[0, 0]
        assert np.max(np.abs(new - true)) <= 0.02 * np.max(np.abs(true))


def test_a_missing_element_gets_a_second_lag_only_where_the_data_call_for_it():
    # (y1, dv1) absent from the model; the plant has it second order (10 s and 6 s) or first order.
    base = rich_model()
    model = base.with_element(0, 2, gain=0.0, time_constant=0.0)
    for tau2, n_lags in ((6.0, 2), (0.0, 1)):
        plant = base.with_element(0, 2, gain=0.8, time_constant=10.0, time_constant2=tau2, delay=2.0)
        res = repair_model(model, open_loop(plant, model, 3000, seed=18, burn_in=300), [(0, 2)],
                           RepairOptions())
        entry = res.changes[0]
        assert entry["kind"] == "missing" and entry["applied"] is True
        assert ("time_constant2" in entry["after"]) == (n_lags == 2)
        new = res.model.discrete_element(0, 2).step_response(300)
        true = plant.discrete_element(0, 2).step_response(300)
        assert np.max(np.abs(new - true)) <= 0.05 * np.max(np.abs(true))


def test_the_summary_line_of_a_null_error_says_n_a():
    """An error that is not finite is null in the JSON; the text summary says n/a (it raised a TypeError)."""
    from mpm_monitor.core.wording import repair_summary_lines

    lines = repair_summary_lines({"changes": [], "error_before": {"y1": None, "y2": 0.02},
                                  "error_after": {"y1": None, "y2": 0.019}})
    assert lines[-1] == "prediction error RMS before -> after repair: y1 n/a -> n/a, y2 0.0200 -> 0.0190"
    # Nothing repaired (--no-repair, or nothing located): one error per output, not "before -> after" twice over.
    lines = repair_summary_lines({"changes": [], "error_before": {"y1": None, "y2": 0.02},
                                  "error_after": {"y1": None, "y2": 0.02}})
    assert lines == ["prediction error RMS (nothing repaired): y1 n/a, y2 0.0200"]
    # What the repaired model's detection still locates is listed last, where there is any.
    lines = repair_summary_lines({"changes": [], "error_before": {"y2": 0.02}, "error_after": {"y2": 0.019},
                                  "located_after": [{"output": "y2", "input": "u5", "p_value": 2e-4}]})
    assert lines[-1] == "elements the repaired model's detection locates: (y2, u5)"
    assert repair_summary_lines({"changes": [], "error_before": {"y2": 0.02}, "error_after": {"y2": 0.019},
                                 "located_after": []})[-1].startswith("prediction error RMS")
    # A second round's elements before it.
    lines = repair_summary_lines({"changes": [], "error_before": {"y2": 0.02}, "error_after": {"y2": 0.019},
                                  "second_round": [{"output": "y2", "input": "u5", "p_value": 6e-4}],
                                  "located_after": [{"output": "y2", "input": "u3", "p_value": 2e-4}]})
    assert lines[-2:] == ["repaired again with the elements the first repair's detection located: (y2, u5)",
                          "elements the repaired model's detection locates: (y2, u3)"]


def test_a_repaired_element_that_does_not_settle_within_a_step_response_model_is_named():
    from mpm_monitor.core.repair.forms import _sampled, unsettled_warning

    model = PlantModel.from_step_response(1.0, ("u1",), ("y1",), np.ones((1, 1, 30)))
    slow = {"gain": 2.0, "time_constant": 30.0, "delay": 0.0}
    written = _sampled(slow, 1.0).step_response(31)[1:]
    share = written[-1] / 2.0                               # 1 - exp(-1), about 63 %
    w = unsettled_warning(model, 0, 0, slow, written)
    assert f"reaches only {100 * share:.0f}% of its final value within the model's 30 samples" in w
    # 97 % of the final value: 3.5 time constants, 105 samples
    assert "a model of 106 samples would hold it" in w or "a model of 105 samples would hold it" in w
    fast = {"gain": 2.0, "time_constant": 3.0, "delay": 0.0}
    assert unsettled_warning(model, 0, 0, fast, _sampled(fast, 1.0).step_response(31)[1:]) is None
    # the old coefficients scaled (a gain change): not the fitted shape, not named
    assert unsettled_warning(model, 0, 0, slow, 2.0 * np.ones(30)) is None
    ramp = PlantModel.from_step_response(1.0, ("u1",), ("y1",), np.arange(1.0, 31.0)[None, None, :], ramp=[True])
    assert unsettled_warning(ramp, 0, 0, slow, written) is None


def test_a_pure_integrators_dead_time_change_on_a_ramp_row_is_a_delay():
    """A step-response model whose ramp row has a pure integrator (0.05 per sample after 2 samples); the
    plant's dead time grew by 4 samples.  The ladder started with one lag, which read the integrator's dead
    time a sample short with a lag of a sample: the new response, a pure integrator again, then differed in
    the lag and the dead time, ``mixed``.  It starts from the pure integrator now: ``delay``, with the
    model's response as its reference exactly."""
    k = np.arange(1, 61)
    model = _step_plant(step_model(60), 1, 0, np.where(k > 2, 0.05 * (k - 2), 0.0))
    plant = _step_plant(model, 1, 0, np.where(k > 6, 0.05 * (k - 6), 0.0))
    report = analyze(model, open_loop(plant, model, 3000, seed=17, burn_in=300))
    assert ("y2", "u1") in report.located_elements
    change = next(c for c in report.repair["changes"] if (c["output"], c["input"]) == ("y2", "u1"))
    before, after = change["evidence"]["parametric_before"], change["evidence"]["parametric_after"]
    assert change["kind"] == "delay" and change["applied"] is True
    assert before["time_constant"] == after["time_constant"] == 0.0
    assert before["delay"] == 2.0 and after["delay"] == 6.0
    assert before["gain"] == pytest.approx(0.05, rel=1e-9) and after["gain"] == pytest.approx(0.05, rel=1e-2)
    np.testing.assert_allclose(change["after"]["step_response"], plant.step_response[1, 0], rtol=0, atol=1e-9)


def test_a_ramp_row_the_model_has_no_element_in_is_repaired_integrating():
    """A step-response model's ``ramp`` row with every element zero: the plant's level integrates u1.  The
    row did not count as integrating (no element ramps), so the element the model lacks was fitted first
    order, its repair failed the held-out check, and nothing was repaired.  The ``ramp`` flag declares the
    level: the element is fitted integrating and the row's error falls to the noise."""
    zeros = np.zeros(60)
    plant = _step_plant(step_model(60), 1, 2, zeros)
    model = _step_plant(plant, 1, 0, zeros)
    assert model.ramp[1] and not model.present[1].any()
    report = analyze(model, open_loop(plant, model, 3000, seed=18, burn_in=300))
    assert ("y2", "u1") in report.located_elements
    change = next(c for c in report.repair["changes"] if (c["output"], c["input"]) == ("y2", "u1"))
    assert change["kind"] == "missing" and change["applied"] is True
    new = np.asarray(change["after"]["step_response"])
    true = plant.step_response[1, 0]
    assert np.max(np.abs(new - true)) <= 0.05 * np.max(np.abs(true))
    assert report.repair["error_after"]["y2"] < 0.2 * report.repair["error_before"]["y2"]
    assert model.integrating_outputs == (False, True)


@pytest.mark.parametrize("freed, kind", [
    ({"time_constant", "gain"}, "time_constant"),   # the gain freed by the joint test, moved by 0.01 %
    ({"gain"}, "gain"),                              # freed alone: it still names the kind
    ({"time_constant", "delay"}, "mixed"),           # two changes of material size
])
def test_a_parameter_freed_by_the_joint_test_with_a_negligible_change_names_no_kind(freed, kind):
    """bench.structures_mc --pure-gains run 228: an element that lost its 71 s lag; the gain's own test was
    significant (p = 1e-4) for a change of 0.01 %, under min_relative_change, so it did not count; the joint test
    of the unchanged parameters then freed it, and the kind was ``mixed``.  The gain is re-estimated; the kind
    is the time constant's."""
    from types import SimpleNamespace

    from mpm_monitor.core.repair.classify import _ElementTests, _Located, _verdict
    from mpm_monitor.core.repair.forms import FIRST_ORDER

    results = {k: [0.0, True] if k in freed else [0.5, False] for k in ("time_constant", "delay")}
    results["gain"] = [1.1e-4, False]                  # significant, but under min_relative_change
    tests = _ElementTests.of(results, 0.001)
    assert "gain" not in tests.changed
    tests.changed |= freed                              # as _joint_hold frees it
    est = SimpleNamespace(cond=1.0, fit=SimpleNamespace(n_resid=2900), ar=np.zeros(2))
    ref = {"gain": -3.8672, "time_constant": 71.2, "delay": 2.0, "time_constant2": 0.0, "lead": 0.0,
           "integrating": False}
    loc = _Located(form=FIRST_ORDER, reference=ref, lag=3, missing=False, poles=(0.986,))
    after = dict(ref, gain=-3.8676, time_constant=0.0)
    verdict = _verdict(est, (after, {}), tests, 1e-4, 0.001, loc)
    assert verdict.kind == kind and set(verdict.changed) == freed


def structures_scenario_report(opts, index: int, seed: int = 0):
    """``(scenario, report)``: bench.structures_mc's scenario ``index`` (``seed``, ``opts``) and the analysis, with the
    repair, of its closed loop (3,000 samples)."""
    from bench.structures_mc import make_structures_scenario, simulate

    sc = make_structures_scenario(seed, index, opts)
    return sc, analyze(sc.model, simulate(sc, 3000, opts).as_logged_data(f"structures scenario {seed}/{index}"))


def _scenario_change(opts, index: int, kind: str, seed: int = 0):
    """``(mismatch, change)``: the first mismatch of ``kind`` of bench.structures_mc's scenario ``index`` (``seed``,
    ``opts``), and its entry in the repair's ``changes`` after the analysis of the scenario's closed loop."""
    sc, report = structures_scenario_report(opts, index, seed)
    mismatch = next(m for m in sc.mismatches if m["kind"] == kind)
    i, j = mismatch["output"], mismatch["column"]
    change = next(c for c in report.repair["changes"]
                  if (c["output"], c["input"]) == (sc.model.outputs[i], sc.model.columns[j]))
    return mismatch, change


def test_a_lost_lag_stays_a_pure_gain_in_the_refit_on_the_whole_record():
    """bench.structures_mc --pure-gains run 236: (y4, u4) lost its 56.5 s lag, its plant a pure gain with 7 s of dead
    time.  The repair fitted it as a pure gain; the refit on the whole record then freed its pole again, which came
    back at 3.5e-4 (above its reading as no lag), and wrote a lag of 0.12 s at 6 s of dead time: the same response
    to 2.4e-4, but not the plant's element.  The refit now holds the pure gain it was repaired as."""
    from bench.structures_mc import StructuresOptions

    mismatch, change = _scenario_change(StructuresOptions(pure_gains=True), 236, "lost_only_lag")
    assert change["kind"] == "time_constant" and change["applied"] is True
    assert change["after"]["time_constant"] == 0.0 and change["after"]["delay"] == mismatch["plant"]["delay"] == 7.0


def test_an_element_whose_fit_drifted_to_a_slow_pole_is_searched_again_in_its_own_shape():
    """bench.structures_mc --pure-gains run 119: two pure gains of one row mismatched, (y2, u1)'s gain 4.6 times
    the model's and (y2, u2)'s dead time 6 s instead of 10 s.  With u1's gain that far off, the first fit put u2's
    pole at its upper bound (a lag of 2,000 s); the lag search then scanned only shapes near that, found u2's dead
    time at the end of its range, and the repair wrote u2 with a lag of 2,000 s (its step response 100 % off) and
    u1 with a lag it does not have (``mixed``).  The search now also scans an element's own shape when its fit has
    drifted off it: u1 a ``gain``, u2 a ``delay``, both the plant's elements."""
    from bench.structures_mc import StructuresOptions, make_structures_scenario, simulate

    opts = StructuresOptions(pure_gains=True)
    sc = make_structures_scenario(0, 119, opts)
    report = analyze(sc.model, simulate(sc, 3000, opts).as_logged_data("structures scenario 0/119"))
    changes = {(c["output"], c["input"]): c for c in report.repair["changes"]}
    for m in sc.mismatches:
        i, j = m["output"], m["column"]
        change = changes[(sc.model.outputs[i], sc.model.columns[j])]
        assert change["kind"] == m["kind"] and change["applied"] is True
        assert change["after"]["time_constant"] == 0.0 and change["after"]["delay"] == m["plant"]["delay"]
        assert change["after"]["gain"] == pytest.approx(m["plant"]["gain"], rel=0.01)


def test_two_lost_second_lags_of_one_row_are_found_by_the_lag_search():
    """bench.structures_mc --lost-lag run 146: the plant lost the second lags of (y3, u2) and (y3, u4) (30.5 s and
    31.1 s, beside lags of 53.9 s and 71.4 s and inverse-response leads of -14.7 s and -15.8 s).  The joint fit of
    the row started from the model's two lags and scanned only shapes with both lags scaled together; it came to
    rest far from the plant (u2 with both lags below a sample and a third of its gain, u4 with a lag of 2,000 s and
    a lead of 3,040 s), both ``mixed``, their step responses 69 % and 62 % off (28 % and 24 % before the repair).
    The held-out part still improved (the row's error 0.74 before, 0.53 after, against a noise of about 0.03), so
    the repair was applied.  The lag search now also scans each two-lag element with either lag gone: both are
    the plant's elements, ``time_constant``, and the row's held-out error falls to the noise."""
    from bench.structures_mc import StructuresOptions, step_response_error

    sc, report = structures_scenario_report(StructuresOptions(lost_lag=True), 146)
    changes = {(c["output"], c["input"]): c for c in report.repair["changes"]}
    assert len(sc.mismatches) == 2 and {m["output"] for m in sc.mismatches} == {2}
    for m in sc.mismatches:
        i, j = m["output"], m["column"]
        change = changes[(sc.model.outputs[i], sc.model.columns[j])]
        assert change["kind"] == "time_constant" and change["applied"] is True
        assert change["after"].get("time_constant2", 0.0) == 0.0
        assert change["after"]["delay"] == m["plant"]["delay"]
        for key in ("time_constant", "lead"):
            assert change["after"][key] == pytest.approx(m["plant"][key], rel=0.05), key
        assert step_response_error(sc.plant, report.repaired_model, i, j) <= 0.05
    assert report.repair["holdout_error_after"]["y3"] <= 1.2 * report.repair["holdout_error_before"]["y1"]


def test_a_pure_gain_and_a_lost_only_lag_of_one_row_are_found_by_the_lag_search():
    """bench.structures_mc --pure-gains seed 2 run 55: in row y1 the pure gain (y1, u1) was 66 % high (8.02 against
    the plant's 4.83) and (y1, u2) lost its only lag (10.5 s), the plant's a pure gain.  The loop swung at about 130
    times the noise.  The lag search scanned each one-lag element only at its time constant scaled by 0.5 to 2, and a
    pure gain's spec starts at the row's median time constant: neither element's pure gain was ever scanned.  The
    fit came to rest with both gains of the wrong sign (-3.5 and -4.9) at equal lags, the row's error 2.48 after the
    repair against a noise of 0.026, step responses 1.7 and 3.3 times off.  After its sweeps the search now also
    tries each one-lag element with its lag gone (where that already beats the fit; scanned from the start among the
    other shapes, it sent ``bench.repair_mc --dither-fat`` seed 1 run 36 to a worse fit): both elements are the
    plant's, ``gain`` and ``time_constant``."""
    from bench.structures_mc import StructuresOptions, step_response_error

    sc, report = structures_scenario_report(StructuresOptions(pure_gains=True), 55, seed=2)
    changes = {(c["output"], c["input"]): c for c in report.repair["changes"]}
    kinds = {m["kind"]: m for m in sc.mismatches}
    assert set(kinds) == {"gain", "lost_only_lag"} and {m["output"] for m in sc.mismatches} == {0}
    for kind, said in (("gain", "gain"), ("lost_only_lag", "time_constant")):
        m = kinds[kind]
        i, j = m["output"], m["column"]
        change = changes[(sc.model.outputs[i], sc.model.columns[j])]
        assert change["kind"] == said and change["applied"] is True
        assert change["after"]["time_constant"] == 0.0 and change["after"]["delay"] == m["plant"]["delay"]
        assert change["after"]["gain"] == pytest.approx(m["plant"]["gain"], rel=0.01)
        assert step_response_error(sc.plant, report.repaired_model, i, j) <= 0.01
    assert report.repair["holdout_error_after"]["y1"] <= 1.2 * report.repair["holdout_error_before"]["y2"]


def test_the_pure_gain_shapes_are_tried_after_the_sweeps_not_among_them():
    """bench.repair_mc --dither-fat seed 1 run 36: row y1 has three first-order elements off (u1's and u4's time
    constants, u3's dead time a sample long).  Scanned among the other shapes from the first sweep on, a one-lag
    element's shape with its lag gone took the coordinate search down another path, to a fit of higher cost: all
    three kinds wrong (``mixed``, ``mixed``, ``delay``) and the row's error 13 % above the noise.  Tried after the
    sweeps, where it must already beat the fit, it leaves the plant's elements found: every kind right, the error at
    the noise."""
    from bench.scenarios import ScenarioOptions, make_scenario
    from mpm_monitor.sim.closed_loop import run_closed_loop

    sc = make_scenario(1, 36, dataclasses.replace(ScenarioOptions(), dither_fat=True))
    log = run_closed_loop(sc.plant, sc.model, 3000, seed=sc.loop_seed, mpc=sc.mpc, excitation=sc.excitation,
                          disturbance=sc.disturbance)
    report = analyze(sc.model, log.as_logged_data())
    truth = {(sc.model.outputs[m.output], sc.model.inputs[m.input]): m for m in sc.mismatches}
    changes = {(c["output"], c["input"]): c for c in report.repair["changes"]}
    assert set(truth) == {("y1", "u1"), ("y1", "u3"), ("y1", "u4")} and set(changes) == set(truth)
    for key, m in truth.items():
        assert changes[key]["kind"] == m.kind and changes[key]["applied"] is True, key
        assert changes[key]["after"]["delay"] == m.plant["delay"]
    floor = float(np.sqrt(np.mean((log.disturbance + log.noise)[:, 0] ** 2)))
    assert report.repair["error_after"]["y1"] <= 1.02 * floor


def test_two_lags_that_the_loop_ties_together_are_moved_together():
    """bench.structures_mc --gained-lag seed 3 run 15: both pure gains of row y1, (y1, u1) and (y1, u2), gained a
    lag (26.3 s and 40.1 s) at the same dead times.  A first-order element's input lag is its dead time plus one
    sample, a pure gain's its dead time: the plant's lags lie one sample after the model's, for both.  The loop moves
    u1 and u2 together, and the cost is a valley along the diagonal: at the model's lags it was 6.0, with either lag
    alone a sample later 11.4 and 12.2, with both 2.4.  The coordinate search stayed at the model's lags; the
    classification then read (y1, u1) as a gain change (to 0.012, the plant's -1.78) and (y1, u2) as ``mixed``, step
    responses 100 % and 89 % off.  The search now also moves two lags together: both elements are the plant's."""
    from bench.structures_mc import StructuresOptions, step_response_error

    sc, report = structures_scenario_report(StructuresOptions(gained_lag=True), 15, seed=3)
    changes = {(c["output"], c["input"]): c for c in report.repair["changes"]}
    assert {(m["output"], m["column"]) for m in sc.mismatches} == {(0, 0), (0, 1)}
    for m in sc.mismatches:
        i, j = m["output"], m["column"]
        change = changes[(sc.model.outputs[i], sc.model.columns[j])]
        assert change["kind"] == "time_constant" and change["applied"] is True
        assert change["after"]["delay"] == m["plant"]["delay"]
        assert change["after"]["time_constant"] == pytest.approx(m["plant"]["time_constant"], rel=0.02)
        assert change["after"]["gain"] == m["model"]["gain"]
        assert step_response_error(sc.plant, report.repaired_model, i, j) <= 0.01


def test_two_lags_that_the_loop_ties_together_are_also_exchanged():
    """bench.repair_mc --dither-fat seed 6 run 120 (2x7): row y2 has three mismatches, (y2, u2) a gain 97 % high in
    the plant, (y2, u4) 4 s less dead time, (y2, u5) a larger gain, a slower lag and 8 s of dead time.  u2 and u5 move
    together (their increments correlated 0.89).  The search came to rest with their dead times exchanged (u2's 8 s,
    u5's none) and u4's at none; the kinds came out mixed, delay and mixed, u2's gain unchanged, the row still flagged
    and its error 0.0288 against the plant's 0.0260.  The exchanged lags already cost 0.82 of that fit: the search
    now also exchanges two lags, and every element is repaired in its kind at the plant's dead time."""
    from bench.scenarios import ScenarioOptions, make_scenario
    from mpm_monitor.sim.closed_loop import run_closed_loop

    sc = make_scenario(6, 120, dataclasses.replace(ScenarioOptions(), dither_fat=True))
    log = run_closed_loop(sc.plant, sc.model, 3000, seed=sc.loop_seed, mpc=sc.mpc, excitation=sc.excitation,
                          disturbance=sc.disturbance)
    report = analyze(sc.model, log.as_logged_data())
    drawn = {(sc.model.outputs[m.output], sc.model.inputs[m.input]): m for m in sc.mismatches}
    assert set(drawn) == {("y2", "u2"), ("y2", "u4"), ("y2", "u5")}
    assert {e: k for e, k in ((x.input, x.kind) for x in report.elements if x.mismatch)} == \
        {"u2": "gain", "u4": "delay", "u5": "mixed"}
    changes = {(c["output"], c["input"]): c for c in report.repair["changes"]}
    for key, m in drawn.items():
        assert changes[key]["applied"] is True and changes[key]["after"]["delay"] == m.plant["delay"]
    assert changes[("y2", "u2")]["after"]["gain"] == pytest.approx(2.038, rel=0.05)
    assert report.repair["error_after"]["y2"] < 0.027


def test_a_shape_held_at_the_reference_is_also_tried_at_the_references_input_lag():
    """bench.structures_mc run 6: only the gain of the integrating disturbance element (y2, dv1) changed (lags of
    4.2 s and 1.9 s, a lead of -1.1 s, 3 s of dead time).  The free fit put its input lag two samples late, its lead
    traded against that (the data cannot tell them apart: holding the reference's lag alone fits within the noise).
    The time-constant test held the model's shape at the free fit's lag, where it fits badly (p = 7e-61), and the
    kind came out ``mixed``, the lags and the lead written as 3.07 s, 3.07 s and -0.94 s.  The shape is now also
    tried at the reference's own lag: the kind is ``gain``, and only the gain is re-estimated."""
    from bench.structures_mc import StructuresOptions

    mismatch, change = _scenario_change(StructuresOptions(), 6, "disturbance_gain")
    assert change["kind"] == "gain" and change["applied"] is True
    assert change["evidence"]["p_time_constant"] > 0.01
    for key in ("time_constant", "time_constant2", "lead", "delay"):
        assert change["after"][key] == mismatch["model"][key] == mismatch["plant"][key], key
    assert change["after"]["gain"] == pytest.approx(mismatch["plant"]["gain"], rel=0.01)


def test_the_joint_test_frees_the_parameter_whose_release_fits_best():
    """bench.structures_mc run 262: in row y2, u1's time constant (69 s for the plant's 50 s) and u2's gain (-0.15 for
    -0.63) were off, u2's gain the only change its own test found.  Holding the rest together did not fit (p = 5e-46),
    and the joint test freed u2's time constant, the smallest single p-value, which explained nothing of the misfit
    (p = 3e-46 after it), then u1's gain: u1 read as ``gain`` (its step response 33 % off, from 12 %) and u2 as
    ``mixed``.  Freeing u1's time constant, the release that fits best (p = 0.5 after it), names both kinds right."""
    from bench.structures_mc import StructuresOptions, step_response_error

    sc, report = structures_scenario_report(StructuresOptions(), 262)
    kinds = {(c["output"], c["input"]): c["kind"] for c in report.repair["changes"] if c["applied"]}
    assert kinds == {("y2", "u1"): "time_constant", ("y2", "u2"): "gain"}
    assert {m["kind"] for m in sc.mismatches} == {"time_constant", "gain"}
    for j in (0, 1):
        assert step_response_error(sc.plant, report.repaired_model, 1, j) < 0.05


def test_the_joint_tests_warning_names_the_other_releases_that_fit_too():
    """bench.structures_mc run 52: y2/u3's time constant was off, and releasing either its gain (p = 0.80 after it)
    or its time constant (p = 0.67) let the joint test of the rest pass, their Akaike criteria 0.71 apart; the
    gain's, fitting better, was freed and named the kind.  The warning now says that the other release fits almost
    as well.  One whose criterion is more than 2 higher, or whose joint test still rejects, is not named."""
    from types import SimpleNamespace

    from mpm_monitor.core.repair.classify import _other_releases

    free = SimpleNamespace(row=SimpleNamespace(name=lambda j: f"y2/u{j + 1}"))
    released = {(2, "gain"): (3.62, 0.804), (2, "time_constant"): (4.33, 0.674), (0, "delay"): (50.6, 6e-10)}
    text = _other_releases(free, released, (2, "gain"), 0.001)
    assert text == (" Freeing the time constant of y2/u3 (p = 0.67, criterion 0.71 higher) instead fits almost as well "
                     "(Akaike's criterion within 2 of this one's, p = 0.8): the data do not tell these changes apart, "
                     "and the kind named may be the wrong one.")
    assert _other_releases(free, {**released, (2, "time_constant"): (5.63, 0.3)}, (2, "gain"), 0.001) == ""
    assert _other_releases(free, {**released, (2, "time_constant"): (4.33, 0.0009)}, (2, "gain"), 0.001) == ""
    both = _other_releases(free, {**released, (0, "gain"): (5.0, 0.2)}, (2, "gain"), 0.001)
    assert "the time constant of y2/u3 (p = 0.67, criterion 0.71 higher) or the gain of y2/u1 (p = 0.2" in both


def test_the_lag_scan_is_run_again_under_the_noise_model():
    """bench.structures_mc run 140: (y2, u2), an integrating element with two lags and an inverse-response lead, had
    its dead time one sample longer than the model's.  The lag search's scan, made before the noise model
    (output error), settled at a lag of 6 samples with a lag of 2,000 s and a lead of 1,817 s; under the noise model
    the model's own shape at the plant's lag of 3 fits better (0.3025 against 0.3129), but only moves of one sample
    were tried from there.  The kind was ``mixed`` (the shape's test held it at the lag of 6).  The scan is now run
    again under the noise model, fitting what beats the fit so far: ``delay``, the shape kept."""
    from bench.structures_mc import StructuresOptions

    mismatch, change = _scenario_change(StructuresOptions(), 140, "delay")
    assert change["kind"] == "delay" and change["applied"] is True
    after, plant = change["after"], mismatch["plant"]
    assert after["delay"] == plant["delay"] == 2.0
    for key in ("time_constant", "time_constant2", "lead"):
        assert after[key] == pytest.approx(plant[key], rel=0.02)


def test_a_lead_lag_step_response_element_read_in_one_lag_is_not_changed():
    """A random loop of ``bench.structures_mc`` (family 7, run 8): (y2, u1) lost part of a lag; (y2, dv1), a lag
    of 50.7 s with a lead of 12.8 s and 3 s of dead time, is well modelled, and is located with it when the tail
    confirmation cannot run (data with gaps).  Re-estimated together, the parametric model's classification
    finds no change in (y2, dv1), which is then released.  In step-response form the data call for the
    two-lag form with a lead; its fit drops the second lag (one lag, the dead time 3 s), while the old
    response read in the two-lag form had a second lag of 0.11 s and 2 s of dead time: the element read as
    changed (``mixed``: time constant and delay, p = 0) and stayed located.  The old response is now read in
    the one-lag form the fit was reduced to: ``unknown``, released, as with the parametric model."""
    from bench import structures_mc
    from bench.step_models import step_form
    from mpm_monitor.core.repair import explained_elements

    sc = structures_mc.make_structures_scenario(7, 8)
    data = structures_mc.simulate(sc, 3000).as_logged_data()
    assert sc.model.lead[1, 2] > 0 and sc.model.time_constant2[1, 2] == 0
    for model in (sc.model, step_form(sc.model)):
        joint = explained_elements(model, data, [(1, 0), (1, 2)])
        _, (_, verdicts, _) = joint.rows[1]
        assert verdicts[0].kind == "time_constant" and verdicts[2].kind == "unknown"
        assert joint.released == {(1, 2): [0]}


@pytest.mark.parametrize("seed", [5, 6])
def test_a_lead_cancelling_a_lag_the_plant_lacks_is_dropped_with_it(seed):
    """The model's (y2, u2) is ``1.5 (4.5 s + 1) / ((9 s + 1)(4.5 s + 1))``, a first-order response written with a
    lead that cancels its second lag; the plant's is ``1.8 / (7 s + 1)``.  Fitted with the pair, the gain was held
    at the model's and the pair made it up within the record (a second lag of 2,000 s and a lead of 2,400 s on such
    a log, intervals unbounded), marked applied.  The pair is refitted away: the plant's gain and lag, no lead."""
    model = first_order_model().with_element(1, 1, time_constant2=4.5, lead=4.5)
    plant = first_order_model().with_element(1, 1, gain=1.8, time_constant=7.0)
    report = analyze(model, open_loop(plant, model, 3000, seed=seed, burn_in=300))
    assert ("y2", "u2") in report.located_elements
    change = next(c for c in report.repair["changes"] if (c["output"], c["input"]) == ("y2", "u2"))
    after = change["after"]
    assert change["applied"] is True
    assert after["gain"] == pytest.approx(1.8, rel=REL) and after["time_constant"] == pytest.approx(7.0, rel=0.05)
    assert after.get("time_constant2", 0.0) == 0.0 and after.get("lead", 0.0) == 0.0
    new = report.repaired_model.discrete_element(1, 1).step_response(300)
    true = plant.discrete_element(1, 1).step_response(300)
    assert np.max(np.abs(new - true)) <= 0.02 * np.max(np.abs(true))


def test_a_lead_over_two_lags_that_the_plant_has_is_kept():
    """(y2, dv1) of the rich model is ``-0.5 (2 s + 1) / ((12 s + 1)(3 s + 1))``, its lead within 50 % of its
    second lag, and the plant's gain is -0.7: the element is refitted without the pair too, which fits
    significantly worse, so the repair keeps the lead and the second lag and changes the gain."""
    model = rich_model()
    plant = model.with_element(1, 2, gain=-0.7)
    report = analyze(model, open_loop(plant, model, 3000, seed=3, burn_in=300))
    assert ("y2", "dv1") in report.located_elements
    change = next(c for c in report.repair["changes"] if (c["output"], c["input"]) == ("y2", "dv1"))
    after = change["after"]
    assert change["applied"] is True and change["kind"] == "gain"
    assert after["gain"] == pytest.approx(-0.7, rel=REL)
    assert after["time_constant2"] == pytest.approx(3.0, rel=0.1) and after["lead"] == pytest.approx(2.0, rel=0.1)


def test_an_inverse_response_that_lost_a_lag_keeps_its_lead_when_the_fit_took_a_slow_pair():
    """``bench.structures_mc --lost-lag`` seed 7 run 126: row y4's u1 is an integrator with an inverse response,
    ``0.0392 (1 - 2.5 s) / (s (12.2 s + 1)(5.7 s + 1))`` in the model, and the plant lost the 5.7 s lag.  Fitted in
    the model's form the element came to rest at a lead of 1,781 s over a lag of 2,000 s (a slow pair, SSR 0.331),
    not at the plant's shape (SSR 0.282 in one lag and a lead), and the pair was refitted away with the lead: one
    lag of 10.2 s and a sample more dead time, kind "mixed", the element located again in the repaired model.  The
    lead is tried kept with the other lag first, from the model's lead: the plant's shape, one lag fewer."""
    from bench.structures_mc import StructuresOptions, make_structures_scenario, simulate

    options = StructuresOptions(lost_lag=True)
    sc = make_structures_scenario(7, 126, options)
    assert sc.model.element(3, 0)["time_constant2"] == 5.7 and sc.plant.element(3, 0).get("time_constant2", 0.0) == 0.0
    assert sc.plant.element(3, 0)["lead"] == -2.5 and sc.plant.element(3, 0)["time_constant"] == 12.2
    report = analyze(sc.model, simulate(sc, 3000, options).as_logged_data())
    change = next(c for c in report.repair["changes"] if (c["output"], c["input"]) == ("y4", "u1"))
    after = change["after"]
    assert change["applied"] is True and change["kind"] == "time_constant"
    assert after.get("time_constant2", 0.0) == 0.0 and after["delay"] == 4.0
    assert after["lead"] == pytest.approx(-2.5, rel=0.1) and after["time_constant"] == pytest.approx(12.2, rel=0.05)
    new = report.repaired_model.discrete_element(3, 0).step_response(300)
    true = sc.plant.discrete_element(3, 0).step_response(300)
    assert np.max(np.abs(new - true)) <= 0.01 * np.max(np.abs(true))
    assert ("y4", "u1") not in [(x["output"], x["input"]) for x in report.repair["located_after"]]


def test_delays_in_seconds_are_whole_samples_as_a_model_file_writes_them():
    """Stop 73's audit: with a sample time of 0.1 s an unchanged delay of 6 samples was written 0.6000000000000001
    (6 x 0.1 in floating point) in the repaired model and the report."""
    from mpm_monitor.core.repair.forms import FIRST_ORDER, _Form, _fitted_params, _lag_seconds

    assert 6 * 0.1 != 0.6 and _lag_seconds(6, 0.1) == 0.6
    assert _lag_seconds(7, 1.0) == 7.0 and _lag_seconds(3, 1e-3) == 0.003 and _lag_seconds(0, 0.1) == 0.0
    assert _fitted_params(FIRST_ORDER, 1.0, (0.9,), 0.0, 7, 0.1)["delay"] == 0.6
    assert _fitted_params(_Form(n_lags=2), 1.0, (0.9, 0.5), 0.0, 7, 0.1)["delay"] == 0.6


def test_a_repair_that_leaves_its_row_flagged_says_so():
    """Stop 73's audit: a first-order model element whose plant has a lead (6 s) was repaired in its structure with
    its gain cut from 0.8 to 0.19, confidence 1, the row still flagged by the repaired model's detection, and no
    warning.  The warning names the row and what may be missing; its step-response form is repaired whole."""
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.sim.closed_loop import run_closed_loop
    from mpm_monitor.sim.mpc import MpcOptions

    model = PlantModel(sample_time=1.0, inputs=("ua", "ub"), outputs=("ya", "yb"), gain=[[1.5, 0.6], [0.8, 2.0]],
                       time_constant=[[20, 15], [25, 10]], delay=[[2, 3], [4, 1]])
    plant = PlantModel(sample_time=1.0, inputs=("ua", "ub"), outputs=("ya", "yb"), gain=[[1.5, 0.6], [0.8, 2.0]],
                       time_constant=[[20, 15], [25, 10]], delay=[[2, 3], [4, 1]], lead=[[0, 0], [6, 0]])
    log = run_closed_loop(plant, model, 3000, seed=1, mpc=MpcOptions())
    rep = analyze(model, log.as_logged_data(source="lead"), AnalysisOptions(jobs=1))
    assert rep.located_elements == [("yb", "ua")]
    assert rep.repair["rows_flagged_after"] == ["yb"]
    (w,) = [w for w in rep.warnings if w.startswith("yb: still flagged after the repair of ua; ")]
    assert "does not explain the row's mismatch whole" in w and "a lead, a second lag" in w
    assert w in rep.repair["warnings"]
    # Since stop 80: the repaired model's detection locates the repaired element again, and the warning says so.
    assert [(x["output"], x["input"]) for x in rep.repair["located_after"]] == [("yb", "ua")]
    assert "the detection of the repaired model locates the element of ua again" in w


#: Elements of two lags and a lead the plant keeps but for one lag: (row, column, the model's element).  A lead of
#: 17 s over lags of 30 s and 18 s reads first order within 1 %; an integrator with a lead of 9 s over lags of 12 s
#: and 4 s reads in one lag no better than in two without the lead; an integrator with an inverse response.
LEAD_ELEMENTS = {
    "lead-over-two-lags": (1, 2, dict(gain=-0.5, time_constant=30.0, time_constant2=18.0, lead=17.0, delay=4.0)),
    "integrator-with-a-lead": (1, 0, dict(gain=0.05, time_constant=12.0, time_constant2=4.0, lead=9.0, delay=3.0,
                                          integrating=True)),
    "integrator-inverse-response": (1, 0, dict(gain=0.05, time_constant=12.0, time_constant2=6.0, lead=-4.0,
                                               delay=0.0, integrating=True)),
}


@pytest.mark.parametrize("name", list(LEAD_ELEMENTS))
def test_a_step_response_with_a_lead_that_lost_a_lag_is_a_time_constant_change(name):
    """The step-response form of an element of two lags and a lead; the plant lost the second lag.  Each came out
    ``mixed``: the first, read first order, was fitted in one lag and a lead, and that form's reading of its old
    response had a sample more dead time than the plant; the integrators were read in one lag (their first time
    constant tried from the ramp, not from the pulse response, and the ladder stopped at two lags that read no
    better).  Now the dead time is held from the reading in two lags and a lead: ``time_constant``, the dead time
    kept, the repaired response the plant's.  A pure gain change stays ``gain``."""
    from bench.step_models import step_form

    i, j, element = LEAD_ELEMENTS[name]
    model = rich_model().with_element(i, j, **element)
    for plant, kind in ((model.with_element(i, j, time_constant2=0.0), "time_constant"),
                        (model.with_element(i, j, gain=1.5 * element["gain"]), "gain")):
        res = repair_model(step_form(model), open_loop(step_form(plant), step_form(model), 3000, seed=21,
                                                       burn_in=300), [(i, j)])
        (change,) = res.changes
        assert change["kind"] == kind and change["applied"] is True
        before, fitted = change["evidence"]["parametric_before"], change["evidence"]["parametric_after"]
        assert before["delay"] == fitted["delay"] == element["delay"]
        if kind == "time_constant":             # held from its exact reading in two lags and a lead
            assert before["time_constant2"] == pytest.approx(element["time_constant2"], rel=1e-6)
        new = res.model.step_response[i, j]
        true = plant.discrete_element(i, j).step_response(new.size + 1)[1:]
        if element.get("integrating"):          # the pulse responses: a ramp's own size grows with its length
            new, true = np.diff(new), np.diff(true)
        assert np.max(np.abs(new - true)) <= 0.02 * np.max(np.abs(true))


@pytest.mark.parametrize("seed", [22, 23, 26, 28])
def test_an_integrators_lag_of_one_sample_is_not_taken_for_dead_time(seed):
    """(y2, dv1) an integrator with lags of 2.9 s and 1.0 s (one sample), the disturbance switching between levels;
    the plant's gain is 2.3 times the model's, nothing else changed.  The fit may take the lag of a sample for a
    sample of dead time (a lag of a seventh of a sample, the dead time one longer), which fits no better than the
    model's shape and dead time; the lag was then tried away, and the lag and the dead time both seemed changed:
    ``mixed`` in 4 of 12 records on either form.  A lag is tried away now only where the model's shape and dead
    time do not fit: ``gain``, the shape and the dead time the model's."""
    from bench.step_models import step_form

    model = rich_model().with_element(1, 2, gain=0.0124, time_constant=2.9, time_constant2=1.0, lead=0.0, delay=1.0,
                                      integrating=True)
    plant = model.with_element(1, 2, gain=0.0289)
    rng = np.random.default_rng(seed + 1000)
    n = 3300
    switches = np.cumsum(rng.random(n) < 0.02)
    dv = rng.choice([-1.0, 1.0], size=switches[-1] + 1)[switches] + lfilter([1.0], [1.0, -0.9],
                                                                            0.1 * rng.standard_normal(n))
    for m, p in ((model, plant), (step_form(model), step_form(plant))):
        res = repair_model(m, open_loop(p, m, 3000, seed=seed, burn_in=300, dv=dv[:, None]), [(1, 2)])
        (change,) = res.changes
        assert change["kind"] == "gain" and change["applied"] is True
        fitted = change["evidence"]["parametric_after"] if m.is_step_response else change["after"]
        assert fitted["delay"] == 1.0 and fitted["time_constant2"] == pytest.approx(1.0, rel=1e-6)
        assert fitted["gain"] == pytest.approx(0.0289, rel=0.05)


def test_the_delay_test_rejects_the_models_dead_time_only_where_the_models_shape_there_does_not_fit(monkeypatch):
    """``bench.structures_mc`` seed 0 run 64 in step-response form: (y1, dv2), an integrator with lags of 2.9 s and
    1.0 s, its gain 2.3 times the model's.  With one BLAS thread the fit kept lags of 2.4 s and 0.38 s a sample
    later; the delay test's shape searched from there found none at the model's dead time within p = 0.0005, while
    the model's own shape there fitted within p = 0.13 (one degree of freedom): ``mixed``.  Every delay test at a
    reference's own dead time must now pass where the reference's shape passes there; the element is ``gain``."""
    import warnings

    from bench import structures_mc
    from bench.step_models import step_form
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.repair import classify
    from mpm_monitor.core.statistics import chi2_tail

    checked = []
    lag_p = classify._FreeFit.lag_p

    def checked_lag_p(self, m, lag):
        p = lag_p(self, m, lag)
        loc = self.located[self.js[m]]
        if not loc.missing and lag == loc.held_lag(False):
            reference_p = float(chi2_tail(self.hold_statistic({m: {"pole", "lag"}}, self.settings.options), 1))
            checked.append((p, reference_p))
            assert p >= self.settings.alpha or reference_p < self.settings.alpha
        return p

    monkeypatch.setattr(classify._FreeFit, "lag_p", checked_lag_p)
    sc = structures_mc.make_structures_scenario(0, 64, structures_mc.StructuresOptions())
    data = structures_mc.simulate(sc, 3000).as_logged_data(source="run 64")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = analyze(step_form(sc.model), data, AnalysisOptions(alpha=0.01))
    assert checked
    assert report.repair_result.kinds[(0, 5)] == "gain"


#: A model element with a direct feed-through (analyze accepts it; a closed loop refuses it): (y1, u2) of the rich
#: model with no dead time, a lead over one lag or a pure gain; the plant's change.
FEEDTHROUGH = {
    "lead-lag-gain": (dict(delay=0.0), dict(gain=1.5), "gain"),
    "lead-lag-lead": (dict(delay=0.0), dict(lead=-5.0), "time_constant"),
    "lead-lag-delay": (dict(delay=0.0), dict(delay=2.0), "delay"),
    "pure-gain-gain": (dict(time_constant=0.0, lead=0.0, delay=0.0), dict(gain=1.5), "gain"),
}


@pytest.mark.parametrize("name", list(FEEDTHROUGH))
def test_a_model_element_with_a_feed_through_is_repaired_in_it(name):
    """The repair searched every element from an input lag of one sample, so a model element acting at the sample
    of its input could not be held at its own dead time: its delay test rejected outright, and a gain or lead
    change came out ``mixed`` (gain 1.66, lead -1.0, one sample of dead time) or ``unknown``.  An element the model
    gives a feed-through is searched from lag 0 now: the kind right and the element the plant's."""
    element, change, kind = FEEDTHROUGH[name]
    model = rich_model().with_element(0, 1, **element)
    plant = model.with_element(0, 1, **change)
    report = analyze(model, open_loop(plant, model, 3000, seed=21, burn_in=300))
    assert report.located_elements == [("y1", "u2")]
    (entry,) = report.repair_result.changes
    assert entry["kind"] == kind and entry["applied"] is True
    for key, value in plant.element(0, 1).items():
        assert entry["after"][key] == pytest.approx(value, rel=0.02, abs=0.02), key


def test_a_delay_test_whose_profile_fits_better_than_the_free_fit_passes():
    """bench.structures_mc seed 4 run 165 (a seed bench.structures_pool pools; its kinds never looked at before):
    the measured disturbance's integrator with a lead on y4 had only its gain changed (-0.035 to -0.0211).  The
    free fit stopped at an input lag of 2, the model's is 6; the profile at 6, computed from the fit's shape,
    fitted better than the fit, and its negative likelihood ratio gave a delay p-value that was not a number
    (``p_delay`` null in the report).  The shape test then held the model's shape at lag 2 only (p = 1.7e-50)
    and the kind was ``mixed``.  The statistic is 0 there now: the delay unchanged (p = 1), the model's shape
    held at its own dead time, the kind ``gain``."""
    from bench.structures_mc import StructuresOptions

    sc, report = structures_scenario_report(StructuresOptions(), 165, seed=4)
    (m,) = sc.mismatches
    assert m["kind"] == "disturbance_gain" and m["model"]["integrating"] and m["model"]["lead"] > 0
    change = next(c for c in report.repair["changes"]
                  if (c["output"], c["input"]) == (sc.model.outputs[m["output"]], sc.model.columns[m["column"]]))
    assert change["kind"] == "gain" and change["applied"] is True
    assert change["evidence"]["p_delay"] == 1.0 and change["evidence"]["p_time_constant"] == 1.0
    assert change["after"]["gain"] == pytest.approx(m["plant"]["gain"], rel=0.01)
    for key in ("time_constant", "lead", "delay"):
        assert change["after"][key] == m["model"][key]


def test_a_step_response_row_whose_fit_moved_after_its_noise_model_is_read_from_the_moved_fit():
    """bench.step_models --lost-lag seed 4 run 66 (never looked at before): two lead-lag elements of y1 lost their
    second lag.  In the model's step-response form both came out ``mixed`` and 40 % and 45 % off, the parametric
    form's ``time_constant`` and within 0.4 %.  The first fit (first order for the element whose old response
    reads as one lag) let the noise model take a unit root, with both gains cut by about half; the larger form, fitted
    from the ladder's start, moved its lags and poles after its last noise model (the scan under it), and was
    compared under that stale model: 0.91 against 0.35, though one more estimate of its noise model gives 0.24.
    The noise model is now estimated again from a fit that moved after it: both ``time_constant``, within 2 %."""
    from bench import structures_mc
    from bench.step_models import step_form

    sc = structures_mc.make_structures_scenario(4, 66, structures_mc.StructuresOptions(lost_lag=True))
    data = structures_mc.simulate(sc, 3000).as_logged_data("structures scenario 4/66")
    model = step_form(sc.model)
    res = repair_model(model, data, [(m["output"], m["column"]) for m in sc.mismatches])
    for m in sc.mismatches:
        i, j = m["output"], m["column"]
        assert m["kind"] == "lost_lag" and res.kinds[(i, j)] == "time_constant"
        assert structures_mc.step_response_error(sc.plant, res.model, i, j) < 0.02


def test_a_step_response_lag_that_vanished_in_the_start_form_goes_before_the_ladder_climbs():
    """bench.step_models --lost-lag seed 4 run 63 (never looked at before): the plant's (y1, u1) lost the model's second
    lag (25.4 s; one lag of 55.9 s left).  In the step-response form the fit in the start form (two lags, the old
    response's) took the second lag to its bound and the first to 38 s with the gain 27 % short; the ladder then took a
    lead and two lags, significantly better than that fit, and the element was repaired 17 % off, read as lags of 67 s
    and 2,000 s and a lead of 2,400 s (the parametric form 0.2 % off).  The vanished lag now goes first: one lag,
    the ladder's larger forms no better than it, and the repair within 1 %."""
    from bench import structures_mc
    from bench.step_models import step_form

    sc = structures_mc.make_structures_scenario(4, 63, structures_mc.StructuresOptions(lost_lag=True))
    data = structures_mc.simulate(sc, 3000).as_logged_data("structures scenario 4/63")
    (m,) = sc.mismatches
    i, j = m["output"], m["column"]
    res = repair_model(step_form(sc.model), data, [(i, j)])
    assert m["kind"] == "lost_lag" and res.kinds[(i, j)] == "time_constant"
    assert structures_mc.step_response_error(sc.plant, res.model, i, j) < 0.01
    after = res.changes[0]["evidence"]["parametric_after"]
    assert after.get("lead", 0.0) == 0.0 and after.get("time_constant2", 0.0) == 0.0
    assert after["time_constant"] == pytest.approx(m["plant"]["time_constant"], rel=0.03)


@pytest.mark.parametrize("index", [22, 255])
def test_a_pure_gains_dead_time_change_whose_fit_shows_a_hair_of_lag_is_a_delay(index):
    """bench.structures_mc --pure-gains seed 4 runs 22 and 255 (never run before): a pure gain of the model (dead
    time 1 s) is a sample later in the plant.  Fitted first order, its pole came out 3e-4 or 4e-4, a hair above
    the reading of no lag (2e-4), so it read as a lag of T / 8 at the model's dead time; its time-constant test did
    not reject (the data show no lag), its delay test did, but the dead time read unchanged named no kind, the
    joint test freed the lag, and the kind was ``time_constant``.  A pure gain whose lag the data do not show is
    read as the pure gain it was fitted as: a ``delay`` change, written without a lag at the plant's dead time."""
    from bench.structures_mc import StructuresOptions

    m, change = _scenario_change(StructuresOptions(pure_gains=True), index, "delay", seed=4)
    assert m["model"]["time_constant"] == 0.0 and m["plant"]["delay"] == m["model"]["delay"] + 1
    assert change["kind"] == "delay" and change["applied"] is True
    assert change["after"]["time_constant"] == 0.0 and change["after"]["delay"] == m["plant"]["delay"]


@pytest.mark.parametrize("opts, seed, index, kind", [({}, 11, 267, "delay"), ({"lost_pair": True}, 5, 57, "lost_pair")])
def test_a_right_repair_whose_simulation_error_rose_a_little_is_accepted_one_step_ahead(opts, seed, index, kind):
    """bench.structures_mc seed 11 run 267 (an integrator's dead time 4 -> 5 s) and --lost-pair seed 5 run 57 (a
    gain under the model's cancelling pair), seeds never run before stop 77: the repair fitted the plant's element
    (the delay exactly, the gain within 1 %), whose held-out simulation error came out 0.7 % and 1.6 % above the
    model's (the disturbance the controller answered through the same input), not significantly, while its
    one-step error was significantly smaller (p = 8e-5 and 9e-6).  The simulation error alone refused both
    (``unknown``, 0.35 % and 29 % off); within the tolerance of 5 % the one-step errors decide."""
    from bench.structures_mc import REPORTED_KIND, StructuresOptions, step_response_error

    sc, report = structures_scenario_report(StructuresOptions(**opts), index, seed)
    (m,) = [m for m in sc.mismatches if m["kind"] == kind]
    i, j = m["output"], m["column"]
    (change,) = [c for c in report.repair["changes"]
                 if (c["output"], c["input"]) == (sc.model.outputs[i], sc.model.columns[j])]
    assert change["kind"] == REPORTED_KIND[kind] and change["applied"] is True
    assert step_response_error(sc.plant, report.repaired_model, i, j) < 0.03
    name = sc.model.outputs[i]
    assert 0.0 < report.repair["holdout_error_after"][name] / report.repair["holdout_error_before"][name] - 1.0 < 0.05
    assert any(w.startswith(f"{name}: the re-estimated element(s)") and "the repair is accepted" in w
               for w in report.repair["warnings"])


def test_on_a_loop_that_diverged_the_simulation_error_alone_decides_the_held_out_check():
    """bench.structures_mc --gained-lag seed 5 run 139: the loop diverged (errors of 1e8), and a false location's
    refit with the repair's default AR(4) noise model, 9 times the model's gain, predicted the held-out part one
    step ahead 0.07 % better (p = 0.002) with its simulation error within 1e-9 of the model's.  On a diverging loop
    the tests' p-values mean nothing: the simulation error alone decides, and the element is kept as the model has
    it.  (The analysis raises the tests' ``na`` to 16 on this loop and the repair's noise order with it; under
    AR(16) the one-step errors no longer differ and the element is kept all the same.)"""
    from bench.structures_mc import StructuresOptions, simulate

    sc, report = structures_scenario_report(StructuresOptions(gained_lag=True), 139, 5)
    assert any("grows without bound" in w for w in report.warnings)
    assert report.noise_order["na"] == 16 and report.repair["noise_order"] == 16
    (change,) = [c for c in report.repair["changes"] if (c["output"], c["input"]) == ("y2", "dv2")]
    assert not any(m["output"] == 1 and m["column"] == 5 for m in sc.mismatches)
    assert change["applied"] is False and change["kind"] == "unknown"
    data = simulate(sc, 3000, StructuresOptions(gained_lag=True)).as_logged_data("structures scenario 5/139")
    result = repair_model(sc.model, data, [(1, sc.model.columns.index("dv2"))], RepairOptions(noise_order=4))
    (change,) = result.changes
    assert change["applied"] is False and change["kind"] == "unknown"
    assert any(w.startswith("y2: the re-estimated element(s) dv2 did not predict") and "the loop diverged" in w
               for w in result.warnings)
