"""bench.element_level: its Poisson tail against scipy, its counts, and one run end to end."""

import numpy as np
import pytest
from scipy import stats

from bench.element_level import THRESHOLDS, count, poisson_upper_tail, run_one, score


@pytest.mark.parametrize("k, mean", [(0, 3.0), (1, 0.5), (4, 2.5), (12, 4.7), (70, 68.4), (107, 68.6)])
def test_poisson_upper_tail_equals_scipy(k, mean):
    assert poisson_upper_tail(k, mean) == pytest.approx(stats.poisson.sf(k - 1, mean), rel=1e-9, abs=1e-15)


def test_count_against_a_uniform_sample():
    ps = np.random.default_rng(0).uniform(size=20000)
    c = count(list(ps) + [None, float("nan")])
    assert c["n"] == 20000
    for t in THRESHOLDS:
        assert c["expected"][str(t)] == pytest.approx(20000 * t)
        assert c["below"][str(t)] == int(np.sum(ps < t))
        assert c["tail"][str(t)] > 1e-3


def test_count_sees_a_test_that_rejects_too_often():
    ps = np.random.default_rng(1).uniform(size=5000) ** 2      # P(p < t) = sqrt(t)
    assert count(ps)["tail"]["0.01"] < 1e-6


def test_one_run_gives_the_p_values_of_the_rows_without_a_mismatch():
    rec = run_one(0, 21, 1500)
    assert "error" not in rec and rec["elements"]
    assert {e["output"] for e in rec["elements"]} == {0, 2}         # run 21's mismatch is in row 1
    for e in rec["elements"]:
        assert 0.0 <= e["window"] <= 1.0
        assert (e["response"] is None) == (not e["present"])
    summary = score([rec])
    assert summary["all"]["window"]["n"] == len(rec["elements"])


def test_one_run_in_step_response_form_tests_the_same_elements():
    # The step-response form of the same model on the same log: the same rows' elements, each with a
    # window and a whole-response p-value (every element of a step-response model is present).
    param, step = run_one(0, 21, 1500), run_one(0, 21, 1500, step_response=True)
    assert "error" not in step
    key = lambda e: (e["output"], e["column"])                                   # noqa: E731
    assert sorted(map(key, step["elements"])) == sorted(map(key, param["elements"]))
    for e in step["elements"]:
        assert 0.0 <= e["window"] <= 1.0 and 0.0 <= e["response"] <= 1.0


def test_with_the_noise_order_the_p_values_are_analyze_s():
    # analyze without the repair, the release and the screening is detect at the na it settles on: the
    # same p-values, element by element (the whole-response test's to rounding: analyze takes its
    # products from the moments it shares with the detectability).
    from mpm_monitor.core.analysis import AnalysisOptions, detect
    from mpm_monitor.core.pipeline import analyze

    from bench.structures_mc import StructuresOptions, make_structures_scenario, simulate

    sc = make_structures_scenario(0, 21, StructuresOptions())
    data = simulate(sc, 1500, StructuresOptions()).as_logged_data("run 21")
    na = analyze(sc.model, data, AnalysisOptions(repair=False, release_explained=False,
                                                 drop_spikes=False)).noise_order["na"]
    ref = detect(sc.model, data, AnalysisOptions(repair=False, na=na), detectability=False)
    ref = {(sc.model.outputs.index(e.output), sc.model.columns.index(e.input)): e for e in ref.elements}
    rec = run_one(0, 21, 1500, noise_order=True)
    assert "error" not in rec and rec["elements"]
    for e in rec["elements"]:
        r = ref[(e["output"], e["column"])]
        assert e["window"] == pytest.approx(r.p_value_window, rel=1e-9)
        assert (e["response"] is None) == (r.p_value_response is None)
        if e["response"] is not None:
            assert e["response"] == pytest.approx(r.p_value_response, rel=1e-9)


