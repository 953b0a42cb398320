"""Several seeds of :mod:`bench.structures_mc` pooled: per-seed figures, the pooled ones, and their intervals.

Run::

    python -m bench.structures_pool FILE [FILE ...] [--out bench/results/structures_pool.json]

Each FILE is the JSON result of one ``python -m bench.structures_mc`` run (one seed).  The runs must
share the family and the analysis (samples, alpha, element window, options, candidate flag); only
the seed, the number of runs and the machine may differ.  The records of every file are scored
together by :func:`bench.structures_mc.score`, the function that scores one seed, so the pooled
figures are exactly those of one run over all the seeds' scenarios.

Why pool: one seed of 300 runs holds about 280 located mismatches.  At that size one chance
finding moves the precision by 0.0035, and the number of chance findings is itself a Poisson count
of mean about 1.5 under the element family's level (alpha / 2 per run).  A figure like "precision
at least 0.99" is a statement about the method, which more runs estimate better.  Every seed's own
figures are printed beside the pooled ones, so no seed is hidden.

Intervals are exact (Clopper-Pearson) 95 % intervals of a binomial proportion,
:func:`clopper_pearson`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

from scipy.special import betaincinv

from . import write_json
from .structures_mc import CLEAN_INDEX_OFFSET, REPAIR_HORIZON, REPAIR_TOLERANCE, _f3, score

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "structures_pool.json"
#: Configuration keys that may differ between pooled files.
FREE_KEYS = ("seed", "runs", "clean_integrating", "jobs", "wall_time_s", "machine")


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple:
    """Exact two-sided interval of a binomial proportion ``k / n``.

    Parameters
    ----------
    k : int
        Successes, ``0 <= k <= n``.
    n : int
        Trials, ``n >= 1``.
    level : float
        Coverage, in (0, 1).

    Returns
    -------
    (float, float)
        The ``(1 - level) / 2`` quantile of Beta(k, n - k + 1) (0 when ``k == 0``) and the
        ``(1 + level) / 2`` quantile of Beta(k + 1, n - k) (1 when ``k == n``).
    """
    k, n = int(k), int(n)
    if not (n >= 1 and 0 <= k <= n and 0.0 < level < 1.0):
        raise ValueError(f"clopper_pearson: expected 0 <= k <= n, n >= 1 and 0 < level < 1, got {k}, {n}, {level}")
    tail = 0.5 * (1.0 - level)
    lo = 0.0 if k == 0 else float(betaincinv(k, n - k + 1, tail))
    hi = 1.0 if k == n else float(betaincinv(k + 1, n - k, 1.0 - tail))
    return lo, hi


def load(paths: Sequence[Path]) -> list:
    """The results of ``paths``; refuse files of different families or analyses (one line each)."""
    results = []
    for p in paths:
        try:
            res = json.loads(Path(p).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{p}: cannot read a bench.structures_mc result ({exc})") from None
        if not isinstance(res, dict) or not {"config", "runs"} <= set(res):
            raise ValueError(f"{p}: not a bench.structures_mc result (expected the keys 'config' and 'runs')")
        results.append((Path(p), res))
    if not results:
        raise ValueError("no result files given")
    ref_path, ref = results[0]
    fixed = {k: v for k, v in ref["config"].items() if k not in FREE_KEYS}
    seeds = set()
    for p, res in results:
        cfg = res["config"]
        for k, v in fixed.items():
            if cfg.get(k) != v:
                raise ValueError(f"{p}: config {k!r} is {cfg.get(k)!r}, but {ref_path} has {v!r}: "
                                 f"only runs of the same family and analysis can be pooled")
        if cfg["seed"] in seeds:
            raise ValueError(f"{p}: seed {cfg['seed']} is given twice")
        seeds.add(cfg["seed"])
    return results


def pool(results: list) -> dict:
    """Per-seed and pooled scores of :func:`load`'s results."""
    per_seed, main_all, extra_all, false_pos = [], [], [], []
    for p, res in results:
        main = [r for r in res["runs"] if r["index"] < CLEAN_INDEX_OFFSET]
        extra = [r for r in res["runs"] if r["index"] >= CLEAN_INDEX_OFFSET]
        main_all += main
        extra_all += extra
        seed_score = score(main)
        false_pos += [{"seed": res["config"]["seed"], **f} for f in seed_score["false_positives"]]
        per_seed.append({"seed": res["config"]["seed"], "file": str(p), "summary": _brief(seed_score),
                         "clean_integrating": score(extra)["false_alarms_integrating"] if extra else None})
    pooled = score(main_all)
    ci = score(extra_all)["false_alarms_integrating"] if extra_all else None
    e, fa, rp = pooled["element"], pooled["false_alarms"], pooled["repair"]
    intervals = {
        "precision": clopper_pearson(e["tp"], e["tp"] + e["fp"]) if e["tp"] + e["fp"] else None,
        "recall": clopper_pearson(e["tp"], e["tp"] + e["fn"]) if e["tp"] + e["fn"] else None,
        "false_alarm_clean": clopper_pearson(fa["located"], fa["runs"]) if fa["runs"] else None,
        "false_alarm_clean_integrating": clopper_pearson(ci["located"], ci["runs"]) if ci and ci["runs"] else None,
        "repair_within": clopper_pearson(rp["within"], rp["scored"]) if rp["scored"] else None,
    }
    cfg = dict(results[0][1]["config"])
    for k in FREE_KEYS:
        cfg.pop(k, None)
    return {"config": {**cfg, "seeds": [s["seed"] for s in per_seed], "files": [s["file"] for s in per_seed]},
            "per_seed": per_seed, "pooled": _brief(pooled), "pooled_clean_integrating": ci,
            "intervals95": intervals, "false_positives": false_pos}


