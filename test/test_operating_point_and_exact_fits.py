"""Valid logs that used to give wrong answers or break down (found by fuzzing the command line).

- The model file's operating point (``input_nominal``, ``output_nominal``): a log in absolute units
  analysed with it gives the analysis of the same log in deviation variables, in the function API,
  the repair and the command line.
- A log whose prediction error sits far from zero (outputs and setpoints at 1e5 that the model does
  not describe) raises no "the prediction error shifts" warning and no numpy warning: the
  unexplained-disturbance test runs on the residual centred and scaled.
- A log without noise: the analysis completes, locates the mismatch, and says that the detectable
  gain change of the row fitted exactly is not computed, with no numpy warning.
- A loop that diverged past the scale the analysis takes: the message says the loop diverged.
- A log in very small units (1e-12): its inputs move; the same elements are located.
- A flat log without noise (nothing moves, the outputs constant, while the model's output moves
  from rest): no traceback from an empty setpoint block, its fits count as exact on the scale of the
  prediction error (the output's spread is 0), and no experiment of a 1e-16 dither is recommended.
"""

import dataclasses
import warnings

import numpy as np
import pytest

from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.errors import DataFileError
from mpm_monitor.core.logged_data import check_scale, in_deviations
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.repair import RepairOptions, repair_model
from mpm_monitor.core.repair.disturbance import unexplained_disturbance
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.mpc import MpcOptions
from mpm_monitor.sim.plant import DisturbanceOptions

PLANT = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1", "y2"),
                   gain=np.array([[1.0, 0.3], [0.2, 1.5]]), time_constant=np.array([[10.0, 15.0], [8.0, 12.0]]),
                   delay=np.array([[1.0, 2.0], [2.0, 1.0]]))
MPC = MpcOptions(prediction_horizon=40, control_horizon=10)
U0, Y0 = np.array([1.0e4, -250.0]), np.array([350.0, 2.0e3])


def _log(model, n=2000, seed=0, **kw):
    return run_closed_loop(PLANT, model, n, seed=seed, mpc=MPC, **kw).as_logged_data(source="loop.csv")


def _absolute(data):
    return dataclasses.replace(data, u=data.u + U0, y=data.y + Y0, r=data.r + Y0)


def test_in_deviations_subtracts_the_operating_point_once():
    model = dataclasses.replace(PLANT, input_nominal=U0, output_nominal=Y0)
    data = _log(PLANT, n=300)
    dev = in_deviations(model, _absolute(data))
    assert dev.deviations
    np.testing.assert_allclose(dev.u, data.u, atol=1e-9)
    np.testing.assert_allclose(dev.y, data.y, atol=1e-9)
    np.testing.assert_allclose(dev.r, data.r, atol=1e-9)
    assert in_deviations(model, dev) is dev                      # never twice
    assert in_deviations(PLANT, data) is data                    # a model at the origin: as logged


def test_a_log_in_absolute_units_with_the_operating_point_gives_the_deviation_analysis():
    wrong = PLANT.with_element(0, 1, gain=0.3 * 1.6)
    data = _log(wrong)
    nominal = dataclasses.replace(wrong, input_nominal=U0, output_nominal=Y0)
    options = AnalysisOptions()
    ref = analyze(wrong, data, options)
    got = analyze(nominal, _absolute(data), options)
    assert ref.located_elements == [("y1", "u2")]
    assert got.located_elements == ref.located_elements
    for a, b in zip(ref.rows, got.rows):
        assert b.rsi == pytest.approx(a.rsi, rel=1e-6)
    assert got.repair["error_after"]["y1"] == pytest.approx(ref.repair["error_after"]["y1"], rel=1e-6)
    # Without the operating point the same absolute log is mostly offset (what the old code analysed).
    blind = detect(wrong, _absolute(data), AnalysisOptions(repair=False))
    assert blind.overall_rsi > 10 * ref.overall_rsi
    # The repair on its own converts too.
    rep = repair_model(nominal, _absolute(data), [(0, 1)], RepairOptions())
    assert rep.model.gain[0, 1] == pytest.approx(0.3, rel=0.1)


