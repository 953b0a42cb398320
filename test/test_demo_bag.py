"""Issue 6 acceptance, round trip: the demo with a bag, then ``analyze --bag`` on that bag.

The demo (plant, MPC, setpoint, monitor and recorder nodes in one process, lock-step simulated
time, paper case 3.2) records every topic, ``/diagnostics`` included.  Then:

- ``python -m mpm_monitor analyze --bag`` locates the same rows and elements as the live monitor's
  last diagnostics in the same bag, with the same RSI, and suggests the same repair.  The demo's
  monitor window holds every sample (``window_samples`` = samples, one forced analysis at the end),
  and the test checks that the last recorded result is that analysis of samples 0 .. n-1;
- the bag reads back with ``rosbags.highlevel.AnyReader``: one message per sample on each vector
  topic and on ``/clock``, stamps strictly increasing, every value equal to the batch closed loop
  with the same seed (lock-step reproduces it exactly, see test_nodes_inprocess.py).
"""

import io
import json
import os
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("rclpy")
pytest.importorskip("rosbags")
pytestmark = pytest.mark.timeout(180)

from rosbags.highlevel import AnyReader  # noqa: E402

from mpm_monitor.apps import cli  # noqa: E402
from mpm_monitor.apps.demo import run_demo  # noqa: E402
from mpm_monitor.core.wording import row_repair_text  # noqa: E402
from mpm_monitor.io.bags import live_located_elements, read_diagnostics  # noqa: E402
from mpm_monitor.io.model_file import save_model  # noqa: E402
from mpm_monitor.monitor.statuses import SUMMARY_NAME, row_status_name  # noqa: E402
from mpm_monitor.sim.cases import paper_case  # noqa: E402
from mpm_monitor.sim.closed_loop import run_closed_loop  # noqa: E402

CASE = "3.2"
SAMPLES = 1500
SEED = 1
VECTOR_TOPICS = ("/setpoint", "/input", "/output")


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """(bag directory, printed output) of one quiet demo run with ``--bag``."""
    bag = tmp_path_factory.mktemp("demo") / "bag"
    out = io.StringIO()
    assert run_demo(case=CASE, samples=SAMPLES, bag=str(bag), seed=SEED, quiet=True, out=out, timeout=120.0) == 0
    return bag, out.getvalue()


@pytest.fixture(scope="module")
def offline(demo, tmp_path_factory):
    """The JSON report of ``python -m mpm_monitor analyze --model M --bag BAG`` on the demo's bag."""
    bag, _ = demo
    tmp = tmp_path_factory.mktemp("offline")
    model_file, report_file = tmp / "model.yaml", tmp / "report.json"
    save_model(paper_case(CASE).model, model_file)
    assert cli.main(["analyze", "--model", str(model_file), "--bag", str(bag), "--json", str(report_file)]) == 0
    return json.loads(report_file.read_text())


def last_diagnostics(bag):
    """The statuses of the last recorded DiagnosticArray, by name."""
    statuses = read_diagnostics(bag)
    assert statuses, "no /diagnostics in the bag"
    last_stamp = statuses[-1].log_time
    return statuses, {s.name: s for s in statuses if s.log_time == last_stamp}


def test_the_last_recorded_result_is_the_analysis_of_every_sample(demo):
    bag, printed = demo
    _, last = last_diagnostics(bag)
    summary = last[SUMMARY_NAME].values
    assert summary["completed_samples"] == str(SAMPLES) and summary["missing_samples"] == "0"
    model = paper_case(CASE).model
    for name in [SUMMARY_NAME] + [row_status_name(o) for o in model.outputs]:
        v = last[name].values
        assert (v["samples"], v["window_start"], v["window_end"]) == (str(SAMPLES), "0.0", repr(float(SAMPLES - 1)))
    # the demo's final printout, after the located rows and elements: the suggested repair
    assert printed.index("located elements:") < printed.index("suggested repair:") \
        < printed.index("prediction error RMS before -> after:")


