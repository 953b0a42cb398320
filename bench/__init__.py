"""Benchmarks of mpm_monitor (not unit tests): run as ``python -m bench.<module>``, see bench/README.md."""

import json
from pathlib import Path
from typing import Sequence

import mpm_monitor

# Benchmarks are programs: like the product's entry points they run with one BLAS thread (unless
# the caller set the variables), before any benchmark module loads numpy.
mpm_monitor.limit_blas_threads()


def write_json(path, result, default=float) -> None:
    """Write a benchmark result as indented JSON (creating the folder) and say where."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1, default=default) + "\n", encoding="utf-8")
    print(f"wrote {path}")


def parse_sizes(parser, text: str, flag: str = "--sizes") -> list:
    """``[(outputs, inputs), ...]`` of ``--sizes`` text like ``20x20,100x40``; ``parser.error`` (naming ``flag``) on
    anything else."""
    sizes = []
    for part in text.split(","):
        try:
            ny, nu = (int(x) for x in part.lower().split("x"))
        except ValueError:
            parser.error(f"{flag}: expected sizes like 20x20,100x40, got {part!r}")
        sizes.append((ny, nu))
    return sizes


def sizes_parser(prog: str, doc: str, repeats_help: str):
    """The command line of a bench over plant sizes: ``--sizes --repeats --seed --out`` (add more, then
    :func:`parse_sized`)."""
    import argparse

    parser = argparse.ArgumentParser(prog=prog, description=doc.split("\n")[0])
    parser.add_argument("--sizes", default="20x20,100x40", help="sizes, e.g. 20x20,100x40 (default)")
    parser.add_argument("--repeats", type=int, default=3, help=repeats_help)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="JSON output path")
    return parser


def positive(parser, flag: str, value) -> None:
    """``parser.error`` unless ``value`` (of ``flag``) is None or an integer >= 1."""
    if value is not None and value < 1:
        parser.error(f"{flag}: expected an integer >= 1, got {value}")


def parse_sized(parser, argv):
    """``(args, sizes)`` of a :func:`sizes_parser` command line, ``--sizes`` parsed and ``--repeats`` checked."""
    args = parser.parse_args(argv)
    sizes = parse_sizes(parser, args.sizes)
    positive(parser, "--repeats", args.repeats)
    return args, sizes


def mc_parser(prog: str, doc: str, runs: int, out: Path):
    """The command line of a Monte-Carlo bench: ``--runs --seed --samples --jobs --alpha --out``."""
    import argparse

    parser = argparse.ArgumentParser(prog=prog, description=doc.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=runs)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--samples", type=int, default=3000)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--alpha", type=float, default=0.01)
    parser.add_argument("--out", type=Path, default=out)
    return parser


def imap_tasks(fn, tasks, jobs: int = 1):
    """``fn(task)`` for every task, in order: in this process, or in ``jobs`` spawned processes when ``jobs > 1``."""
    if jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(int(jobs)) as pool:
            yield from pool.imap(fn, tasks)
    else:
        for task in tasks:
            yield fn(task)


def map_runs(star, tasks, jobs: int = 1, progress=None) -> list:
    """``[star(task) for task in tasks]`` (:func:`imap_tasks`); ``progress(done, total, result)`` is
    called after each result, in the order of ``tasks``."""
    results = []
    for result in imap_tasks(star, tasks, jobs):
        results.append(result)
        if progress:
            progress(len(results), len(tasks), result)
    return results


def run_mc_main(argv, prog: str, doc: str, runs: int, out: Path, run, format_table, flags: Sequence[tuple] = ()) -> int:
    """The main of a Monte-Carlo bench: :func:`mc_parser`'s arguments, ``run(runs, seed, samples, jobs,
    alpha, progress)`` with progress every 10 runs on stderr, its :func:`format_table` printed and its
    result written to ``--out``.  ``flags``: ``(name, help, default_out)`` per on/off option ``--name`` (its
    dashes underscores as ``run``'s keyword), whose results go by default to ``default_out``."""
    import sys

    parser = mc_parser(prog, doc, runs, out)
    for name, text, flag_out in flags:
        parser.add_argument(f"--{name}", action="store_true", help=f"{text} (default --out {flag_out.name})")
    args = parser.parse_args(argv)
    keys = [name.replace("-", "_") for name, _, _ in flags]
    chosen = {key: getattr(args, key) for key in keys}
    target = next((flag[2] for key, flag in zip(keys, flags) if chosen[key] and args.out == out), args.out)

    def progress(done, total, rec):
        if done % 10 == 0 or done == total:
            print(f"  {done}/{total}", file=sys.stderr, flush=True)

    result = run(args.runs, args.seed, args.samples, args.jobs, args.alpha, progress, **chosen)
    print(format_table(result))
    write_json(target, result)
    return 0
