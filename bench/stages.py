"""Where the time of ``analyze`` goes: its stages, timed in a fresh interpreter, one BLAS thread.

Usage::

    .venv/bin/python -m bench.stages [--sizes 20x20,100x40] [--repeats 3] [--out bench/results/stages.json]

For each size, the industrial case of :mod:`bench.perf` (one element off, 10,000 samples) is written
as a model file and a CSV, and a fresh interpreter per repeat (one BLAS thread, as the command
line) times:

* ``import``: the imports of the analysis, the repair and the CSV reader;
* ``csv``: reading the CSV;
* then one ``analyze`` with the repair, the named stages wrapped with a timer (their module
  attributes replaced for the run; the tests look them up at call time, so the numbers are those of
  the ordinary code): the model run, the regressions, the row test, the element test (and within
  it the shared moments of the element responses), the detectability, the experiment, the repair
  (and within it the joint classification), and each detection (the first and the one of the
  repaired model).

The cyclic garbage collector is off in the timed interpreter, as in ``python -m mpm_monitor analyze``.

A stage called more than once reports its calls and their sum.  The stages nest (the element test
holds the moments, the detection holds most others), so the figures do not add up to the total;
``rest of the first detection`` is the first detection minus the stages inside it (a stage run within
another, as the row test within the element test with two processes, subtracted once).  Medians over
the repeats.  The figures are the breakdown docs/benchmarks.md's "Where the time goes" quotes; they hold
no target (``bench.perf`` measures the command against its floor).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench import parse_sized, positive, sizes_parser, write_json

#: (label, module, attribute): the stages timed.  ``class.method`` attributes are methods.
STAGES = (
    ("model run", "mpm_monitor.core.signals", "compute_signals"),
    ("regressions", "mpm_monitor.core.regressions", "window_regressions"),
    ("row test", "mpm_monitor.core.row_test", "sdelta_row_test"),
    ("element test", "mpm_monitor.core.element_test", "arx_element_test"),
    ("  moments of the responses", "mpm_monitor.core.response_moments", "ResponseMoments._compute"),
    ("detectability", "mpm_monitor.core.detectability", "element_detectability"),
    ("experiment", "mpm_monitor.core.experiment", "design_experiment"),
    ("detection", "mpm_monitor.core.pipeline", "detect"),
    ("detection", "mpm_monitor.core.pipeline", "detect_unless_coloured"),
    ("joint classification", "mpm_monitor.core.pipeline", "explained_elements"),
    ("repair", "mpm_monitor.core.pipeline", "repair_model"),
    ("waiting for the child", "mpm_monitor.core.pipeline", "settle_report"),
)
#: The stages' labels, each once (two functions are timed as "detection").
LABELS = tuple(dict.fromkeys(label for label, _, _ in STAGES))
#: The stages inside the first detection (its "rest" is what they leave).
INSIDE_DETECTION = ("model run", "regressions", "row test", "element test", "detectability", "experiment")


def child(model_path: str, csv_path: str, jobs: int = 1) -> dict:
    """One timed run in this (fresh) interpreter; the figures as a dict."""
    import gc

    import mpm_monitor

    mpm_monitor.limit_blas_threads()
    gc.disable()            # as the command does for its one analysis (mpm_monitor.apps.cli)
    t0 = time.perf_counter()
    from mpm_monitor.core import analysis, pipeline  # noqa: F401 - the imports timed
    from mpm_monitor.core.repair import model_repair  # noqa: F401
    from mpm_monitor.io.csv_log import read_csv
    from mpm_monitor.io.model_file import load_model

    t1 = time.perf_counter()
    model = load_model(Path(model_path))
    data = read_csv(Path(csv_path), model)
    t2 = time.perf_counter()
    calls: dict = {label: [] for label in LABELS}
    nested: dict = {label: [] for label in LABELS}     # per call: started inside another stage of the detection
    active: list = []

    def timed(label, fn):
        def wrapper(*args, **kwargs):
            nested[label].append(any(a in INSIDE_DETECTION and a != label for a in active))
            active.append(label)
            s = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                calls[label].append(time.perf_counter() - s)
                active.pop()
        wrapper.__wrapped__ = fn
        return wrapper

    for label, module, attr in STAGES:
        owner = importlib.import_module(module)
        name = attr
        if "." in attr:
            cls, name = attr.split(".")
            owner = getattr(owner, cls)
        setattr(owner, name, timed(label, getattr(owner, name)))
    s = time.perf_counter()
    report = pipeline.analyze(model, data, analysis.AnalysisOptions(jobs=jobs))
    total = time.perf_counter() - s
    return {"import_s": t1 - t0, "csv_s": t2 - t1, "analyze_s": total, "calls": calls, "nested": nested,
            "located": [f"{o}:{i}" for o, i in report.located_elements]}


def _summary(runs: list) -> dict:
    """Medians over the runs: each stage's total and its calls."""
    out = {key: statistics.median(r[key] for r in runs) for key in ("import_s", "csv_s", "analyze_s")}
    stages = {}
    for label in LABELS:
        sums = [sum(r["calls"][label]) for r in runs]
        counts = [len(r["calls"][label]) for r in runs]
        # With two processes the parent's share of a stage called row by row varies from run to run (each
        # process takes the next row when it is free): then only the sums and the median count.
        each = [statistics.median(r["calls"][label][k] for r in runs) for k in range(counts[0])] \
            if len(set(counts)) == 1 else []
        stages[label] = {"total_s": statistics.median(sums), "calls": int(statistics.median(counts)), "each_s": each}
    # The first call of each stage inside the detection is the first detection's.
    first = stages["detection"]["each_s"][0] if stages["detection"]["each_s"] else 0.0
    # A stage run inside another one (with two processes the row test runs within the element test, while
    # the child starts on the rows) is not subtracted twice.
    inside = sum(stages[label]["each_s"][0] for label in INSIDE_DETECTION
                 if stages[label]["each_s"] and not runs[0].get("nested", {}).get(label, [False])[0])
    out["stages"] = stages
    out["rest_of_first_detection_s"] = first - inside
    out["located"] = runs[0]["located"]
    return out


