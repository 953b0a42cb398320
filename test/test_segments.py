"""core/segments.py: the segments of data with gaps, and the runs a response is simulated through.

References: python-control simulates an element over a run's whole sample grid with the columns held
through the gaps (built here sample by sample); numpy's lag slicing on that grid.
"""

import control
import numpy as np
import pytest

from mpm_monitor.core.arx import segment_lag_matrix, segment_rows
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.response_test import element_responses, time_constant_sensitivity
from mpm_monitor.core.segments import (GapSegments, as_segments, centred_by, gap_runs, run_lag_matrix, run_positions,
                                       segment_labels, through)

#: Grid numbers of the logged samples: gaps of 1 and 2 samples (short) and of 30 (long, max_gap 10).
GRID = np.concatenate([np.arange(0, 200), np.arange(201, 450), np.arange(452, 700), np.arange(730, 1000)])
SEGMENTS = [(0, 200), (200, 449), (449, 697), (697, 967)]
MAX_GAP = 10


def _held(x, grid):
    """``x`` (stacked logged samples) on the grid from grid[0] to grid[-1], each missing sample the last
    logged one before it; and the logged samples' places on that grid (built sample by sample)."""
    out, places, k = [], [], 0
    for g in range(int(grid[0]), int(grid[-1]) + 1):
        if k < len(grid) and grid[k] == g:
            places.append(len(out))
            out.append(x[k])
            k += 1
        else:
            out.append(out[-1])
    return np.array(out), np.array(places)


def test_the_runs_join_the_segments_across_the_short_gaps_only():
    segs = GapSegments(SEGMENTS, GRID, MAX_GAP)
    assert list(segs) == SEGMENTS and segs == SEGMENTS
    assert gap_runs(SEGMENTS, GRID, MAX_GAP) == [[0, 1, 2], [3]]
    assert [(a, b) for a, b, _ in segs.runs] == [(0, 697), (697, 967)]
    assert segs.runs[1][2] is None and segs.joined
    assert not GapSegments(SEGMENTS, GRID, 0).joined          # every gap long: a run per segment
    assert as_segments(segs) is segs and as_segments(np.array(SEGMENTS)) == SEGMENTS and as_segments(None) is None


def test_an_element_through_the_short_gaps_is_python_control_s_response_to_the_held_columns():
    """A second-order element with a dead time: the response through the runs equals python-control's
    simulation of the same sampled element over each run's whole grid, the columns held in its gaps,
    read at the logged samples; after the long gap it starts from rest."""
    model = PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1",), gain=np.array([[1.7]]),
                       time_constant=np.array([[12.0]]), time_constant2=np.array([[4.0]]), delay=np.array([[3.0]]))
    u = np.random.default_rng(3).standard_normal(GRID.size)
    segs = GapSegments(SEGMENTS, GRID, MAX_GAP)
    got = element_responses(model, 0, [0], u[:, None], segs)[0]
    sys = control.c2d(control.tf([1.7], np.polymul([12.0, 1.0], [4.0, 1.0])), 1.0, "zoh")   # the element, sampled
    for a, b, _ in segs.runs:
        held, places = _held(u[a:b], GRID[a:b])
        shifted = np.concatenate([np.zeros(3), held])[:held.size]       # the dead time, 3 samples
        ref = np.asarray(control.forced_response(sys, T=np.arange(held.size, dtype=float), U=shifted).outputs)
        np.testing.assert_allclose(got[a:b], ref.reshape(-1)[places], rtol=1e-9, atol=1e-12)
    # From rest at every segment instead (a plain list of segments): the first run differs after its gaps.
    plain = element_responses(model, 0, [0], u[:, None], SEGMENTS)[0]
    np.testing.assert_array_equal(plain[:200], got[:200])
    assert np.abs(plain[200:260] - got[200:260]).max() > 0.1
    np.testing.assert_array_equal(plain[697:], got[697:])


