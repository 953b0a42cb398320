"""Spikes in a log (core/spikes.py): what is one and what is not, and the analysis without them.

The level on clean logs and the located elements with spikes are bench/spikes_mc.py.
"""

import dataclasses

import numpy as np
import pytest
from scipy import stats

from mpm_monitor.apps.cli import build_parser
from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.logged_data import LoggedData
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.spikes import (MAX_SPIKE, SPIKE_THRESHOLD, change_scale, find_spikes, spike_mask,
                                     without_spikes)
from mpm_monitor.sim.closed_loop import run_closed_loop
from mpm_monitor.sim.mpc import MpcOptions

RNG = np.random.default_rng(4)
NOISE = RNG.normal(size=600)


def _flagged(x, segments=None):
    return list(np.flatnonzero(spike_mask(x, segments or [(0, len(x))])))


def test_the_scale_is_the_normal_mad_of_the_changes():
    d = np.diff(NOISE)
    assert change_scale(NOISE, [(0, 600)]) == pytest.approx(stats.median_abs_deviation(d, scale="normal"))
    # Across a gap no change is taken: the two segments' own changes only.
    x = np.concatenate([NOISE[:300], 1e6 + NOISE[300:]])
    assert change_scale(x, [(0, 300), (300, 600)]) == pytest.approx(
        stats.median_abs_deviation(np.concatenate([np.diff(x[:300]), np.diff(x[300:])]), scale="normal"))
    # A quantized channel (most changes 0): the median nonzero |change|; a constant one: 0.
    q = np.zeros(600)
    q[100:103] = 0.1
    assert change_scale(q, [(0, 600)]) == pytest.approx(0.1)
    assert change_scale(np.ones(50), [(0, 50)]) == 0.0


@pytest.mark.parametrize("m", range(1, MAX_SPIKE + 1))
def test_bursts_of_one_to_three_samples_that_come_back_are_spikes(m):
    for sign in (1.0, -1.0):
        x = NOISE.copy()
        x[200:200 + m] += sign * 40.0
        assert _flagged(x) == list(range(200, 200 + m))


def test_what_is_not_a_spike():
    s = change_scale(NOISE, [(0, 600)])
    x = NOISE.copy()
    x[200:200 + MAX_SPIKE + 1] += 40.0                    # four samples: a burst too long
    assert _flagged(x) == []
    x = NOISE.copy()
    x[300:] += 40.0                                      # a step: the channel stays at its new level
    assert _flagged(x) == []
    x = NOISE + np.linspace(0.0, 300.0, 600)             # a ramp
    assert _flagged(x) == []
    x = NOISE.copy()                                     # a controller's kick that decays: it does not come back
    x[200:260] += 40.0 * np.exp(-np.arange(60) / 3.0) + 15.0
    assert _flagged(x) == []
    x = NOISE.copy()
    x[200] += 0.9 * SPIKE_THRESHOLD * s                  # below the threshold
    assert _flagged(x) == []
    x[200] += 0.3 * SPIKE_THRESHOLD * s                  # above it
    assert _flagged(x) == [200]


def test_a_controller_move_on_an_almost_still_input_is_not_a_spike():
    """An MPC input that barely moves but for its moves after a setpoint step (the values of an outside
    loop: 0.730, 0.822, 0.849, 0.820, 0.749, 0.666 ...): its robust scale is tiny, the hump is far
    beyond it, but the moves around the hump are as large; a glitch of the same channel is still one."""
    rng = np.random.default_rng(4)
    x = 0.73 + 1e-4 * rng.standard_normal(400)
    move = [0.822, 0.849, 0.820, 0.749, 0.666, 0.60, 0.56, 0.54, 0.53]
    x[200:200 + len(move)] = move
    x[200 + len(move):] = 0.53 + 1e-4 * rng.standard_normal(400 - 200 - len(move))
    assert _flagged(x) == []
    x[300] += 5.0
    assert _flagged(x) == [300]


def test_an_mpc_kick_at_a_setpoint_step_is_not_a_spike():
    """A quiet loop's MPC answers a setpoint step with one or two large moves that come back (case 3.1
    under setpoint steps: u2 -0.148, 0.847, 0.949, 0.965, -0.24): the loop's most informative samples.
    The same burst with no setpoint step near it is a spike."""
    n = 400
    rng = np.random.default_rng(6)
    r = np.zeros((n, 1))
    r[250:] = 1.0
    u = -0.15 + 0.005 * rng.standard_normal((n, 1))
    u[250:253, 0] = [0.847, 0.949, 0.965]
    u[253:, 0] = -0.24 + 0.005 * rng.standard_normal(n - 253)
    y = 0.01 * rng.standard_normal((n, 1))
    data = LoggedData(t=np.arange(n, dtype=float), r=r, u=u, y=y, inputs=("u",), outputs=("y",), sample_time=1.0)
    assert find_spikes(data) == {}
    moved = dataclasses.replace(data, r=(np.arange(n) >= 300).astype(float)[:, None])   # the step 50 samples later
    assert list(np.flatnonzero(find_spikes(moved)["u"])) == [250, 251, 252]