def format_size(size: str, s: dict) -> str:
    lines = [f"{size}: analyze {s['analyze_s']:.2f} s (imports {s['import_s']:.2f} s and the CSV {s['csv_s']:.2f} s "
             f"before it); located {', '.join(s['located']) or 'none'}"]
    for label in LABELS:
        st = s["stages"][label]
        each = " + ".join(f"{x:.3f}" for x in st["each_s"]) if st["calls"] <= 4 and st["each_s"] else \
            f"{st['calls']} calls"
        lines.append(f"  {label:<28} {st['total_s']:7.3f} s   ({each})")
    lines.append(f"  {'rest of the first detection':<28} {s['rest_of_first_detection_s']:7.3f} s")
    return "\n".join(lines)


def run(sizes, repeats: int = 3, seed: int = 0, log=print, jobs: int = 1) -> dict:
    """The breakdown at every size; a JSON-ready dict."""
    from bench.perf import INDUSTRIAL_SAMPLES, machine_info, write_industrial_case

    tmp = Path(tempfile.mkdtemp(prefix="mpm_stages_"))
    out = {"machine": machine_info(), "repeats": repeats, "samples": INDUSTRIAL_SAMPLES, "jobs": jobs, "sizes": {}}
    for ny, nu in sizes:
        yml, csv = write_industrial_case(tmp, ny, nu, INDUSTRIAL_SAMPLES, seed)
        runs = []
        for _ in range(repeats):
            done = subprocess.run([sys.executable, "-m", "bench.stages", "--jobs", str(jobs), "--child", str(yml), str(csv)],
                                  capture_output=True, text=True, check=True)
            runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
        size = f"{ny}x{nu}"
        out["sizes"][size] = {"summary": _summary(runs), "runs": runs}
        log(format_size(size, out["sizes"][size]["summary"]))
    out["machine"]["load_average_end"] = list(os.getloadavg())
    return out


def main(argv=None) -> int:
    parser = sizes_parser("python -m bench.stages", __doc__, "fresh interpreters per size (default 3)")
    parser.add_argument("--jobs", type=int, default=1,
                        help="processes of the analysis (AnalysisOptions.jobs; default 1: every stage in the process, "
                             "so that each is timed whole; with 2 the stages a child shares show the parent's wall time)")
    parser.add_argument("--child", nargs=2, metavar=("MODEL", "CSV"), help=argparse.SUPPRESS)
    args, sizes = parse_sized(parser, argv)
    if args.child:
        print(json.dumps(child(*args.child, jobs=args.jobs)))
        return 0
    positive(parser, "--jobs", args.jobs)
    result = run(sizes, args.repeats, args.seed, jobs=args.jobs)
    if args.out:
        write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
