"""bench.drift_mc: its drift, one record analysed both ways, and the summary's counting."""

import numpy as np

from bench.drift_mc import ANALYSES, DRIFT_POLE, DRIFTS, drift, format_table, run_one, summarize


def test_the_drift_is_the_ar1_it_says():
    v = drift("wood-berry", False, 0, 0.01, 2)
    assert v.shape == (4000, 2)
    e = v[1:] - DRIFT_POLE * v[:-1]                     # the innovations back
    assert abs(e.std() / 0.01 - 1) < 0.05 and abs(np.corrcoef(e[1:, 0], e[:-1, 0])[0, 1]) < 0.05
    assert np.array_equal(v, drift("wood-berry", False, 0, 0.01, 2))


def test_one_record_analysed_fixed_and_raised_and_summarized():
    rec = run_one("wood-berry", False, 6, "a0.005", {})
    assert rec["fixed"]["na_used"] == 4 and rec["raised"]["na_used"] > 4     # the drift colours na = 4's residual
    assert rec["raised"]["located"] == []
    recs = [rec, dict(rec, variant="none", mismatched=True, truth=[["xb", "steam"]],
                      fixed=dict(rec["fixed"], located=[["xb", "steam"], ["xd", "reflux"]]),
                      raised=dict(rec["raised"], located=[["xb", "steam"]]))]
    s = summarize(recs)
    assert s["a0.005"]["clean"] == 1 and s["none"]["mismatched"] == 1
    assert s["none"]["fixed"]["extra_located"] == 1 and s["none"]["raised"]["extra_located"] == 0
    assert s["none"]["raised"]["true_located"] == 1
    assert set(s["a0.005"]) >= set(ANALYSES) and set(s) == set(DRIFTS)
    table = format_table({"summary": s, "config": {"seeds": 1, "plants": ["wood-berry"], "samples": 4000,
                                                   "overrides": {}}})
    assert "a0.005  raised" in table