def test_with_drops_the_rows_kept_give_the_p_values_and_the_rows_test_is_counted():
    full, dropped = run_one(0, 21, 1500), run_one(0, 21, 1500, drop=0.01)
    assert "dropped" not in full and "rows_lost" not in full
    assert dropped["dropped"] > 0 and dropped["rows_lost"] > dropped["dropped"]   # a gap costs the rows whose lags reach it
    assert run_one(0, 21, 1500, drop=0.01)["dropped"] == dropped["dropped"]        # the drops a function of the run
    for rec in (full, dropped):
        assert [w["output"] for w in rec["rows"]] == [0, 2]                         # the rows without the mismatch
        assert all(0.0 <= w["row"] <= 1.0 for w in rec["rows"])
    assert [w["row"] for w in dropped["rows"]] != [w["row"] for w in full["rows"]]
    assert score([full, dropped])["rows (S_Delta test)"]["row"]["n"] == 4


def test_a_family_draws_its_own_loops_and_an_unknown_family_is_refused():
    from bench.element_level import family_options
    from bench.structures_mc import StructuresOptions, make_structures_scenario

    assert family_options("main") == StructuresOptions()
    assert family_options("lost-pair") == StructuresOptions(lost_pair=True)
    with pytest.raises(ValueError, match="family: expected one of main, lost-lag"):
        family_options("lost_pair")
    # A family draws its own mismatches (seed 8's run 1 loses a lead-lag pair); a clean run is the same loop in
    # every family (seed 8's run 44, a false location of the main family too).
    assert [m["kind"] for m in make_structures_scenario(8, 1, family_options("lost-pair")).mismatches] == ["lost_pair"]
    lost_pair, main = (make_structures_scenario(8, 44, family_options(f)) for f in ("lost-pair", "main"))
    assert lost_pair.mismatches == main.mismatches == () and lost_pair.loop_seed == main.loop_seed
    rec = run_one(8, 1, 1500, family="lost-pair")
    assert "error" not in rec and rec["elements"] and {e["output"] for e in rec["elements"]} == {1}   # its mismatch is in row 0


def test_z_is_the_chi_square_quantile_root():
    from bench.element_level import _z

    for p in (0.5, 0.05, 1e-3, 1e-12):
        assert _z(p) == pytest.approx(np.sqrt(stats.chi2.isf(p, 1)), rel=1e-9)
    assert _z(0.0) == _z(1e-300) == pytest.approx(37.0658, abs=1e-4) and _z(1.0) == pytest.approx(0.0, abs=1e-12)


def test_paired_compares_element_by_element():
    from bench.element_level import paired

    def rec(index, ps, key=None):
        els = [{"output": 0, "column": j, "role": "input", "integrating": False, "present": True,
                "mismatch_run": False, "window": p, "response": p} for j, p in enumerate(ps)]
        return {"index": index, "elements": els, "rows": []} if key is None else \
            {"index": index, "elements": [], "rows": [], key: {"elements": els, "rows": []}}

    base = [rec(0, [0.5, 0.01]), rec(1, [0.2])]
    same = paired(base, base)["all"]["window"]
    assert same["n"] == 3 and same["dz_mean"] == 0.0 and same["dz_sd"] == 0.0 and same["z2"] == same["z2_base"]
    # Run 0's second element moves from 0.01 to 0.5; run 1 is missing from the other run; an error is skipped.
    other = [rec(0, [0.5, 0.5], "cut"), dict(rec(1, [0.2], "cut"), error="x")]
    c = paired(base, other, "cut")["all"]["response"]
    dz = np.sqrt(stats.chi2.isf(0.5, 1)) - np.sqrt(stats.chi2.isf(0.01, 1))
    assert c["n"] == 2
    assert c["dz_mean"] == pytest.approx(dz / 2) and c["dz_sd"] == pytest.approx(abs(dz) / 2)
    assert c["z2_base"] == pytest.approx((stats.chi2.isf(0.5, 1) + stats.chi2.isf(0.01, 1)) / 2)


def test_with_cut_the_log_without_drops_loses_as_many_rows_and_no_gap():
    rec = run_one(0, 21, 1500, drop=0.01, cut=True)
    assert "error" not in rec and "error" not in rec["cut"] and rec["rows_lost"] > 0
    assert "rows_lost" not in rec["cut"]                          # cut short: no gap
    key = lambda e: (e["output"], e["column"])                   # noqa: E731
    assert sorted(map(key, rec["cut"]["elements"])) == sorted(map(key, rec["elements"]))
    assert [e["window"] for e in rec["cut"]["elements"]] != [e["window"] for e in rec["elements"]]
    assert "cut" not in run_one(0, 21, 1500, cut=True)             # nothing to cut without drops