def test_a_residual_far_from_zero_raises_no_shift_warning():
    data = _log(PLANT)
    shifted = dataclasses.replace(data, y=data.y + 1.0e5, r=data.r + 1.0e5)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        report = analyze(PLANT, shifted, AnalysisOptions())
    assert not [w for w in report.warnings if "shifts" in w or "drifts" in w]
    # The test itself: the same verdict on d and on d + 1e5, d * 1e9, d * 1e-9.
    rng = np.random.default_rng(3)
    d = np.convolve(rng.standard_normal(3000), [1.0, 0.6], mode="same")
    d[1800:] += 0.5
    base = unexplained_disturbance(d)
    assert base["detected"] and base["kind"] == "step"
    for moved in (d + 1.0e5, d * 1.0e9, d * 1.0e-9):
        out = unexplained_disturbance(moved)
        assert out["detected"] and out["index"] == base["index"]
        assert out["statistic"] == pytest.approx(base["statistic"], rel=1e-6)


def test_a_residual_at_rounding_level_is_not_tested():
    rng = np.random.default_rng(4)
    d = 1e-17 * rng.standard_normal(2000)
    d[1000:] += 1e-17
    assert unexplained_disturbance(d, scale=1.0)["detected"] is False
    assert unexplained_disturbance(d)["p_value"] < 1.0           # without a scale it is a signal like any


