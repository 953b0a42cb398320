"""bench.monte_carlo --bounds: the loops run again with their MPC's inputs and moves bounded."""

import numpy as np

from bench import monte_carlo
from bench.scenarios import make_scenario


def test_the_bounds_come_from_the_free_run_and_the_bounded_mpc_keeps_them():
    sc = make_scenario(0, 3)
    assert sc.dither                                             # the bounds hold the MPC's inputs, not the dither
    free = monte_carlo._closed_loop(sc, 600)
    u = free.u - free.dither
    bounded, limits = monte_carlo.bounded_scenario(sc, u, 0.8)
    hi = np.quantile(np.abs(u), 0.8, axis=0)
    dmax = np.quantile(np.abs(np.diff(u, axis=0)), 0.9, axis=0)
    np.testing.assert_allclose(limits["u_max"], hi)
    np.testing.assert_allclose(limits["du_max"], dmax)
    assert bounded.plant == sc.plant and bounded.model == sc.model and bounded.loop_seed == sc.loop_seed
    log = monte_carlo._closed_loop(bounded, 600)
    ub = log.u - log.dither
    assert np.array_equal(log.dither, free.dither)               # the same loop seed: the same dither
    assert np.all(np.abs(ub) <= hi * (1 + 1e-7) + 1e-9)
    assert np.all(np.abs(np.diff(ub, axis=0)) <= dmax * (1 + 1e-7) + 1e-9)
    act = monte_carlo.bound_activity(ub, limits)
    # The free run had 20 % of each input beyond the bound: the bounded loop sits on it often.
    assert 0.05 < act["u"] < 0.6 and act["any"] >= act["u"]
    assert monte_carlo.bound_activity(u, limits)["u"] < 0.25     # the free run crosses the bound, rarely sits on it


def test_bound_activity_counts_the_samples_at_a_bound():
    u = np.array([[0.0, 1.0], [0.5, -1.0], [1.0, 0.2], [0.9, 0.2]])
    act = monte_carlo.bound_activity(u, {"u_max": [1.0, 1.0], "du_max": [0.5, 5.0]})
    assert act["u"] == 3 / 8             # |u| = 1: samples 0 and 1 of input 2, sample 2 of input 1
    assert act["du"] == 2 / 6            # the moves of input 1 of 0.5: samples 1 and 2 (sample 0 has none)
    assert act["any"] == 3 / 4           # sample 3: 0.9 and 0.2, moves of 0.1 and 0


def test_a_bounded_run_keeps_the_free_result_beside_and_compares():
    rec = monte_carlo.run_one(0, 3, 600, ("arx",), bounds=0.8)
    assert set(rec["bounds"]) == {"quantile", "u_max", "du_max", "active", "free_separability", "free_collinear_inputs"}
    assert "arx" in rec["results"] and "arx" in rec["results_unbounded"]
    free = monte_carlo.run_one(0, 3, 600, ("arx",))
    assert rec["results_unbounded"]["arx"]["located"] == free["results"]["arx"]["located"]
    comp = monte_carlo.compare_unbounded([rec])
    same = sorted(map(tuple, rec["results"]["arx"]["located"])) == sorted(map(tuple, free["results"]["arx"]["located"]))
    assert comp["runs"] == 1 and comp["same_located"] == int(same) and comp["differ"] == ([] if same else [3])
    assert comp["active"]["u"]["median"] == rec["bounds"]["active"]["u"]
    assert rec["bounds"]["free_separability"] == free["separability"]     # the free run's ambiguity on its own inputs