def test_a_glitch_at_a_setpoint_step_of_a_busy_loop_is_still_a_spike():
    """Setpoints switching every few samples put a step near every sample: an input glitch there is
    far larger than the input's usual moves at the steps, so it is a spike (the paper cases' spiked
    logs located every element when such glitches were spared)."""
    n = 400
    rng = np.random.default_rng(8)
    r = np.sign(rng.standard_normal((n, 1)))
    u = 0.1 * rng.standard_normal((n, 1))
    k = 200 + int(np.flatnonzero(r[201:, 0] != r[200:-1, 0])[0]) + 1      # a sample where the setpoint steps
    u[k, 0] += 5.0
    y = 0.01 * rng.standard_normal((n, 1))
    data = LoggedData(t=np.arange(n, dtype=float), r=r, u=u, y=y, inputs=("u",), outputs=("y",), sample_time=1.0)
    assert list(np.flatnonzero(find_spikes(data)["u"])) == [k]


def test_edges_and_gaps():
    x = NOISE.copy()
    x[0] += 50.0                                         # the first sample has one neighbour only
    x[599] += 50.0
    x[300] += 50.0                                       # the first sample after a gap
    assert _flagged(x, [(0, 300), (300, 600)]) == []
    assert _flagged(x) == [300]                          # the same sample inside one segment


def test_a_quantized_channel_keeps_its_toggles_but_not_a_glitch():
    q = np.round(np.cumsum(RNG.normal(scale=0.02, size=600)) / 0.05) * 0.05
    assert _flagged(q) == []
    q[400] += 5.0
    assert _flagged(q) == [400]


PLANT = PlantModel(sample_time=1.0, inputs=("u1", "u2"), outputs=("y1", "y2"),
                   gain=np.array([[1.0, 0.4], [0.3, 1.2]]), time_constant=np.array([[10.0, 14.0], [8.0, 12.0]]),
                   delay=np.array([[1.0, 2.0], [2.0, 1.0]]))


@pytest.fixture(scope="module")
def loop():
    model = PLANT.with_element(0, 1, gain=0.2)
    data = run_closed_loop(PLANT, model, 2000, seed=3, mpc=MpcOptions(prediction_horizon=40, control_horizon=10)) \
        .as_logged_data(source="loop.csv")
    return model, data


def test_a_clean_closed_loop_log_has_no_spike(loop):
    _, data = loop
    assert find_spikes(data) == {}
    same, note = without_spikes(data)
    assert same is data and note is None


def test_the_analysis_leaves_the_spikes_out_and_says_so(loop):
    model, data = loop
    options = AnalysisOptions(repair=False)
    clean = analyze(model, data, options)
    assert clean.located_elements == [("y1", "u2")]
    y, u = data.y.copy(), data.u.copy()
    y[700, 0] += 300.0 * y[:, 0].std()                   # a glitch on y1 and a two-sample one on u2
    u[1300:1302, 1] -= 100.0 * u[:, 1].std()
    spiked = dataclasses.replace(data, y=y, u=u)
    found = find_spikes(spiked)
    assert sorted(found) == ["u2", "y1"]
    assert list(np.flatnonzero(found["y1"])) == [700] and list(np.flatnonzero(found["u2"])) == [1300, 1301]
    report = analyze(model, spiked, options)
    assert report.located_elements == [("y1", "u2")]
    assert report.samples < data.n_samples and report.gaps["samples_missing"] == 3
    note = report.warnings[0]
    assert note.startswith("loop.csv: spikes") and "y1 at t = 700 s" in note and "u2 at t = 1300 s" in note
    assert "3 samples left out as missing samples" in note
    # The option turns it off: the spikes stay in the data the tests fit.
    kept, none = without_spikes(spiked, threshold=1e9)
    assert kept is spiked and none is None
    assert not AnalysisOptions(drop_spikes=False).drop_spikes


def test_the_command_line_turns_it_off():
    args = build_parser().parse_args(["analyze", "--model", "m.yaml", "--data", "d.csv", "--no-drop-spikes"])
    assert args.drop_spikes is False
    args = build_parser().parse_args(["analyze", "--model", "m.yaml", "--data", "d.csv"])
    assert args.drop_spikes is True


def test_logged_data_without_spikes_keeps_other_notes():
    t = np.arange(100.0)
    x = NOISE[:100].copy()
    x[50] += 80.0
    data = LoggedData(t=t, r=np.zeros((100, 1)), u=NOISE[100:200, None].copy(), y=x[:, None], inputs=("u1",),
                      outputs=("y1",), sample_time=1.0, source="s.csv", notes=("an earlier note",))
    kept, note = without_spikes(data)
    assert kept.n_samples == 99 and kept.notes == ("an earlier note", note)
    assert data.notes == ("an earlier note",)


def test_two_processes_find_the_same_spikes(loop):
    # Each channel is examined by itself, so the halves of the channels split over two processes give the
    # same masks, kicks spared included (an input's glitch near a setpoint step is judged in the parent).
    _, data = loop
    y, u, r = data.y.copy(), data.u.copy(), data.r.copy()
    y[700, 0] += 300.0 * y[:, 0].std()
    u[1300:1302, 1] -= 100.0 * u[:, 1].std()
    y[1500:1503, 1] += 80.0 * y[:, 1].std()
    r[900, 1] += 50.0 * (np.abs(r[:, 1]).max() + 1.0)
    spiked = dataclasses.replace(data, y=y, u=u, r=r)
    one = find_spikes(spiked)
    two = find_spikes(spiked, jobs=2)
    assert sorted(one) == sorted(two) and len(one) >= 3
    assert all(np.array_equal(one[k], two[k]) for k in one)
    kept_one, note_one = without_spikes(spiked)
    kept_two, note_two = without_spikes(spiked, jobs=2)
    assert note_one == note_two and np.array_equal(kept_one.t, kept_two.t)
