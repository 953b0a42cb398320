"""Model files with richer elements, step responses and measured disturbances.

Every new key is read, written back identically, and every bad value of it is refused with one line
naming the key and the element.  An unknown key is refused, never ignored: a misspelt
``time_constant_2`` read as absent would silently turn the model into another one.
"""

import numpy as np
import pytest
import yaml
from test_model import _with_line, _write

from mpm_monitor.core.errors import InputError, ModelFileError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io.model_file import KNOWN_KEYS, dump_model, load_model, model_from_dict, save_model

RICH = """\
sample_time: 1.0
inputs:  [u1, u2, u3]
outputs: [y1, y2, y3]
disturbances: [dv1]
gain:           [[4.05, 1.77, 0.05, 0.8], [5.39, 5.72, 6.90, 0], [4.38, 4.42, 7.20, -1.2]]
time_constant:  [[50, 60, 0, 20], [50, 60, 40, 0], [33, 44, 19, 30]]
delay:          [[6, 7, 6, 2], [4, 3, 3, 0], [5, 5, 0, 4]]
lead:           [[0, 0, 0, 0], [12, 0, 0, 0], [0, -8, 0, 0]]
time_constant2: [[0, 0, 0, 0], [0, 25, 0, 0], [0, 15, 0, 0]]
integrating:    [[false, false, true, false], [false, false, false, false], [false, false, false, false]]
"""

STEP = """\
sample_time: 2.0
inputs: [u1, u2]
outputs: [level, temp]
step_response:
  length: 6
  coefficients:
  - [[0, 0.1, 0.3, 0.6, 1.0, 1.5], [0, 0, -0.2, -0.4, -0.5, -0.55]]
  - [[0, 0, 0, 0.5, 0.9, 1.0], [0.3, 0.6, 0.8, 0.9, 1.0, 1.0]]
ramp: [true, false]
"""


def test_rich_model_loads_every_key(tmp_path):
    m = load_model(_write(tmp_path, RICH))
    assert m.inputs == ("u1", "u2", "u3") and m.disturbances == ("dv1",) and m.n_columns == 4
    assert m.columns == ("u1", "u2", "u3", "dv1") and m.role(3) == "disturbance" and m.role(0) == "input"
    assert m.lead[1, 0] == 12 and m.lead[2, 1] == -8 and m.time_constant2[1, 1] == 25
    assert m.integrating[0, 2] and m.integrating_outputs == (True, False, False)
    assert m.element(1, 0) == {"gain": 5.39, "time_constant": 50.0, "delay": 4.0, "lead": 12.0}
    assert m.element(0, 2)["integrating"] is True
    assert m.discrete_element(0, 2).integrating and not m.discrete_element(1, 1).integrating


def test_rich_model_round_trips_exactly(tmp_path):
    m = load_model(_write(tmp_path, RICH))
    path = tmp_path / "back.yaml"
    save_model(m, path)
    back = load_model(path)
    assert back == m
    for key in ("gain", "time_constant", "delay", "lead", "time_constant2", "integrating"):
        np.testing.assert_array_equal(getattr(back, key), getattr(m, key))


def test_step_response_model_loads_and_round_trips(tmp_path):
    m = load_model(_write(tmp_path, STEP))
    assert m.is_step_response and m.step_length == 6 and m.ramp == (True, False)
    assert m.integrating_outputs == (True, False)
    np.testing.assert_array_equal(m.delay, [[2.0, 4.0], [6.0, 0.0]])           # samples before it moves x 2 s
    np.testing.assert_allclose(m.gain, [[0.25, -0.025], [1.0, 1.0]])            # ramp row: last slope per second
    assert m.element(0, 1)["step_response"] == [0, 0, -0.2, -0.4, -0.5, -0.55]
    text = dump_model(m)
    assert "time_constant" not in text and "gain" not in text
    back = load_model(_write(tmp_path, text, "back.yaml"))
    assert back == m
    np.testing.assert_array_equal(back.step_response, m.step_response)


def test_step_response_element_follows_its_coefficients(tmp_path):
    m = load_model(_write(tmp_path, STEP))
    y = m.discrete_element(0, 0).step_response(12)
    np.testing.assert_allclose(y[1:7], [0, 0.1, 0.3, 0.6, 1.0, 1.5], atol=1e-14)
    np.testing.assert_allclose(np.diff(y[6:]), 0.5, atol=1e-14)                 # ramp: last slope kept
    y = m.discrete_element(1, 1).step_response(12)
    np.testing.assert_allclose(y[7:], 1.0, atol=1e-14)                          # held at its last value


