"""The command's timeline over its processes: what each one computes when, and where a core idles.

Usage::

    .venv/bin/python -m bench.timeline [--sizes 20x20,100x40] [--repeats 3] [--jobs N] [--out FILE]

For each size, the industrial case of :mod:`bench.perf` (one element off, 10,000 samples) is written as
a model file and a CSV, and ``python -m mpm_monitor analyze`` runs on it ``repeats`` times, each in a
fresh interpreter whose processes write marks into one file: the time (``time.monotonic``, one clock for
every process of the machine), the process and the event.

* The traced interpreter's start (its first own line, after the interpreter's start-up) and its end
  (``main`` returned, before the exit).
* The start of the imports of ``mpm_monitor.core.pipeline`` (the analysis), ``scipy.linalg``,
  ``yaml`` and ``scipy.special``.
* The analysis (``pipeline.analyze``), each detection (``pipeline.detect``,
  ``pipeline.detect_unless_coloured``) and the repair (``pipeline.repair_model``): start and end.
* In each child of :class:`mpm_monitor.core.parallel.Forked`: the start and the end of its function
  (named by its qualified name: ``StartedCsvRead.__init__`` the CSV's parse, ``_TestsAhead.start`` the
  repair's disturbance tests, ``split_map`` a stage split over two processes, ``_detect/
  values_and_experiment`` the detectability and the experiment), and the end of sending its result.
* In the parent: each wait for a child's result (:meth:`Forked.result`) and its return.

The functions are wrapped, not changed: the modules are patched as they are imported (the analysis's
after its code ran), so the imports happen when the command does them.  Each mark costs a ``write``.

From the marks, each process's busy time: a child from the start of its function to the end of its
sending, the parent from its start to its end less its waits.  Then the time in which two processes or
more were busy (both cores of a two-core machine), one, and none; the stretches of at least
:data:`MIN_STRETCH` s in which one was busy, each named by the parent's phase then; and the whole
timeline of the run whose time is the median.

Last, what an even split of the analysis's work would give.  The work is the busy seconds of every
process between the analysis's begin and its finish; spread evenly over the two cores, with the rest
of the run (before and after the analysis) as it was, the command would take ``rest + work / 2`` from
the launch.  No schedule of the same work does better on two cores.  Against the command's targets
(twice the floor, which runs in turn with the traced command, as in ``bench.perf``, and 3 s at 100x40)
it prints how much work the analysis would still have to shed.  The traced command writes its marks
and imports :mod:`bench` first, so its times are a little above ``bench.perf``'s; the targets are
measured there (``bench.stages`` times the stages in one process).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from bench import parse_sized, positive, sizes_parser, write_json

#: Environment variable naming the marks' file in the traced interpreter.
LOG_VARIABLE = "MPM_TIMELINE_LOG"
#: Imports marked as they begin.
MARKED_IMPORTS = ("mpm_monitor.core.pipeline", "scipy.linalg", "yaml", "scipy.special")
#: Functions of ``mpm_monitor.core.pipeline`` marked at their start and end.
PIPELINE_PHASES = ("analyze", "detect", "detect_unless_coloured", "repair_model")
#: Stretches of one busy process shorter than this (s) are not listed (they are counted).
MIN_STRETCH = 0.010


# --- in the traced interpreter -------------------------------------------------------------------

def _marker(path: str):
    """``mark(event, label="")``: one line ``time <tab> pid <tab> event <tab> label`` appended to ``path``."""
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def mark(event: str, label: str = "") -> None:
        os.write(fd, f"{time.monotonic():.6f}\t{os.getpid()}\t{event}\t{label}\n".encode())
    return mark


def _name(fn) -> str:
    """A child's function by its qualified name, ``outer/inner`` for a function defined in another."""
    qual = getattr(fn, "__qualname__", None) or type(fn).__name__
    return qual.replace(".<locals>.", "/").replace("/<lambda>", "")


def _wrap(fn, mark, label: str):
    def wrapper(*args, **kwargs):
        mark("begin", label)
        try:
            return fn(*args, **kwargs)
        finally:
            mark("finish", label)
    wrapper.__wrapped__ = fn
    return wrapper


