"""bench.gaps_mc: its structures family (measured disturbances) and the step-response form."""

import numpy as np

from bench import gaps_mc, structures_mc
from bench.monte_carlo import family_log
from bench.step_models import step_form


def test_the_structures_family_carries_its_measured_disturbances_into_the_live_window():
    model, plant, data, truth = family_log("structures", "1", 0, 400)
    sc = structures_mc.make_structures_scenario(0, 1)
    assert model == sc.model and plant == sc.plant and model.n_disturbances == 1
    # Run 1's mismatches: (y1, column 2) -- its measured disturbance -- and (y3, u2), by name.
    assert truth == [["y1", "dv1"], ["y3", "u2"]]
    kept = gaps_mc.drop_rows(data.n_samples, 0.01, np.random.default_rng(3))
    live = gaps_mc.live_window_data(data, kept)
    offline = data.take(kept)
    assert live.n_samples == offline.n_samples < data.n_samples
    for key in ("r", "u", "dv", "y"):
        assert np.array_equal(getattr(live, key), getattr(offline, key))


def test_a_run_with_the_step_response_form_analyses_that_form(monkeypatch):
    args = ("structures", "7", 0, 1500, 0.002)
    seen, located = [], gaps_mc._located
    monkeypatch.setattr(gaps_mc, "_located", lambda model, data: seen.append(model.is_step_response) or
                        located(model, data))
    rec = gaps_mc.run_one(*args, step=True)
    assert seen == [True] * 3                       # the full log, offline and live
    assert all("error" not in rec[k] for k in ("full", "offline", "live"))
    assert rec["truth"] == [["y3", "dv1"]]           # column 4 of 4 inputs and 2 measured disturbances
    model, _, data, _ = family_log(*args[:4])
    assert rec["full"] == gaps_mc._located(step_form(model), data)
    tasks = gaps_mc.tasks(1, 1, 0, 1500, 0.002, step=True, structures=2)
    assert [t[0] for t in tasks] == ["paper"] * 3 + ["mc", "structures", "structures"] and all(t[6] for t in tasks)


def test_the_cut_reference_loses_as_many_rows_at_the_end(monkeypatch):
    """``--cut``: the log without drops, cut short by the regression rows the drops lose."""
    seen, located = [], gaps_mc._located
    monkeypatch.setattr(gaps_mc, "_located", lambda model, data: seen.append(data) or located(model, data))
    rec = gaps_mc.run_one("mc", "3", 0, 1500, 0.01, cut=True)
    full, offline, _, cut = seen
    assert offline.n_samples < full.n_samples and rec["offline"]["rows_lost"] > full.n_samples - offline.n_samples
    assert cut.n_samples == full.n_samples - rec["offline"]["rows_lost"] and len(cut.segments) == 1
    assert np.array_equal(cut.y, full.y[:cut.n_samples])
    assert rec["same_cut"] == (rec["full"]["located"] == rec["cut"]["located"] and rec["full"]["rows"] == rec["cut"]["rows"])
    summary = gaps_mc.summarize([rec])
    assert summary["mc"]["same_cut"] == float(rec["same_cut"])
    assert "cut short" in gaps_mc.format_table(summary, 0.01)


def test_bursts_drop_about_the_fraction_asked_in_runs_of_the_mean_length():
    """``--burst``: runs of dropped samples, geometric lengths of the mean asked, about the fraction asked
    dropped; the first and last samples kept; the default (each sample on its own) draws as before."""
    n = 200_000
    kept = gaps_mc.drop_bursts(n, 0.01, 5.0, np.random.default_rng(4))
    assert kept[0] == 0 and kept[-1] == n - 1 and np.all(np.diff(kept) > 0)
    lengths = np.diff(kept)[np.diff(kept) > 1] - 1
    assert 4.5 < lengths.mean() < 5.5                     # bursts that overlap join: a little longer
    assert 0.008 < 1 - kept.size / n < 0.0105             # overlapping bursts drop a little less
    assert np.mean(lengths > 10) > 0.05                   # some longer than the live window's max_gap
    single = gaps_mc.drop_rows(n, 0.01, np.random.default_rng(4))
    gaps = np.diff(single)[np.diff(single) > 1] - 1
    assert gaps.mean() < 1.05                             # each sample on its own: gaps of one sample


def test_a_run_with_bursts_records_its_gaps(monkeypatch):
    seen, located = [], gaps_mc._located
    monkeypatch.setattr(gaps_mc, "_located", lambda model, data: seen.append(data) or located(model, data))
    rec = gaps_mc.run_one("mc", "3", 0, 1500, 0.02, burst=6.0)
    full, offline, live = seen
    held = np.asarray(offline.grid_index)
    assert rec["gaps"] == int(np.sum(np.diff(held) > 1)) > 0
    assert rec["longest_gap"] == int(np.max(np.diff(held))) - 1 > 1
    assert rec["dropped"] == full.n_samples - offline.n_samples
    summary = gaps_mc.summarize([rec])
    assert summary["mc"]["gaps_per_run"] == rec["gaps"]
    assert "bursts of mean length 6" in gaps_mc.format_table(summary, 0.02, 6.0)
    assert rec["longest_gap"] == 12                       # the live window restarted after it (max_gap 10) ...
    assert live.n_samples < offline.n_samples
    seen.clear()
    again = gaps_mc.run_one("mc", "3", 0, 1500, 0.02, burst=6.0, split_gap=1500)   # ... but not with split_gap
    assert again["dropped"] == rec["dropped"] and seen[2].n_samples == offline.n_samples
    np.testing.assert_array_equal(seen[2].t, offline.t)


def test_gap_transients_records_and_counts_a_run():
    """bench.gap_transients: one run's record (the same drops as bench.gaps_mc's for the same run) and its table."""
    from bench import gap_transients

    rec = gap_transients.run_one("paper", "3.1", 1000, 1500, 0.01)
    model, _, data, _ = family_log("paper", "3.1", 1000, 1500)
    kept = gaps_mc.drop_rows(data.n_samples, 0.01, np.random.default_rng([1000, 0]))
    assert rec["dropped"] == data.n_samples - kept.size > 0
    for key in ("full", "offline"):
        assert set(rec[key]) == {"located", "na", "disturbances"} and rec[key]["na"] >= 4
    assert rec["same"] == (rec["full"]["located"] == rec["offline"]["located"])
    summary = gap_transients.summarize([rec])
    assert summary["paper"]["runs"] == 1 and summary["all"]["clean_runs"] == 1
    assert "same located" in gap_transients.format_table(summary, 0.01)
