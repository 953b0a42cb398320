"""A flagged row whose RSI exceeds RSI_NEAR_INSTABILITY is named as a loop near instability, with the
frequency and period where the mismatch amplifies it (row_test.near_instability_warnings)."""

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.row_test import RSI_NEAR_INSTABILITY, RowResult, near_instability_warnings
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.mpc import MpcOptions

MODEL = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1",), gain=np.array([[2.0]]),
                   time_constant=np.array([[10.0]]), delay=np.array([[4.0]]))
MPC = MpcOptions(prediction_horizon=30, control_horizon=5, input_rate_weight=0.1)


def _row(name, rsi, mismatch=True):
    return RowResult(output=name, rsi=rsi, mismatch=mismatch, p_value=0.0, p_value_raw=0.0, statistic=1.0,
                     df=(1, 1), fit_percent=0.0)


def test_the_warning_names_the_peak_frequency_and_period_or_the_steady_state():
    w = np.array([0.0, 0.1, 0.5, 1.0])
    gains = np.array([[1.0, 1.2, 6.0, 1.0],      # peak at 0.5 rad/sample: period 2 pi / 0.5 * 2 s = 25.1 s
                      [9.0, 2.0, 1.0, 1.0],      # peak at 0
                      [1.0, 8.0, 1.0, 1.0],      # not flagged: no warning
                      [1.0, 2.9, 1.0, 1.0]])     # below the limit
    rows = [_row("y1", 6.0), _row("y2", 9.0), _row("y3", 8.0, mismatch=False), _row("y4", 2.9)]
    out = near_instability_warnings(rows, w, gains, 2.0)
    assert len(out) == 2 and RSI_NEAR_INSTABILITY == 3.0
    assert out[0].startswith("row y1: RSI 6,") and "at 0.5 rad/sample (period 25.1 s)" in out[0]
    assert out[1].startswith("row y2: RSI 9,") and "in steady state (frequency 0)" in out[1]
    # An integrating output's peak at frequency 0 is its ARX's root near 1, not the loop's: not named.
    assert near_instability_warnings(rows, w, gains, 2.0, (False, True, False, False)) == out[:1]


def test_a_loop_driven_near_instability_by_its_gain_error_is_named_and_a_matching_one_is_not():
    for factor, named in ((1.0, False), (3.0, True)):
        log = run_closed_loop(MODEL.with_element(0, 0, gain=2.0 * factor), MODEL, 3000, seed=1, mpc=MPC)
        rep = analyze(MODEL, log.as_logged_data("gain x%g" % factor), AnalysisOptions(repair=False))
        found = [w for w in rep.warnings if "runs close to instability" in w]
        assert bool(found) == named, (factor, rep.warnings)
        if named:
            # The period named is where the loop rings: the peak of the control error's periodogram
            # (numpy's FFT, beyond the slowest few bins of the setpoint steps), 14.7 s here.
            period = float(found[0].split("(period ")[1].split(" s)")[0])
            e = (log.y - log.r)[:, 0]
            power = np.abs(np.fft.rfft(e - e.mean())) ** 2
            k = 5 + int(np.argmax(power[5:]))
            assert abs(period * np.fft.rfftfreq(e.size)[k] - 1.0) < 0.1 and rep.rows[0].rsi > RSI_NEAR_INSTABILITY
