"""Robustness of the file inputs (issue 7, item 2): model files, CSV logs, bags and the CLI.

Property-based (hypothesis) over model files and CSV contents: whatever the bytes, the reader
returns a valid object or raises its own :class:`~mpm_monitor.core.errors.InputError` subclass
(``ModelFileError``/``DataFileError``, both ``ValueError``) with exactly one line that starts with
the file name and says where (key, line, byte); never any other exception.  The same over a bag's
storage file (with and without its chunks' CRCs) and its ``metadata.yaml``, read with a model and
without, and over a killed recording's storage file given to ``recover_bag``: the data, the
recovered bag, or one ``BagError`` line that names the bag.  The command line
(``python -m mpm_monitor analyze``) turns every bad model, CSV or bag into exit code 2 and one line
on stderr, without a traceback; the YAML loader refuses Python tags without running them.

The examples are derandomized (same examples on every run) so that CI is reproducible; the counts
are chosen to keep this file to a few seconds.
"""

import functools
import os
import re
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.core.errors import BagError, DataFileError, InputError, ModelFileError
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io import csv_log
from mpm_monitor.io.bags import (BagWriter, read_bag, read_bag_channels, read_raw_messages, recover_bag,
                                 write_logged_data)
from mpm_monitor.io.csv_log import csv_header, read_csv, write_csv
from mpm_monitor.io.model_file import dump_model, load_model, save_model

REPO = Path(__file__).resolve().parents[1]

SETTINGS = settings(max_examples=150, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

#: What a message must say about *where* the problem is (a key, a line, a byte, or the whole file).
WHERE = re.compile(r"key '|keys '|line \d+|byte \d+|character \d+|empty file|expected a YAML mapping|"
                   r"no data lines|NUL bytes|nested")

GOOD_MODEL = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1", "y2"),
                        gain=[[1.0, 0.5], [0.2, 1.0]], time_constant=[[5.0, 5.0], [5.0, 5.0]],
                        delay=[[1.0, 0.0], [0.0, 2.0]])


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("robust_files")


@pytest.fixture(scope="module")
def monkeypatch_module():
    """A monkeypatch for hypothesis tests (the function-scoped one is not reset between examples)."""
    with pytest.MonkeyPatch.context() as mp:
        yield mp


def assert_one_line_error(exc: BaseException, path) -> str:
    """The message is one line, starts with the file name and says where the problem is."""
    msg = str(exc)
    assert isinstance(exc, ValueError) and isinstance(exc, InputError)
    assert len(msg.splitlines()) == 1, f"not one line: {msg!r}"
    assert msg.startswith(f"{path}:"), msg
    assert WHERE.search(msg), f"message does not say where: {msg!r}"
    return msg


def model_outcome(path):
    """Load a model file; a valid model must round-trip through dump/load."""
    try:
        model = load_model(path)
    except ModelFileError as exc:
        assert_one_line_error(exc, path)
        return None
    assert isinstance(model, PlantModel)
    assert np.all(np.isfinite(model.gain)) and np.all(model.time_constant >= 0)
    again = path.with_suffix(".again.yaml")
    save_model(model, again)
    assert load_model(again) == model
    return model


# ------------------------------------------------------------------------------------------------
# Model files: random YAML structures

_weird_numbers = st.sampled_from([1e308, -1e308, 1.7976931348623157e308, 5e-324, -0.0, 1e-308,
                                  10**400, -10**400, 2**63, 2**64, float("nan"), float("inf"), -float("inf")])
_scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6), _weird_numbers,
                     st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=6),
                     st.binary(max_size=4))
_values = st.recursive(_scalars, lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=4), c, max_size=3),
                       max_leaves=10)
_names = st.lists(st.one_of(st.text(min_size=1, max_size=5), st.sampled_from(["u1", "y1", "a,b", " x", "x\ny", "u1"])),
                  min_size=0, max_size=3)


def _matrix_of(draw, elements, ny, nu):
    shape_ok = draw(st.booleans())
    rows = ny if shape_ok else draw(st.integers(0, 3))
    cols = nu if shape_ok else draw(st.integers(0, 3))
    return [[draw(elements) for _ in range(cols)] for _ in range(rows)]


@st.composite
def model_documents(draw):
    """A dict close to a model file: each key valid, missing, of a wrong type or with odd values."""
    ny, nu = draw(st.integers(1, 3)), draw(st.integers(1, 3))
    ts = draw(st.sampled_from([1.0, 0.5, 2, 1e-308, 1e308]))
    good = {
        "sample_time": ts,
        "inputs": [f"u{j + 1}" for j in range(nu)],
        "outputs": [f"y{i + 1}" for i in range(ny)],
        "gain": [[1.0] * nu for _ in range(ny)],
        "time_constant": [[10.0] * nu for _ in range(ny)],
        "delay": [[0.0] * nu for _ in range(ny)],
    }
    numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True), _weird_numbers, st.integers(-5, 5),
                        st.builds(lambda k: k * ts, st.integers(0, 5)))
    doc = {}
    for key, val in good.items():
        how = draw(st.sampled_from(["good", "good", "missing", "random", "numbers", "names"]))
        if how == "good":
            doc[key] = val
        elif how == "random":
            doc[key] = draw(_values)
        elif how == "numbers":
            doc[key] = _matrix_of(draw, numbers, ny, nu) if isinstance(val, list) else draw(numbers)
        elif how == "names":
            doc[key] = draw(_names)
    for key in ("input_nominal", "output_nominal", "name"):
        if draw(st.booleans()):
            doc[key] = draw(st.one_of(_values, st.lists(numbers, max_size=3)))
    return doc


def _yaml_text(doc) -> str:
    try:
        return yaml.safe_dump(doc, allow_unicode=True, default_flow_style=draw_flow(doc))
    except yaml.YAMLError:  # pragma: no cover - safe_dump represents every value we generate
        raise


def draw_flow(doc) -> bool:
    return len(doc) % 2 == 0


@SETTINGS
@given(doc=model_documents())
def test_random_model_structures_give_a_model_or_a_one_line_error(work, doc):
    path = work / "random_structure.yaml"
    path.write_text(_yaml_text(doc), encoding="utf-8")
    model_outcome(path)


# ------------------------------------------------------------------------------------------------
# Model files: damaged text and bytes

GOOD_TEXT = dump_model(GOOD_MODEL).encode()


@st.composite
def damaged_bytes(draw, good: bytes):
    """Truncated, with bytes inserted or replaced (not UTF-8, control characters), or spliced."""
    data = bytearray(good)
    for _ in range(draw(st.integers(1, 3))):
        how = draw(st.sampled_from(["truncate", "insert", "replace", "unicode", "duplicate"]))
        pos = draw(st.integers(0, len(data)))
        if how == "truncate":
            del data[pos:]
        elif how == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=4))
        elif how == "replace" and pos < len(data):
            data[pos] = draw(st.integers(0, 255))
        elif how == "unicode":
            data[pos:pos] = draw(st.text(min_size=1, max_size=3)).encode("utf-8", "surrogatepass")
        elif how == "duplicate":
            end = draw(st.integers(pos, len(data)))
            data[pos:pos] = data[pos:end]
    return bytes(data)


@SETTINGS
@given(raw=damaged_bytes(GOOD_TEXT))
def test_damaged_model_file_gives_a_model_or_a_one_line_error(work, raw):
    path = work / "damaged.yaml"
    path.write_bytes(raw)
    model_outcome(path)


_name_chars = st.characters(codec="utf-8", exclude_categories=("Cc", "Cs", "Zl", "Zp"), exclude_characters=",")
_valid_names = st.text(_name_chars, min_size=1, max_size=6).filter(
    lambda s: s == s.strip() and s != "t" and not s.startswith("r_"))  # those would clash in the CSV header


@st.composite
def valid_models(draw):
    ny, nu = draw(st.integers(1, 3)), draw(st.integers(1, 3))
    names = draw(st.lists(_valid_names, min_size=ny + nu, max_size=ny + nu, unique=True))
    ts = draw(st.one_of(st.sampled_from([1.0, 0.1, 1e-300, 1e300]), st.floats(1e-3, 1e3)))
    finite = st.floats(allow_nan=False, allow_infinity=False)
    gain = draw(st.lists(st.lists(finite, min_size=nu, max_size=nu), min_size=ny, max_size=ny))
    tau = draw(st.lists(st.lists(st.floats(0, 1e308), min_size=nu, max_size=nu), min_size=ny, max_size=ny))
    delay = draw(st.lists(st.lists(st.integers(0, 20), min_size=nu, max_size=nu), min_size=ny, max_size=ny))
    return PlantModel(sample_time=ts, inputs=names[ny:], outputs=names[:ny], gain=gain, time_constant=tau,
                      delay=np.array(delay) * ts, name=draw(st.text(max_size=8)))


@SETTINGS
@given(model=valid_models())
def test_valid_models_with_unicode_names_and_extreme_values_round_trip(work, model):
    """Save/load is exact, and a CSV written with the model's (unicode) names reads back exactly."""
    path = work / "valid.yaml"
    save_model(model, path)
    assert load_model(path) == model
    n = 4
    rng = np.random.default_rng(0)
    t = np.arange(n) * model.sample_time
    r, u, y = rng.normal(size=(n, model.n_outputs)), rng.normal(size=(n, model.n_inputs)), rng.normal(size=(n, model.n_outputs))
    csv_path = work / "valid.csv"
    write_csv(csv_path, t, r, u, y, model.inputs, model.outputs)
    data = read_csv(csv_path, model)
    np.testing.assert_array_equal(data.r, r)
    np.testing.assert_array_equal(data.u, u)
    np.testing.assert_array_equal(data.y, y)


