"""bench.quiet_rows: its counts, read from records made by hand, and one small real run."""

from bench import quiet_rows


def _rec(condition, mismatched, truth, located, released):
    return {"condition": condition, "mismatched": mismatched, "truth": truth, "located": located,
            "released": released}


def test_the_summary_counts_with_and_without_the_release():
    name = quiet_rows.CONDITIONS[1][0]
    records = [
        _rec(name, False, [], [], [["y1", "u1"]]),                       # a false alarm released
        _rec(name, False, [], [["y2", "u1"]], []),                       # a false alarm kept
        _rec(name, False, [], [], []),
        _rec(name, True, [["y1", "u2"]], [["y1", "u2"]], [["y2", "u2"]]),  # true located, a wrong one released
        _rec(name, True, [["y2", "u1"]], [], [["y2", "u1"]]),            # a true element released
    ]
    s = quiet_rows.summarize(records)[name]
    assert s["kept"] == {"false_alarms": 2, "clean": 3, "true_located": 2, "true": 2, "runs_with_wrong": 1,
                         "mismatched": 2}
    assert s["released"] == {"false_alarms": 1, "clean": 3, "true_located": 1, "true": 2, "runs_with_wrong": 0,
                             "mismatched": 2}
    assert (s["released_true"], s["released_wrong"], s["runs_released"]) == (1, 2, 3)
    assert quiet_rows.summarize(records)[quiet_rows.CONDITIONS[0][0]]["kept"]["clean"] == 0


def test_a_small_run_gives_records_of_every_condition():
    result = quiet_rows.run(runs=1, seed=3, samples=1500, jobs=1, alpha=0.01)
    assert len(result["records"]) == 2 * len(quiet_rows.CONDITIONS)
    for rec in result["records"]:
        assert not set(map(tuple, rec["located"])) & set(map(tuple, rec["released"]))
        assert len(rec["truth"]) == (1 if rec["mismatched"] else 0)
    text = quiet_rows.format_table(result)
    assert all(name in text for name, *_ in quiet_rows.CONDITIONS)
