"""bench.timeline: the command's processes, from the marks they write (synthetic marks, and one small run)."""

import pytest

from bench import timeline

P, C1, C2 = 100, 101, 102


def _marks():
    # The parent starts at 10 s, forks a child (1) at 11 s that works until 13 s while the parent works too,
    # waits for it from 12 s to 13.1 s, then runs alone; a second child (2) works from 13.5 to 14 s.
    return sorted([
        (10.0, P, "start", ""),
        (10.5, P, "begin", "analyze"), (10.6, P, "begin", "detect_unless_coloured"),
        (11.0, C1, "child start", "split_map/take_all"), (13.0, C1, "child end", "split_map/take_all"),
        (13.1, C1, "child sent", ""),
        (12.0, P, "wait", ""), (13.1, P, "got", ""),
        (13.2, P, "finish", "detect_unless_coloured"), (13.3, P, "begin", "repair_model"),
        (13.5, C2, "child start", "_detect/values_and_experiment"),
        (14.0, C2, "child end", "_detect/values_and_experiment"), (14.0, C2, "child sent", ""),
        (14.5, P, "finish", "repair_model"), (14.6, P, "finish", "analyze"), (15.0, P, "end", ""),
    ])


def test_busy_intervals_occupancy_and_phases_of_synthetic_marks():
    marks = _marks()
    iv = timeline.busy_intervals(marks)
    assert iv["parent"] == [(0.0, pytest.approx(2.0)), (pytest.approx(3.1), pytest.approx(5.0))]
    assert iv["1 split_map/take_all"] == [(pytest.approx(1.0), pytest.approx(3.1))]
    assert iv["2 _detect/values_and_experiment"] == [(pytest.approx(3.5), pytest.approx(4.0))]
    occ = timeline.occupancy(iv)
    # two busy: 1.0-2.0 and 3.5-4.0; one: 0-1, 2-3.1 (the child alone), 3.1-3.5, 4-5; none: never
    assert occ["busy"][2] == pytest.approx(1.5)
    assert occ["busy"][1] == pytest.approx(3.5)
    assert occ["busy"][0] == pytest.approx(0.0)
    assert occ["span"] == pytest.approx(5.0)
    assert occ["use"] == pytest.approx((2 * 1.5 + 3.5) / 10.0)
    ph = timeline.phases(marks)
    assert [p for _, _, p in ph] == ["before the analysis", "analysis", "detection", "analysis", "repair",
                                     "analysis", "after the analysis"]
    assert ph[2][:2] == (pytest.approx(0.6), pytest.approx(3.2))
    lone = timeline.lone_stretches(iv, marks)
    assert [(round(a, 3), round(b, 3), who, phase) for a, b, who, phase in lone] == [
        (0.0, 0.5, "parent", "before the analysis"), (0.5, 0.6, "parent", "analysis"),
        (0.6, 1.0, "parent", "detection"),
        (2.0, 3.1, "1 split_map/take_all", "detection"),
        (3.1, 3.2, "parent", "detection"), (3.2, 3.3, "parent", "analysis"), (3.3, 3.5, "parent", "repair"),
        (4.0, 4.5, "parent", "repair"), (4.5, 4.6, "parent", "analysis"), (4.6, 5.0, "parent", "after the analysis")]


def test_the_analysis_work_and_what_an_even_split_would_leave_to_shed():
    marks = _marks()
    iv = timeline.busy_intervals(marks)
    # The analysis runs 0.5-4.6 s: the parent busy 0.5-2.0 and 3.1-4.6 (3.0 s), child 1 1.0-3.1 (2.1 s),
    # child 2 3.5-4.0 (0.5 s).
    analysis, work = timeline.analysis_work(iv, marks)
    assert analysis == pytest.approx(4.1) and work == pytest.approx(5.6)
    s = timeline.summarize(marks, launch=9.8, exit_time=15.1)          # 5.3 s from the launch
    assert s["balanced_from_launch_s"] == pytest.approx(5.3 - 4.1 + 2.8)
    median = {k: s[k] for k in ("from_launch_s", "analysis_s", "analysis_work_s", "balanced_from_launch_s")}
    # The rest of the run takes 1.2 s: a target of 3.2 s leaves two cores 2 x 2.0 s for the 5.6 s of work.
    b = timeline.work_to_shed(median, 3.2)
    assert b["shed_s"] == pytest.approx(1.6) and b["shed_fraction"] == pytest.approx(1.6 / 5.6)
    assert timeline.work_to_shed(median, 4.0)["shed_s"] == 0.0
    assert timeline.work_to_shed(median, 1.0)["shed_s"] is None
    text = timeline.format_bound("3x3", dict(median, floor_s=1.6), {"2 x the floor": b})
    assert "shed 1.600 s of work (29 %)" in text
    assert timeline.analysis_work(iv, [m for m in marks if m[3] != "analyze"]) == (0.0, 0.0)


def test_a_child_that_sent_nothing_is_busy_to_the_end_of_its_function():
    marks = [m for m in _marks() if not (m[1] == C1 and m[2] == "child sent")]
    assert timeline.busy_intervals(marks)["1 split_map/take_all"] == [(pytest.approx(1.0), pytest.approx(3.0))]


def test_a_small_analysis_is_traced_across_its_processes(tmp_path):
    from bench.perf import write_industrial_case

    yml, csv = write_industrial_case(tmp_path, 3, 3, 3000)
    s = timeline.one_run(yml, csv, jobs=2)
    events = [(who, event, label) for _, who, event, label in s["marks"]]
    assert events[0] == ("parent", "start", "") and events[-1] == ("parent", "end", "")
    for label in ("analyze", "detect_unless_coloured", "repair_model", "detect"):
        assert ("parent", "begin", label) in events and ("parent", "finish", label) in events, label
    assert ("parent", "import", "scipy.linalg") in events
    children = [label for who, event, label in events if event == "child start" and who != "parent"]
    assert "_detect/values_and_experiment" in children        # the detectability beside the repair
    assert s["busy_s"]["parent"] <= s["span_s"] + 1e-9
    assert s["both_cores_s"] + s["one_core_s"] + s["no_core_s"] == pytest.approx(s["span_s"])
    assert 0.5 <= s["use"] <= 1.0
    assert s["from_launch_s"] >= s["span_s"] > 0
    assert 0 < s["analysis_s"] < s["span_s"] and s["analysis_work_s"] >= s["analysis_s"] * 0.5
    assert "processor use" in timeline.format_run("3x3", s)


def test_bad_arguments_are_refused():
    with pytest.raises(SystemExit):
        timeline.main(["--sizes", "20by20"])
    with pytest.raises(SystemExit):
        timeline.main(["--repeats", "0"])
    with pytest.raises(SystemExit):
        timeline.main(["--jobs", "0"])
