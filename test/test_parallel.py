"""The second process of the analysis (:mod:`mpm_monitor.core.parallel`): results, errors, and an
analysis split over two processes equal to one in a single process, bit for bit."""

import dataclasses
import json
import os
import threading

import numpy as np
import pytest

from mpm_monitor.apps.reproduce import simulate_case
from mpm_monitor.core import parallel
from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.analysis_report import settle_report
from mpm_monitor.core.parallel import Forked, split_map
from mpm_monitor.core.pipeline import analyze

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")


@pytest.fixture(autouse=True)
def alone():
    """These tests fork: a thread another test left running (which stops every fork) is named here."""
    others = [t.name for t in threading.enumerate() if t is not threading.current_thread()]
    assert not others, f"threads left running by earlier tests stop the forks tested here: {others}"


def test_forked_runs_in_another_process_and_returns_arrays_bit_for_bit():
    rng = np.random.default_rng(0)
    big = rng.standard_normal((700, 900))             # out of band, 5 MB: more than a pipe holds
    strided = big[:, ::3]                            # not contiguous: pickled in band
    result = Forked(lambda: (os.getpid(), big * 2.0, strided.copy(), {"k": [1, 2.5, "x"]})).result()
    assert result[0] != os.getpid()
    assert np.array_equal(result[1], big * 2.0)
    assert np.array_equal(result[2], strided)
    assert result[3] == {"k": [1, 2.5, "x"]}


def test_a_large_result_comes_through_the_spool_bit_for_bit_and_writable():
    # Arrays of at least SPOOL_MIN_BYTES are written by the child into a file in memory that the parent maps
    # privately: the same numbers, writable (a write copies its page, the child's file is not changed).
    rng = np.random.default_rng(1)
    big = rng.standard_normal((600, 500))
    small = np.arange(7.0)
    assert big.nbytes >= parallel.SPOOL_MIN_BYTES
    got_big, got_small = Forked(lambda: (big * 3.0, small + 1.0)).result()
    assert np.array_equal(got_big, big * 3.0) and np.array_equal(got_small, small + 1.0)
    if parallel._spool_file() is not None:           # Linux: the arrays lie on the mapped file
        with open("/proc/self/maps") as fh:
            assert "mpm_monitor-result" in fh.read()
    got_big[0, 0] = -1.0
    assert got_big[0, 0] == -1.0 and got_big[0, 1] == big[0, 1] * 3.0
    # Without a spool (elsewhere than Linux) they come through the pipe, the same numbers.
    spool_file = parallel._spool_file
    try:
        parallel._spool_file = lambda: None
        again = Forked(lambda: big * 3.0).result()
    finally:
        parallel._spool_file = spool_file
    assert np.array_equal(again, big * 3.0)


def test_row_moments_cross_to_the_parent_with_their_strided_view_and_without_a_copy():
    from mpm_monitor.core.response_moments import RowMoments, _StridedView

    M = np.random.default_rng(2).standard_normal((4, 6, 3, 5))
    rm = RowMoments(i=1, found=[], moves=np.ones(5, bool), zx=M[:, 1:], uw=np.zeros((4, 15)), zo=np.zeros((20, 2)),
                    oo=np.eye(2), ow=np.zeros((2, 15)), ww=np.zeros((5, 3, 3)), xsum=np.zeros((5, 3)),
                    mu=np.zeros((1, 5)))
    state = rm.__getstate__()
    assert isinstance(state["zx"], _StridedView) and state["zx"].base is M
    back = Forked(lambda: rm).result()
    assert np.array_equal(back.zx, M[:, 1:]) and back.zx.strides == M[:, 1:].strides
    assert np.array_equal(back.oo, rm.oo)


def test_row_moments_from_a_child_get_their_elements_back_from_the_model():
    # The elements are left out of the pickle; ResponseMoments.keep puts back the model's own objects.
    from mpm_monitor.core.response_moments import ResponseMoments

    case, data, _ = simulate_case("3.2", 1500, 3)
    model = case.model
    moments = ResponseMoments(model, data.columns, data.y - data.y.mean(axis=0), list(range(model.n_columns)), 12,
                              14, 2)
    here = moments.row(1)
    there = Forked(lambda: moments.row(1)).result()
    assert [j for j, _, _ in there.found] == [j for j, _, _ in here.found] and all(el is None for _, el, _ in there.found)
    again = ResponseMoments(model, data.columns, data.y - data.y.mean(axis=0), list(range(model.n_columns)), 12, 14, 2)
    again.keep(there)
    assert [(j, el, ref) for j, el, ref in again.kept(1).found] == here.found
    assert all(a is b for (_, a, _), (_, b, _) in zip(again.kept(1).found, here.found))
    assert np.array_equal(again.kept(1).zx, here.zx) and np.array_equal(again.kept(1).ww, here.ww)