def test_the_time_constant_sensitivity_runs_through_the_held_response():
    x = np.cumsum(np.random.default_rng(1).standard_normal(GRID.size)) * 0.1
    segs = GapSegments(SEGMENTS, GRID, MAX_GAP)
    got = time_constant_sensitivity(x, 6.0, segs)
    p = np.exp(-1.0 / 6.0)
    for a, b, _ in segs.runs:
        held, places = _held(x[a:b], GRID[a:b])
        dx = np.diff(held, prepend=0.0)
        ref = np.zeros_like(dx)
        for k in range(dx.size):
            ref[k] = (p * ref[k - 1] if k else 0.0) + (1.0 - p) * dx[k]
        np.testing.assert_allclose(got[a:b], ref[places], rtol=1e-10, atol=1e-12)


def test_through_without_runs_is_the_function_on_each_segment_or_on_the_whole():
    x = np.arange(967, dtype=float)
    assert np.array_equal(through(x, np.cumsum), np.cumsum(x))
    got = through(x, np.cumsum, SEGMENTS)
    for a, b in SEGMENTS:
        assert np.array_equal(got[a:b], np.cumsum(x[a:b]))


@pytest.mark.parametrize("start", [5, 12])
def test_run_lags_read_the_held_grid_and_equal_the_segment_lags_inside_a_segment(start):
    rng = np.random.default_rng(7)
    x = rng.standard_normal((GRID.size, 2))
    segs = GapSegments(SEGMENTS, GRID, MAX_GAP)
    lags = range(1, 31)
    got = run_lag_matrix(x, lags, start, segs)
    place = run_positions(start, segs)
    assert got.shape == (sum(b - a - start for a, b in SEGMENTS), 60) and place.shape == (got.shape[0],)
    # The first `start` lags never leave the segment: the segments' own lag matrix.
    inside = run_lag_matrix(x, range(1, start + 1), start, segs)
    np.testing.assert_array_equal(inside, segment_lag_matrix(x, range(1, start + 1), start, SEGMENTS))
    # Every lag against the run's held grid, built sample by sample; 0 before the run's first sample.
    rows = segment_rows(np.arange(GRID.size), start, SEGMENTS)
    for r, (t, at) in enumerate(zip(rows, place)):
        a, b = next((a, b) for a, b, _ in segs.runs if a <= t < b)
        for c in range(2):
            held, places = _held(x[a:b, c], GRID[a:b])
            assert places[t - a] == at
            want = [held[at - lag] if at - lag >= 0 else 0.0 for lag in lags]
            np.testing.assert_array_equal(got[r, c * 30:(c + 1) * 30], want)
    # Without segments: one run of every sample.
    assert np.array_equal(run_positions(start, None, 50), np.arange(start, 50))
    np.testing.assert_array_equal(run_lag_matrix(x[:50], range(1, 4), start), segment_lag_matrix(x[:50], range(1, 4), start))


def test_centred_by_label_and_the_rows_segment_labels():
    X = np.random.default_rng(2).standard_normal((10, 3))
    labels = np.array([0, 0, 1, 1, 1, 0, 2, 2, 2, 2])
    got = centred_by(X, labels)
    for g in range(3):
        np.testing.assert_allclose(got[labels == g], X[labels == g] - X[labels == g].mean(axis=0), atol=1e-15)
    assert np.array_equal(segment_labels(3, [(0, 5), (5, 7), (7, 12)]), [0, 0, 2, 2])      # (5, 7) has no row
    assert np.array_equal(segment_labels(3, None, 4), np.zeros(4))


