"""bench.candidates_mc --setpoint-steps: the loop with setpoints in steps, channels changed by hand, and what the
exogeneity test's F test alone would have decided."""

import numpy as np

from bench import candidates_mc


def test_a_hand_channel_has_its_steps_and_one_follows_a_setpoint_step_when_asked():
    rng = np.random.default_rng(3)
    free = candidates_mc.hand_steps(3000, rng)
    moves = np.flatnonzero(np.diff(free))
    assert 1 <= moves.size <= candidates_mc.HAND_STEPS and np.all(np.abs(free) <= 1.0)
    setpoint_steps = np.array([400, 1700, 2500])
    after = candidates_mc.hand_steps(3000, rng, setpoint_steps)
    steps = np.flatnonzero(np.diff(after)) + 1                  # the samples a new level starts at
    lags = steps[:, None] - setpoint_steps[None, :]
    assert np.any((lags >= 1) & (lags <= 5))


def test_a_level_run_with_setpoint_steps_records_both_decisions():
    rec = candidates_mc.null_run(0, 1, 1500, setpoint_steps=True)
    assert {"hand_steps", "hand_steps_after_setpoint"} <= set(rec["raw_p"]) | set(rec["not_exogenous"])
    # The test rejects only where the F test alone rejects too (its p-value is at least the F test's).
    assert set(rec["not_exogenous"]) <= set(rec["not_exogenous_by_f_alone"])
    res = {"seed": 0, "samples": 1500, "setpoints": "steps",
           "level": {"runs": 1, "alpha": 0.01, "false_alarm_rate": 0.0, "runs_with_not_exogenous": 0.0,
                     "runs_with_not_exogenous_by_f_alone": 1.0, "runs_with_element_located": 0.0,
                     "by_kind": {"steps by hand": {"channels": 1, "located": 0, "runs_with_one_located": 0,
                                                   "not_exogenous": 0, "not_exogenous_by_f_alone": 1,
                                                   "raw_tests": 3, "raw_rejection_at_5pct": 0.0}}},
           "detection": {"runs": 1, "located_rate": 1.0, "added_rate": 1.0, "decoys_added": 0,
                         "loop_channel_not_exogenous_rate": 1.0, "effect_channel_not_exogenous": 0,
                         "effect_channel_not_exogenous_by_f_alone": 0, "gain_error_median": None,
                         "before_over_floor_median": 10.0, "after_over_floor_median": 1.0,
                         "after_over_floor_max": 1.0, "after_within_10pct_of_floor": 1.0, "median_analyze_s": 0.1}}
    text = candidates_mc.format_table(res)
    assert "setpoints in steps" in text and "(F test alone 1)" in text and "7 unrelated candidates" in text