def test_a_log_without_noise_is_analysed_and_its_exact_row_has_no_detectable_change():
    wrong = PLANT.with_element(0, 0, gain=1.2)
    data = _log(wrong, n=1500, disturbance=DisturbanceOptions(disturbance_std=0.0, noise_std=0.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        report = analyze(wrong, data, AnalysisOptions())
    assert report.located_elements == [("y1", "u1")]
    y2 = [e for e in report.elements if e.output == "y2"]
    assert y2 and all(e.detectable_gain_change is None for e in y2)
    assert any("fitted exactly" in w and "y2" in w for w in report.warnings)
    assert report.repaired_model.gain[0, 0] == pytest.approx(1.0, rel=1e-3)
    # The exact row y2 (model right, no noise) is not tested on the rounding of its fit: no mismatch.
    assert not report.rows[1].mismatch and report.rows[1].p_value == 1.0
    assert not [w for w in report.warnings if "row y2 differs" in w]


def test_a_log_without_noise_and_without_mismatch_raises_no_alarm():
    # Every row's prediction error is 0 or rounding: nothing is mismatched, on any BLAS.
    data = _log(PLANT, n=1500, disturbance=DisturbanceOptions(disturbance_std=0.0, noise_std=0.0))
    rng = np.random.default_rng(9)
    for size in (0.0, 1e-13):
        y = np.array(data.y, dtype=float) + size * np.std(data.y, axis=0) * rng.standard_normal(data.y.shape)
        report = detect(PLANT, dataclasses.replace(data, y=y), AnalysisOptions(test_all_rows=True))
        assert not any(r.mismatch for r in report.rows)
        assert all(r.p_value == 1.0 for r in report.rows)
        assert report.located_elements == []
        assert all(e.p_value == 1.0 for e in report.elements)


def test_a_flat_log_without_noise_is_analysed_and_recommends_no_vanishing_dither(tmp_path, capsys):
    from mpm_monitor.apps.cli import main as cli_main
    from mpm_monitor.core.logged_data import LoggedData
    from mpm_monitor.io.csv_log import write_log_csv
    from mpm_monitor.io.model_file import save_model

    n = 1500
    data = LoggedData(t=np.arange(n, dtype=float), r=np.zeros((n, 2)), u=np.full((n, 2), 0.5), y=np.zeros((n, 2)),
                      inputs=PLANT.inputs, outputs=PLANT.outputs, sample_time=1.0, source="flat.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        report = analyze(PLANT, data, AnalysisOptions())
    assert report.located_elements == [] and not any(r.mismatch for r in report.rows)
    assert report.experiment is None
    assert all(e.detectable_gain_change is None for e in report.elements)
    # Every output is still: named as such, not as "a log without noise?", and no element is tested.
    assert not any("fitted exactly" in w for w in report.warnings)
    assert report.warnings[0].startswith("outputs y1, y2 never move in this window (every value the same")
    assert "(no p-value, detectable_gain_change null)" in report.warnings[0]
    assert all(e.p_value is None and not e.mismatch for e in report.elements)
    # The command line: the same, exit 0, no traceback.
    save_model(PLANT, tmp_path / "m.yaml")
    write_log_csv(tmp_path / "flat.csv", data)
    assert cli_main(["analyze", "--model", str(tmp_path / "m.yaml"), "--data", str(tmp_path / "flat.csv")]) == 0
    out = capsys.readouterr()
    assert "Traceback" not in out.err and "experiment recommended" not in out.out


def test_a_diverged_loop_past_the_scale_is_named_as_diverged():
    n = 600
    t = np.arange(n, dtype=float)
    grow = np.exp(t / 1.5)                                            # 1e173 at the end
    data = dataclasses.replace(_log(PLANT, n=n), y=np.column_stack([grow, 0.01 * grow]))
    with pytest.raises(DataFileError, match="the loop diverged"):
        check_scale(PLANT, data)


def test_a_log_in_very_small_units_is_analysed_like_the_same_log_in_units():
    """Whether an input moves is judged against its own size, not against 1 (a log in units of 1e-12)."""
    wrong = PLANT.with_element(0, 1, gain=0.3 * 1.6)
    data = _log(wrong)
    tiny = dataclasses.replace(data, u=data.u * 1e-12, y=data.y * 1e-12, r=data.r * 1e-12)
    ref, got = analyze(wrong, data, AnalysisOptions(repair=False)), analyze(wrong, tiny, AnalysisOptions(repair=False))
    assert got.located_elements == ref.located_elements == [("y1", "u2")]
    assert not [w for w in got.warnings if "never move" in w]


@pytest.mark.parametrize("factor, match", [
    (1e-90, None),
    (1e-160, r"loop\.csv: the setpoints are at most [0-9.e+-]+ \(largest: 'y[12]' at t = \d+ s\): too small for the "
             r"analysis \(at least 1e-100\); rescale the units"),
    (1e60, r"loop\.csv: setpoint 'y[12]' at t = \d+ s is [0-9.e+]+: too large for the analysis"),
])
def test_a_log_in_units_the_arithmetic_cannot_carry_is_refused_in_one_line(factor, match):
    """Scaled by 1e-160 the arithmetic divided by zero (a traceback); by 1e60 numpy warned of overflows and
    by 1e80 other elements were located.  Within the range the analysis is that of the log in units."""
    wrong = PLANT.with_element(0, 1, gain=0.3 * 1.6)
    data = _log(wrong)
    scaled = dataclasses.replace(data, u=data.u * factor, y=data.y * factor, r=data.r * factor)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        if match is None:
            got = analyze(wrong, scaled, AnalysisOptions(repair=False))
            assert got.located_elements == [("y1", "u2")]
            return
        with pytest.raises(DataFileError, match=match) as info:
            analyze(wrong, scaled, AnalysisOptions(repair=False))
    assert "\n" not in str(info.value)


def test_a_row_exact_but_for_rounding_has_no_detectable_change():
    # The exact row's error is 0 or a few ulps depending on how the BLAS rounds: 1e-13 of added
    # "noise" (1e-13 of the output's spread) is still an exact fit, 1e-6 is noise.
    wrong = PLANT.with_element(0, 0, gain=1.2)
    data = _log(wrong, n=1500, disturbance=DisturbanceOptions(disturbance_std=0.0, noise_std=0.0))
    rng = np.random.default_rng(8)
    for size, exact in ((1e-13, True), (1e-6, False)):
        y = np.array(data.y, dtype=float)
        y[:, 1] += size * np.std(y[:, 1]) * rng.standard_normal(y.shape[0])
        report = detect(wrong, dataclasses.replace(data, y=y), AnalysisOptions())
        y2 = [e for e in report.elements if e.output == "y2"]
        assert y2 and all((e.detectable_gain_change is None) == exact for e in y2)
        assert any("fitted exactly" in w and "y2" in w for w in report.warnings) == exact
        if exact:     # its tests are not run on rounding either
            assert not report.rows[1].mismatch and report.rows[1].p_value == 1.0
