"""bench.disturbance_level: its records, their summary and the paper's noise it draws."""

import numpy as np

from bench import disturbance_level as bench


def test_paper_noise_has_the_stationary_spread_of_its_pole():
    rng = np.random.default_rng(0)
    d = np.concatenate([bench.paper_noise(rng, 4000, 0.95) for _ in range(10)])
    # AR(1) of pole 0.95 driven by 7.5e-3, plus 5e-3 white: variance 7.5e-3^2 / (1 - 0.95^2) + 5e-3^2.
    assert abs(np.std(d) / np.sqrt(7.5e-3 ** 2 / (1 - 0.95 ** 2) + 5e-3 ** 2) - 1.0) < 0.1


def test_records_are_reproducible_and_the_summary_counts_them():
    a = bench.run_one(3, 6, 1, "step", 0.95, 2.0, 1500)
    assert a == bench.run_one(3, 6, 1, "step", 0.95, 2.0, 1500)
    assert 450 <= a["at"] <= 1050
    result = bench.run(level_draws=2, power_draws=1, samples=600)
    records, summary = result["records"], result["summary"]
    assert len(records) == 2 * (len(bench.LEVEL_POLES) + len(bench.DRIFT_NOISE_LEVEL_POLES)) + len(bench.POWER) \
        + len(bench.DRIFT_NOISE_POWER)
    assert {r.get("noise", "paper") for r in records} == {"paper", "drift"}
    assert sum(s["draws"] for s in summary) == len(records)
    for s in summary:
        for rule in ("plain", "confirmed"):
            mine = [r[rule]["reported"] for r in records if r["condition"] == s["condition"]]
            assert s[rule]["reported"] == sum(x is not None for x in mine)
            assert s[rule]["steps"] + s[rule]["drifts"] == s[rule]["reported"]
    text = bench.format_table(summary)
    assert "level" in text and "drift" in text and "level*" in text


def test_drift_noise_has_the_spread_of_its_two_parts():
    rng = np.random.default_rng(0)
    d = np.concatenate([bench.drift_noise(rng, 4000, 0.95) for _ in range(10)])
    # AR(1) of pole 0.95 driven by 5e-3, plus 2e-2 white.
    assert abs(np.std(d) / np.sqrt(5e-3 ** 2 / (1 - 0.95 ** 2) + 2e-2 ** 2) - 1.0) < 0.1


def test_a_loop_record_names_what_each_rule_reports():
    rec = bench.run_loop(0, 99, 0, 0.99)
    assert rec["kind"] == "loop" and rec["pole"] == 0.99
    for rule in ("plain", "confirmed"):
        assert (rec[rule]["reported"] is None) == (not rec[rule]["outputs"])
        assert set(rec[rule]["outputs"]) <= {"y1", "y2", "y3"}
    assert set(rec["confirmed"]["outputs"]) <= set(rec["plain"]["outputs"])
