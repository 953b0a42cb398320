"""Locations in rows the S_Delta row test does not flag: released when the element test with ``max_na``
own lags does not locate them (``AnalysisOptions.release_quiet_rows``).

Usage::

    .venv/bin/python -m bench.quiet_rows [--runs 60] [--seed 0] [--samples 3000] [--jobs 2]
                                         [--out bench/results/quiet_rows.json]

The loops are :mod:`bench.scenarios`' random FOPDT plants of 2 to 4 outputs and inputs under the
paper's MPC and setpoint PRBS (no dither), with the unmeasured disturbance of each condition in place of
the paper's noise:

* ``paper``: the paper's noise (a disturbance of innovation 7.5e-3 through ``z / (z - 0.95)`` and
  measurement noise 5e-3);
* ``drift a / noise s``: a drift of pole 0.95 and innovation ``a`` under white measurement noise of
  standard deviation ``s`` (0.1 / 0.5, 0.3 / 1.5 and 1.0 / 5.0): the noise moves the inputs as much as
  the setpoints of amplitude 1 do, or more, and the drift's colour is what ``na`` = 4 own lags leave.

Each condition runs ``--runs`` clean loops (the plant as the model) and ``--runs`` loops with one
mismatched element (the scenarios' kinds and sizes).  Every log is analysed once (``analyze`` without the
repair, the defaults); the analysis without the release is read from the same report (the located
elements and the released ones, ``unlocated_at_na``: the release changes nothing else of the detection).
Per condition and decision: clean runs with a located element (false alarms), the true elements located,
the runs with a wrong element located, and the elements released (true and wrong ones).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from bench import map_runs, mc_parser, write_json

#: (name, disturbance innovation, disturbance pole, measurement noise); None: the paper's noise.
CONDITIONS = (("paper", None, None, None), ("drift 0.1 / noise 0.5", 0.1, 0.95, 0.5),
              ("drift 0.3 / noise 1.5", 0.3, 0.95, 1.5), ("drift 1.0 / noise 5.0", 1.0, 0.95, 5.0))


def one_run(task) -> dict:
    """Simulate and analyse one loop: ``task = (condition index, seed, index, mismatched, samples, alpha)``."""
    from bench.scenarios import ScenarioOptions, make_scenario
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze
    from mpm_monitor.sim.closed_loop import run_closed_loop
    from mpm_monitor.sim.plant import DisturbanceOptions

    c, seed, index, mismatched, samples, alpha = task
    name, a, pole, noise = CONDITIONS[c]
    sc = make_scenario(seed, index, ScenarioOptions(min_size=2, max_size=4, dither_fraction=0.0),
                       n_mismatches=1 if mismatched else 0)
    disturbance = sc.disturbance if a is None else DisturbanceOptions(disturbance_std=a, disturbance_pole=pole,
                                                                     noise_std=noise)
    t0 = time.perf_counter()
    log = run_closed_loop(sc.plant, sc.model, samples, seed=sc.loop_seed, mpc=sc.mpc, excitation=sc.excitation,
                          disturbance=disturbance)
    rep = analyze(sc.model, log.as_logged_data(), AnalysisOptions(alpha=alpha, repair=False))
    outputs, inputs = sc.model.outputs, sc.model.columns
    truth = {(outputs[m.output], inputs[m.input]) for m in sc.mismatches}
    located = set(rep.located_elements)
    released = {(e.output, e.input) for e in rep.elements if e.unlocated_at_na is not None}
    return {"condition": name, "index": index, "mismatched": bool(mismatched), "shape": list(sc.shape),
            "truth": sorted(truth), "located": sorted(located), "released": sorted(released),
            "na": (rep.noise_order or {}).get("na"), "seconds": time.perf_counter() - t0}


def summarize(records: list) -> dict:
    """Per condition, with the release (``released``) and without it (``kept``: the located elements and the
    released ones)."""
    def sets(r):
        return tuple({tuple(k) for k in r[key]} for key in ("located", "released", "truth"))

    out = {}
    for name, *_ in CONDITIONS:
        recs = [(r["mismatched"],) + sets(r) for r in records if r["condition"] == name]
        row = {}
        for decision in ("kept", "released"):
            found = [(bad, located | released if decision == "kept" else located, truth)
                     for bad, located, released, truth in recs]
            row[decision] = {
                "false_alarms": sum(1 for bad, got, _ in found if not bad and got),
                "clean": sum(1 for bad, _, _ in found if not bad),
                "true_located": sum(len(got & truth) for bad, got, truth in found if bad),
                "true": sum(len(truth) for bad, _, truth in found if bad),
                "runs_with_wrong": sum(1 for bad, got, truth in found if bad and got - truth),
                "mismatched": sum(1 for bad, _, _ in found if bad)}
        row["released_true"] = sum(len(released & truth) for _, _, released, truth in recs)
        row["released_wrong"] = sum(len(released - truth) for _, _, released, truth in recs)
        row["runs_released"] = sum(1 for _, _, released, _ in recs if released)
        out[name] = row
    return out


def format_table(result: dict) -> str:
    """The summary as a text table."""
    c = result["config"]
    lines = [f"locations in rows the row test does not flag: {c['runs']} clean + {c['runs']} one-mismatch loops per "
             f"condition, 2..4 x 2..4, {c['samples']} samples, alpha {c['alpha']} (seed {c['seed']}, "
             f"{c['wall_time_s']:.0f} s)",
             f"{'condition':<24} {'decision':<9} {'false alarms':>12} {'true located':>13} {'runs w. wrong':>14}"
             f" {'released true/wrong':>20}"]
    for name, row in result["summary"].items():
        for decision in ("kept", "released"):
            s = row[decision]
            rel = f"{row['released_true']}/{row['released_wrong']}" if decision == "released" else ""
            lines.append(f"{name:<24} {decision:<9} {s['false_alarms']:>6}/{s['clean']:<5} "
                         f"{s['true_located']:>6}/{s['true']:<6} {s['runs_with_wrong']:>7}/{s['mismatched']:<6}"
                         f" {rel:>20}")
    return "\n".join(lines)


def run(runs: int, seed: int, samples: int, jobs: int, alpha: float, progress=None) -> dict:
    """Every condition's clean and one-mismatch loops; the records, summary and configuration."""
    t0 = time.perf_counter()
    tasks = [(c, seed, index, mismatched, samples, alpha) for c in range(len(CONDITIONS))
             for mismatched in (False, True) for index in range(runs)]
    records = map_runs(one_run, tasks, jobs, progress)
    config = {"runs": runs, "seed": seed, "samples": samples, "alpha": alpha, "jobs": jobs,
              "conditions": [dict(zip(("name", "innovation", "pole", "noise"), c)) for c in CONDITIONS],
              "wall_time_s": time.perf_counter() - t0}
    return {"config": config, "summary": summarize(records), "records": records}


def main(argv=None) -> int:
    parser = mc_parser("python -m bench.quiet_rows", __doc__, 60, Path("bench/results/quiet_rows.json"))
    args = parser.parse_args(argv)

    def progress(done, total, rec):
        if done % 20 == 0 or done == total:
            print(f"  {done}/{total}", file=sys.stderr, flush=True)

    result = run(args.runs, args.seed, args.samples, args.jobs, args.alpha, progress)
    print(format_table(result))
    write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
