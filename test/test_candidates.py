"""Candidate channels: logged variables the model does not use, tested as causes of the prediction error.

Acceptance (the undeclared-effect loop of mpm_monitor.sim.undeclared): the undeclared channel is
located and added with its element within 10% (delay within one sample) and the error afterwards
within 10% of the noise floor; decoys (a random walk, a filtered noise) are never added; a channel
driven by an input of the loop is reported as not exogenous and never added.  The level of the test
on random-walk candidates (the spurious regression the whitening avoids) is checked by simulation on
the regression alone; the full Monte-Carlo is bench.candidates_mc.
"""

import dataclasses
import json
import re

import numpy as np
import pytest

from mpm_monitor.apps.cli import main as cli_main
from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.candidates import (
    cause_tests,
    exogeneity_test,
    select_candidates,
    whiten,
    with_candidate_columns,
    without_columns,
)
from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.io.csv_log import read_csv, write_csv
from mpm_monitor.io.model_file import load_model, save_model
from mpm_monitor.io.report import write_report
from mpm_monitor.sim.undeclared import (
    EFFECT_CHANNEL,
    FILTERED_NOISE_CHANNEL,
    LOOP_CHANNEL,
    RANDOM_WALK_CHANNEL,
    UndeclaredEffect,
    undeclared_effect_run,
)


@pytest.fixture(scope="module")
def effect_run():
    return undeclared_effect_run(3000, seed=3)


@pytest.fixture(scope="module")
def effect_report(effect_run):
    return analyze(effect_run.model, effect_run.data, AnalysisOptions(), candidates="all")


# ------------------------------------------------------------------------------------ acceptance
def test_the_undeclared_channel_is_found_added_and_fitted(effect_run, effect_report):
    rep, truth = effect_report, effect_run.effect
    cands = rep.candidates
    assert cands.located == [(truth.output, EFFECT_CHANNEL)]
    assert cands.added == [EFFECT_CHANNEL]
    entry = [e for e in rep.elements if e.role == "candidate" and e.mismatch]
    assert [(e.output, e.input, e.kind) for e in entry] == [(truth.output, EFFECT_CHANNEL, "missing")]
    m = rep.repaired_model
    assert m.disturbances == (EFFECT_CHANNEL,)
    el = m.element(m.outputs.index(truth.output), m.columns.index(EFFECT_CHANNEL))
    assert abs(el["gain"] - truth.gain) <= 0.1 * truth.gain
    assert abs(el["time_constant"] - truth.time_constant) <= 0.1 * truth.time_constant
    assert abs(el["delay"] - truth.delay) <= 1.0 * m.sample_time
    # zeros on the other outputs; the model's own elements untouched
    others = [i for i, o in enumerate(m.outputs) if o != truth.output]
    assert all(m.gain[i, m.columns.index(EFFECT_CHANNEL)] == 0 for i in others)
    np.testing.assert_array_equal(m.gain[:, :m.n_inputs], effect_run.model.gain)
    floor = effect_run.noise_floor[truth.output]
    assert rep.repair["error_before"][truth.output] > 5 * floor
    assert rep.repair["error_after"][truth.output] <= 1.1 * floor
    change = [c for c in rep.repair["changes"] if c["input"] == EFFECT_CHANNEL]
    assert len(change) == 1 and change[0]["applied"] and change[0]["kind"] == "missing"


def test_decoys_are_not_added_and_the_loop_channel_is_not_exogenous(effect_report):
    cands = effect_report.candidates
    assert set(cands.tried) == {EFFECT_CHANNEL, RANDOM_WALK_CHANNEL, FILTERED_NOISE_CHANNEL, LOOP_CHANNEL}
    assert set(cands.not_exogenous) == {LOOP_CHANNEL}
    assert cands.not_exogenous[LOOP_CHANNEL] == "moves with u2: may be an effect of the loop, not a cause"
    assert LOOP_CHANNEL not in cands.p_values
    for decoy in (RANDOM_WALK_CHANNEL, FILTERED_NOISE_CHANNEL):
        assert all(p >= effect_report.alpha for p in cands.p_values[decoy].values())
    assert not any(e.mismatch for e in effect_report.elements if e.input != EFFECT_CHANNEL)
    assert any("u2_flow moves with u2" in w for w in effect_report.warnings)


