"""core.resolution: the grid a channel is logged on, and the warning about outputs logged coarser than their noise."""

import numpy as np
import pytest

from mpm_monitor.core.resolution import RESOLUTION_RATIO, resolution, resolution_warnings


@pytest.mark.parametrize("step", [0.01, 0.1, 0.25, 2.0, 1e-4])
def test_a_rounded_channel_gives_its_step_also_about_an_operating_point(step):
    rng = np.random.default_rng(1)
    x = np.round(np.cumsum(rng.normal(size=2000)) * 0.05 / step) * step
    assert resolution(x) == pytest.approx(step, rel=1e-6)
    assert resolution(x - 350.0) == pytest.approx(step, rel=1e-6)       # in deviations from an operating point


def test_no_grid_for_a_channel_logged_to_full_precision_or_with_too_few_values():
    rng = np.random.default_rng(2)
    assert resolution(rng.normal(size=3000)) is None
    assert resolution(np.cumsum(rng.normal(size=3000))) is None
    assert resolution(np.r_[np.zeros(10), np.ones(10)]) is None            # a switch: two values
    assert resolution(np.full(50, 3.0)) is None
    # Values on a grid but for one off it: no grid.
    x = np.round(rng.normal(size=500) * 10) / 10
    x[7] = 0.1234567
    assert resolution(x) is None


def test_the_warning_names_the_outputs_coarser_than_the_ratio_times_their_noise():
    rng = np.random.default_rng(3)
    n = 3000
    d = rng.normal(size=(n, 3)) * np.array([1.0, 1.0, 0.01])
    y = np.cumsum(rng.normal(size=(n, 3)), axis=0) + d
    coarse = RESOLUTION_RATIO * 1.3
    y[:, 0] = np.round(y[:, 0] / coarse) * coarse                            # coarser than 1.5 x its noise of 1
    y[:, 1] = np.round(y[:, 1] / 0.5) * 0.5                                  # finer
    (w,) = resolution_warnings(["y1", "y2", "y3"], y, d.std(axis=0))
    assert w.startswith("outputs logged with a coarse resolution: y1 in steps of 1.95 (1.9")
    assert "y2" not in w and "y3" not in w
    assert resolution_warnings(["y1", "y2", "y3"], y, d.std(axis=0), skip=[0]) == []
    assert resolution_warnings(["y1", "y2", "y3"], y, np.zeros(3)) == []     # no error to compare with


def test_analyze_warns_about_a_log_rounded_coarser_than_its_noise_and_not_about_the_log_itself():
    import dataclasses

    from mpm_monitor.apps.reproduce import simulate_case
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze

    case, data, _ = simulate_case("3.2", 3000, 0)
    options = AnalysisOptions(repair=False)
    assert not any("coarse resolution" in w for w in analyze(case.model, data, options).warnings)
    fine = dataclasses.replace(data, y=np.round(np.asarray(data.y), 3))       # three decimals: far below the noise
    assert not any("coarse resolution" in w for w in analyze(case.model, fine, options).warnings)
    coarse = dataclasses.replace(data, y=np.round(np.asarray(data.y) * 2) / 2)
    (w,) = [w for w in analyze(case.model, coarse, options).warnings if "coarse resolution" in w]
    assert all(f"{name} in steps of 0.5 (" in w for name in case.model.outputs)


def test_the_first_samples_decide_only_what_the_whole_column_would():
    """The warning's shortcut (the smallest gap among the first samples) rules out only outputs that the whole
    column rules out too: a log at rest at its start, on a coarse grid later, is still named."""
    rng = np.random.default_rng(4)
    n = 3000
    d = rng.normal(size=(n, 2)) * 0.1
    y = np.zeros((n, 2))
    y[600:, 0] = np.round(np.cumsum(rng.normal(size=n - 600)) / 0.5) * 0.5     # at rest, then on a grid of 0.5
    y[:, 1] = np.cumsum(rng.normal(size=n))
    y[:300, 1] = np.round(y[:300, 1] / 0.5) * 0.5                               # on the grid at its start only
    (w,) = resolution_warnings(["y1", "y2"], y, d.std(axis=0))
    assert "y1 in steps of 0.5 (" in w and "y2" not in w


def test_an_input_is_named_when_its_step_through_the_largest_gain_exceeds_the_ratio_times_the_row_noise():
    from mpm_monitor.core.resolution import column_resolution_warnings

    rng = np.random.default_rng(5)
    n = 3000
    d = rng.normal(size=(n, 2)) * np.array([0.1, 1.0])
    x = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    x[:, 0] = np.round(x[:, 0] / 0.2) * 0.2        # through gain 1 to y1: 2 x its noise of 0.1
    x[:, 1] = np.round(x[:, 1] / 0.2) * 0.2        # its gain to y1 integrates, to y2 is 1: 0.2 x y2's noise
    x[:, 2] = np.round(x[:, 2] / 0.05) * 0.05      # 0.5 x y1's noise
    gain = np.array([[1.0, 3.0, 1.0], [0.5, 1.0, 0.0]])
    integrating = np.array([[False, True, False], [False, False, False]])
    (w,) = column_resolution_warnings(["u1", "u2", "u3"], ["y1", "y2"], x, gain, integrating, d.std(axis=0))
    assert w.startswith("inputs logged with a coarse resolution: u1 in steps of 0.2 (through its gain to y1, 1.98 times")
    assert "u2" not in w and "u3" not in w
    assert column_resolution_warnings(["u1", "u2", "u3"], ["y1", "y2"], x, gain, integrating, d.std(axis=0), skip=[0]) == []


def test_analyze_warns_about_inputs_rounded_coarser_than_their_effect_allows():
    import dataclasses

    from mpm_monitor.apps.reproduce import simulate_case
    from mpm_monitor.core.analysis import AnalysisOptions
    from mpm_monitor.core.pipeline import analyze

    case, data, _ = simulate_case("3.2", 3000, 0)
    options = AnalysisOptions(repair=False)
    plain = analyze(case.model, data, options)
    assert not any("coarse resolution" in w for w in plain.warnings)
    coarse = dataclasses.replace(data, u=np.round(np.asarray(data.u) * 10) / 10)   # gains about 5, noise about 0.1
    (w,) = [w for w in analyze(case.model, coarse, options).warnings if "coarse resolution" in w]
    assert w.startswith("inputs logged with a coarse resolution: u1 in steps of 0.1 (through its gain to y")
