"""How long ``load_model`` takes on a large step-response (DMC) model file.

Usage::

    .venv/bin/python -m bench.model_load [--sizes 40x40,100x40] [--lengths 120,400] [--repeats 3]
                                         [--out bench/results/model_load.json]

For each size (outputs x inputs) and step-response length, a model of first-order step responses
(gains 0.5 to 2, time constants 5 to 60 samples, six significant digits, one line per output as
``save_model`` writes it) is written to a temporary file, and a fresh interpreter per repeat times
``load_model`` on it (the file read, the YAML parse, the validation and the model's construction).
Medians over the repeats; the file's size in MB and its numbers are printed beside them.  The figures
hold no target: they say what a large DMC model costs the command before its analysis starts.

``--block`` writes the models with ``yaml.safe_dump`` in YAML's block style (one number per line) instead.

``--analyze OxI`` also times the whole command, ``python -m mpm_monitor analyze`` with the repair, on
a DMC model of that size against its parametric form, on the same log: :func:`bench.plants.random_plant`
sampled every 8 s (time constants 10 to 80 s, dead times 0 to 8 samples), one gain 30 % off in the
controller's model, 10,000 samples of the closed loop; the step-response form is
:func:`bench.step_models.step_form` (settled to 12 time constants: about 130 coefficients).  The two
forms are run in turn, ``--repeats`` times each; medians, and the located elements of each.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from bench import parse_sized, parse_sizes, sizes_parser, write_json


def write_model(path: Path, ny: int, nu: int, length: int, seed: int = 0, block: bool = False) -> int:
    """A step-response model file of ``ny`` outputs, ``nu`` inputs and ``length`` coefficients; its bytes.
    ``block``: written by ``yaml.safe_dump`` in block style (one number per line) instead of ``save_model``."""
    from mpm_monitor.core.model import PlantModel
    from mpm_monitor.io.model_file import save_model

    rng = np.random.default_rng(seed)
    k = np.arange(length)
    gain = rng.uniform(0.5, 2.0, (ny, nu, 1))
    tau = rng.uniform(5.0, 60.0, (ny, nu, 1))
    coef = np.round(gain * (1.0 - np.exp(-k / tau)), 6)
    model = PlantModel.from_step_response(1.0, tuple(f"u{j + 1}" for j in range(nu)),
                                          tuple(f"y{i + 1}" for i in range(ny)), coef)
    if block:
        import yaml

        path.write_text(yaml.safe_dump(model.to_dict(), sort_keys=False))
    else:
        save_model(model, path)
    return path.stat().st_size


def child(path: str) -> dict:
    """One timed load in this (fresh) interpreter."""
    import time

    from mpm_monitor.io.model_file import load_model

    t0 = time.perf_counter()
    model = load_model(Path(path))
    return {"load_s": time.perf_counter() - t0, "shape": list(model.step_response.shape)}


def run(sizes, lengths, repeats: int = 3, seed: int = 0, log=print, block: bool = False) -> dict:
    """The load times of every size and length (module docstring); a JSON-ready dict."""
    out = {"repeats": repeats, "seed": seed, "style": "block" if block else "flow", "cells": []}
    with tempfile.TemporaryDirectory(prefix="mpm_model_load_") as folder:
        _load_cells(Path(folder), sizes, lengths, repeats, seed, log, out["cells"], block)
    out["load_average_end"] = list(os.getloadavg())
    return out


def _load_cells(tmp: Path, sizes, lengths, repeats: int, seed: int, log, cells: list, block: bool = False) -> None:
    """Each cell of :func:`run`, its model written in ``tmp``, appended to ``cells``."""
    for ny, nu in sizes:
        for length in lengths:
            path = tmp / f"m{ny}x{nu}x{length}.yaml"
            size = write_model(path, ny, nu, length, seed, block)
            times = []
            for _ in range(repeats):
                done = subprocess.run([sys.executable, "-m", "bench.model_load", "--child", str(path)],
                                      capture_output=True, text=True, check=True)
                times.append(json.loads(done.stdout.strip().splitlines()[-1])["load_s"])
            cell = {"outputs": ny, "inputs": nu, "length": length, "numbers": ny * nu * length,
                    "megabytes": size / 2 ** 20, "load_s": statistics.median(times), "runs_s": times}
            cells.append(cell)
            log(f"{ny}x{nu}, {length} coefficients{' (block style)' if block else ''}: {cell['numbers']:,} numbers, "
                f"{cell['megabytes']:.1f} MB, "
                f"load_model {cell['load_s']:.3f} s (median of {repeats})")
            path.unlink()


def write_analyze_case(folder: Path, ny: int, nu: int, samples: int = 10_000, seed: int = 0) -> tuple:
    """``(parametric model file, step-response model file, CSV)`` of ``--analyze``'s case in ``folder``."""
    from mpm_monitor.io.csv_log import write_log_csv
    from mpm_monitor.io.model_file import save_model
    from mpm_monitor.sim.closed_loop import run_closed_loop

    from .plants import random_plant
    from .step_models import step_form

    plant = random_plant(ny, nu, np.random.default_rng(seed + 5000 + 100 * ny + nu))
    plant = plant.replace(sample_time=8.0, delay=plant.delay * 8.0)
    model = plant.with_element(0, 1, gain=plant.gain[0, 1] * 1.3)
    log = run_closed_loop(plant, model, samples, seed=seed + 7)
    paths = folder / f"model_{ny}x{nu}.yaml", folder / f"dmc_{ny}x{nu}.yaml", folder / f"log_{ny}x{nu}.csv"
    save_model(model, paths[0])
    save_model(step_form(model), paths[1])
    write_log_csv(paths[2], log)
    return paths