def test_the_json_report_lists_the_candidates(effect_report):
    doc = json.loads(json.dumps(effect_report.to_dict()))
    c = doc["candidates"]
    assert c["tried"] == list(effect_report.candidates.tried)
    assert c["added"] == [EFFECT_CHANNEL]
    assert c["p_values"][EFFECT_CHANNEL]["y1"] < 1e-10
    assert c["not_exogenous"] == {LOOP_CHANNEL: "moves with u2: may be an effect of the loop, not a cause"}
    assert c["unusable"] == {}
    cand = [e for e in doc["elements"] if e["role"] == "candidate"]
    assert {(e["output"], e["input"]) for e in cand} == {(o, n) for n in (EFFECT_CHANNEL, RANDOM_WALK_CHANNEL,
                                                                         FILTERED_NOISE_CHANNEL) for o in
                                                         ("y1", "y2", "y3")}
    assert doc["repair"]["model"]["disturbances"] == [EFFECT_CHANNEL]
    text = effect_report.summary_text()
    assert "(y1, feed_temperature (candidate))" in text
    assert "candidates added to the model as measured disturbances: feed_temperature" in text


def test_a_loop_channel_alone_is_never_added(effect_run):
    data = dataclasses.replace(effect_run.data, extra={LOOP_CHANNEL: effect_run.data.extra[LOOP_CHANNEL]})
    rep = analyze(effect_run.model, data, AnalysisOptions(), candidates=[LOOP_CHANNEL])
    assert list(rep.candidates.not_exogenous) == [LOOP_CHANNEL]
    assert rep.candidates.added == [] and rep.repaired_model == effect_run.model


def test_without_candidates_the_report_has_no_candidates_key(effect_run):
    rep = detect(effect_run.model, effect_run.data)
    assert "candidates" not in rep.to_dict() and rep.candidates is None
    assert not any(e.role == "candidate" for e in rep.elements)


def test_candidate_tests_share_the_family_with_the_elements(effect_run):
    plain = detect(effect_run.model, effect_run.data)
    rep = detect(effect_run.model, effect_run.data, candidates=[RANDOM_WALK_CHANNEL, FILTERED_NOISE_CHANNEL])
    by_key = {(e.output, e.input): e for e in rep.elements}
    for e in plain.elements:
        if e.p_value is None:
            continue
        wider = by_key[(e.output, e.input)]
        assert wider.p_value_raw == e.p_value_raw
        assert wider.p_value >= e.p_value - 1e-15       # a larger Holm family never lowers a p-value
    assert sum(e.role == "candidate" for e in rep.elements) == 2 * effect_run.model.n_outputs


# ------------------------------------------------------------------------------------ usability
def test_unusable_channels_are_reported_with_a_warning(effect_run):
    n = effect_run.data.n_samples
    extra = dict(effect_run.data.extra)
    extra["stuck"] = np.full(n, 3.0)
    extra["broken"] = np.where(np.arange(n) == 10, np.nan, 1.0 + np.arange(n) * 0.01)
    # Moving, but so small that its squares underflow: it was called constant.
    extra["tiny"] = 1e-300 * np.random.default_rng(3).standard_normal(n)
    data = dataclasses.replace(effect_run.data, extra=extra, unusable={"status": "not numeric (line 5: 'OK')"})
    chosen = select_candidates(data, "stuck,broken,status,tiny,ambient", effect_run.model)
    assert chosen.names == ("ambient",)
    peak = float(np.abs(extra["tiny"]).max())
    assert chosen.unusable == {"stuck": "constant: it never moves", "broken": "holds NaN or infinity",
                               "status": "not numeric (line 5: 'OK')",
                               "tiny": f"values up to {peak:.3g}: too small for the analysis (at least 1e-100); rescale"}
    rep = detect(effect_run.model, data, candidates=chosen)
    assert set(rep.candidates.unusable) == {"stuck", "broken", "status", "tiny"}
    assert any(w.startswith("candidate stuck is unusable (constant") for w in rep.warnings)
    assert not any(e.input in ("stuck", "broken", "status", "tiny") for e in rep.elements)


