"""Live monitor node: setpoint, input and output (and measured disturbances) in; ``/diagnostics`` and row RSI out.

Wraps :class:`~mpm_monitor.monitor.monitor_core.MonitorCore` (window, schedule, statuses) and
:class:`~mpm_monitor.monitor.worker.AnalysisWorker` (the analysis of
:func:`mpm_monitor.core.pipeline.analyze` in a background thread).  The subscription callbacks only
decode and append to the window, so no sample waits for an analysis; every ``analysis_period``
completed samples the window is copied and handed to the worker, and its result comes back
through a short steady-clock timer and is published on ``/diagnostics`` (docs/interfaces.md, "ROS 2
topics and statuses") and as a ``std_msgs/Float64MultiArray`` of row RSI values on
``mpm_monitor/rsi``.  The latest statuses are
re-published every ``republish_period`` wall-clock seconds, turning STALE when no complete sample
came for ``stale_timeout`` seconds; bad messages (wrong channel names, lengths, non-finite values,
off-grid or conflicting stamps) make the summary ERROR with the reason.

With ``repair`` (the default) each analysis also traces the located elements to their kind and
re-estimates them (:mod:`mpm_monitor.core.repair`); the statuses carry the suggested repair, and the
``std_srvs/Trigger`` service ``~/write_repaired_model`` writes the latest repaired model to the file
named by the parameter ``repaired_model_file`` (atomically; ``success`` false with the reason when
there is no analysis yet, no change to write, or the write fails).

Experiments (docs/interfaces.md, "Detectability and experiment", "Live experiment"): when the
latest analysis recommends one (the report's ``experiment``), the summary says so; with
``auto_experiment`` the node asks the dither service ``experiment_service`` (the MPC node's
``~/start_dither``, ``rcl_interfaces/srv/SetParameters``) for it, asynchronously (the answer is
collected by the result timer; a call without an answer within :data:`DITHER_CALL_TIMEOUT` seconds
counts as failed), follows it on ``dither_topic``, says in the summary that it runs and how many
samples are left, and analyses the window that includes it as soon as it has ended.  It never asks
while a call or an experiment is under way, and after an experiment (or a refused or failed call)
not before ``experiment_cooldown`` samples; a request longer than the window is capped to fit
it (:mod:`mpm_monitor.monitor.experiment`).  A failed or refused call is a status message,
never an exception; without the service the summary only reports the recommendation.

When the model has measured disturbances the node also subscribes to ``disturbance_topic`` (one value
per measured disturbance) and a sample needs its four vectors (docs/interfaces.md, "Measured
disturbances").  With ``candidate_topic`` it also takes candidate channels (a JointState whose names
are the channels; docs/interfaces.md, "Candidate channels"): they never hold up a sample, every
analysis tests those with a value at every sample of its window as causes of the prediction error,
the statuses name a candidate effect, and the repaired model adds a located one as a measured
disturbance.  It works with any publisher of the contract topics, not only this package's plant
and MPC nodes.

Parameters (all declared with type, description and range): see :data:`PARAMS`.
"""

from __future__ import annotations

if __name__ == "__main__":  # python -m: start as the console script does (entry.py), before any import
    from .entry import run_module

    run_module("monitor_node")  # imports this module under its own name and ends the process

import dataclasses
import time
from typing import Callable, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, MultiArrayDimension
from std_srvs.srv import Trigger

from ..core.errors import ConfigurationError, ModelFileError
from ..core.options import ParamSpec
from ..monitor.experiment import ExperimentOptions
from ..monitor.monitor_core import MonitorCore, MonitorOptions
from ..monitor.statuses import ERROR, STALE, SUMMARY_NAME, StatusData
from ..monitor.window import WindowOptions
from ..monitor.worker import AnalysisWorker, ProcessAnalyzer, run_analysis
from .ros_io import (
    MODEL_PARAMS,
    MessageError,
    VectorCodec,
    check_distinct_topics,
    declare_parameters,
    diagnostics_qos,
    resolve_model,
    run_node,
    stamp_to_ns,
    topic_params,
    vector_qos,
)

#: Wall-clock seconds between two looks for finished analyses.
RESULT_POLL_PERIOD = 0.02