def _patch_parallel(parallel, mark) -> None:
    outcome, send, result = parallel._outcome, parallel._send, parallel.Forked.result

    def _outcome(fn):
        mark("child start", _name(fn))
        try:
            return outcome(fn)
        finally:
            mark("child end", _name(fn))

    def _send(*args, **kwargs):
        try:
            return send(*args, **kwargs)
        finally:
            mark("child sent")

    def waited(self):
        mark("wait")
        try:
            return result(self)
        finally:
            mark("got")

    parallel._outcome, parallel._send, parallel.Forked.result = _outcome, _send, waited


class _ImportMarks:
    """A finder that marks the start of :data:`MARKED_IMPORTS` and wraps the analysis's phases once
    ``mpm_monitor.core.pipeline`` has run: for that module it returns the spec the finders after it
    give, its loader wrapped; for every other it returns None (the next finder finds it)."""

    def __init__(self, mark):
        self.mark = mark

    def find_spec(self, name, path, target=None):
        if name in MARKED_IMPORTS:
            self.mark("import", name)
        if name != "mpm_monitor.core.pipeline":
            return None
        for finder in sys.meta_path:
            if finder is self or not hasattr(finder, "find_spec"):
                continue
            spec = finder.find_spec(name, path, target)
            if spec is not None and spec.loader is not None:
                run = spec.loader.exec_module
                mark = self.mark

                def exec_module(module):
                    run(module)
                    for attr in PIPELINE_PHASES:
                        setattr(module, attr, _wrap(getattr(module, attr), mark, attr))
                spec.loader.exec_module = exec_module
                return spec
        return None


def traced_main(argv) -> None:
    """``python -m mpm_monitor`` with ``argv``, its processes writing marks to ``$MPM_TIMELINE_LOG``; exits."""
    mark = _marker(os.environ[LOG_VARIABLE])
    mark("start")
    sys.meta_path.insert(0, _ImportMarks(mark))
    import mpm_monitor

    mpm_monitor.limit_blas_threads()           # as python -m mpm_monitor, before numpy
    from mpm_monitor.core import parallel

    _patch_parallel(parallel, mark)
    from mpm_monitor.apps.cli import main

    code = main(list(argv))
    mark("end")
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0 if code is None else int(code))


# --- reading the marks ---------------------------------------------------------------------------

def read_marks(path) -> list:
    """The marks of a file, ``[(t, pid, event, label)]`` in the order of their times."""
    marks = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            t, pid, event, label = line.rstrip("\n").split("\t")
            marks.append((float(t), int(pid), event, label))
    return sorted(marks, key=lambda m: m[0])


def _bounds(marks: list) -> tuple:
    """``(t0, parent, end)``: the time of the ``start`` mark, the process that wrote it, and its ``end``
    in seconds from ``t0`` (the last mark's when it wrote none)."""
    t0, parent = next((m[0], m[1]) for m in marks if m[2] == "start")
    return t0, parent, next((m[0] for m in marks if m[2] == "end" and m[1] == parent), marks[-1][0]) - t0


def busy_intervals(marks: list) -> dict:
    """Each process's busy intervals, ``{name: [(t0, t1), ...]}`` in seconds from the start.

    The parent (the process that marked ``start``) is busy from its start to its end less its waits;
    a child from the start of its function to the end of its sending (or of its function, when it sent
    nothing).  A child's name is its function's, numbered from 1 in the order the children started
    (``2 split_map``).  A function run inline, without a child, is the parent's.
    """
    t0, parent, end = _bounds(marks)
    busy, since = [], 0.0
    for t, pid, event, _ in marks:
        if pid != parent:
            continue
        if event == "wait":
            busy.append((since, t - t0))
        elif event == "got":
            since = t - t0
    busy.append((since, end))
    out = {"parent": [(a, b) for a, b in busy if b > a]}
    children: dict = {}
    for t, pid, event, label in marks:
        if pid == parent:
            continue
        if event == "child start" and pid not in children:
            children[pid] = [f"{len(children) + 1} {label}", t - t0, None]
        elif event in ("child end", "child sent") and pid in children:
            children[pid][2] = t - t0
    for name, a, b in children.values():
        out[name] = [(a, b if b is not None else a)]
    return out