MODEL_HEAD = "sample_time: 1\ninputs: [u1]\noutputs: [y1]\n"


@pytest.mark.parametrize("text, match", [
    (MODEL_HEAD + f"gain: [[{10**400}]]\ntime_constant: [[1]]\ndelay: [[0]]\n", r"key 'gain': row 1 \(y1\), column 1 \(u1\): expected a finite"),
    (f"sample_time: {10**400}\ninputs: [u1]\noutputs: [y1]\ngain: [[1]]\ntime_constant: [[1]]\ndelay: [[0]]\n",
     r"key 'sample_time'"),
    (MODEL_HEAD + f"gain: [[1]]\ntime_constant: [[1]]\ndelay: [[0]]\ninput_nominal: [{10**400}]\n", r"key 'input_nominal'"),
    (MODEL_HEAD + "gain: " + "[" * 20000 + "]" * 20000 + "\n", r"nested too deeply"),
    (MODEL_HEAD + "gain: [[1]]\ntime_constant: [[1]]\ndelay: [[1.0e+300]]\n", r"key 'delay'.*at most"),
    ("sample_time: 1.0e-300\ninputs: [u1]\noutputs: [y1]\ngain: [[1]]\ntime_constant: [[1]]\ndelay: [[1.0]]\n",
     r"key 'delay'.*at most"),
    ('sample_time: 1\ninputs: ["u\\nx"]\noutputs: [y1]\ngain: [[1]]\ntime_constant: [[1]]\ndelay: [[0]]\n',
     r"key 'inputs'.*control"),
    ('sample_time: 1\ninputs: [u1]\noutputs: ["y\\u2028", "y\\u2028"]\ngain: [[1], [1]]\ntime_constant: [[1], [1]]\n'
     'delay: [[0], [0]]\n', r"key 'outputs'"),
    (MODEL_HEAD + "gain: [[1]]\ntime_constant: [[1]]\ndelay: [[0]]\n\x07\n", r"character \d+"),
    ('sample_time: 1\ninputs: [t]\noutputs: [y1]\ngain: [[1]]\ntime_constant: [[1]]\ndelay: [[0]]\n',
     r"name 't' would be two columns of the CSV log"),
    ('sample_time: 1\ninputs: [r_y1]\noutputs: [y1]\ngain: [[1]]\ntime_constant: [[1]]\ndelay: [[0]]\n',
     r"keys 'outputs' and 'inputs': name 'r_y1' would be two columns of the CSV log"),
    # A disturbance's clash was said of the keys 'inputs' and 'outputs'
    ('sample_time: 1\ninputs: [u1]\noutputs: [y1]\ndisturbances: [t]\ngain: [[1, 1]]\ntime_constant: [[1, 1]]\n'
     'delay: [[0, 0]]\n', r"key 'disturbances': name 't' would be two columns of the CSV log"),
    ('sample_time: 1\ninputs: [u1]\noutputs: [y1]\ndisturbances: [r_y1]\ngain: [[1, 1]]\ntime_constant: [[1, 1]]\n'
     'delay: [[0, 0]]\n', r"keys 'outputs' and 'disturbances': name 'r_y1'"),
    # YAML 1.1 would read these as another model: base 60 (90), the last of two keys, 10 (underscore)
    (MODEL_HEAD + "gain: [[1]]\ntime_constant: [[1:30]]\ndelay: [[0]]\n", r"key 'time_constant'.*got '1:30'"),
    (MODEL_HEAD + "gain: [[1]]\ntime_constant: [[1]]\ndelay: [[0]]\ngain: [[2]]\n",
     r"not valid YAML at line 7, column 1: found duplicate key 'gain'"),
    (MODEL_HEAD + "gain: [[1_0]]\ntime_constant: [[1]]\ndelay: [[0]]\n", r"key 'gain'.*got '1_0'"),
])
def test_edge_case_model_files_refused_with_one_line(work, text, match):
    path = work / "edge.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(ModelFileError, match=match) as info:
        load_model(path)
    assert_one_line_error(info.value, path)


@pytest.mark.parametrize("deep", [
    "gain: " + "[" * 200000 + "]" * 200000 + "\n",              # flow sequences
    "gain: " + "{a: " * 30000 + "}" * 30000 + "\n",             # flow mappings
    "gain:\n" + "- " * 30000 + "x\n",                         # block sequences, compact on one line
    "gain:\r" + "- " * 30000 + "x\r",                         # the same with bare CR line ends
])
def test_nesting_libyaml_cannot_compose_is_refused_in_one_line(work, deep):
    """libyaml's composer recurses in C once per level: near 25,000 levels it overflowed the stack (a segmentation
    fault, exit 139, no message; the depth of 20,000 above still passed).  In a child process, so that a crash is
    a failure of this test, not of the run."""
    path = work / "deep.yaml"
    path.write_bytes((MODEL_HEAD + deep).encode("utf-8"))
    code = ("import sys\nfrom mpm_monitor.io.model_file import load_model\nfrom mpm_monitor.core.errors import "
            "ModelFileError\ntry:\n    load_model(sys.argv[1])\nexcept ModelFileError as exc:\n    print(exc)\n")
    out = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-500:]
    assert out.stdout.strip() == f"{path}: not a model file: lists or mappings nested too deeply"


@given(st.recursive(st.integers(0, 9), lambda kids: st.lists(kids, max_size=3) |
                    st.dictionaries(st.sampled_from("abc"), kids, max_size=3), max_leaves=40),
       st.booleans())
@settings(max_examples=200, deadline=None)
def test_the_nesting_bound_is_never_below_the_nesting(value, flow):
    """The one-pass bound that decides whether libyaml's event parser checks the nesting first is an upper
    bound, block style or flow style."""
    from mpm_monitor.io.yaml_nesting import nesting_bound as _nesting_bound

    def depth(x):
        return 1 + max((depth(v) for v in (x.values() if isinstance(x, dict) else x)), default=0) \
            if isinstance(x, (list, dict)) else 0

    text = yaml.safe_dump({"gain": value}, default_flow_style=flow)
    assert _nesting_bound(text) >= depth({"gain": value})


def test_numbers_are_read_as_yaml_1_2_and_json_write_them(work):
    """``5e-05`` is a number (YAML 1.1: a string; json.dump writes it so, as in the report's repair.model),
    ``010`` is ten (1.1: octal eight); the JSON form of a model loads as the model."""
    import json

    path = work / "numbers.yaml"
    path.write_text(MODEL_HEAD + "gain: [[5e-05]]\ntime_constant: [[1E3]]\ndelay: [[010]]\n", encoding="utf-8")
    m = load_model(path)
    assert (m.gain[0, 0], m.time_constant[0, 0], m.delay[0, 0]) == (5e-05, 1000.0, 10.0)
    as_json = work / "model.json"
    as_json.write_text(json.dumps(m.to_dict()), encoding="utf-8")
    assert load_model(as_json) == m


def test_names_like_dates_are_names_and_optional_nulls_are_absent(work):
    """YAML 1.2 has no timestamps: ``2001-12-14`` was read as a date and refused as a name (the dumper still quotes
    it, for YAML 1.1 readers).  ``ramp: null`` and, in a step-response model, ``lead: null`` were refused, where an
    optional key given as null is absent."""
    path = work / "dates.yaml"
    path.write_text("name: 2001-12-14\nsample_time: 1\ninputs: [2024-01-01]\noutputs: [y1]\ngain: [[1]]\n"
                    "time_constant: [[1]]\ndelay: [[0]]\nramp:\n", encoding="utf-8")
    m = load_model(path)
    assert (m.name, m.inputs) == ("2001-12-14", ("2024-01-01",))
    assert "'2024-01-01'" in dump_model(m) and load_model(path) == m
    path.write_text("sample_time: 1\ninputs: [u1]\noutputs: [y1]\nstep_response: {length: 2, coefficients: [[[0.5, 1.0]]]}\nlead: ~\n"
                    "integrating: null\n", encoding="utf-8")
    assert load_model(path).is_step_response
    path.write_text("sample_time: 1\ninputs: [u1]\noutputs: [y1]\nstep_response: {length: 2, coefficients: [[[0.5, 1.0]]]}\ngain: null\n",
                    encoding="utf-8")
    with pytest.raises(ModelFileError, match="key 'gain': a step-response model"):
        load_model(path)


def test_python_tags_are_refused_and_never_run(work):
    """``yaml.safe_load``: a ``!!python/object`` tag is refused, the command in it never runs."""
    marker = work / "pwned"
    for tag in ("!!python/object/apply:os.system", "!!python/object/apply:subprocess.call"):
        path = work / "evil.yaml"
        path.write_text(f"sample_time: {tag} [['touch {marker}']]\n" if "subprocess" in tag else
                        f"sample_time: {tag} ['touch {marker}']\n", encoding="utf-8")
        with pytest.raises(ModelFileError, match=r"line 1.*python/object") as info:
            load_model(path)
        assert_one_line_error(info.value, path)
    path.write_text("!!python/object:mpm_monitor.core.model.PlantModel {sample_time: 1}\n", encoding="utf-8")
    with pytest.raises(ModelFileError, match=r"python/object"):
        load_model(path)
    assert not marker.exists()


