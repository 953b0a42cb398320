"""The live experiment without ROS: the monitor's decisions and words about experiments.

The analysis is a fake (plain objects with the report fields the monitor reads, and an
``experiment`` as the core's report gives it); the service and the dither topic are played by
calling :class:`~mpm_monitor.monitor.experiment.ExperimentTracker` as the node does.  Through the
nodes: test_experiment_live.py.
"""

import types

import numpy as np
import pytest

from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.monitor.experiment import END_MARGIN, ExperimentOptions, recommendation_of
from mpm_monitor.monitor.monitor_core import MonitorCore, MonitorOptions
from mpm_monitor.monitor.statuses import SUMMARY_NAME
from mpm_monitor.monitor.window import WindowOptions
from mpm_monitor.monitor.worker import run_analysis

NS = 1_000_000_000
INPUTS = ("u1", "u2", "u3", "u4", "u5")
OUTPUTS = ("y1", "y2")


def fat_model():
    from mpm_monitor.core.model import PlantModel

    return PlantModel(sample_time=1.0, inputs=INPUTS, outputs=OUTPUTS, gain=np.ones((2, 5)),
                      time_constant=np.full((2, 5), 10.0), delay=np.zeros((2, 5)))


MODEL = fat_model()


def experiment(dither=None, samples=1200):
    return types.SimpleNamespace(dither=dither or {"u4": 0.08, "u5": 0.08}, samples=samples,
                                 expected_detectable_gain_change=0.2, why="u4 and u5 move with u1")


def report(exp=None):
    """A fake report: row y1 mismatched, its inputs ambiguous; ``exp`` its experiment."""
    rows = [types.SimpleNamespace(output=o, rsi=1.3 if o == "y1" else 1.0, mismatch=o == "y1", p_value=1e-6)
            for o in OUTPUTS]
    elements = [types.SimpleNamespace(output="y1", input=i, mismatch=False, p_value=0.5, kind=None, ambiguous=True)
                for i in INPUTS]
    return types.SimpleNamespace(rows=rows, elements=elements, overall_rsi=1.3, warnings=[], experiment=exp)


def core(auto=True, cooldown=100, window=400):
    opts = MonitorOptions(window=WindowOptions(window_samples=window), analysis_period=50, min_samples=100,
                          stale_timeout=1e6, hardware_id="test",
                          experiment=ExperimentOptions(auto=auto, service="/t/mpc/start_dither", cooldown=cooldown))
    return MonitorCore(MODEL, opts)


def feed(c, k0, k1):
    for k in range(k0, k1):
        c.add("setpoint", k * NS, np.zeros(2), 0.0)
        c.add("input", k * NS, np.full(5, 0.01 * k), 0.0)
        c.add("output", k * NS, np.zeros(2), 0.0)


def analyse(c, exp):
    c.accept(run_analysis(lambda m, d, o: report(exp), MODEL, None, c.take_job()))


def summary(c):
    return {s.name: s for s in c.statuses(now=0.0)}[SUMMARY_NAME]


# ------------------------------------------------------------------------- the recommendation
def test_recommendation_read_from_an_object_or_the_json_and_capped_at_the_window():
    rec = recommendation_of(types.SimpleNamespace(experiment=experiment({"u5": 0.1, "u2": 0.05}, 900)), INPUTS, 1000)
    assert rec.dither == (("u2", 0.05), ("u5", 0.1)) and rec.samples == 900 and not rec.capped  # model order
    assert rec.why == "u4 and u5 move with u1" and rec.expected_detectable_gain_change == 0.2
    doc = {"dither": {"u4": 0.08}, "samples": 5000, "expected_detectable_gain_change": 0.2, "why": "w"}
    rec = recommendation_of(types.SimpleNamespace(experiment=doc), INPUTS, 3000)
    assert rec.samples == 2990 and rec.recommended_samples == 5000 and rec.capped
    assert rec.cap_text(3000) == "capped at 2990 samples to fit the window of 3000; 5000 recommended"
    # the window analysed when an experiment ends is taken up to END_MARGIN samples after its last
    # dithered sample (the zero vector may come late): a request of window - END_MARGIN still fits
    assert recommendation_of(types.SimpleNamespace(experiment=doc), INPUTS, 2000).samples == 2000 - END_MARGIN
    assert recommendation_of(types.SimpleNamespace(experiment=doc), INPUTS, 10).samples == 1
    assert rec.amplitudes_text() == "amplitude 0.08"
    for none in (types.SimpleNamespace(experiment=None), types.SimpleNamespace(), None,
                 types.SimpleNamespace(experiment=experiment({"u9": 0.1})),
                 types.SimpleNamespace(experiment=experiment({"u1": 0.0})),
                 types.SimpleNamespace(experiment=experiment(samples=0))):
        assert recommendation_of(none, INPUTS, 1000) is None


