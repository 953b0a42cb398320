"""The initial-transient estimate stays well-posed when a row has many nearly equal poles.

An integrating row with five second-order elements (ten lags between 5 and 17 s) made least
squares fit the free responses with amplitudes ~5e5 cancelling each other; the conditioned
estimate keeps amplitudes of the transient's own size and recovers it.
"""

import numpy as np

from mpm_monitor.core.discretize import discretize, settling_samples
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.signals import (
    TRANSIENT_MAX_CANCELLATION,
    cancellation,
    free_responses,
    initial_transient,
    transient_amplitudes,
)

N = 3000


def _crowded_row():
    nc = 5
    return PlantModel(sample_time=1.0, inputs=tuple(f"u{k}" for k in range(nc)), outputs=("y1",),
                      gain=np.full((1, nc), 0.05), time_constant=np.array([[12.0, 13.1, 14.3, 15.2, 16.9]]),
                      time_constant2=np.array([[5.1, 5.9, 6.4, 7.2, 7.7]]), delay=np.ones((1, nc)),
                      integrating=np.ones((1, nc), bool))


def _drifting_error(amplitude, seed=0):
    rng = np.random.default_rng(seed)
    t = np.arange(N)
    d0 = 0.002 * t + np.cumsum(rng.normal(0, 0.01, N)) + rng.normal(0, 0.005, N)
    d0[1:] += amplitude * 0.9 ** t[:-1]
    return d0[:, None]


def _basis(model):
    disc = discretize(model)
    span = min(N - disc.memory, max(settling_samples(model), 50))
    poles = np.array(list(disc.lag_poles(0)))
    basis = free_responses(poles, np.array([]), [], np.arange(span))
    return disc.memory, span, basis - basis.mean(axis=0)


def test_crowded_poles_plain_least_squares_is_ill_posed():
    model = _crowded_row()
    lag, span, X = _basis(model)
    assert X.shape[1] == 10
    seg = _drifting_error(0.3)[lag:lag + span, 0]
    plain, *_ = np.linalg.lstsq(X, seg - seg.mean(), rcond=1e-10)
    assert cancellation(X, plain) > 1e5            # the failure the conditioning mends


def test_crowded_poles_transient_is_well_posed_and_recovered():
    model = _crowded_row()
    lag, span, X = _basis(model)
    for amplitude in (0.3, 3.0):
        d0 = _drifting_error(amplitude)
        seg = d0[lag:lag + span, 0]
        coef = transient_amplitudes(X, seg - seg.mean())
        assert cancellation(X, coef) <= TRANSIENT_MAX_CANCELLATION
        assert np.abs(coef).max() < 100 * amplitude
        tr = initial_transient(model, d0)
        assert np.abs(tr[:500]).max() < 1.5 * amplitude + 0.2


def test_well_posed_estimate_is_plain_least_squares_bit_for_bit():
    poles = np.array([0.5, 0.8, 0.95])
    k = np.arange(300)
    X = free_responses(poles, np.array([]), [], k)
    X = X - X.mean(axis=0)
    rng = np.random.default_rng(1)
    target = X @ np.array([1.0, -2.0, 0.5]) + rng.normal(0, 0.01, 300)
    target = target - target.mean()
    plain, *_ = np.linalg.lstsq(X, target, rcond=1e-10)
    assert np.array_equal(transient_amplitudes(X, target), plain)


def _first_order_row():
    return PlantModel(sample_time=1.0, inputs=("u1",), outputs=("y1",), gain=np.array([[1.0]]),
                      time_constant=np.array([[8.0]]), delay=np.ones((1, 1)))


def test_the_decisions_noise_model_reads_only_the_samples_before_a_runs_first_gap(monkeypatch):
    """With ``clean`` (the samples before a run's first gap) the noise model that whitens the decision is fitted
    on them alone: whatever follows (held outputs, the model's response to held columns) leaves the estimate as it
    is.  With too few samples there, the whole record after the span is read, as without ``clean``."""
    import mpm_monitor.core.signals as signals
    from mpm_monitor.core.signals import TRANSIENT_NOISE_SAMPLES

    model = _first_order_row()
    lag, span = discretize(model).memory, max(settling_samples(model), 50)
    rng = np.random.default_rng(3)
    e = rng.normal(0, 0.01, N)
    d0 = np.zeros(N)
    for t in range(2, N):                               # an AR(2) disturbance
        d0[t] = 1.2 * d0[t - 1] - 0.4 * d0[t - 2] + e[t]
    d0[1:] += 0.5 * 0.88 ** np.arange(N - 1)            # and a transient of the row's pole
    clean = 1500
    spoiled = d0.copy()
    spoiled[clean:] += 0.3 * np.sin(np.arange(N - clean) / 3.0)     # what a gap leaves after it
    a = initial_transient(model, d0[:, None], clean=clean)
    assert np.abs(a).max() > 0.2                        # the transient is found
    assert np.array_equal(a, initial_transient(model, spoiled[:, None], clean=clean))
    assert np.array_equal(initial_transient(model, d0[:clean, None])[:clean], a[:clean])

    read = []
    fit = signals.least_squares_ar
    monkeypatch.setattr(signals, "least_squares_ar", lambda x, order: read.append(x.size) or fit(x, order))
    short = lag + span + TRANSIENT_NOISE_SAMPLES - 1
    for c in (clean, None, short):
        initial_transient(model, spoiled[:, None], clean=c)
    assert read == [clean - lag - span, N - lag - span, N - lag - span]