# ------------------------------------------------------------------------------------------------
# CSV contents

CSV_MODEL = PlantModel(sample_time=0.5, inputs=("u1", "ü2"), outputs=("y1",), gain=[[1.0, 2.0]],
                       time_constant=[[1.0, 1.0]], delay=[[0.0, 0.5]])
NEEDED = csv_header(CSV_MODEL.inputs, CSV_MODEL.outputs)


def data_outcome(path, model=CSV_MODEL):
    try:
        data = read_csv(path, model)
    except DataFileError as exc:
        assert_one_line_error(exc, path)
        return None
    assert isinstance(data, LoggedData)
    n = data.n_samples
    assert n >= 1
    assert data.r.shape == (n, model.n_outputs) and data.u.shape == (n, model.n_inputs)
    assert data.y.shape == (n, model.n_outputs)
    for arr in (data.t, data.r, data.u, data.y):
        assert np.all(np.isfinite(arr))
    with np.errstate(over="ignore", invalid="ignore"):
        steps = np.diff(data.t)
    k = steps / model.sample_time           # whole samples: 1, or more across a gap (missing rows)
    assert np.all(np.abs(k - np.round(k)) <= 1e-3) and np.all(np.round(k) >= 1)
    return data


_cell_numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), _weird_numbers.map(str),
                          st.integers(-10**30, 10**30).map(str))
_cells = st.one_of(_cell_numbers, _cell_numbers, st.text(max_size=6), st.sampled_from(["", " ", "1_0", "1e999", "0x10",
                                                                                       '"1"', '"', "\u0663", "nan"]))


@st.composite
def csv_texts(draw):
    """A header (the needed columns shuffled, extra columns, sometimes one missing or repeated) and
    ragged rows of random cells; ``t`` regular, jittered or random."""
    cols = list(NEEDED) + draw(st.lists(st.sampled_from(["extra", "note", "r_y2"]), max_size=2))
    if draw(st.integers(0, 9)) == 0:
        cols.remove(draw(st.sampled_from(NEEDED)))
    if draw(st.integers(0, 9)) == 0:
        cols.append(draw(st.sampled_from(NEEDED)))
    cols = draw(st.permutations(cols))
    n = draw(st.integers(0, 8))
    t_mode = draw(st.sampled_from(["regular", "regular", "jitter", "random"]))
    lines = [",".join(cols)]
    for k in range(n):
        row = []
        for c in cols:
            if c == "t" and t_mode != "random":
                jitter = draw(st.sampled_from([0.0, 0.0, 1e-5, 0.3, -0.5])) if t_mode == "jitter" else 0.0
                row.append(repr(k * 0.5 + jitter))
            else:
                row.append(draw(_cells) if draw(st.integers(0, 3)) == 0 else repr(draw(st.floats(-1e6, 1e6))))
        if draw(st.integers(0, 9)) == 0:
            row = row[:draw(st.integers(0, len(row)))] + draw(st.lists(_cells, max_size=2))
        lines.append(",".join(row))
    return "\n".join(lines) + draw(st.sampled_from(["\n", "", "\r\n", "\n\n"]))


@SETTINGS
@given(text=csv_texts())
def test_random_csv_gives_data_or_a_one_line_error(work, text):
    path = work / "random.csv"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    data_outcome(path)


def _outcome_of(read):
    """``("data", LoggedData)`` or ``("error", message)`` of ``read()``."""
    try:
        return "data", read()
    except DataFileError as exc:
        return "error", str(exc)


def _same_data(a: LoggedData, b: LoggedData) -> None:
    for key in ("t", "r", "u", "y", "dv"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
        assert np.array_equal(np.signbit(getattr(a, key)), np.signbit(getattr(b, key))), key
    assert a.extra.keys() == b.extra.keys()
    for name in a.extra:
        np.testing.assert_array_equal(a.extra[name], b.extra[name], err_msg=name)
    assert a.unusable == b.unusable


@SETTINGS
@given(text=csv_texts())
def test_fast_csv_path_reads_what_the_careful_parser_reads(work, text, monkeypatch_module):
    # numpy's C parser is only a shortcut: on any file the result (data, or the one-line error)
    # is the careful csv-module parser's, value for value.
    path = work / "both.csv"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    both = _outcome_of(lambda: read_csv(path, CSV_MODEL))
    with monkeypatch_module.context() as mp:
        mp.setattr(csv_log, "_fast_table", lambda *args: None)
        careful = _outcome_of(lambda: read_csv(path, CSV_MODEL))
    assert both[0] == careful[0], (both, careful)
    if both[0] == "error":
        assert both[1] == careful[1]
    else:
        _same_data(both[1], careful[1])


def _good_csv_bytes(n=6) -> bytes:
    t = np.arange(n) * CSV_MODEL.sample_time
    rng = np.random.default_rng(1)
    import io
    buf = io.StringIO()
    buf.write(",".join(NEEDED) + "\n")
    for k in range(n):
        buf.write(",".join(repr(float(v)) for v in np.r_[t[k], rng.normal(size=4) * 1e300]) + "\n")
    return buf.getvalue().encode()


@SETTINGS
@given(raw=damaged_bytes(_good_csv_bytes()))
def test_damaged_csv_bytes_give_data_or_a_one_line_error(work, raw):
    path = work / "damaged.csv"
    path.write_bytes(raw)
    data_outcome(path)


@pytest.mark.parametrize("body, match", [
    (b"\xff\xfe" + "t,r_y1,u1,ü2,y1\n0,1,1,1,1\n".encode("utf-16-le"), r"not UTF-8 text \(byte \d+\)"),
    (b"t,r_y1,u1,\xfc2,y1\n0,1,1,1,1\n", r"not UTF-8 text \(byte 10\)"),
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1e999,1,1\n".encode(), r"line 3, column 'u1': expected a finite number"),
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1,1\n".encode(), r"line 3: expected 5 fields"),
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1,1,".encode(), r"line 3, column 'y1': expected a number, got ''"),
    ("t,r_y1,u1,ü2,y1\n1e308,1,1,1,1\n-1e308,1,1,1,1\n".encode(), r"line 3: t = -1e\+308 s goes back"),
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n" "0.5,\"1\n2\",1,1,1\n".encode(), r"line 3, column 'r_y1': expected a number"),
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1,1," + "9" * 200_000 + "\n", r"line 3: not valid CSV: a field longer than "
                                                                     r"131,072 characters: expected numbers$"),
    # A stray carriage return inside a line (the csv module's own words ask about "universal-newline mode").
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1\r,1,1\n1,1,1,1,1\n", r"line 3: not valid CSV: a carriage return \(\\r\) "
                                                           r"inside the line, outside quotes: expected lines ending in "
                                                           r"\\n or \\r\\n$"),
    # A stray far-off t: a gap no int64 counts (was a negative "rows lost" and overflow warnings).
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1,1,1\n1e19,1,1,1,1\n".encode(), r"line 4: t = 1e\+19 s lies 2e\+19 sample "
                                                                         r"times after the first sample"),
    # Python's float() reads these as 10 and 12; no export means them as numbers.
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1_0,1,1\n".encode(), r"line 3, column 'u1': expected a number, got '1_0'"),
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1,1,\u0661\u0662\n".encode(), r"line 3, column 'y1': expected a number"),
    ("t,r_y1,u1,ü2,y1\n0,1,1,1,1\n0.5,1,1,1,\uff11\n".encode(), r"line 3, column 'y1': expected a number"),
    # The line and character of a byte that is not UTF-8 (a Latin-1 degree sign in a cell).
    (b"t,r_y1,u1,\xc3\xbc2,y1\n0,1,1,1,1\n0.5,1,1,1,2\xb0\n", r"not UTF-8 text \(byte 38\) on line 3, character 12: "
                                                           r"expected a CSV file$"),
    # A quote left open in a column the model does not read: every line after it was one cell, the rest of the
    # log lost with exit 0 (3 of 5 rows read).
    ("t,r_y1,u1,ü2,y1,note\n0,1,1,1,1,\n0.5,1,1,1,1,\"stuck\n1,1,1,1,1,\n1.5,1,1,1,1,\n2,1,1,1,1,\n".encode(),
     r"line 3: not valid CSV: a quote \(\"\) opened on this line is never closed: the file ends inside it$"),
    # ... and in a long log, where the open cell passes the csv module's field limit first.
    ("t,r_y1,u1,ü2,y1,note\n0,1,1,1,1,\"stuck\n" + "".join(f"{k},1,1,1,1,\n" for k in range(1, 12_000)),
     r"line 2: not valid CSV: a quote \(\"\) opened on this line is not closed [\d,]+ lines further on, where the "
     r"quoted cell passes 131,072 characters: expected numbers$"),
    # A quoted cell over two lines: the lines after it keep their own numbers (line 5 was reported as 4).
    ("t,r_y1,u1,ü2,y1,note\n0,1,1,1,1,\"two\nlines\"\n0.5,1,1,1,1,\n1,1,x,1,1,\n".encode(),
     r"line 5, column 'u1': expected a number, got 'x'$"),
    # A header with another separator: what was read, and the separator.
    ("t;r_y1;u1;ü2;y1\n0;1;1;1;1\n".encode(), r"line 1 \(header\): missing columns 't', 'r_y1', 'u1', 'ü2', 'y1' "
                                             r"\(expected .*\); the header reads 't;r_y1;u1;ü2;y1', its columns "
                                             r"separated by semicolons: expected commas$"),
    # A character that does not print, escaped (a zero-width space before u1).
    ("t,r_y1,\u200bu1,ü2,y1\n0,1,1,1,1\n".encode(), r"missing column 'u1' \(expected .*\); the header reads "
                                                  r"'t,r_y1,\\u200bu1,ü2,y1'$"),
])
def test_edge_case_csv_refused_with_one_line(work, body, match):
    path = work / "edge.csv"
    path.write_bytes(body if isinstance(body, bytes) else body.encode())
    with pytest.raises(DataFileError, match=match) as info:
        read_csv(path, CSV_MODEL)
    assert_one_line_error(info.value, path)


