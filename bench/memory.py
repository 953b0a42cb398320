"""Memory of the sliding-window analysis (issue 8), measured with tracemalloc.

Run from the repository root::

    .venv/bin/python -m bench.memory [--quick] [--tall] [--out bench/results/memory.json]

For n x n plants and windows of W samples, :class:`mpm_monitor.core.sliding.SlidingWindowAnalyzer`
is built and filled, and tracemalloc (which numpy reports its buffers to) gives

* ``held``: bytes the analyzer keeps between analyses (window buffer, Gram matrices, model state);
* ``analysis_peak``: the extra peak during one ``analyze()`` (window copies, fits, report).

The held memory is fitted as ``a(n) + b(n) W`` per plant size; ``b / channels`` with
``channels = 3 n_outputs + n_inputs`` (r, u, y and the model output yhat are kept) is the figure in
bytes per sample per channel, and ``a`` is the part that does not grow with the window (mostly the
two Gram matrices, which grow with the square of the number of lagged regressors).

``--tall`` adds industrial sizes, 50x50 and 100x40 (outputs x inputs), with a window of 10,000
samples: one cell each (the analysis of a 100x40 window takes tens of seconds).
"""

from __future__ import annotations

import argparse
import json
import sys
import tracemalloc
from pathlib import Path

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.sliding import SlidingWindowAnalyzer

from .plants import random_plant

OPTIONS = AnalysisOptions(repair=False, test_all_rows=True)


#: Industrial sizes of ``--tall`` (outputs, inputs) and their window.
TALL_SIZES = ((50, 50), (100, 40))
TALL_WINDOW = 10_000


def _plant(n: int, n_inputs=None):
    nu = n if n_inputs is None else n_inputs
    return random_plant(n, nu, np.random.default_rng(2000 + n if n_inputs is None else 2000 + 100 * n + nu))


def measure_one(n: int, window: int, seed: int = 0, n_inputs=None) -> dict:
    """Held and analysis-peak bytes of an analyzer of an ``n x n`` (or ``n x n_inputs``) plant with a
    full window of ``window`` samples."""
    nu = n if n_inputs is None else n_inputs
    model = _plant(n, n_inputs)
    rng = np.random.default_rng(seed)
    total = window + 100
    r = np.where(rng.random((total, n)) < 0.5, 1.0, -1.0)
    u = rng.standard_normal((total, nu))
    y = rng.standard_normal((total, n))
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        an = SlidingWindowAnalyzer(model, OPTIONS, window)
        an.push_many(r, u, y)
        an.flush()
        held = tracemalloc.get_traced_memory()[0] - base
        tracemalloc.reset_peak()
        before = tracemalloc.get_traced_memory()[0]
        report = an.analyze()
        peak = tracemalloc.get_traced_memory()[1] - before
        del report
        parts = an.memory_bytes()
    finally:
        tracemalloc.stop()
    return {"n": n, "n_inputs": nu, "window": window, "channels": 3 * n + nu, "held_bytes": int(held),
            "analysis_peak_bytes": int(peak), "buffer_bytes": parts["buffer"], "gram_bytes": parts["gram"]}


def measure_tall(log=print) -> list:
    """One cell of :func:`measure_one` per industrial size (:data:`TALL_SIZES`, :data:`TALL_WINDOW`)."""
    cells = []
    for ny, nu in TALL_SIZES:
        c = measure_one(ny, TALL_WINDOW, n_inputs=nu)
        cells.append(c)
        log(f"  {ny}x{nu}, W={TALL_WINDOW}: held {c['held_bytes'] / 2**20:.0f} MiB (Gram {c['gram_bytes'] / 2**20:.0f} MiB, "
            f"buffer {c['buffer_bytes'] / 2**20:.0f} MiB); one analyze() peaks {c['analysis_peak_bytes'] / 2**20:.0f} MiB "
            f"above that")
    return cells


def measure_memory(quick: bool = False, log=print) -> dict:
    """The grid of :func:`measure_one`, the per-size linear fits and a one-line summary."""
    sizes = (2, 5, 10) if quick else (2, 5, 10, 20)
    windows = (2000, 5000) if quick else (2000, 5000, 10000, 20000)
    rows, fits = [], []
    for n in sizes:
        cells = [measure_one(n, w) for w in windows]
        rows += cells
        w = np.array([c["window"] for c in cells], float)
        held = np.array([c["held_bytes"] for c in cells], float)
        slope, intercept = np.polyfit(w, held, 1)
        peak_slope = np.polyfit(w, [c["analysis_peak_bytes"] for c in cells], 1)[0]
        ch = cells[0]["channels"]
        fit = {"n": n, "channels": ch, "bytes_per_sample": slope, "bytes_per_sample_per_channel": slope / ch,
               "fixed_bytes": intercept, "gram_bytes": cells[0]["gram_bytes"],
               "analysis_peak_bytes_per_sample_per_channel": peak_slope / ch}
        fits.append(fit)
        log(f"  {n}x{n}: held {slope / ch:.2f} B/sample/channel + {intercept / 1e6:.2f} MB fixed "
            f"(Gram {cells[0]['gram_bytes'] / 1e6:.2f} MB); analysis peak {peak_slope / ch:.1f} B/sample/channel")
    per_ch = [f["bytes_per_sample_per_channel"] for f in fits]
    peak_ch = [f["analysis_peak_bytes_per_sample_per_channel"] for f in fits]
    grams = ", ".join("{0}x{0}: {1:.2f} MB".format(f["n"], f["gram_bytes"] / 1e6) for f in fits)
    summary = (f"held {min(per_ch):.1f}-{max(per_ch):.1f} bytes per sample per channel (channels = 3 n_outputs + "
               f"n_inputs; float64 rows of the window plus a quarter-window slack), plus Gram matrices independent "
               f"of the window ({grams}); one analyze() peaks {min(peak_ch):.0f}-{max(peak_ch):.0f} bytes per "
               f"sample per channel above that")
    return {"cells": rows, "fits": fits, "summary": summary}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.memory", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--tall", action="store_true", help="also 50x50 and 100x40 with a window of 10,000")
    parser.add_argument("--out", default="bench/results/memory.json")
    args = parser.parse_args(argv)
    result = measure_memory(args.quick)
    print(result["summary"])
    if args.tall:
        result["tall"] = measure_tall()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
