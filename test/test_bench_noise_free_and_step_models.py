"""bench.noise_free and bench.step_models: a few runs end to end, their summaries against their records."""

from bench import noise_free, step_models
from mpm_monitor.core.repair import KINDS


def test_noise_free_scores_its_records():
    result = noise_free.run(3, seed=0, samples=1500)
    s = result["summary"]
    assert s["runs"] == 3 and len(result["records"]) == 3
    # With the plant as its model no row is flagged in a log without noise (the exact fits).
    assert s["plant_as_model"]["rows_flagged"] == 0 and s["plant_as_model"]["runs_with_any_alarm"] == 0
    assert s["model_as_drawn"]["of_them_flagged"] == 0
    assert "plant as its model: 0 of 3 runs" in noise_free.format_table(result)


def test_step_models_compares_the_two_forms_of_the_model():
    result = step_models.run(3, seed=5, samples=2000)
    s = result["summary"]
    assert s["scored"] == 3
    for r in result["records"]:
        assert r["step_length"] > 0 and "parametric" in r and "step" in r
    differ = [r["index"] for r in result["records"] if r["parametric"] != r["step"]]
    assert s["runs_where_the_two_differ"] == differ
    total = sum(len(r["mismatched"]) for r in result["records"])
    assert s["parametric"]["mismatched_elements"] == s["step"]["mismatched_elements"] == total
    for key in ("parametric", "step"):
        # A repair error for every located mismatched element, none for another.
        errors = [e for r in result["records"] for e in r[f"{key}_repair_error"].values()]
        located = sum(len({tuple(t) for t in r[key]} & {tuple(t) for t in r["mismatched"]})
                      for r in result["records"])
        assert len(errors) == located and all(e >= 0 for e in errors)
        assert s[key]["repaired_within_10_percent"] == sum(e <= 0.1 for e in errors)
        # A kind for every located element, of the repair's kinds.
        for r in result["records"]:
            assert sorted(r[f"{key}_kinds"]) == sorted(f"{i},{j}" for i, j in r[key])
            assert set(r[f"{key}_kinds"].values()) <= set(KINDS)
        # The kind right: of the located mismatched elements, those whose kind is the one their change calls for.
        judged = [(r[f"{key}_kinds"][f"{i},{j}"], r["expected_kinds"][f"{i},{j}"]) for r in result["records"]
                  for i, j in r[key] if [i, j] in r["mismatched"]]
        assert s[key]["kinds_judged"] == len(judged) == located
        assert s[key]["kind_right"] == sum(said == want for said, want in judged)
    differ = [[r["index"], k, r["parametric_kinds"][k], r["step_kinds"][k]] for r in result["records"]
              for k in sorted(set(r["parametric_kinds"]) & set(r["step_kinds"]))
              if r["parametric_kinds"][k] != r["step_kinds"][k]]
    assert s["kinds_that_differ"] == differ
    for key in ("parametric", "step"):
        after = [e for r in result["records"] for e in r[f"{key}_located_after"]]
        assert s[key]["located_after_new"] + s[key]["located_after_again"] == len(after)
    assert "step: " in step_models.format_table(result)
    assert "the repaired model's detection locates" in step_models.format_table(result)


def test_located_after_counts_splits_new_and_again_and_counts_the_drawn():
    records = [{"mismatched": [[0, 1], [1, 0]], "located": [[0, 1]], "after": [[0, 1], [1, 0], [1, 2]]},
               {"mismatched": [], "located": [[2, 2]], "after": [[2, 2]]},
               {"mismatched": [[0, 0]], "located": [[0, 0]]}]                       # no after: nothing
    assert step_models.located_after_counts(records, "located", "after") == {
        "located_after_new": 2, "located_after_new_drawn": 1, "located_after_again": 2, "located_after_again_drawn": 1}


def test_step_models_lost_lag_runs_the_lost_lag_loops_into_its_own_file(tmp_path, monkeypatch, capsys):
    """``--lost-lag`` draws the loops of ``bench.structures_mc --lost-lag`` (every mismatch a lost second lag) and
    writes, unless ``--out`` is given, to its own file, not over the default one."""
    import json

    from bench import structures_mc

    monkeypatch.setattr(step_models, "DEFAULT_OUT", tmp_path / "step_models.json")
    monkeypatch.setattr(step_models, "LOST_LAG_OUT", tmp_path / "step_models_lost_lag.json")
    assert step_models.main(["--runs", "1", "--seed", "3", "--samples", "1500", "--lost-lag"]) == 0
    assert not (tmp_path / "step_models.json").exists()
    result = json.loads((tmp_path / "step_models_lost_lag.json").read_text())
    assert result["config"]["lost_lag"] is True
    sc = structures_mc.make_structures_scenario(3, 0, structures_mc.StructuresOptions(lost_lag=True))
    assert sc.mismatches and all(m["kind"] == "lost_lag" for m in sc.mismatches)
    assert result["records"][0]["mismatched"] == sorted([m["output"], m["column"]] for m in sc.mismatches)
    assert set(result["records"][0]["expected_kinds"].values()) == {"time_constant"}
    assert "every mismatch a lost second lag" in capsys.readouterr().out