def test_an_extra_column_named_in_latin_1_is_ignored_not_the_file(work):
    """Extra columns are ignored: one whose name is not UTF-8 (``temp\xb0C`` written in Latin-1) no longer
    refuses the whole file; it is unusable, named so.  A needed column named so is still refused."""
    good = "t,r_y1,u1,\u00fc2,y1\n" + "".join(f"{k * 0.5},1,{k % 3},1,{k % 5}\n" for k in range(6))
    lines = good.encode().split(b"\n")
    lines[0] += b",temp\xb0C"
    lines[1:] = [line + b",20.5" if line else line for line in lines[1:]]
    path = work / "latin1_extra.csv"
    path.write_bytes(b"\n".join(lines))
    data = read_csv(path, CSV_MODEL)
    assert data.n_samples == 6 and data.extra == {}
    assert data.unusable == {"temp\ufffdC": "its name in the header is not UTF-8 text"}
    path.write_bytes(good.encode().replace(b"u1", b"\xfc1", 1))
    with pytest.raises(DataFileError, match=r"not UTF-8 text \(byte \d+\)"):
        read_csv(path, CSV_MODEL)


# ------------------------------------------------------------------------------------------------
# Bags: whatever the bytes of the storage file or of metadata.yaml, every reader returns its data or
# raises a one-line BagError naming the bag; recover returns what it recovered or one line


def _logged(n=200, scale=1.0, seed=2) -> LoggedData:
    rng = np.random.default_rng(seed)
    m = GOOD_MODEL
    return LoggedData(t=100.0 + np.arange(n) * m.sample_time, r=rng.normal(size=(n, 2)) * scale,
                      u=rng.normal(size=(n, 2)) * scale, y=rng.normal(size=(n, 2)) * scale,
                      inputs=m.inputs, outputs=m.outputs, sample_time=m.sample_time)


@functools.lru_cache(maxsize=None)
def _good_bag(crc: bool) -> tuple:
    """``(storage file bytes, metadata.yaml bytes)`` of a small bag of :data:`GOOD_MODEL` (BagWriter's, in
    three chunks); without ``crc`` its chunks' CRCs set to 0 ("not computed", as rosbags' writer leaves
    them), so that damage inside a chunk reaches the records instead of the CRC check."""
    import tempfile

    from mpm_monitor.io.bags.mcap_records import CHUNK, CHUNK_CRC_OFFSET, MAGIC, mcap_records

    data = _logged(n=30)
    with tempfile.TemporaryDirectory() as d:
        write_logged_data(Path(d) / "src", data)
        msgs = read_raw_messages(Path(d) / "src", ["setpoint", "input", "output"])
        w = BagWriter(Path(d) / "bag", fsync=False)
        for k, m in enumerate(msgs):
            if not w.has_topic(m.topic):
                w.add_topic(m.topic, m.msgtype)
            w.write(m.topic, m.log_time, m.data)
            if k % 30 == 29:
                w.flush()
        w.close()
        raw = bytearray((Path(d) / "bag" / "bag.mcap").read_bytes())
        meta = (Path(d) / "bag" / "metadata.yaml").read_bytes()
    if not crc:
        for op, start, _ in list(mcap_records(bytes(raw), len(MAGIC), len(raw))):
            if op == CHUNK:
                struct.pack_into("<I", raw, start + CHUNK_CRC_OFFSET, 0)
    return bytes(raw), meta


def _bag_with(work, name: str, mcap: bytes, meta) -> Path:
    bag = work / name
    shutil.rmtree(bag, ignore_errors=True)
    bag.mkdir()
    (bag / "bag.mcap").write_bytes(mcap)
    if meta is not None:
        (bag / "metadata.yaml").write_bytes(meta)
    return bag


def assert_one_line_bag_error(exc: BaseException, bag) -> None:
    msg = str(exc)
    assert isinstance(exc, BagError), repr(exc)
    assert len(msg.splitlines()) == 1, f"not one line: {msg!r}"
    assert msg.startswith(f"{bag}"), msg


def bag_outcome(bag) -> None:
    """``read_bag`` with the model and ``read_bag_channels`` without: data, or one line naming the bag."""
    for read in (lambda: read_bag(bag, GOOD_MODEL), lambda: read_bag_channels(bag)):
        try:
            data = read()
        except BagError as exc:
            assert_one_line_bag_error(exc, bag)
        else:
            assert isinstance(data, LoggedData) and data.n_samples >= 1


def recover_outcome(work, bag) -> None:
    """``recover_bag`` of a bag without metadata.yaml: messages recovered into a bag that reads, or one
    line naming the storage file."""
    out = work / "recovered"
    shutil.rmtree(out, ignore_errors=True)
    notes = []
    try:
        n = recover_bag(bag, out, warn=notes.append)
    except BagError as exc:
        assert_one_line_bag_error(exc, bag)
        assert not out.exists()
        return
    assert n >= 1 and all(len(note.splitlines()) == 1 for note in notes)
    try:
        got = read_raw_messages(out, ["setpoint", "input", "output"])
    except BagError as exc:     # a topic none of whose messages survived
        assert_one_line_bag_error(exc, out)
    else:
        assert 1 <= len(got) <= n


#: A damaged storage file: of the bag with its chunks' CRCs, or of the bag without.
DAMAGED_MCAP = st.deferred(lambda: st.booleans().flatmap(lambda crc: damaged_bytes(_good_bag(crc)[0])))


@SETTINGS
@given(raw=DAMAGED_MCAP)
def test_damaged_storage_file_gives_data_or_a_one_line_error(work, raw):
    bag_outcome(_bag_with(work, "damaged_mcap", raw, _good_bag(True)[1]))


@SETTINGS
@given(meta=st.deferred(lambda: damaged_bytes(_good_bag(True)[1])))
def test_damaged_metadata_gives_data_or_a_one_line_error(work, meta):
    bag_outcome(_bag_with(work, "damaged_metadata", _good_bag(True)[0], meta))


@SETTINGS
@given(raw=DAMAGED_MCAP)
def test_recover_of_a_damaged_storage_file_gives_a_bag_or_a_one_line_error(work, raw):
    recover_outcome(work, _bag_with(work, "damaged_killed", raw, None))


# ------------------------------------------------------------------------------------------------
# The CLI: exit 2 and one line on stderr for every bad model, CSV or bag