def test_unknown_or_model_channels_are_refused_in_one_line(effect_run):
    with pytest.raises(ConfigurationError, match="no column 'nope' .* are: feed_temperature, ambient"):
        select_candidates(effect_run.data, "nope", effect_run.model)
    with pytest.raises(ConfigurationError, match="'u2' is a channel of the model"):
        select_candidates(effect_run.data, ["u2"], effect_run.model)
    with pytest.raises(ConfigurationError, match="^candidates: 't' is the log's time, not a candidate$"):
        select_candidates(effect_run.data, ["t"], effect_run.model)
    setpoint = f"r_{effect_run.model.outputs[0]}"
    with pytest.raises(ConfigurationError, match=f"^candidates: '{setpoint}' is a setpoint of the log, not a candidate$"):
        select_candidates(effect_run.data, [setpoint], effect_run.model)
    with pytest.raises(ConfigurationError, match="expected 'all' or NAME"):
        select_candidates(effect_run.data, "ambient,,x")
    with pytest.raises(ConfigurationError, match="arx element test only"):
        detect(effect_run.model, effect_run.data, AnalysisOptions(method="xcorr"), candidates="all")


# ------------------------------------------------------------------------------------ the statistics
def _ar_noise(n, rng, pole=0.95):
    e = rng.normal(size=n)
    x = np.empty(n)
    prev = 0.0
    for k in range(n):
        prev = pole * prev + e[k]
        x[k] = prev
    return x


def test_random_walk_candidates_hold_the_level_with_an_imperfect_noise_model():
    """Whitened random-walk candidates keep the F test's level on a coloured residual that the ARX
    models imperfectly (na = 1 for an error of two AR(1) components)."""
    rng = np.random.default_rng(0)
    n, runs, alpha = 600, 200, 0.05
    rejected = 0
    for _ in range(runs):
        d = _ar_noise(n, rng, 0.97) + _ar_noise(n, rng, 0.5)
        walk = np.cumsum(rng.normal(size=n))
        t, = cause_tests(d, np.zeros((n, 0)), whiten(walk)[:, None], na=1, nb=4, n_lag=10, start=20)
        rejected += t.p_value < alpha
    assert rejected / runs <= alpha + 2 * np.sqrt(alpha * (1 - alpha) / runs)


def test_an_effect_of_a_random_walk_is_found_through_its_whitened_form():
    rng = np.random.default_rng(5)
    n = 1500
    walk = np.cumsum(rng.normal(size=n))
    d = _ar_noise(n, rng, 0.9) * 0.5
    d[3:] += 0.2 * walk[:-3]
    t, = cause_tests(d, np.zeros((n, 0)), whiten(walk)[:, None], na=4, nb=4, n_lag=10, start=20)
    assert t.p_value < 1e-10 and t.delay == 3


def test_a_cause_test_of_a_prediction_error_at_rounding_level_is_decided_outright():
    # A log without noise whose model is right: d is rounding (1e-13 of the output's spread).  Against
    # the output's spread the fit is exact and there is nothing to explain: p 1, not a p-value of
    # rounding; an effect of the candidate on an exactly fitted d is rejected outright (p 0).
    rng = np.random.default_rng(6)
    n, spread = 1500, 2.0
    walk = np.cumsum(rng.normal(size=n))
    d = 1e-13 * spread * rng.normal(size=n)
    t, = cause_tests(d, np.zeros((n, 0)), whiten(walk)[:, None], na=2, nb=4, n_lag=10, start=20, output_spread=spread)
    assert (t.statistic, t.p_value) == (0.0, 1.0)
    plain, = cause_tests(d, np.zeros((n, 0)), whiten(walk)[:, None], na=2, nb=4, n_lag=10, start=20)
    assert 0.0 < plain.p_value < 1.0                      # without the spread: an F test of rounding
    effect = d.copy()
    effect[3:] += 0.2 * walk[:-3]
    t, = cause_tests(effect, np.zeros((n, 0)), whiten(walk)[:, None], na=2, nb=4, n_lag=10, start=20,
                     output_spread=spread)
    assert t.p_value == 0.0 and t.delay == 3


def test_whitening_a_random_walk_gives_its_increments():
    rng = np.random.default_rng(1)
    steps = rng.normal(size=2000)
    w = whiten(np.cumsum(steps))
    assert np.corrcoef(w[20:], steps[20:])[0, 1] > 0.99


