"""The model file's one-pass reading of one-line number lists (``model_file._parse_number_lists``).

A step-response model is mostly flow lists of numbers; they are read in one pass, not as a YAML node
per number.  Whatever the text, the values are those PyYAML's pure-Python loader (with the package's
YAML 1.2 resolvers) constructs from the text as written, and a text that loader refuses is refused.
The reference here is that loader (``model_file._LOADER``), independent of libyaml and of the
one-pass reading.
"""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mpm_monitor.core.errors import ModelFileError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io import model_file
from mpm_monitor.io.model_file import _NOT_PARSED, _parse_number_lists, _parse_yaml, dump_model, load_model


def _reference(text):
    """The pure-Python loader's value, or the YAMLError class it raises."""
    try:
        return yaml.load(text, Loader=model_file._LOADER)
    except yaml.YAMLError as exc:
        return type(exc)


def _same(a, b) -> bool:
    """Equal values of equal types (a NaN equals a NaN)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    if isinstance(a, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return a == b


def _parsed(text):
    try:
        return _parse_yaml(text)
    except yaml.YAMLError as exc:
        return type(exc)


NUMBERS = ["0", "1", "-3", "+7", "010", "2.5", "-0.125", "1.", ".5", "-.5", "1e3", "1E-05", "2.5e+2", ".inf",
           "-.Inf", "+.INF", ".nan", ".NaN", "12345678901234567890123", "1" + "0" * 400, "-1e400"]
#: Mostly numbers (a list of them is read in one pass), sometimes a token that makes the list YAML's.
TOKENS = NUMBERS * 6 + ["1_000", "0x1F", "1:30", "yes", "true", "~", "1 2", "'3'", "\"4\"", "- 1", ""]


@st.composite
def number_list(draw):
    tokens = draw(st.lists(st.sampled_from(TOKENS), min_size=0, max_size=6))
    seps = [draw(st.sampled_from([",", ", ", " ,", " , ", ",  ", ",\n  ", " ,\n", ",\r\n    ", "\n,", ",\n"]))
            for _ in tokens]
    body = "".join(t + s for t, s in zip(tokens, seps))
    if tokens and draw(st.booleans()):
        body = body.rstrip(", ")            # no trailing comma
    return "[" + draw(st.sampled_from(["", " "])) + body + "]"


#: Places a list can stand in a text, some of them where it is not a list (a string, a comment, a key).
CONTEXTS = [
    "a: {L}\n",
    "a: [{L}, {L}]\n",
    "a:\n  - {L}\n  - {L}   # {L}\n",
    "a: &x {L}\nb: *x\n",
    "a: !!seq {L}\n",
    "a: \"x {L}\"\n",
    "a: 'x {L}'\n",
    "a: x {L}\n",
    "a: |\n  {L}\n",
    "# {L}\na: 1\n",
    "{L}: 1\n",
    "a: {{b: {L}}}\n",
    "a: {L}3\n",
    "a: {L} 3\n",
    "a: {L}{L}\n",
    "a: [{L},\n    {L}]\n",
    "a: [\n  {L}\n]\n",
    "a: !mpm_monitor_numbers 0\n",
    "a: {L}\nb: !mpm_monitor_numbers 0\n",
    "%TAG ! tag:example.com,2000:\n---\na: {L}\n",
    "a: {L}\na: {L}\n",
    "a:\n- {L}\n  - {L}\n",
    "a:\n  - {L}\n  - {L}\nb: [{L},\n{L}]\n",
    "a:\n  b: {L}\nc: {L} # {L}\n",
    "- {L}\n---\n- {L}\n",
]


@settings(max_examples=600, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck))
@given(st.sampled_from(CONTEXTS), st.lists(number_list(), min_size=4, max_size=4))
def test_the_values_are_the_careful_loaders_whatever_the_text(context, lists):
    text = context.format(L="{L}").replace("{L}", "\0")
    for lst in lists:
        text = text.replace("\0", lst, 1)
    text = text.replace("\0", "[]")
    ref = _reference(text)
    got = _parsed(text)
    if isinstance(ref, type):
        assert got is not None and isinstance(got, type) and issubclass(got, yaml.YAMLError), (text, got)
    else:
        assert _same(got, ref), (text, got, ref)


@pytest.mark.parametrize("text", [
    "a: [0, -0.1842, 1e-3, .5, 1., +2, -.inf, .NaN]\n",
    "a: [[1, 2], [3, 4.5,]]   # row [5, 6]\n",
    "a: &x [1, 2]\nb: [*x, *x]\n",
    "# [1, 2]\na: [3]  # [4]\n",                 # a comment's list is left as written
    "a: 'x # [1]'\nb: [2]\n",
    "a: [0, 1,\n  2.5, 3]\nb:\n  - [[1,\n2], [3,\r\n 4]]\n",   # lists over several lines, as PyYAML wraps them
])
def test_the_one_pass_reading_is_taken_and_gives_the_careful_values(text):
    fast = _parse_number_lists(text)
    assert fast is not _NOT_PARSED
    assert _same(fast, _reference(text))


def test_an_alias_of_a_list_is_the_same_object_as_in_yaml():
    data = _parse_number_lists("a: &x [1, 2]\nb: *x\n")
    assert data["a"] is data["b"] and data["a"] == [1, 2]


@pytest.mark.parametrize("text", [
    "a: \"[1, 2]\"\n",                        # inside a string
    "a: x [1, 2]\n",                          # inside a longer plain scalar
    "a: |\n  [1, 2]\nb: [3]\n",               # inside a block string
    "a: [1, 2]3\n",                           # a YAML error around it
    "a: [1, 2]\nb: !mpm_monitor_numbers 0\n",  # the tag already in the text
    "[1, 2]: 1\n",                            # a list as a key
    "a: x [1,\n  2]\n",                      # inside a plain scalar folded over two lines
    "a: \"[1,\n  2]\"\n",                  # inside a quoted string over two lines
])
def test_a_list_the_parse_does_not_construct_as_written_leaves_the_text_to_yaml(text):
    assert _parse_number_lists(text) is _NOT_PARSED
    assert _same(_parsed(text), _reference(text))


def test_a_step_response_model_is_read_in_one_pass_and_loads_the_same(tmp_path: Path):
    rng = np.random.default_rng(4)
    coef = np.cumsum(rng.normal(size=(3, 2, 25)), axis=2)
    coef[..., 0] = 0.0
    model = PlantModel.from_step_response(2.0, ("u1", "u2"), ("y1", "y2", "y3"), coef)
    text = dump_model(model)
    assert _parse_number_lists(text) is not _NOT_PARSED
    assert _same(_parse_number_lists(text), _reference(text))
    path = tmp_path / "m.yaml"
    path.write_text(text)
    back = load_model(path)
    np.testing.assert_array_equal(back.step_response, coef)


@pytest.mark.parametrize("entry, message", [
    ("true", "row 1, column 2, coefficient 2: expected a number, got True"),
    ("'0.5'", "row 1, column 2, coefficient 2: expected a number, got '0.5'"),
    ("1" + "0" * 400, "row 1, column 2, coefficient 2: expected a finite number, got an integer of 401 digits"),
])
def test_a_coefficient_that_is_not_a_number_is_named_as_before(tmp_path: Path, entry, message):
    path = tmp_path / "m.yaml"
    path.write_text("sample_time: 1\ninputs: [u1, u2]\noutputs: [y1]\nstep_response:\n  length: 3\n"
                    f"  coefficients:\n  - [[0, 1, 2], [0, {entry}, 2]]\n")
    with pytest.raises(ModelFileError) as err:
        load_model(path)
    assert str(err.value) == f"{path}: key 'step_response': {message}"


def test_the_alias_count_still_refuses_a_billion_laughs(tmp_path: Path):
    lines = ["a0: &a0 [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]"]
    lines += [f"a{k}: &a{k} [{', '.join([f'*a{k - 1}'] * 10)}]" for k in range(1, 9)]
    path = tmp_path / "m.yaml"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ModelFileError, match="aliases expand to more than"):
        load_model(path)


def test_the_load_bench_runs_and_reads_back_the_model_it_wrote():
    from bench import model_load

    out = model_load.run([(2, 3)], [5], repeats=1, log=lambda *_: None)
    (cell,) = out["cells"]
    assert (cell["outputs"], cell["inputs"], cell["length"], cell["numbers"]) == (2, 3, 5, 30)
    assert cell["load_s"] > 0 and len(cell["runs_s"]) == 1


def test_the_load_bench_times_analyze_on_both_forms_of_a_model():
    from bench import model_load

    out = model_load.run_analyze(2, 2, repeats=1, log=lambda *_: None)
    assert out["length"] > 100 and set(out["runs_s"]) == {"parametric", "step_response"}
    # The controller's (y1, u2) gain is 30 % off: both forms locate it.
    assert out["located"]["parametric"] == out["located"]["step_response"] == ["y1:u2"]
