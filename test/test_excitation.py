"""Excitation signals (excitation.py): PRBS statistics and spectrum, step/hold, zero, the timed dither of an experiment.

Reference for the spectrum: a binary signal that switches with probability p at every sample is a
two-state Markov chain with autocorrelation rho^|k|, rho = 1 - 2 p, hence the normalised power
spectrum (1 - rho^2) / (1 - 2 rho cos w + rho^2) (Ljung, *System Identification*, 2nd ed., 13.3);
flat for p = 1/2.
"""

import numpy as np
import pytest
from scipy import signal

from mpm_monitor.core.errors import ConfigurationError
from mpm_monitor.sim.excitation import PrbsGenerator, PrbsOptions, StepHoldGenerator, TimedDither, ZeroGenerator


def _prbs(n, seed, channels=1, **kw):
    return PrbsGenerator(channels, PrbsOptions(**kw), np.random.default_rng(seed)).generate(n)


def _run_lengths(x):
    """Lengths of the runs of equal values in a 1-D sequence."""
    edges = np.flatnonzero(np.diff(x) != 0)
    bounds = np.r_[0, edges + 1, x.size]
    return np.diff(bounds)


def test_prbs_values_are_offset_plus_minus_amplitude():
    x = _prbs(2000, 1, channels=3, amplitude=0.7, offset=2.0)
    assert x.shape == (2000, 3)
    assert set(np.unique(x)) == {1.3, 2.7}
    # Both levels occur on every channel.
    assert np.all((x == 1.3).any(axis=0)) and np.all((x == 2.7).any(axis=0))
    # Zero amplitude: a constant at the offset.
    np.testing.assert_array_equal(_prbs(10, 1, amplitude=0.0, offset=-1.0), -1.0)


def test_prbs_deterministic_per_seed():
    a = _prbs(500, 123, channels=2, switch_probability=0.3)
    b = _prbs(500, 123, channels=2, switch_probability=0.3)
    np.testing.assert_array_equal(a, b)
    c = _prbs(500, 124, channels=2, switch_probability=0.3)
    assert np.any(a != c)
    # next() and generate() give the same sequence.
    gen = PrbsGenerator(2, PrbsOptions(switch_probability=0.3), np.random.default_rng(123))
    np.testing.assert_array_equal(np.array([gen.next() for _ in range(500)]), a)


@pytest.mark.parametrize("p", [0.05, 0.2, 0.5, 0.9])
def test_prbs_switch_rate_matches_probability(p):
    # Switches per sample ~ Binomial(n - 1, p) / (n - 1): std sqrt(p (1 - p) / n) <= 0.0035 for
    # n = 20000; bound 5 std on each of 2 channels.
    n = 20000
    x = _prbs(n, 7, channels=2, switch_probability=p)
    rate = np.mean(np.diff(x, axis=0) != 0, axis=0)
    np.testing.assert_allclose(rate, p, atol=5 * np.sqrt(p * (1 - p) / n))


def test_prbs_p_half_spectrum_is_flat():
    # Welch PSD (Hann, 256 per segment, 2^15 samples, ~255 segments): each band average of ~32
    # bins has a relative std ~ 1.5 %; bound: low band (0 - 1/4 Nyquist) / high band (3/4 - 1)
    # within [0.85, 1.15].
    x = _prbs(2 ** 15, 3, switch_probability=0.5)[:, 0]
    f, pxx = signal.welch(x, nperseg=256, detrend=False)
    low = pxx[(f > 0) & (f <= 0.125)].mean()
    high = pxx[(f >= 0.375) & (f < 0.5)].mean()
    assert 0.85 < low / high < 1.15
    # White with unit variance: two-sided density 1, i.e. one-sided 2 (scipy's default scaling).
    np.testing.assert_allclose(pxx[1:-1].mean(), 2.0, rtol=0.05)


@pytest.mark.parametrize("p", [0.1, 0.5, 0.8])
def test_prbs_spectrum_matches_markov_reference(p):
    # Reference: 2 (1 - rho^2) / (1 - 2 rho cos w + rho^2), rho = 1 - 2 p (one-sided density for
    # unit variance, scipy.signal.welch scaling).  Band averages over 8 bands within 15 %.
    x = _prbs(2 ** 15, 5, switch_probability=p)[:, 0]
    f, pxx = signal.welch(x, nperseg=256, detrend=False)
    rho = 1 - 2 * p
    w = 2 * np.pi * f
    ref = 2 * (1 - rho ** 2) / (1 - 2 * rho * np.cos(w) + rho ** 2)
    inner = (f > 0) & (f < 0.5)
    for band in np.array_split(np.flatnonzero(inner), 8):
        np.testing.assert_allclose(pxx[band].mean(), ref[band].mean(), rtol=0.15)
    if p < 0.5:  # the test can tell a low-pass PRBS from a flat one
        assert pxx[1:10].mean() > 3 * pxx[-10:-1].mean()