#: Wall-clock seconds the node waits for the dither service's answer before it counts the call as failed.
DITHER_CALL_TIMEOUT = 10.0

#: The analysis options the node declares as parameters, in their order (:data:`ANALYSIS_PARAMS`).
NODE_ANALYSIS_OPTIONS = ("alpha", "na", "nb", "band", "n_freq", "max_delay", "method", "initial_state", "repair",
                         "element_response", "confirm_responses", "release_explained", "release_quiet_rows",
                         "repair_again", "drop_spikes", "max_na", "jobs")


def analysis_params() -> tuple:
    """The node's analysis parameters, generated from the analysis options' ParamSpecs.

    Every option keeps its name, default, description and range, except two that a ROS 2
    parameter cannot hold as they are: ``band`` becomes the doubles ``band_low`` and ``band_high``,
    and ``max_delay`` (None = from the model) the integer ``max_delay`` with -1 for None.
    """
    from ..core.analysis_options import ANALYSIS_PARAMS

    out = []
    for name in NODE_ANALYSIS_OPTIONS:
        spec = ANALYSIS_PARAMS[name]
        if name == "band":
            for edge, which, default in (("low", "Lower", spec.default[0]), ("high", "Upper", spec.default[1])):
                out.append(dataclasses.replace(spec, name=f"band_{edge}", kind="double", default=default, length=None,
                                               description=f"{which} edge of the {spec.description}"))
        elif name == "max_delay":
            out.append(dataclasses.replace(spec, default=-1, low=-1,
                                           description=spec.description.rstrip(".") + " (-1 = from the model)."))
        else:
            out.append(spec)
    return tuple(out)


PARAMS = MODEL_PARAMS + (
    ParamSpec("window_samples", "int", 3000, "Length of the sliding window analysed, samples.", 10, 10_000_000),
    ParamSpec("analysis_period", "int", 500, "Completed samples between two analyses.", 1, 10_000_000),
    ParamSpec("min_samples", "int", 1000, "Samples needed before the first analysis (<= window_samples).",
              10, 10_000_000),
    ParamSpec("stale_timeout", "double", 5.0, "Wall-clock seconds without a complete sample before the statuses "
              "turn STALE.", 0.01, 86400.0),
    ParamSpec("republish_period", "double", 1.0, "Wall-clock seconds between re-publications of the latest "
              "statuses.", 0.01, 3600.0),
    ParamSpec("hold_setpoint", "bool", False, "Hold the latest setpoint for samples without one (setpoints "
              "published only on change)."),
    ParamSpec("reorder_samples", "int", 10, "Samples a later complete sample may run ahead of an incomplete one "
              "before the latter is given up as a gap.", 0, 100000),
    ParamSpec("stamp_tolerance", "double", 0.25, "Largest distance of a stamp from the sample grid, fraction of "
              "the sample time.", 0.001, 0.49),
    ParamSpec("max_gap", "int", 10, "Longest gap (missing samples) the window keeps its samples across, analysed "
              "around and never interpolated; a longer gap restarts the window (0: every gap does), unless split_gap "
              "keeps it.", 0, 10_000_000),
    ParamSpec("split_gap", "int", 0, "Longest gap (missing samples) after which the window still keeps its samples "
              "when longer than max_gap, as on a link that drops bursts of messages: the data are analysed in spans "
              "split there, as analyze splits a log with a long gap; a longer gap restarts the window (0: every gap "
              "longer than max_gap does).", 0, 10_000_000),
) + analysis_params() + (
    ParamSpec("repaired_model_file", "string", "", "File (YAML) the ~/write_repaired_model service writes the "
              "latest repaired model to ('' = the service refuses); fixed at start-up, so that no one on the "
              "domain can point the node at another file.", read_only=True),
    ParamSpec("analysis_process", "bool", True, "Run the analysis in a child process, so that it never competes "
              "with the subscription callbacks for the Python interpreter (false: in the background thread itself)."),
    ParamSpec("analysis_niceness", "int", 10, "Niceness added to the analysis process (Linux nice): where the cores "
              "are busy, the monitor's subscription callbacks and the other processes, such as the controller, are "
              "served first and the analysis waits, so that fewer samples are lost (0: the monitor's priority).",
              0, 19),
    ParamSpec("analysis_thread", "bool", True, "Run the analysis in a background thread (false: inside the "
              "callback, for debugging only)."),
    ParamSpec("hardware_id", "string", "", "hardware_id of the statuses ('' = the node's full name)."),
    ParamSpec("auto_experiment", "bool", False, "Ask experiment_service for the experiment (a dither) the latest "
              "analysis recommends; one at a time (false: only report the recommendation)."),
    ParamSpec("experiment_service", "string", "mpc/start_dither", "The dither service (rcl_interfaces/SetParameters, "
              "as the MPC node's ~/start_dither)."),
    ParamSpec("experiment_cooldown", "int", 10000, "Samples after an experiment's analysis, or a refused or failed "
              "call, before the next call.", 0, 10**9),
) + topic_params("setpoint", "input", "output", "dither", "disturbance") + (
    ParamSpec("candidate_topic", "string", "", "Topic of candidate channels (JointState, the names are the channels: "
              "logged variables the model does not use, tested as causes of the prediction error and added to the "
              "repaired model when located; '' = none).", read_only=True, empty_is_none=True),
    ParamSpec("diagnostics_topic", "string", "/diagnostics", "Topic of the diagnostics (DiagnosticArray)."),
    ParamSpec("rsi_topic", "string", "mpm_monitor/rsi", "Topic of the row RSI values (Float64MultiArray, model "
              "output order)."),
)


