"""SampleWindow: alignment by stamp, completion, gaps, duplicates, conflicts, late and bad vectors.

Pure Python: no rclpy; stamps are passed in as integer nanoseconds.
"""

import numpy as np
import pytest

from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.monitor.window import EARLY_BLOCK, SampleWindow, WindowOptions

NS = 1_000_000_000
OUT = ("y1", "y2")
INP = ("u1", "u2", "u3")


def make(window=20, **kw):
    return SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=window, **kw))


def sample_values(k):
    """Distinct values per sample so that mis-alignment is visible."""
    return (np.array([k, -k], float) + 0.1, np.array([k, 2 * k, 3 * k], float) + 0.2, np.array([k, k * k], float) + 0.3)


def feed(w, k, order=("setpoint", "input", "output"), stamp=None):
    r, u, y = sample_values(k)
    vals = {"setpoint": r, "input": u, "output": y}
    st = k * NS if stamp is None else stamp
    return sum(w.add(ch, st, vals[ch]) for ch in order)


def test_in_order_samples_fill_the_window_and_slide():
    w = make(window=10)
    for k in range(25):
        assert feed(w, k) == 1
    assert w.n_completed == 25 and w.n_window == 10
    d = w.data()
    np.testing.assert_array_equal(d.t, np.arange(15, 25, dtype=float))
    for i, k in enumerate(range(15, 25)):
        r, u, y = sample_values(k)
        np.testing.assert_array_equal(d.r[i], r)
        np.testing.assert_array_equal(d.u[i], u)
        np.testing.assert_array_equal(d.y[i], y)
    assert d.inputs == INP and d.outputs == OUT and d.sample_time == 1.0
    assert w.take_problems() == []


@pytest.mark.parametrize("order", [("output", "input", "setpoint"), ("input", "setpoint", "output"),
                                   ("setpoint", "output", "input")])
def test_any_interleaving_of_the_topics_gives_the_same_samples(order):
    w = make()
    for k in range(12):
        feed(w, k, order=order)
    d = w.data()
    assert d.n_samples == 12
    np.testing.assert_array_equal(d.u[5], sample_values(5)[1])
    assert w.take_problems() == []


def test_a_topic_running_ahead_is_buffered_until_its_partners_arrive():
    w = make()
    for k in range(8):
        r, u, y = sample_values(k)
        w.add("output", k * NS, y)
        w.add("setpoint", k * NS, r)
    assert w.n_completed == 0 and w.n_pending == 8
    for k in range(8):
        assert w.add("input", k * NS, sample_values(k)[1]) == 1
    assert w.n_completed == 8 and w.n_pending == 0


def test_reordered_samples_within_the_limit_complete_in_order():
    w = make(reorder_samples=3)
    feed(w, 0)
    feed(w, 2)
    feed(w, 3)
    assert w.n_completed == 1  # 2 and 3 wait for 1
    assert feed(w, 1) == 3
    np.testing.assert_array_equal(w.data().t, [0, 1, 2, 3])
    assert w.health().gaps == 0


def test_a_missing_sample_is_a_gap_and_the_window_restarts_after_it():
    # max_gap 0: every gap is long (since the interface "Gaps", a gap up to max_gap keeps the window)
    w = make(reorder_samples=2, max_gap=0)
    for k in range(5):
        feed(w, k)
    r, u, y = sample_values(5)
    w.add("setpoint", 5 * NS, r)
    w.add("output", 5 * NS, y)  # input of sample 5 never comes
    for k in range(6, 10):
        feed(w, k)
    h = w.health()
    assert h.gaps == 1 and h.missing_samples == 1
    d = w.data()
    np.testing.assert_array_equal(d.t, [6, 7, 8, 9])  # contiguous data only
    problems = w.take_problems()
    assert [p.kind for p in problems] == ["gap"]
    assert "t = 5 s" in problems[0].message and "no input" in problems[0].message
    assert w.n_since_reset == 4