def test_files_without_new_keys_read_as_before(tmp_path):
    text = ("sample_time: 1.0\ninputs: [u1, u2]\noutputs: [y1]\ngain: [[1.5, 0]]\ntime_constant: [[20, 0]]\n"
            "delay: [[3, 0]]\n")
    m = load_model(_write(tmp_path, text))
    assert m.disturbances == () and not m.integrating.any() and not m.lead.any() and not m.time_constant2.any()
    assert not m.is_step_response and m.n_columns == m.n_inputs == 2
    assert set(m.to_dict()) == {"sample_time", "inputs", "outputs", "gain", "time_constant", "delay"}
    assert dump_model(m) == text.replace("1.0\n", "1\n", 1)


def test_with_element_changes_the_new_parameters_of_one_element(tmp_path):
    m = load_model(_write(tmp_path, RICH))
    m2 = m.with_element(2, 1, lead=-4.0, time_constant2=10.0)
    assert m2.lead[2, 1] == -4.0 and m2.time_constant2[2, 1] == 10.0
    assert np.array_equal(np.delete(m2.lead.ravel(), 9), np.delete(m.lead.ravel(), 9))
    s = load_model(_write(tmp_path, STEP, "step.yaml"))
    s2 = s.with_element(1, 0, step_response=[0, 0, 0, 0.6, 1.1, 1.2])
    assert s2.step_response[1, 0, 3] == 0.6 and s2.step_length == 6
    with pytest.raises(ValueError):
        s.with_element(0, 0, gain=2.0)


