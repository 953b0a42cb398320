"""bench.drift_mc: its drift, one record analysed both ways, and the summary's counting."""

import numpy as np

from bench.drift_mc import (ANALYSES, DRIFT_POLE, OTHER_DISTURBANCES, disturbance, drift, format_table, run_one,
                            setpoint_levels, summarize, variants)


def test_the_drift_is_the_ar1_it_says():
    v = drift("wood-berry", False, 0, 0.01, 2)
    assert v.shape == (4000, 2)
    e = v[1:] - DRIFT_POLE * v[:-1]                     # the innovations back
    assert abs(e.std() / 0.01 - 1) < 0.05 and abs(np.corrcoef(e[1:, 0], e[:-1, 0])[0, 1]) < 0.05
    assert np.array_equal(v, drift("wood-berry", False, 0, 0.01, 2))


def test_one_record_analysed_fixed_and_raised_and_summarized():
    rec = run_one("wood-berry", False, 6, "a0.005", {})
    assert rec["regime"] == "steps"
    assert rec["fixed"]["na_used"] == 4 and rec["raised"]["na_used"] > 4     # the drift colours na = 4's residual
    assert rec["raised"]["located"] == []
    recs = [rec, dict(rec, variant="none", mismatched=True, truth=[["xb", "steam"]],
                      fixed=dict(rec["fixed"], located=[["xb", "steam"], ["xd", "reflux"]]),
                      raised=dict(rec["raised"], located=[["xb", "steam"]]))]
    s = summarize(recs)
    assert set(s) == {"steps a0.005", "steps none"}
    assert s["steps a0.005"]["clean"] == 1 and s["steps none"]["mismatched"] == 1
    assert s["steps none"]["fixed"]["extra_located"] == 1 and s["steps none"]["raised"]["extra_located"] == 0
    assert s["steps none"]["raised"]["true_located"] == 1
    assert set(s["steps a0.005"]) >= set(ANALYSES)
    table = format_table({"summary": s, "config": {"seeds": 1, "plants": ["wood-berry"], "samples": 4000,
                                                   "overrides": {}}})
    assert "steps  a0.005   raised" in table


def test_the_levels_regime_holds_levels_in_range_for_their_time():
    r = setpoint_levels(np.random.default_rng(0), 4000, 3)
    assert r.shape == (4000, 3) and np.all(np.abs(r) <= 1.0)
    for i in range(3):
        first = int(np.flatnonzero(r[:, i])[0])
        assert 20 <= first < 100
        changes = np.flatnonzero(np.diff(r[first:, i])) + 1
        holds = np.diff(np.concatenate([[0], changes]))
        assert np.all(holds >= 150) and np.all(holds[:-1] < 400)
    rec = run_one("wood-berry", False, 3, "a0.005", {}, "levels")
    assert rec["regime"] == "levels" and "error" not in rec["raised"]


def test_the_other_disturbances_are_what_they_say_and_run_in_the_levels_regime_only():
    assert variants("steps") == ("none", "a0.005", "a0.01")
    assert variants("levels")[3:] == OTHER_DISTURBANCES
    assert disturbance("none", "3.1", False, 0, 3) is None
    np.testing.assert_array_equal(disturbance("a0.01", "3.1", False, 0, 3), drift("3.1", False, 0, 0.01, 3))
    sine = disturbance("sine", "3.1", False, 0, 3)
    assert sine.shape == (4000, 3) and abs(np.abs(sine).max() - 0.05) < 1e-4
    np.testing.assert_allclose(sine[200:], sine[:-200], atol=1e-12)               # period 200 samples
    steps = disturbance("steps", "3.1", False, 0, 3)
    jumps = np.abs(np.diff(steps, axis=0))
    assert set(np.round(jumps[jumps > 0], 12)) == {0.1} and 4 <= int((jumps > 0).sum()) <= 14
    walk = disturbance("walk", "3.1", False, 0, 3)
    assert abs(np.diff(walk, axis=0).std() / 0.001 - 1) < 0.05
    ar2 = disturbance("ar2", "3.1", False, 0, 3)
    innovation = ar2[2:] - 1.6 * ar2[1:-1] + 0.8 * ar2[:-2]
    assert abs(innovation.std() / 0.005 - 1) < 0.05
    slow = disturbance("drift995", "3.1", False, 0, 3)
    assert abs((slow[1:] - 0.995 * slow[:-1]).std() / 0.003 - 1) < 0.05
