"""Model file (docs/interfaces.md, "Model file"): load/save round trip and refusal of every bad file.

Every bad file must raise :class:`ModelFileError` (a ``ValueError``) with a one-line message that
names the offending key (or says why the file as a whole is unusable).
"""

import numpy as np
import pytest

from mpm_monitor.core.errors import InputError, ModelFileError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io.model_file import dump_model, load_model, model_from_dict, save_model
from mpm_monitor.sim.cases import shell_plant

GOOD = """\
sample_time: 1.0
inputs:  [u1, u2, u3]
outputs: [y1, y2, y3]
gain:          [[4.05, 1.77, 5.88], [5.39, 5.72, 6.90], [4.38, 4.42, 7.20]]
time_constant: [[50, 60, 50], [50, 60, 40], [33, 44, 19]]
delay:         [[6, 7, 6], [4, 3, 3], [5, 5, 0]]
"""


def _write(tmp_path, text, name="model.yaml"):
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def _with_line(text, key, new_line):
    """``text`` with the line of ``key`` replaced (or removed when ``new_line`` is None)."""
    out = []
    for line in text.splitlines():
        if line.split(":")[0].strip() == key:
            if new_line is not None:
                out.append(new_line)
        else:
            out.append(line)
    return "\n".join(out) + "\n"


def _replace_line(key, new_line):
    """GOOD with the line of ``key`` replaced (or removed when ``new_line`` is None)."""
    return _with_line(GOOD, key, new_line)


# --------------------------------------------------------------------------- good files


def test_contract_example_loads_as_the_shell_plant(tmp_path):
    model = load_model(_write(tmp_path, GOOD))
    ref = shell_plant()
    assert model.inputs == ("u1", "u2", "u3") and model.outputs == ("y1", "y2", "y3")
    assert model.sample_time == 1.0
    np.testing.assert_array_equal(model.gain, ref.gain)
    np.testing.assert_array_equal(model.time_constant, ref.time_constant)
    np.testing.assert_array_equal(model.delay, ref.delay)
    np.testing.assert_array_equal(model.delay_samples, [[6, 7, 6], [4, 3, 3], [5, 5, 0]])
    # Optional keys absent -> zero operating point.
    np.testing.assert_array_equal(model.input_nominal, np.zeros(3))
    np.testing.assert_array_equal(model.output_nominal, np.zeros(3))


def test_save_load_round_trip_shell(tmp_path):
    model = shell_plant()
    path = tmp_path / "shell.yaml"
    save_model(model, path)
    back = load_model(path)
    assert back == model
    # Exact float equality, not only equality of the dict form.
    for key in ("gain", "time_constant", "delay", "input_nominal", "output_nominal"):
        np.testing.assert_array_equal(getattr(back, key), getattr(model, key))
    assert back.name == model.name


def test_save_load_round_trip_awkward_values(tmp_path):
    # Full-precision floats, tiny and huge magnitudes (written in exponent form), a fractional
    # sample time, nominal values, and names YAML would otherwise read as booleans / null.
    rng = np.random.default_rng(7)
    ts = 1e-5
    gain = rng.standard_normal((2, 3)) * 10.0 ** rng.integers(-25, 25, size=(2, 3))
    gain[0, 1] = 0.0
    tau = rng.random((2, 3)) * 10.0 ** rng.integers(-8, 20, size=(2, 3))
    tau[1, 2] = 0.0
    delay = rng.integers(0, 9, size=(2, 3)) * ts
    model = PlantModel(sample_time=ts, inputs=("yes", "no", "u 3"), outputs=("null", "on"), gain=gain,
                       time_constant=tau, delay=delay, input_nominal=[1e16, -2e-30, 0.1],
                       output_nominal=[3.0, -1.0 / 3.0], name="a: b # c")
    path = tmp_path / "awkward.yaml"
    save_model(model, path)
    back = load_model(path)
    assert back == model
    for key in ("gain", "time_constant", "delay", "input_nominal", "output_nominal"):
        np.testing.assert_array_equal(getattr(back, key), getattr(model, key))
    assert back.sample_time == ts
    assert back.inputs == model.inputs and back.outputs == model.outputs and back.name == model.name


