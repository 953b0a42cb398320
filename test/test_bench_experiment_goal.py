"""bench.experiment_mc's goal check: the hardest target of an experiment given a 20 % gain error."""

import pytest

from bench.experiment_mc import ALPHA, _decisions, _goal_summary, dithered_log, one
from bench.scenarios import make_scenario


def test_goal_summary_counts_by_the_reruns_own_value():
    checks = [{"detectable_rerun": 0.15, "located": [True, True, False]},
              {"detectable_rerun": 0.25, "located": [False, True]},
              {"detectable_rerun": 0.2, "located": [True]}]
    s = _goal_summary(checks)["goal_check"]
    assert s["all"] == {"experiments": 3, "runs": 6, "located": 4, "rate": pytest.approx(4 / 6)}
    assert s["rerun_at_most_goal"]["runs"] == 4 and s["rerun_at_most_goal"]["located"] == 3
    assert s["rerun_above_goal"] == {"experiments": 1, "runs": 2, "located": 1, "rate": 0.5}
    assert _goal_summary([]) == {}


def test_the_goal_check_errs_the_hardest_unmismatched_target_of_the_experiment():
    rec = one(0, 4, 3000, goal_repeats=1)           # a 5x8 loop whose experiment is predicted to reach the goal
    assert rec["experiment"]["expected_detectable_gain_change"] <= 0.2 + 1e-9
    g = rec["goal_check"]
    sc = make_scenario(0, 4)
    i, j = sc.model.outputs.index(g["target"][0]), sc.model.inputs.index(g["target"][1])
    assert (i, j) not in {(m.output, m.input) for m in sc.mismatches} and sc.model.present[i, j]
    assert g["sign"] in (-1.0, 1.0) and len(g["located"]) == 1 and isinstance(g["located"][0], bool)
    # Independently: the re-run's largest value among the experiment's targets that qualify.
    model = sc.model
    rep2, _ = _decisions(model, dithered_log(sc, rec["experiment"]["dither"], rec["experiment"]["samples"]), ALPHA)
    targets = {tuple(k) for k in rec["results"]["arx"]["ambiguous"]}
    values = [e.detectable_gain_change for e in rep2.elements
              if (model.outputs.index(e.output), model.inputs.index(e.input)) in targets and not e.mismatch
              and model.present[model.outputs.index(e.output), model.inputs.index(e.input)]
              and (model.outputs.index(e.output), model.inputs.index(e.input)) not in
              {(m.output, m.input) for m in sc.mismatches}]
    assert g["detectable_rerun"] == max(values)


def test_the_scores_after_count_the_reruns():
    """A run with an experiment is scored by its re-run (it was left out: the re-run's results were not under
    "arx", and the figures "after" were those of the runs without an experiment alone)."""
    from bench.experiment_mc import summarise

    def rec(index, located, ambiguous, mismatches, rerun=None):
        r = {"index": index, "shape": [2, 2], "shape_class": "square", "dither": False, "collinear_inputs": [],
             "mismatches": [{"output": i, "input": j, "kind": "gain", "size": 0.5, "plant": {}, "model": {}}
                            for i, j in mismatches],
             "results": {"arx": {"located": located, "ambiguous": ambiguous, "rows": sorted({i for i, _ in located}),
                                 "time_s": 0.1}},
             "experiment": None}
        if rerun is not None:
            r["experiment"] = {"dither": {"u1": 0.1}, "samples": 2000, "expected_detectable_gain_change": 0.2,
                               "why": "", "beyond": None}
            r["experiment_relative_amplitude"] = {"u1": 0.5}
            r["rerun"] = {"results": {"located": rerun, "ambiguous": [], "rows": sorted({i for i, _ in rerun}),
                                      "time_s": 0.1},
                          "collinear_inputs": [], "ambiguous_after": 0, "largest_detectable_after": 0.1,
                          "experiment_after": None}
        return r

    records = [rec(0, [[0, 0]], [], [(0, 0)]),                                   # found at once
               rec(1, [], [[1, 0], [1, 1]], [(1, 1)], rerun=[[1, 1]])]           # ambiguous, then found
    s = summarise(records)
    assert (s["before"]["tp"], s["before"]["ambiguous_true"]) == (1, 1)
    assert (s["after"]["tp"], s["after"]["fp"], s["after"]["fn"], s["after"]["ambiguous_true"]) == (2, 0, 0, 0)
    assert s["after"]["recall_all"] == 1.0

    # A dithered input that did not move in the first log has no amplitude / std (None): the summary counts it
    # apart and takes the median of the others (seed 7 ended in a TypeError there).
    still = rec(2, [], [[1, 0], [1, 1]], [(1, 1)], rerun=[[1, 1]])
    still["experiment_relative_amplitude"] = {"u1": None, "u2": 0.3}
    s = summarise(records + [still])
    assert s["dithered_inputs_that_did_not_move"] == 1
    assert s["median_relative_amplitude"] == 0.4 and s["relative_amplitude_quartiles"][1] == 0.4


def test_small_loops_have_one_to_three_outputs_and_inputs_and_exclude_still(capsys):
    from bench import experiment_mc
    from bench.scenarios import SMALL

    shapes = {(make_scenario(0, k, SMALL).plant.n_outputs, make_scenario(0, k, SMALL).plant.n_inputs)
              for k in range(40)}
    assert shapes <= {(i, j) for i in (1, 2, 3) for j in (1, 2, 3)} and (1, 2) in shapes and (2, 3) in shapes
    with pytest.raises(SystemExit) as exit_:
        experiment_mc.main(["--still", "--small"])
    assert exit_.value.code == 2 and "--still and --small: choose one" in capsys.readouterr().err