def test_exogeneity_separates_a_loop_response_from_an_exogenous_channel():
    rng = np.random.default_rng(2)
    n = 2000
    u = np.column_stack([_ar_noise(n, rng, 0.8), rng.normal(size=n)])
    driven = np.zeros(n)
    driven[3:] = 0.5 * u[:-3, 1] + 0.3 * u[:-3, 0] * 0
    driven += 0.3 * rng.normal(size=n)
    exo = np.cumsum(rng.normal(size=n))
    t = exogeneity_test(driven, u, ("u1", "u2"), n_lag=8, alpha=0.01)
    assert t.p_value < 1e-6 and t.inputs == ("u2",)
    assert exogeneity_test(exo, u, ("u1", "u2"), n_lag=8, alpha=0.01).p_value > 1e-3


def _steps(n, times, levels):
    x = np.zeros(n)
    for t, level in zip(times, levels):
        x[t:] = level
    return x


def test_a_step_channel_after_an_input_step_by_chance_stays_exogenous():
    """Inputs that move in rare steps (setpoint steps) and a channel changed by hand in six steps, one
    of them 3 samples after an input step by chance: the channel's own-lag residual is six spikes, the
    input lags fit one, and the F test alone rejected (here in 6 of 20 draws, down to p = 2e-14, against
    its level of 1 %).  The robust score test counts the coincidence as one observation: no draw rejects."""
    n, f_rejects = 2000, 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        grid = np.arange(20, n - 20)
        u_steps = np.sort(rng.choice(grid, 20, replace=False))
        u = np.column_stack([_steps(n, u_steps, rng.uniform(-1, 1, 20)),
                             _steps(n, np.sort(rng.choice(grid, 20, replace=False)), rng.uniform(-1, 1, 20))])
        u += 0.01 * rng.normal(size=u.shape)
        c = _steps(n, np.sort(np.r_[rng.choice(grid, 5, replace=False), u_steps[7] + 3]), rng.uniform(-1, 1, 6))
        c += 0.001 * (seed % 2) * rng.normal(size=n)          # half the draws with a little noise
        t = exogeneity_test(c, u, ("u1", "u2"), n_lag=8, alpha=0.01)
        assert t.p_value == max(t.p_value_f, t.p_value_robust)
        assert t.p_value > 0.01, (seed, t)
        f_rejects += t.p_value_f < 0.01
    assert f_rejects >= 5


def test_the_robust_score_statistic_against_its_matrix_form():
    """``n - RSS(1 on Z)`` against ``s' (Z'Z)^-1 s`` computed directly, and its level under the null."""
    from mpm_monitor.core.candidates import robust_score_test
    from mpm_monitor.core.statistics import chi2_tail

    rng = np.random.default_rng(5)
    n = 400
    base = np.column_stack([np.ones(n), rng.normal(size=(n, 3))])
    tested = rng.normal(size=(n, 4)) + 0.5 * base[:, 1:2]
    y = base @ np.array([1.0, 0.5, -0.2, 0.1]) + 0.3 * tested[:, 2] + rng.standard_t(3, size=n)
    stat, p = robust_score_test(base, tested, y)
    coef = np.linalg.solve(base.T @ base, base.T @ y)
    e = y - base @ coef
    R = tested - base @ np.linalg.solve(base.T @ base, base.T @ tested)
    Z = e[:, None] * R
    s = Z.sum(axis=0)
    ref = float(s @ np.linalg.solve(Z.T @ Z, s))
    assert stat == pytest.approx(ref, rel=1e-9) and p == pytest.approx(float(chi2_tail(ref, 4)), rel=1e-9)
    assert p < 1e-3                                     # the tested column acts
    rejections = 0
    for _ in range(400):                                # null, heavy-tailed errors: the level holds
        y = base @ np.array([1.0, 0.5, -0.2, 0.1]) + rng.standard_t(3, size=n) * (1 + np.abs(base[:, 1]))
        rejections += robust_score_test(base, tested, y)[1] < 0.05
    assert 6 <= rejections <= 34                        # 5 % of 400 = 20, its two-sided 0.1 % binomial range (14 here)


# ------------------------------------------------------------------------------------ model columns
def test_candidate_columns_are_added_and_dropped_in_every_structure(effect_run):
    model = effect_run.model
    wide, data = with_candidate_columns(model, effect_run.data, [EFFECT_CHANNEL, RANDOM_WALK_CHANNEL])
    assert wide.disturbances == (EFFECT_CHANNEL, RANDOM_WALK_CHANNEL) and data.dv.shape == (3000, 2)
    assert EFFECT_CHANNEL not in data.extra and not wide.present[:, 3:].any()
    assert without_columns(wide, [EFFECT_CHANNEL, RANDOM_WALK_CHANNEL]) == model
    step = PlantModel.from_step_response(1.0, ("u1",), ("y1",), np.ones((1, 1, 5)))
    data1 = dataclasses.replace(effect_run.data, u=effect_run.data.u[:, :1], inputs=("u1",), r=effect_run.data.r[:, :1],
                                y=effect_run.data.y[:, :1], outputs=("y1",))
    wide_step, _ = with_candidate_columns(step, data1, [EFFECT_CHANNEL])
    assert wide_step.step_response.shape == (1, 2, 5) and not wide_step.present[0, 1]
    assert without_columns(wide_step, [EFFECT_CHANNEL]) == step