def test_duplicate_and_conflicting_vectors_keep_the_first():
    w = make()
    feed(w, 0)
    r, u, y = sample_values(1)
    w.add("output", NS, y)
    w.add("output", NS, y)                 # same values: duplicate
    w.add("output", NS, y + 1.0)           # different values: conflict
    w.add("setpoint", NS, r)
    w.add("input", NS, u)
    w.add("input", 0, sample_values(0)[1])  # sample 0 again, already in the window
    kinds = [p.kind for p in w.take_problems()]
    assert kinds == ["duplicate", "conflict", "out_of_order", "duplicate"]
    np.testing.assert_array_equal(w.data().y[1], y)
    h = w.health()
    assert h.duplicate == 2 and h.conflict == 1


def test_a_repeated_or_conflicting_vector_before_a_kept_gap_is_found_in_the_window():
    """A gap the window keeps lies between the re-sent sample and the newest: the vector was looked up by counting
    back from the newest sample, missed, and counted ``late`` ("arrived after it was given up"), so a second
    publisher on a topic showed as a warning instead of the ERROR of a conflict (an outside check)."""
    w = make(window=100)
    for k in range(30):
        if k != 10:                                    # sample 10 never comes: a gap of one sample, kept
            feed(w, k)
    assert w.n_window == 29 and w.window_gaps()[0] == 1
    w.take_problems()
    r, u, y = sample_values(5)
    w.add("output", 5 * NS, y)                         # the same vector again
    w.add("output", 6 * NS, y + 1.0)                   # a different vector for sample 6
    w.add("input", 12 * NS, sample_values(12)[1])      # after the gap: found too
    kinds = [p.kind for p in w.take_problems() if p.kind != "out_of_order"]
    assert kinds == ["duplicate", "conflict", "duplicate"]
    h = w.health()
    assert (h.duplicate, h.conflict, h.late) == (2, 1, 0)
    np.testing.assert_array_equal(w.data().y[6], sample_values(6)[2])          # the first vector kept
    # A sample the gap lost, or one older than the window, is still late.
    w.add("output", 10 * NS, sample_values(10)[2])
    assert w.health().late == 1


def test_a_vector_for_a_sample_given_up_is_late():
    w = make(reorder_samples=0)
    feed(w, 0)
    feed(w, 2)  # sample 1 given up at once
    r, u, y = sample_values(1)
    w.add("output", NS, y)
    kinds = [p.kind for p in w.take_problems()]
    assert kinds == ["gap", "out_of_order", "late"]


def test_off_grid_stamps_are_refused_with_the_offset():
    w = make(stamp_tolerance=0.1)
    feed(w, 0)
    assert w.add("output", int(1.3 * NS), sample_values(1)[2]) == 0
    p = w.take_problems()
    assert [x.kind for x in p] == ["off_grid"] and "+0.3 s off the sample grid" in p[0].message
    assert p[0].is_error


def test_small_stamp_jitter_is_put_on_the_grid():
    w = make(stamp_tolerance=0.25)
    for k in range(5):
        feed(w, k, stamp=k * NS + (-1) ** k * 10_000_000)
    assert w.n_completed == 5
    np.testing.assert_array_equal(w.data().t, np.arange(5.0) + 0.01)  # phase of the first output


def test_grid_phase_comes_from_the_first_output():
    w = make()
    phase = 250_000_000
    r, u, y = sample_values(0)
    w.add("setpoint", phase, r)  # before any output: waits for the phase
    w.add("input", phase, u)
    assert w.add("output", phase, y) == 1
    np.testing.assert_allclose(w.data().t, [0.25])


@pytest.mark.parametrize("values, what", [(np.array([1.0]), "1 value"), (np.array([1.0, np.nan]), "non-finite")])
def test_bad_values_are_refused_and_reported(values, what):
    w = make()
    assert w.add("output", 0, values) == 0
    p = w.take_problems()
    assert len(p) == 1 and p[0].kind == "bad_value" and what in p[0].message
    assert w.health().bad_value == 1


