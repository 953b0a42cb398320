"""core/signals.py for every element structure and the measured-disturbance columns.

References: ``yhat`` against python-control's ``forced_response`` of every element reference summed
(test/structure_models.py: ``c2d`` of the continuous element built from its parameters, delays as
``z^-n_d``; a step-response element from its coefficients), 1e-9.  The initial-state estimate is
checked by an invariant: a record cut from a longer run (the model's state unknown at its first
sample) gives, once the estimate is subtracted, the prediction error of the model run from the
true start up to a constant (the level of an integrating output) and the noise of the estimate.
"""

import numpy as np
import pytest
from structure_models import MODELS, reference_response, rich_model, step_model

from mpm_monitor.core.discretize import discretize, simulate_elements
from mpm_monitor.core.errors import DataFileError
from mpm_monitor.core.filters import lfilter
from mpm_monitor.core.logged_data import LoggedData, check_disturbance_signal, check_loop_data
from mpm_monitor.core.model import PlantModel
from mpm_monitor.core.signals import compute_signals
from mpm_monitor.core.sliding import SlidingWindowAnalyzer


def _prbs(rng, n, width, hold=8):
    return np.repeat(rng.choice([-1.0, 1.0], size=(n // hold + 1, width)), hold, axis=0)[:n]


def _record(model, n, seed, noise=0.01, burn_in=0):
    """Open-loop columns and outputs of ``model`` (PRBS inputs, AR(1) disturbance), the first
    ``burn_in`` samples cut off (the model's state at the record's start then unknown)."""
    rng = np.random.default_rng(seed)
    total = n + burn_in
    x = np.hstack([_prbs(rng, total, model.n_inputs),
                   lfilter([1.0], [1.0, -0.9], rng.standard_normal((total, model.n_disturbances)), axis=0)])
    v = lfilter([1.0], [1.0, -0.9], noise * rng.standard_normal((total, model.n_outputs)), axis=0)
    y_true = simulate_elements(model, x)
    return x[burn_in:], y_true[burn_in:] + v[burn_in:], v[burn_in:]


@pytest.mark.parametrize("name", sorted(MODELS))
def test_yhat_is_the_response_to_inputs_and_disturbances(name):
    model = MODELS[name]()
    nu = model.n_inputs
    x, y, _ = _record(model, 400, seed=1)
    r = np.zeros_like(y)
    ref = reference_response(model, x)
    sig = compute_signals(model, r, x[:, :nu], y, "zero", dv=x[:, nu:])
    np.testing.assert_allclose(sig.yhat, ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sig.d, y - ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sig.eps, r - sig.d, rtol=0, atol=0)
    # Data that start at rest keep the zero initial state.
    est = compute_signals(model, r, x[:, :nu], y, "estimate", dv=x[:, nu:])
    np.testing.assert_array_equal(est.transient, 0.0)
    # Without the disturbance column the response is another one: the column is used.
    assert np.max(np.abs(simulate_elements(model, np.hstack([x[:, :nu], 0 * x[:, nu:]])) - ref)) > 0.05


def _transient_error(model, seed):
    """RMS of (d - v) after the model's memory, centred, with the initial state estimated and zero."""
    x, y, v = _record(model, 1500, seed=seed, noise=0.002, burn_in=700)
    nu = model.n_inputs
    start = discretize(model).memory
    out = {}
    for how in ("estimate", "zero"):
        d = compute_signals(model, np.zeros_like(y), x[:, :nu], y, how, dv=x[:, nu:]).d[start:]
        e = (d - d.mean(axis=0)) - (v[start:] - v[start:].mean(axis=0))
        out[how] = np.sqrt(np.mean(e ** 2, axis=0))
    return out


def test_initial_state_of_second_lags_leads_and_integrators_is_estimated():
    # Rich model (second lags, an inverse response, integrators): the free responses of every
    # pole in (0, 1) are removed; the integrator's level is a constant the centring removes.
    err = _transient_error(rich_model(), seed=7)
    assert np.all(err["zero"] > 0.05)                # the unknown start matters
    assert np.all(err["estimate"] < 0.02 * err["zero"])


def test_a_repeated_lag_needs_its_k_p_to_the_k_response():
    model = PlantModel(1.0, ("u",), ("y",), gain=[[2.0]], time_constant=[[15.0]], time_constant2=[[15.0]],
                       delay=[[2.0]])
    assert discretize(model).lag_poles(0) == {round(float(np.exp(-1 / 15.0)), 12): 2}
    err = _transient_error(model, seed=5)
    # With p^k alone the estimate leaves about half of the transient (0.045 of 0.085).
    assert err["zero"][0] > 0.05 and err["estimate"][0] < 0.02 * err["zero"][0]


def test_the_lag_poles_of_a_first_order_row_are_those_of_the_element_by_element_clustering():
    """A row of first-order elements: each element's pole rounded, deduplicated and sorted, integrators,
    zero poles and static elements left out."""
    from mpm_monitor.core.discretize import INTEGRATOR_TOLERANCE

    rng = np.random.default_rng(11)
    tau = 10.0 ** rng.uniform(-1.5, 3.5, (3, 30))
    tau[0, :4] = tau[0, 4]                                # one pole four times
    tau[1, :3] = 0.0                                      # static elements: no pole
    gain = rng.normal(size=(3, 30))
    gain[2, :5] = 0.0
    integrating = np.zeros((3, 30), dtype=bool)
    integrating[1, :2] = True                             # pure integrators (pole 1)
    tau[2, 5] = 1e-3                                      # a pole of exp(-1000): 0 to rounding
    model = PlantModel(1.0, tuple(f"u{j}" for j in range(30)), ("y1", "y2", "y3"), gain=gain, time_constant=tau,
                       delay=rng.integers(0, 9, (3, 30)).astype(float), integrating=integrating)
    disc = discretize(model)
    for i in range(3):
        expected = {}
        for j in np.flatnonzero(disc.active[i]):
            for p in disc.poles(i, j):
                v = float(np.round(p, 12))
                if 0.0 < v < 1.0 - INTEGRATOR_TOLERANCE:
                    expected[v] = 1
        assert len(expected) > 10
        got = disc.lag_poles(i)
        assert got == dict(sorted(expected.items())) and list(got) == sorted(expected)


def test_a_step_response_model_has_no_free_response_beyond_its_coefficients():
    # Noise-free record cut from a longer run: once the inputs before the record have left the
    # N coefficients (the model's memory: its longest register, then one sample in the elements'
    # state), the prediction error of the model started at rest is exactly the ramp row's level
    # (a constant), and 0 on the other row.
    model = step_model(40)
    x, y, _ = _record(model, 300, seed=4, noise=0.0, burn_in=200)
    nu = model.n_inputs
    mem = discretize(model).memory + 1
    assert 40 <= mem <= 46
    sig = compute_signals(model, np.zeros_like(y), x[:, :nu], y, "estimate", dv=x[:, nu:])
    np.testing.assert_array_equal(sig.transient, 0.0)            # no pole in (0, 1): nothing to estimate
    assert np.abs(sig.d[:mem - 1, 0]).max() > 0.01                # the unknown start shows before ...
    np.testing.assert_allclose(sig.d[mem:, 0], 0.0, atol=1e-12)  # ... and not after
    assert abs(sig.d[mem:, 1].mean()) > 0.01                    # the ramp row's level ...
    np.testing.assert_allclose(sig.d[mem:, 1], sig.d[mem, 1], atol=1e-12)     # ... is constant


def _dv_data(n=50, **kw):
    model = rich_model()
    base = dict(t=np.arange(n, dtype=float), r=np.zeros((n, 2)), u=np.zeros((n, 2)), y=np.zeros((n, 2)),
                inputs=model.inputs, outputs=model.outputs, sample_time=1.0, source="log.csv",
                dv=np.zeros((n, 1)), disturbances=model.disturbances)
    base.update(kw)
    return model, LoggedData(**base)


@pytest.mark.parametrize("kw,match", [
    (dict(dv=np.zeros((50, 2))), r"^log.csv: measured disturbance: expected shape \(50, 1\), got \(50, 2\)$"),
    (dict(dv=np.zeros((49, 1))), r"^log.csv: measured disturbance: expected shape \(50, 1\), got \(49, 1\)$"),
    (dict(dv=np.full((50, 1), np.nan)), r"^log.csv: measured disturbance: values contain NaN or infinity$"),
    (dict(disturbances=("w",)), r"^log.csv: measured disturbances \['w'\] do not match the model's disturbances "
                                r"\['dv1'\]$"),
    (dict(dv=None, disturbances=()), r"^log.csv: measured disturbances \[\] do not match"),
])
def test_bad_disturbances_are_refused_with_one_line(kw, match):
    model, data = _dv_data(**kw)
    with pytest.raises(DataFileError, match=match):
        check_loop_data(model, data)


def test_bad_dv_for_signals_and_the_sliding_analyzer():
    model = rich_model()
    z = np.zeros((300, 2))
    with pytest.raises(DataFileError, match=r"^measured disturbance: expected shape \(300, 1\), got none$"):
        compute_signals(model, z, z, z)
    with pytest.raises(DataFileError, match=r"^measured disturbance: expected shape \(300, 1\), got \(300,\)$"):
        compute_signals(model, z, z, z, dv=np.zeros(300))
    an = SlidingWindowAnalyzer(model, window=2000)
    with pytest.raises(DataFileError, match=r"^measured disturbance: expected shape \(1,\), got \(2,\)$"):
        an.push(np.zeros(2), np.zeros(2), np.zeros(2), dv=np.zeros(2))
    with pytest.raises(DataFileError, match=r"^measured disturbance: expected shape \(1,\), got none$"):
        an.push(np.zeros(2), np.zeros(2), np.zeros(2))
    with pytest.raises(DataFileError, match=r"^measured disturbance: expected shape \(5, 1\), got \(4, 1\)$"):
        an.push_many(z[:5], z[:5], z[:5], dv=np.zeros((4, 1)))
    # A model without disturbances refuses a dv, and accepts none.
    assert check_disturbance_signal(None, 0, 3).shape == (3, 0)
    with pytest.raises(DataFileError, match=r"expected shape \(3, 0\), got \(3, 1\)"):
        check_disturbance_signal(np.zeros((3, 1)), 0, 3)