def occupancy(intervals: dict, cores: int = 2) -> dict:
    """Seconds in which ``cores`` or more processes were busy, each smaller count, and none.

    Returns
    -------
    dict
        ``{"busy": {k: seconds}}`` for ``k = 0 .. cores`` (``cores`` meaning at least that many),
        ``"span"`` the seconds from the first start to the last end, and ``"use"`` the processor time
        a machine of ``cores`` cores could give (at most ``cores`` processes at once) over ``cores *
        span``.
    """
    events = sorted([(a, 1) for iv in intervals.values() for a, _ in iv] + [(b, -1) for iv in intervals.values()
                                                                            for _, b in iv])
    busy = {k: 0.0 for k in range(cores + 1)}
    if not events:
        return {"busy": busy, "span": 0.0, "use": 0.0}
    level, last = 0, events[0][0]
    for t, step in events:
        busy[min(level, cores)] += t - last
        level, last = level + step, t
    span = events[-1][0] - events[0][0]
    used = sum(k * s for k, s in busy.items())
    return {"busy": busy, "span": span, "use": used / (cores * span) if span > 0 else 0.0}


def phases(marks: list) -> list:
    """The parent's phases, ``[(t0, t1, phase)]`` in seconds from the start: ``before the analysis``,
    ``detection`` and ``repair`` (the outermost of each), ``analysis`` between them, ``after the analysis``."""
    t0, parent, end = _bounds(marks)
    own = [(t - t0, event, label) for t, pid, event, label in marks if pid == parent and event in ("begin", "finish")]
    begin = next((t for t, e, label in own if e == "begin" and label == "analyze"), None)
    if begin is None:
        return [(0.0, end, "before the analysis")]
    finish = next((t for t, e, label in own if e == "finish" and label == "analyze"), end)
    out = [(0.0, begin, "before the analysis")]
    depth, cursor, current = 0, begin, None
    for t, event, label in own:
        if label == "analyze":
            continue
        name = "repair" if label == "repair_model" else "detection"
        if event == "begin":
            if depth == 0:
                out.append((cursor, t, "analysis"))
                cursor, current = t, name
            depth += 1
        else:
            depth -= 1
            if depth == 0:
                out.append((cursor, t, current))
                cursor = t
    out.append((cursor, finish, "analysis"))
    out.append((finish, end, "after the analysis"))
    return [(a, b, p) for a, b, p in out if b > a]


def lone_stretches(intervals: dict, marks: list, min_length: float = MIN_STRETCH) -> list:
    """Stretches of at least ``min_length`` s in which one process alone was busy, cut where the parent's
    phase (:func:`phases`) changes: ``[(t0, t1, process, phase)]``."""
    events = sorted([(a, 1, name) for name, iv in intervals.items() for a, _ in iv]
                    + [(b, -1, name) for name, iv in intervals.items() for _, b in iv], key=lambda e: (e[0], e[1]))
    active: dict = {}
    out, since = [], None
    ph = phases(marks)
    for t, step, name in events:
        if len(active) == 1 and since is not None:
            (alone,) = active
            for a, b, phase in ph:                  # the stretch cut at the parent's phases
                lo, hi = max(a, since), min(b, t)
                if hi - lo >= min_length:
                    out.append((lo, hi, alone, phase))
        active[name] = active.get(name, 0) + step
        if active[name] == 0:
            del active[name]
        since = t if len(active) == 1 else None
    return out


def analysis_work(intervals: dict, marks: list) -> tuple:
    """``(analysis_s, work_s)``: the parent's analysis (``pipeline.analyze``) from its begin to its finish,
    and the busy seconds of every process inside it (the work a perfect split over two cores would halve).
    ``(0, 0)`` when the run has no analysis."""
    t0, parent, _ = _bounds(marks)
    own = {(event, label): t - t0 for t, pid, event, label in marks if pid == parent and event in ("begin", "finish")}
    begin, finish = own.get(("begin", "analyze")), own.get(("finish", "analyze"))
    if begin is None or finish is None:
        return 0.0, 0.0
    work = sum(max(0.0, min(b, finish) - max(a, begin)) for iv in intervals.values() for a, b in iv)
    return finish - begin, work


