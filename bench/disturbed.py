"""``analyze`` on a log whose every output carries an unmeasured step: what the disturbance confirmation costs.

Usage::

    .venv/bin/python -m bench.disturbed [--sizes 20x20,100x40] [--repeats 3] [--code DIR] [--out bench/results/disturbed.json]

Plant logs nearly always hold disturbances no input explains: a feed change, a fouling heat exchanger.
The repair tests every output's prediction error for such a step or drift, and confirms each one it would
report on simulated records of that output's own noise (``RepairOptions.disturbance_draws``, 200 by
default), so the cost of ``analyze`` grows with the outputs that carry one.  For each size, the industrial
case of :mod:`bench.perf` (one element off, 10,000 samples) is simulated again with an unmeasured step on
every output (each of one standard deviation of that output's clean log, at a sample drawn in the middle
40 % of the record; the controller answers it), written as a model file and a CSV, and
``python -m mpm_monitor analyze`` runs on it as a user runs it (``--jobs`` default: two processes on two
cores) and in one process (``--jobs 1``), in turn, ``--repeats`` times each after a warm-up.  Medians of the
wall time, the largest resident memory (``/usr/bin/time``) and how many disturbances the report names.

``--code DIR`` runs the command of another checkout (``DIR/mpm_monitor``, e.g. a ``git worktree`` of an
earlier commit) on the same files: the figures before and after a change, measured in one session.  The
figures hold no target; the issue's targets are on the clean log (:mod:`bench.perf`).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench import parse_sized, sizes_parser, write_json
from bench.perf import INDUSTRIAL_SAMPLES, _run_process, industrial_case, machine_info


def disturbed_case(ny: int, nu: int, samples: int = INDUSTRIAL_SAMPLES, seed: int = 0) -> tuple:
    """``(model, log, steps)``: :func:`bench.perf.industrial_case` with one element off, run again with an
    unmeasured step on every output (``steps``, shape (samples, ny), output units: one standard deviation of
    the output in the clean log, from a sample drawn uniformly in [0.3, 0.7] of the record)."""
    from mpm_monitor.sim.closed_loop import run_closed_loop

    plant, model, clean = industrial_case(ny, nu, samples, seed, mismatches=1)
    rng = np.random.default_rng(seed + 51)
    steps = np.zeros((samples, ny))
    size = np.std(np.asarray(clean.y, float), axis=0)
    for i, at in enumerate(rng.integers(int(0.3 * samples), int(0.7 * samples), ny)):
        steps[at:, i] = size[i]
    log = run_closed_loop(plant, model, samples, seed=seed + 7, output_disturbance=steps)
    return model, log, steps


def write_case(folder: Path, ny: int, nu: int, samples: int = INDUSTRIAL_SAMPLES, seed: int = 0) -> tuple:
    """``(model file, CSV)`` of :func:`disturbed_case`, written in ``folder``."""
    from mpm_monitor.io.csv_log import write_log_csv
    from mpm_monitor.io.model_file import save_model

    model, log, _ = disturbed_case(ny, nu, samples, seed)
    csv, yml = folder / f"disturbed_{ny}x{nu}.csv", folder / f"model_{ny}x{nu}.yaml"
    write_log_csv(csv, log)
    save_model(model, yml)
    return yml, csv


def reported(code: Path, yml: Path, csv: Path, folder: Path) -> dict:
    """What the command of ``code`` reports on the files: the disturbances named and the located elements."""
    out = folder / "report.json"
    subprocess.run([sys.executable, "-m", "mpm_monitor", "analyze", "--model", str(yml), "--data", str(csv),
                    "--json", str(out)], cwd=code, env=_env(code), stdout=subprocess.DEVNULL, check=True)
    report = json.loads(out.read_text(encoding="utf-8"))
    return {"disturbances": len(report["repair"].get("disturbances", [])),
            "located": [f"{e['output']}:{e['input']}" for e in report["elements"] if e["mismatch"]]}


def _env(code: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(code)
    return env


def run(sizes, repeats: int = 3, seed: int = 0, code: Path = Path("."), samples: int = INDUSTRIAL_SAMPLES,
        log=print) -> dict:
    """The figures of each size (see the module's docstring); ``samples`` per log."""
    code = code.resolve()
    out = {"machine": machine_info(), "repeats": repeats, "samples": samples, "code": str(code), "sizes": {}}
    with tempfile.TemporaryDirectory(prefix="mpm_disturbed_") as tmp:
        folder = Path(tmp)
        for ny, nu in sizes:
            t0 = time.perf_counter()
            yml, csv = write_case(folder, ny, nu, samples, seed)
            written = time.perf_counter() - t0
            command = [sys.executable, "-m", "mpm_monitor", "analyze", "--model", str(yml), "--data", str(csv)]
            runs = {"two": [], "one": []}
            for cmd in (command, command + ["--jobs", "1"]):           # warm-up
                _run_process(cmd, cwd=code, env=_env(code))
            for _ in range(repeats):
                runs["two"].append(_run_process(command, cwd=code, env=_env(code)))
                runs["one"].append(_run_process(command + ["--jobs", "1"], cwd=code, env=_env(code)))
            res = {"case_written_s": written, **reported(code, yml, csv, folder)}
            for key, got in runs.items():
                res[f"{key}_wall_s"] = statistics.median(x[0] for x in got)
                res[f"{key}_walls"] = [x[0] for x in got]
                res[f"{key}_max_rss_mib"] = max(x[1] for x in got)
                res[f"{key}_exit"] = [x[2] for x in got]
            out["sizes"][f"{ny}x{nu}"] = res
            log(f"  {ny}x{nu} x {samples}, a step on each of the {ny} outputs: {res['disturbances']} "
                f"disturbances reported, located {', '.join(res['located']) or 'none'}; analyze "
                f"{res['two_wall_s']:.2f} s ({res['two_max_rss_mib']:.0f} MiB), --jobs 1 {res['one_wall_s']:.2f} s "
                f"(exit {res['two_exit']}, {res['one_exit']})")
    return out


def main(argv=None) -> int:
    parser = sizes_parser("python -m bench.disturbed", __doc__, "runs of each command (default 3)")
    parser.add_argument("--code", default=".", help="the checkout whose mpm_monitor runs (default: this one)")
    args, sizes = parse_sized(parser, argv)
    result = run(sizes, args.repeats, args.seed, Path(args.code))
    if args.out:
        write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