@pytest.fixture(scope="module")
def files(work):
    """A good model, a good CSV and a good bag, plus malformed variants of each."""
    d = work / "cli"
    d.mkdir()
    out = {"model": d / "model.yaml", "csv": d / "data.csv", "bag": d / "bag"}
    save_model(GOOD_MODEL, out["model"])
    data = _logged()
    write_csv(out["csv"], data.t, data.r, data.u, data.y, data.inputs, data.outputs)
    write_logged_data(out["bag"], data)

    def bag_copy(name):
        p = d / name
        shutil.copytree(out["bag"], p)
        return p, next(p.glob("*.mcap"))

    p, mcap = bag_copy("truncated_bag")
    mcap.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    out["truncated_bag"] = p
    p, mcap = bag_copy("garbage_mcap")
    mcap.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 8)
    out["garbage_mcap"] = p
    p, mcap = bag_copy("no_mcap")
    mcap.unlink()
    out["no_mcap"] = p
    p, _ = bag_copy("latin1_metadata")
    (p / "metadata.yaml").write_bytes((p / "metadata.yaml").read_bytes() + b"# \xe9t\xe9\xff\n")
    out["latin1_metadata"] = p
    p, _ = bag_copy("garbage_metadata")
    (p / "metadata.yaml").write_text("rosbag2_bagfile_information: [1, 2\n", encoding="utf-8")
    out["garbage_metadata"] = p
    p, _ = bag_copy("scalar_metadata")       # YAML, but not rosbag2's: rosbags said "string indices must be ..."
    (p / "metadata.yaml").write_text("hi\n", encoding="utf-8")
    out["scalar_metadata"] = p
    p, _ = bag_copy("deep_metadata")         # nested past the parser's recursion: a traceback from our own check
    (p / "metadata.yaml").write_text("rosbag2_bagfile_information: " + "[" * 50000 + "]" * 50000 + "\n",
                                     encoding="utf-8")
    out["deep_metadata"] = p
    p, _ = bag_copy("python_tag_metadata")
    marker = d / "pwned"
    (p / "metadata.yaml").write_text(f"rosbag2_bagfile_information: !!python/object/apply:os.system ['touch {marker}']\n",
                                     encoding="utf-8")
    out["python_tag_metadata"] = p
    out["marker"] = marker
    out["empty_dir"] = d / "empty_dir"
    out["empty_dir"].mkdir()
    out["missing_dir"] = d / "missing_dir"
    # wrong schema: /output is a String topic
    wrong = BagWriter(d / "wrong_schema", fsync=False)
    from mpm_monitor.io.bags import default_typestore, joint_state_cdr
    ts = default_typestore()
    for t in ("/setpoint", "/input"):
        wrong.add_topic(t, "sensor_msgs/msg/JointState")
    wrong.add_topic("/output", "std_msgs/msg/String")
    string_msg = ts.types["std_msgs/msg/String"](data="y1")
    for k in range(20):
        stamp = int(1e9 * (100 + k))
        wrong.write("/setpoint", stamp, joint_state_cdr(ts, stamp, ("y1", "y2"), [0, 0]))
        wrong.write("/input", stamp, joint_state_cdr(ts, stamp, ("u1", "u2"), [0, 0]))
        wrong.write("/output", stamp, bytes(ts.serialize_cdr(string_msg, "std_msgs/msg/String")))
    wrong.close()
    out["wrong_schema"] = d / "wrong_schema"
    # JointState whose bytes are cut: right schema, undecodable message
    cut = BagWriter(d / "cut_messages", fsync=False)
    for t in ("/setpoint", "/input", "/output"):
        cut.add_topic(t, "sensor_msgs/msg/JointState")
    for k in range(20):
        stamp = int(1e9 * (100 + k))
        for t, names in (("/setpoint", ("y1", "y2")), ("/input", ("u1", "u2")), ("/output", ("y1", "y2"))):
            raw = joint_state_cdr(ts, stamp, names, [0, 0])
            cut.write(t, stamp, raw[: len(raw) // 2] if t == "/output" and k == 5 else raw)
    cut.close()
    out["cut_messages"] = d / "cut_messages"
    # bad model and CSV files
    out["bad_model"] = d / "bad_model.yaml"
    out["bad_model"].write_bytes(dump_model(GOOD_MODEL).encode()[:40])
    out["latin1_model"] = d / "latin1_model.yaml"
    out["latin1_model"].write_bytes(dump_model(GOOD_MODEL).replace("u1", "\xfc1").encode("latin-1"))
    out["evil_model"] = d / "evil_model.yaml"
    out["evil_model"].write_text(f"!!python/object/apply:os.system ['touch {marker}']\n", encoding="utf-8")
    out["ragged_csv"] = d / "ragged.csv"
    lines = out["csv"].read_text().splitlines(keepends=True)
    lines[7] = lines[7].rstrip("\n") + ",9\n"
    out["ragged_csv"].write_text("".join(lines), encoding="utf-8")
    out["truncated_csv"] = d / "truncated.csv"
    text = out["csv"].read_bytes()
    cut = text.index(b",", 2 * len(text) // 3) + 1   # a recording cut mid-line: the last line is short
    out["truncated_csv"].write_bytes(text[:cut])
    out["latin1_csv"] = d / "latin1.csv"
    out["latin1_csv"].write_bytes(text.replace(b"u1", b"\xfc1", 1))
    out["huge_csv"] = d / "huge.csv"
    big = _logged(scale=1e306)
    write_csv(out["huge_csv"], big.t, big.r, big.u, big.y, big.inputs, big.outputs)
    out["huge_t_csv"] = d / "huge_t.csv"
    write_csv(out["huge_t_csv"], [1.7e308, -1.7e308], big.r[:2], big.u[:2], big.y[:2], big.inputs, big.outputs)
    out["huge_gain_model"] = d / "huge_gain.yaml"
    save_model(GOOD_MODEL.replace(gain=np.full((2, 2), 1e250)), out["huge_gain_model"])
    return out


def _run_cli(capsys, argv):
    code = cli_main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


BAD_CLI_CASES = {
    "truncated model": (["--model", "bad_model", "--data", "csv"], r"bad_model\.yaml"),
    "latin-1 model": (["--model", "latin1_model", "--data", "csv"], r"not UTF-8 text \(byte \d+\)"),
    "python tag model": (["--model", "evil_model", "--data", "csv"], r"python/object"),
    "missing model": (["--model", "missing_dir", "--data", "csv"], r"cannot read model file"),
    "ragged csv": (["--model", "model", "--data", "ragged_csv"], r"ragged\.csv: line 8: expected 7 fields as in the header, got 8"),
    "truncated csv": (["--model", "model", "--data", "truncated_csv"], r"truncated\.csv: line \d+: expected 7 fields as in the header, got [1-6]"),
    "latin-1 csv": (["--model", "model", "--data", "latin1_csv"], r"not UTF-8 text"),
    "huge values csv": (["--model", "model", "--data", "huge_csv"], r"huge\.csv.*too large"),
    "huge gain model": (["--model", "huge_gain_model", "--data", "csv"], r"huge_gain\.yaml.*too large"),
    "huge t csv": (["--model", "model", "--data", "huge_t_csv"], r"huge_t\.csv: line 3: t = -1\.7e\+308 s goes back"),
    "truncated mcap": (["--model", "model", "--bag", "truncated_bag"], r"truncated_bag: "),
    "garbage mcap": (["--model", "model", "--bag", "garbage_mcap"], r"garbage_mcap: "),
    "no mcap file": (["--model", "model", "--bag", "no_mcap"], r"no_mcap: "),
    "latin-1 metadata": (["--model", "model", "--bag", "latin1_metadata"], r"latin1_metadata: "),
    "garbage metadata": (["--model", "model", "--bag", "garbage_metadata"], r"garbage_metadata: "),
    "python tag metadata": (["--model", "model", "--bag", "python_tag_metadata"], r"python_tag_metadata: "),
    "deep metadata": (["--model", "model", "--bag", "deep_metadata"], r"deep_metadata: cannot read bag: "),
    "scalar metadata": (["--model", "model", "--bag", "scalar_metadata"],
                        r"scalar_metadata: metadata\.yaml is not a rosbag2 bag's description: expected a mapping "
                        r"'rosbag2_bagfile_information'"),
    "empty dir": (["--model", "model", "--bag", "empty_dir"], r"empty directory"),
    "missing dir": (["--model", "model", "--bag", "missing_dir"], r"no such bag directory"),
    "wrong schema": (["--model", "model", "--bag", "wrong_schema"], r"topic '/output' has type std_msgs/msg/String"),
    "cut message": (["--model", "model", "--bag", "cut_messages"], r"topic '/output': message 6 cannot be decoded"),
}


@pytest.mark.parametrize("case", sorted(BAD_CLI_CASES))
def test_analyze_bad_input_exits_2_with_one_line(files, capsys, case):
    args, match = BAD_CLI_CASES[case]
    argv = ["analyze"] + [str(files[a]) if a in files else a for a in args] + ["--no-repair"]
    code, out, err = _run_cli(capsys, argv)
    assert code == 2, (code, err)
    assert len(err.splitlines()) == 1, err
    assert err.startswith("error: ") and "Traceback" not in err
    assert re.search(match, err), err
    assert not files["marker"].exists()


def test_analyze_good_input_runs(files, capsys):
    """Control for the cases above: the same files unspoilt give exit 0 and a JSON report."""
    for src in (["--data", str(files["csv"])], ["--bag", str(files["bag"])]):
        code, out, err = _run_cli(capsys, ["analyze", "--model", str(files["model"]), *src, "--json", "-",
                                           "--no-repair"])
        assert code == 0, err
        assert '"rows"' in out


@pytest.mark.parametrize("argv, flag, value", [
    (["simulate", "--case", "3.2", "--samples", "100"], "--seed", "-1"),
    (["simulate", "--case", "3.2", "--samples", "100"], "--seed", "1.5"),
    (["simulate", "--case", "3.2", "--samples", "100"], "--dither", "nan"),
    (["simulate", "--case", "3.2", "--samples", "100"], "--dither", "-0.1"),
    (["simulate", "--case", "3.2", "--samples", "100"], "--dither", "inf"),
    (["simulate", "--case", "3.2", "--samples", "100"], "--dither", "1e300"),    # written, then refused by every reader
    (["reproduce", "--case", "3.2", "--samples", "100"], "--seed", "-1"),
    (["demo", "--case", "3.2"], "--seed", "-7"),
])
def test_a_seed_or_dither_out_of_range_is_one_line(files, capsys, argv, flag, value):
    """A negative seed (numpy's generators refuse it: a traceback) or a dither amplitude that is not a finite
    number >= 0 (NaN and negative ones ran without a dither, silently): exit 2, one line naming the flag."""
    csv = files["csv"].parent / "simulated.csv"
    extra = ["--csv", str(csv)] if argv[0] == "simulate" else []
    with pytest.raises(SystemExit) as e:
        cli_main(argv + extra + [flag, value])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"error: argument {flag}: expected " in err and repr(value) in err, err
    assert not csv.exists()


@pytest.mark.parametrize("command, flag, value, expected", [
    ("analyze", "--alpha", "2", "expected a value in (0, 0.5), got 2.0"),
    ("analyze", "--max-delay", "-1", "expected a value in [0, 1000], got -1"),
    ("analyze", "--jobs", "0", "expected a value in [1, 64], got 0"),
    ("analyze", "--band", "3 1", "expected 0 <= low < high <= pi rad/sample, got [3.0, 1.0]"),
    ("reproduce", "--na", "-2", "expected a value in [0, 50], got -2"),
    ("analyze", "--candidates", "a,,b", "expected 'all' or NAME[,NAME...] of logged channels, got 'a,,b'"),
])
def test_an_analysis_option_out_of_range_is_named_by_its_flag(files, capsys, command, flag, value, expected):
    """The options' checks name them as the library does (``parameter max_delay: ...``, ``candidates: ...``); on the
    command line the message names the flag that was given (``--max-delay: ...``)."""
    src = (["--model", str(files["model"]), "--data", str(files["csv"])] if command == "analyze"
           else ["--case", "3.2", "--samples", "100"])
    code, out, err = _run_cli(capsys, [command, *src, flag, *value.split()])
    assert code == 2 and err == f"error: {flag}: {expected}\n", err


@pytest.mark.parametrize("flag,target,match", [
    ("--json", "missing_dir/r.json", r"--json .*missing_dir/r\.json: directory .*missing_dir does not exist"),
    ("--repair-out", "missing_dir/m.yaml", r"--repair-out .*: directory .*missing_dir does not exist"),
    ("--json", ".", r"--json .*: is a directory"),
    ("--json", "{csv}/r.json", r"--json .*/r\.json: .*\.csv is a file, not a directory$"),
    ("--report", "{csv}/d", r"--report .*/d: .*\.csv is a file, not a directory$"),
    ("--report", "{csv}", r"--report .*\.csv: is a file: expected a directory to write into$"),
])
def test_analyze_unwritable_output_is_refused_before_the_analysis(files, capsys, monkeypatch, flag, target, match):
    """An output path that cannot be written is one line and exit 2, before the log is even read (an
    analysis is not run only to be lost at the end)."""
    import mpm_monitor.io.csv_log as csv_mod

    def never(*a, **k):
        raise AssertionError("the log was read")

    monkeypatch.setattr(csv_mod, "read_csv", never)
    path = files["csv"].parent / target.format(csv=files["csv"].name)
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(files["model"]), "--data", str(files["csv"]),
                                       flag, str(path)])
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(match, err), err


@pytest.mark.parametrize("flag, target", [("--report", "/sys/kernel/mpm_report"), ("--json", "/sys/kernel/r.json")])
def test_an_output_in_a_directory_nothing_can_be_created_in_is_refused_first(files, capsys, monkeypatch, flag, target):
    """sysfs, where even root creates nothing (``os.access`` grants root everything): refused before the log
    is read, in one line, rather than after the analysis."""
    import mpm_monitor.io.csv_log as csv_mod

    def never(*a, **k):
        raise AssertionError("the log was read")

    monkeypatch.setattr(csv_mod, "read_csv", never)
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(files["model"]), "--data", str(files["csv"]),
                                       flag, target])
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(rf"{flag} {target}: (/sys/kernel is )?not writable", err), err