def time_analyze(model: Path, csv: Path) -> tuple:
    """``(seconds, located elements)`` of one ``python -m mpm_monitor analyze`` with the repair."""
    import time

    report = model.with_suffix(".json")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "mpm_monitor", "analyze", "--model", str(model), "--data", str(csv),
                    "--json", str(report)], capture_output=True, text=True, check=True)
    seconds = time.perf_counter() - t0
    doc = json.loads(report.read_text())
    located = sorted(f"{e['output']}:{e['input']}" for e in doc["elements"] if e.get("mismatch"))
    return seconds, located


def run_analyze(ny: int, nu: int, repeats: int = 3, seed: int = 0, log=print) -> dict:
    """``--analyze``: the command on the DMC model and on its parametric form, in turn (module docstring)."""
    from mpm_monitor.io.model_file import load_model

    times: dict = {"parametric": [], "step_response": []}
    located: dict = {}
    with tempfile.TemporaryDirectory(prefix="mpm_model_analyze_") as folder:
        par, dmc, csv = write_analyze_case(Path(folder), ny, nu, seed=seed)
        length, megabytes = load_model(dmc).step_length, dmc.stat().st_size / 2 ** 20
        for _ in range(repeats):
            for form, path in (("parametric", par), ("step_response", dmc)):
                seconds, located[form] = time_analyze(path, csv)
                times[form].append(seconds)
    out = {"outputs": ny, "inputs": nu, "length": length, "megabytes": megabytes,
           "samples": 10_000, "runs_s": times, "located": located,
           **{f"{form}_s": statistics.median(t) for form, t in times.items()}}
    log(f"analyze {ny}x{nu}, 10,000 samples, with the repair: parametric model {out['parametric_s']:.2f} s, "
        f"step-response model ({length} coefficients, {out['megabytes']:.1f} MB) {out['step_response_s']:.2f} s "
        f"(x{out['step_response_s'] / out['parametric_s']:.2f}; medians of {repeats}); located "
        f"{', '.join(located['parametric']) or 'none'} and {', '.join(located['step_response']) or 'none'}")
    return out


def main(argv=None) -> int:
    parser = sizes_parser("python -m bench.model_load", __doc__, "fresh interpreters per cell (default 3)")
    parser.set_defaults(sizes="40x40,100x40")
    parser.add_argument("--lengths", default="120,400", help="step-response lengths (default 120,400)")
    parser.add_argument("--block", action="store_true",
                        help="write the models in YAML's block style, one number per line (yaml.safe_dump's default)")
    parser.add_argument("--analyze", metavar="OxI", default=None,
                        help="also time analyze on a DMC model of this size against its parametric form")
    parser.add_argument("--child", metavar="MODEL", help=__import__("argparse").SUPPRESS)
    args, sizes = parse_sized(parser, argv)
    if args.child:
        print(json.dumps(child(args.child)))
        return 0
    try:
        lengths = [int(x) for x in args.lengths.split(",")]
    except ValueError:
        parser.error(f"--lengths: expected whole numbers separated by commas, got {args.lengths!r}")
    if any(n < 1 for n in lengths):
        parser.error(f"--lengths: expected whole numbers >= 1, got {args.lengths!r}")
    analyze_size = None
    if args.analyze is not None:
        analyze_sizes = parse_sizes(parser, args.analyze, "--analyze")
        if len(analyze_sizes) != 1 or min(analyze_sizes[0]) < 1:
            parser.error(f"--analyze: expected one size such as 100x40, got {args.analyze!r}")
        analyze_size = analyze_sizes[0]
    result = run(sizes, lengths, args.repeats, args.seed, block=args.block)
    if analyze_size is not None:
        result["analyze"] = run_analyze(*analyze_size, repeats=args.repeats, seed=args.seed)
    if args.out:
        write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
