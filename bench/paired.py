"""Paired runs of the command on two versions of the code: the ratio that compares code with code.

Usage::

    .venv/bin/python -m bench.paired BASE [NEW] [--sizes 20x20,100x40] [--pairs 15] [--jobs 2]
                                     [--out bench/results/paired.json]

``BASE`` and ``NEW`` are git revisions of this repository (``NEW`` omitted: the working tree as it is).
Each revision is checked out in a temporary git worktree, removed at the end.  For each size the
industrial case of :mod:`bench.perf` (one element off, 10,000 samples) is written once, and
``python -m mpm_monitor analyze`` runs on it with one BLAS thread from each tree in turn (NEW, BASE,
NEW, BASE, ...; one warm-up run of each first), its JSON report written.  Printed per size: the median
wall time of each, the median of the ratios NEW / BASE pair by pair with their range, the largest
resident set of one process of each, and whether the two reports are byte-identical (a change of speed
that keeps the numbers gives the same report).

Why a tool: the machine's speed drifts by 10 to 30 % within minutes, so only runs taken in turn compare;
and both copies must have their bytecode.  These machines set ``PYTHONDONTWRITEBYTECODE``, so a copy
without its ``__pycache__`` compiles every module it imports on every run (about 0.1 s at 20x20: a
tenth of the command).  Each tree's package is compiled (``compileall``) before the runs, and the
command is checked to import the package of the tree it runs in.  No target: the figures are what a
change's note quotes.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable, Optional

REPO = Path(__file__).resolve().parent.parent


def compiled_tree(rev: Optional[str], folder: Path, repo: Path = REPO) -> Path:
    """The repository at ``rev`` with its package's bytecode compiled: a detached git worktree in
    ``folder`` (``None``: ``repo``'s own working tree, compiled in place).

    Raises
    ------
    RuntimeError
        When git cannot check the revision out (its message on one line).
    """
    tree = repo if rev is None else folder
    if rev is not None:
        done = subprocess.run(["git", "-C", str(repo), "worktree", "add", "--detach", "--quiet", str(folder), rev],
                              capture_output=True, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"git worktree add {rev}: {' '.join(done.stderr.split())}")
    done = subprocess.run([sys.executable, "-m", "compileall", "-q", str(tree / "mpm_monitor")], capture_output=True,
                          text=True)
    if done.returncode != 0:
        remove_tree(tree, repo)
        raise RuntimeError(f"compileall {tree / 'mpm_monitor'}: {' '.join((done.stdout + done.stderr).split())[:300]}")
    return tree


def remove_tree(tree: Path, repo: Path = REPO) -> None:
    """Remove a worktree made by :func:`compiled_tree` (never ``repo`` itself)."""
    if tree.resolve() != repo.resolve():
        subprocess.run(["git", "-C", str(repo), "worktree", "remove", "--force", str(tree)], capture_output=True)


def imported_from(tree: Path) -> Path:
    """The package directory ``python -m mpm_monitor`` imports when run in ``tree``."""
    done = subprocess.run([sys.executable, "-c", "import mpm_monitor, sys; sys.stdout.write(mpm_monitor.__file__)"],
                          cwd=tree, capture_output=True, text=True, check=True)
    return Path(done.stdout).resolve().parent


def pair_runs(run_a: Callable[[], tuple], run_b: Callable[[], tuple], pairs: int) -> dict:
    """``run_a`` and ``run_b`` in turn, ``pairs`` times each after one warm-up of each.

    Each call returns ``(wall seconds, largest resident MiB, exit code)``.  Returns the medians, the
    median and the range of the ratios ``a / b`` pair by pair, the largest resident sets and the exit codes.
    """
    run_a()
    run_b()
    a, b = [], []
    for _ in range(pairs):
        a.append(run_a())
        b.append(run_b())
    ratios = [x[0] / y[0] for x, y in zip(a, b)]
    return {"pairs": pairs, "a_wall_s": statistics.median(x[0] for x in a), "b_wall_s": statistics.median(x[0] for x in b),
            "ratio_median": statistics.median(ratios), "ratio_min": min(ratios), "ratio_max": max(ratios),
            "a_max_rss_mib": max(x[1] for x in a), "b_max_rss_mib": max(x[1] for x in b),
            "a_exit": sorted({x[2] for x in a}), "b_exit": sorted({x[2] for x in b}),
            "a_walls": [x[0] for x in a], "b_walls": [x[0] for x in b]}


def _command_runner(tree: Path, model: Path, csv: Path, report: Path, jobs: int) -> Callable[[], tuple]:
    """One run of the command in ``tree`` (one BLAS thread), its report written to ``report``."""
    from bench.perf import _run_process

    cmd = [sys.executable, "-m", "mpm_monitor", "analyze", "--model", str(model), "--data", str(csv),
           "--json", str(report), "--jobs", str(jobs)]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    return lambda: _run_process(cmd, cwd=tree, env=env)


def run(base: str, new: Optional[str], sizes, pairs: int = 15, jobs: int = 2, seed: int = 0, log=print) -> dict:
    """The paired runs at every size; a JSON-ready dict (``a``: NEW, ``b``: BASE)."""
    from bench.perf import INDUSTRIAL_SAMPLES, machine_info, stale_bytecode, write_industrial_case

    tmp = Path(tempfile.mkdtemp(prefix="mpm_paired_"))
    trees = []
    try:
        trees.append(compiled_tree(base, tmp / "base"))
        trees.append(compiled_tree(new, tmp / "new"))
        base_tree, new_tree = trees
        for tree in trees:
            where = imported_from(tree)
            if where != (tree / "mpm_monitor").resolve():
                raise RuntimeError(f"python -m mpm_monitor run in {tree} imports {where}, not the tree's package")
        out = {"machine": machine_info(), "base": base, "new": new or "working tree", "pairs": pairs, "jobs": jobs,
               "samples": INDUSTRIAL_SAMPLES, "sizes": {},
               "stale_bytecode_modules": [stale_bytecode(t / "mpm_monitor") for t in trees]}
        for ny, nu in sizes:
            model, csv = write_industrial_case(tmp, ny, nu, INDUSTRIAL_SAMPLES, seed)
            reports = (tmp / f"new_{ny}x{nu}.json", tmp / f"base_{ny}x{nu}.json")
            got = pair_runs(_command_runner(new_tree, model, csv, reports[0], jobs),
                            _command_runner(base_tree, model, csv, reports[1], jobs), pairs)
            got["reports_identical"] = all(p.exists() for p in reports) and \
                reports[0].read_bytes() == reports[1].read_bytes()
            size = f"{ny}x{nu}"
            out["sizes"][size] = got
            log(format_size(size, got))
        out["machine"]["load_average_end"] = list(os.getloadavg())
        return out
    finally:
        for tree in trees:
            remove_tree(tree)


def format_size(size: str, got: dict) -> str:
    return (f"{size}: new {got['a_wall_s']:.3f} s, base {got['b_wall_s']:.3f} s; new / base x{got['ratio_median']:.3f} "
            f"(median of {got['pairs']} pairs, {got['ratio_min']:.3f} to {got['ratio_max']:.3f}); largest resident set "
            f"{got['a_max_rss_mib']:.0f} and {got['b_max_rss_mib']:.0f} MiB; exit codes {got['a_exit']} and "
            f"{got['b_exit']}; reports {'identical' if got['reports_identical'] else 'DIFFERENT'}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.paired", description=__doc__.split("\n")[0])
    parser.add_argument("base", help="git revision of the code compared against")
    parser.add_argument("new", nargs="?", default=None, help="git revision (default: the working tree)")
    parser.add_argument("--sizes", default="20x20,100x40", help="plant sizes, e.g. 20x20,100x40")
    parser.add_argument("--pairs", type=int, default=15)
    parser.add_argument("--jobs", type=int, default=2, help="the command's --jobs (default 2, as the command's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="bench/results/paired.json")
    args = parser.parse_args(argv)
    try:
        sizes = tuple(tuple(int(v) for v in s.split("x")) for s in args.sizes.split(","))
        if any(len(s) != 2 or min(s) < 1 for s in sizes):
            raise ValueError
    except ValueError:
        parser.error(f"--sizes {args.sizes!r}: expected sizes like 20x20,100x40")
    if args.pairs < 1:
        parser.error("--pairs must be at least 1")
    if args.jobs < 1:
        parser.error("--jobs must be at least 1")
    try:
        result = run(args.base, args.new, sizes, args.pairs, args.jobs, args.seed)
    except RuntimeError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
