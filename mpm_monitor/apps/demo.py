"""The node suite in one process: plant, MPC, setpoint and monitor on a private context, in lock-step.

:func:`case_parameters` gives every node's parameters for a case (the same numbers as
:func:`mpm_monitor.sim.cases.simulation_case`, so a run through the nodes with a seed reproduces the
batch run :func:`mpm_monitor.sim.closed_loop.run_closed_loop` with that seed sample for sample).
:class:`Suite` builds the four nodes on one context and one executor, waits until every publisher
sees its subscribers, starts the plant and spins until the monitor has analysed the last sample.
:func:`run_demo` is ``python -m mpm_monitor demo``; the launcher ``launch_scripts/suite_inprocess.py``
and the throughput benchmark (``bench/ros_throughput.py``) build the same :class:`Suite`.

Simulated time (lock-step): the plant publishes ``/clock = k Ts``, ``dv(k)`` (the level case's
measured disturbance) and ``y(k)``; the setpoint node answers the clock with ``r(k)`` (and the
dither); the MPC answers ``r(k), y(k)`` (and ``dv(k)``) with ``u(k)``; the plant applies ``u(k)``
and moves to ``k + 1``.  Every vector is stamped ``k Ts``; the topics are
RELIABLE with depth 1000 and each step waits for the previous one, so no sample can be dropped.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from ..core.errors import ConfigurationError, InputError
from ..core.model import PlantModel
from ..core.wording import repair_text
from ..io.model_file import save_model
from ..sim.cases import CASE_NAMES, DEMO_CASES, simulation_case

#: Environment of a context that talks to nobody outside its process.
PRIVATE_ENV = {"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}


@contextlib.contextmanager
def _env(values: dict):
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def private_context():
    """An initialised ``rclpy.context.Context`` isolated from every other process.

    The discovery range is OFF while the context is initialised (the middleware reads it then), so
    nodes on this context see each other and nothing else, whatever ``ROS_DOMAIN_ID`` is.
    """
    import rclpy
    from rclpy.context import Context

    ctx = Context()
    with _env(PRIVATE_ENV):
        rclpy.init(args=[], context=ctx)
    return ctx


# ------------------------------------------------------------------------------- parameters
def case_parameters(case: str, seed: int = 1, model_file: str = "") -> dict:
    """Parameters of each node for a case, as ``{node_name: {parameter: value}}``.

    Parameters
    ----------
    case : str
        "3.1", "3.2", "3.3" (the paper's) or "level".
    seed : int
        Seed of the plant noise, the PRBS and the dither.
    model_file : str
        The controller's model file for the MPC, setpoint and monitor nodes; "" = ``case``.
    """
    if case not in DEMO_CASES:
        raise ConfigurationError(f"case: expected one of {', '.join(DEMO_CASES)}, got {case!r}")
    c = simulation_case(case)
    dist, mpc, exc = c.disturbance, c.mpc, c.excitation

    def weight(w):
        return [float(v) for v in np.atleast_1d(w)]

    model_src = {"model_file": model_file} if model_file else {"case": case}
    plant = {"case": case, "seed": int(seed), "disturbance_std": dist.disturbance_std,
             "disturbance_pole": dist.disturbance_pole, "noise_std": dist.noise_std}
    dv = c.measured_disturbance
    if dv is not None:
        plant.update(dv_step_amplitude=dv.step_amplitude, dv_switch_probability=dv.switch_probability,
                     dv_min_hold=dv.min_hold, dv_noise_std=dv.noise_std, dv_noise_pole=dv.noise_pole,
                     dv_offset=dv.offset)
    mpc_p = dict(model_src, prediction_horizon=mpc.prediction_horizon, control_horizon=mpc.control_horizon,
                 output_weight=weight(mpc.output_weight), input_weight=weight(mpc.input_weight),
                 input_rate_weight=weight(mpc.input_rate_weight), use_dither=exc.dither is not None)
    sp = dict(model_src, mode="prbs", seed=int(seed), amplitude=exc.setpoint.amplitude,
              switch_probability=exc.setpoint.switch_probability, min_hold=exc.setpoint.min_hold,
              offset=exc.setpoint.offset)
    if exc.dither is not None:
        sp.update(dither_amplitude=exc.dither.amplitude, dither_switch_probability=exc.dither.switch_probability,
                  dither_min_hold=exc.dither.min_hold)
    monitor = dict(model_src)
    return {"plant": plant, "mpc": mpc_p, "setpoint": sp, "monitor": monitor}


def _overrides(values: dict) -> list:
    from rclpy.parameter import Parameter

    return [Parameter(k, value=v) for k, v in values.items()]


# ------------------------------------------------------------------------------------ suite
class Suite:
    """Plant, MPC, setpoint and monitor nodes on one context and one executor.

    Parameters
    ----------
    context : rclpy.context.Context
        Usually :func:`private_context`.
    params : dict
        ``{node_name: {parameter: value}}`` (e.g. :func:`case_parameters` updated with the monitor's
        window); the plant's ``max_samples`` sets the run length.
    namespace : str
        Namespace of the four nodes (their relative topics follow it).
    analyze : callable, optional
        Injected into the monitor (default: the real analysis).
    executor : {"events", "single"}
    extra_subscribers : int
        Further subscribers (a recorder) each vector topic must see before the plant starts.
    """

    def __init__(self, context, params: dict, namespace: str = "", analyze: Optional[Callable] = None,
                 executor: str = "events", extra_subscribers: int = 0):
        from ..nodes.monitor_node import MonitorNode
        from ..nodes.mpc_node import MpcNode
        from ..nodes.plant_node import PlantNode
        from ..nodes.ros_io import make_executor
        from ..nodes.setpoint_node import SetpointNode

        self.context = context
        plant_p = dict(params["plant"], autostart=False)
        self.samples = int(plant_p.get("max_samples", 0))
        kw = dict(context=context, namespace=namespace)
        self.plant = PlantNode(parameter_overrides=_overrides(plant_p), **kw)
        self.setpoint = SetpointNode(parameter_overrides=_overrides(params["setpoint"]), **kw)
        self.mpc = MpcNode(parameter_overrides=_overrides(params["mpc"]), **kw)
        self.monitor = MonitorNode(parameter_overrides=_overrides(params["monitor"]), analyze=analyze, **kw)
        self.nodes = [self.plant, self.setpoint, self.mpc, self.monitor]
        self.extra_subscribers = int(extra_subscribers)
        self.executor = make_executor(context, executor)
        for n in self.nodes:
            self.executor.add_node(n)
        self.started_at: Optional[float] = None
        self.loop_seconds: Optional[float] = None

    def add_node(self, node) -> None:
        """Spin another node (a listener, a recorder) in the same executor."""
        self.executor.add_node(node)
        self.nodes.append(node)

    def connected(self, diagnostics_listeners: int = 0) -> bool:
        """True when every publisher of the loop sees all its subscribers."""
        x = self.extra_subscribers
        checks = [(self.plant._pub, 2 + x), (self.setpoint._pub, 2 + x), (self.mpc._pub, 2 + x),
                  (self.monitor._diag_pub, diagnostics_listeners)]
        if self.plant._dv_pub is not None:
            checks.append((self.plant._dv_pub, 2 + x))
        if self.plant._clock_pub is not None:
            checks.append((self.plant._clock_pub, 1))
        if self.setpoint._dither_pub is not None:
            checks.append((self.setpoint._dither_pub, 1 if self.mpc.params["use_dither"] else 0))
        return all(pub.get_subscription_count() >= n for pub, n in checks)

    def spin_until(self, done: Callable[[], bool], timeout: float) -> bool:
        from ..nodes.ros_io import spin_until

        return spin_until(self.executor, done, timeout=timeout, context=self.context, step=0.02)

    def start(self, connect_timeout: float = 20.0, diagnostics_listeners: int = 0) -> None:
        """Wait for discovery, then publish the first sample."""
        if not self.spin_until(lambda: self.connected(diagnostics_listeners), connect_timeout):
            raise RuntimeError(f"the nodes did not discover each other within {connect_timeout:g} s")
        self.started_at = time.perf_counter()
        self.plant.start()

    def loop_done(self) -> bool:
        """True when the plant ran its samples and the monitor holds every one of them."""
        return self.plant.finished and self.monitor.core.window.n_completed >= self.samples

    def final_result_ready(self) -> bool:
        """True when the monitor has a result for the window ending at the last sample."""
        out = self.monitor.core.latest_outcome
        return out is not None and out.job.completed >= self.samples

    def run(self, timeout: float = 120.0, final_analysis: bool = True) -> bool:
        """Spin until the loop ends (and, with ``final_analysis``, the last window is analysed)."""
        deadline = time.monotonic() + timeout
        if not self.spin_until(self.loop_done, timeout):
            return False
        if self.started_at is not None:
            self.loop_seconds = time.perf_counter() - self.started_at
        if not final_analysis:
            return True
        self.monitor.request_analysis()
        return self.spin_until(self.final_result_ready, max(0.0, deadline - time.monotonic()))

    def close(self) -> None:
        """Stop the analysis thread and destroy the nodes."""
        for n in self.nodes:
            close = getattr(n, "close", None)
            if close is not None:
                close()
        for n in self.nodes:
            self.executor.remove_node(n)
            n.destroy_node()
        self.executor.shutdown()


class DiagnosticsPrinter:
    """Subscribes to the monitor's diagnostics and prints each new result once."""

    def __init__(self, context, topic: str = "/diagnostics", namespace: str = "", out=sys.stdout, quiet=False):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.node import Node

        from ..nodes.ros_io import diagnostics_qos

        self.node = Node("mpm_demo_printer", context=context, namespace=namespace)
        self.node.create_subscription(DiagnosticArray, topic, self._on_msg, diagnostics_qos())
        self.out = out
        self.quiet = quiet
        self.latest = None
        self._printed = set()

    def wait_for(self, suite: "Suite", timeout: float) -> bool:
        """Spin ``suite`` until the monitor's latest result has been received here."""
        return suite.spin_until(lambda: self.latest is not None
                                and _analyses(self.latest) >= suite.monitor.core.results, timeout)

    def _on_msg(self, msg) -> None:
        from ..monitor.statuses import LEVEL_NAMES, SUMMARY_NAME

        statuses = {s.name: s for s in msg.status}
        summary = statuses.get(SUMMARY_NAME)
        if summary is None:
            return
        values = {kv.key: kv.value for kv in summary.values}
        self.latest = msg
        key = (values.get("analyses"), summary.level)
        if key in self._printed or self.quiet:
            self._printed.add(key)
            return
        self._printed.add(key)
        w = self.out.write
        w(f"[/diagnostics] {summary.name}: {LEVEL_NAMES.get(summary.level[0], '?')}: {summary.message}\n")
        for s in msg.status:
            if s is summary:
                continue
            v = {kv.key: kv.value for kv in s.values}
            rsi = v.get("rsi", "nan")
            try:
                rsi = f"{float(rsi):.3f}"
            except ValueError:
                pass
            w(f"    {s.name}: {LEVEL_NAMES.get(s.level[0], '?'):5s} rsi={rsi:6s} mismatch={v.get('mismatch', '?'):5s} "
              f"flagged_inputs=[{v.get('flagged_inputs', '')}]\n")
        self.out.flush()


def _write_model(model: PlantModel, directory: str, name: str) -> str:
    path = str(Path(directory) / name)
    save_model(model, path)
    return path


def run_demo(case: str = "3.2", samples: Optional[int] = None, bag: Optional[str] = None, seed: int = 1,
             quiet: bool = False, out=sys.stdout, timeout: float = 600.0) -> int:
    """``python -m mpm_monitor demo``: the four nodes on a case, diagnostics printed as they arrive.

    Parameters
    ----------
    case : str
        "3.1", "3.2", "3.3" (the paper's) or "level" (an integrating level and a measured inflow).
    samples : int, optional
        Samples to simulate (default 3000).
    bag : str, optional
        Record every topic, ``/diagnostics`` included, to this rosbag2 (MCAP) directory.
    seed : int
    quiet : bool
        Print only the final result.

    Returns
    -------
    int
        0 when the demo ran.
    """
    n = 3000 if samples is None else int(samples)
    c = simulation_case(case)
    from ..core.analysis import AnalysisOptions
    from ..core.regressions import regression_layout

    need = max(100, regression_layout(c.model, AnalysisOptions()).min_samples)
    if n < need:
        raise InputError(f"--samples: case {case} needs at least {need} samples for the monitor's analysis, got {n}")
    recorder_cls = None
    if bag:
        if Path(bag).exists():
            raise InputError(f"--bag {bag}: already exists; give a new directory")
        try:
            from ..nodes.recorder_node import RecorderNode as recorder_cls
        except ImportError as exc:
            raise InputError(f"--bag needs the recorder node (mpm_monitor.nodes.recorder_node), which cannot be "
                             f"imported: {exc}") from None
    ctx = private_context()
    suite = recorder = None
    try:
        with tempfile.TemporaryDirectory(prefix="mpm_demo_") as tmp:
            model_file = _write_model(c.model, tmp, f"model_case_{case.replace('.', '_')}.yaml")
            params = case_parameters(case, seed=seed, model_file=model_file)
            params["plant"]["max_samples"] = n
            min_samples = min(1000, n)
            # the data stop when the run ends: keep the last result from ageing to STALE while it is computed
            params["monitor"].update(window_samples=n, min_samples=min_samples,
                                     analysis_period=max(min_samples, n // 3), stale_timeout=60.0)
            if quiet:           # before the nodes exist: each logs what it runs when it starts
                from rclpy.logging import LoggingSeverity, set_logger_level

                for name in params:
                    set_logger_level(name, LoggingSeverity.WARN)
            suite = Suite(ctx, params)
            if quiet:
                for node in suite.nodes:
                    node.get_logger().set_level(LoggingSeverity.WARN)
            printer = DiagnosticsPrinter(ctx, out=out, quiet=quiet)
            suite.add_node(printer.node)
            if recorder_cls is not None:
                topics = ["setpoint", "input", "output", "/diagnostics", "mpm_monitor/rsi", "/clock"]
                if c.excitation.dither is not None:
                    topics.append("dither=sensor_msgs/msg/JointState")
                if c.plant.n_disturbances:
                    topics.append("disturbance")
                recorder = recorder_cls(bag_dir=bag, topics=topics, context=ctx)
                if quiet:
                    from rclpy.logging import LoggingSeverity

                    recorder.get_logger().set_level(LoggingSeverity.WARN)
                suite.add_node(recorder)
                suite.extra_subscribers = 1
            if not quiet:
                what = "paper case" if case in CASE_NAMES else "case"
                out.write(f"demo: {what} {case} ({c.description}), {n} samples in simulated time, seed {seed}\n"
                          f"      the monitor analyses the last {n} samples every {params['monitor']['analysis_period']}"
                          f" samples after the first {min_samples}\n")
                out.flush()
            suite.start(diagnostics_listeners=1 + (recorder is not None))
            ok = suite.run(timeout=timeout)
            # let the final diagnostics reach the printer (and the recorder)
            printer.wait_for(suite, 5.0)
            if recorder is not None:
                _settle(suite, recorder)
                count = recorder.close()
                out.write(f"recorded {count} messages to {bag}\n")
            if not ok:
                out.write(f"demo: stopped after {timeout:g} s at sample {suite.plant.k} of {n}\n")
            report = suite.monitor.core.latest_report
            loop_s = suite.loop_seconds or float("nan")
            out.write(f"\n{suite.monitor.core.window.n_completed} samples through the nodes in {loop_s:.1f} s "
                      f"({suite.monitor.core.window.n_completed / loop_s:.0f} samples/s), "
                      f"{suite.monitor.core.window.health().missing_samples} dropped\n")
            if report is None:
                out.write("no analysis result\n")
            else:
                rows = [r.output for r in report.rows if r.mismatch]
                els = [_element_text(e) for e in report.elements if e.mismatch]
                out.write("located rows: " + (", ".join(rows) if rows else "none") + "\n")
                out.write("located elements: " + (", ".join(els) if els else "none") + "\n")
                exp_el = ", ".join(f"({o}, {i})" for o, i in c.mismatched_elements) or "none"
                source = "paper" if case in CASE_NAMES else "expected"
                out.write(f"{source}: rows {', '.join(c.mismatched_rows) or 'none'}; elements {exp_el}\n")
                out.write(repair_text(report, c.model, c.plant))
            out.flush()
    finally:
        if suite is not None:
            suite.close()
        ctx.try_shutdown()
    return 0


def _element_text(e) -> str:
    """``(y1, u2)``, or ``(level, inflow: measured disturbance)`` for a measured disturbance's element."""
    kind = ": measured disturbance" if getattr(e, "role", "input") == "disturbance" else ""
    return f"({e.output}, {e.input}{kind})"


def _settle(suite: Suite, recorder, quiet: float = 0.5, timeout: float = 5.0) -> None:
    """Spin until the recorder has taken no new message for ``quiet`` seconds (at most ``timeout``).

    The printer having the final diagnostics does not mean the recorder's copy has been taken yet
    (each subscription has its own queue); without this, the bag could miss the last result.
    """
    state = {"count": recorder.message_count, "since": time.monotonic()}

    def quiet_enough():
        n = recorder.message_count
        if n != state["count"]:
            state.update(count=n, since=time.monotonic())
        return time.monotonic() - state["since"] >= quiet

    suite.spin_until(quiet_enough, timeout)


def _analyses(msg) -> int:
    from ..monitor.statuses import SUMMARY_NAME

    for s in msg.status:
        if s.name == SUMMARY_NAME:
            for kv in s.values:
                if kv.key == "analyses":
                    return int(kv.value)
    return 0
