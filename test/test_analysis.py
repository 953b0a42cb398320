"""The detection: S_Delta row test and Delta element test on simulated closed loops.

The located rows and elements are compared with the ground truth of the simulation (the plant and
model differ exactly in the listed elements).  The full seed count is in bench/monte_carlo.py.
"""

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.errors import ConfigurationError, DataFileError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.io.csv_log import write_log_csv
from mpm_monitor.io.model_file import save_model
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import ExcitationOptions, run_closed_loop
from mpm_monitor.sim.excitation import PrbsOptions

FAST = AnalysisOptions(repair=False)


def _run_case(name, seed, samples=3000, excitation=None):
    case = paper_case(name)
    log = run_closed_loop(case.plant, case.model, samples, seed=seed, mpc=case.mpc,
                          excitation=excitation or case.excitation, disturbance=case.disturbance)
    return case, log.as_logged_data()


@pytest.mark.parametrize("name", ["3.1", "3.2", "3.3"])
@pytest.mark.parametrize("seed", [11, 12])
def test_paper_cases_locate_exactly_the_mismatch(name, seed):
    case, data = _run_case(name, seed)
    report = analyze(case.model, data, FAST)
    assert set(report.flagged_rows) == set(case.mismatched_rows)
    assert set(report.located_elements) == set(case.mismatched_elements)
    assert not report.ambiguous_elements


def test_rsi_near_one_without_mismatch_and_above_one_with():
    case, data = _run_case("3.1", 3)
    rep = analyze(case.model, data, FAST)
    assert all(abs(r.rsi - 1.0) < 0.05 for r in rep.rows)
    case, data = _run_case("3.2", 3)
    rep = analyze(case.model, data, FAST)
    rsi = {r.output: r.rsi for r in rep.rows}
    assert rsi["y1"] > 1.2 and rsi["y2"] > 1.08 and abs(rsi["y3"] - 1.0) < 0.05


def test_row_test_false_alarm_rate_is_calibrated():
    """Raw row p-values on mismatch-free data are uniform: P(p < 0.1) ~ 0.1 (binomial bound)."""
    case = paper_case("3.1")
    p = []
    for seed in range(12):
        log = run_closed_loop(case.plant, case.model, 1500, seed=200 + seed, mpc=case.mpc,
                              excitation=case.excitation, disturbance=case.disturbance)
        p += [r.p_value_raw for r in analyze(case.model, log.as_logged_data(), FAST).rows]
    hits = int(np.sum(np.array(p) < 0.1))
    # binomial(36, 0.1): mean 3.6, sd 1.8
    assert hits <= 3.6 + 4 * 1.8


def test_collinear_inputs_give_ambiguity_not_a_wrong_element():
    """Case 3.3 without dither: the MPC drives u2 and u5 identically; never guess between them."""
    case, data = _run_case("3.3", 5, excitation=ExcitationOptions())
    rep = analyze(case.model, data, FAST)
    truth = set(case.mismatched_elements)
    assert set(rep.located_elements) <= truth          # nothing wrong is located
    assert rep.ambiguous_elements
    amb = {e.input for e in rep.elements if e.ambiguous}
    assert {"u2", "u5"} <= amb
    assert any("move together" in w for w in rep.warnings)
    assert rep.collinear_groups


def _random_model(ny, nu, rng):
    return PlantModel(1.0, [f"u{j + 1}" for j in range(nu)], [f"y{i + 1}" for i in range(ny)],
                      gain=rng.uniform(0.5, 3, (ny, nu)) * rng.choice([-1, 1], (ny, nu)),
                      time_constant=rng.uniform(10, 60, (ny, nu)),
                      delay=rng.integers(1, 6, (ny, nu)).astype(float))