# ---------------------------------------------------------------------------- the decisions
def test_one_call_per_recommendation_and_none_while_it_runs():
    c = core()
    t = c.experiment
    feed(c, 0, 100)
    analyse(c, experiment())
    rec = t.next_request(c.window.n_completed, service_ready=True)
    assert rec is not None and rec.dither == (("u4", 0.08), ("u5", 0.08))
    assert rec.samples == 400 - END_MARGIN == 390   # capped to fit the window
    t.on_requested(rec)
    assert summary(c).message.endswith("experiment requested: dither on u4, u5 for 390 samples (amplitudes 0.08, "
                                       "0.08) from /t/mpc/start_dither")
    assert t.next_request(c.window.n_completed, True) is None          # a call under way
    feed(c, 100, 102)
    for k in range(100, 102):   # the dither may start before the node has taken the answer: it counts
        t.on_dither(k * NS, np.array([0, 0, 0, 0.08, 0.08]))
    t.on_dither(102 * NS, np.zeros(5))  # a zero vector before the answer ends nothing
    assert t.phase == "requested"
    t.on_response(True, "dither on u4, u5 (amplitudes 0.08, 0.08) for 390 samples, from the next sample", 102)
    for k in range(102, 110):   # the MPC's dither of samples 102..109, with the samples themselves
        t.on_dither(k * NS, np.array([0, 0, 0, 0.08, -0.08]))
        feed(c, k, k + 1)
    s = summary(c)
    assert s.message.endswith("experiment running: dither on u4, u5 (amplitudes 0.08, 0.08; 380 samples left)")
    assert s.value("experiment") == "running" and s.value("experiment_samples_left") == "380"
    assert s.value("experiment_dither") == "u4=0.08,u5=0.08" and s.value("experiments") == "1"
    # analyses during the experiment keep recommending: no second call
    feed(c, 110, 150)
    assert c.analysis_due()
    analyse(c, experiment())
    assert t.next_request(c.window.n_completed, True) is None
    assert "experiment recommended" not in summary(c).message