def test_an_error_in_the_child_is_raised_in_the_parent():
    def fails():
        raise KeyError("no such row")
    with pytest.raises(KeyError, match="no such row"):
        Forked(fails).result()


def test_an_error_that_does_not_pickle_is_named():
    class Local(Exception):      # a local class does not pickle
        pass

    def fails():
        raise Local("a local error")
    with pytest.raises(ChildProcessError, match="Local: a local error"):
        Forked(fails).result()


def test_what_a_child_that_dies_was_to_compute_is_computed_in_the_parent():
    parent = os.getpid()

    def dies_in_the_child():
        if os.getpid() != parent:
            os._exit(3)                              # killed, say, by the system running out of memory
        return "computed by the parent"
    handle = Forked(dies_in_the_child)
    assert handle.forked
    assert handle.result() == "computed by the parent"
    assert not handle.forked                         # its side effects, if any, are the parent's
    assert split_map(lambda x: dies_in_the_child() + f" {x}", range(4), jobs=2) == \
        [f"computed by the parent {x}" for x in range(4)]


def test_split_map_keeps_the_order_and_takes_each_item_once_in_one_process_or_the_other():
    import time

    parent = os.getpid()

    def f(x):
        time.sleep(0.02)                             # long enough for the child to take some items
        return x * x, os.getpid()
    out = split_map(f, range(7), jobs=2)
    assert [v for v, _ in out] == [x * x for x in range(7)]
    pids = [p for _, p in out]
    assert parent in pids and len(set(pids)) == 2    # both processes took items, each item once
    assert split_map(lambda x: os.getpid(), range(7), jobs=1) == [parent] * 7


def test_split_map_queues_runs_of_items_when_they_are_many():
    n = 3 * parallel._QUEUE_LENGTH + 5               # more items than the queue has places: runs of them
    assert split_map(lambda x: 2 * x, range(n), jobs=2) == [2 * x for x in range(n)]


def test_split_map_gives_the_items_to_the_process_that_is_free():
    import time

    parent = os.getpid()

    def f(x):
        time.sleep(0.3 if os.getpid() == parent else 0.01)     # the parent is slow: the child takes the rest
        return os.getpid()
    pids = split_map(f, range(12), jobs=2)
    assert 1 <= pids.count(parent) <= 2


def test_split_map_raises_the_error_of_an_item_the_child_took():
    import time

    parent = os.getpid()

    def f(x):
        if os.getpid() != parent:
            raise KeyError(f"no such row {x}")
        time.sleep(0.05)
        return x
    with pytest.raises(KeyError, match="no such row"):
        split_map(f, range(6), jobs=2)


def test_side_effects_of_the_child_stay_there():
    import time

    seen, parent = [], os.getpid()

    def f(x):
        time.sleep(0.01)
        seen.append(x)
        return os.getpid()
    pids = split_map(f, range(6), jobs=2)
    assert seen == [x for x in range(6) if pids[x] == parent] and len(seen) < 6


def test_a_process_with_other_threads_does_not_fork():
    stop = threading.Event()
    worker = threading.Thread(target=stop.wait)
    worker.start()
    try:
        assert not parallel.can_fork()
        assert split_map(lambda x: os.getpid(), range(4), jobs=2) == [os.getpid()] * 4
        assert Forked(os.getpid).result() == os.getpid()
    finally:
        stop.set()
        worker.join()


@pytest.fixture
def forks(monkeypatch):
    """The pids of the children forked during a test (to check that each was waited for)."""
    pids, fork = [], os.fork

    def recorded():
        pid = fork()
        if pid:
            pids.append(pid)
        return pid
    monkeypatch.setattr(os, "fork", recorded)
    return pids


def _all_reaped(pids) -> bool:
    for pid in pids:
        try:
            os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            continue                                 # already waited for
        return False
    return True


