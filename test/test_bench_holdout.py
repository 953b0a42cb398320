"""bench.holdout_mc: the held-out check scored against the plant."""

import dataclasses

from bench.holdout_mc import format_table, one, summarize
from bench.scenarios import SETPOINT_STEPS


def _check(run, simulation_alone, accepted, one_step_rule, better, wrong=()):
    return {"run": run, "output": "y1", "inputs": ["u1"], "simulation_alone": simulation_alone, "accepted": accepted,
            "one_step_rule": one_step_rule, "scored": True, "simulation_after": 1.0, "simulation_before": 1.1,
            "one_step_after": 0.5, "one_step_before": 0.6, "p_one_step": 0.01, "p_rise": 0.3, "better": better,
            "perturbed": [{"simulation_alone": a, "accepted": b, "one_step_rule": c, "worse": w} for a, b, c, w in wrong]}


def test_the_tally_counts_false_acceptances_and_held_back_repairs_for_the_three_rules():
    checks = [_check(0, True, True, True, True, [(False, False, True, True), (True, True, True, False)]),
              _check(1, False, True, True, True, [(False, True, True, True)]),
              _check(2, False, False, True, True), _check(3, True, True, True, False),
              _check(4, False, False, False, False),
              {"run": 5, "output": "y2", "inputs": ["u1"], "accepted": True, "scored": False}]
    res = summarize(checks)
    assert (res["checks"], res["scored"], res["better"], res["worse"]) == (6, 5, 3, 2)
    assert (res["wrong_made"], res["wrong_made_worse"]) == (3, 2)
    assert res["rules"]["simulation_alone"] == {"accepted": 2, "accepted_but_worse": 1, "refused_but_better": 2,
                                                "wrong_made_accepted": 0}
    assert res["rules"]["accepted"] == {"accepted": 3, "accepted_but_worse": 1, "refused_but_better": 1,
                                        "wrong_made_accepted": 1}
    assert res["rules"]["one_step_rule"] == {"accepted": 4, "accepted_but_worse": 1, "refused_but_better": 0,
                                             "wrong_made_accepted": 2}
    assert [c["run"] for c in res["differ"]] == [1]
    assert [c["run"] for c in res["unbounded_only"]] == [2]
    assert [c["run"] for c in res["refused"]] == [2, 4]
    text = format_table(res)
    assert "wrong made accepted   2 of 2" in text and "run   4 y1 (u1)" in text and "WORSE" in text
    assert "one step, within 5 % (default)" in text and "accepted only by the unbounded one-step route: 1" in text


def test_a_loop_whose_right_repair_the_simulation_error_alone_refuses_is_accepted_and_scored_better():
    # bench.repair_mc --setpoint-steps, run 17: (y2, u4) delay 5 -> 8 s, exactly the plant's.
    checks = one(0, 17, 3000, dataclasses.replace(SETPOINT_STEPS, dither_fat=True))
    (y2,) = [c for c in checks if c["output"] == "y2"]
    assert y2["scored"] and y2["better"] and not y2["simulation_alone"] and y2["accepted"] and y2["one_step_rule"]
    assert y2["truth_after"] < 1e-9 < y2["truth_before"]
    assert y2["p_one_step"] < 0.05 <= y2["p_rise"] and y2["one_step_after"] < y2["one_step_before"]
    # Each wrong candidate made of it is checked and scored.
    assert [w["perturbation"] for w in y2["perturbed"]] == ["gain x0.5", "gain x1.5", "time constant x2"]