def test_dump_is_one_matrix_row_per_line_and_parses_back():
    text = dump_model(shell_plant())
    assert sum(line.startswith("gain:") for line in text.splitlines()) == 1
    assert model_from_dict(__import__("yaml").safe_load(text)) == shell_plant()


def test_model_is_immutable():
    model = shell_plant()
    with pytest.raises(ValueError):
        model.gain[0, 0] = 1.0


def test_with_element_changes_one_element_only():
    model = shell_plant()
    new = model.with_element(0, 2, gain=3.5)
    assert new.gain[0, 2] == 3.5
    changed = new.gain != model.gain
    assert changed.sum() == 1 and changed[0, 2]
    assert new != model


def _model_variants():
    """Pairs of models that differ in one thing each, or in nothing (a copy, an integer for a float)."""
    base = shell_plant()
    step = PlantModel.from_step_response(1.0, base.inputs, base.outputs,
                                         np.cumsum(np.full((3, 3, 5), 0.25), axis=2), name="dmc")
    variants = [base, base.replace(), base.replace(gain=np.array(base.gain)), base.replace(sample_time=0.5),
                base.replace(name="other"), base.replace(outputs=("a", "b", "c")), base.with_element(1, 1, lead=3.0),
                base.with_element(0, 0, time_constant2=4.0), base.with_element(2, 0, integrating=True, time_constant=0.0),
                base.with_element(2, 2, delay=1), base.replace(input_nominal=[1.0, 0, 0]),
                base.replace(output_nominal=[0, 0, -0.0]), base.with_element(0, 1, gain=-0.0 + base.gain[0, 1]),
                step, step.replace(), step.replace(ramp=(True, False, False)), step.replace(name=""),
                step.replace(step_response=np.array(step.step_response)[:, :, :4]),
                step.replace(step_response=np.array(step.step_response) * (1 + 1e-15))]
    return variants


def test_models_are_equal_when_they_write_the_same_file():
    """``==`` compares the arrays; the file's dicts (:meth:`PlantModel.to_dict`) are the reference."""
    variants = _model_variants()
    pairs = 0
    for a in variants:
        for b in variants:
            assert (a == b) == (a.to_dict() == b.to_dict()), (a.to_dict(), b.to_dict())
            assert (a != b) == (a.to_dict() != b.to_dict())
            pairs += a == b
    assert len(variants) < pairs < len(variants) ** 2 // 2     # equal pairs beyond the diagonal, and unequal ones
    assert shell_plant().__eq__("a model") is NotImplemented


# --------------------------------------------------------------------------- bad files

