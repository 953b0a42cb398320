"""What the repair computes once instead of again gives the same numbers.

- The disturbance test of an output whose prediction error an earlier evaluation of the repair
  tested as it is (a row not repaired, or not repaired again) is taken over: the tests equal those
  of every output tested afresh, and only the changed outputs are tested again.
- The step test's quadratic forms of the cumulative regressors equal ``np.einsum`` term by term.

No timings here: bench/stages.py and bench/repair_mc.py measure them.
"""

import numpy as np
import pytest

from mpm_monitor.core.repair import model_repair, repair_model, unexplained_disturbance
from mpm_monitor.core.repair.disturbance import _row_quadratic_forms
from mpm_monitor.sim.cases import shell_plant
from mpm_monitor.sim.closed_loop import run_closed_loop

N_SAMPLES = 4000


@pytest.fixture(scope="module")
def stepped_gain_log():
    """A gain error on y2/u2 and an unmeasured step on y2: the repair redoes row y2 with the step."""
    sh = shell_plant()
    model = sh.with_element(1, 1, gain=4.0)
    step = np.zeros((N_SAMPLES, 3))
    step[N_SAMPLES // 2:, 1] = 0.1
    return model, run_closed_loop(sh, model, N_SAMPLES, seed=11, output_disturbance=step).as_logged_data()


def test_disturbance_tests_of_unchanged_outputs_are_taken_over(stepped_gain_log, monkeypatch):
    model, data = stepped_gain_log
    calls = []

    def counted(d, *args, **kwargs):
        calls.append(np.array(d, copy=True))
        return unexplained_disturbance(d, *args, **kwargs)

    monkeypatch.setattr(model_repair, "unexplained_disturbance", counted)
    res = repair_model(model, data, [(1, 1)])
    assert any("allowed for the unexplained step" in w for w in res.warnings)      # two evaluations
    # Every output once, then the redone row only.
    assert len(calls) == model.n_outputs + 1
    np.testing.assert_array_equal(calls[-1], res.signals.d[:, 1])
    opts = res.options
    spread = np.std(np.asarray(data.y, float), axis=0)
    fresh = [unexplained_disturbance(res.signals.d[:, i], model.sample_time, opts.disturbance_alpha,
                                     opts.disturbance_trim, opts.noise_order, scale=float(spread[i]))
             for i in range(model.n_outputs)]
    expected = [{"output": model.outputs[i], "kind": t["kind"], "size": t["size"], "time": t["time"],
                 "rate": t["rate"], "p_value": t["p_value"], "statistic": t["statistic"]}
                for i, t in enumerate(fresh) if t["detected"]]
    assert res.disturbances == expected
    assert [d["output"] for d in res.disturbances] == ["y2"]


@pytest.mark.parametrize("n, k", [(1, 1), (60, 5), (9000, 5), (20000, 7), (3000, 23)])
def test_row_quadratic_forms_equal_einsum(n, k):
    rng = np.random.default_rng(n + k)
    x = rng.standard_normal((n, k)) * 10.0 ** rng.uniform(-3, 3, k)
    x[:, 0] = 1.0
    q = np.cumsum(x[::-1], axis=0)[::-1]                 # as the step test builds it: a reversed view
    a = np.linalg.pinv(x.T @ x)
    np.testing.assert_array_equal(_row_quadratic_forms(q, a), np.einsum("ij,jk,ik->i", q, a, q))
