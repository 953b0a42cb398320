"""Measured disturbances outside the nodes: the monitor's window with four channels, bags with the
disturbance topic (read, write, export, ``analyze --bag``) and the command line's cases and topics.

The bags are written with ``rosbags.rosbag2.Writer`` from known samples (independent of the
package's BagWriter), except where the package's own writer is what is tested.
"""

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from mpm_monitor.apps.cli import DEMO_CASES as CLI_CASES
from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.core.errors import BagError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io import bags as bag_io
from mpm_monitor.io.bags import export_csv, read_bag, read_bag_channels, read_raw_messages, write_logged_data
from mpm_monitor.io.model_file import save_model
from mpm_monitor.monitor.monitor_core import MonitorCore, MonitorOptions
from mpm_monitor.monitor.window import SampleWindow, WindowOptions
from mpm_monitor.sim.cases import DEMO_CASES, level_case
from mpm_monitor.sim.closed_loop import run_closed_loop

NS = 1_000_000_000
OUT, INP, DV = ("y1", "y2"), ("u1",), ("f1", "f2")

TS = bag_io.default_typestore()
JS = TS.types["sensor_msgs/msg/JointState"]
HEADER = TS.types["std_msgs/msg/Header"]
TIME = TS.types["builtin_interfaces/msg/Time"]

MODEL = PlantModel(sample_time=1.0, inputs=INP, outputs=OUT, disturbances=DV, gain=np.ones((2, 3)),
                   time_constant=np.full((2, 3), 4.0), delay=np.ones((2, 3)))


# ----------------------------------------------------------------------------- window


def _window(**kw):
    return SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=50, **kw), disturbances=DV)


def _vectors(k):
    return {"setpoint": np.array([k, -k]) + 0.1, "input": np.array([k]) + 0.2, "output": np.array([k, k * k]) + 0.3,
            "disturbance": np.array([2 * k, 3 * k]) + 0.4}


def test_window_with_disturbances_needs_the_four_channels_and_keeps_dv_aligned():
    w = _window()
    assert w.channels == ("setpoint", "input", "output", "disturbance")
    for k in range(5):   # three of the four channels: nothing completes
        v = _vectors(k)
        assert sum(w.add(ch, k * NS, v[ch]) for ch in ("output", "setpoint", "input")) == 0
    assert w.n_completed == 0
    for k in range(5):   # the measured disturbances complete them, in order
        assert w.add("disturbance", k * NS, _vectors(k)["disturbance"]) == 1
    for k in range(5, 12):     # any interleaving
        v = _vectors(k)
        order = ("disturbance", "output", "input", "setpoint") if k % 2 else ("setpoint", "disturbance", "input",
                                                                              "output")
        assert sum(w.add(ch, k * NS, v[ch]) for ch in order) == 1
    d = w.data()
    assert d.disturbances == DV and d.dv.shape == (12, 2)
    for k in range(12):
        np.testing.assert_array_equal(d.dv[k], _vectors(k)["disturbance"])
        np.testing.assert_array_equal(d.y[k], _vectors(k)["output"])
    assert w.health().received == {"setpoint": 12, "input": 12, "output": 12, "disturbance": 12}
    assert w.take_problems() == []


def test_window_disturbance_problems_name_the_channel():
    w = _window(reorder_samples=2)
    w.add("disturbance", 0, [1.0])                                  # one value for two disturbances
    problems = w.take_problems()
    assert problems[0].kind == "bad_value"
    assert problems[0].message == "disturbance: 1 value(s) at t = 0 s, expected 2 (f1, f2)"
    # a sample without its dv is given up as a gap that says so
    for k in range(6):
        v = _vectors(k)
        for ch in ("setpoint", "input", "output") + (("disturbance",) if k != 1 else ()):
            w.add(ch, k * NS, v[ch])
    gaps = [p for p in w.take_problems() if p.kind == "gap"]
    assert gaps and "(no disturbance)" in gaps[0].message
    with pytest.raises(ValueError, match="channel: expected one of setpoint, input, output, disturbance"):
        w.add("dither", 0, [0.0])


def test_window_with_held_setpoints_still_needs_dv():
    w = _window(hold_setpoint=True)
    w.add("setpoint", 0, [1.0, 2.0])
    v = _vectors(0)
    assert w.add("output", 0, v["output"]) + w.add("input", 0, v["input"]) == 0
    assert w.add("disturbance", 0, v["disturbance"]) == 1


def test_window_without_disturbances_keeps_three_channels():
    w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=20))
    assert w.channels == ("setpoint", "input", "output")
    with pytest.raises(ValueError, match="channel: expected one of setpoint, input, output, got 'disturbance'"):
        w.add("disturbance", 0, [1.0])
    v = _vectors(0)
    assert sum(w.add(ch, 0, v[ch]) for ch in ("setpoint", "input", "output")) == 1
    assert w.data().dv.shape == (1, 0)


