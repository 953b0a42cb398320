"""io/python_control.py: the model as python-control transfer functions, and back.

Reference: python-control 0.10 -- the element references of test/structure_models.py (``c2d`` of the
continuous element built from its parameters, times ``z^-n_d``; a step-response element from the
definition of its coefficients), their ``step_response`` and ``frequency_response``.  Tolerance
1e-9 absolute on responses of order 1; parameters of a round trip through the roots of the
polynomials to 1e-9 relative.
"""

import control
import numpy as np
import pytest
from structure_models import MODELS, element_reference, frequency_reference, rich_model, step_model, step_reference

from mpm_monitor.core.discretize import frequency_response, simulate_elements
from mpm_monitor.core.errors import ModelFileError
from mpm_monitor.core.model import PlantModel
from mpm_monitor.io.python_control import from_continuous, step_response_model, to_continuous, to_transfer_function

OMEGA = np.linspace(1e-3, np.pi, 61)


def _fr(sys, omega, ts):
    fr = sys.frequency_response(omega / ts)
    return np.moveaxis(np.asarray(fr.magnitude) * np.exp(1j * np.asarray(fr.phase)), -1, 0)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_discrete_transfer_function_has_the_model_responses(name):
    model = MODELS[name]()
    tf = to_transfer_function(model)
    assert tf.dt == model.sample_time and (tf.noutputs, tf.ninputs) == (2, 3)
    assert list(tf.input_labels) == ["u1", "u2", "dv1"] and list(tf.output_labels) == ["y1", "y2"]
    # Frequency response of the whole MIMO system against the independent reference and the model's own.
    ref = frequency_reference(model, OMEGA)
    np.testing.assert_allclose(_fr(tf, OMEGA, model.sample_time), ref, rtol=0, atol=1e-9)
    np.testing.assert_allclose(frequency_response(model, OMEGA), ref, rtol=0, atol=1e-9)
    # Step responses, element by element, by python-control from the converted system.
    n = 150
    t = np.arange(n) * model.sample_time
    for i in range(2):
        for j in range(3):
            got = np.asarray(control.step_response(tf[i, j], T=t).outputs).reshape(n)
            if model.is_step_response:
                ref_ij = step_reference(model, i, j, n)
            else:
                ref_ij = np.asarray(control.step_response(element_reference(model, i, j), T=t).outputs).reshape(n)
            np.testing.assert_allclose(got, ref_ij, rtol=0, atol=1e-9, err_msg=f"element ({i}, {j})")


def test_continuous_round_trip_gives_the_model_back():
    for model in (rich_model(), MODELS["first-order"]()):
        tf, delay = to_continuous(model)
        assert tf.isctime(strict=True)
        back = from_continuous(tf, delay, model.sample_time, disturbances=1, name=model.name)
        assert back.inputs == model.inputs and back.disturbances == model.disturbances
        np.testing.assert_array_equal(back.integrating, model.integrating)
        np.testing.assert_array_equal(back.delay, model.delay)
        for key in ("gain", "time_constant", "time_constant2", "lead"):
            np.testing.assert_allclose(getattr(back, key), getattr(model, key), rtol=1e-9, atol=1e-12, err_msg=key)
    with pytest.raises(ModelFileError, match="a step-response model has no continuous form"):
        to_continuous(step_model())


def test_continuous_transfer_functions_become_a_parametric_model():
    tf = control.tf([[[2.0], [0.5, 1.0], [0.3]]], [[[10.0, 1.0], [1.0, 0.3, 0.02], [2.0, 0.0]]],
                    inputs=["a", "b", "w"], outputs=["y"])
    model = from_continuous(tf, [[3.0, 0.0, 2.0]], 1.0, disturbances=1)
    assert model.inputs == ("a", "b") and model.disturbances == ("w",)
    # 0.5 s + 1 over (s + 0.1)(s + 0.2) = 50 (0.5 s + 1) / ((10 s + 1)(5 s + 1)).
    e = model.element(0, 1)
    np.testing.assert_allclose([e["gain"], e["lead"], e["time_constant"], e["time_constant2"]], [50.0, 0.5, 10.0, 5.0])
    e = model.element(0, 2)
    assert e["integrating"] is True and e["gain"] == pytest.approx(0.15)
    assert model.element(0, 0) == {"gain": 2.0, "time_constant": 10.0, "delay": 3.0}