def test_the_parents_own_error_wins_and_the_child_is_reaped(forks):
    import time

    def f(x):
        if os.getpid() == parent:
            raise ValueError("parent's row")
        time.sleep(0.05)                             # the child does not take every item first
        return x
    parent = os.getpid()
    with pytest.raises(ValueError, match="parent's row"):
        split_map(f, range(4), jobs=2)
    assert len(forks) == 1 and _all_reaped(forks)    # no child left behind


@pytest.fixture(scope="module")
def case_32():
    case, data, _ = simulate_case("3.2", 3000, 1000)
    return case, data


def _json(report) -> str:
    return json.dumps(report.to_dict(), sort_keys=True)


def _with_gaps(data):
    """``data`` without samples 300, 301 and 1700 (two gaps)."""
    keep = np.ones(data.n_samples, bool)
    keep[[300, 301, 1700]] = False
    return data.take(np.flatnonzero(keep))


@pytest.mark.parametrize("gaps", [False, True])
def test_an_analysis_in_two_processes_equals_one_in_one_process(case_32, gaps):
    case, data = case_32
    if gaps:
        data = _with_gaps(data)
    one = analyze(case.model, data, AnalysisOptions(jobs=1))
    two = analyze(case.model, data, AnalysisOptions(jobs=2))
    assert one.located_elements                       # the case's mismatch is found, with its repair
    assert _json(one) == _json(two)


def test_with_every_stage_split_two_processes_equal_one(case_32, monkeypatch, forks):
    """The stages split only on large windows (the model run, the Gram products, the singular values): here
    on a small one, thresholds at 0; the row test runs while the element test's child takes rows."""
    from mpm_monitor.core import analysis, element_test, row_test

    case, data = case_32
    one = analyze(case.model, data, AnalysisOptions(jobs=1))
    assert not forks
    monkeypatch.setattr(analysis, "SPLIT_MIN_WORK", 0)
    monkeypatch.setattr(analysis, "LIGHT_SPLIT_MIN_WORK", 0)
    inside, during = [], []
    split, test = element_test.split_map, row_test.sdelta_row_test

    def split_map(*args, **kwargs):
        inside.append(True)
        try:
            return split(*args, **kwargs)
        finally:
            inside.pop()
    monkeypatch.setattr(element_test, "split_map", split_map)
    monkeypatch.setattr(row_test, "sdelta_row_test", lambda *a, **k: during.append(bool(inside)) or test(*a, **k))
    two = analyze(case.model, data, AnalysisOptions(jobs=2))
    assert during[0]                                 # the first detection's row test: beside the element test's child
    assert len(forks) > 3 and _all_reaped(forks)
    assert _json(one) == _json(two)


@pytest.mark.parametrize("gaps", [False, True])
def test_the_repairs_disturbance_tests_run_in_the_idle_second_process(case_32, monkeypatch, forks, gaps):
    """On a window split row by row but not in its lighter stages, the second process computes the repair's
    disturbance tests of the model as given beside the first stages; the repair tests only the outputs it
    repairs (here thresholds that put case 3.2 in that regime).  With gaps it tests every output itself."""
    from mpm_monitor.core import analysis
    from mpm_monitor.core.repair import residual_tests

    case, data = case_32
    if gaps:
        data = _with_gaps(data)
    parent, tested = os.getpid(), []
    test = residual_tests.unexplained_disturbance
    monkeypatch.setattr(residual_tests, "unexplained_disturbance",
                        lambda d, *a, **k: (tested.append(np.array(d)) if os.getpid() == parent else None) or
                        test(d, *a, **k))
    one = analyze(case.model, data, AnalysisOptions(jobs=1))
    monkeypatch.setattr(analysis, "SPLIT_MIN_WORK", 0)
    assert analysis.light_jobs(2, data.n_samples, case.model) == 1
    tested.clear()
    two = analyze(case.model, data, AnalysisOptions(jobs=2))
    names = case.model.outputs
    kept = [i for i in range(len(names)) if names[i] not in {change["output"] for change in two.repair["changes"]}]
    assert kept and len(kept) < len(names)
    # The prediction errors of the rows not repaired, tested here or not (with gaps the repair's are those of
    # the segments, which the report's signals do not hold: every output is tested here then).
    here = [i for i in kept if any(x.shape == two.signals.d[:, i].shape and np.array_equal(x, two.signals.d[:, i])
                                   for x in tested)]
    if gaps:
        assert len(tested) >= len(names)
    else:
        assert tested and not here
    assert _json(one) == _json(two) and _all_reaped(forks)