def test_monitor_core_with_disturbances_hands_dv_to_the_analysis_and_names_a_silent_disturbance():
    core = MonitorCore(MODEL, MonitorOptions(window=WindowOptions(window_samples=20), min_samples=10,
                                             analysis_period=10, stale_timeout=1.0))
    for k in range(10):
        v = _vectors(k)
        for ch in ("setpoint", "input", "output", "disturbance"):
            core.add(ch, k * NS, v[ch], now=float(k) * 0.01)
    assert core.analysis_due()
    job = core.take_job()
    np.testing.assert_array_equal(job.data.dv[:, 1], 3 * np.arange(10) + 0.4)
    for k in range(10, 15):        # the disturbance stops
        v = _vectors(k)
        for ch in ("setpoint", "input", "output"):
            core.add(ch, k * NS, v[ch], now=1.0)
    summary = core.statuses(now=5.0)[-1]
    assert summary.level == 3 and "disturbance" in summary.message


# ------------------------------------------------------------------------------- bags


def _write(path, data, topics=("/setpoint", "/input", "/output", "/disturbance"), skip_dv=()):
    """r, u, y, dv of ``data`` (LoggedData) as JointState messages stamped t[k], written with rosbags."""
    roles = (("setpoint", data.outputs, data.r), ("input", data.inputs, data.u), ("output", data.outputs, data.y),
             ("disturbance", data.disturbances, data.dv))
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = [w.add_connection(t, JS.__msgtype__, typestore=TS) for t in topics]
        for k, t in enumerate(data.t):
            ns = int(round(t * NS))
            for conn, (role, names, values) in zip(conns, roles):
                if role == "disturbance" and k in skip_dv:
                    continue
                msg = JS(header=HEADER(stamp=TIME(sec=ns // NS, nanosec=ns % NS), frame_id=""), name=list(names),
                         position=np.asarray(values[k], dtype=np.float64), velocity=np.zeros(0), effort=np.zeros(0))
                w.write(conn, ns, TS.serialize_cdr(msg, JS.__msgtype__))


@pytest.fixture(scope="module")
def level_run():
    case = level_case()
    log = run_closed_loop(case.plant, case.model, 400, seed=2, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance, measured_disturbance=case.measured_disturbance)
    return case, log.as_logged_data("level run")


def test_read_bag_puts_the_disturbance_topic_into_dv(tmp_path, level_run):
    case, data = level_run
    _write(tmp_path / "b", data)
    got = read_bag(tmp_path / "b", case.model)
    assert got.disturbances == ("inflow",) and got.n_samples == 400
    for key in ("t", "r", "u", "y", "dv"):
        np.testing.assert_array_equal(getattr(got, key), getattr(data, key))
    # the same with the four names given (three-name form and four-name form agree)
    same = read_bag(tmp_path / "b", case.model, topics=("setpoint", "input", "output", "disturbance"))
    np.testing.assert_array_equal(same.dv, data.dv)
    # a model without measured disturbances reads the three topics only
    plain = read_bag(tmp_path / "b", PlantModel(1.0, case.model.inputs, case.model.outputs,
                                                gain=case.model.gain[:, :2], time_constant=np.ones((2, 2)),
                                                delay=np.ones((2, 2))))
    assert plain.dv.shape == (400, 0) and plain.disturbances == ()


def test_read_bag_with_other_topic_names_and_refusals(tmp_path, level_run):
    case, data = level_run
    _write(tmp_path / "b", data, topics=("/r", "/u", "/y", "/plant/dv"))
    got = read_bag(tmp_path / "b", case.model, topics=("r", "u", "y", "plant/dv"))
    np.testing.assert_array_equal(got.dv, data.dv)
    with pytest.raises(BagError, match=r"no topic '/disturbance' \(sensor_msgs/msg/JointState\) in the bag"):
        read_bag(tmp_path / "b", case.model, topics=("r", "u", "y"))
    plain = PlantModel(1.0, case.model.inputs, case.model.outputs, gain=np.ones((2, 2)),
                       time_constant=np.ones((2, 2)), delay=np.ones((2, 2)))
    with pytest.raises(BagError, match="a fourth topic .*/plant/dv.* but the model has no measured disturbances"):
        read_bag(tmp_path / "b", plain, topics=("r", "u", "y", "plant/dv"))
    with pytest.raises(BagError, match="expected three topics .* or four .* got 2"):
        read_bag(tmp_path / "b", case.model, topics=("r", "u"))
    with pytest.raises(BagError, match="topics must differ"):
        read_bag(tmp_path / "b", case.model, topics=("r", "u", "y", "y"))
    # names of the disturbance topic must be the model's
    other = PlantModel(1.0, case.model.inputs, case.model.outputs, disturbances=("feed",), gain=case.model.gain,
                       time_constant=case.model.time_constant, delay=case.model.delay,
                       integrating=case.model.integrating)
    with pytest.raises(BagError, match=r"topic '/plant/dv': message 1 .* channel names \[inflow\], expected the "
                                       r"measured disturbances \[feed\]"):
        read_bag(tmp_path / "b", other, topics=("r", "u", "y", "plant/dv"))


def test_a_missing_disturbance_sample_is_a_gap(tmp_path, level_run):
    # Until the interface "Gaps" the bag was refused; the sample is now left out, t skips it.
    case, data = level_run
    _write(tmp_path / "b", data, skip_dv=(57,))
    back = read_bag(tmp_path / "b", case.model)
    assert back.n_samples == data.n_samples - 1 and 57.0 not in back.t
    assert len(back.segments) == 2
    np.testing.assert_array_equal(back.dv, np.delete(data.dv, 57, axis=0))


def test_read_bag_channels_reads_the_disturbance_topic_when_there(tmp_path, level_run):
    case, data = level_run
    _write(tmp_path / "with", data)
    got = read_bag_channels(tmp_path / "with")
    assert got.disturbances == ("inflow",) and got.sample_time == 1.0
    np.testing.assert_array_equal(got.dv, data.dv)
    _write(tmp_path / "without", data, topics=("/setpoint", "/input", "/output"))
    assert read_bag_channels(tmp_path / "without").disturbances == ()
    with pytest.raises(BagError, match="no topic '/disturbance'"):
        read_bag_channels(tmp_path / "without", topics=("setpoint", "input", "output", "disturbance"))


def test_write_logged_data_writes_the_disturbance_topic_and_reads_back(tmp_path, level_run):
    case, data = level_run
    n = write_logged_data(tmp_path / "b", data)
    assert n == 4 * 400
    got = read_bag(tmp_path / "b", case.model)
    np.testing.assert_array_equal(got.dv, data.dv)
    raw = read_raw_messages(tmp_path / "b", ("setpoint",), optional=("disturbance", "nothing"))
    assert {m.topic for m in raw} == {"/setpoint", "/disturbance"} and len(raw) == 800


def test_analyze_and_export_of_a_bag_with_the_disturbance_topic(tmp_path, level_run, capsys):
    case, data = level_run
    _write(tmp_path / "b", data, topics=("/r", "/u", "/y", "/dv"))
    save_model(case.model, tmp_path / "m.yaml")
    code = cli_main(["analyze", "--model", str(tmp_path / "m.yaml"), "--bag", str(tmp_path / "b"),
                     "--topics", "r", "u", "y", "dv", "--json", str(tmp_path / "rep.json"), "--no-repair"])
    assert code == 0
    import json

    rep = json.loads((tmp_path / "rep.json").read_text())
    roles = {(e["output"], e["input"]): e["role"] for e in rep["elements"]}
    assert roles[("temperature", "inflow")] == "disturbance" and roles[("level", "outflow")] == "input"
    capsys.readouterr()
    assert cli_main(["analyze", "--model", str(tmp_path / "m.yaml"), "--bag", str(tmp_path / "b"),
                     "--topics", "r", "u"]) == 2
    assert "--topics: expected three topic names (SETPOINT INPUT OUTPUT) or four (and DISTURBANCE), got 2" in \
        capsys.readouterr().err
    assert export_csv(tmp_path / "b", tmp_path / "x.csv", model_path=tmp_path / "m.yaml",
                      topics=("r", "u", "y", "dv")) == 400
    assert cli_main(["export", "--bag", str(tmp_path / "b"), "--csv", str(tmp_path / "y.csv"),
                     "--topics", "r", "u", "y", "dv"]) == 0
    assert "wrote 400 samples" in capsys.readouterr().out


def test_the_command_line_knows_every_case():
    assert CLI_CASES == DEMO_CASES


def test_level_params_file_matches_the_case():
    """config/case_level.yaml gives every node the numbers of mpm_monitor.sim.cases (no drift), the
    plant's measured-disturbance sizes included."""
    from mpm_monitor.apps.demo import case_parameters
    from mpm_monitor.apps.launchers.common import case_params_file, load_params_file

    loaded = load_params_file(case_params_file("level"))
    expected = case_parameters("level", seed=1)
    assert "dv_step_amplitude" in expected["plant"]
    for node, params in expected.items():
        for key, value in params.items():
            assert loaded[node][key] == pytest.approx(value), (node, key)
