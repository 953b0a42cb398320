"""Data with gaps: the model run takes the logged columns of a segment too short for a regression row
(:meth:`~mpm_monitor.core.gaps.GapPlan.left_out_fill`) instead of holding its columns through it."""

import numpy as np

from mpm_monitor.core.analysis import AnalysisOptions
from mpm_monitor.core.gaps import plan_gaps
from mpm_monitor.core.logged_data import in_deviations
from mpm_monitor.core.pipeline import analyze
from mpm_monitor.core.signals import segment_signals

DETECT = AnalysisOptions(repair=False)


def test_the_model_runs_on_the_logged_columns_of_a_segment_too_short_for_a_row():
    """Two samples dropped 10 apart leave a segment of 9 samples between them, too short for a regression row: it
    is left out of the stacked rows, but the model runs on its logged columns (it held them through the whole
    span before), so the prediction error is the one of the model run over every logged sample (from rest, the
    initial state not estimated: the same numbers).  The model's run is compared without the fitted response to
    the unknown columns of the two missing samples (:func:`~mpm_monitor.core.gap_inputs.gap_response`), which is
    fitted on the rows each run keeps."""
    from mpm_monitor.apps.reproduce import simulate_case

    case, data, _ = simulate_case("3.2", 1500, 1000)
    model = case.model
    data = in_deviations(model, data.take(np.setdiff1d(np.arange(data.n_samples), [700, 710])))
    plan = plan_gaps(data, 17, 17)
    assert len(plan.segments) == 3 and len(plan.used) == 2          # the 9 samples between are left out
    fill = plan.left_out_fill(data)
    assert fill[0].tolist() == list(range(701, 710))
    grid = plan.take(data.grid_index)
    kept = segment_signals(model, plan.take(data.r), plan.take(data.u), plan.take(data.y), plan.local_segments,
                           "zero", grid=grid, max_gap=plan.max_gap, fill=fill, gap_inputs=False)
    every = segment_signals(model, data.r, data.u, data.y, data.segments, "zero", grid=data.grid_index,
                            max_gap=plan.max_gap, gap_inputs=False)
    np.testing.assert_allclose(kept.d, plan.take(every.d), atol=1e-12)
    held = segment_signals(model, plan.take(data.r), plan.take(data.u), plan.take(data.y), plan.local_segments,
                           "zero", grid=grid, max_gap=plan.max_gap, gap_inputs=False)
    assert np.abs(held.d - plan.take(every.d)).max() > 1e-3       # what holding through the span did


def test_two_drops_a_few_samples_apart_no_longer_hold_the_model_through_the_span_between():
    """bench.gaps_mc's structures run 57 of seed 2 (clean; seven samples dropped, two of them 16 apart): the 15
    samples between were left out and the model held its columns through all 17, which put a transient of 20
    times the noise into y3's prediction error; the whiteness check raised ``na`` to 16 and (y1, u3) was located.
    With the model run on the logged columns between, nothing is located, as in the whole log."""
    from bench.gaps_mc import DROP, drop_rows
    from bench.monte_carlo import family_log

    model, _, data, truth = family_log("structures", "57", 2, 3000)
    kept = drop_rows(data.n_samples, DROP, np.random.default_rng([2, 57, 8]))
    assert truth == [] and np.setdiff1d(np.arange(data.n_samples), kept).tolist() == \
        [178, 824, 2063, 2079, 2207, 2363, 2368]
    whole = analyze(model, data, DETECT)
    gappy = analyze(model, data.take(kept), DETECT)
    assert whole.located_elements == [] and gappy.located_elements == []
    assert gappy.noise_order["na"] == 4


def test_drops_around_a_left_out_segment_longer_than_max_gap_do_not_restart_the_model():
    """Two samples dropped 14 apart leave 13 samples between them, too short for a regression row (17): with
    ``max_gap`` 10 the stacked rows jump 15 samples, but only one sample at a time is unknown (the 13 between
    are logged), so the model runs through both drops on the logged columns (it restarted from rest after the
    span before): the prediction error of the model run over every logged sample."""
    from mpm_monitor.apps.reproduce import simulate_case
    from mpm_monitor.core.segments import GapSegments

    case, data, _ = simulate_case("3.2", 1500, 1000)
    model = case.model
    data = in_deviations(model, data.take(np.setdiff1d(np.arange(data.n_samples), [700, 714])))
    plan = plan_gaps(data, 17, 10)
    assert len(plan.used) == 2 and plan.gap_lengths.tolist() == [1, 1]
    fill = plan.left_out_fill(data)
    grid = plan.take(data.grid_index)
    assert GapSegments(plan.local_segments, grid, plan.max_gap, fill[0]).joined
    kept = segment_signals(model, plan.take(data.r), plan.take(data.u), plan.take(data.y), plan.local_segments,
                           "zero", grid=grid, max_gap=plan.max_gap, fill=fill, gap_inputs=False)
    every = segment_signals(model, data.r, data.u, data.y, data.segments, "zero", grid=data.grid_index,
                            max_gap=plan.max_gap, gap_inputs=False)
    np.testing.assert_allclose(kept.d, plan.take(every.d), atol=1e-12)


def test_an_elements_response_runs_on_the_logged_columns_of_a_segment_left_out(monkeypatch):
    """The whole-response test's regressors (each element's response to its column) run on the logged columns of
    a segment too short for a row, as the model's run does: with the two drops of the first test, every
    element's response at the stacked samples is its response over every logged sample (the two unknown samples
    held), centred alike; held through the 11 samples as before, it was not.  The analysis hands those columns
    to the tests (its regressions' segments)."""
    from mpm_monitor.apps.reproduce import simulate_case
    from mpm_monitor.core.discretize import model_columns
    from mpm_monitor.core.response_test import element_responses
    from mpm_monitor.core.segments import GapSegments, centred_fill

    case, data, _ = simulate_case("3.2", 1500, 1000)
    model = case.model
    data = in_deviations(model, data.take(np.setdiff1d(np.arange(data.n_samples), [700, 710])))
    plan = plan_gaps(data, 17, 17)
    fill = plan.left_out_fill(data)
    grid = plan.take(data.grid_index)
    segs = GapSegments(plan.local_segments, grid, plan.max_gap, fill[0], fill[1])
    u = model_columns(plan.take(data.u), None)
    mean = u.mean(axis=0)
    every = GapSegments(data.segments, data.grid_index, plan.max_gap)
    assert len(every.runs) == 1
    columns = range(model.n_columns)
    for i in range(model.n_outputs):
        got = element_responses(model, i, columns, u - mean, centred_fill(segs, mean))
        want = element_responses(model, i, columns, model_columns(data.u, None) - mean, every)
        held = element_responses(model, i, columns, u - mean, segs)
        assert set(got) == set(want) and got
        for j in got:
            np.testing.assert_allclose(got[j], plan.take(want[j]), rtol=1e-10, atol=1e-12)
            assert np.abs(held[j] - got[j]).max() > 1e-3 * np.abs(got[j]).max()
    from mpm_monitor.core.response_moments import ResponseMoments

    seen = []
    init = ResponseMoments.__init__

    def spied(self, *args, **kwargs):
        init(self, *args, **kwargs)
        seen.append(self.segments)

    monkeypatch.setattr(ResponseMoments, "__init__", spied)
    analyze(model, data, DETECT)
    assert seen and all(list(g) == list(segs) for g in seen)
    np.testing.assert_array_equal(seen[0].values, fill[1] - mean)