def analysis_options_from_params(p: dict):
    """:class:`~mpm_monitor.core.analysis.AnalysisOptions` from the node's parameter values.

    The inverse of :func:`analysis_params`: ``band_low``, ``band_high`` -> ``band``; ``max_delay`` -1 -> None.
    """
    from ..core.analysis import AnalysisOptions

    values = {name: p[name] for name in NODE_ANALYSIS_OPTIONS if name != "band"}
    values["band"] = (p["band_low"], p["band_high"])
    values["max_delay"] = None if p["max_delay"] < 0 else p["max_delay"]
    try:
        return AnalysisOptions(**values)
    except ConfigurationError as exc:
        if not str(exc).startswith("parameter band:"):
            raise
        # The option's refusal names band, which the node has as the two parameters band_low and band_high.
        raise ConfigurationError(f"parameters band_low and band_high: expected 0 <= band_low < band_high <= pi "
                                 f"rad/sample, got band_low {p['band_low']:g}, band_high {p['band_high']:g}") from None


def monitor_options_from_params(p: dict, hardware_id: str, service_name: Optional[str] = None) -> MonitorOptions:
    """:class:`~mpm_monitor.monitor.monitor_core.MonitorOptions` from the node's parameter values.

    ``service_name`` is the dither service as messages name it (default: the parameter as given).
    """
    window = WindowOptions(window_samples=p["window_samples"], reorder_samples=p["reorder_samples"],
                           stamp_tolerance=p["stamp_tolerance"], hold_setpoint=p["hold_setpoint"],
                           max_gap=p["max_gap"], split_gap=p["split_gap"])
    experiment = ExperimentOptions(auto=p["auto_experiment"], service=service_name or p["experiment_service"],
                                   cooldown=p["experiment_cooldown"])
    return MonitorOptions(window=window, analysis_period=p["analysis_period"], min_samples=p["min_samples"],
                          stale_timeout=p["stale_timeout"], hardware_id=hardware_id, experiment=experiment,
                          candidates=bool(p["candidate_topic"]))


def status_to_msg(s) -> DiagnosticStatus:
    """A :class:`~mpm_monitor.monitor.statuses.StatusData` as ``diagnostic_msgs/DiagnosticStatus``."""
    return DiagnosticStatus(level=bytes([s.level]), name=s.name, message=s.message, hardware_id=s.hardware_id,
                            values=[KeyValue(key=k, value=v) for k, v in s.values])


