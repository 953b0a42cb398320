"""Every analysis option described once (core/options.py, AnalysisOptions): its ParamSpec is the one check,
and the command line's flags and the monitor node's parameters are generated from it.

The flag names, parameter names and defaults asserted here are the interface documented in the README
(command-line table, monitor parameter table): they must not change when the specs are edited.
"""

import dataclasses
import math
import os

import numpy as np
import pytest

from mpm_monitor.apps.cli import build_parser
from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.analysis_options import ANALYSIS_PARAMS
from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.core.options import ParamSpec


def test_open_ranges_and_array_lengths():
    rate = ParamSpec("alpha", "double", 0.01, "x", 0.0, 0.5, open_low=True, open_high=True)
    assert rate.range_text() == "(0, 0.5)" and rate.check(0.25) == 0.25 and rate.check(np.float32(0.5 - 1e-3)) > 0
    for bad in (0.0, 0.5, -1.0):
        with pytest.raises(ConfigurationError, match=r"parameter alpha: expected a value in \(0, 0.5\)"):
            rate.check(bad)
    band = ParamSpec("band", "double_array", (0.0, 1.0), "x", 0.0, 1.0, length=2)
    assert band.check((0.25, 1)) == [0.25, 1.0]
    with pytest.raises(ConfigurationError, match="expected 2 numbers"):
        band.check([0.1, 0.2, 0.3])
    with pytest.raises(ConfigurationError, match=r"expected values in \[0, 1\]"):
        band.check([0.1, 1.5])
    assert ParamSpec("n", "int", 1, "x", 1, 10).check(np.int64(3)) == 3


def test_every_analysis_option_has_its_spec_with_the_dataclass_default():
    fields = {f.name: f.default for f in dataclasses.fields(AnalysisOptions)}
    assert list(ANALYSIS_PARAMS) == list(fields)
    for name, spec in ANALYSIS_PARAMS.items():
        assert spec.default == fields[name] and spec.description.endswith(".")
        assert (spec.check(spec.default) is None) == (spec.default is None)
    assert {n: s.kind for n, s in ANALYSIS_PARAMS.items()} == {
        "na": "int", "max_na": "int", "nb": "int", "alpha": "double", "band": "double_array", "n_freq": "int", "max_delay": "int",
        "initial_state": "string", "method": "string", "repair": "bool", "collinearity_threshold": "double",
        "test_all_rows": "bool", "element_window": "string", "element_response": "bool",
        "confirm_responses": "bool", "release_explained": "bool", "release_quiet_rows": "bool",
            "repair_again": "bool", "drop_spikes": "bool",
        "max_gap": "int",
        "jobs": "int"}


def test_options_are_converted_to_their_types_and_checked_by_the_specs():
    o = AnalysisOptions(na=np.int64(3), n_freq=64.0, band=[0.1, 1], alpha=np.float64(0.05))
    assert type(o.na) is int and type(o.n_freq) is int and o.band == (0.1, 1.0) and type(o.alpha) is float
    assert hash(o) == hash(AnalysisOptions(na=3, n_freq=64, band=(0.1, 1.0), alpha=0.05))
    for kw, match in [({"repair": "yes"}, "repair"), ({"band": (0.0, 4.0)}, "band"), ({"band": (0.5, 0.5)}, "band"),
                      ({"max_delay": -1}, "max_delay"), ({"collinearity_threshold": 1.0}, "collinearity_threshold"),
                      ({"element_window": "half"}, "element_window"), ({"na": True}, "na")]:
        with pytest.raises(ConfigurationError, match=match):
            AnalysisOptions(**kw)