@pytest.mark.parametrize("argv", [
    ["analyze", "--model", "MODEL", "--data", ""],
    ["analyze", "--model", "", "--data", "CSV"],
    ["analyze", "--model", "MODEL", "--bag", " "],
    ["analyze", "--model", "MODEL", "--data", "CSV", "--json", ""],
    ["analyze", "--model", "MODEL", "--data", "CSV", "--repair-out", ""],
    ["analyze", "--model", "MODEL", "--data", "CSV", "--report", ""],
    ["export", "--bag", "", "--csv", "out.csv"],
])
def test_an_empty_path_is_refused_in_one_line(files, capsys, argv):
    """``--data "$UNSET"``: an empty path read as no data at all (a traceback down the bag's path), as the
    current directory (``--model``) or as no output (``--json``, written nowhere with exit 0)."""
    argv = [str(files["model"]) if a == "MODEL" else str(files["csv"]) if a == "CSV" else a for a in argv]
    with pytest.raises(SystemExit) as e:
        cli_main(argv)
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(r"error: argument --[a-z-]+: expected a file or directory path, got '\s*'$", err), err


def test_a_closed_output_pipe_ends_the_command_quietly(files):
    """``analyze ... | true``: the reader is gone before the summary is written; the command ends with the
    status of a command SIGPIPE ends (141) and nothing on stderr, not a BrokenPipeError traceback."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "mpm_monitor", "analyze", "--model", str(files["model"]),
                             "--data", str(files["csv"]), "--no-repair"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 141 and err == "", err


@pytest.mark.parametrize("target, match", [
    ("missing_dir/out.csv", r"^error: --csv .*missing_dir/out\.csv: directory .*missing_dir does not exist$"),
    (".", r"^error: --csv .*: is a directory: expected the path of a file to write$"),
])
def test_export_unwritable_csv_is_refused_before_the_bag_is_read(files, capsys, monkeypatch, target, match):
    import mpm_monitor.io.bags.read as bag_read

    def never(*a, **k):
        raise AssertionError("the bag was read")

    monkeypatch.setattr(bag_read, "open_reader", never)
    code, out, err = _run_cli(capsys, ["export", "--bag", str(files["bag"]), "--csv", str(files["csv"].parent / target)])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert re.search(match, err.strip()), err


def test_a_write_that_fails_after_the_analysis_is_one_line(files, capsys, monkeypatch):
    """A disk that fills (or a directory removed) between the check and the write: one line, exit 2."""
    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full)
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(files["model"]), "--data", str(files["csv"]),
                                       "--json", str(files["csv"].parent / "r.json"), "--no-repair"])
    assert code == 2 and err.strip() == f"error: --json {files['csv'].parent / 'r.json'}: cannot write: No space left on device"


@pytest.mark.parametrize("case", ["python tag model", "truncated mcap", "latin-1 metadata", "huge values csv",
                                  "huge t csv"])
def test_analyze_subprocess_exits_2_without_traceback(files, case):
    """The real entry point (``python -m mpm_monitor``): exit 2, exactly one stderr line."""
    args, match = BAD_CLI_CASES[case]
    argv = [str(files[a]) if a in files else a for a in args]
    env = dict(os.environ, PYTHONWARNINGS="default")
    proc = subprocess.run([sys.executable, "-m", "mpm_monitor", "analyze", *argv, "--no-repair"],
                          capture_output=True, text=True, timeout=60, cwd=REPO, env=env)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr and re.search(match, lines[0])
    assert not files["marker"].exists()


def test_a_lead_of_absurd_size_is_refused_in_one_line(files, capsys):
    """``lead: 1.0e300`` (a number since model files are read as YAML 1.2) raised the element's gain at
    high frequency beyond float range and the summary line crashed on a null error; now the scale
    check counts the lead's gain, |K| |lead| / (tau + tau2), and refuses in one line."""
    path = files["csv"].parent / "lead_huge.yaml"
    path.write_text(dump_model(GOOD_MODEL) + "lead: [[1.0e300, 0], [0, 0]]\n", encoding="utf-8")
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(path), "--data", str(files["csv"]), "--no-repair"])
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert re.search(r"with the high-frequency gain of element \(y1, u1\)'s lead \(gain x \|lead\| / its lags\) up "
                     r"to 2e\+299 in .*lead_huge\.yaml: too large for the analysis", err), err


def test_a_lag_or_lead_of_1e308_gives_no_numpy_warning_on_stderr(files, capsys, tmp_path):
    """A time constant of 1e308 s overflowed the settling time (numpy's warning on stderr, then "the analysis
    broke down numerically"): it is now a lag that never settles, analysed; a lead of 1e308 s is refused by
    the scale check in one line, without numpy's overflow warnings before it."""
    slow = tmp_path / "slow.yaml"
    save_model(GOOD_MODEL.replace(time_constant=np.array([[1e308, 1.0], [1.0, 1.0]])), slow)
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(slow), "--data", str(files["csv"]), "--no-repair"])
    assert code == 0 and err == "", err
    lead = tmp_path / "lead.yaml"
    save_model(GOOD_MODEL.replace(lead=np.array([[1e308, 0.0], [0.0, 0.0]])), lead)
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(lead), "--data", str(files["csv"])])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "too large for the analysis" in err, err


def test_a_huge_operating_point_is_named_as_the_model_s(files, capsys, tmp_path):
    """``output_nominal: [1e41]``: the log's setpoints (about 1) in deviations are 1e41, which was reported as
    the log's value alone; the message names the operating point it was taken from."""
    model = tmp_path / "nominal.yaml"
    save_model(GOOD_MODEL.replace(output_nominal=np.array([1e41, 0.0])), model)
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(model), "--data", str(files["csv"])])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert re.search(r"is 1e\+41 \(the logged value minus output_nominal 1e\+41 of .*\): too large", err), err