def summarize(marks: list, launch: float = None, exit_time: float = None) -> dict:
    """The figures of one run's marks (JSON-ready)."""
    iv = busy_intervals(marks)
    occ = occupancy(iv)
    t0, parent, _ = _bounds(marks)
    analysis_s, work_s = analysis_work(iv, marks)
    from_launch = None if launch is None or exit_time is None else exit_time - launch
    return {
        "from_launch_s": from_launch,
        "analysis_s": analysis_s, "analysis_work_s": work_s,
        # The run with its analysis's work spread evenly over the two cores: the best any split of the same
        # work could give (the rest of the run as it was).
        "balanced_from_launch_s": None if from_launch is None else from_launch - analysis_s + work_s / 2,
        "start_after_launch_s": None if launch is None else t0 - launch,
        "span_s": occ["span"], "both_cores_s": occ["busy"][2], "one_core_s": occ["busy"][1], "no_core_s": occ["busy"][0],
        "use": occ["use"],
        "busy_s": {name: sum(b - a for a, b in v) for name, v in iv.items()},
        "lone": [list(s) for s in lone_stretches(iv, marks)],
        "phases": [list(p) for p in phases(marks)],
        "marks": [(round(t - t0, 6), "parent" if pid == parent else pid, event, label) for t, pid, event, label in marks],
    }


# --- the benchmark -------------------------------------------------------------------------------

def one_run(yml: Path, csv: Path, jobs=None) -> dict:
    """One traced ``analyze`` of the case in a fresh interpreter: :func:`summarize` of its marks."""
    import subprocess
    import tempfile

    repo = str(Path(__file__).resolve().parent.parent)
    with tempfile.TemporaryDirectory(prefix="mpm_timeline_") as tmp:
        log_path = os.path.join(tmp, "marks.tsv")
        argv = ["analyze", "--model", str(yml), "--data", str(csv), "--json", os.path.join(tmp, "report.json")]
        if jobs is not None:
            argv += ["--jobs", str(jobs)]
        env = dict(os.environ, **{LOG_VARIABLE: log_path})
        env["PYTHONPATH"] = repo + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        code = f"import sys; from bench.timeline import traced_main; traced_main({argv!r})"
        launch = time.monotonic()
        done = subprocess.run([sys.executable, "-c", code], cwd=repo, env=env, capture_output=True, text=True)
        exit_time = time.monotonic()
        if done.returncode != 0:
            raise RuntimeError(f"analyze failed (exit {done.returncode}): {done.stderr.strip()[-500:]}")
        return summarize(read_marks(log_path), launch, exit_time)


def format_run(size: str, s: dict, timeline: bool = True) -> str:
    """One run's figures (:func:`summarize`) as text; with ``timeline`` its marks too."""
    def share(x: float) -> str:
        return f"{x:.3f} s ({100 * x / s['span_s']:.0f} %)" if s["span_s"] else f"{x:.3f} s"

    lines = [f"{size}: {s['span_s']:.3f} s from the first mark to the end ({s['from_launch_s']:.3f} s from the launch); "
             f"two processes busy {share(s['both_cores_s'])}, one {share(s['one_core_s'])}, none "
             f"{share(s['no_core_s'])}; processor use {100 * s['use']:.0f} % of two cores",
             "  busy: " + ", ".join(f"{name} {t:.3f} s" for name, t in s["busy_s"].items()),
             f"  one process alone for {MIN_STRETCH * 1e3:.0f} ms or more:"]
    for a, b, who, phase in s["lone"]:
        lines.append(f"    {a:6.3f} - {b:6.3f} s  {b - a:6.3f} s  {who} ({phase})")
    if timeline:
        lines.append("  marks (s from the first; parent or the child's process id):")
        for t, who, event, label in s["marks"]:
            lines.append(f"    {t:7.3f}  {who!s:>8}  {event} {label}".rstrip())
    return "\n".join(lines)


def work_to_shed(median: dict, target_s: float) -> dict:
    """Against a target for the time from the launch: the time with the analysis's work spread evenly over two
    cores (the rest of the run as it was), and the work the analysis would have to shed even then.

    Returns
    -------
    dict
        ``target_s``; ``balanced_s`` (:func:`summarize`'s ``balanced_from_launch_s``); ``shed_s``, the busy
        seconds of work to remove so that the balanced run meets the target (0 when it does), and
        ``shed_fraction`` of the analysis's work; None for both when the rest of the run alone (before and
        after the analysis) exceeds the target.
    """
    rest = median["from_launch_s"] - median["analysis_s"]
    work = median["analysis_work_s"]
    room = 2.0 * (target_s - rest)               # the work two cores can do in the time the target leaves
    shed = None if room <= 0 else max(0.0, work - room)
    return {"target_s": target_s, "balanced_s": median["balanced_from_launch_s"], "shed_s": shed,
            "shed_fraction": None if shed is None or work <= 0 else shed / work}