def test_level_groups_are_the_runs_for_a_row_that_keeps_one_level_through_short_gaps():
    from mpm_monitor.core.segments import centred_by_level, level_groups

    grid = np.concatenate([np.arange(5), np.arange(6, 10), np.arange(30, 36)])     # gaps of 1 and of 20 samples
    segments = GapSegments([(0, 5), (5, 9), (9, 15)], grid, 3)
    assert level_groups(segments, True).tolist() == [0, 0, 1]
    assert level_groups(segments, False).tolist() == [0, 1, 2]
    assert level_groups([(0, 5), (5, 9), (9, 15)], True).tolist() == [0, 1, 2]    # plain segments: each its own
    assert level_groups(None, True) is None
    x = np.column_stack([np.arange(15.0), np.r_[np.full(5, 1.0), np.full(4, 3.0), np.full(6, -2.0)]])
    per_run = centred_by_level(x, segments, level_groups(segments, True))
    np.testing.assert_allclose(per_run[:9], x[:9] - x[:9].mean(axis=0))
    np.testing.assert_allclose(per_run[9:], x[9:] - x[9:].mean(axis=0))
    per_segment = centred_by_level(x, segments, level_groups(segments, False))
    np.testing.assert_allclose(per_segment[:, 1], 0.0)
    np.testing.assert_allclose(centred_by_level(x, None, None), x - x.mean(axis=0))


def test_a_gap_whose_missing_samples_have_known_columns_but_short_stretches_keeps_the_run():
    """Two drops 15 samples apart with the segment between them left out (too short for a row, its columns
    logged): 17 samples off the stacked grid, but at most one unknown in a row, so one run for max_gap 10."""
    from mpm_monitor.core.segments import unknown_span

    grid = np.concatenate([np.arange(100), np.arange(117, 200)])        # 100 and 116 dropped, 101 .. 115 left out
    known = np.arange(101, 116)
    assert unknown_span(99, 117, None) == 17
    assert unknown_span(99, 117, known) == 1
    assert unknown_span(99, 117, np.array([105])) == 11
    assert unknown_span(5, 6, known) == 0
    assert gap_runs([(0, 100), (100, 183)], grid, 10) == [[0], [1]]
    assert gap_runs([(0, 100), (100, 183)], grid, 10, known) == [[0, 1]]
    assert not GapSegments([(0, 100), (100, 183)], grid, 10).joined
    assert GapSegments([(0, 100), (100, 183)], grid, 10, known).joined


#: Known columns inside GRID's gaps: the 1-sample gap (200) and the first of the 2-sample gap (450; 451 stays
#: unknown and holds it); 710 lies in the long gap, between two runs (its stretches of unknown samples stay long).
KNOWN = np.array([200, 450, 710])


def _filled(x, grid, known, values):
    """``x`` (stacked logged samples of one run) on the run's grid, the known samples at their values and every
    other missing sample the last logged or known one before it; the logged samples' places (sample by sample)."""
    by_grid = dict(zip(grid.tolist(), x))
    by_grid.update((g, v) for g, v in zip(known.tolist(), values) if grid[0] < g < grid[-1])
    out = []
    for g in range(int(grid[0]), int(grid[-1]) + 1):
        out.append(by_grid[g] if g in by_grid else out[-1])
    return np.array(out), np.array(grid - grid[0])


