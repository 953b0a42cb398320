"""bench.monte_carlo --setpoint-steps: the same scenarios with setpoints moved in steps."""

import numpy as np
import pytest

from bench import monte_carlo
from bench.scenarios import SETPOINT_STEPS, ScenarioOptions, make_scenario


def test_setpoint_steps_change_only_the_setpoints_excitation():
    for index in range(5):
        a, b = make_scenario(0, index, SETPOINT_STEPS), make_scenario(0, index, ScenarioOptions())
        assert a.excitation.setpoint.min_hold == 60 and a.excitation.setpoint.switch_probability == 0.01
        assert b.excitation.setpoint.min_hold == 1 and b.excitation.setpoint.switch_probability == 0.5
        assert a.plant == b.plant and a.model == b.model and a.mismatches == b.mismatches
        assert a.dither == b.dither and a.loop_seed == b.loop_seed


def test_still_and_setpoint_steps_exclude_each_other(capsys):
    with pytest.raises(SystemExit) as exc:
        monte_carlo.main(["--still", "--setpoint-steps", "--runs", "1"])
    assert exc.value.code == 2 and "exclude each other" in capsys.readouterr().err


def test_a_setpoint_steps_loop_holds_each_setpoint_for_its_minimum():
    sc = make_scenario(0, 2, SETPOINT_STEPS)
    log = monte_carlo._closed_loop(sc, 1500)
    for r in log.r.T:
        switches = np.flatnonzero(np.diff(r) != 0)
        assert 0 < switches.size < 1500 / 60 and np.all(np.diff(switches) >= 60)


def test_repair_mc_takes_the_setpoint_steps():
    from bench import repair_mc

    res = repair_mc.run(1, 0, 1500, dither_fat=True, setpoint_steps=True)
    assert res["setpoints"] == "steps" and "setpoints in steps" in repair_mc.format_table(res)
