"""The leak verdict of bench.endurance on made-up memory series (the benchmark itself runs for hours)."""

import numpy as np

from bench.endurance import memory_verdict


def _series(mb_of_k, sent=1_000_000, readings=200):
    k = np.linspace(0, sent, readings)
    return [(float(i), int(kk), float(mb_of_k(kk)), 50.0) for i, kk in enumerate(k)]


def test_flat_memory_passes_and_shows_no_trend():
    rng = np.random.default_rng(0)
    v = memory_verdict(_series(lambda k: 100.0 + rng.normal(0, 0.3)), 1_000_000, 2)
    assert v["within_10_percent"] is True
    assert abs(v["trend_mb_per_million_samples"]) < 2.0


def test_a_slow_leak_fails_and_its_rate_is_measured():
    # 30 MB per million samples on 100 MB: 27 % more at the end than after the first 10 %.
    v = memory_verdict(_series(lambda k: 100.0 + 30.0 * k / 1e6), 1_000_000, 2)
    assert v["within_10_percent"] is False
    assert abs(v["trend_mb_per_million_samples"] - 30.0) < 0.5
    assert v["at_10_percent_mb"] < v["at_end_mb"]


def test_warm_up_before_the_first_tenth_is_not_a_leak():
    # Memory grows while the window fills (the first 5 %), then stays.
    v = memory_verdict(_series(lambda k: 80.0 + 20.0 * min(k / 5e4, 1.0)), 1_000_000, 2)
    assert v["within_10_percent"] is True
    assert v["peak_mb"] == 100.0


def test_too_few_readings_give_no_verdict():
    assert "within_10_percent" not in memory_verdict([(0.0, 0, 90.0, None)], 1000, 2)
    # The analysis process (column 3) not started yet: no readings of it.
    assert "within_10_percent" not in memory_verdict([(0.0, k, 90.0, None) for k in (0, 500, 1000)], 1000, 3)


def test_the_publisher_leaves_out_samples_on_their_own_or_in_bursts():
    import numpy as np

    from bench.endurance import left_out

    alone = left_out(100_000, 0.004, 1.0, 0)
    np.testing.assert_array_equal(alone, np.random.default_rng(99).random(100_000) < 0.004)   # as before bursts
    bursts = left_out(100_000, 0.004, 5.0, 0)
    assert not bursts[0] and not bursts[-1] and 0.003 < bursts.mean() < 0.0045
    edges = np.diff(np.r_[0, bursts.astype(int), 0])
    lengths = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    assert 4.0 < lengths.mean() < 6.5 and np.array_equal(left_out(100_000, 0.004, 5.0, 0), bursts)
