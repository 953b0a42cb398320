"""bench.quantized: the outputs rounded to a multiple of their noise, and the analysis's warning."""

import numpy as np

from bench import quantized


def test_rounded_puts_each_output_on_its_own_grid():
    y = np.array([[0.26, 1.4], [-0.74, 2.6]])
    out = quantized.rounded(y, np.array([0.5, 2.0]))
    np.testing.assert_allclose(out, [[0.5, 2.0], [-0.5, 2.0]])


def test_one_run_is_analysed_as_simulated_and_rounded_and_the_coarse_log_is_warned_about():
    rec = quantized.one(0, 3, 1200, 0.01, (0.5, 10.0))
    assert rec["truth"] == [[3, 5]] and len(rec["noise_std"]) == rec["shape"][0]
    assert not rec["0"]["warned"] and not rec["0.5"]["warned"] and rec["10"]["warned"]
    assert rec["0.5"]["located"] == rec["0"]["located"]
    s = quantized.summarise([rec], (0.5, 10.0))
    assert s["0"]["hits"] == len(rec["0"]["located"]) and s["10"]["runs_warned"] == 1
    assert "runs warned" in quantized.format_table({"config": {"runs": 1, "seed": 0, "samples": 1200, "alpha": 0.01,
                                                               "ratios": [0.5, 10.0]}, "summary": s, "seconds": 1.0})


def test_an_inputs_step_moves_its_most_sensitive_output_by_that_outputs_noise():
    gain = np.array([[2.0, 0.0], [-0.5, 0.0], [1.0, 4.0]])
    noise = np.array([0.2, 0.1, 0.4])
    # Input 1: min(0.2 / 2, 0.1 / 0.5, 0.4 / 1) = 0.1; input 2: only row 3, 0.4 / 4.
    np.testing.assert_allclose(quantized.input_steps(gain, noise), [0.1, 0.1])