@pytest.mark.parametrize("argv, match", [
    (["export", "--bag", "BAG", "--csv", "BAG/out.csv", "--model", "MODEL"], r"--csv .*out\.csv: lies in the --bag input"),
    (["export", "--bag", "BAG", "--csv", "MODEL", "--model", "MODEL"], r"--csv .*model\.yaml: is the --model input"),
    (["analyze", "--model", "MODEL", "--data", "CSV", "--json", "CSV"], r"--json .*data\.csv: is the --data input"),
    (["analyze", "--model", "MODEL", "--data", "CSV", "--json", "MODEL"], r"--json .*model\.yaml: is the --model input"),
    # simulate wrote its log over its plant, or its controller model over the plant, without a word
    (["simulate", "--plant", "MODEL", "--model", "MODEL", "--csv", "MODEL", "--samples", "300"],
     r"--csv .*model\.yaml: is the --plant input"),
    (["simulate", "--plant", "MODEL", "--model", "MODEL", "--csv", "OUT.csv", "--write-model", "MODEL",
      "--samples", "300"], r"--write-model .*model\.yaml: is the --plant input"),
    (["simulate", "--case", "3.2", "--csv", "CSV", "--write-model", "CSV", "--samples", "300"],
     r"--write-model .*data\.csv: the same path as --csv"),
])
def test_an_output_onto_an_input_is_refused_before_any_work(files, capsys, tmp_path, argv, match):
    """``export --csv BAG/bag_0.mcap`` destroyed the recording, ``--csv M.yaml --model M.yaml`` the model."""
    import shutil

    bag = tmp_path / "bag"
    shutil.copytree(files["bag"], bag)
    model, csv = tmp_path / "model.yaml", tmp_path / "data.csv"
    shutil.copy(files["model"], model)
    shutil.copy(files["csv"], csv)
    before = {p: p.read_bytes() for p in (model, csv)}
    argv = [a.replace("BAG", str(bag)).replace("MODEL", str(model)).replace("CSV", str(csv)) for a in argv]
    code, out, err = _run_cli(capsys, argv)
    assert code == 2 and len(err.strip().splitlines()) == 1 and re.search(match, err), err
    assert {p: p.read_bytes() for p in (model, csv)} == before and not (bag / "out.csv").exists()


def test_a_csv_write_cut_short_leaves_no_shorter_log(tmp_path, monkeypatch):
    """An export interrupted while writing left a CSV of its complete lines, which reads as a valid, shorter
    log; the log is now written beside the file and renamed over it once complete."""
    import mpm_monitor.io.csv_log as csv_mod

    data = _logged()
    path = tmp_path / "log.csv"
    write_csv(path, data.t, data.r, data.u, data.y, data.inputs, data.outputs)
    whole = path.read_bytes()
    calls = {"n": 0}
    real = csv_mod._fmt

    def cut(v):
        calls["n"] += 1
        if calls["n"] > 50:
            raise KeyboardInterrupt
        return real(v)

    monkeypatch.setattr(csv_mod, "_fmt", cut)
    with pytest.raises(KeyboardInterrupt):
        write_csv(path, data.t, data.r, data.u, data.y, data.inputs, data.outputs)
    assert path.read_bytes() == whole and sorted(p.name for p in tmp_path.iterdir()) == ["log.csv"]
    with pytest.raises(KeyboardInterrupt):
        write_csv(tmp_path / "new.csv", data.t, data.r, data.u, data.y, data.inputs, data.outputs)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.csv"]


def test_a_command_started_with_its_output_closed_exits_with_its_code(files, tmp_path):
    """``export ... >&-``: sys.stdout is None, and the exit's flush of it was an AttributeError traceback (exit 1,
    also for bad input, which must exit 2)."""
    import subprocess
    import sys

    py = f"{sys.executable} -m mpm_monitor"
    ok = subprocess.run(["bash", "-c", f"{py} export --bag {files['bag']} --csv {tmp_path / 'o.csv'} >&-"],
                        capture_output=True, timeout=120)
    assert ok.returncode == 0 and b"Traceback" not in ok.stderr, ok.stderr
    bad = subprocess.run(["bash", "-c", f"{py} export --bag {tmp_path / 'nothing'} --csv {tmp_path / 'p.csv'} >&-"],
                         capture_output=True, timeout=120)
    assert bad.returncode == 2 and b"Traceback" not in bad.stderr and len(bad.stderr.strip().splitlines()) == 1, bad.stderr


@pytest.mark.parametrize("flags, match", [
    (["--json", "OUT", "--repair-out", "OUT"], r"--repair-out .*out: the same path as --json"),
    (["--json", "OUT", "--report", "OUT"], r"--report .*out: the same path as --json"),
    (["--repair-out", "OUT", "--report", "./OUT"], r"--report .*out: the same path as --repair-out"),
    # wrote the model as given, with exit 0 and no word
    (["--repair-out", "OUT", "--no-repair"], r"--repair-out .*out: there is no repaired model with --no-repair"),
])
def test_two_outputs_onto_one_path_are_refused_before_any_work(files, capsys, tmp_path, monkeypatch, flags, match):
    """``--json P --repair-out P`` wrote the report and then the repaired model over it, with exit 0; ``--json P
    --report P`` failed after the analysis on the directory it could not make."""
    monkeypatch.chdir(tmp_path)
    argv = ["analyze", "--model", str(files["model"]), "--data", str(files["csv"])] + \
        [str(tmp_path / "out") if a == "OUT" else ("./out" if a == "./OUT" else a) for a in flags]
    code, out, err = _run_cli(capsys, argv)
    assert code == 2 and len(err.strip().splitlines()) == 1 and re.search(match, err), err
    assert not (tmp_path / "out").exists()


def test_export_with_a_model_of_another_sample_time_warns(files, capsys, tmp_path):
    """An outside check: ``export --model`` with a sample time half the bag's wrote a CSV whose every row follows a
    gap, exit 0 and no word; ``analyze`` then refused that CSV.  The export now says so (a warning: the CSV is what
    the bag holds on that grid); an export on the right grid says nothing."""
    model = load_model(files["model"])
    half = tmp_path / "half.yaml"
    save_model(model.replace(sample_time=model.sample_time / 2), half)
    code, out, err = _run_cli(capsys, ["export", "--bag", str(files["bag"]), "--model", str(half),
                                       "--csv", str(tmp_path / "half.csv")])
    assert code == 0, err
    assert re.search(rf"warning: \d+ gaps in the samples on the model's grid of {model.sample_time / 2:g} s \(\d+ "
                     rf"missing\): every sample follows a gap, the bag's stamps a median {model.sample_time:g} s apart: "
                     rf"is the model's sample_time right\? \(analyze refuses such a log\)", err), err
    code, out, err = _run_cli(capsys, ["export", "--bag", str(files["bag"]), "--model", str(files["model"]),
                                       "--csv", str(tmp_path / "same.csv")])
    assert code == 0 and "gap" not in err, err


def test_recover_refuses_a_folder_of_two_recordings_and_a_file(files, capsys, tmp_path):
    """An outside check: ``runA_0.mcap`` and ``runB_0.mcap`` (a session a day later) in one folder were recovered into
    one bag, "recovered 6000 messages", without a word; ``--bag X/ok.mcap`` said "no .mcap file to recover"."""
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    mcap = next(Path(files["bag"]).glob("*.mcap"))
    shutil.copy(mcap, mixed / "runA_0.mcap")
    shutil.copy(mcap, mixed / "runB_0.mcap")
    with pytest.raises(BagError) as info:
        recover_bag(mixed, tmp_path / "out")
    assert str(info.value) == (f"{mixed}: holds the storage files of 2 recordings (runA_*.mcap, runB_*.mcap): expected "
                               f"one recording's NAME_0.mcap, NAME_1.mcap, ... (move the others to folders of their own)")
    assert not (tmp_path / "out").exists()
    with pytest.raises(BagError) as info:
        recover_bag(mixed / "runA_0.mcap", tmp_path / "out")
    assert str(info.value) == (f"{mixed / 'runA_0.mcap'}: is a file: expected the bag directory (the folder that holds "
                               f"its .mcap files)")
    (mixed / "runB_0.mcap").rename(mixed / "runA_1.mcap")      # one recording split in two: recovered
    assert recover_bag(mixed, tmp_path / "out") > 0
    # The recovered bag inside the damaged one's folder was taken (export --csv there is refused).
    code, out, err = _run_cli(capsys, ["recover", "--bag", str(mixed), "--out", str(mixed / "recovered")])
    assert code == 2 and err.strip() == (f"error: --out {mixed / 'recovered'}: lies in the --bag input {mixed}: expected "
                                         f"an output path apart from the inputs"), err
    assert not (mixed / "recovered").exists()


@pytest.mark.parametrize("name, role", [("report.html", "--model"), ("residuals.png", "--data"),
                                        ("report.html", "--json"), ("steps.png", "--repair-out"),
                                        ("detectability.png", "--json")])
def test_a_report_directory_that_would_overwrite_an_input_or_an_output_is_refused(files, capsys, tmp_path, name, role):
    """An outside check: ``--model DIR/report.html --data DIR/residuals.png --report DIR`` replaced both inputs with
    the HTML and a figure, and ``--json DIR/report.html --report DIR`` the JSON report, with exit 0 and no word (a
    stale steps.png or detectability.png is removed, as bad)."""
    report = tmp_path / "rep"
    report.mkdir()
    target = report / name
    argv = ["analyze", "--model", str(files["model"]), "--data", str(files["csv"]), "--report", str(report)]
    if role in ("--model", "--data"):
        shutil.copy(files["model" if role == "--model" else "csv"], target)
        argv[argv.index(role) + 1] = str(target)
    else:
        argv += [role, str(target)]
    before = target.read_bytes() if target.exists() else None
    code, out, err = _run_cli(capsys, argv)
    kind = "input" if role in ("--model", "--data") else "output"
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert err.strip() == (f"error: --report {report}: writes {name} there, which is the {role} {kind} {target}: "
                           f"expected a report directory apart from the inputs and the other outputs"), err
    assert (target.read_bytes() if target.exists() else None) == before
    assert sorted(p.name for p in report.iterdir()) == ([name] if before is not None else [])