# ------------------------------------------------------------------------------------ command line, HTML
def test_analyze_candidates_on_the_command_line(tmp_path, effect_run, capsys):
    d = effect_run.data
    write_csv(tmp_path / "log.csv", d.t, d.r, d.u, d.y, d.inputs, d.outputs, extra=d.extra)
    save_model(effect_run.model, tmp_path / "m.yaml")
    code = cli_main(["analyze", "--model", str(tmp_path / "m.yaml"), "--data", str(tmp_path / "log.csv"),
                     "--candidates", "all", "--json", str(tmp_path / "r.json"), "--repair-out",
                     str(tmp_path / "new.yaml"), "--report", str(tmp_path / "html")])
    assert code == 0
    out = capsys.readouterr().out
    assert "candidates added to the model as measured disturbances: feed_temperature" in out
    doc = json.loads((tmp_path / "r.json").read_text())
    assert doc["candidates"]["added"] == [EFFECT_CHANNEL]
    new = load_model(tmp_path / "new.yaml")
    assert new.disturbances == (EFFECT_CHANNEL,)
    # the repaired model reads the same CSV with the candidate as its measured disturbance
    assert read_csv(tmp_path / "log.csv", new).disturbances == (EFFECT_CHANNEL,)
    page = (tmp_path / "html" / "report.html").read_text()
    assert "<h2>Candidate channels</h2>" in page and "moves with u2" in page and "added to the model" in page
    code = cli_main(["analyze", "--model", str(tmp_path / "m.yaml"), "--data", str(tmp_path / "log.csv"),
                     "--candidates", "feed_temp"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no column 'feed_temp'" in err and "feed_temperature" in err


def test_columns_whose_names_no_model_can_hold_are_unusable_not_fatal(tmp_path, effect_run, capsys):
    """The effect channel under a header name with a comma (quoted in the CSV) or a tab: it was tested, located,
    and the repair then failed on its name as a model's measured disturbance ("error: model: key 'disturbances'
    ...", exit 2, no report); a column with an empty header name was left out of ``all`` without a word.  Each is
    now unusable, with the reason, and the analysis runs."""
    import csv

    d = effect_run.data
    write_csv(tmp_path / "log.csv", d.t, d.r, d.u, d.y, d.inputs, d.outputs, extra=d.extra)
    rows = list(csv.reader((tmp_path / "log.csv").read_text().splitlines()))
    k = rows[0].index(EFFECT_CHANNEL)
    for row in rows[1:]:
        row += [row[k], row[k]]
    rows[0][k] = "feed,temp"
    rows[0] += ["feed\ttemp", ""]
    with open(tmp_path / "odd.csv", "w", newline="") as f:
        csv.writer(f).writerows(rows)
    save_model(effect_run.model, tmp_path / "m.yaml")
    code = cli_main(["analyze", "--model", str(tmp_path / "m.yaml"), "--data", str(tmp_path / "odd.csv"),
                     "--candidates", "all", "--json", str(tmp_path / "r.json"), "--jobs", "1"])
    assert code == 0, capsys.readouterr().err
    unusable = json.loads((tmp_path / "r.json").read_text())["candidates"]["unusable"]
    assert unusable["feed,temp"].startswith("its name holds a comma, which a model's channel name cannot")
    assert unusable["feed\ttemp"].startswith("its name holds a control character")
    assert unusable[f"(column {len(rows[0])})"] == "the header gives it no name: name it there to test it"
    # Named on its own, the channel with a comma is that channel (it was split and refused as "no column 'feed'").
    code = cli_main(["analyze", "--model", str(tmp_path / "m.yaml"), "--data", str(tmp_path / "odd.csv"),
                     "--candidates", "feed,temp", "--json", str(tmp_path / "r1.json"), "--jobs", "1"])
    assert code == 0, capsys.readouterr().err
    tried = json.loads((tmp_path / "r1.json").read_text())["candidates"]
    assert list(tried["unusable"]) == ["feed,temp"]


def test_html_report_without_a_located_candidate(tmp_path, effect_run):
    data = dataclasses.replace(effect_run.data, extra={RANDOM_WALK_CHANNEL: effect_run.data.extra[RANDOM_WALK_CHANNEL]})
    rep = analyze(effect_run.model, data, AnalysisOptions(), candidates="all")
    page = write_report(tmp_path, effect_run.model, data, rep).read_text()
    assert "<h2>Candidate channels</h2>" in page and "Added: none." in page


def test_an_effect_with_a_dead_time_beyond_the_models_is_found_and_fitted():
    """The undeclared channel's dead time (20 s) is longer than the columns' lags reach (the model's longest delay
    7 samples: max_delay 12, lags 1 .. 16): with the candidate's lags as far as the columns' it came out p = 1,
    silently (an outside check).  Its lags reach three times max_delay, and the summary says how far."""
    run = undeclared_effect_run(3000, seed=6, effect=UndeclaredEffect(delay=20.0), loop_channel=False)
    rep = analyze(run.model, run.data, AnalysisOptions(), candidates=EFFECT_CHANNEL)
    assert rep.candidates.located == [("y1", EFFECT_CHANNEL)] and rep.candidates.max_delay == 36
    m = rep.repaired_model
    el = m.element(0, m.columns.index(EFFECT_CHANNEL))
    assert abs(el["gain"] - 0.8) <= 0.08 and abs(el["delay"] - 20.0) <= 1.0
    assert "effects searched for dead times up to 36 samples, 3 x --max-delay" in rep.candidates.summary_lines()[0]
    assert rep.to_dict()["candidates"]["max_delay"] == 36


def test_no_effect_run_gives_no_candidate():
    run = undeclared_effect_run(2000, seed=4, effect=UndeclaredEffect(gain=0.0), loop_channel=False)
    rep = detect(run.model, run.data, candidates="all")
    assert rep.candidates.located == [] and not any(e.mismatch for e in rep.elements)


def test_a_candidate_on_an_integrating_output_is_repaired_as_integrating():
    """The level case without its measured inflow in the model, the inflow given as a candidate: on the
    level (an integrating output) the inflow's element is fitted integrating, as the level's own
    elements are; fitted self-regulating it left the level's error 40 times the noise."""
    from mpm_monitor.apps.reproduce import simulate_case
    from mpm_monitor.core.candidates import without_columns
    from mpm_monitor.core.pipeline import analyze

    case, data, _ = simulate_case("level", 1500, 1)
    name = case.model.disturbances[0]
    model = without_columns(case.model, [name])
    logged = dataclasses.replace(data, dv=np.zeros((data.n_samples, 0)), disturbances=(), extra={name: data.dv[:, 0]})
    rep = analyze(model, logged, AnalysisOptions(), candidates=name)
    level = [i for i, flag in enumerate(model.integrating_outputs) if flag][0]
    repaired = rep.repaired_model
    j = repaired.columns.index(name)
    assert bool(repaired.integrating[level, j])
    out = model.outputs[level]
    assert rep.repair["error_after"][out] < 2.0 * min(rep.repair["error_after"].values())


def test_no_candidate_regression_row_reaches_across_a_gap(effect_run):
    """With gaps, the whitening, the exogeneity test and the cause tests regress only the rows whose
    lags stay inside their segment: a jump of the candidate across a gap (a sensor reset while the
    log was down) enters no regression, and the effect is located as on the whole log."""
    from mpm_monitor.core.candidates import whiten

    data = effect_run.data
    name = next(iter(data.extra))
    rows = np.setdiff1d(np.arange(data.n_samples), np.arange(1200, 1230))
    gappy = data.take(rows)
    jumped = dict(gappy.extra)
    jumped[name] = jumped[name] + 50.0 * (np.arange(gappy.n_samples) >= 1200)     # a level shift in the gap
    gappy = dataclasses.replace(gappy, extra=jumped)
    segments = gappy.segments
    assert len(segments) == 2
    w = whiten(jumped[name], segments=segments)
    a = segments[1][0]
    np.testing.assert_array_equal(w[a:a + 4], 0.0)
    # the whitened series does not see the shift (a level per segment, no lag across the gap)
    np.testing.assert_allclose(w, whiten(data.take(rows).extra[name], segments=segments), rtol=0, atol=1e-9)
    assert np.max(np.abs(whiten(jumped[name]) - whiten(data.take(rows).extra[name]))) > 1.0   # read as one record
    full = detect(effect_run.model, data, AnalysisOptions(repair=False), candidates=[name])
    rep = detect(effect_run.model, gappy, AnalysisOptions(repair=False), candidates=[name])
    assert rep.candidates.located == full.candidates.located and full.candidates.located
    assert not any("contiguous" in w for w in rep.warnings)


def test_spans_too_short_for_the_candidate_test_make_the_candidates_unusable(effect_run):
    """An outside check: a sample missing every 20 rows left spans of 19 samples, shorter than the candidate
    test's lags; the element tests ran (the analysis without candidates passed) and the cause tests ended in a
    traceback ("need at least one array to concatenate"), or at 25 rows in a numerical breakdown.  The candidates
    are now unusable, with the rows the spans give and those needed, and the rest of the analysis is that without
    candidates."""
    data = effect_run.data
    name = next(iter(data.extra))
    for every in (20, 25):
        gappy = data.take(np.flatnonzero(np.arange(data.n_samples) % every != every - 1))
        rep = detect(effect_run.model, gappy, AnalysisOptions(repair=False), candidates=[name])
        plain = detect(effect_run.model, gappy, AnalysisOptions(repair=False))
        why = rep.candidates.unusable[name]
        assert re.fullmatch(r"the spans between gaps give \d+ regression rows for its test \(a row needs the \d+ "
                            r"samples before it in its span\), at least \d+ needed", why), why
        assert rep.candidates.p_values == {} and rep.candidates.located == []
        assert f"candidate {name} is unusable ({why}); it was not tested" in rep.warnings
        assert [(e.output, e.input, e.p_value) for e in rep.elements if e.role != "candidate"] == \
            [(e.output, e.input, e.p_value) for e in plain.elements]


def test_a_candidates_null_detectable_change_is_said(effect_report):
    """Contract: detectable_gain_change is null only where it cannot be computed, with a warning saying why."""
    cands = [e for e in effect_report.elements if e.role == "candidate"]
    assert cands and all(e.detectable_gain_change is None for e in cands)
    assert any(w.startswith("candidate channels: the smallest gain change this window detects is computed for the "
                            "model's own columns only") for w in effect_report.warnings)


def test_a_spike_in_an_output_with_a_candidate_added_to_the_model():
    """The sample of a spike in an output keeps its logged inputs for the model's simulation
    (LoggedData.column_fill); a candidate channel added to the model as a measured disturbance has no
    such value there and is held.  (A shape error ended the analysis before.)"""
    from mpm_monitor.apps.reproduce import simulate_case
    from mpm_monitor.core.candidates import without_columns
    from mpm_monitor.core.pipeline import analyze

    case, data, _ = simulate_case("level", 1500, 1)
    name = case.model.disturbances[0]
    model = without_columns(case.model, [name])
    y = data.y.copy()
    y[700, 0] += 1000.0
    logged = dataclasses.replace(data, y=y, dv=np.zeros((data.n_samples, 0)), disturbances=(),
                                 extra={name: data.dv[:, 0]})
    rep = analyze(model, logged, AnalysisOptions(), candidates=name)
    assert "spikes" in rep.warnings[0]
    assert sorted(rep.candidates.located) == sorted((o, name) for o in model.outputs)
    assert max(rep.repair["error_after"].values()) < 0.05


@pytest.mark.parametrize("scale", [1e-14, 1e9])
def test_a_candidate_in_other_units_gives_the_same_decisions_and_element(effect_run, effect_report, scale):
    """The candidate's units do not matter: a channel logged in units of 1e-14 moves (it was called
    constant), its exogeneity test keeps its columns' rank (it was called an effect of the loop), and the
    element added has the same gain per unit of the original channel."""
    data = effect_run.data
    extra = dict(data.extra)
    extra[EFFECT_CHANNEL] = np.asarray(extra[EFFECT_CHANNEL]) * scale
    rep = analyze(effect_run.model, dataclasses.replace(data, extra=extra), AnalysisOptions(), candidates="all")
    assert rep.candidates.located == effect_report.candidates.located
    assert rep.candidates.added == effect_report.candidates.added == [EFFECT_CHANNEL]
    assert not any(EFFECT_CHANNEL in w and ("never moves" in w or "moves with" in w) for w in rep.warnings)

    def element(report):
        m = report.repaired_model
        i, j = m.outputs.index(effect_run.effect.output), m.columns.index(EFFECT_CHANNEL)
        return m.gain[i, j], m.time_constant[i, j], m.delay[i, j]

    gain, tau, delay = element(rep)
    gain0, tau0, delay0 = element(effect_report)
    assert gain * scale == pytest.approx(gain0, rel=1e-8)
    assert tau == pytest.approx(tau0, rel=1e-8) and delay == delay0


def test_copies_of_the_logs_channels_are_named_not_tested(effect_run, effect_report):
    """A historian export holds the same tag twice: a copy of an input was "moves with u2: may be an effect of the
    loop" (the other input's name), and a copy of the effect channel in other units was located beside it.  A
    candidate that another channel fits as ``a x + b`` to within COPY_TOLERANCE of its spread is now named as that
    channel's copy and not tested; a second sensor (its own noise) and a copy stored as 32-bit floats are told
    apart."""
    data = effect_run.data
    rng = np.random.default_rng(11)
    effect = np.asarray(data.extra[EFFECT_CHANNEL], dtype=float)
    extra = dict(data.extra)
    extra["effect_in_other_units"] = 2.0 * effect + 5.0
    extra["u1_tag"] = data.u[:, 0].copy()
    extra["y2_tag"] = data.y[:, 1] * 0.5
    extra["sp_tag"] = data.r[:, 0] - 1.0
    extra["u3_float32"] = (data.u[:, 2] + 300.0).astype(np.float32).astype(float)
    extra["second_sensor"] = effect + 1e-3 * effect.std() * rng.standard_normal(effect.shape)
    rep = analyze(effect_run.model, dataclasses.replace(data, extra=extra), AnalysisOptions(), candidates="all")
    unusable = rep.candidates.unusable
    assert unusable["effect_in_other_units"] == (f"a copy of candidate {EFFECT_CHANNEL} times 2 plus 5: it is "
                                                 f"examined as {EFFECT_CHANNEL}")
    assert unusable["u1_tag"] == "an exact copy of input u1: the model has it already"
    assert unusable["y2_tag"] == "a copy of output y2 times 0.5: the output itself, not a cause"
    assert unusable["sp_tag"] == "a copy of setpoint r_y1 minus 1: a setpoint acts through the inputs, not beside them"
    assert unusable["u3_float32"].startswith("a copy of input u3 plus 300") and "the model has it already" in \
        unusable["u3_float32"]
    assert "second_sensor" not in unusable and "second_sensor" in rep.candidates.p_values
    # The second sensor is a candidate of its own, as good a cause as the first: one of the two is added.
    assert effect_report.candidates.added == [EFFECT_CHANNEL]
    assert rep.candidates.added in ([EFFECT_CHANNEL], ["second_sensor"])
    assert not any(name == "effect_in_other_units" for _, name in rep.candidates.located)
    assert "candidate u1_tag is unusable (an exact copy of input u1: the model has it already); it was not tested" \
        in rep.warnings
    assert not any("u1_tag moves with" in w for w in rep.warnings)


def test_a_candidate_the_joint_fit_releases_is_not_left_among_the_located(effect_run):
    """Two sensors of the same cause are both flagged; re-estimated together, one explains the row and the other
    is released ("... it is not reported as located").  The candidates' ``located`` list still held it, so the
    JSON report and its elements disagreed."""
    data = effect_run.data
    effect = np.asarray(data.extra[EFFECT_CHANNEL], dtype=float)
    extra = dict(data.extra)
    extra["second_sensor"] = effect + 1e-2 * effect.std() * np.random.default_rng(11).standard_normal(effect.shape)
    rep = analyze(effect_run.model, dataclasses.replace(data, extra=extra), AnalysisOptions(), candidates="all")
    flagged = [(e.output, e.input) for e in rep.elements if e.role == "candidate" and e.mismatch]
    released = [(e.output, e.input) for e in rep.elements if e.role == "candidate" and e.explained_by]
    assert len(flagged) == 1 and len(released) == 1
    assert rep.candidates.located == flagged
    assert rep.candidates.added == [flagged[0][1]]
    assert any(f"also flagged {released[0][1]}" in w and "not reported as located" in w for w in rep.warnings)
