"""The report's indented JSON text is json.dumps(..., indent=2)'s, character for character."""

import json
import math

import numpy as np
import pytest

from mpm_monitor.apps.reproduce import simulate_case
from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.io.json_text import dumps_indented

AWKWARD = [
    {"a": [1, 2.5, True, None, float("nan")], "b": [], "c": {}, "d": [[1.0, 2.0], [float("inf")], [-math.inf]],
     "e": "\u00e9\"x\\ [ ] { } \n\t", "f": (1, 2), "g": [False, 0, 0.0], "h": [[], {}, [[]]], "": 3},
    [1.5, -0.0, 1e300, 5e-324, 1e16, 123456789.0, 0.1],
    [float("nan")], [1, 2, 3], ["x", "y"], [None], 7, 2.5, "text", None, True, [], {},
    {"nested": {"deeper": {"list": [{"k": [0.5]}]}}},
    [0, 0, 1, 0.25, -3, 1e300, 2 ** 70, float("nan"), -0.0, float("inf"), -math.inf, 5e-324],   # ints and floats
    {"step_response": [[[0, 0, 0.5, 1], [0, 1.25, 2, 2]], [[0, 0, 0, 0]]]},
]


@pytest.mark.parametrize("doc", AWKWARD)
@pytest.mark.parametrize("indent", [2, 4])
def test_the_same_text_as_json_dumps(doc, indent):
    assert dumps_indented(doc, indent) == json.dumps(doc, indent=indent)


def test_what_the_fast_path_does_not_write_is_left_to_json():
    # Keys that are not strings, and numpy scalars (a subclass of float and one that is not): json's own rules.
    for doc in ({1: 2, "a": [1.0]}, {"x": np.float64(0.25)}, [np.float64(1.5), 2.0], {"y": [np.int64(3)]},
                [1, np.float64(0.5)], [0, True, 1.5]):
        try:
            expected = json.dumps(doc, indent=2)
        except TypeError as exc:
            with pytest.raises(TypeError, match=str(exc).split(" ")[0]):
                dumps_indented(doc)
        else:
            assert dumps_indented(doc) == expected


def test_a_report_is_written_as_json_writes_it():
    case, data, _ = simulate_case("3.2", 1500, 3)
    doc = analyze(case.model, data, AnalysisOptions()).to_dict()
    assert dumps_indented(doc) == json.dumps(doc, indent=2)
