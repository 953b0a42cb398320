"""Endurance of the live monitor: a monitor process fed by a plain publisher for a long run.

Run from the repository root::

    .venv/bin/python -m bench.endurance --size 3 --rate 1000 --samples 1000000 --json bench/results/endurance_3x3.json
    .venv/bin/python -m bench.endurance --size 20 --rate 100 --samples 1000000 --json bench/results/endurance_20x20.json
    .venv/bin/python -m bench.endurance --size 3 --ceiling 1000,1500,2000,3000 --samples 30000
    .venv/bin/python -m bench.endurance --size 3 --rate 1000 --samples 200000 --loss 0.002 --json bench/results/endurance_lossy.json
    .venv/bin/python -m bench.endurance --size 3 --rate 900 --samples 200000 --loss 0.004 --burst 5 --split-gap 3000

The monitor runs as it runs in a plant: its own process (``python -m mpm_monitor.nodes.monitor_node``,
the analysis in its child process, with the repair), on a ROS domain of its own
(:func:`bench.ros_domain.held_domain`, discovery on this host only) and in a namespace of its own.
This process publishes the three contract topics (``setpoint``, ``input``, ``output``,
``sensor_msgs/JointState``) from a thread, paced at ``--rate`` samples per second of wall time,
stamped ``k / rate``; the values are a closed-loop run of an ``n x n`` plant under the MPC with the
controller model's (y1, u2) gain 30 % off (:func:`bench.plants.square_model`), ``--segment``
samples long and repeated cyclically, so every analysis locates and repairs a real mismatch.  It
listens to the monitor's diagnostics.

Figures:

* ``sent``, ``completed``, ``dropped = sent - completed`` and the window's own counters (missing
  samples, gaps, late, restarts) from the monitor's last summary;
* ``analyses`` (the summary's counter) and, for every new analysis, the publish-to-status latency:
  wall time from publishing the last sample of the analysed window to receiving the status that
  reports it (p50 / p90 / p99 / max), and the analysis' own duration;
* with ``--loss P`` the publisher leaves out each sample's messages with probability ``P`` (a
  lossy link); ``injected_losses`` counts them, and ``full_windows`` says how many analyses after
  the window first filled held a full window of samples (the monitor bridges gaps of up to
  ``max_gap`` samples instead of restarting its window); with ``--burst L`` the samples left out come
  in bursts of geometric length, mean ``L`` (:func:`bench.gaps_mc.drop_bursts`: a Wi-Fi link loses
  several messages in a row), and ``--split-gap N`` sets the monitor's ``split_gap`` (it then keeps its
  window across a burst longer than ``max_gap`` of up to ``N`` samples);
* resident memory (``VmRSS`` from ``/proc``) of the monitor process and of its analysis process (its
  largest child) every ``--rss-every`` seconds, and the verdict on a slow leak: the monitor's memory
  at the end against its memory after the first 10 % of the run (the issue's criterion: within
  10 %), with the trend over the rest of the run (MB per million samples).

The run stops early (and says so) when the monitor process exits.  This is a measurement, not a unit
test; a run of a million samples takes ``1e6 / rate`` seconds (17 minutes at 1 kHz, 2.8 hours at
100 Hz).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np

from .plants import square_model
from .ros_domain import close_listener, domain_context, domain_env, held_domain, stop_process

NS = 1_000_000_000

#: Monitor parameters by plant size: (window_samples, min_samples, analysis_period).
MONITOR_SETTINGS = {3: (3000, 1000, 500), 20: (3000, 1500, 500)}


@dataclasses.dataclass(frozen=True)
class EnduranceConfig:
    """One run: plant size, rate, length, monitor parameters.

    Attributes
    ----------
    size : int
        Outputs = inputs of the plant.
    rate_hz : float
        Samples published per second of wall time (also ``1 / sample_time``).
    samples : int
        Samples published.
    window_samples, min_samples, analysis_period : int
        The monitor's parameters.
    repair : bool
        The monitor's ``repair`` parameter.
    segment : int
        Length of the closed-loop run repeated cyclically.
    rss_every : float
        Seconds between two memory readings.
    seed : int
    loss : float
        Probability that a sample's three messages are not published (a lossy link: 0.002 is one
        sample in 500), drawn independently per sample from ``seed``.
    niceness : int or None
        The monitor's ``analysis_niceness`` parameter (None: the node's default).
    burst : float
        Mean length of a burst of samples not published (1: each sample on its own).
    split_gap : int or None
        The monitor's ``split_gap`` parameter (None: the node's default).
    """

    size: int = 3
    rate_hz: float = 1000.0
    samples: int = 1_000_000
    window_samples: int = 3000
    min_samples: int = 1000
    analysis_period: int = 500
    repair: bool = True
    segment: int = 20_000
    rss_every: float = 5.0
    seed: int = 0
    loss: float = 0.0
    niceness: Optional[int] = None
    burst: float = 1.0
    split_gap: Optional[int] = None


# ------------------------------------------------------------------------------------- set-up
def loop_data(size: int, samples: int, seed: int):
    """``(model, r, u, y)``: a closed loop of ``samples`` samples of the ``size x size`` plant under
    the MPC, the controller model's (y1, u2) gain 30 % off (sample time 1 s)."""
    from mpm_monitor.sim.closed_loop import run_closed_loop

    model = square_model(size, seed)
    plant = model.with_element(0, min(1, size - 1), gain=model.gain[0, min(1, size - 1)] * 1.3)
    log = run_closed_loop(plant, model, samples, seed=seed + 1)
    return model, log.r, log.u, log.y