def test_a_report_directory_in_the_bag_is_refused(files, capsys, tmp_path):
    """``--json BAG/x.json`` was refused ("lies in the --bag input"), ``--report BAG`` wrote six files into it."""
    bag = tmp_path / "bag"
    shutil.copytree(files["bag"], bag)
    listing = sorted(p.name for p in bag.iterdir())
    for report in (bag, bag / "report"):
        code, out, err = _run_cli(capsys, ["analyze", "--model", str(files["model"]), "--bag", str(bag),
                                           "--report", str(report)])
        where = "is" if report == bag else "lies in"
        assert code == 2 and err.strip() == (f"error: --report {report}: {where} the --bag input {bag}: expected an "
                                             f"output path apart from the inputs"), err
        assert sorted(p.name for p in bag.iterdir()) == listing


def test_an_output_through_a_symbolic_link_updates_the_file_it_points_to(files, capsys, tmp_path):
    """An outside check: ``--model model.yaml --repair-out model.yaml`` (an update in place), ``model.yaml`` a link
    to ``releases/v3/model.yaml``, replaced the link with a regular file and left the release's model as it was;
    ``--json`` and ``simulate --csv`` through a link did the same."""
    release = tmp_path / "releases" / "v3"
    release.mkdir(parents=True)
    shutil.copy(files["model"], release / "model.yaml")
    link = tmp_path / "model.yaml"
    link.symlink_to(Path("releases") / "v3" / "model.yaml")
    (release / "report.json").write_text("old", encoding="utf-8")
    json_link = tmp_path / "report.json"
    json_link.symlink_to(release / "report.json")
    before = (release / "model.yaml").stat().st_ino
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(link), "--data", str(files["csv"]),
                                       "--repair-out", str(link), "--json", str(json_link)])
    assert code == 0, err
    assert link.is_symlink() and json_link.is_symlink()
    assert (release / "report.json").read_text(encoding="utf-8").startswith("{")
    assert (release / "model.yaml").stat().st_ino != before          # replaced (renamed over), through the link
    csv_target = release / "log.csv"
    csv_link = tmp_path / "log.csv"
    csv_link.symlink_to(csv_target)                     # a link to a file not made yet
    code, out, err = _run_cli(capsys, ["simulate", "--case", "3.2", "--samples", "300", "--csv", str(csv_link)])
    assert code == 0, err
    assert csv_link.is_symlink() and csv_target.read_text(encoding="utf-8").startswith("t,")


def test_a_report_writes_only_the_files_the_cli_checks(files, tmp_path):
    """The names :func:`_report_apart` checks are every file :func:`write_report` writes."""
    from mpm_monitor.io.report import REPORT_FILES

    report = tmp_path / "rep"
    code = cli_main(["analyze", "--model", str(files["model"]), "--data", str(files["csv"]), "--report", str(report)])
    assert code == 0
    written = {p.name for p in report.iterdir()}
    assert written <= set(REPORT_FILES) and "report.html" in written and "residuals.png" in written


@pytest.mark.parametrize("k, value", [(5, 1e308), (120, -1e41)])
def test_a_single_sentinel_value_is_named_as_one_not_as_a_loop_that_diverged(files, capsys, tmp_path, k, value):
    """One output value of 1e308 early in a log was reported as "the loop diverged ... analyze the samples logged
    before it diverged" (five samples there); a few values far out of a channel's range that the log returns from
    are named as such."""
    data = _logged()
    y = data.y.copy()
    y[k, 0] = value
    path = tmp_path / "sentinel.csv"
    write_csv(path, data.t, data.r, data.u, y, data.inputs, data.outputs)
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(files["model"]), "--data", str(path)])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert re.search(rf"output .y1. at t = {100 + k:g} s is {re.escape(f'{abs(value):.3g}')}: too large .* while its other values stay "
                     r"within [0-9.]+ \(1 such value\): a bad-value sentinel\?", err), err
    assert "diverged" not in err


def test_topics_with_a_csv_are_refused_not_ignored(files, capsys):
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(files["model"]), "--data", str(files["csv"]),
                                       "--topics", "a", "b", "c"])
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--topics: names the topics of a --bag" in err, err


def test_simulate_names_both_files_when_plant_and_model_differ_in_shape_or_sample_time(files, capsys, tmp_path):
    """The refusal named neither flag nor file ("plant and controller model must have the same ...")."""
    model = load_model(files["model"])
    slower = tmp_path / "slower.yaml"
    save_model(model.replace(sample_time=model.sample_time / 2), slower)
    smaller = tmp_path / "smaller.yaml"
    save_model(PlantModel(sample_time=model.sample_time, inputs=("u1",), outputs=("y1",), gain=[[1.0]],
                          time_constant=[[5.0]], delay=[[0.0]]), smaller)
    for plant, match in ((slower, r"expected the same sample_time, got [\d.]+ s vs [\d.]+ s"),
                         (smaller, r"expected the same inputs and outputs, got \['u1'\] / \['y1'\] vs ")):
        code, out, err = _run_cli(capsys, ["simulate", "--plant", str(plant), "--model", str(files["model"]),
                                           "--csv", str(tmp_path / "log.csv"), "--samples", "300"])
        assert code == 2 and len(err.strip().splitlines()) == 1, err
        assert err.startswith(f"error: --plant {plant} and --model {files['model']}: ") and re.search(match, err), err
        assert not (tmp_path / "log.csv").exists()


def _with_operating_point(tmp_path, name, **nominals):
    """A 1x1 model with a measured disturbance, at the operating point ``nominals``, saved as ``name``."""
    model = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1",), disturbances=("feed",),
                       gain=[[2.0, 0.5]], time_constant=[[10.0, 15.0]], delay=[[2.0, 3.0]], **nominals)
    save_model(model, tmp_path / name)
    return tmp_path / name


def test_simulate_writes_the_log_at_the_model_files_operating_point(capsys, tmp_path):
    """``simulate --plant M --model M`` wrote the log in deviations and ``analyze`` with M subtracted M's operating
    point from it: the output offset by 30 (58 times its spread) with the plant equal to the model, and on an
    integrating output a ramp and a false element."""
    point = dict(input_nominal=[10.0], output_nominal=[50.0], disturbance_nominal=[350.0])
    model = _with_operating_point(tmp_path, "model.yaml", **point)
    flat = _with_operating_point(tmp_path, "flat.yaml")
    logs = {}
    for name, path in (("point", model), ("flat", flat)):
        logs[name] = tmp_path / f"{name}.csv"
        code, out, err = _run_cli(capsys, ["simulate", "--plant", str(path), "--model", str(path), "--csv",
                                           str(logs[name]), "--samples", "600", "--seed", "3"])
        assert code == 0, err
    data = read_csv(logs["point"], load_model(model))     # read_csv keeps the logged values
    same = read_csv(logs["flat"], load_model(flat))
    # The same loop (the same seed), its logged values at the operating point.
    np.testing.assert_allclose(data.u, same.u + 10.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(data.y, same.y + 50.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(data.r, same.r + 50.0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(data.dv, same.dv + 350.0, rtol=0, atol=1e-12)
    # Without an operating point the log is the deviations, as it always was.
    assert abs(float(np.mean(same.u))) < 5.0
    code, out, err = _run_cli(capsys, ["analyze", "--model", str(model), "--data", str(logs["point"])])
    assert code == 0, err
    assert "offset" not in out + err and "located elements: none" in out, out + err


def test_simulate_names_both_files_when_the_model_has_a_disturbance_the_plant_lacks(capsys, tmp_path):
    """An outside check: "controller model: measured disturbance(s) feed not among the plant's (none)" named
    neither file."""
    model = _with_operating_point(tmp_path, "model.yaml")
    plant = tmp_path / "plant.yaml"
    save_model(PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1",), gain=[[2.0]], time_constant=[[10.0]],
                          delay=[[2.0]]), plant)
    code, out, err = _run_cli(capsys, ["simulate", "--plant", str(plant), "--model", str(model), "--csv",
                                       str(tmp_path / "log.csv"), "--samples", "300"])
    assert code == 2 and err.strip() == (f"error: --plant {plant} and --model {model}: controller model: measured "
                                         f"disturbance(s) feed not among the plant's (none)"), err


@pytest.mark.parametrize("plant_point, model_point, expected", [
    (dict(input_nominal=[10.0]), dict(input_nominal=[12.0]), "input_nominal: u1 10 vs 12"),
    (dict(output_nominal=[50.0]), {}, "output_nominal: y1 50 vs 0"),
    (dict(disturbance_nominal=[350.0]), dict(disturbance_nominal=[300.0]), "disturbance_nominal: feed 350 vs 300"),
])
def test_simulate_refuses_a_plant_and_model_at_different_operating_points(capsys, tmp_path, plant_point, model_point,
                                                                          expected):
    plant = _with_operating_point(tmp_path, "plant.yaml", **plant_point)
    model = _with_operating_point(tmp_path, "model.yaml", **model_point)
    code, out, err = _run_cli(capsys, ["simulate", "--plant", str(plant), "--model", str(model), "--csv",
                                       str(tmp_path / "log.csv"), "--samples", "300"])
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"error: --plant {plant} and --model {model}: expected the same operating point"), err
    assert err.strip().endswith(f"got {expected}"), err
    assert not (tmp_path / "log.csv").exists()
