"""bench.repair_mc --far-delays: delay mismatches beyond the repair's own search range."""

import dataclasses

import pytest

from bench.scenarios import FAR_DELAYS, ScenarioOptions, make_scenario


def test_far_delays_draw_only_delays_shifted_by_11_to_30_samples():
    shifts = []
    for index in range(40):
        sc = make_scenario(0, index, FAR_DELAYS)
        assert 1 <= len(sc.mismatches) <= 2
        for m in sc.mismatches:
            assert m.kind == "delay" and m.plant["gain"] == m.model["gain"]
            assert m.plant["time_constant"] == m.model["time_constant"]
            shifts.append(m.model["delay"] - m.plant["delay"])
            assert 11 <= abs(shifts[-1]) <= 30 and m.model["delay"] >= 0
    assert min(shifts) < 0 < max(shifts)        # both directions drawn


def test_the_default_draw_is_unchanged_by_the_new_option():
    """Without delay_shift_range the scenarios are those drawn before the option existed (same random calls)."""
    plain = ScenarioOptions(kinds=("delay",), min_mismatches=1, max_mismatches=2, max_delay=40)
    for index in range(10):
        sc = make_scenario(0, index, plain)
        for m in sc.mismatches:
            theta = round(m.plant["delay"])
            assert abs(m.model["delay"] - theta) == max(1, round(m.size * theta))


def test_delay_shift_range_is_checked():
    with pytest.raises(ValueError, match="delay_shift_range"):
        dataclasses.replace(FAR_DELAYS, delay_shift_range=(0, 5))


def test_repair_mc_scores_the_repaired_delays():
    from bench import repair_mc

    res = repair_mc.run(2, 0, 1500, dither_fat=True, far_delays=True)
    assert res["far_delays"] and "delays 11 to 30 samples off" in repair_mc.format_table(res)
    assert res["delays_scored"] == sum(len(r["delays"]) for r in res["records"])
    for r in res["records"]:
        for x in r["delays"]:
            assert abs(x["plant"] - x["model"]) >= 11


def test_repair_mc_takes_kinds_and_the_largest_delay():
    from bench import repair_mc

    res = repair_mc.run(1, 0, 1500, dither_fat=True, kinds=("missing",), max_delay=40)
    assert res["kinds"] == ["missing"] and res["max_delay"] == 40
    assert "kinds missing, plant delays up to 40" in repair_mc.format_table(res)
    sc = make_scenario(0, 0, dataclasses.replace(ScenarioOptions(), kinds=("missing",), min_mismatches=1,
                                                 max_delay=40))
    assert res["drawn_elements"] == len(sc.mismatches) >= 1
