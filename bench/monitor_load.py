"""Load on the live monitor: does it keep up, and does its analysis block the subscriptions? (issue 7)

Run::

    python -m bench.monitor_load [--quick] [--json bench/results/monitor_load.json]

A plain rclpy publisher (no plant or MPC node of ours) sends the three contract topics
(``setpoint``, ``input``, ``output`` as ``sensor_msgs/JointState``) from a thread of the same
process, stamped in simulated time ``k * Ts``, paced at the plant's real rate (or as fast as it
can, for the ceiling).  The monitor node (:class:`mpm_monitor.nodes.monitor_node.MonitorNode`)
spins in a SingleThreadedExecutor on the main thread and runs the real analysis
(:func:`mpm_monitor.core.pipeline.analyze`, no repair) in its worker thread while the samples keep
coming.  Both share one private context (``ROS_AUTOMATIC_DISCOVERY_RANGE=OFF``).

Figures per run:

* ``sent`` / ``completed`` / ``dropped``: samples published, samples the monitor aligned into its
  window, and the difference (``dropped`` must be 0; ``missing``, ``gaps`` and ``late`` are the
  window's own counters);
* ``lag``: wall time from publishing a sample's last vector to the sample completing in the
  window (p50 / p99 / max, milliseconds), and the largest lag of a sample published while an
  analysis was running -- if the analysis blocked the subscriptions this would be about the
  analysis time;
* ``analyses`` and ``analysis s``: analyses finished during the run and their mean/max duration;
  a job submitted while one runs replaces the waiting one (``replaced``), so a slow analysis
  never builds a backlog.

Scenarios (the issue's figures): a 20x20 plant at 10 Hz (window 1,500 samples, analysis every
100 samples = 10 s; the first 1,200 samples are sent at 200 Hz to reach the analysis sooner, then
30 s paced at 10 Hz) and a 3x3 plant at
1 kHz (window 3,000 samples = 3 s, analysis every 500 samples, 10 s paced).  Then the ceiling:
the same two sizes paced at increasing rates until the monitor loses samples (the publisher, the
executor and the analysis share the interpreter, so this is the rate one process sustains).

The models are :func:`bench.plants.square_model` (diagonally dominant FOPDT, delays 1..7
samples) rescaled to the sample time; the data are random (PRBS setpoints, white inputs and
outputs): the analysis cost depends on the sizes, not on the values.  This is a measurement, not a
unit test; ``test_robust_monitor`` asserts zero drops at a modest rate with :func:`run_load`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from .plants import square_model
from .ros_domain import close_nodes

NS = 1_000_000_000


@dataclasses.dataclass
class LoadResult:
    """Figures of one :func:`run_load` run (see the module docstring)."""

    size: str
    rate_hz: Optional[float]          # None = as fast as possible
    analysis_in: str                  # "process" or "thread"
    sent: int
    completed: int
    dropped: int
    missing: int
    gaps: int
    late: int
    publish_seconds: float            # wall time the publisher took for the paced/unpaced part
    achieved_rate: float              # samples per second of that part
    lag_ms_p50: float
    lag_ms_p99: float
    lag_ms_max: float
    lag_ms_max_during_analysis: float
    samples_during_analysis: int
    analyses: int
    analysis_s_mean: float
    analysis_s_max: float
    replaced: int
    analysis_error: str               # the last analysis failure ("" = none)

    def line(self) -> str:
        rate = "max" if self.rate_hz is None else f"{self.rate_hz:g} Hz"
        return (f"{self.size:>6} {rate:>8} {self.analysis_in:>7} {self.sent:>7} {self.completed:>9} {self.dropped:>7} "
                f"{self.achieved_rate:>9.0f} {self.lag_ms_p50:>7.1f} {self.lag_ms_p99:>7.1f} {self.lag_ms_max:>7.1f} "
                f"{self.lag_ms_max_during_analysis:>8.1f} {self.samples_during_analysis:>7} {self.analyses:>4} "
                f"{self.analysis_s_mean:>6.2f} {self.analysis_s_max:>6.2f}"
                + (f"  ANALYSIS FAILED: {self.analysis_error}" if self.analysis_error else ""))


HEADER = (f"{'size':>6} {'rate':>8} {'ana. in':>7} {'sent':>7} {'completed':>9} {'dropped':>7} {'samples/s':>9} "
          f"{'lag p50':>7} {'p99':>7} {'max':>7} {'max(ana)':>8} {'n(ana)':>7} {'ana':>4} {'mean s':>6} {'max s':>6}")


def load_model(n: int, sample_time: float):
    """An n x n FOPDT model with the dynamics of :func:`bench.plants.square_model` in samples."""
    m = square_model(n)
    return m.replace(sample_time=sample_time, time_constant=m.time_constant * sample_time,
                     delay=np.rint(m.delay) * sample_time, name=f"{n}x{n} load model")


def run_load(n: int, rate_hz: Optional[float], samples: int, window_samples: int, min_samples: int,
             analysis_period: int, prefill: int = 0, prefill_rate_hz: Optional[float] = None, seed: int = 0,
             analyze=None, analysis_process: bool = True, timeout: float = 300.0, quiet: bool = True) -> LoadResult:
    """Publish ``prefill`` samples at ``prefill_rate_hz`` then ``samples`` paced at ``rate_hz``
    (None = unpaced) to a monitor node analysing in its worker thread; measure what it completes
    and how late.

    Parameters
    ----------
    n : int
        Outputs = inputs of the plant.
    rate_hz : float or None
        Publication rate of the measured part, samples per second of wall time; also 1 / sample time.
    samples, prefill : int
        Samples of the measured part and of the fill-up before it (to reach ``min_samples`` sooner).
    prefill_rate_hz : float or None
        Rate of the fill-up (None = as fast as possible: a burst).
    window_samples, min_samples, analysis_period : int
        Monitor parameters (samples).
    analyze : callable, optional
        Injected analysis (default the real one).
    analysis_process : bool
        The monitor's parameter of that name: the real analysis in a child process (default) or in
        the worker thread itself.
    """
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from mpm_monitor.apps.demo import _overrides, private_context
    from mpm_monitor.io.model_file import save_model
    from mpm_monitor.nodes.monitor_node import MonitorNode
    from mpm_monitor.nodes.ros_io import VectorCodec, make_executor, spin_until, vector_qos

    ts = 1.0 / rate_hz if rate_hz else 0.001
    model = load_model(n, ts)
    period = int(round(ts * NS))
    total = prefill + samples
    rng = np.random.default_rng(seed)
    r = np.sign(rng.normal(size=(total, n)))
    u = rng.normal(size=(total, n))
    y = rng.normal(size=(total, n))
    ctx = private_context()
    tmp = tempfile.mkdtemp(prefix="mpm_load_")
    model_file = str(Path(tmp) / "model.yaml")
    save_model(model, model_file)
    busy = []              # (start, end) monotonic seconds of each analysis
    busy_lock = threading.Lock()

    monitor = MonitorNode(context=ctx, namespace="/load", analyze=analyze, parameter_overrides=_overrides({
        "model_file": model_file, "window_samples": window_samples, "min_samples": min_samples,
        "analysis_period": analysis_period, "analysis_thread": True, "analysis_process": analysis_process,
        "stale_timeout": 3600.0, "diagnostics_topic": "diagnostics", "repair": False}))
    inner = monitor._analyze   # the real analysis, in a child process unless analysis_process is False

    failures = []

    def timed_analyze(m, data, options):
        t0 = time.monotonic()
        try:
            return inner(m, data, options)
        except Exception as exc:
            failures.append(f"{type(exc).__name__}: {str(exc)[:200]}")
            raise
        finally:
            with busy_lock:
                busy.append((t0, time.monotonic()))

    monitor._analyze = timed_analyze
    done_at = np.full(total, np.nan)
    core = monitor.core
    orig_add = core.add

    def add(channel, stamp_ns, values, now):
        k_done = orig_add(channel, stamp_ns, values, now)
        if k_done:
            last = core.window.last_sample_stamp_ns // period
            t = time.monotonic()
            for kk in range(last - k_done + 1, last + 1):
                if 0 <= kk < total:
                    done_at[kk] = t
        return k_done

    core.add = add
    pub_node = Node("load_publisher", context=ctx, namespace="/load")
    pubs = {c: pub_node.create_publisher(JointState, c, vector_qos()) for c in ("setpoint", "input", "output")}
    codec_y = VectorCodec(model.outputs, "output")
    codec_u = VectorCodec(model.inputs, "input")
    ex = make_executor(ctx, "single")
    ex.add_node(monitor)
    ex.add_node(pub_node)
    published_at = np.full(total, np.nan)
    bounds = {}

    def publisher():
        t_fill = time.monotonic()
        t_start = None
        for k in range(total):
            if k == prefill:
                t_start = time.monotonic()
                bounds["start"] = t_start
            target = None
            if rate_hz and k >= prefill:
                target = t_start + (k - prefill) / rate_hz
            elif prefill_rate_hz and k < prefill:
                target = t_fill + k / prefill_rate_hz
            if target is not None:
                delay = target - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            stamp = k * period
            pubs["output"].publish(codec_y.encode(y[k], stamp))
            pubs["input"].publish(codec_u.encode(u[k], stamp))
            pubs["setpoint"].publish(codec_y.encode(r[k], stamp))
            published_at[k] = time.monotonic()
        bounds["end"] = time.monotonic()

    try:
        assert spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values()), 20.0), \
            "discovery failed"
        thread = threading.Thread(target=publisher, name="load publisher", daemon=True)
        thread.start()
        progress = {"n": -1, "t": time.monotonic()}

        def finished():
            n_done = core.window.n_completed
            now = time.monotonic()
            if n_done != progress["n"]:
                progress["n"], progress["t"] = n_done, now
            if thread.is_alive():
                return False
            # everything aligned, or nothing new for 3 s after the last publication (samples lost)
            return n_done >= total or now - progress["t"] > 3.0

        spin_until(ex, finished, timeout, step=0.01)
        thread.join(5.0)
        spin_until(ex, lambda: monitor.worker.idle, 60.0, step=0.05)
        h = core.window.health()
        measured = slice(prefill, total)
        lag = (done_at[measured] - published_at[measured]) * 1e3
        lag_ok = lag[np.isfinite(lag)]
        with busy_lock:
            intervals = list(busy)
        pub = published_at[measured]
        during = np.zeros(pub.shape, dtype=bool)
        for a, b in intervals:
            during |= (pub >= a) & (pub <= b)
        lag_during = lag[during & np.isfinite(lag)]
        durations = [b - a for a, b in intervals]
        seconds = bounds.get("end", time.monotonic()) - bounds.get("start", time.monotonic())
        res = LoadResult(
            size=f"{n}x{n}", rate_hz=rate_hz,
            analysis_in="process" if monitor._process_analyzer is not None else "thread", sent=total, completed=int(h.completed),
            dropped=int(total - h.completed), missing=int(h.missing_samples), gaps=int(h.gaps), late=int(h.late),
            publish_seconds=seconds, achieved_rate=samples / seconds if seconds > 0 else float("nan"),
            lag_ms_p50=float(np.percentile(lag_ok, 50)) if lag_ok.size else float("nan"),
            lag_ms_p99=float(np.percentile(lag_ok, 99)) if lag_ok.size else float("nan"),
            lag_ms_max=float(lag_ok.max()) if lag_ok.size else float("nan"),
            lag_ms_max_during_analysis=float(lag_during.max()) if lag_during.size else float("nan"),
            samples_during_analysis=int(during.sum()), analyses=len(intervals),
            analysis_s_mean=float(np.mean(durations)) if durations else float("nan"),
            analysis_s_max=float(np.max(durations)) if durations else float("nan"),
            replaced=int(monitor.worker.replaced),
            analysis_error=f"{len(failures)} failed, last: {failures[-1]}" if failures else "")
        if not quiet:
            print(res.line())
            sys.stdout.flush()
        return res
    finally:
        monitor.close()
        close_nodes(ex, ctx, monitor, pub_node)


SCENARIOS = {
    # name: (n, rate_hz, samples, window, min_samples, period, prefill, prefill_rate_hz)
    "20x20 @ 10 Hz": (20, 10.0, 300, 1500, 1200, 100, 1200, 200.0),
    "3x3 @ 1 kHz": (3, 1000.0, 10_000, 3000, 1000, 500, 0, None),
}
#: Ceiling: the same sizes paced at increasing rates until samples are lost (n, rates, samples, window,
#: min_samples, period).
CEILING = {
    "20x20": (20, (100.0, 200.0, 400.0, 800.0, 1600.0), 3000, 1500, 1200, 300),
    "3x3": (3, (2000.0, 3000.0, 4000.0, 6000.0, 8000.0), 8000, 3000, 1000, 500),
}
QUICK = {
    "20x20 @ 10 Hz": (20, 10.0, 50, 1500, 1200, 25, 1200, 200.0),
    "3x3 @ 1 kHz": (3, 1000.0, 3000, 3000, 1000, 500, 0, None),
}


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.monitor_load", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="shorter runs, paced scenarios only")
    p.add_argument("--only", default=None, help="comma-separated scenario names (see SCENARIOS)")
    p.add_argument("--no-ceiling", action="store_true", help="skip the search for the highest rate without loss")
    p.add_argument("--thread", action="store_true", help="also run each paced scenario with the analysis in the "
                   "worker thread (analysis_process false), for comparison")
    p.add_argument("--json", default=None, help="write the figures to this file")
    args = p.parse_args(argv)
    scenarios = QUICK if args.quick else SCENARIOS
    if args.only:
        wanted = [s.strip() for s in args.only.split(",")]
        scenarios = {k: v for k, v in SCENARIOS.items() if k in wanted}
    print(f"monitor load: plain publisher thread -> monitor node (SingleThreadedExecutor) with the real analysis "
          f"in its worker thread; {os.cpu_count()} CPU(s), Python {platform.python_version()}; lags in ms")
    print(HEADER)
    results = []
    for name, (n, rate, samples, window, min_samples, period, prefill, prefill_rate) in scenarios.items():
        for in_process in ((True, False) if args.thread else (True,)):
            res = run_load(n, rate, samples, window, min_samples, period, prefill=prefill,
                           prefill_rate_hz=prefill_rate, analysis_process=in_process, quiet=False)
            results.append({"scenario": name if in_process else f"{name} (thread)", **dataclasses.asdict(res)})
    if not (args.quick or args.only or args.no_ceiling):
        print("ceiling: paced at increasing rates until samples are lost")
        for name, (n, rates, samples, window, min_samples, period) in CEILING.items():
            best = None
            for rate in rates:
                res = run_load(n, rate, samples, window, min_samples, period, quiet=False)
                results.append({"scenario": f"{name} ceiling", **dataclasses.asdict(res)})
                if res.dropped or res.achieved_rate < 0.95 * rate:
                    break
                best = rate
            print(f"{name}: highest paced rate without a lost sample: {best:g} Hz" if best else
                  f"{name}: samples lost already at {rates[0]:g} Hz")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"cpu_count": os.cpu_count(), "python": platform.python_version(), "runs": results}, fh,
                      indent=2)
            fh.write("\n")
    paced_ok = all(r["dropped"] == 0 for r in results if r["analysis_in"] == "process" and "ceiling" not in r["scenario"])
    return 0 if paced_ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