def test_the_window_that_includes_the_experiment_is_analysed_once_it_has_ended():
    c = core(window=400)
    t = c.experiment
    feed(c, 0, 100)
    analyse(c, experiment(samples=300))
    t.on_requested(t.next_request(100, True))
    t.on_response(True, "ok", 100)
    for k in range(100, 400):
        t.on_dither(k * NS, np.array([0, 0, 0, 0.08, 0.08]))
        if k < 399:
            feed(c, k, k + 1)
            if c.analysis_due():   # the regular analyses (every 50 samples) during the experiment
                analyse(c, experiment(samples=300))
    assert c.window.n_completed == 399 and not c.analysis_due()
    t.on_dither(400 * NS, np.zeros(5))   # the zero vector: the experiment has ended
    assert t.phase == "ended" and not c.analysis_due()   # the window does not hold sample 399 yet
    assert "experiment ended: dither on u4, u5 for 300 samples (t = 100-399 s); analysing the window that " \
           "includes it" in summary(c).message
    feed(c, 399, 400)
    assert c.analysis_due()                 # at once, not at the next analysis_period
    job = c.take_job()
    assert job.first_stamp == 0.0 and job.last_stamp == 399.0 and t.phase == "analysing"
    assert job.keep   # no later window replaces it while it waits for the analysis process
    c.accept(run_analysis(lambda m, d, o: report(None), MODEL, None, job))
    s = summary(c)
    assert t.phase == "done" and s.value("experiment") == "done"
    assert s.message.endswith("this analysis includes the experiment: dither on u4, u5 for 300 samples "
                              "(t = 100-399 s)")
    # the same recommendation again right after: not before experiment_cooldown (100) samples
    feed(c, 400, 450)
    analyse(c, experiment(samples=300))
    assert t.next_request(450, True) is None
    assert "experiment recommended: dither on u4, u5 for 300 samples (amplitudes 0.08, 0.08; not before sample " \
           "500 (experiment_cooldown))" in summary(c).message
    feed(c, 450, 500)
    job = c.take_job()
    assert not job.keep   # a regular window
    c.accept(run_analysis(lambda m, d, o: report(experiment(samples=300)), MODEL, None, job))
    assert t.next_request(500, True) is not None


def test_an_experiment_whose_zero_vector_never_comes_ends_by_its_count():
    c = core()
    t = c.experiment
    feed(c, 0, 100)
    analyse(c, experiment(samples=50))
    t.on_requested(t.next_request(100, True))
    t.on_response(True, "ok", 100)
    feed(c, 100, 150)
    assert t.phase == "running" and t.samples_left(150) == 0   # no dither topic: the count
    feed(c, 150, 160)
    assert t.phase == "ended" and c.analysis_due()


def test_refused_failed_missing_service_and_auto_off_only_report_the_recommendation():
    c = core(cooldown=1000)
    t = c.experiment
    feed(c, 0, 100)
    analyse(c, experiment())
    assert t.next_request(100, service_ready=False) is None
    assert summary(c).message.endswith("experiment recommended: dither on u4, u5 for 390 samples (amplitudes 0.08, "
                                       "0.08; capped at 390 samples to fit the window of 400; 1200 recommended; "
                                       "no dither service at /t/mpc/start_dither)")
    assert summary(c).value("experiment") == "recommended"
    t.on_requested(t.next_request(100, service_ready=True))
    t.on_response(False, "refused: u4: amplitude 0.08 above max_dither 0.05 (input units)", 100)
    s = summary(c)
    assert s.value("experiment") == "recommended" and "above max_dither" in s.value("experiment_detail")
    assert s.message.endswith("(amplitudes 0.08, 0.08; capped at 390 samples to fit the window of 400; "
                              "1200 recommended; "
                              "refused by /t/mpc/start_dither: u4: amplitude 0.08 above max_dither 0.05 "
                              "(input units); not before sample 1100 (experiment_cooldown))")
    assert t.next_request(100, True) is None
    t2 = core(cooldown=0).experiment
    t2.on_outcome(types.SimpleNamespace(report=report(experiment()), error=None, job=None))
    t2.on_requested(t2.next_request(100, True))
    t2.on_call_failed("no answer within 10 s", 100)
    assert t2.phase == "failed" and t2.next_request(100, True) is not None   # cooldown 0: at once again
    off = core(auto=False)
    feed(off, 0, 100)
    analyse(off, experiment())
    assert off.experiment.next_request(100, True) is None
    assert summary(off).message.endswith("(amplitudes 0.08, 0.08; capped at 390 samples to fit the window of 400; "
                                         "1200 recommended; auto_experiment is false)")


def test_no_recommendation_no_experiment_words():
    c = core()
    feed(c, 0, 100)
    analyse(c, None)
    s = summary(c)
    assert "experiment" not in s.message and s.value("experiment") is None
    with pytest.raises(ConfigurationError, match="experiment_cooldown"):
        ExperimentOptions(cooldown=-1)
