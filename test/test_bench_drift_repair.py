"""bench.drift_repair: the repair under a drift on every output (a small case, one run)."""

import json

import pytest

from bench import drift_repair


def test_one_small_run_is_scored(tmp_path, capsys):
    out = tmp_path / "drift.json"
    assert drift_repair.main(["--size", "3", "--runs", "1", "--samples", "2000", "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    (record,) = result["records"]
    assert record["located"] == ["y1:u2"] and record["allowed_for"]        # the drift allowed for in y1's repair
    s = result["summary"]
    assert s["runs"] == 1 and s["located_y1_u2"] == 1 and s["false_locations"] == 0 and s["repaired"] == 1
    assert "located in 1 of 1" in capsys.readouterr().out


def test_summary_counts():
    records = [{"located": ["y1:u2"], "gain_error": 0.01, "allowed_for": True},
               {"located": ["y1:u2", "y2:u1"], "gain_error": 0.5, "allowed_for": False},
               {"located": [], "gain_error": None, "allowed_for": False}]
    s = drift_repair.summary(records)
    assert (s["located_y1_u2"], s["false_locations"], s["repaired"], s["within_2pct"], s["beyond_10pct"]) == (2, 1, 2, 1, 1)
    assert s["largest_error"] == 0.5 and s["allowed_for"] == 1


def test_bad_arguments_are_refused():
    with pytest.raises(SystemExit):
        drift_repair.main(["--runs", "0"])
