"""The bounded MPC's QP: the exact active-set solver against OSQP, on the same problems, in the same run.

Paper case 3.2's loop (its plant, mismatched model, MPC tuning, setpoints and disturbance) with bounds
active much of the time (``|u| <= 0.6``, ``|du| <= 0.3``: test_analysis's constrained-MPC test) runs for
``samples`` samples, driven by the MPC's own solver (:mod:`mpm_monitor.sim.qp`, a dual active-set method,
warm-started from the last sample's held bounds).  Each QP it solves is solved again by OSQP as the MPC
solved it up to stop 54: tolerance 1e-9 (``qp_tolerance``), polished, warm-started from its last solution
shifted by one move, one solver kept across samples.

Recorded per QP: both solve times (``time.perf_counter``), the active-set iterations, the largest
difference of the moves, and the cost of each answer (``1/2 dU' H dU + q' dU``; the exact minimum is the
lower).  Printed: the medians and 90th percentiles of both times and their ratio, the differences, and how
often OSQP's answer cost more than the active set's.

Run: ``python -m bench.mpc_qp [--samples 3000] [--seed 21] [--out bench/results/mpc_qp.json]``
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.mpc import InternalModelMpc

from . import write_json

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "mpc_qp.json"
BOUNDS = dict(u_min=-0.6, u_max=0.6, du_max=0.3)


class _Compared:
    """OSQP as the MPC used it, kept beside one controller, fed the same problems."""

    def __init__(self, ctrl: InternalModelMpc):
        import osqp
        import scipy.sparse as sp

        self.nu, self.H, self.A = ctrl.model.n_inputs, ctrl._H, ctrl.qp_rows
        self.solver = osqp.OSQP()
        self.setup = lambda q, lo, hi: self.solver.setup(
            sp.csc_matrix(np.triu(self.H)), q, sp.csc_matrix(self.A), lo, hi, verbose=False,
            eps_abs=ctrl.options.qp_tolerance, eps_rel=ctrl.options.qp_tolerance, polishing=True,
            warm_starting=True, max_iter=20000)
        self.ready = False
        self.last = None

    def solve(self, q, lo, hi) -> np.ndarray:
        if not self.ready:
            self.setup(q, lo, hi)
            self.ready = True
        else:
            self.solver.update(q=q, l=lo, u=hi)
        if self.last is not None:
            self.solver.warm_start(x=np.concatenate([self.last[self.nu:], np.zeros(self.nu)]))
        res = self.solver.solve(raise_error=False)
        self.last = np.asarray(res.x, dtype=float)
        return self.last


def run(samples: int = 3000, seed: int = 21, clock=time.perf_counter) -> dict:
    """Run the loop and compare the solvers on every QP (module docstring)."""
    case = paper_case("3.2")
    mpc = dataclasses.replace(case.mpc, **BOUNDS)
    records = []
    own = InternalModelMpc.solve_qp
    compared = {}

    def solve_qp(ctrl, eps, x, u_prev, dv=None):
        t0 = clock()
        du = own(ctrl, eps, x, u_prev, dv)
        t_own = clock() - t0
        other = compared.setdefault(id(ctrl), _Compared(ctrl))
        q, lo, hi, _ = ctrl.qp_problem(eps, x, u_prev, dv)
        t0 = clock()
        du_osqp = other.solve(q, lo, hi)
        t_osqp = clock() - t0
        cost = lambda v: float(0.5 * v @ ctrl._H @ v + q @ v)  # noqa: E731
        active = ctrl._last_active
        records.append({"own_s": t_own, "osqp_s": t_osqp, "held": 0 if active is None else int(active[0].size),
                        "difference": float(np.max(np.abs(du - du_osqp))),
                        "cost_own": cost(du), "cost_osqp": cost(du_osqp)})
        return du

    InternalModelMpc.solve_qp = solve_qp
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PendingDeprecationWarning)   # osqp's raise_error default
            run_closed_loop(case.plant, case.model, samples, seed=seed, mpc=mpc, excitation=case.excitation,
                            disturbance=case.disturbance)
    finally:
        InternalModelMpc.solve_qp = own
    own_t = np.array([r["own_s"] for r in records])
    osqp_t = np.array([r["osqp_s"] for r in records])
    diff = np.array([r["difference"] for r in records])
    excess = np.array([r["cost_osqp"] - r["cost_own"] for r in records])
    summary = {"samples": samples, "seed": seed, "qp_solves": len(records),
               "median_held_bounds": float(np.median([r["held"] for r in records])),
               "own_median_ms": 1e3 * float(np.median(own_t)), "own_p90_ms": 1e3 * float(np.percentile(own_t, 90)),
               "osqp_median_ms": 1e3 * float(np.median(osqp_t)),
               "osqp_p90_ms": 1e3 * float(np.percentile(osqp_t, 90)),
               "median_ratio_osqp_over_own": float(np.median(osqp_t / own_t)),
               "largest_move_difference": float(diff.max()), "median_move_difference": float(np.median(diff)),
               "osqp_costlier": int(np.sum(excess > 1e-12 * np.maximum(1.0, np.abs([r["cost_own"] for r in records])))),
               "own_costlier": int(np.sum(excess < -1e-9 * np.maximum(1.0, np.abs([r["cost_own"] for r in records]))))}
    return {"summary": summary, "records": records}


def format_table(result: dict) -> str:
    s = result["summary"]
    return "\n".join([
        f"Bounded MPC QP, paper case 3.2 with |u| <= 0.6 and |du| <= 0.3: {s['samples']} samples (seed {s['seed']}), "
        f"{s['qp_solves']} QPs, median {s['median_held_bounds']:.0f} bounds held",
        f"  active set (exact): median {s['own_median_ms']:.2f} ms, 90th percentile {s['own_p90_ms']:.2f} ms",
        f"  OSQP (1e-9, polished, warm): median {s['osqp_median_ms']:.2f} ms, 90th percentile {s['osqp_p90_ms']:.2f} ms",
        f"  median ratio OSQP / active set: x{s['median_ratio_osqp_over_own']:.1f}",
        f"  moves: largest difference {s['largest_move_difference']:.2e}, median {s['median_move_difference']:.2e}",
        f"  OSQP's answer cost more on {s['osqp_costlier']} QPs; the active set's on {s['own_costlier']} "
        f"(by more than 1e-9 relative)",
    ])


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.mpc_qp", description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=3000)
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--out", default=str(DEFAULT_OUT))
    args = p.parse_args(argv)
    if args.samples < 1:
        p.error("--samples: expected an integer >= 1")
    result = run(args.samples, args.seed)
    print(format_table(result))
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
