"""Benchmarks of mpm_monitor (not unit tests): run as ``python -m bench.<module>``, see bench/README.md."""

import json
from pathlib import Path

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


def map_runs(star, tasks, jobs: int = 1, progress=None) -> list:
    """``[star(task) for task in tasks]``, in ``jobs`` spawned worker processes when ``jobs > 1``.

    ``star`` is a module-level function of one argument (a task tuple); ``progress(done, total,
    result)`` is called after each result, in the order of ``tasks``.
    """
    results = []

    def done(result):
        results.append(result)
        if progress:
            progress(len(results), len(tasks), result)

    if jobs > 1:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(int(jobs)) as pool:
            for result in pool.imap(star, tasks):
                done(result)
    else:
        for task in tasks:
            done(star(task))
    return results