@pytest.mark.parametrize("ny,nu,dither", [(7, 3, None), (3, 7, 0.3)])
def test_non_square_plants(ny, nu, dither):
    rng = np.random.default_rng(ny * 10 + nu)
    plant = _random_model(ny, nu, rng)
    i2 = min(4, ny - 1)
    model = plant.with_element(1, 0, gain=plant.gain[1, 0] * 1.5).with_element(
        i2, 2, time_constant=plant.time_constant[i2, 2] * 2)
    exc = ExcitationOptions(dither=None if dither is None else PrbsOptions(amplitude=dither))
    log = run_closed_loop(plant, model, 4000, seed=1, excitation=exc)
    rep = analyze(model, log.as_logged_data(), FAST)
    assert set(rep.located_elements) == {("y2", "u1"), (f"y{i2 + 1}", "u3")}
    assert set(rep.flagged_rows) == {"y2", f"y{i2 + 1}"}


def test_deterministic():
    case, data = _run_case("3.2", 4, samples=1500)
    a = analyze(case.model, data, FAST).to_dict()
    b = analyze(case.model, data, FAST).to_dict()
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


def test_the_row_table_stays_aligned_with_long_output_names():
    # An output name longer than the row column (10 characters) widened its line only: "bottom_temp    1.003".
    case, data = _run_case("3.2", 4, samples=1500)
    names = ("bottom_temperature", "y2", "top_pressure")
    model = dataclasses.replace(case.model, outputs=names)
    data = dataclasses.replace(data, outputs=names)
    lines = analyze(model, data, FAST).summary_text().splitlines()
    head = next(k for k, line in enumerate(lines) if line.startswith("row "))
    table = lines[head:head + 4]
    assert [line.split()[0] for line in table] == ["row", *names]
    # Every RSI ends (its third decimal) where the header's "RSI" ends.
    assert [line.index(".") + 4 for line in table[1:]] == [table[0].index("RSI") + 3] * 3


def test_report_has_the_contract_keys():
    case, data = _run_case("3.2", 4, samples=1500)
    doc = json.loads(json.dumps(analyze(case.model, data, AnalysisOptions()).to_dict()))
    assert doc["sample_time"] == 1.0 and doc["samples"] == 1500
    assert [r["output"] for r in doc["rows"]] == ["y1", "y2", "y3"]
    for r in doc["rows"]:
        assert set(r) >= {"output", "rsi", "mismatch", "p_value"}
        assert isinstance(r["mismatch"], bool) and isinstance(r["rsi"], float)
    tested = {(e["output"], e["input"]) for e in doc["elements"]}
    assert {("y1", "u1"), ("y1", "u2"), ("y1", "u3"), ("y2", "u1")} <= tested
    kinds = {"gain", "time_constant", "delay", "missing", "mixed", "unknown"}
    for e in doc["elements"]:
        assert set(e) >= {"output", "input", "mismatch", "p_value", "kind"}
        if e["mismatch"]:
            assert e["kind"] in kinds
    assert set(doc["repair"]) >= {"model", "changes", "error_before", "error_after"}
    assert isinstance(doc["warnings"], list)


def test_too_few_samples_is_a_clear_error():
    case, data = _run_case("3.2", 4, samples=60)
    with pytest.raises(DataFileError, match=r"60 samples; .* need at least \d+ samples$"):
        analyze(case.model, data, FAST)


def test_a_delay_that_makes_the_log_too_short_is_named():
    """A delay typed in the wrong unit (500 s for 5 s) made a 400-sample log "too short" without a word of
    the delay that set the tests' lags."""
    case, data = _run_case("3.2", 4, samples=400)
    delay = case.model.delay.copy()
    delay[1, 2] = 500.0
    model = case.model.replace(delay=delay)
    with pytest.raises(DataFileError, match=r"400 samples; .* max_delay=505 need at least \d+ samples; max_delay is "
                                            r"the model's longest delay \+ 5 samples: \(y2, u3\) 500 s, 500 samples$"):
        analyze(model, data, FAST)
    with pytest.raises(DataFileError, match=r"need at least \d+ samples$"):     # max_delay given: not the model's
        analyze(model, data, dataclasses.replace(FAST, max_delay=600))


