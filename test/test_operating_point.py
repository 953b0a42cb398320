"""Operating points: ``disturbance_nominal`` of the model file, a candidate channel logged in its units,
and the warning on a prediction error offset by an operating point the model file does not declare."""

import dataclasses

import numpy as np
import pytest

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.data_warnings import OFFSET_RATIO, offset_warnings
from mpm_monitor.core.errors import DataFileError, ModelFileError
from mpm_monitor.core.logged_data import in_deviations
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.io.model_file import load_model, save_model
from mpm_monitor.sim.cases import level_case
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.undeclared import EFFECT_CHANNEL, undeclared_effect_run

OFFSET = 350.0


def _shifted(data, dv_shift=0.0, extra_shift=None):
    extra = dict(data.extra)
    if extra_shift is not None:
        extra[extra_shift[0]] = np.asarray(extra[extra_shift[0]]) + extra_shift[1]
    return dataclasses.replace(data, dv=np.asarray(data.dv) + dv_shift, extra=extra)


def test_the_model_file_reads_writes_and_checks_disturbance_nominal(tmp_path):
    text = ("sample_time: 1\ninputs: [u1]\noutputs: [y1]\ndisturbances: [feed]\n"
            "gain: [[2, 0.5]]\ntime_constant: [[10, 20]]\ndelay: [[1, 2]]\n")
    (tmp_path / "m.yaml").write_text(text + "disturbance_nominal: [20]\n")
    m = load_model(tmp_path / "m.yaml")
    np.testing.assert_array_equal(m.disturbance_nominal, [20.0])
    save_model(m, tmp_path / "back.yaml")
    assert "disturbance_nominal: [20" in (tmp_path / "back.yaml").read_text()
    assert load_model(tmp_path / "back.yaml") == m
    (tmp_path / "none.yaml").write_text(text)
    assert not np.any(load_model(tmp_path / "none.yaml").disturbance_nominal)
    (tmp_path / "bad.yaml").write_text(text + "disturbance_nominal: [20, 1]\n")
    with pytest.raises(ModelFileError, match=r"bad\.yaml: key 'disturbance_nominal': expected a list of 1 numbers \(one per channel of "
                                         r"feed\), got 2 numbers$"):
        load_model(tmp_path / "bad.yaml")
    (tmp_path / "nan.yaml").write_text(text + "disturbance_nominal: [.nan]\n")
    with pytest.raises(ModelFileError, match=r"key 'disturbance_nominal': entry 1 \(feed\): expected a finite number, got nan$"):
        load_model(tmp_path / "nan.yaml")


@pytest.fixture(scope="module")
def level_loop():
    case = level_case()
    log = run_closed_loop(case.plant, case.model, 2000, seed=4, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance, measured_disturbance=case.measured_disturbance)
    return case.model, log.as_logged_data("level")


def test_a_declared_disturbance_at_its_operating_point_reads_as_its_deviation(level_loop):
    model, data = level_loop
    assert model.n_disturbances == 1
    base = analyze(model, data, AnalysisOptions(repair=False))
    at = analyze(model.replace(disturbance_nominal=[20.0]), _shifted(data, dv_shift=20.0), AnalysisOptions(repair=False))
    np.testing.assert_allclose(in_deviations(model.replace(disturbance_nominal=[20.0]), _shifted(data, 20.0)).dv, data.dv,
                               atol=1e-12)
    assert at.located_elements == base.located_elements
    for key in ("error_before", "error_after"):
        assert at.repair[key] == pytest.approx(base.repair[key], rel=1e-9)
    assert not any("offset from the logged output" in w for w in at.warnings + base.warnings)
    # Undeclared: the model's output is offset, and the warning says where to declare it.
    off = analyze(model, _shifted(data, dv_shift=20.0), AnalysisOptions(repair=False))
    assert any("offset from the logged output" in w and "disturbance_nominal" in w for w in off.warnings)


def test_offset_warnings_name_only_the_offset_rows():
    model = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1", "y2", "y3"), gain=np.ones((3, 1)),
                       time_constant=np.ones((3, 1)), delay=np.zeros((3, 1)))
    rng = np.random.default_rng(0)
    d = rng.standard_normal((500, 3)) * 0.1
    d[:, 1] += 2.0 * OFFSET_RATIO * 0.1            # y2 far off
    d[:, 2] += 0.5 * OFFSET_RATIO * 0.1            # y3 a little
    y = rng.standard_normal((500, 3))
    (w,) = offset_warnings(model, d, y)
    assert "y2 by 2" in w and "y1" not in w and "y3" not in w
    assert offset_warnings(model, d, y, skip=("y2",)) == []
    # A log without noise: an error of rounding size is no offset, an exact constant is.
    assert offset_warnings(model, np.full((500, 3), 1e-15), y) == []
    assert "y1 by 0.3 (no spread)" in offset_warnings(model, np.full((500, 3), 0.3), y)[0]