def test_hold_setpoint_uses_the_latest_setpoint_at_or_before_each_sample():
    w = make(hold_setpoint=True)
    w.add("setpoint", 0, np.array([1.0, 1.0]))
    w.add("setpoint", int(2.5 * NS), np.array([2.0, 2.0]))  # off grid is fine for a held setpoint
    for k in range(5):
        _, u, y = sample_values(k)
        w.add("input", k * NS, u)
        w.add("output", k * NS, y)
    d = w.data()
    np.testing.assert_array_equal(d.r[:, 0], [1, 1, 1, 2, 2])
    assert w.take_problems() == []


def _hold_run(window: int, n: int, late: dict):
    """A ``hold_setpoint`` window: setpoint 1 from t = 0, the inputs and outputs of samples 0 .. n - 1, and after
    sample ``k`` the setpoints ``late[k]`` (``(stamp s, value)`` pairs)."""
    w = make(window=window, hold_setpoint=True)
    w.add("setpoint", 0, np.array([1.0, 1.0]))
    for k in range(n):
        _, u, y = sample_values(k)
        w.add("input", k * NS, u)
        w.add("output", k * NS, y)
        for t, value in late.get(k, ()):
            w.add("setpoint", int(t * NS), np.full(2, value))
    return w


def test_hold_setpoint_delivered_after_its_sample_holds_for_it():
    """The setpoint stamped t = 10 s arrives after the input and output of t = 10 s (topics of different publishers
    arrive in no set order): sample 10 was complete with the old setpoint, and the new one started a sample late,
    without a word (an outside check).  The samples in the window from its stamp take it."""
    w = _hold_run(50, 20, {10: [(10, 2.0)], 15: [(13, 3.0)]})             # the second two samples later still
    np.testing.assert_array_equal(w.data().r[:, 0], [1] * 10 + [2] * 3 + [3] * 7)
    assert w.take_problems() == []
    # A setpoint stamped before the window's oldest sample holds for the samples up to the next one.
    w = _hold_run(10, 17, {16: [(9, 4.0), (3, 5.0)]})
    np.testing.assert_array_equal(w.data().r[:, 0], [5, 5, 4, 4, 4, 4, 4, 4, 4, 4])


def test_a_publisher_that_never_stamps_its_messages_is_named():
    """Every vector stamped 0 (header.stamp never filled): the window said "two different vectors for sample t = 0
    s (two publishers on one topic?)" and "stream restarted ... (publisher restart or clock jump)" by turns and
    restarted every few outputs, never naming the cause (an outside check).  A third vector stamped 0 in a row with
    other values is refused as an unset stamp (the second may be a second publisher's: a conflict); the same vector
    again (a re-send at t = 0) is still a duplicate."""
    w = make()
    for k in range(30):
        feed(w, k, stamp=0)
    h = w.health()
    assert (h.restarts, h.conflict, h.completed) == (0, 3, 1)      # the second vectors: perhaps a second publisher
    problems = [p for p in w.take_problems() if p.kind != "conflict"]
    assert problems and all(p.kind == "bad_value" for p in problems)
    assert "header.stamp unset (0) on successive messages with different values" in problems[0].message
    assert h.bad_value == 3 * 28
    w = make()
    feed(w, 0)
    feed(w, 0)                                               # sample 0 sent again: duplicates, as before
    assert w.health().duplicate == 3 and w.health().bad_value == 0


def test_hold_setpoint_waits_for_the_first_setpoint():
    w = make(hold_setpoint=True)
    _, u, y = sample_values(0)
    w.add("input", 0, u)
    w.add("output", 0, y)
    assert w.n_completed == 0
    assert w.add("setpoint", 0, np.array([1.0, 2.0])) == 1


def test_a_channel_that_never_comes_is_reported_and_memory_stays_bounded():
    w = make(max_pending=5)
    for k in range(50):
        r, u, y = sample_values(k)
        w.add("setpoint", k * NS, r)
        w.add("output", k * NS, y)
    assert w.n_pending <= 6 and w.n_completed == 0
    assert w.health().missing_samples >= 44
    problems = w.take_problems()
    assert problems and all(p.kind == "gap" and "no input" in p.message for p in problems)