BAD = {
    # case: (text, regex)
    "misspelt time_constant_2": (RICH + "time_constant_2: [[0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0]]\n",
                                 r"unknown key 'time_constant_2' \(did you mean 'time_constant2'\?\): .*"
                                 r"time_constant2"),
    "unknown key": (RICH + "gains: 1\n", r"unknown key 'gains' \(did you mean 'gain'\?\)"),
    "unknown key far from any": (RICH + "colour: red\n", r"unknown key 'colour': a model file holds only the keys "
                                                         r"sample_time, inputs, "),
    "lead not finite": (_with_line(RICH, "lead", "lead: [[0, 0, 0, 0], [.nan, 0, 0, 0], [0, 0, 0, 0]]"),
                        r"key 'lead': row 2 \(y2\), column 1 \(u1\): expected a finite number, got nan"),
    "lead without a lag": (_with_line(RICH, "lead", "lead: [[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]]").replace(
        "time_constant:  [[50, 60, 0, 20]", "time_constant:  [[0, 60, 0, 20]").replace(
        "lead: [[0, 0, 0, 0]", "lead: [[3, 0, 0, 0]"),
        r"key 'lead': row 1 \(y1\), column 1 \(u1\): a lead of 3 s needs a lag"),
    "lead a string": (_with_line(RICH, "lead", "lead: [[0, 0, 0, 0], [fast, 0, 0, 0], [0, 0, 0, 0]]"),
                      r"key 'lead': row 2 \(y2\), column 1 \(u1\): expected a number, got 'fast'"),
    "lead wrong shape": (_with_line(RICH, "lead", "lead: [[0, 0, 0], [0, 0, 0], [0, 0, 0]]"),
                         r"key 'lead': expected 3 rows x 4 columns"),
    "negative time_constant2": (
        _with_line(RICH, "time_constant2", "time_constant2: [[0, 0, 0, 0], [0, -25, 0, 0], [0, 15, 0, 0]]"),
        r"key 'time_constant2': row 2 \(y2\), column 2 \(u2\): expected >= 0 seconds, got -25"),
    "time_constant2 without time_constant": (
        _with_line(RICH, "time_constant2", "time_constant2: [[0, 0, 5, 0], [0, 25, 0, 0], [0, 15, 0, 0]]"),
        r"key 'time_constant2': row 1 \(y1\), column 3 \(u3\): a second lag of 5 s without a first one"),
    "time_constant2 infinite": (
        _with_line(RICH, "time_constant2", "time_constant2: [[0, 0, 0, 0], [0, .inf, 0, 0], [0, 15, 0, 0]]"),
        r"key 'time_constant2': row 2 \(y2\), column 2 \(u2\): expected a finite number, got inf"),
    "integrating not boolean": (
        _with_line(RICH, "integrating", "integrating: [[0, 0, 1, 0], [0, 0, 0, 0], [0, 0, 0, 0]]"),
        r"key 'integrating': row 1 \(y1\), column 1 \(u1\): expected true or false, got 0"),
    "integrating a string": (
        _with_line(RICH, "integrating", "integrating: [[false, false, 'yes', false], [false, false, false, false], "
                                        "[false, false, false, false]]"),
        r"key 'integrating': row 1 \(y1\), column 3 \(u3\): expected true or false, got 'yes'"),
    "integrating wrong shape": (
        _with_line(RICH, "integrating", "integrating: [[false, false, true, false]]"),
        r"key 'integrating': expected 3 rows x 4 columns"),
    "disturbance columns missing": (_with_line(RICH, "disturbances", "disturbances: [dv1, dv2]"),
                                    r"key 'gain': expected 3 rows x 5 columns \(outputs x \(inputs, then disturbances\)\)"),
    "disturbance named like an input": (_with_line(RICH, "disturbances", "disturbances: [u2]"),
                                        r"keys 'disturbances' and 'inputs': a name cannot be both, found u2"),
    "disturbances not a list": (_with_line(RICH, "disturbances", "disturbances: dv1"),
                                r"key 'disturbances': expected a list of names, got str"),
    "step_response wrong length": (STEP.replace("length: 6", "length: 5"),
                                   r"key 'step_response': row 1 \(level\), column 1 \(u1\): expected 5 coefficients \(length\), got 6"),
    "step_response non-finite": (STEP.replace("0.9, 1.0], [0.3", ".nan, 1.0], [0.3"),
                                 r"key 'step_response': row 2 \(temp\), column 1 \(u1\), coefficient 5: expected a number|"
                                 r"key 'step_response': row 2 \(temp\), column 1 \(u1\), coefficient 5: expected a finite"),
    "step_response wrong rows": (STEP.replace("  - [[0, 0, 0, 0.5, 0.9, 1.0], [0.3, 0.6, 0.8, 0.9, 1.0, 1.0]]\n", ""),
                                 r"key 'step_response': expected coefficients of 2 rows x 2 columns x N >= 1 values, "
                                 r"got shape 1x2x6"),
    "step_response not a mapping": (_with_line(STEP, "step_response", "step_response: [1, 2]").split("  length")[0]
                                    + "ramp: [true, false]\n",
                                    r"key 'step_response': expected a mapping with 'length' and 'coefficients'"),
    "step_response zero length": (STEP.replace("length: 6", "length: 0"),
                                  r"key 'step_response': 'length': expected a whole number of samples >= 1, got 0"),
    "step_response with gain": (STEP + "gain: [[1, 1], [1, 1]]\n",
                                r"key 'gain': a step-response model \(key 'step_response'\) has no gain"),
    "ramp not boolean": (_with_line(STEP, "ramp", "ramp: [1, 0]"), r"key 'ramp': entry 1: expected true or false, got 1"),
    "ramp wrong length": (_with_line(STEP, "ramp", "ramp: [true]"), r"key 'ramp': expected one true/false per output"),
    "ramp on a parametric model": (RICH + "ramp: [true, false, false]\n",
                                   r"key 'ramp': only a step-response model"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_new_key_refused_with_one_line_naming_key_and_element(tmp_path, case):
    text, pattern = BAD[case]
    path = _write(tmp_path, text)
    with pytest.raises(ModelFileError, match=pattern) as info:
        load_model(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(str(path) + ": "), msg
    assert isinstance(info.value, InputError)


def test_every_known_key_is_written_by_some_model(tmp_path):
    written = set(yaml.safe_load(dump_model(load_model(_write(tmp_path, RICH))))) | set(
        yaml.safe_load(dump_model(load_model(_write(tmp_path, STEP, "s.yaml")))))
    written |= {"input_nominal", "output_nominal", "disturbance_nominal", "name"}
    assert written == set(KNOWN_KEYS)


def test_model_from_dict_checks_keys_too():
    doc = yaml.safe_load(RICH)
    doc["Delay"] = doc.pop("delay")
    with pytest.raises(ModelFileError, match=r"unknown key 'Delay' \(did you mean 'delay'\?\)"):
        model_from_dict(doc, "doc")


def test_constructor_refuses_bad_new_values_like_the_loader():
    base = dict(sample_time=1.0, inputs=["u"], outputs=["y"], gain=[[1.0]], time_constant=[[10.0]], delay=[[0.0]])
    with pytest.raises(ModelFileError, match=r"key 'time_constant2': row 1 \(y\), column 1 \(u\): expected >= 0"):
        PlantModel(time_constant2=[[-1.0]], **base)
    with pytest.raises(ModelFileError, match=r"key 'lead': row 1 \(y\), column 1 \(u\): expected a finite"):
        PlantModel(lead=[[np.inf]], **base)
