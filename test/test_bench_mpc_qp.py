"""bench.mpc_qp: the bounded MPC's own QP solver and OSQP on the same problems (a short run)."""

import itertools

from bench import mpc_qp


def test_both_solvers_answer_every_qp_and_agree():
    ticks = itertools.count()
    result = mpc_qp.run(samples=40, seed=21, clock=lambda: float(next(ticks)))   # time injected
    s = result["summary"]
    assert s["qp_solves"] == len(result["records"]) > 20          # the bounds are active from the start
    assert s["median_held_bounds"] >= 5
    assert all(r["own_s"] == 1.0 and r["osqp_s"] == 1.0 for r in result["records"])
    assert s["largest_move_difference"] < 1e-4                      # OSQP at 1e-9: the same moves to 1e-5
    assert s["own_costlier"] == 0                                   # the exact minimum costs no more
    assert "median ratio OSQP / active set" in mpc_qp.format_table(result)


def test_the_command_refuses_no_samples(capsys):
    import pytest

    with pytest.raises(SystemExit):
        mpc_qp.main(["--samples", "0"])
    assert "--samples: expected an integer >= 1" in capsys.readouterr().err
