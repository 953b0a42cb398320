"""bench.drift_intervals: the truth it scores against, one record and the summary's counting."""

from bench.drift_intervals import format_table, group_of, run_one, scored_changes, summarize, true_kind
from bench.quiet_loops import plant_of


def test_the_true_kind_is_what_differs_between_plant_and_model():
    model, plant = plant_of("wood-berry", True)[:2]
    assert true_kind(model, plant, 1, 1) == "gain" and true_kind(model, plant, 0, 0) is None
    model, plant = plant_of("3.2", True)[:2]
    kinds = {(i, j): true_kind(model, plant, i, j) for i in range(3) for j in range(3)}
    assert {k: v for k, v in kinds.items() if v} == {(0, 1): "mixed", (0, 2): "gain", (1, 0): "time_constant"}
    assert group_of("none") == "none" and group_of("a0.005") == "drift" and group_of("sine") == "other"


def test_an_interval_is_scored_against_the_plants_value():
    model, plant = plant_of("wood-berry", True)[:2]
    g = float(plant.gain[1, 1])
    change = {"output": "xb", "input": "steam", "kind": "gain", "applied": True,
              "interval": {"gain": [g - 0.1, g + 0.1], "time_constant": [15.0, 16.0], "delay": [3.0, 3.0]}}
    (c,) = scored_changes(model, plant, [change])
    assert c["held"] == {"gain": True, "time_constant": False, "delay": True} and c["true_kind"] == "gain"
    (c,) = scored_changes(model, plant, [dict(change, interval={"gain": [g + 0.01, g + 0.1]})])
    assert c["held"] == {"gain": False}


def test_one_record_and_the_summary():
    rec = run_one("wood-berry", True, 0, "a0.01", "levels")
    assert rec["na"] > 4 and rec["noise_order"] == rec["na"]       # the drift raised na, and the repair's order
    assert rec["located"] == [["xb", "steam"]]
    (c,) = rec["changes"]
    assert c["mismatched"] and c["true_kind"] == "gain" and set(c["held"]) == {"gain", "time_constant", "delay"}
    clean = dict(rec, mismatched=False, truth=[], located=[], changes=[], disturbances=[["xd", "step", 0.1]])
    s = summarize([rec, clean, dict(clean, variant="none", disturbances=[])])
    assert set(s) == {"drift", "none"}
    assert s["drift"]["disturbances_clean"] == [1, 1] and s["none"]["disturbances_clean"] == [0, 1]
    assert s["drift"]["kinds_right"] == [int(c["kind"] == "gain"), 1]
    assert s["drift"]["intervals_mismatched"]["gain"] == [int(c["held"]["gain"]), 1]
    table = format_table({"summary": s, "config": {"seeds": 1, "plants": ["wood-berry"], "samples": 4000}})
    assert table.splitlines()[2].startswith("none  ") and "drift" in table
    assert s["drift"]["disturbances_clean_by_variant"] == {"a0.01": [1, 1]}
    assert s["none"]["disturbances_clean_by_variant"] == {"none": [0, 1]}
    assert "clean loops with a disturbance reported: a0.01 1/1" in table