@pytest.mark.parametrize("gaps", [False, True])
def test_the_repairs_rows_are_taken_by_two_processes_with_the_same_result(case_32, monkeypatch, forks, tmp_path, gaps):
    """Case 3.2 repairs rows y1 and y2: with two processes (the threshold at 0 for this small window) each row is
    processed whole by one of them, and the report is the one of one process."""
    from mpm_monitor.core import analysis
    from mpm_monitor.core.repair import model_repair

    case, data = case_32
    if gaps:
        data = _with_gaps(data)
    one = analyze(case.model, data, AnalysisOptions(jobs=1))
    assert {c["output"] for c in one.repair["changes"] if c["applied"]} == {"y1", "y2"}
    log = tmp_path / "rows"
    process = model_repair._process_row

    def logged(rec, i, *args, **kwargs):
        with open(log, "a") as f:          # a child's side effects stay in the child: its pid goes to a file
            f.write(f"{os.getpid()} {i}\n")
        return process(rec, i, *args, **kwargs)
    monkeypatch.setattr(model_repair, "_process_row", logged)
    monkeypatch.setattr(analysis, "SPLIT_MIN_WORK", 0)
    two = analyze(case.model, data, AnalysisOptions(jobs=2))
    rows = [line.split() for line in log.read_text().splitlines()]
    assert sorted(int(i) for _, i in rows) == [0, 1]
    assert len({pid for pid, _ in rows}) == 2 and _all_reaped(forks)
    assert _json(one) == _json(two)


def test_an_error_after_the_disturbance_tests_started_leaves_no_child(case_32, monkeypatch, forks):
    from mpm_monitor.core import analysis, pipeline

    monkeypatch.setattr(analysis, "SPLIT_MIN_WORK", 0)

    def broken(*args, **kwargs):
        raise RuntimeError("broken repair data")
    monkeypatch.setattr(pipeline, "repair_data", broken)
    case, data = case_32
    with pytest.raises(RuntimeError, match="broken repair data") as caught:
        analyze(case.model, data, AnalysisOptions(jobs=2))
    # Every child reaped while the traceback, which holds the analysis's frames, is still alive.
    assert caught.traceback and len(forks) >= 2 and _all_reaped(forks)


def test_a_detection_in_two_processes_equals_one_in_one_process_without_the_response_test(case_32):
    case, data = case_32
    options = dict(repair=False, element_response=False)
    assert _json(detect(case.model, data, AnalysisOptions(jobs=1, **options))) == \
        _json(detect(case.model, data, AnalysisOptions(jobs=2, **options)))


@pytest.mark.parametrize("test_all_rows", [True, False])
def test_a_detection_of_which_only_the_rows_are_read_has_the_same_rows(case_32, test_all_rows):
    case, data = case_32
    options = AnalysisOptions(repair=False, test_all_rows=test_all_rows)
    full = detect(case.model, data, options)
    rows_only = detect(case.model, data, options, rows_only=True)
    assert np.isnan(rows_only.overall_rsi) and np.all(np.isnan(rows_only.sigma_max))
    assert [dataclasses.asdict(r) for r in rows_only.rows] == [dataclasses.asdict(r) for r in full.rows]
    assert rows_only.located_elements == full.located_elements and rows_only.flagged_rows == full.flagged_rows


def test_a_rows_only_detection_with_no_row_to_test_takes_no_input_lags(case_32, monkeypatch):
    from mpm_monitor.core.lagged_gram import LaggedGram

    built = []
    rebuild = LaggedGram.rebuild
    monkeypatch.setattr(LaggedGram, "rebuild",
                        lambda self, *a, **k: built.append(self.n_columns) or rebuild(self, *a, **k))
    case, data = case_32
    plant = detect(case.plant, data, AnalysisOptions(repair=False, test_all_rows=False), rows_only=True)
    assert plant.flagged_rows == [] and plant.elements == [] and plant.arx_tables == []
    assert np.isnan(plant.max_variance_inflation)
    assert len(built) == 1                       # the setpoint lags' Gram only
    full = detect(case.plant, data, AnalysisOptions(repair=False, test_all_rows=False))
    assert len(built) == 3
    assert [dataclasses.asdict(r) for r in plant.rows] == [dataclasses.asdict(r) for r in full.rows]


