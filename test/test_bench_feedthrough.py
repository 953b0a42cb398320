"""bench.feedthrough_mc: a few runs end to end, its summary against its records."""

from bench import feedthrough_mc


def test_feedthrough_mc_draws_a_feedthrough_model_and_scores_its_runs(tmp_path, capsys):
    seen = set()
    for k in range(12):
        plant, model, structure, change = feedthrough_mc.draw(0, k)
        seen.add(change)
        assert model.discrete_element(0, 0).input_lag == 0 and model.delay[0, 0] == 0.0
        assert (model.time_constant[0, 0] == 0.0) == (structure == "pure_gain")
        # Only (y1, u1) differs, and only where the run has a change.
        assert (plant.element(0, 0) != model.element(0, 0)) == (change != "none")
        assert all(plant.element(i, j) == model.element(i, j) for i in range(2) for j in range(3) if (i, j) != (0, 0))
    assert seen == set(feedthrough_mc.EXPECTED_KIND)
    out = tmp_path / "ft.json"
    assert feedthrough_mc.main(["--runs", "6", "--seed", "2", "--samples", "1500", "--out", str(out)]) == 0
    import json

    result = json.loads(out.read_text())
    s, records = result["summary"], result["records"]
    assert s["runs"] == len(records) == 6
    hits = [r for r in records if r["change"] != "none" and [0, 0] in r["located"]]
    assert s["located"] == len(hits)
    assert s["kind_right"] == sum(r["kinds"]["0,0"] == feedthrough_mc.EXPECTED_KIND[r["change"]] for r in hits)
    assert s["clean_runs"] == sum(r["change"] == "none" for r in records)
    assert sum(x["runs"] for x in s["by_structure"].values()) == 6
    assert s["located_after_new"] + s["located_after_again"] == sum(len(r["located_after"]) for r in records)
    assert "feed-through model elements" in capsys.readouterr().out