def test_analyze_bag_locates_what_the_live_monitor_recorded(demo, offline):
    bag, _ = demo
    statuses, last = last_diagnostics(bag)
    live = live_located_elements(statuses)
    assert offline["samples"] == SAMPLES
    offline_rows = {r["output"]: r["mismatch"] for r in offline["rows"]}
    offline_located = {(e["output"], e["input"]) for e in offline["elements"] if e["mismatch"]}
    assert offline_located == live["located"]
    assert offline_rows == live["rows"]
    assert offline_located, "case 3.2 has a mismatch: an empty answer on both sides would prove nothing"
    # same samples, same options: the same numbers, and the same suggested repair
    for r in offline["rows"]:
        v = last[row_status_name(r["output"])].values
        assert float(v["rsi"]) == pytest.approx(r["rsi"], rel=1e-9)
        assert v["repair"] == row_repair_text(offline["repair"]["changes"], r["output"])
        assert float(v["error_after"]) == pytest.approx(offline["repair"]["error_after"][r["output"]], rel=1e-9)
    applied = sum(bool(c["applied"]) for c in offline["repair"]["changes"])
    assert last[SUMMARY_NAME].values["repair_changes"] == str(applied)


def test_the_bag_reads_back_with_every_message_intact_and_in_order(demo):
    bag, _ = demo
    case = paper_case(CASE)
    log = run_closed_loop(case.plant, case.model, SAMPLES, seed=SEED, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    expected = {"/setpoint": (case.model.outputs, log.r), "/input": (case.model.inputs, log.u),
                "/output": (case.model.outputs, log.y)}
    stamps = {t: [] for t in VECTOR_TOPICS + ("/clock", "/diagnostics")}
    log_times = {}
    values = {t: [] for t in VECTOR_TOPICS}
    with AnyReader([bag]) as reader:
        topics = {c.topic for c in reader.connections}
        assert set(stamps) | {"/mpm_monitor/rsi"} <= topics
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            log_times.setdefault(conn.topic, []).append(t)
            if conn.topic in VECTOR_TOPICS:
                names, _ = expected[conn.topic]
                assert tuple(msg.name) == names
                assert len(msg.velocity) == 0 and len(msg.effort) == 0
                stamps[conn.topic].append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
                values[conn.topic].append(np.asarray(msg.position, float))
            elif conn.topic == "/clock":
                stamps["/clock"].append(msg.clock.sec * 10**9 + msg.clock.nanosec)
            elif conn.topic == "/diagnostics":
                stamps["/diagnostics"].append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
                assert all(s.name.startswith("mpm_monitor: ") for s in msg.status)
    ts_ns = int(case.model.sample_time * 1e9)
    for topic in VECTOR_TOPICS + ("/clock",):
        # every sample once, in order, on the sample grid
        assert stamps[topic] == [k * ts_ns for k in range(SAMPLES)], topic
    for topic in VECTOR_TOPICS:
        _, arr = expected[topic]
        np.testing.assert_allclose(np.array(values[topic]), arr, rtol=0, atol=1e-12, err_msg=topic)
    assert len(stamps["/diagnostics"]) >= 2 and np.all(np.diff(stamps["/diagnostics"]) >= 0)
    for topic, times in log_times.items():
        assert np.all(np.diff(times) >= 0), f"{topic}: recorded out of order"


def test_the_demo_refuses_fewer_samples_than_its_monitor_can_analyse():
    """Below what the analysis needs the monitor could only publish ERROR and the demo print "no analysis
    result" with exit 0; it now says so up front."""
    from mpm_monitor.core.errors import InputError

    with pytest.raises(InputError, match=r"^--samples: case 3\.1 needs at least 215 samples for the monitor's "
                                         r"analysis, got 150$"):
        run_demo(case="3.1", samples=150, quiet=True)


def test_quiet_demo_prints_no_node_log_lines():
    # The nodes logged what they run ("[INFO] [...] [plant]: plant 3x3 ...") as they started, before --quiet set
    # their level: four lines on the standard error of a run asked to print only the final result.
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="OFF", PYTHONDONTWRITEBYTECODE="1")
    done = subprocess.run([sys.executable, "-m", "mpm_monitor", "demo", "--quiet", "--samples", "300"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "[INFO]" not in done.stderr, done.stderr
    assert "located elements: (y1, u2), (y1, u3), (y2, u1)" in done.stdout, done.stdout
