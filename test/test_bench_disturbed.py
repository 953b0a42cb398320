"""bench.disturbed: analyze on a log whose every output carries an unmeasured step (a small case, one repeat)."""

import numpy as np
import pytest

from bench import disturbed


def test_the_case_has_one_step_on_every_output_that_the_controller_answers():
    model, log, steps = disturbed.disturbed_case(3, 3, samples=3000)
    assert steps.shape == (3000, 3)
    for i in range(3):
        moved = np.flatnonzero(np.diff(steps[:, i]))
        assert moved.size == 1 and 900 <= moved[0] + 1 < 2100          # one step, in [0.3, 0.7] of the record
        assert steps[-1, i] > 0 and np.all(steps[:moved[0] + 1, i] == 0)
    assert np.asarray(log.y).shape == (3000, 3) and model.n_outputs == 3


def test_the_command_reports_each_step_and_is_timed_both_ways():
    out = disturbed.run([(3, 3)], repeats=1, samples=3000, log=lambda *_: None)
    res = out["sizes"]["3x3"]
    assert res["disturbances"] == 3                       # every output's step, confirmed
    assert res["two_exit"] == [0] and res["one_exit"] == [0]
    assert res["two_wall_s"] > 0 and res["one_wall_s"] > 0 and len(res["two_walls"]) == 1


def test_bad_sizes_are_refused():
    with pytest.raises(SystemExit):
        disturbed.main(["--sizes", "3by3"])
    with pytest.raises(SystemExit):
        disturbed.main(["--repeats", "0"])