BAD_FILES = {
    # case id: (file text or bytes, regex the one-line message must match)
    "missing key sample_time": (_replace_line("sample_time", None), r"missing key 'sample_time'"),
    "missing key inputs": (_replace_line("inputs", None), r"missing key 'inputs'"),
    "missing key outputs": (_replace_line("outputs", None), r"missing key 'outputs'"),
    "missing key gain": (_replace_line("gain", None), r"missing key 'gain'"),
    "missing key time_constant": (_replace_line("time_constant", None), r"missing key 'time_constant'"),
    "missing key delay": (_replace_line("delay", None), r"missing key 'delay'"),
    "wrong shape (too few rows)": (
        _replace_line("gain", "gain: [[4.05, 1.77, 5.88], [5.39, 5.72, 6.90]]"),
        r"key 'gain': expected 3 rows x 3 columns .*got shape 2x3"),
    "wrong shape (too few columns)": (
        _replace_line("time_constant", "time_constant: [[50, 60], [50, 60], [33, 44]]"),
        r"key 'time_constant': expected 3 rows x 3 columns .*got shape 3x2"),
    "wrong shape (scalar)": (_replace_line("delay", "delay: 3"), r"key 'delay': expected a list of rows"),
    "wrong shape (flat list)": (_replace_line("delay", "delay: [6, 7, 6]"), r"key 'delay': row 1: expected a list"),
    "ragged rows": (
        _replace_line("gain", "gain: [[4.05, 1.77, 5.88], [5.39, 5.72], [4.38, 4.42, 7.20]]"),
        r"key 'gain': row 2 has 2 entries, row 1 has 3"),
    "negative time constant": (
        _replace_line("time_constant", "time_constant: [[50, 60, 50], [50, -60, 40], [33, 44, 19]]"),
        r"key 'time_constant': row 2 \(y2\), column 2 \(u2\): expected >= 0 seconds, got -60"),
    "negative delay": (
        _replace_line("delay", "delay: [[6, 7, 6], [4, 3, 3], [5, -5, 0]]"),
        r"key 'delay': row 3 \(y3\), column 2 \(u2\): expected >= 0"),
    "delay not a multiple of sample_time": (
        _replace_line("delay", "delay: [[6, 7, 6], [4, 3.5, 3], [5, 5, 0]]"),
        r"key 'delay': row 2 \(y2\), column 2 \(u2\): expected a multiple of sample_time 1 s, got 3.5 s"),
    "delay not a multiple of a fractional sample_time": (
        _replace_line("sample_time", "sample_time: 0.4").replace(
            "delay:         [[6, 7, 6], [4, 3, 3], [5, 5, 0]]", "delay: [[0.4, 0.8, 6.0], [1.2, 0, 6.2], [0, 0, 0]]"),
        r"key 'delay': row 2 \(y2\), column 3 \(u3\): expected a multiple of sample_time 0.4 s, got 6.2 s"),
    "nan in gain": (
        _replace_line("gain", "gain: [[4.05, 1.77, 5.88], [5.39, .nan, 6.90], [4.38, 4.42, 7.20]]"),
        r"key 'gain': row 2 \(y2\), column 2 \(u2\): expected a finite number, got nan"),
    "inf in time_constant": (
        _replace_line("time_constant", "time_constant: [[50, 60, 50], [50, 60, 40], [33, 44, .inf]]"),
        r"key 'time_constant': row 3 \(y3\), column 3 \(u3\): expected a finite number, got inf"),
    "-inf in delay": (
        _replace_line("delay", "delay: [[-.inf, 7, 6], [4, 3, 3], [5, 5, 0]]"),
        r"key 'delay': row 1 \(y1\), column 1 \(u1\): expected a finite number, got -inf"),
    "nan sample_time": (_replace_line("sample_time", "sample_time: .nan"), r"key 'sample_time': expected a positive finite"),
    "inf sample_time": (_replace_line("sample_time", "sample_time: .inf"), r"key 'sample_time': expected a positive finite"),
    "zero sample_time": (_replace_line("sample_time", "sample_time: 0"), r"key 'sample_time': expected a positive"),
    "negative sample_time": (_replace_line("sample_time", "sample_time: -1"), r"key 'sample_time': expected a positive"),
    "nan in input_nominal": (GOOD + "input_nominal: [0, .nan, 0]\n", r"key 'input_nominal': entry 2 \(u2\): expected a finite number, got nan$"),
    "wrong length of output_nominal": (GOOD + "output_nominal: [0, 0]\n", r"key 'output_nominal': expected a list of 3 numbers \(one per channel of y1, y2, y3\), got 2 numbers$"),
    "integer too large in input_nominal": (GOOD + "input_nominal: [1" + "0" * 400 + ", 0, 0]\n",
                                           r"key 'input_nominal': entry 1: expected a finite number, got an integer of 401 digits"),
    "string in output_nominal": (GOOD + "output_nominal: [0, zero, 0]\n",
                                 r"key 'output_nominal': entry 2: expected a number, got 'zero'"),
    "not YAML": ("sample_time: 1.0\ninputs: [u1, u2\n  gain: {{{\n", r"not valid YAML at line \d+, column \d+"),
    "YAML but not a mapping": ("- 1\n- 2\n", r"expected a YAML mapping with keys sample_time, .*got list"),
    "empty file": ("", r"empty file: expected a YAML model"),
    "only a comment": ("# nothing here\n", r"empty file"),
    "not UTF-8": (GOOD.encode("utf-8").replace(b"u1, u2", b"u\xff, u2"), r"not UTF-8 text \(byte \d+\)"),
    "non-numeric cell": (
        _replace_line("gain", "gain: [[4.05, 1.77, 5.88], [5.39, abc, 6.90], [4.38, 4.42, 7.20]]"),
        r"key 'gain': row 2 \(y2\), column 2 \(u2\): expected a number, got 'abc'"),
    "boolean cell": (
        _replace_line("delay", "delay: [[6, 7, 6], [4, 3, 3], [5, 5, true]]"),
        r"key 'delay': row 3 \(y3\), column 3 \(u3\): expected a number, got True"),
    "number written as a string": (
        _replace_line("time_constant", "time_constant: [[50, '60', 50], [50, 60, 40], [33, 44, 19]]"),
        r"key 'time_constant': row 1 \(y1\), column 2 \(u2\): expected a number, got '60'"),
    "duplicate input names": (_replace_line("inputs", "inputs: [u1, u2, u1]"), r"key 'inputs': names must be unique, repeated: u1"),
    "duplicate output names": (_replace_line("outputs", "outputs: [y1, y3, y3]"), r"key 'outputs': names must be unique, repeated: y3"),
    "name both input and output": (_replace_line("outputs", "outputs: [y1, y2, u3]"), r"'inputs' and 'outputs': a name cannot be both"),
    "empty inputs": (_replace_line("inputs", "inputs: []"), r"key 'inputs': expected a non-empty list"),
    "non-string name": (_replace_line("inputs", "inputs: [u1, 2, u3]"), r"key 'inputs': expected names as strings, got 2 "
                                                                        r"\(a name that reads as a number or a boolean is "
                                                                        r"written in quotes: '1e3'\)$"),
    "inputs not a list": (_replace_line("inputs", "inputs: u1"), r"key 'inputs': expected a list of names, got str"),
    "sample_time a string": (_replace_line("sample_time", "sample_time: one"), r"key 'sample_time': expected a positive number of seconds, got 'one'"),
    "sample_time a list": (_replace_line("sample_time", "sample_time: [1.0]"), r"key 'sample_time': expected a positive number of seconds, got \[1.0\]"),
    "sample_time a boolean": (_replace_line("sample_time", "sample_time: true"), r"key 'sample_time': expected a positive number of seconds, got True"),
    "name not a string": (GOOD + "name: [1, 2]\n", r"key 'name': expected a string"),
    # An explicit tag whose constructor refuses the value (a traceback before): its line and column.
    "!!int on a fraction": (_replace_line("sample_time", "sample_time: !!int 1.5"),
                            r"not valid YAML at line 1, column 14: '1.5' cannot be read as !!int \(ValueError"),
    "!!float on a decimal comma": (
        _replace_line("gain", 'gain: [[!!float "4,05", 1.77, 5.88], [5.39, 5.72, 6.90], [4.38, 4.42, 7.20]]'),
        r"not valid YAML at line \d+, column \d+: '4,05' cannot be read as !!float"),
    "!!bool on a word": (GOOD + "integrating: [[!!bool maybe, false, false], [false, false, false], [false, false, false]]\n",
                         r"not valid YAML at line \d+, column \d+: 'maybe' cannot be read as !!bool"),
    "!!timestamp on a word": (GOOD + "name: !!timestamp tuesday\n", r"not valid YAML at line \d+, column \d+: 'tuesday' "
                                                                   r"cannot be read as !!timestamp"),
    "!!map on a list": (_replace_line("outputs", "outputs: !!map [y1, y2, y3]"),
                        r"not valid YAML at line \d+, column 10: expected a mapping for !!map, got a sequence"),
    "a merge key": ("base: &b {sample_time: 1.0}\n<<: *b\n" + GOOD, r"not valid YAML at line 2, column 1: a merge key "
                                                                     r"\(<<\) is not read in a model file"),
    # YAML 1.1's yes/no/on/off are not booleans here (YAML 1.2, as the numbers): silently true before.
    "yes and no as integrating": (
        GOOD + "integrating: [[no, off, false], [yes, no, false], [false, false, false]]\n",
        r"key 'integrating': row 1 \(y1\), column 1 \(u1\): expected true or false, got 'no'"),
    "yes as a key": (GOOD + "yes: 1\n", r"unknown key 'yes'"),
    # A key with another name an engineer uses: the hint names the model file's key.
    "dead_time for delay": (_replace_line("delay", "dead_time: [[6, 7, 6], [4, 3, 3], [5, 5, 0]]"),
                            r"unknown key 'dead_time' \(did you mean 'delay'\?\)"),
    # A few lines of nested aliases expand to billions of values (a "billion laughs"): refused at once, not after
    # minutes and gigabytes (or a MemoryError traceback).
    "billion laughs": (GOOD + "x: &a0 [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"
                       + "".join(f"x{k}: &a{k} [{', '.join([f'*a{k - 1}'] * 9)}]\n" for k in range(1, 11)),
                       r"not a model file: its aliases expand to more than 20,000,000 values"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_model_file_refused_with_one_line_naming_the_key(tmp_path, case):
    text, pattern = BAD_FILES[case]
    path = _write(tmp_path, text)
    with pytest.raises(ModelFileError, match=pattern) as info:
        load_model(path)
    msg = str(info.value)
    assert "\n" not in msg, msg
    assert msg.startswith(str(path) + ": "), msg  # the file is named
    # The error is a user-input error (CLI exit 2), a ValueError, never e.g. a KeyError.
    assert isinstance(info.value, InputError) and isinstance(info.value, ValueError)


def test_unreadable_path_refused(tmp_path):
    with pytest.raises(ModelFileError, match=r"cannot read model file"):
        load_model(tmp_path / "does-not-exist.yaml")
    with pytest.raises(ModelFileError, match=r"cannot read model file"):
        load_model(tmp_path)  # a directory


def test_constructor_validates_like_the_loader():
    ref = shell_plant()
    with pytest.raises(ModelFileError, match=r"key 'time_constant': row 1 \(y1\), column 3 \(u3\): expected >= 0"):
        ref.with_element(0, 2, time_constant=-1.0)
    with pytest.raises(ModelFileError, match=r"key 'delay': .*expected a multiple of sample_time"):
        ref.with_element(2, 0, delay=2.5)
    with pytest.raises(ModelFileError, match=r"key 'gain': expected 3 rows x 3 columns"):
        ref.replace(gain=np.ones((3, 2)))


def test_good_files_variants_accepted(tmp_path):
    # The checks must not refuse legitimate files: zero gains ("no such effect"), zero time
    # constants, delays on a fractional sample grid, integer sample time, 1x1 model.
    text = ("sample_time: 0.2\ninputs: [u]\noutputs: [y]\ngain: [[0]]\ntime_constant: [[0]]\n"
            "delay: [[0.6]]\n")
    model = load_model(_write(tmp_path, text))
    assert model.delay_samples[0, 0] == 3
    assert model.gain[0, 0] == 0.0
    # 0.3 / 0.1 and 0.7 / 0.1 are not integers in binary floating point; they must still be accepted.
    text = ("sample_time: 0.1\ninputs: [u1, u2]\noutputs: [y]\ngain: [[1, 2]]\ntime_constant: [[0, 5]]\n"
            "delay: [[0.3, 0.7]]\n")
    model = load_model(_write(tmp_path, text, name="grid.yaml"))
    np.testing.assert_array_equal(model.delay_samples, [[3, 7]])


def test_analyze_exits_2_on_bad_model(tmp_path):
    import subprocess
    import sys

    bad = _write(tmp_path, _replace_line("gain", None))
    data = _write(tmp_path, "t,r_y1\n0,0\n", name="data.csv")
    proc = subprocess.run([sys.executable, "-m", "mpm_monitor", "analyze", "--model", str(bad), "--data", str(data)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "missing key 'gain'" in proc.stderr and "Traceback" not in proc.stderr


def test_names_that_read_as_numbers_or_booleans_round_trip(tmp_path):
    """A name the loader reads as a number or a boolean unquoted (YAML 1.2: ``2e3``, ``1E3``, ``NO`` is a plain
    string here, ``true`` is not) is written quoted, so a written model file loads back (``--repair-out`` wrote
    ``name: 2e3``, which the loader then refused as a number)."""
    text = (GOOD.replace("inputs:", "name: '2e3'\ninputs:", 1).replace("[u1, u2, u3]", "['1e3', 'true', NO]")
            .replace("[y1, y2, y3]", "['2E1', 'off', '010']"))
    model = load_model(_write(tmp_path, text))
    assert model.name == "2e3" and model.inputs == ("1e3", "true", "NO") and model.outputs == ("2E1", "off", "010")
    out = tmp_path / "written.yaml"
    save_model(model, out)
    assert load_model(out) == model


def test_a_model_file_longer_than_the_limit_or_endless_is_refused(tmp_path, monkeypatch):
    """``--model /dev/zero`` read until the memory ran out (a MemoryError traceback)."""
    import mpm_monitor.io.model_file as mf

    monkeypatch.setattr(mf, "MAX_MODEL_BYTES", 1000)
    with pytest.raises(ModelFileError, match=r"^/dev/zero: longer than 1,000 bytes: expected a YAML model file$"):
        load_model("/dev/zero")
    path = _write(tmp_path, GOOD + "#" * 1000 + "\n")
    with pytest.raises(ModelFileError, match=r"longer than 1,000 bytes"):
        load_model(path)



def test_a_model_file_is_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    """``--repair-out`` and the monitor's repaired model were written in place: a write cut short left half a file
    where a controller may read its model.  Now written beside it and renamed over it."""
    import os

    path = tmp_path / "model.yaml"
    save_model(shell_plant(), path)
    before = path.read_bytes()

    def fails(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", fails)
    with pytest.raises(OSError):
        save_model(shell_plant().replace(gain=2 * shell_plant().gain), path)
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["model.yaml"]
    monkeypatch.undo()
    save_model(shell_plant().replace(gain=2 * shell_plant().gain), path)
    assert load_model(path) == shell_plant().replace(gain=2 * shell_plant().gain)


def test_to_dict_writes_each_number_as_float_then_int_where_whole():
    """The model's dict holds, for every entry, ``int(float(x))`` where ``float(x)`` is whole and below
    2**53 in magnitude and ``float(x)`` otherwise (a reference loop over the entries here)."""

    def num(x):
        x = float(x)
        return int(x) if x.is_integer() and abs(x) < 2 ** 53 else x

    rng = np.random.default_rng(11)
    coef = np.round(np.cumsum(rng.normal(size=(3, 2, 40)), axis=2), rng.integers(0, 3))
    coef[..., :3] = 0.0
    coef[0, 0, 5:8] = [-0.0, 2.0 ** 53, 2.0 ** 53 - 1]
    coef[1, 1, 9] = 1e300
    model = PlantModel.from_step_response(0.5, ("u1", "u2"), ("y1", "y2", "y3"), coef,
                                          input_nominal=[1.0, 2.5], output_nominal=[-3.0, 0.0, 7.25])
    d = model.to_dict()
    want = [[[num(v) for v in el] for el in row] for row in coef]
    got = d["step_response"]["coefficients"]
    assert got == want
    assert [[[type(v) for v in el] for el in row] for row in got] == [[[type(v) for v in el] for el in row]
                                                                       for row in want]
    assert d["input_nominal"] == [1, 2.5] and type(d["input_nominal"][0]) is int
    assert d["output_nominal"] == [-3, 0, 7.25] and [type(v) for v in d["output_nominal"]] == [int, int, float]
    par = PlantModel(1.0, ("u",), ("y1", "y2"), gain=[[2.5], [-1.0]], time_constant=[[10.0], [0.0]],
                     delay=[[3.0], [0.0]])
    pd = par.to_dict()
    assert pd["gain"] == [[2.5], [-1]] and type(pd["gain"][1][0]) is int
    assert pd["delay"] == [[3], [0]] and all(type(r[0]) is int for r in pd["delay"])


def test_models_equal_exactly_when_their_dicts_do():
    rng = np.random.default_rng(12)
    coef = np.cumsum(rng.normal(size=(2, 2, 30)), axis=2)
    a = PlantModel.from_step_response(1.0, ("u1", "u2"), ("y1", "y2"), coef)
    b = PlantModel.from_step_response(1.0, ("u1", "u2"), ("y1", "y2"), coef.copy())
    assert a == b
    changed = coef.copy()
    changed[1, 0, 17] = np.nextafter(changed[1, 0, 17], np.inf)
    assert a != PlantModel.from_step_response(1.0, ("u1", "u2"), ("y1", "y2"), changed)
    assert a != PlantModel.from_step_response(1.0, ("u1", "u2"), ("y1", "y2"), coef[:, :, :29])


def test_the_repair_reports_json_values_keep_numbers_and_turn_non_finite_ones_to_null():
    import math

    from mpm_monitor.core.repair.result import _jsonable

    def reference(x):
        if isinstance(x, dict):
            return {str(k): reference(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [reference(v) for v in x]
        if isinstance(x, (np.bool_, bool)):
            return bool(x)
        if isinstance(x, np.integer):
            return int(x)
        if isinstance(x, (float, np.floating)):
            return float(x) if math.isfinite(float(x)) else None
        return x

    cases = [[1, 2.5, -0.0], [1.0, float("nan"), 3], [float("inf")], [10 ** 400, 1.5], [10 ** 400], (1, 2),
             [True, 1], [np.float64(1.5), 2.0], [np.int64(3)], [], [[1.5, 2], ["a", None]], {1: [2.0, float("-inf")]}]
    for case in cases:
        got, want = _jsonable(case), reference(case)
        assert got == want and [type(v) for v in (got if isinstance(got, list) else got.values())] == \
            [type(v) for v in (want if isinstance(want, list) else want.values())], case
    row = [0.5, 1.0]
    assert _jsonable(row) is not row        # a copy, as before


@pytest.mark.parametrize("key", ["lead", "time_constant2", "integrating", "disturbances", "input_nominal",
                                 "output_nominal"])
def test_an_optional_key_given_as_null_is_read_as_absent(tmp_path, key):
    """As docs/interfaces.md says: ``lead: null`` (or ``lead:`` alone) is the file without the key."""
    for text in (GOOD + f"{key}: null\n", GOOD + f"{key}:\n"):
        assert load_model(_write(tmp_path, text)) == load_model(_write(tmp_path, GOOD, "plain.yaml"))


@pytest.mark.parametrize("key, expected", [("gain", "expected a list of rows"), ("sample_time", "positive number"),
                                           ("inputs", "list of names"), ("name", "expected a string")])
def test_a_required_key_or_the_name_given_as_null_is_refused(tmp_path, key, expected):
    text = _replace_line(key, f"{key}: null") if key != "name" else GOOD + "name: null\n"
    with pytest.raises(ModelFileError, match=f"key '{key}'.*{expected}") as err:
        load_model(_write(tmp_path, text))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("key", ["inputs", "outputs"])
def test_an_empty_list_of_channels_is_named_before_the_matrices(tmp_path, key):
    """``outputs: []`` (with empty matrices) was refused as "key 'gain': expected at least one row"."""
    names = {"inputs": "[u1]", "outputs": "[y1]"}
    names[key] = "[]"
    (tmp_path / "m.yaml").write_text(f"sample_time: 1\ninputs: {names['inputs']}\noutputs: {names['outputs']}\n"
                                     "gain: []\ntime_constant: []\ndelay: []\n")
    with pytest.raises(ModelFileError, match=rf"m\.yaml: key '{key}': expected a non-empty list of names$"):
        load_model(tmp_path / "m.yaml")