def test_a_long_outage_of_one_topic_is_one_gap_not_one_per_sample():
    """The input silent for 1,200 samples (max_pending 1,000): each sample received beyond max_pending gave up the
    oldest as a gap of one sample that the window "keeps its samples across", 212 gaps in all, and the window
    restarted only on the last (989 samples).  The samples given up at once are one gap now, which restarts it."""
    w = make(window=3000)
    for k in range(3000):
        r, u, y = sample_values(k)
        w.add("setpoint", k * NS, r)
        w.add("output", k * NS, y)
        if not 400 <= k < 1600:
            w.add("input", k * NS, u)
    h = w.health()
    assert h.missing_samples == 1200 and h.gaps == 2 and h.resets == 1 and h.completed == 1800
    gaps = [p.message for p in w.take_problems() if p.kind == "gap"]
    assert len(gaps) == 2 and gaps[0].startswith("990 sample(s) missing from t = 400 s (no input); the window "
                                                 "restarts after the gap")


def test_a_first_output_stamped_early_does_not_put_the_grid_off_for_good():
    """The grid's phase came from the first output alone: stamped 0.2 sample early, with every input 0.1 sample late
    (both within the quarter sample a stamp may be off), every input was 0.3 sample off the grid, refused, and no
    sample ever completed.  Before the first sample completes, the phase moves to fit every stamp so far."""
    w = make(window=50)
    for k in range(30):
        r, u, y = sample_values(k)
        w.add("output", k * NS - (NS // 5 if k == 0 else 0), y)
        w.add("input", k * NS + NS // 10, u)
        w.add("setpoint", k * NS, r)
    assert w.n_completed == 30 and w.health().off_grid == 0
    data = w.data()
    np.testing.assert_array_equal(data.y[:, 0], np.arange(30) + 0.3)
    np.testing.assert_array_equal(data.u[:, 0], np.arange(30) + 0.2)
    assert abs(data.t[0]) <= 0.25
    np.testing.assert_allclose(np.diff(data.t), 1.0)
    problems = w.take_problems()
    assert [p.kind for p in problems] == ["rephase"] and "phase moved by" in problems[0].message
    # Stamps jittered by up to 0.2 sample either way around the grid: every sample completes.
    rng = np.random.default_rng(3)
    w = make(window=200)
    for k in range(150):
        r, u, y = sample_values(k)
        for ch, v in (("output", y), ("input", u), ("setpoint", r)):
            w.add(ch, k * NS + int(rng.uniform(-0.2, 0.2) * NS), v)
    assert w.n_completed == 150 and w.health().restarts == 0
    # Stamps no one phase fits (0.6 sample apart) are still refused: off the grid.
    w = make()
    r, u, y = sample_values(0)
    w.add("output", 0, y)
    w.add("input", 3 * NS // 10, u)              # 0.3 sample late: the phase moves by 0.15
    w.add("setpoint", -3 * NS // 10, r)          # 0.3 sample early: 0.45 off the moved grid
    assert w.health().off_grid == 1 and w.n_completed == 0


def test_a_topic_whose_clock_jumps_ahead_is_an_error_not_a_gap():
    """The input's stamps jumped 5 samples forward at sample 800 while the loop ran on in real time: the window
    paired y(k) with u(k - 5) from then on, said as a gap of 5 samples, and the analysis of that window located
    mismatches the loop did not have.  The input's vectors arrive well before the others' of the same sample: a
    data error, and the window restarts.  Vectors delivered late for a while (a stall) are no sign of it."""
    def run(shift_input, late_output=0):
        w = make(window=3000)
        for k in range(2000):
            r, u, y = sample_values(k)
            t = k * NS
            jump = 5 * NS if shift_input and k >= 800 else 0
            w.add("output", t, y, arrival_ns=t + (late_output * NS if 1000 <= k < 1100 else 0))
            w.add("input", t + jump, u, arrival_ns=t + NS // 10)
            w.add("setpoint", t, r, arrival_ns=t + NS // 5)
        return w
    w = run(shift_input=True)
    clock = [p for p in w.take_problems() if p.kind == "clock"]
    assert clock and clock[0].channel == "input" and clock[0].is_error
    assert clock[0].message.startswith("input: its vectors arrive about 4.9 samples (4.9 s) before") and \
        "run ahead" in clock[0].message
    # The window restarts again each time (the clock stays apart): it never holds enough for an analysis.
    assert w.health().resets >= 40 and w.n_window < 2 * EARLY_BLOCK
    w = run(shift_input=False, late_output=3)    # the output held up 3 s for 100 samples: late, not early
    assert not [p for p in w.take_problems() if p.kind == "clock"] and w.n_window == 2000


def test_a_topic_whose_stamps_run_behind_is_named_once_and_kept():
    """The input's stamps run 5 samples behind the loop's time from the start: its vectors arrive 5 samples
    after the others' of the same sample.  That is also what a delivery held up 5 s looks like, so it is a
    warning, not an error: named once, while it lasts, and the window keeps every sample."""
    w = make(window=3000)
    for k in range(2000):
        r, u, y = sample_values(k)
        t = k * NS
        w.add("output", t, y, arrival_ns=t)
        w.add("input", t - 5 * NS, u, arrival_ns=t + NS // 10)
        w.add("setpoint", t, r, arrival_ns=t + NS // 5)
    problems = w.take_problems()
    behind = [p for p in problems if p.kind == "behind"]
    assert len(behind) == 1 and behind[0].channel == "input" and not behind[0].is_error
    assert behind[0].message.startswith("input: its vectors arrive about 4.9 samples (4.9 s) after the other topics'")
    assert not [p for p in problems if p.is_error] and w.n_window > 1990 and w.health().resets == 0


def test_options_are_checked():
    with pytest.raises(ConfigurationError, match="window_samples"):
        WindowOptions(window_samples=5)
    with pytest.raises(ConfigurationError, match="stamp_tolerance"):
        WindowOptions(stamp_tolerance=0.5)
    with pytest.raises(ValueError, match="channel"):
        make().add("dither", 0, [1.0])


# ----------------------------------------------------------------------- gaps (docs/interfaces.md, "Gaps")


def test_a_short_gap_keeps_the_window_with_t_skipping_the_missing_samples():
    w = make(reorder_samples=2, max_gap=3)
    for k in list(range(8)) + list(range(11, 15)):         # samples 8, 9, 10 never come: 3 <= max_gap
        feed(w, k)
    d = w.data()
    np.testing.assert_array_equal(d.t, [0, 1, 2, 3, 4, 5, 6, 7, 11, 12, 13, 14])
    assert d.segments == [(0, 8), (8, 12)]
    for i, t in enumerate(d.t):                             # nothing interpolated, nothing mis-aligned
        np.testing.assert_array_equal(d.u[i], sample_values(int(t))[1])
    problems = w.take_problems()
    assert [p.kind for p in problems] == ["gap"]
    assert "3 sample(s) missing from t = 8 s" in problems[0].message and "keeps its samples" in problems[0].message
    h = w.health()
    assert h.gaps == 1 and h.missing_samples == 3 and h.resets == 0
    assert w.window_gaps() == (3, 1) and w.n_since_reset == 12


def test_a_gap_longer_than_max_gap_restarts_the_window():
    w = make(reorder_samples=2, max_gap=3)
    for k in list(range(8)) + list(range(12, 15)):         # 4 samples missing: > max_gap
        feed(w, k)
    np.testing.assert_array_equal(w.data().t, [12, 13, 14])
    problems = w.take_problems()
    assert "4 sample(s) missing" in problems[0].message and problems[0].message.endswith(
        "restarts after the gap (longer than max_gap = 3; split_gap would keep its samples across such a gap)")
    assert w.health().resets == 1 and w.window_gaps() == (0, 0)


def test_a_gap_longer_than_max_gap_keeps_the_window_up_to_split_gap():
    """A lossy link drops bursts: with ``split_gap`` the window keeps its samples across a gap longer than
    ``max_gap`` (the analysis splits the data there); a gap longer than both still restarts it."""
    w = make(window=40, reorder_samples=2, max_gap=3, split_gap=6)
    for k in list(range(8)) + list(range(14, 18)) + list(range(25, 29)):   # 6 missing (kept), then 7 (restart)
        feed(w, k)
    problems = [p.message for p in w.take_problems()]
    assert len(problems) == 2
    assert problems[0].startswith("6 sample(s) missing from t = 8 s") and \
        "keeps its samples across the gap, longer than max_gap = 3 (at most split_gap = 6)" in problems[0]
    assert "7 sample(s) missing" in problems[1] and problems[1].endswith("restarts after the gap (longer than "
                                                                         "split_gap = 6)")
    np.testing.assert_array_equal(w.data().t, [25, 26, 27, 28])
    assert w.health().resets == 1 and w.health().missing_samples == 13
    w = make(window=40, reorder_samples=2, max_gap=3, split_gap=6)
    for k in list(range(8)) + list(range(14, 18)):
        feed(w, k)
    d = w.data()
    np.testing.assert_array_equal(d.t, [0, 1, 2, 3, 4, 5, 6, 7, 14, 15, 16, 17])
    assert d.segments == [(0, 8), (8, 12)] and w.window_gaps() == (6, 1) and w.n_since_reset == 12
    for i, t in enumerate(d.t):                             # nothing interpolated, nothing mis-aligned
        np.testing.assert_array_equal(d.y[i], sample_values(int(t))[2])
    # split_gap below max_gap changes nothing: max_gap still bounds the short gaps
    w = make(reorder_samples=2, max_gap=3, split_gap=2)
    for k in list(range(8)) + list(range(11, 15)):
        feed(w, k)
    assert w.health().resets == 0 and "(at most max_gap = 3)" in w.take_problems()[0].message


def test_the_window_holds_exactly_the_samples_since_the_last_gap_longer_than_max_gap_and_split_gap():
    """Random bursts of samples between random gaps: the window holds the last ``window_samples`` samples sent
    since the last gap longer than both bounds, in order, each with its own values; restarts and lost samples
    counted as such."""
    rng = np.random.default_rng(5)
    for _ in range(30):
        max_gap, split_gap, window = int(rng.integers(0, 5)), int(rng.integers(0, 30)), int(rng.integers(20, 60))
        w = make(window=window, reorder_samples=2, max_gap=max_gap, split_gap=split_gap)
        k, since, resets = 0, [], 0
        for _ in range(25):
            for _ in range(int(rng.integers(3, 15))):
                feed(w, k)
                since.append(k)
                k += 1
            gap = int(rng.integers(1, 40))
            if gap > max(max_gap, split_gap):
                since, resets = [], resets + 1
            k += gap
        for _ in range(3):                                 # the last gap is given up
            feed(w, k)
            since.append(k)
            k += 1
        held = since[-window:]
        d = w.data()
        np.testing.assert_array_equal(d.t, held)
        for i, t in enumerate(held):
            np.testing.assert_array_equal(d.y[i], sample_values(t)[2])
        assert w.health().resets == resets and w.health().gaps == 25
        steps = np.diff(held)
        assert w.window_gaps() == (int(np.sum(steps - 1)), int(np.sum(steps > 1)))


def test_samples_lost_in_the_window_leave_it_as_it_slides():
    w = make(window=10, reorder_samples=1, max_gap=2)
    for k in [0, 1, 2, 4, 5, 6, 7, 9, 10, 11]:
        feed(w, k)
    assert w.n_window == 10 and w.window_gaps() == (2, 2)
    for k in range(12, 16):
        feed(w, k)                                          # the gap at 3 slides out
    np.testing.assert_array_equal(w.data().t, [5, 6, 7, 9, 10, 11, 12, 13, 14, 15])
    assert w.window_gaps() == (1, 1)
    assert w.health().missing_samples == 2                  # since the window was created


def test_random_short_gaps_keep_every_sample_on_its_stamp():
    rng = np.random.default_rng(3)
    w = make(window=200, reorder_samples=0, max_gap=4)
    sent = [k for k in range(400) if rng.random() > 0.05]
    for k in sent:
        feed(w, k)
    d = w.data()
    steps = np.diff(d.t)
    assert np.all(steps >= 1) and np.all(steps <= 5) and np.all(steps == np.round(steps))
    for i, t in enumerate(d.t):
        np.testing.assert_array_equal(d.y[i], sample_values(int(t))[2])
    assert int(d.t[-1]) == sent[-1] and d.n_samples == 200


def test_max_gap_checked():
    with pytest.raises(ConfigurationError, match=r"max_gap: expected an integer in \[0, 10000000\]"):
        WindowOptions(max_gap=-1)
    with pytest.raises(ConfigurationError, match=r"split_gap: expected an integer in \[0, 10000000\] \(samples\), got 2.5"):
        WindowOptions(split_gap=2.5)


def _hold_values(k):
    return {"setpoint": np.array([float(k), -float(k)]), "input": np.array([k, 2.0 * k, 3.0 * k]) + 0.2,
            "output": np.array([float(k), k + 1.0]) + 0.3}


def test_hold_setpoint_places_setpoints_in_stamp_order():
    """Hold mode: setpoints that arrive out of order (within the reorder window) or one stamped an
    hour ahead (a bad clock) still give every sample the setpoint stamped at or before it."""
    for bad in ("swapped", "future"):
        w = SampleWindow(OUT, INP, 1.0, WindowOptions(window_samples=60, hold_setpoint=True, reorder_samples=10))
        for k in range(0, 40, 2):
            order = (k + 1, k) if bad == "swapped" else (k, k + 1)
            for kk in order:
                w.add("setpoint", kk * NS, _hold_values(kk)["setpoint"])
            if bad == "future" and k == 10:
                w.add("setpoint", (k + 3600) * NS, _hold_values(k + 3600)["setpoint"])
            for kk in (k, k + 1):
                w.add("input", kk * NS, _hold_values(kk)["input"])
                w.add("output", kk * NS, _hold_values(kk)["output"])
        d = w.data()
        assert d.n_samples == 40, bad
        np.testing.assert_array_equal(d.r[:, 0], d.t, err_msg=bad)
        assert len(w._setpoints) <= 3                      # the held ones are pruned as samples complete


def test_the_oldest_incomplete_sample_is_named_with_what_it_lacks():
    """Samples complete in order: a sample that lacks a vector holds every newer one (until more than reorder_samples
    of them are complete).  The window names it, and the monitor's waiting message says it."""
    from mpm_monitor.monitor.statuses import waiting_message

    w = make(window=50, reorder_samples=10)
    for k in range(8):
        r, u, y = sample_values(k)
        w.add("setpoint", k * NS, r)
        w.add("output", k * NS, y)
        if k != 3:
            w.add("input", k * NS, u)
    assert w.n_completed == 3 and w.oldest_incomplete() == (3 * NS, ["input"], 5)
    assert waiting_message(w.n_window, 50, w.oldest_incomplete()) == (
        "no analysis yet: 3 of 50 samples collected; 5 more held incomplete, from t = 3 s (no input)")
    feed(w, 8)
    w.add("output", 9 * NS, sample_values(9)[2])
    assert w.oldest_incomplete() == (3 * NS, ["input"], 7)
    w.add("input", 3 * NS, sample_values(3)[1])
    assert w.n_completed == 9 and w.oldest_incomplete() == (9 * NS, ["setpoint", "input"], 1)
    feed(w, 9)
    assert w.oldest_incomplete() is None
    assert waiting_message(w.n_window, 50, None) == "no analysis yet: 10 of 50 samples collected"
