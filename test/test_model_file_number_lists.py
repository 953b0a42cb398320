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


@pytest.mark.parametrize("text", [
    "- - .inf\n  - 0\n",                             # the first item, on its parents' line, infinite
    "a:\n- - -.Inf\n  - .nan\n",
    "a: [1, " + "1" * 5000 + "]\n",                  # an int Python will not convert from text
    "a:\n- 1\n- " + "2" * 5000 + "\n",
])
def test_numbers_the_conversion_must_treat_apart_give_the_careful_result(text):
    assert _same(_parsed(text), _reference(text))


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
    ("true", "row 1 (y1), column 2 (u2), coefficient 2: expected a number, got True"),
    ("'0.5'", "row 1 (y1), column 2 (u2), coefficient 2: expected a number, got '0.5'"),
    ("1" + "0" * 400, "row 1 (y1), column 2 (u2), coefficient 2: expected a finite number, got an integer of 401 digits"),
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
    block = model_load.run([(2, 3)], [5], repeats=1, log=lambda *_: None, block=True)
    assert block["style"] == "block" and block["cells"][0]["numbers"] == 30


def test_the_load_bench_times_analyze_on_both_forms_of_a_model():
    from bench import model_load

    out = model_load.run_analyze(2, 2, repeats=1, log=lambda *_: None)
    assert out["length"] > 100 and set(out["runs_s"]) == {"parametric", "step_response"}
    # The controller's (y1, u2) gain is 30 % off: both forms locate it.
    assert out["located"]["parametric"] == out["located"]["step_response"] == ["y1:u2"]


# ------------------------------------------------------------------------ block style (yaml.safe_dump's)
_plain_numbers = st.one_of(st.integers(-10 ** 6, 10 ** 6), st.floats(allow_nan=False, width=64).filter(
    lambda x: abs(x) < 1e300), st.sampled_from([float("inf"), -float("inf")]))
_values = st.recursive(
    st.one_of(_plain_numbers, _plain_numbers, _plain_numbers, _plain_numbers,
              st.sampled_from(["a", "b c", "1_0", "- 1", "x:"]), st.booleans()),
    lambda inner: st.one_of(st.lists(inner, min_size=1, max_size=4),
                            st.dictionaries(st.sampled_from(["k", "key", "coefficients", "x y"]), inner,
                                            min_size=1, max_size=3)),
    max_leaves=30)


@st.composite
def block_text(draw):
    """A YAML text in block style (yaml.safe_dump's default), sometimes edited by hand: a comment or a
    blank line inserted, a line's indentation changed, a line dropped, Windows line ends."""
    text = yaml.safe_dump(draw(_values), default_flow_style=False, sort_keys=False)
    lines = text.split("\n")
    for _ in range(draw(st.integers(0, 2))):
        k = draw(st.integers(0, len(lines) - 1))
        edit = draw(st.sampled_from(["comment", "blank", "indent", "dedent", "drop", "trailing comment"]))
        if edit == "comment":
            lines.insert(k, " " * draw(st.integers(0, 6)) + "# note")
        elif edit == "blank":
            lines.insert(k, "")
        elif edit == "indent":
            lines[k] = "  " + lines[k]
        elif edit == "dedent" and lines[k].startswith("  "):
            lines[k] = lines[k][2:]
        elif edit == "drop":
            del lines[k]
        elif edit == "trailing comment" and lines[k]:
            lines[k] += "  # c"
    text = "\n".join(lines)
    return text.replace("\n", "\r\n") if draw(st.booleans()) else text


@settings(max_examples=500, derandomize=True, deadline=None, suppress_health_check=list(HealthCheck))
@given(block_text())
def test_block_style_values_are_the_careful_loaders_whatever_the_text(text):
    ref = _reference(text)
    got = _parsed(text)
    if isinstance(ref, type):
        assert isinstance(got, type) and issubclass(got, yaml.YAMLError), (text, got)
    else:
        assert _same(got, ref), (text, got, ref)


def test_a_step_response_model_in_block_style_is_read_in_one_pass(tmp_path: Path):
    rng = np.random.default_rng(5)
    coef = np.cumsum(rng.normal(size=(3, 2, 25)), axis=2)
    coef[..., 0] = 0.0
    model = PlantModel.from_step_response(2.0, ("u1", "u2"), ("y1", "y2", "y3"), coef)
    text = yaml.safe_dump(model.to_dict(), sort_keys=False)
    assert "[" not in text                                  # block style throughout
    lists: list = []
    assert model_file._replace_block_lists(text, lists).count("!mpm_monitor_numbers") == 6 == len(lists)
    assert _same(_parse_number_lists(text), _reference(text))
    path = tmp_path / "m.yaml"
    path.write_text(text)
    np.testing.assert_array_equal(load_model(path).step_response, coef)


@pytest.mark.parametrize("text", [
    "a:\n- 1\n- 2\n- x\n",                          # the sequence goes on with a string
    "a:\n- 1\n# c\n- 2\n",                          # a comment inside it
    "a:\n- 1\n- 2  # c\n",                          # a comment on an item
    "a:\n- - 1\n  - 2\n  - b\n",                   # a nested one that goes on
    "a:\n- 1\n- 2\n  - 3\n",                        # a line after it indented more
    "a: x\n- 1\n- 2\n",                             # not a key's value (a YAML error)
    "a: # c\n- 1\n- 2\n",                           # a key with a comment: not looked into
    "a: x #:\n- 1\n- 2\n",                          # a ':' that ends a comment
    "a:\n  k:\n- 1\n- 2\n",                         # a key indented more than the run
    "ab- 1\n  - 2\n",                               # the line before holds more than '- ' markers
    "n: '[x]'\na:\n- 1\n- 2\n",                     # a bracket anywhere: left to YAML
])
def test_a_block_run_that_may_not_be_a_whole_sequence_of_numbers_is_left_to_yaml(text):
    lists: list = []
    assert model_file._replace_block_lists(text, lists) == text and not lists
    assert _same(_parsed(text), _reference(text))


def test_a_block_run_replaced_inside_a_block_string_is_never_read_as_numbers():
    text = "a: |\n  k:\n  - 1\n  - 2\nb: 1\n"
    assert model_file._replace_block_lists(text, []) != text        # it looks like a key's sequence
    assert _parse_number_lists(text) is _NOT_PARSED                  # but is not read as one
    assert _parsed(text) == {"a": "k:\n- 1\n- 2\n", "b": 1}