class MonitorNode(Node):
    """The live monitor node (see the module docstring).

    Parameters
    ----------
    name : str
        Node name.
    analyze : callable, optional
        ``analyze(model, data, options) -> report``; default :func:`mpm_monitor.core.pipeline.analyze`
        (injectable for tests of the plumbing).
    **kwargs
        Passed to ``rclpy.node.Node`` (``context``, ``parameter_overrides``, ``cli_args``, ...).
    """

    def __init__(self, name: str = "monitor", analyze: Optional[Callable] = None, **kwargs):
        super().__init__(name, **kwargs)
        p = declare_parameters(self, PARAMS)
        self.params = p
        self._process_analyzer = None
        if analyze is None:
            from ..core.pipeline import analyze
            if p["analysis_process"] and p["analysis_thread"]:
                self._process_analyzer = analyze = ProcessAnalyzer(analyze, niceness=p["analysis_niceness"])
        self._analyze = analyze
        self._analysis_options = analysis_options_from_params(p)
        self._hw = p["hardware_id"] or self.get_fully_qualified_name()
        # Checked here, not when a model file that failed loads later (in a timer's callback).
        # The two topics it publishes too: one topic of two types in one node is an RCLError out of create_*.
        check_distinct_topics(self, p, ["setpoint_topic", "input_topic", "output_topic", "disturbance_topic",
                                        "candidate_topic"] + ["dither_topic"] * p["auto_experiment"]
                              + ["diagnostics_topic", "rsi_topic"])
        self._dither_client = (self.create_client(SetParameters, p["experiment_service"])
                               if p["auto_experiment"] else None)
        self._dither_call = None   # (future, wall-clock time sent) of the call under way
        self._monitor_options = monitor_options_from_params(p, self._hw,
                                                            self.resolve_service_name(p["experiment_service"]))
        self._diag_pub = self.create_publisher(DiagnosticArray, p["diagnostics_topic"], diagnostics_qos())
        self._rsi_pub = self.create_publisher(Float64MultiArray, p["rsi_topic"], diagnostics_qos())
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._errors_published = 0
        self._last_publish = 0.0
        self.results = 0
        self.model = self.core = self.worker = None
        self._subs = []
        #: Why the model file did not load (None once it has): the node then publishes only an ERROR
        #: summary with this reason and tries the file again every ``republish_period``.
        self.model_error: Optional[str] = None
        self._model_retry_timer = None
        try:
            model = resolve_model(p["model_file"], p["case"])
        except ModelFileError as exc:
            self.model_error = str(exc)
            self.get_logger().error(f"{exc}; retrying every {p['republish_period']:g} s")
            self._model_retry_timer = self.create_timer(p["republish_period"], self._retry_model, clock=self._steady)
        else:
            self._start(model)
        self._timer = self.create_timer(p["republish_period"], self.publish_statuses, clock=self._steady)
        self._write_srv = self.create_service(Trigger, "~/write_repaired_model", self._on_write_repaired_model)

    def _start(self, model) -> None:
        """Build the window, the worker and the subscriptions for ``model``."""
        p = self.params
        self.model = model
        self.core = MonitorCore(self.model, self._monitor_options)
        self.core.start(time.monotonic())
        channels = self.core.window.channels      # setpoint, input, output (, disturbance)
        self._codecs = {ch: VectorCodec.for_channel(self.model, ch, p[f"{ch}_topic"]) for ch in channels}
        self.worker = AnalysisWorker(self._run_job, threaded=p["analysis_thread"])
        q = vector_qos()
        self._subs = [self.create_subscription(JointState, p[f"{ch}_topic"],
                                               (lambda msg, ch=ch: self._on_vector(ch, msg)), q)
                      for ch in channels]
        if p["candidate_topic"]:
            self._subs.append(self.create_subscription(JointState, p["candidate_topic"], self._on_candidates, q))
        if self._dither_client is not None:
            self._dither_codec = VectorCodec.for_channel(self.model, "dither", p["dither_topic"])
            self._subs.append(self.create_subscription(JointState, p["dither_topic"], self._on_dither, q))
        # The events executor has no guard conditions: results are collected by a short steady timer.
        self._result_timer = self.create_timer(RESULT_POLL_PERIOD, self._on_results, clock=self._steady)
        dv = f", {self.model.n_disturbances} measured disturbance(s)" if self.model.n_disturbances else ""
        self.get_logger().info(
            f"monitoring {self.model.n_outputs}x{self.model.n_inputs}{dv} ({self.model.name or 'model'}): window "
            f"{p['window_samples']} samples, analysis every {p['analysis_period']} after {p['min_samples']}")

    def _retry_model(self) -> None:
        """Try the model file again (it may have been fixed); start monitoring once it loads."""
        try:
            model = resolve_model(self.params["model_file"], self.params["case"])
        except ModelFileError as exc:
            if str(exc) != self.model_error:
                self.model_error = str(exc)
                self.get_logger().error(str(exc))
            return
        self.destroy_timer(self._model_retry_timer)
        self._model_retry_timer = None
        self.model_error = None
        self.get_logger().info(f"model file {self.params['model_file']} loaded")
        self._start(model)
        self.publish_statuses()

    # ------------------------------------------------------------------------------ inputs
    def _on_vector(self, channel: str, msg: JointState) -> None:
        now = time.monotonic()
        core = self.core
        try:
            stamp, values = self._codecs[channel].decode(msg)
        except MessageError as exc:
            core.bad_message(channel, str(exc), now)
            self.get_logger().warning(str(exc), throttle_duration_sec=5.0)
        else:
            if core.add(channel, stamp, values, now) and core.analysis_due():
                self.worker.submit(core.take_job())
        if core.data_errors != self._errors_published and now - self._last_publish > 0.2:
            self._errors_published = core.data_errors
            self.publish_statuses()

    def _on_candidates(self, msg: JointState) -> None:
        # A refused vector is a bad message of the core's (its statuses), and a warning here as in _on_vector.
        problem = self.core.add_candidates(stamp_to_ns(msg.header.stamp), msg.name, msg.position, time.monotonic())
        if problem is not None:
            self.get_logger().warning(problem, throttle_duration_sec=5.0)

    # ---------------------------------------------------------------------------- analysis
    def request_analysis(self) -> bool:
        """Analyse the window now if it holds samples not analysed yet (e.g. at the end of a run)."""
        if self.core is not None and self.core.analysis_due(force=True):
            self.worker.submit(self.core.take_job())
            return True
        return False

    def _run_job(self, job):
        return run_analysis(self._analyze, self.model, self._analysis_options, job)

    def _on_results(self) -> None:
        if self._dither_call is not None:
            self._poll_dither_call()
        outcomes = self.worker.take_outcomes()
        if not outcomes:
            return
        for outcome in outcomes:
            self.core.accept(outcome)
            self.results += 1
            if outcome.error:
                self.get_logger().error(outcome.error)
        self._request_experiment()
        rsi = self.core.rsi_vector()
        if rsi is not None:
            msg = Float64MultiArray()
            msg.layout.dim = [MultiArrayDimension(label="outputs", size=len(rsi), stride=len(rsi))]
            msg.data = [float(v) for v in rsi]
            self._rsi_pub.publish(msg)
        self.publish_statuses()

    # -------------------------------------------------------------------------- experiments
    def _on_dither(self, msg: JointState) -> None:
        """A dither vector: follow the running experiment (its zero vector ends it)."""
        try:
            stamp, values = self._dither_codec.decode(msg)
        except MessageError as exc:
            self.get_logger().warning(f"ignored: {exc}", throttle_duration_sec=5.0)
            return
        core = self.core
        core.experiment.on_dither(stamp, values)
        if core.analysis_due():
            self.worker.submit(core.take_job())

    def _request_experiment(self) -> None:
        """Call the dither service when the latest analysis recommends an experiment and none is under way."""
        if self._dither_client is None:
            return
        tracker = self.core.experiment
        rec = tracker.next_request(self.core.window.n_completed, self._dither_client.service_is_ready())
        if rec is None:
            return
        double, integer = ParameterType.PARAMETER_DOUBLE, ParameterType.PARAMETER_INTEGER
        request = SetParameters.Request(parameters=[
            ParameterMsg(name=name, value=ParameterValue(type=double, double_value=float(a))) for name, a in rec.dither
        ] + [ParameterMsg(name="samples", value=ParameterValue(type=integer, integer_value=int(rec.samples)))])
        try:
            future = self._dither_client.call_async(request)
        except Exception as exc:  # a failed call is a status, never an exception
            tracker.on_call_failed(f"{type(exc).__name__}: {exc}".splitlines()[0], self.core.window.n_completed)
            return
        self._dither_call = (future, time.monotonic())
        tracker.on_requested(rec)
        self.get_logger().info(f"experiment requested from {tracker.options.service}: dither on "
                               f"{', '.join(rec.inputs)} ({rec.amplitudes_text()}) for {rec.samples} samples")

    def _poll_dither_call(self) -> None:
        """Take the dither service's answer when it has come (or give the call up after the timeout)."""
        future, sent = self._dither_call
        tracker, completed = self.core.experiment, self.core.window.n_completed
        if future.done():
            self._dither_call = None
            try:
                results = list(future.result().results)
            except Exception as exc:
                results, why = [], f"{type(exc).__name__}: {exc}".splitlines()[0]
            else:
                why = "the answer holds no result"
            if results:
                tracker.on_response(bool(results[0].successful), str(results[0].reason), completed)
            else:
                tracker.on_call_failed(why, completed)
        elif time.monotonic() - sent > DITHER_CALL_TIMEOUT:
            self._dither_call = None
            self._dither_client.remove_pending_request(future)
            tracker.on_call_failed(f"no answer within {DITHER_CALL_TIMEOUT:g} s", completed)
        else:
            return
        if tracker.phase == "running":  # one call site per severity
            self.get_logger().info(f"{tracker.options.service}: {tracker.detail}")
        else:
            self.get_logger().warning(f"{tracker.options.service}: {tracker.phase}: {tracker.detail}")
        self.publish_statuses()

    def _on_write_repaired_model(self, request, response):
        """``~/write_repaired_model`` (std_srvs/Trigger): write the latest repaired model to ``repaired_model_file``."""
        try:
            path = self.params["repaired_model_file"]
            if self.core is None:
                ok, msg = False, f"no analysis yet: model not loaded: {self.model_error}"
            else:
                ok, msg = self.core.write_repaired_model(path, protected=(self.params["model_file"],))
        except Exception as exc:  # a service call never takes the node down
            ok, msg = False, f"cannot write the repaired model: {type(exc).__name__}: {exc}".splitlines()[0]
        response.success, response.message = bool(ok), msg
        if ok:  # one call site per severity (rclpy refuses a severity change at the same call site)
            self.get_logger().info(f"write_repaired_model: {msg}")
        else:
            self.get_logger().warning(f"write_repaired_model: {msg}")
        return response

    # ---------------------------------------------------------------------------- outputs
    def current_statuses(self, now: Optional[float] = None) -> list:
        """The statuses as plain data (what the next publication will carry)."""
        now = time.monotonic() if now is None else now
        if self.core is None:  # the model file did not load: only the summary, with the reason
            return [StatusData(ERROR, SUMMARY_NAME, f"model not loaded: {self.model_error} (retrying every "
                               f"{self.params['republish_period']:g} s)", self._hw,
                               (("model_file", self.params["model_file"]),))]
        statuses = self.core.statuses(now)
        if any(s.level == STALE for s in statuses):
            wrong = self._publishers_of_other_types()
            if wrong:
                statuses = [dataclasses.replace(s, message=f"{s.message}; {wrong}") if s.level == STALE else s
                            for s in statuses]
        return statuses

    def _publishers_of_other_types(self) -> str:
        """The publishers of another message type than ``JointState`` on the topics the monitor subscribes to,
        in words (empty: none).  DDS never connects them, so their messages never arrive and the statuses turn
        STALE with nothing else to say why."""
        expected = "sensor_msgs/msg/JointState"
        found = []
        for sub in self._subs:
            kinds = sorted({info.topic_type for info in self.get_publishers_info_by_topic(sub.topic_name)}
                           - {expected})
            if kinds:
                found.append(f"topic {sub.topic_name} has a publisher of type {', '.join(kinds)} (expected {expected})")
        return "; ".join(found)

    def publish_statuses(self) -> None:
        """Publish the current statuses on the diagnostics topic."""
        now = time.monotonic()
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [status_to_msg(s) for s in self.current_statuses(now)]
        self._diag_pub.publish(arr)
        self._last_publish = now

    def close(self) -> None:
        """Stop the analysis thread (and give up a dither call under way)."""
        if self._dither_call is not None:
            self._dither_client.remove_pending_request(self._dither_call[0])
            self._dither_call = None
        if self.worker is not None:
            self.worker.close()
        if self._process_analyzer is not None:
            self._process_analyzer.close()


def main(args=None) -> int:
    """Console script ``monitor_node``."""
    return run_node(lambda context: MonitorNode(context=context), args)