def format_bound(size: str, median: dict, bound: dict) -> str:
    """The lines of :func:`work_to_shed` at every target."""
    lines = [f"{size}: the analysis {median['analysis_s']:.3f} s holds {median['analysis_work_s']:.3f} s of work of "
             f"all processes; spread evenly over two cores the command would take "
             f"{median['balanced_from_launch_s']:.3f} s from the launch (it took {median['from_launch_s']:.3f} s); "
             f"floor {median['floor_s']:.3f} s (medians of the runs)"]
    for name, b in bound.items():
        if b["shed_s"] is None:
            verdict = "the rest of the run alone exceeds it"
        elif b["shed_s"] == 0:
            verdict = "met by an even split"
        else:
            verdict = f"even so the analysis would have to shed {b['shed_s']:.3f} s of work ({100 * b['shed_fraction']:.0f} %)"
        lines.append(f"  target {name} = {b['target_s']:.3f} s: {verdict}")
    return "\n".join(lines)


def run(sizes, repeats: int = 3, seed: int = 0, jobs=None, log=print) -> dict:
    """The timeline at every size; a JSON-ready dict (every run, and medians)."""
    import statistics
    import tempfile

    from bench.perf import (INDUSTRIAL_SAMPLES, TARGET_100X40_S, TARGET_COMMAND_OVER_FLOOR, _run_process, floor_command,
                            machine_info, write_industrial_case)

    tmp = Path(tempfile.mkdtemp(prefix="mpm_timeline_case_"))
    out = {"machine": machine_info(), "repeats": repeats, "samples": INDUSTRIAL_SAMPLES, "jobs": jobs, "sizes": {}}
    for ny, nu in sizes:
        yml, csv = write_industrial_case(tmp, ny, nu, INDUSTRIAL_SAMPLES, seed)
        _run_process(floor_command(csv))                  # a warm-up: the CSV in the page cache for both
        runs, floors = [], []
        for _ in range(repeats):                          # the command and its floor in turn
            runs.append(one_run(yml, csv, jobs))
            floors.append(_run_process(floor_command(csv))[0])
        keys = ("from_launch_s", "span_s", "both_cores_s", "one_core_s", "no_core_s", "use", "analysis_s",
                "analysis_work_s", "balanced_from_launch_s")
        median = {k: statistics.median(r[k] for r in runs) for k in keys}
        median["floor_s"] = statistics.median(floors)
        typical = sorted(runs, key=lambda r: r["span_s"])[(len(runs) - 1) // 2]
        size = f"{ny}x{nu}"
        targets = {f"{TARGET_COMMAND_OVER_FLOOR:g} x the floor": TARGET_COMMAND_OVER_FLOOR * median["floor_s"]}
        if (ny, nu) == (100, 40):
            targets[f"{TARGET_100X40_S:g} s"] = TARGET_100X40_S
        out["sizes"][size] = {"median": median, "floors_s": floors, "typical_run": typical, "runs": runs,
                              "bound": {name: work_to_shed(median, t) for name, t in targets.items()}}
        log(f"{size}: medians of {repeats}: {median['span_s']:.3f} s from the first mark, two processes busy "
            f"{median['both_cores_s']:.3f} s, one {median['one_core_s']:.3f} s, none {median['no_core_s']:.3f} s, "
            f"processor use {100 * median['use']:.0f} %; the run of the median time:")
        log(format_run(size, typical))
        log(format_bound(size, median, out["sizes"][size]["bound"]))
    out["machine"]["load_average_end"] = list(os.getloadavg())
    return out


def main(argv=None) -> int:
    parser = sizes_parser("python -m bench.timeline", __doc__, "runs per size (default 3)")
    parser.add_argument("--jobs", type=int, default=None, help="the command's --jobs (default: its own default)")
    args, sizes = parse_sized(parser, argv)
    positive(parser, "--jobs", args.jobs)
    result = run(sizes, args.repeats, args.seed, args.jobs)
    if args.out:
        write_json(args.out, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
