"""Models of every element structure, and their python-control references, for the tests.

The reference of a parametric element is built from its parameters with python-control alone:
the continuous ``K (lead s + 1) / ((tau s + 1)(tau2 s + 1))`` (over ``s`` when integrating),
``control.c2d(..., 'zoh')`` (scipy's ``cont2discrete``), times ``z^-n_d``.  The reference of a
step-response element follows the definition of the model file: the impulse response
``s_l - s_(l-1)`` as a finite impulse response, and for a ramp output the last slope continued,
``h_N / (1 - z^-1)`` after ``N`` samples.
"""

import control
import numpy as np

from mpm_monitor.core.model import PlantModel

INPUTS, DISTURBANCES, OUTPUTS = ("u1", "u2"), ("dv1",), ("y1", "y2")


def rich_model(sample_time: float = 1.0) -> PlantModel:
    """2 outputs x (2 inputs + 1 measured disturbance): second lag, inverse response (negative lead),
    first order, integrator with a lag, integrator with a lead, second lag with a lead."""
    ts = sample_time
    return PlantModel(
        sample_time=ts, inputs=INPUTS, outputs=OUTPUTS, disturbances=DISTURBANCES,
        gain=[[2.0, 1.0, 0.8], [0.05, 0.02, -0.5]],
        time_constant=[[10.0, 8.0, 6.0], [5.0, 0.0, 12.0]],
        time_constant2=[[4.0, 0.0, 0.0], [0.0, 0.0, 3.0]],
        lead=[[0.0, -3.0, 0.0], [0.0, 4.0, 2.0]],
        integrating=[[False, False, False], [True, True, False]],
        delay=np.array([[2, 1, 0], [3, 2, 4]]) * ts)


def step_model(n: int = 40) -> PlantModel:
    """2 outputs x (2 inputs + 1 disturbance) step-response model of ``n`` coefficients; output y2 ramps."""
    k = np.arange(1, n + 1)
    coefs = np.zeros((2, 3, n))
    coefs[0, 0] = np.where(k > 3, 1.5 * (1 - np.exp(-(k - 3) / 6.0)), 0.0)
    coefs[0, 1] = np.where(k > 1, -0.7 * (1 - np.exp(-(k - 1) / 4.0)) + 0.02 * np.sin(k / 5.0) * (k < 30), 0.0)
    coefs[0, 2] = 0.4 * (1 - np.exp(-k / 3.0))
    coefs[1, 0] = np.where(k > 2, 0.05 * (k - 2) - 0.2 * (1 - np.exp(-(k - 2) / 4.0)), 0.0)    # a ramp
    coefs[1, 2] = np.where(k > 5, 0.3 * (1 - np.exp(-(k - 5) / 2.0)), 0.0)                      # settles
    return PlantModel.from_step_response(1.0, INPUTS, OUTPUTS, coefs, ramp=(False, True), disturbances=DISTURBANCES)


def first_order_model() -> PlantModel:
    """2 outputs x (2 inputs + 1 disturbance), every element first order plus dead time."""
    return PlantModel(sample_time=1.0, inputs=INPUTS, outputs=OUTPUTS, disturbances=DISTURBANCES,
                      gain=[[1.2, 0.6, 0.9], [0.4, 1.5, 0.7]], time_constant=[[8.0, 5.0, 6.0], [4.0, 9.0, 3.0]],
                      delay=[[2.0, 1.0, 0.0], [0.0, 3.0, 2.0]])


MODELS = {"rich": rich_model, "step": step_model, "first-order": first_order_model}