def parallel_cpus() -> int:
    """The cores this process may run on, read here independently of the package."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _option_flags(parser, command):
    sub = next(a for a in parser._actions if a.dest == "command").choices[command]
    return {flag: a for a in sub._actions for flag in a.option_strings}


@pytest.mark.parametrize("command", ["analyze", "reproduce"])
def test_cli_analysis_flags_keep_their_names_and_defaults(command):
    parser = build_parser()
    flags = _option_flags(parser, command)
    expected = {"--method": "arx", "--alpha": 0.01, "--na": 4, "--nb": 4, "--band": (0.0, math.pi),
                "--initial-state": "estimate", "--no-repair": True, "--no-element-response": True}
    for flag, default in expected.items():
        assert flag in flags, flag
        assert flags[flag].default == default, flag
    assert flags["--band"].nargs == 2 and flags["--band"].metavar == ("LOW", "HIGH")
    assert flags["--method"].choices == ("arx", "xcorr", "pcorr")
    assert flags["--initial-state"].choices == ("estimate", "zero")
    from mpm_monitor.apps.cli import _analysis_options

    head = ["analyze", "--model", "m.yaml", "--data", "d.csv"] if command == "analyze" else \
        ["reproduce", "--case", "3.1"]
    from mpm_monitor.core.parallel import default_jobs

    # The command's one default of its own: the processes, 2 where the machine gives it two cores.
    assert flags["--jobs"].default is None and default_jobs() == min(2, parallel_cpus())
    assert _analysis_options(parser.parse_args(head)) == AnalysisOptions(jobs=default_jobs())
    assert _analysis_options(parser.parse_args(head + ["--jobs", "1"])) == AnalysisOptions()
    given = _analysis_options(parser.parse_args(head + ["--band", "0.1", "2", "--no-repair", "--alpha", "0.05",
                                                        "--na", "2", "--nb", "3", "--initial-state", "zero",
                                                        "--method", "pcorr", "--no-element-response", "--jobs", "2"]))
    assert given == AnalysisOptions(band=(0.1, 2.0), repair=False, alpha=0.05, na=2, nb=3, initial_state="zero",
                                    method="pcorr", element_response=False, jobs=2)


def test_monitor_node_analysis_parameters_keep_their_names_and_defaults():
    pytest.importorskip("rclpy")
    from mpm_monitor.nodes.monitor_node import PARAMS, analysis_options_from_params

    specs = {s.name: s for s in PARAMS}
    expected = {"alpha": 0.01, "na": 4, "nb": 4, "band_low": 0.0, "band_high": math.pi, "n_freq": 256,
                "max_delay": -1, "method": "arx", "initial_state": "estimate", "repair": True}
    names = [s.name for s in PARAMS]
    assert names[names.index("alpha"):names.index("alpha") + len(expected)] == list(expected)
    assert {n: specs[n].default for n in expected} == expected
    assert (specs["max_delay"].low, specs["max_delay"].high) == (-1, 1000)
    assert (specs["band_high"].kind, specs["band_high"].high) == ("double", math.pi)
    assert specs["alpha"].description == ANALYSIS_PARAMS["alpha"].description
    defaults = {s.name: s.default for s in PARAMS}
    assert analysis_options_from_params(defaults) == AnalysisOptions()
    given = dict(defaults, band_low=0.2, band_high=1.0, max_delay=7, repair=False)
    assert analysis_options_from_params(given) == AnalysisOptions(band=(0.2, 1.0), max_delay=7, repair=False)
    with pytest.raises(ConfigurationError, match="alpha"):
        specs["alpha"].check(0.5)


def test_a_string_parameter_of_choices_names_them_for_a_value_of_another_type():
    """``-p case:=true`` said 'expected a string, got True', without the choices a wrong string gets."""
    case = ParamSpec("case", "string", "", "x", choices=("", "3.1", "level"))
    for bad, shown in ((True, "True"), ("9.9", "'9.9'")):
        with pytest.raises(ConfigurationError, match=rf"^parameter case: expected one of '', '3.1', 'level', got {shown}$"):
            case.check(bad)
    with pytest.raises(ConfigurationError, match=r"^parameter name: expected a string, got True$"):
        ParamSpec("name", "string", "", "x").check(True)