BAD_CONTINUOUS = {
    "complex": ([1.0], [1.0, 0.2, 1.0], "complex poles"),
    "unstable": ([1.0], [5.0, -1.0], "right half-plane"),
    "three lags": ([1.0], np.convolve(np.convolve([1, 1], [2, 1]), [3, 1]), "more than two lags"),
    "two zeros": ([1.0, 2.0, 1.0], np.convolve([1, 1], [2, 1]), "more than one zero"),
    "derivative": ([1.0, 0.0], [5.0, 1.0], r"a zero at s = 0"),
    "improper": ([1.0, 1.0], [1.0], r"more zeros than poles"),
    "double integrator": ([1.0], [1.0, 0.0, 0.0], "more than one pole at s = 0"),
}


@pytest.mark.parametrize("case", sorted(BAD_CONTINUOUS))
def test_unsupported_continuous_forms_are_refused_with_one_line(case):
    num, den, why = BAD_CONTINUOUS[case]
    tf = control.tf([[[1.0], num]], [[[4.0, 1.0], den]], inputs=["u1", "u2"], outputs=["y1"])
    with pytest.raises(ModelFileError, match=r"^transfer function: element \(y1, u2\): num .* / den .*: .*" + why) as exc:
        from_continuous(tf, [[0.0, 0.0]], 1.0)
    assert "\n" not in str(exc.value) and "supported: K (lead s + 1)" in str(exc.value)


def test_bad_systems_and_delays_are_refused():
    tf = control.tf([[[1.0]]], [[[4.0, 1.0]]])
    with pytest.raises(ModelFileError, match=r"delay: expected 1 rows x 1 columns \(seconds\), got shape \(2,\)"):
        from_continuous(tf, [0.0, 1.0], 1.0)
    with pytest.raises(ModelFileError, match="expected a continuous system"):
        from_continuous(control.tf([1.0], [1.0, -0.5], 1.0), [[0.0]], 1.0)
    with pytest.raises(ModelFileError, match="expected a discrete system with a sampling time"):
        step_response_model(tf, 10)
    with pytest.raises(ModelFileError, match=r"disturbances: expected 0 .. 1"):
        from_continuous(tf, [[0.0]], 1.0, disturbances=2)


def test_step_response_model_of_a_parametric_model():
    # The coefficients are the exact sampled step responses; the integrating output ramps.
    model = rich_model()
    n = 300
    sm = step_response_model(to_transfer_function(model), n, disturbances=1)
    assert sm.is_step_response and sm.step_length == n and sm.ramp == (False, True)
    assert sm.disturbances == ("dv1",)
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(sm.step_response[i, j], model.discrete_element(i, j).step_response(n + 1)[1:],
                                       rtol=0, atol=1e-9)
    # Beyond N the step model continues as the parametric one: held, or the last slope on y2.
    u = np.random.default_rng(0).standard_normal((2 * n, 3))
    np.testing.assert_allclose(simulate_elements(sm, u), simulate_elements(model, u), rtol=0, atol=1e-6)
    assert step_response_model(to_transfer_function(model), n, disturbances=1, ramp=(True, True)).ramp == (True, True)


def test_step_response_model_round_trip_is_exact():
    sm = step_model(40)
    back = step_response_model(to_transfer_function(sm), 40, disturbances=1)
    assert back.ramp == sm.ramp and back.columns == sm.columns
    np.testing.assert_allclose(back.step_response, sm.step_response, rtol=0, atol=1e-12)


def test_discrete_elements_a_step_response_model_cannot_hold_are_refused():
    cases = [(control.tf([1.0, 0.0], [1.0, -0.5], 1.0), "a direct feed-through"),
             (control.tf([1.0], [1.0, -1.5], 1.0), "outside the unit circle"),
             (control.tf([1.0], [1.0, -2.0, 1.0], 1.0), "more than one pole at z = 1"),
             (control.tf([1.0, 0.0, 0.0], [1.0, -0.5], 1.0), "not causal")]
    for sys, why in cases:
        with pytest.raises(ModelFileError, match=r"^transfer function: element \(y\[0\], u\[0\]\): .*" + why):
            step_response_model(sys, 20)
    with pytest.raises(ModelFileError, match=r"length: expected an integer >= 2"):
        step_response_model(control.tf([1.0], [1.0, -0.5], 1.0), 1)
    # The default labels of python-control are acceptable channel names.
    ok = step_response_model(control.tf([1.0], [1.0, -0.5], 1.0), 20)
    assert isinstance(ok, PlantModel) and ok.inputs == ("u[0]",)