def rescaled(model, sample_time: float):
    """The model with the same dynamics in samples at another sample time."""
    return model.replace(sample_time=sample_time, time_constant=model.time_constant * sample_time,
                         delay=np.rint(model.delay) * sample_time, name=f"{model.n_outputs}x{model.n_inputs} endurance")


def left_out(total: int, loss: float, burst: float, seed: int) -> np.ndarray:
    """Which of ``total`` samples the publisher leaves out, shape (total,), bool: each with probability ``loss``
    on its own, or with ``burst`` > 1 in bursts of that mean length (:func:`bench.gaps_mc.drop_bursts`; the first
    and last sample kept), drawn from ``seed``."""
    rng = np.random.default_rng(seed + 99)
    if burst <= 1:
        return rng.random(total) < loss
    from .gaps_mc import drop_bursts

    lose = np.ones(total, dtype=bool)
    lose[drop_bursts(total, loss, burst, rng)] = False
    return lose


def _rss_kb(pid: int) -> Optional[int]:
    try:
        with open(f"/proc/{pid}/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _children(pid: int) -> list:
    out = []
    try:
        for tid in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{tid}/children", encoding="ascii") as fh:
                out += [int(c) for c in fh.read().split()]
    except OSError:
        pass
    return out


def memory_of(pid: int) -> dict:
    """Resident memory (MB) of the process ``pid`` and of its largest child (the analysis process)."""
    kids = [(c, _rss_kb(c)) for c in _children(pid)]
    kids = [(c, k) for c, k in kids if k is not None]
    main = _rss_kb(pid)
    big = max(kids, key=lambda ck: ck[1]) if kids else (None, None)
    return {"monitor_mb": None if main is None else main / 1024.0,
            "analysis_mb": None if big[1] is None else big[1] / 1024.0, "analysis_pid": big[0],
            "children_mb": sum(k for _, k in kids) / 1024.0}


# ---------------------------------------------------------------------------------------- run
def run(cfg: EnduranceConfig, log=print) -> dict:
    """Publish ``cfg.samples`` samples to a monitor process and measure (see the module docstring)."""
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.node import Node
    from sensor_msgs.msg import JointState

    from mpm_monitor.io.model_file import save_model
    from mpm_monitor.monitor.statuses import SUMMARY_NAME
    from mpm_monitor.nodes.ros_io import VectorCodec, diagnostics_qos, make_executor, spin_until, vector_qos

    t_setup = time.monotonic()
    base, r, u, y = loop_data(cfg.size, cfg.segment, cfg.seed)
    ts = 1.0 / cfg.rate_hz
    model = rescaled(base, ts)
    period = int(round(ts * NS))
    tmp = Path(tempfile.mkdtemp(prefix="mpm_endurance_"))
    model_file = tmp / "model.yaml"
    save_model(model, model_file)
    ns = f"/endurance{os.getpid()}"
    total = int(cfg.samples)
    published_at = np.full(total, np.nan)
    events = []                 # one per new analysis: (t_recv, window_end_s, analyses, analysis_s, completed)
    latest = {}
    memory = []                 # (t, samples published, monitor_mb, analysis_mb)
    state = {"published": 0, "behind": 0, "done": False, "lost": 0}
    lose = left_out(total, cfg.loss, cfg.burst, cfg.seed)

    with held_domain() as domain:
        env = dict(os.environ, **domain_env(domain), PYTHONUNBUFFERED="1")
        params = {"model_file": str(model_file), "window_samples": cfg.window_samples,
                  "min_samples": cfg.min_samples, "analysis_period": cfg.analysis_period,
                  "repair": "true" if cfg.repair else "false", "stale_timeout": 3600.0,
                  "republish_period": 1.0, "diagnostics_topic": "diagnostics"}
        if cfg.niceness is not None:
            params["analysis_niceness"] = cfg.niceness
        if cfg.split_gap is not None:
            params["split_gap"] = cfg.split_gap
        cmd = [sys.executable, "-m", "mpm_monitor.nodes.monitor_node", "--ros-args", "-r", f"__ns:={ns}"]
        for k, v in params.items():
            cmd += ["-p", f"{k}:={v}"]
        monitor_log = open(tmp / "monitor.log", "wb")
        proc = subprocess.Popen(cmd, env=env, stdout=monitor_log, stderr=subprocess.STDOUT)
        ctx = domain_context(domain)
        node = Node("endurance_publisher", context=ctx, namespace=ns)
        pubs = {c: node.create_publisher(JointState, c, vector_qos()) for c in ("setpoint", "input", "output")}
        codec_y, codec_u = VectorCodec(model.outputs, "output"), VectorCodec(model.inputs, "input")

        def on_diagnostics(msg):
            now = time.monotonic()
            for s in msg.status:
                if s.name != SUMMARY_NAME:
                    continue
                values = {kv.key: kv.value for kv in s.values}
                values["_level"] = s.level[0] if isinstance(s.level, (bytes, bytearray)) else int(s.level)
                values["_message"] = s.message
                n_an = int(values.get("analyses", "0") or 0)
                if n_an > int(latest.get("analyses", "0") or 0) and values.get("window_end", "nan") != "nan":
                    events.append((now, float(values["window_end"]), n_an, float(values.get("analysis_seconds", "nan")),
                                   int(values.get("completed_samples", "0")), int(values.get("samples", "0") or 0)))
                latest.clear()
                latest.update(values)

        node.create_subscription(DiagnosticArray, "diagnostics", on_diagnostics, diagnostics_qos())
        ex = make_executor(ctx, "single")
        ex.add_node(node)

        def publisher():
            t0 = time.monotonic()
            state["start"] = t0
            for k in range(total):
                target = t0 + k / cfg.rate_hz
                delay = target - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                elif delay < -0.1:
                    state["behind"] += 1
                if lose[k]:
                    state["lost"] += 1
                    continue
                j = k % r.shape[0]
                stamp = k * period
                pubs["output"].publish(codec_y.encode(y[j], stamp))
                pubs["input"].publish(codec_u.encode(u[j], stamp))
                pubs["setpoint"].publish(codec_y.encode(r[j], stamp))
                published_at[k] = time.monotonic()
                state["published"] = k + 1 - state["lost"]
                if proc.poll() is not None:
                    break
            state["end"] = time.monotonic()
            state["done"] = True

        def sampler():
            while True:
                m = memory_of(proc.pid)
                memory.append((time.monotonic(), state["published"], m["monitor_mb"], m["analysis_mb"]))
                if state.get("sampler_stop"):
                    return
                time.sleep(cfg.rss_every)

        result = {}
        try:
            if not spin_until(ex, lambda: all(p.get_subscription_count() >= 1 for p in pubs.values())
                              or proc.poll() is not None, 60.0):
                raise RuntimeError("the monitor process did not subscribe within 60 s")
            if proc.poll() is not None:
                raise RuntimeError(f"the monitor process exited (code {proc.returncode}); see {tmp / 'monitor.log'}")
            log(f"{cfg.size}x{cfg.size} at {cfg.rate_hz:g} Hz, {total} samples (about {total / cfg.rate_hz / 60:.0f} "
                f"min), window {cfg.window_samples}, analysis every {cfg.analysis_period}, repair "
                f"{'on' if cfg.repair else 'off'}, analysis niceness "
                f"{'default' if cfg.niceness is None else cfg.niceness}; monitor pid {proc.pid}, domain {domain}; set-up "
                f"{time.monotonic() - t_setup:.1f} s")
            pub_thread = threading.Thread(target=publisher, name="publisher", daemon=True)
            mem_thread = threading.Thread(target=sampler, name="memory", daemon=True)
            pub_thread.start()
            mem_thread.start()
            next_report = time.monotonic() + max(30.0, cfg.rss_every)

            def publishing_done():
                nonlocal next_report
                now = time.monotonic()
                if now >= next_report:
                    next_report = now + 60.0
                    mon = memory[-1][2] if memory else float("nan")
                    ana = memory[-1][3] if memory and memory[-1][3] is not None else float("nan")
                    log(f"  {state['published']:>9} sent, {latest.get('completed_samples', '?'):>9} completed, "
                        f"{latest.get('analyses', '0'):>5} analyses; RSS monitor {mon:.0f} MB, analysis {ana:.0f} MB")
                return state["done"]

            spin_until(ex, publishing_done, None, step=0.05)
            sent = state["published"]
            # Let the monitor finish: every sample aligned (or no progress for 10 s), then the last analysis.
            progress = {"n": -1, "t": time.monotonic()}

            def aligned():
                n = int(latest.get("completed_samples", "0") or 0)
                now = time.monotonic()
                if n != progress["n"]:
                    progress["n"], progress["t"] = n, now
                return n >= sent or now - progress["t"] > 10.0 or proc.poll() is not None

            spin_until(ex, aligned, 600.0, step=0.05)
            done_n = int(latest.get("completed_samples", "0") or 0)
            last_due = done_n - (done_n - cfg.min_samples) % cfg.analysis_period if done_n >= cfg.min_samples else None
            if last_due is not None:
                spin_until(ex, lambda: (events and round(events[-1][1] / ts) >= last_due - 1)
                           or proc.poll() is not None, 300.0, step=0.05)
            spin_until(ex, lambda: False, 1.5, step=0.05)       # one more republication of the counters
            state["sampler_stop"] = True
            mem_thread.join(cfg.rss_every + 5.0)
            result = summarize(cfg, sent, state, latest, events, memory, published_at, ts,
                               proc.poll())
            result["monitor_log"] = str(tmp / "monitor.log")
        finally:
            state["sampler_stop"] = True
            state["done"] = True
            stop_process(proc, 20.0)
            monitor_log.close()
            close_listener(ex, node, ctx)
    result["monitor_exit_code"] = proc.returncode
    return result


# ------------------------------------------------------------------------------------ figures
def _percentiles(x) -> dict:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not x.size:
        return {"n": 0}
    return {"n": int(x.size), "min": float(x.min()), "p50": float(np.percentile(x, 50)),
            "p90": float(np.percentile(x, 90)),
            "p99": float(np.percentile(x, 99)), "max": float(x.max()), "mean": float(x.mean())}


def memory_verdict(memory: list, sent: int, key: int) -> dict:
    """Memory at the end against after the first 10 % of the run, and the trend over the rest.

    ``memory`` rows are ``(t, samples, monitor_mb, analysis_mb)``; ``key`` selects the column.
    """
    rows = [(k, m[key]) for m in memory for k in [m[1]] if m[key] is not None]
    if len(rows) < 2 or sent <= 0:
        return {"readings": len(rows)}
    k = np.array([a for a, _ in rows], float)
    mb = np.array([b for _, b in rows], float)
    after = np.flatnonzero(k >= 0.1 * sent)
    if not after.size:
        return {"readings": len(rows)}
    ref = float(mb[after[0]])
    end = float(mb[-1])
    rest = after
    slope = float(np.polyfit(k[rest], mb[rest], 1)[0] * 1e6) if rest.size >= 3 and np.ptp(k[rest]) > 0 else float("nan")
    return {"readings": len(rows), "at_10_percent_mb": ref, "at_end_mb": end, "peak_mb": float(mb.max()),
            "end_over_10_percent": end / ref if ref > 0 else float("nan"),
            "within_10_percent": bool(abs(end / ref - 1.0) <= 0.10) if ref > 0 else None,
            "trend_mb_per_million_samples": slope}


def summarize(cfg: EnduranceConfig, sent: int, state: dict, latest: dict, events: list, memory: list,
              published_at: np.ndarray, ts: float, exit_code) -> dict:
    """The figures of a run (see the module docstring)."""
    completed = int(latest.get("completed_samples", "0") or 0)
    lat = []
    for t_recv, window_end, *_ in events:
        k_end = int(round(window_end / ts))
        if 0 <= k_end < published_at.size and np.isfinite(published_at[k_end]):
            lat.append(t_recv - published_at[k_end])
    seconds = state.get("end", time.monotonic()) - state.get("start", time.monotonic())
    return {
        "config": dataclasses.asdict(cfg), "machine": {"cpu_count": os.cpu_count(), "python": platform.python_version(),
                                                       "load_average_end": list(os.getloadavg())},
        "sent": sent, "completed": completed, "dropped": sent - completed,
        "window": {k: int(latest.get(k, "0") or 0) for k in ("missing_samples", "gaps", "late", "restarts",
                                                               "bad_messages", "off_grid", "duplicates",
                                                               "out_of_order", "conflicts")},
        "publish_seconds": seconds, "achieved_rate_hz": sent / seconds if seconds > 0 else float("nan"),
        "publisher_behind_100ms": int(state.get("behind", 0)),
        "analyses": int(latest.get("analyses", "0") or 0), "analyses_seen": len(events),
        "injected_losses": int(state.get("lost", 0)),
        "analysed_window_samples": _percentiles([e[5] for e in events]),
        "full_windows": {"analyses_after_first_fill": sum(1 for e in events if e[4] >= cfg.window_samples),
                         "full": sum(1 for e in events if e[4] >= cfg.window_samples and e[5] >= cfg.window_samples)},
        "latency_s": _percentiles(lat), "analysis_seconds": _percentiles([e[3] for e in events]),
        "final_summary": {"level": latest.get("_level"), "message": latest.get("_message"),
                          "located_elements": latest.get("located_elements")},
        "memory": {"monitor": memory_verdict(memory, sent, 2), "analysis": memory_verdict(memory, sent, 3),
                   "series": [{"t": t - memory[0][0], "samples": k, "monitor_mb": a, "analysis_mb": b}
                              for t, k, a, b in memory] if memory else []},
        "monitor_exit_code_at_end": exit_code,
    }


def format_result(res: dict) -> str:
    """The run's figures as a few lines of text."""
    c = res["config"]
    lat, ana = res["latency_s"], res["analysis_seconds"]
    mon, an = res["memory"]["monitor"], res["memory"]["analysis"]

    def mem(v):
        if "at_end_mb" not in v:
            return "not enough readings"
        return (f"{v['at_10_percent_mb']:.0f} MB after 10% -> {v['at_end_mb']:.0f} MB at the end "
                f"(x{v['end_over_10_percent']:.3f}, peak {v['peak_mb']:.0f} MB, trend "
                f"{v['trend_mb_per_million_samples']:+.1f} MB per million samples)")
    w = res["window"]
    lines = [
        f"endurance {c['size']}x{c['size']} at {c['rate_hz']:g} Hz: {res['sent']} sent in {res['publish_seconds']:.0f} s "
        f"({res['achieved_rate_hz']:.1f} samples/s), {res['completed']} completed, {res['dropped']} dropped "
        f"(missing {w['missing_samples']}, gaps {w['gaps']}, late {w['late']}, restarts {w['restarts']})",
        f"  analyses {res['analyses']} (statuses seen {res['analyses_seen']}); publish-to-status latency "
        + (f"p50 {lat['p50']:.2f} s, p90 {lat['p90']:.2f} s, p99 {lat['p99']:.2f} s, max {lat['max']:.2f} s"
           if lat.get("n") else "none")
        + (f"; analysis {ana['mean']:.2f} s mean, {ana['max']:.2f} s max" if ana.get("n") else ""),
        f"  injected losses {res['injected_losses']}; analysed windows: {res['full_windows']['full']} of "
        f"{res['full_windows']['analyses_after_first_fill']} after the first fill hold {c['window_samples']} samples"
        + (f" (min {res['analysed_window_samples']['min']:.0f})" if res['analysed_window_samples'].get('n') else ""),
        f"  memory of the monitor: {mem(mon)}",
        f"  memory of its analysis process: {mem(an)}",
        f"  final summary: {res['final_summary']['message']}",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.endurance", description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=3, help="outputs = inputs of the plant (default 3)")
    p.add_argument("--rate", type=float, default=1000.0, help="samples per second (default 1000)")
    p.add_argument("--samples", type=int, default=1_000_000)
    p.add_argument("--window", type=int, default=None, help="window_samples (default by size)")
    p.add_argument("--min-samples", type=int, default=None)
    p.add_argument("--period", type=int, default=None, help="analysis_period (default by size)")
    p.add_argument("--no-repair", action="store_true")
    p.add_argument("--segment", type=int, default=20_000, help="length of the closed-loop run repeated")
    p.add_argument("--rss-every", type=float, default=5.0, help="seconds between memory readings")
    p.add_argument("--ceiling", default=None, help="comma-separated rates: run each (shortest first) until "
                   "samples are lost, and report the highest without a loss")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--loss", type=float, default=0.0, help="probability that a sample is not published (a lossy "
                   "link; 0.002: one in 500)")
    p.add_argument("--burst", type=float, default=1.0, help="mean length of a burst of samples not published "
                   "(default 1: each on its own)")
    p.add_argument("--split-gap", type=int, default=None, help="the monitor's split_gap (default: the node's)")
    p.add_argument("--niceness", type=int, default=None, help="the monitor's analysis_niceness (default: the node's)")
    p.add_argument("--json", default=None, help="write the figures here")
    args = p.parse_args(argv)
    window, min_samples, period = MONITOR_SETTINGS.get(args.size, (3000, 1500, 500))
    cfg = EnduranceConfig(size=args.size, rate_hz=args.rate, samples=args.samples,
                          window_samples=args.window or window, min_samples=args.min_samples or min_samples,
                          analysis_period=args.period or period, repair=not args.no_repair, segment=args.segment,
                          rss_every=args.rss_every, seed=args.seed, loss=args.loss, niceness=args.niceness,
                          burst=args.burst, split_gap=args.split_gap)
    results = []
    if args.ceiling:
        best = None
        for rate in sorted(float(v) for v in args.ceiling.split(",")):
            res = run(dataclasses.replace(cfg, rate_hz=rate))
            print(format_result(res), flush=True)
            results.append(res)
            if res["dropped"] or res["achieved_rate_hz"] < 0.98 * rate:
                break
            best = rate
        print(f"{args.size}x{args.size}: highest rate without a lost sample: "
              + (f"{best:g} Hz" if best else "none of those tried"))
    else:
        res = run(cfg)
        print(format_result(res), flush=True)
        results.append(res)
    if args.json:
        out = Path(args.json)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(results if args.ceiling else results[0], indent=1, default=float) + "\n")
        print(f"wrote {out}")
    return 0 if all(r["dropped"] == 0 and r["monitor_exit_code_at_end"] is None for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