def test_channels_must_match_the_model():
    case, data = _run_case("3.2", 4, samples=400)
    other = case.model.replace(inputs=("a", "b", "c"))
    with pytest.raises(DataFileError, match="do not match the model"):
        analyze(other, data, FAST)


@pytest.mark.parametrize("kw,match", [({"alpha": 0.0}, "alpha"), ({"na": -1}, "na"), ({"nb": 0}, "nb"),
                                      ({"band": (1.0, 0.5)}, "band"), ({"method": "magic"}, "method"),
                                      ({"initial_state": "guess"}, "initial_state")])
def test_bad_options_are_refused(kw, match):
    with pytest.raises(ConfigurationError, match=match):
        AnalysisOptions(**kw)


def test_initial_state_estimate_handles_a_log_that_starts_mid_operation():
    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 3600, seed=9, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    data = log.as_logged_data().slice(600, 3600)     # the model's state at the first sample is not zero
    rep = analyze(case.model, data, FAST)
    assert set(rep.located_elements) == set(case.mismatched_elements)


# ------------------------------------------------------------------------------------ CLI


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "mpm_monitor", *args], capture_output=True, text=True, timeout=120)


def test_analyze_cli_writes_the_json_report(tmp_path):
    case = paper_case("3.2")
    log = run_closed_loop(case.plant, case.model, 2000, seed=2, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    save_model(case.model, tmp_path / "model.yaml")
    write_log_csv(tmp_path / "data.csv", log)
    res = _cli("analyze", "--model", str(tmp_path / "model.yaml"), "--data", str(tmp_path / "data.csv"),
               "--json", "-", "--no-repair")
    assert res.returncode == 0, res.stderr
    doc = json.loads(res.stdout)
    located = {(e["output"], e["input"]) for e in doc["elements"] if e["mismatch"]}
    assert located == set(case.mismatched_elements)
    # --repair-out - wrote a file named "-" (where --json - and --data - mean the streams): refused up front.
    res = _cli("analyze", "--model", str(tmp_path / "model.yaml"), "--data", str(tmp_path / "data.csv"),
               "--json", "-", "--repair-out", "-")
    assert res.returncode == 2 and res.stdout == "" and res.stderr.startswith("error: --repair-out -: expected a file")
    assert len(res.stderr.splitlines()) == 1 and not (Path.cwd() / "-").exists()


@pytest.mark.parametrize("content,match", [
    ("sample_time: 1\ninputs: [u1]\n", "missing key 'outputs'"),
    ("not: [valid", "not valid YAML"),
])
def test_analyze_cli_bad_model_exits_2_with_one_line(tmp_path, content, match):
    (tmp_path / "m.yaml").write_text(content)
    (tmp_path / "d.csv").write_text("t,r_y1,u1,y1\n0,0,0,0\n")
    res = _cli("analyze", "--model", str(tmp_path / "m.yaml"), "--data", str(tmp_path / "d.csv"))
    assert res.returncode == 2
    assert match in res.stderr and "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_analyze_cli_bad_csv_exits_2_naming_line_and_column(tmp_path):
    case = paper_case("3.2")
    save_model(case.model, tmp_path / "model.yaml")
    (tmp_path / "d.csv").write_text("t,r_y1,r_y2,r_y3,u1,u2,u3,y1,y2,y3\n0,1,1,1,0,0,0,0,0,0\n1,1,1,1,x,0,0,0,0,0\n")
    res = _cli("analyze", "--model", str(tmp_path / "model.yaml"), "--data", str(tmp_path / "d.csv"))
    assert res.returncode == 2
    assert "line 3, column 'u1'" in res.stderr and "Traceback" not in res.stderr


# ------------------------------------------------------------------- beyond the paper's assumptions


def test_constrained_mpc_with_active_bounds_locates_exactly():
    """Bounds on u and du active a fifth of the time (the paper's correlation pitfall) change nothing."""
    import dataclasses

    case = paper_case("3.2")
    mpc = dataclasses.replace(case.mpc, u_min=-0.6, u_max=0.6, du_max=0.3)
    log = run_closed_loop(case.plant, case.model, 3000, seed=21, mpc=mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    assert np.mean(np.isclose(np.abs(log.u), 0.6)) > 0.1          # the bounds really are active
    rep = analyze(case.model, log.as_logged_data(), FAST)
    assert set(rep.located_elements) == set(case.mismatched_elements)


def test_strongly_coloured_disturbance_keeps_the_level_and_the_location():
    """A disturbance pole of 0.99 (the paper assumes 0.95): case 3.1 flags nothing, 3.2 is exact."""
    from mpm_monitor.sim.plant import DisturbanceOptions

    slow = DisturbanceOptions(disturbance_std=7.5e-3, disturbance_pole=0.99, noise_std=5e-3)
    for name in ("3.1", "3.2"):
        case = paper_case(name)
        log = run_closed_loop(case.plant, case.model, 3000, seed=22, mpc=case.mpc, excitation=case.excitation,
                              disturbance=slow)
        rep = analyze(case.model, log.as_logged_data(), FAST)
        assert set(rep.flagged_rows) == set(case.mismatched_rows)
        assert set(rep.located_elements) == set(case.mismatched_elements)


def test_slow_small_setpoint_moves_still_locate_case_3_2():
    """Weak excitation: PRBS switching with probability 0.02 and amplitude 0.3 instead of 0.5 and 1."""
    case = paper_case("3.2")
    exc = ExcitationOptions(setpoint=PrbsOptions(amplitude=0.3, switch_probability=0.02))
    log = run_closed_loop(case.plant, case.model, 3000, seed=23, mpc=case.mpc, excitation=exc,
                          disturbance=case.disturbance)
    rep = analyze(case.model, log.as_logged_data(), FAST)
    assert set(rep.located_elements) == set(case.mismatched_elements)


def test_a_setpoint_held_at_a_value_like_0_1_never_moves():
    """A setpoint held at 0.1 has a standard deviation of about 1e-17 (the rounding of its mean): it was taken
    as moving, and its column of S_Delta came out as rounding (row RSI 1e11, a warning of a loop near
    instability).  A setpoint moves when its values are not all the same."""
    from mpm_monitor.core.row_test import moving_setpoints

    case, data = _run_case("3.1", 5, samples=2000)
    r = data.r.copy()
    r[:, 0] = 0.1
    assert r[:, 0].std() > 0 and moving_setpoints(r) == [1, 2]
    rep = analyze(case.model, dataclasses.replace(data, r=r), FAST)
    assert any("setpoints of y1 never move" in w for w in rep.warnings), rep.warnings
    assert max(row.rsi for row in rep.rows) < 10 and not any("RSI" in w for w in rep.warnings)


def test_a_repaired_element_of_dead_time_0_is_not_said_to_lie_at_the_edge_of_its_delays():
    """(y3, u3) of case 3.1 has no dead time, in the model and the plant; its gain off, the repair's best delay
    is 0, the least there is, and was reported as "at the edge of the searched range; the true delay may lie
    outside it (raise max_delay_shift)", an option the command does not have and a delay that cannot be
    negative."""
    case = paper_case("3.1")
    assert case.model.delay[2, 2] == 0 and case.plant.delay[2, 2] == 0
    gain = case.plant.gain.copy()
    gain[2, 2] *= 1.8
    plant = case.plant.replace(gain=gain)
    log = run_closed_loop(plant, case.model, 3000, seed=4, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance)
    report = analyze(case.model, log.as_logged_data(), AnalysisOptions())
    assert ("y3", "u3") in {(e.output, e.input) for e in report.elements if e.mismatch}
    assert not [w for w in report.warnings if "edge of the searched range" in w and "y3/u3" in w], report.warnings


def test_an_output_that_never_moves_is_named_first():
    """A stuck sensor (y2 held at 0.1): the report spoke of an exact fit, a coloured residual, inputs moving
    together and an unmeasured disturbance of -2.8e-17, and never said the output does not move."""
    case, data = _run_case("3.1", 5, samples=2000)
    assert not any("never move" in w for w in analyze(case.model, data, FAST).warnings)
    y = data.y.copy()
    y[:, 1] = 0.1
    rep = analyze(case.model, dataclasses.replace(data, y=y), FAST)
    assert rep.warnings[0].startswith("output y2 never moves in this window (every value the same: a stuck sensor")
    assert "(no p-value, detectable_gain_change null)" in rep.warnings[0]
    # Its row's prediction error is the model's own response: not called "fitted exactly" (a log without noise?),
    # and named once, not again by the detectability.
    assert not any("fitted exactly" in w and "y2" in w for w in rep.warnings)
    assert all(e.detectable_gain_change is None for e in rep.elements if e.output == "y2")
    assert sum("y2 never moves" in w for w in rep.warnings) == 1, rep.warnings
    assert rep.still_outputs == ["y2"] and rep.to_dict()["still_outputs"] == ["y2"]


def test_a_stuck_output_is_not_repaired_to_zero_gains():
    """A stuck sensor (y2 held at its value at one instant) while the other rows keep a mismatch: every element
    of y2 was located and the repaired model set their gains to about 1e-17, as if the plant had lost its row,
    and an unmeasured "step of -5.6e-17" was reported in it.  Now its elements are listed untested, the repair
    leaves them as they are and finds the other rows' mismatch as on the log with y2 moving."""
    case, data = _run_case("3.2", 5, samples=3000)
    full = analyze(case.model, data, AnalysisOptions())
    y = data.y.copy()
    y[:, 1] = y[1000, 1]
    rep = analyze(case.model, dataclasses.replace(data, y=y), AnalysisOptions())
    y2 = [e for e in rep.elements if e.output == "y2"]
    assert [e.input for e in y2] == list(case.model.columns)
    assert all(not e.mismatch and e.p_value is None and e.statistic is None and not e.ambiguous for e in y2)
    assert [k for k in rep.located_elements if k[0] != "y2"] == \
        [k for k in full.located_elements if k[0] != "y2"] and rep.located_elements
    i = case.model.outputs.index("y2")
    assert np.array_equal(rep.repaired_model.gain[i], case.model.gain[i])
    assert not any(c["output"] == "y2" for c in rep.repair["changes"])
    assert not any(w.startswith("y2:") for w in rep.warnings), rep.warnings
    assert not any(x["output"] == "y2" for x in rep.repair.get("disturbances", []))
    assert "not tested (the output never moves: a stuck sensor or a held value?): every element of y2" \
        in rep.summary_text()
    # The baselines' element tests (every row) are set aside on the still row as well.
    base = analyze(case.model, dataclasses.replace(data, y=y), AnalysisOptions(method="xcorr", repair=False))
    assert base.still_outputs == ["y2"]
    assert all(e.p_value is None and not e.mismatch for e in base.elements if e.output == "y2")


def test_step_responses_cut_short_of_settling_are_named():
    """A step-response model of N = 20 samples for lags of 50 s: every element was located and the repair kept
    them all "unknown" ("may be too small"), and no word said the responses end long before they settle."""
    from mpm_monitor.core.data_warnings import unsettled_warnings

    from mpm_monitor.core.model import PlantModel

    case = paper_case("3.1")

    def step_model(n):
        sr = [[case.model.discrete_element(i, j).step_response(n + 1)[1:] for j in range(3)] for i in range(3)]
        return PlantModel.from_step_response(case.model.sample_time, case.model.inputs, case.model.outputs, sr)

    warning = unsettled_warnings(step_model(20))
    assert len(warning) == 1 and "(y1, u1), (y1, u2), (y1, u3), (y2, u1), (y2, u2), (y2, u3) and 3 more have not " \
                                  "settled within the model's 20 samples" in warning[0]
    assert unsettled_warnings(case.model) == []                      # parametric: nothing to say
    assert unsettled_warnings(step_model(400)) == []                 # settled (lags of 50 s at most)
    # Fewer than 10 samples were never checked: a model of 3, shorter than the dead times, said nothing.
    (short,) = unsettled_warnings(step_model(3))
    assert "have not settled within the model's 3 samples" in short
    fast = PlantModel.from_step_response(1.0, ("u1",), ("y1",), [[[0.6, 0.95, 1.0, 1.0, 1.0]]])
    assert unsettled_warnings(fast) == []                            # settled within its 5 samples


def test_a_long_window_is_confirmed_with_tails_on_its_last_rows(monkeypatch):
    """The confirmation with tails fits hundreds of tail lags on every regression row: 17 kB a sample on a 3x3
    log, 1.8 GB at 100,000 samples and more than the machine at 1,000,000.  Past TAIL_FIT_BYTES of regressors it
    takes the window's last rows (here a budget of 4 MB stands for a window of millions of samples), and says so."""
    from mpm_monitor.core import confirmation

    case, data = _run_case("3.2", 5, samples=3000)
    full = analyze(case.model, data, AnalysisOptions(repair=False))
    monkeypatch.setattr(confirmation, "TAIL_FIT_BYTES", 4 * 2 ** 20)
    short = analyze(case.model, data, AnalysisOptions(repair=False))
    said = [w for w in short.warnings if "confirmation of its located elements with the others' slow tails used "
                                          "the last" in w]
    assert said and not any("used the last" in w for w in full.warnings)
    rows = int(said[0].split("used the last ")[1].split()[0])
    width = int(said[0].split("(its regressors ")[1].split()[0])
    assert rows * width * 8 <= 4 * 2 ** 20 < (rows + 1) * width * 8
    assert short.located_elements == full.located_elements


def test_a_log_too_large_for_the_memory_is_one_line_not_a_traceback(tmp_path, monkeypatch, capsys):
    """Out of memory (a log of millions of samples under a memory limit) ended in a 59-line MemoryError
    traceback."""
    from mpm_monitor.apps import cli
    from mpm_monitor.core import pipeline
    from mpm_monitor.io.csv_log import write_log_csv
    from mpm_monitor.io.model_file import save_model

    case, data = _run_case("3.1", 5, samples=400)
    save_model(case.model, tmp_path / "m.yaml")
    write_log_csv(tmp_path / "log.csv", data)

    def too_much(*args, **kwargs):
        raise MemoryError()
    monkeypatch.setattr(pipeline, "analyze", too_much)
    assert cli.main(["analyze", "--model", str(tmp_path / "m.yaml"), "--data", str(tmp_path / "log.csv")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: analyze: out of memory") and err.count("\n") == 1


def test_an_output_held_over_the_last_part_of_the_window_is_named():
    """A sensor that sticks during the window (its last 600 samples one value): nothing said so, and its row's
    elements were located as if the model were wrong.  A warning names it now; a quantized output (its value
    repeated at many samples throughout) is not named."""
    case, data = _run_case("3.2", 5, samples=3000)
    y = data.y.copy()
    y[2400:, 1] = y[2400, 1]
    rep = detect(case.model, dataclasses.replace(data, y=y), AnalysisOptions(repair=False))
    said = [w for w in rep.warnings if w.startswith("output y2 holds one value over its last 600 samples (from t = "
                                                    f"{data.t[2400]:.15g} s)")]
    assert said, rep.warnings
    assert not any("holds one value" in w for w in detect(case.model, data, AnalysisOptions(repair=False)).warnings)
    coarse = data.y.copy()
    coarse[:, 1] = np.round(coarse[:, 1], 1)            # a measurement in steps of 0.1: repeats everywhere
    coarse[2400:, 1] = coarse[2400, 1]
    rep = detect(case.model, dataclasses.replace(data, y=coarse), AnalysisOptions(repair=False))
    assert not any("holds one value" in w for w in rep.warnings)