def test_a_report_not_settled_gets_its_detectable_changes_and_experiment_from_the_second_process(case_32):
    case, data = case_32
    options = AnalysisOptions(repair=False, jobs=2)
    settled = detect(case.model, data, options)
    later = detect(case.model, data, options, settle=False)
    assert later.pending is not None and later.experiment is None
    assert all(e.detectable_gain_change is None for e in later.elements)
    assert not all(isinstance(w, str) for w in later.warnings)      # the placeholder of their warnings
    assert settle_report(later) is later and later.pending is None
    assert _json(later) == _json(settled)
    assert any(e.detectable_gain_change is not None for e in later.elements)


def test_an_error_of_the_second_process_is_raised_by_the_analysis_and_no_child_is_left(case_32, monkeypatch, forks):
    from mpm_monitor.core import detectability

    def broken(*args, **kwargs):
        raise FloatingPointError("broken detectability")
    monkeypatch.setattr(detectability, "element_detectability", broken)
    case, data = case_32
    with pytest.raises(Exception, match="broken detectability"):
        analyze(case.model, data, AnalysisOptions(jobs=2))
    assert forks and _all_reaped(forks)


def test_a_detectability_whose_child_dies_is_computed_here_with_the_same_numbers(case_32, monkeypatch):
    """The parent forgets the window's moments once the child has them (ResponseMoments.forget); when the child
    dies, they are computed again here, and the report is the one of a single process."""
    from mpm_monitor.core import detectability, response_moments

    parent, real = os.getpid(), detectability.element_detectability
    forgot = []
    forget = response_moments.ResponseMoments.forget
    monkeypatch.setattr(response_moments.ResponseMoments, "forget", lambda self: forgot.append(1) or forget(self))

    def dies_in_the_child(*args, **kwargs):
        if os.getpid() != parent:
            os._exit(3)
        return real(*args, **kwargs)
    case, data = case_32
    one = analyze(case.model, data, AnalysisOptions(jobs=1))
    assert not forgot
    monkeypatch.setattr(detectability, "element_detectability", dies_in_the_child)
    two = analyze(case.model, data, AnalysisOptions(jobs=2))
    assert forgot
    assert any(e.detectable_gain_change is not None for e in two.elements)
    assert _json(one) == _json(two)


def _analysis_where(model, data, options):
    """In the monitor's analysis process: whether it may fork, and the report of ``analyze`` there."""
    return parallel.can_fork(), _json(analyze(model, data, options))


def test_the_monitors_analysis_process_may_use_its_second_process(case_32):
    from mpm_monitor.monitor.worker import ProcessAnalyzer

    case, data = case_32
    pa = ProcessAnalyzer(_analysis_where)
    try:
        forks, report = pa(case.model, data, AnalysisOptions(jobs=2))
    finally:
        pa.close()
    assert forks                                     # its watchdog thread is marked fork_safe
    assert report == _json(analyze(case.model, data, AnalysisOptions(jobs=1)))


def test_a_thread_marked_fork_safe_does_not_stop_a_fork():
    stop = threading.Event()
    watchdog = parallel.fork_safe(threading.Thread(target=stop.wait))
    watchdog.start()
    try:
        assert parallel.can_fork()
        assert Forked(os.getpid).result() != os.getpid()
    finally:
        stop.set()
        watchdog.join()


def test_a_handle_dropped_without_its_result_leaves_no_process(forks):
    import gc
    import time

    handle = Forked(lambda: time.sleep(30))
    pid = handle._pid
    del handle
    gc.collect()
    assert forks == [pid] and _all_reaped(forks)


def test_the_command_writes_the_same_report_with_one_and_two_processes(case_32, tmp_path):
    from mpm_monitor.apps.cli import main
    from mpm_monitor.io.csv_log import write_csv
    from mpm_monitor.io.model_file import save_model

    case, data = case_32
    csv, model = tmp_path / "log.csv", tmp_path / "model.yaml"
    write_csv(csv, data.t, data.r, data.u, data.y, data.inputs, data.outputs)
    save_model(case.model, model)
    reports = []
    for jobs in ("1", "2"):
        out = tmp_path / f"report_{jobs}.json"
        assert main(["analyze", "--model", str(model), "--data", str(csv), "--json", str(out), "--jobs", jobs]) == 0
        reports.append(json.loads(out.read_text()))
    assert reports[0]["located"] and reports[0] == reports[1]