def test_prbs_channels_are_independent():
    # Sample correlation of independent white sequences: std 1/sqrt(n) ~ 0.007; bound 0.04.
    x = _prbs(20000, 9, channels=3)
    c = np.corrcoef(x.T)
    assert np.max(np.abs(c[np.triu_indices(3, 1)])) < 0.04


@pytest.mark.parametrize("min_hold,p", [(1, 1.0), (3, 1.0), (4, 0.5), (10, 0.3)])
def test_prbs_min_hold_respected(min_hold, p):
    # Every run (but the truncated last one) lasts at least min_hold samples; a run lasts
    # min_hold - 1 + Geometric(p) samples, mean min_hold - 1 + 1/p (std of the mean of ~N runs
    # sqrt(1 - p) / p / sqrt(N)); bound 5 std.
    x = _prbs(20000, 2, switch_probability=p, min_hold=min_hold)[:, 0]
    runs = _run_lengths(x)[:-1]
    assert runs.min() >= min_hold
    if p == 1.0:
        assert np.all(runs == min_hold)  # deterministic: switches exactly every min_hold samples
    else:
        expect = min_hold - 1 + 1 / p
        np.testing.assert_allclose(runs.mean(), expect, atol=5 * np.sqrt(1 - p) / p / np.sqrt(runs.size))
        assert np.any(runs == min_hold)  # the bound is reached, not merely respected


@pytest.mark.parametrize("kw,pattern", [
    (dict(amplitude=-1.0), "amplitude"),
    (dict(amplitude=np.inf), "amplitude"),
    (dict(switch_probability=0.0), "switch_probability"),
    (dict(switch_probability=1.5), "switch_probability"),
    (dict(min_hold=0), "min_hold"),
    (dict(min_hold=1.5), "min_hold"),
    (dict(offset=np.nan), "offset"),
])
def test_prbs_options_refused(kw, pattern):
    with pytest.raises(ConfigurationError, match=pattern):
        PrbsOptions(**kw)


def test_step_hold_generator():
    levels = [[1.0, -1.0], [0.5, 0.0], [-2.0, 3.0]]
    gen = StepHoldGenerator(levels, hold_samples=4)
    x = gen.generate(30)
    assert x.shape == (30, 2)
    expect = np.repeat(np.array(levels), 4, axis=0)
    np.testing.assert_array_equal(x[:12], expect)
    np.testing.assert_array_equal(x[12:24], expect)  # the sequence repeats
    np.testing.assert_array_equal(x[24:], expect[:6])
    # next() continues where generate() stopped; returned vectors are copies.
    v = gen.next()
    np.testing.assert_array_equal(v, levels[1])
    v[:] = 99.0
    np.testing.assert_array_equal(StepHoldGenerator(levels, 1).generate(3), levels)


@pytest.mark.parametrize("levels,hold,pattern", [
    ([], 3, "levels"),
    ([[1.0, np.nan]], 3, "levels"),
    ([[1.0]], 0, "hold_samples"),
    ([[1.0]], 2.5, "hold_samples"),
])
def test_step_hold_generator_refused(levels, hold, pattern):
    with pytest.raises(ConfigurationError, match=pattern):
        StepHoldGenerator(levels, hold)


def test_zero_generator():
    gen = ZeroGenerator(3)
    np.testing.assert_array_equal(gen.generate(5), np.zeros((5, 3)))
    np.testing.assert_array_equal(gen.next(), np.zeros(3))


# ------------------------------------------------------------------- the timed dither (experiments)
def test_timed_dither_lasts_its_samples_on_its_inputs_then_zero():
    d = TimedDither([0.0, 0.5, 0.0, 0.2, 0.0], 7, np.random.default_rng(3))
    values = np.array([d.next() for _ in range(9)])
    assert not d.running and d.samples_left == 0
    np.testing.assert_array_equal(np.abs(values[:7]), np.tile([0.0, 0.5, 0.0, 0.2, 0.0], (7, 1)))
    np.testing.assert_array_equal(values[7:], 0.0)
    again = TimedDither([0.0, 0.5, 0.0, 0.2, 0.0], 7, np.random.default_rng(3))
    np.testing.assert_array_equal([again.next() for _ in range(7)], values[:7])  # seeded: the same PRBS
    assert len({tuple(np.sign(v)) for v in values[:7]}) > 1                       # and it does switch


@pytest.mark.parametrize("amplitudes, samples, what", [([0.0, 0.0], 5, "amplitudes"), ([0.1, -0.1], 5, "amplitudes"),
                                                      ([0.1, np.nan], 5, "amplitudes"), ([0.1, 0.0], 0, "samples")])
def test_timed_dither_refuses_bad_settings(amplitudes, samples, what):
    with pytest.raises(ConfigurationError, match=what):
        TimedDither(amplitudes, samples, np.random.default_rng(0))