def parametric_reference(model: PlantModel, i: int, j: int):
    """The discrete python-control transfer function of parametric element (i, j) (module docstring)."""
    ts = model.sample_time
    k = float(model.gain[i, j])
    if k == 0:
        return control.tf([0.0], [1.0], ts)
    lead = float(model.lead[i, j])
    num = [k * lead, k] if lead else [k]
    den = np.array([1.0])
    for tau in (model.time_constant[i, j], model.time_constant2[i, j]):
        if tau > 0:
            den = np.convolve(den, [float(tau), 1.0])
    if model.integrating[i, j]:
        den = np.convolve(den, [1.0, 0.0])
    sysd = control.tf(num, [1.0], ts) if den.size == 1 else control.c2d(control.tf(num, den), ts, "zoh")
    nd = int(model.delay_samples[i, j])
    return sysd * control.tf([1.0], [1.0] + [0.0] * nd, ts)


def step_reference(model: PlantModel, i: int, j: int, n: int) -> np.ndarray:
    """Unit-step response ``y(0) .. y(n-1)`` of step-response element (i, j) from the model file's definition."""
    s = np.concatenate([[0.0], model.step_response[i, j]])       # y(0) = 0, y(l) = s_l
    big_n = s.size - 1
    k = np.arange(n)
    y = np.where(k <= big_n, s[np.minimum(k, big_n)], s[big_n])
    if model.ramp[i]:
        y = y + np.where(k > big_n, (k - big_n) * (s[big_n] - s[big_n - 1]), 0.0)
    return y


def fir_reference(model: PlantModel, i: int, j: int):
    """The discrete python-control transfer function of step-response element (i, j) (module docstring)."""
    s = model.step_response[i, j]
    h = np.diff(np.concatenate([[0.0], s]))          # impulse response at lags 1 .. N
    num_inv = np.concatenate([[0.0], h])             # powers z^0 .. z^-N
    if model.ramp[i]:
        # G = sum_l h_l z^-l + h_N z^-(N+1) / (1 - z^-1) = [FIR (1 - z^-1) + h_N z^-(N+1)] / (1 - z^-1)
        num_inv = np.concatenate([np.convolve(num_inv, [1.0, -1.0]), [0.0]])
        num_inv[s.size + 1] += h[-1]
        den_inv = np.zeros(num_inv.size)
        den_inv[:2] = [1.0, -1.0]
    else:
        den_inv = np.zeros(num_inv.size)
        den_inv[0] = 1.0
    return control.tf(num_inv, den_inv, model.sample_time)


def element_reference(model: PlantModel, i: int, j: int):
    return fir_reference(model, i, j) if model.is_step_response else parametric_reference(model, i, j)


def reference_system(model: PlantModel):
    """The whole model as a MIMO python-control transfer function built from the element references."""
    nums, dens = [], []
    for i in range(model.n_outputs):
        nums.append([])
        dens.append([])
        for j in range(model.n_columns):
            ref = element_reference(model, i, j)
            nums[-1].append(np.asarray(ref.num[0][0], dtype=float))
            dens[-1].append(np.asarray(ref.den[0][0], dtype=float))
    return control.tf(nums, dens, model.sample_time)


def reference_response(model: PlantModel, columns: np.ndarray) -> np.ndarray:
    """``y(k)`` of the model to ``columns`` (n_samples, n_columns) from rest, by python-control's
    ``forced_response`` of every element reference, summed over the columns."""
    n = columns.shape[0]
    t = np.arange(n) * model.sample_time
    y = np.zeros((n, model.n_outputs))
    for i in range(model.n_outputs):
        for j in range(model.n_columns):
            ref = element_reference(model, i, j)
            y[:, i] += np.asarray(control.forced_response(ref, T=t, U=columns[:, j]).outputs).reshape(n)
    return y


def frequency_reference(model: PlantModel, omega: np.ndarray) -> np.ndarray:
    """``G(e^{j omega})`` (omega in rad/sample) of :func:`reference_system`, shape (n_freq, n_outputs, n_columns)."""
    fr = reference_system(model).frequency_response(omega / model.sample_time)
    return np.moveaxis(np.asarray(fr.magnitude) * np.exp(1j * np.asarray(fr.phase)), -1, 0)