def test_an_integrating_output_is_named_for_a_ramp_not_for_its_level():
    """A level has no fixed level: a clean log cut from a running loop (its level far from the model's start) was
    named as offset by an undeclared operating point.  What an undeclared operating point of a column feeding the
    level does is a ramp (the model integrates it), which was not named; the tests then located an element of
    that row that is right.  The level is named for a ramp now, and never for its offset."""
    model = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1", "lvl"), gain=np.array([[1.0], [0.05]]),
                       time_constant=np.array([[10.0], [5.0]]), delay=np.zeros((2, 1)),
                       integrating=np.array([[False], [True]]))
    rng = np.random.default_rng(1)
    d = rng.standard_normal((2000, 2)) * 0.1
    y = rng.standard_normal((2000, 2))
    level = d.copy()
    level[:, 1] += 50.0                            # a level far from the model's: not named
    assert offset_warnings(model, level, y) == []
    walk = d.copy()
    walk[:, 1] += np.cumsum(rng.standard_normal(2000)) * 0.01      # an unmeasured disturbance that wanders
    assert offset_warnings(model, walk, y) == []
    ramp = d.copy()
    t = 100.0 + np.arange(2000) * 0.5
    ramp[:, 1] += 0.002 * (t - t[0])               # 2 over the window, against 0.1 of noise
    (w,) = offset_warnings(model, ramp, y, t=t)
    assert w.startswith("the prediction error of an integrating output ramps: lvl by 0.002") and \
        "per second (2 over the window, 19.9 times the spread about it)" in w and "input_nominal" in w and "y1" not in w


@pytest.fixture(scope="module")
def effect_run():
    return undeclared_effect_run(3000, seed=3)


def test_a_candidate_logged_in_its_units_is_added_at_its_operating_point(effect_run, tmp_path):
    """A feed temperature logged at 350: the element is the same, the repaired model says its operating
    point, and predicts the logged outputs from the logged channel."""
    model, data = effect_run.model, effect_run.data
    base = analyze(model, data, AnalysisOptions(), candidates=[EFFECT_CHANNEL])
    shifted = _shifted(data, extra_shift=(EFFECT_CHANNEL, OFFSET))
    rep = analyze(model, shifted, AnalysisOptions(), candidates=[EFFECT_CHANNEL])
    assert rep.candidates.added == base.candidates.added == [EFFECT_CHANNEL]
    m = rep.repaired_model
    j = m.columns.index(EFFECT_CHANNEL)
    assert m.element(0, j) == pytest.approx(base.repaired_model.element(0, j), rel=1e-3)
    # The operating point that centres the row's prediction error: the simulation's channel is in
    # deviations (its plant acts on it from 0), so 0 without the offset and 350 with it.
    # In deviations (the channel swings around 0) the operating point is 0; in its units it is the
    # one that centres the row's prediction error, found to a few thousandths of the channel's spread.
    assert base.repaired_model.disturbance_nominal[0] == 0.0
    assert abs(m.disturbance_nominal[0] - OFFSET) < 0.02 * np.std(data.extra[EFFECT_CHANNEL])
    assert rep.repair["error_after"] == pytest.approx(base.repair["error_after"], rel=0.02)
    floor = effect_run.noise_floor[effect_run.effect.output]
    assert rep.repair["error_after"][effect_run.effect.output] <= 1.1 * floor
    # Read back on the same log (the channel now a declared disturbance): its errors are the repair's.
    save_model(m, tmp_path / "repaired.yaml")
    back_model = load_model(tmp_path / "repaired.yaml")
    back_data = dataclasses.replace(shifted, dv=np.asarray(shifted.extra[EFFECT_CHANNEL])[:, None],
                                    disturbances=(EFFECT_CHANNEL,),
                                    extra={k: v for k, v in shifted.extra.items() if k != EFFECT_CHANNEL})
    back = analyze(back_model, back_data, AnalysisOptions(repair=False))
    assert back.repair["error_before"] == pytest.approx(rep.repair["error_after"], rel=1e-6)
    assert not any("offset from the logged output" in w for w in back.warnings)



@pytest.mark.parametrize("key, field, shift", [("output_nominal", "y", 1e17), ("input_nominal", "u", -3e16),
                                               ("disturbance_nominal", "dv", 1e18)])
def test_an_operating_point_that_rounds_the_moves_away_is_refused(level_loop, key, field, shift):
    """``output_nominal: [1e17]`` with outputs of order 1: every deviation rounded to -1e17 exactly, and a moving
    output was reported as a stuck sensor.  The operating point is refused in one line naming it and the channel."""
    model, data = level_loop
    nominal = np.zeros(np.shape(getattr(data, field))[1])
    nominal[0] = shift
    with pytest.raises(DataFileError) as err:
        in_deviations(model.replace(**{key: nominal}), data)
    msg = str(err.value)
    assert len(msg.splitlines()) == 1 and msg.startswith("level: ")
    names = {"y": data.outputs, "u": data.inputs, "dv": data.disturbances}[field]
    assert f"the model's {key} of {names[0]} ({shift:g})" in msg and "its moves are lost" in msg, msg


def test_a_large_operating_point_near_the_logged_values_is_taken(level_loop):
    """Values logged at 1e9 about an operating point of 1e9 keep their moves (their own spacing is the rounding),
    and so does an operating point of 1e6 on values of order 1: neither is refused."""
    model, data = level_loop
    y0 = np.full(model.n_outputs, 1e9)
    lifted = dataclasses.replace(data, y=np.asarray(data.y) + y0, r=np.asarray(data.r) + y0)
    dev = in_deviations(model.replace(output_nominal=y0), lifted)
    np.testing.assert_allclose(dev.y, data.y, atol=1e-6)
    far = in_deviations(model.replace(output_nominal=np.full(model.n_outputs, 1e6)), data)
    np.testing.assert_allclose(far.y, np.asarray(data.y) - 1e6)