def _brief(s: dict) -> dict:
    """A score without its long lists."""
    return {k: v for k, v in s.items() if k not in ("misses", "false_positives", "repair_failures")}


def _iv(iv) -> str:
    return "-" if iv is None else f"{iv[0]:.3f}-{iv[1]:.3f}"


def format_table(out: dict) -> str:
    """The figures as plain text (what ``main`` prints)."""
    cfg = out["config"]
    lines = [f"Structures Monte-Carlo pooled over seeds {', '.join(map(str, cfg['seeds']))}: "
             f"{cfg['samples']} samples, alpha {cfg['alpha']}, element window {cfg['element_window']}",
             f"{'seed':>6} {'runs':>5} {'hits':>5} {'fp':>3} {'precision':>9} {'recall':>7} {'misses':>6} "
             f"{'clean FA':>9} {'clean int. FA':>13} {'repair within':>13}"]

    def row(label, s, ci):
        e, fa, rp = s["element"], s["false_alarms"], s["repair"]
        cint = f"{ci['located']}/{ci['runs']}" if ci else "-"
        lines.append(f"{label:>6} {s['runs']:>5} {e['tp']:>5} {e['fp']:>3} {_f3(e['precision']):>9} "
                     f"{_f3(e['recall']):>7} {e['fn']:>6} {fa['located']:>4}/{fa['runs']:<4} {cint:>13} "
                     f"{rp['within']:>6}/{rp['scored']:<6}")

    for s in out["per_seed"]:
        row(str(s["seed"]), s["summary"], s["clean_integrating"])
    row("pooled", out["pooled"], out["pooled_clean_integrating"])
    iv = out["intervals95"]
    p = out["pooled"]
    lines += [f"pooled, with exact 95% intervals: precision {_f3(p['element']['precision'])} ({_iv(iv['precision'])}), "
              f"recall on identifiable elements {_f3(p['element']['recall'])} ({_iv(iv['recall'])}),",
              f"  false alarms (a located element) in clean runs {p['false_alarms']['located']}/"
              f"{p['false_alarms']['runs']} ({_iv(iv['false_alarm_clean'])}), in clean integrating runs "
              + (f"{out['pooled_clean_integrating']['located']}/{out['pooled_clean_integrating']['runs']} "
                 f"({_iv(iv['false_alarm_clean_integrating'])})" if out["pooled_clean_integrating"] else "-")
              + f"; alpha {cfg['alpha']}",
              f"  repaired step response within {100 * REPAIR_TOLERANCE:.0f}% over {REPAIR_HORIZON} samples "
              f"{_f3(p['repair']['fraction_within'])} ({_iv(iv['repair_within'])})"]
    fps = out["false_positives"]
    if fps:
        lines.append(f"false positives ({len(fps)}; seed/run element, in a row with a mismatch): "
                     + ", ".join(f"{f['seed']}/{f['index']} {tuple(f['element'])} "
                                 f"{'yes' if f['row_mismatched'] else 'no'}"
                                 for f in fps))
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.structures_pool", description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", type=Path, help="bench.structures_mc result files, one per seed")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON output")
    args = parser.parse_args(argv)
    try:
        out = pool(load(args.files))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_table(out))
    write_json(args.out, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