def test_an_element_through_gaps_with_known_columns_is_python_control_s_response_to_them():
    """The columns of missing samples known (a segment left out, a spike; GapPlan.left_out_fill): a column's
    response runs on them and holds them on, as the model's run does (signals.segment_signals); python-control's
    simulation over each run's grid is the reference.  Centred alike (centred_fill), column by column; a column
    the known samples lack (a candidate channel added since) is held as before; without ``column`` nothing is
    filled."""
    from mpm_monitor.core.segments import centred_fill

    model = PlantModel(sample_time=1.0, inputs=("u1", "u2", "u3"), outputs=("y1",), gain=np.array([[0.5, 1.7, -1.1]]),
                       time_constant=np.array([[5.0, 12.0, 7.0]]), time_constant2=np.array([[0.0, 4.0, 0.0]]),
                       delay=np.array([[1.0, 3.0, 2.0]]))
    rng = np.random.default_rng(4)
    u = rng.standard_normal((GRID.size, 3)) + 2.0
    columns = rng.standard_normal((KNOWN.size, 2)) * 5.0 + 2.0         # known samples of u1 and u2 only
    segs = GapSegments(SEGMENTS, GRID, MAX_GAP, KNOWN, columns)
    assert [(a, b) for a, b, _ in segs.runs] == [(0, 697), (697, 967)] and segs.values is None
    mean = u.mean(axis=0)
    filled = centred_fill(segs, mean)
    assert filled == segs and filled.runs is segs.runs and filled.values.shape == (3, 3)
    assert np.isnan(filled.values[:, 2]).all() and segs.values is None
    u_c = u - mean
    got = element_responses(model, 0, [0, 1, 2], u_c, filled)
    held = element_responses(model, 0, [0, 1, 2], u_c, segs)
    for j, (tau, tau2, delay) in enumerate([(5.0, 0.0, 1), (12.0, 4.0, 3), (7.0, 0.0, 2)]):
        den = np.polymul([tau, 1.0], [tau2, 1.0]) if tau2 else [tau, 1.0]
        sys = control.c2d(control.tf([model.gain[0, j]], den), 1.0, "zoh")
        for a, b, _ in segs.runs:
            known = columns[:, j] - mean[j] if j < 2 else np.full(KNOWN.size, np.nan)
            grid_x, places = _filled(u_c[a:b, j], GRID[a:b], KNOWN, known) if j < 2 else _held(u_c[a:b, j], GRID[a:b])
            shifted = np.concatenate([np.zeros(delay), grid_x])[:grid_x.size]
            ref = np.asarray(control.forced_response(sys, T=np.arange(grid_x.size, dtype=float), U=shifted).outputs)
            np.testing.assert_allclose(got[j][a:b], ref.reshape(-1)[places], rtol=1e-9, atol=1e-12)
        if j < 2:       # the known samples moved the response after the gaps (not after the long one: a new run)
            assert np.abs(got[j][200:260] - held[j][200:260]).max() > 1e-3
            np.testing.assert_array_equal(got[j][697:], held[j][697:])
        else:
            np.testing.assert_array_equal(got[j], held[j])
    np.testing.assert_array_equal(through(u_c[:, 1], model.discrete_element(0, 1).respond, filled),
                                  held[1])                                        # no column: held
    assert centred_fill(SEGMENTS, mean) is SEGMENTS and centred_fill(None, mean) is None
    assert centred_fill(segs, mean, [1]).values[:, 1].tolist() == [0.0, 0.0, 0.0]


def test_run_lags_of_a_column_read_its_known_samples_in_the_gaps():
    """run_lag_matrix with ``column``: the lags read the known samples inside a run's gaps (and hold them), as the
    model's run; every other lag as without them."""
    from mpm_monitor.core.segments import centred_fill

    rng = np.random.default_rng(8)
    x = rng.standard_normal((GRID.size, 2))
    columns = rng.standard_normal((KNOWN.size, 2)) + 3.0
    filled = centred_fill(GapSegments(SEGMENTS, GRID, MAX_GAP, KNOWN, columns), np.zeros(2))
    lags, start = range(1, 8), 5
    place = run_positions(start, filled)
    rows = segment_rows(np.arange(GRID.size), start, SEGMENTS)
    for c in range(2):
        got = run_lag_matrix(x[:, c], lags, start, filled, c)
        plain = run_lag_matrix(x[:, c], lags, start, filled)
        assert np.abs(got - plain).max() > 0.1
        for r, (t, at) in enumerate(zip(rows, place)):
            a, b = next((a, b) for a, b, _ in filled.runs if a <= t < b)
            grid_x, _ = _filled(x[a:b, c], GRID[a:b], KNOWN, columns[:, c])
            want = [grid_x[at - lag] if at - lag >= 0 else 0.0 for lag in lags]
            np.testing.assert_array_equal(got[r], want)
