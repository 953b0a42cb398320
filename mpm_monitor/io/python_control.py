"""The controller's model as python-control transfer functions, and back.

* :func:`to_transfer_function`: the model as a discrete MIMO ``control.TransferFunction``: every
  element's exact sampled form ``z^-delay num(z^-1) / den(z^-1)``
  (:meth:`~mpm_monitor.core.model.PlantModel.discrete_element`), the dead time exact as a power of
  ``z``; the system's inputs are the model's columns (the manipulated inputs, then the measured
  disturbances).
* :func:`to_continuous`: a parametric model as a continuous MIMO transfer function (without the
  dead times) and its matrix of dead times in seconds.
* :func:`from_continuous`: back from continuous element transfer functions of the forms a model
  holds (``K (lead s + 1) / ((tau s + 1)(tau2 s + 1))``, optionally divided by ``s``: at most two
  real stable poles besides one at ``s = 0``, at most one real zero away from 0) and a matrix of
  dead times, to a parametric :class:`~mpm_monitor.core.model.PlantModel`; any other form is
  refused with one line naming the element.
* :func:`step_response_model`: a discrete MIMO transfer function as a step-response model of ``N``
  coefficients (the form of DMC-type controllers); an output with an integrating element keeps
  the last slope beyond ``N`` (``ramp``).

python-control (``control``) is needed only here: the core computes with numpy and scipy alone.
"""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np

from ..core.errors import ModelFileError
from ..core.filters import lfilter
from ..core.model import PlantModel

#: Relative tolerance for a pole or zero to count as real, as 0, or as 1 (discrete integrator).
ROOT_TOLERANCE = 1e-9

SUPPORTED_FORMS = ("K (lead s + 1) / ((tau s + 1)(tau2 s + 1)), optionally divided by s (at most two real stable "
                   "lags, one integrator, one real zero away from 0)")


def _control():
    try:
        import control
    except ImportError as exc:   # pragma: no cover - control is a pinned dependency
        raise ImportError("mpm_monitor.io.python_control needs python-control: pip install control") from exc
    return control


# ------------------------------------------------------------------------------------------- to control
def _positive_powers(num: np.ndarray, den: np.ndarray, delay: int):
    """``z^-delay num(z^-1) / den(z^-1)`` as numerator and denominator in descending powers of ``z``."""
    nz = np.concatenate([np.zeros(delay), num])
    size = max(nz.size, den.size)
    return np.pad(nz, (0, size - nz.size)), np.pad(np.asarray(den, float), (0, size - den.size))


def to_transfer_function(model: PlantModel):
    """The model as a discrete MIMO ``control.TransferFunction`` (see the module docstring).

    Parameters
    ----------
    model : PlantModel
        Any structure, with or without measured disturbances.

    Returns
    -------
    control.TransferFunction
        ``n_outputs x n_columns``, sampling time ``model.sample_time``; input labels the model's
        columns (inputs, then disturbances), output labels its outputs.
    """
    control = _control()
    nums, dens = [], []
    for i in range(model.n_outputs):
        row_n, row_d = [], []
        for j in range(model.n_columns):
            el = model.discrete_element(i, j)
            if el.is_zero:
                n, d = np.zeros(1), np.ones(1)
            else:
                n, d = _positive_powers(el.num, el.den, el.delay)
            row_n.append(n)
            row_d.append(d)
        nums.append(row_n)
        dens.append(row_d)
    return control.tf(nums, dens, model.sample_time, inputs=list(model.columns), outputs=list(model.outputs))


def to_continuous(model: PlantModel):
    """A parametric model as continuous element transfer functions and dead times.

    Parameters
    ----------
    model : PlantModel
        A parametric model (not a step-response one).

    Returns
    -------
    tf : control.TransferFunction
        Continuous, ``n_outputs x n_columns``: ``K (lead s + 1) / ((tau s + 1)(tau2 s + 1))``, divided
        by ``s`` where integrating (0 where the model has no such effect); labels as
        :func:`to_transfer_function`.
    delay : ndarray, shape (n_outputs, n_columns)
        Dead times in seconds.

    Raises
    ------
    ModelFileError
        For a step-response model (it has no continuous form).
    """
    control = _control()
    if model.is_step_response:
        raise ModelFileError("model: a step-response model has no continuous form (use to_transfer_function)")
    nums, dens = [], []
    for i in range(model.n_outputs):
        row_n, row_d = [], []
        for j in range(model.n_columns):
            k = float(model.gain[i, j])
            if k == 0.0:
                row_n.append(np.zeros(1))
                row_d.append(np.ones(1))
                continue
            lead = float(model.lead[i, j])
            num = k * np.array([lead, 1.0]) if lead else np.array([k])
            den = np.ones(1)
            for tau in (model.time_constant[i, j], model.time_constant2[i, j]):
                if tau > 0:
                    den = np.convolve(den, [float(tau), 1.0])
            if model.integrating[i, j]:
                den = np.convolve(den, [1.0, 0.0])
            row_n.append(num)
            row_d.append(den)
        nums.append(row_n)
        dens.append(row_d)
    tf = control.tf(nums, dens, inputs=list(model.columns), outputs=list(model.outputs))
    return tf, np.array(model.delay)


# ------------------------------------------------------------------------------------------- from control
def _labels(sys, n_disturbances: int):
    """(inputs, disturbances, outputs) names of a system's labels."""
    cols = list(sys.input_labels)
    if not 0 <= int(n_disturbances) <= len(cols):
        raise ModelFileError(f"transfer function: disturbances: expected 0 .. {len(cols)} (its inputs), "
                             f"got {n_disturbances!r}")
    nu = len(cols) - int(n_disturbances)
    return tuple(cols[:nu]), tuple(cols[nu:]), tuple(sys.output_labels)


def _trim(p) -> np.ndarray:
    p = np.atleast_1d(np.asarray(p, dtype=float))
    nz = np.flatnonzero(p != 0)
    return p[nz[0]:] if nz.size else np.zeros(1)


def _describe(num, den) -> str:
    return f"num {np.round(num, 6).tolist()} / den {np.round(den, 6).tolist()}"


def _continuous_element(num, den, where: str) -> dict:
    """The parametric keys of one continuous element (or a refusal naming it and the form)."""
    num, den = _trim(num), _trim(den)
    if not np.any(num != 0):
        return {"gain": 0.0}

    def refuse(why: str):
        raise ModelFileError(f"transfer function: element {where}: {_describe(num, den)}: {why}; supported: "
                             f"{SUPPORTED_FORMS}")

    if not np.all(np.isfinite(num)) or not np.all(np.isfinite(den)):
        refuse("non-finite coefficients")
    if num.size > den.size:
        refuse("more zeros than poles (not proper)")
    num, den = num / den[0], den / den[0]
    poles = np.roots(den) if den.size > 1 else np.zeros(0)
    scale = max(1.0, float(np.max(np.abs(poles), initial=0.0)))
    if np.any(np.abs(np.imag(poles)) > ROOT_TOLERANCE * scale):
        refuse("complex poles (an oscillating element)")
    poles = np.real(poles)
    at_zero = np.abs(poles) <= ROOT_TOLERANCE * scale
    lags = poles[~at_zero]
    if at_zero.sum() > 1:
        refuse("more than one pole at s = 0")
    if np.any(lags > 0):
        refuse("a pole in the right half-plane (an unstable element)")
    if lags.size > 2:
        refuse("more than two lags")
    if num.size > 2:
        refuse("more than one zero")
    integrating = bool(at_zero.any())
    # den = s^i (tau s + 1)(tau2 s + 1) / (tau tau2): the constant of the lag part is den's last
    # coefficient (before the s factor).
    lag_den = den[:-1] if integrating else den
    lag_const = float(lag_den[-1])
    if num.size == 2:
        if num[1] == 0 or abs(num[1]) <= ROOT_TOLERANCE * abs(num[0]):
            refuse("a zero at s = 0 (a derivative)")
        lead = float(num[0] / num[1])
        const = float(num[1])
    else:
        lead, const = 0.0, float(num[0])
    taus = sorted((float(-1.0 / p) for p in lags), reverse=True)
    out = {"gain": const / lag_const, "lead": lead, "integrating": integrating,
           "time_constant": taus[0] if taus else 0.0, "time_constant2": taus[1] if len(taus) > 1 else 0.0}
    return out


def from_continuous(tf, delay, sample_time: float, disturbances: int = 0, name: str = "") -> PlantModel:
    """A parametric model from continuous element transfer functions and their dead times.

    Parameters
    ----------
    tf : control.TransferFunction
        Continuous (``dt`` 0), ``n_outputs x n_columns``; input labels the columns (the inputs,
        then the ``disturbances`` measured disturbances), output labels the outputs.  Every element
        is ``K (lead s + 1) / ((tau s + 1)(tau2 s + 1))``, optionally divided by ``s``, or 0.
    delay : array_like, shape (n_outputs, n_columns)
        Dead times in seconds, multiples of ``sample_time``.
    sample_time : float
        Seconds per sample of the model.
    disturbances : int
        How many of the last system inputs are measured disturbances (default none).
    name : str

    Returns
    -------
    PlantModel

    Raises
    ------
    ModelFileError
        One line naming the element and its form when it is not one of those above (complex or
        unstable poles, more than two lags or one integrator, more than one zero, a zero at 0, an
        improper element), or a discrete system, or a delay matrix of the wrong shape.
    """
    if not tf.isctime(strict=True):
        raise ModelFileError(f"transfer function: expected a continuous system (dt 0), got dt {tf.dt!r}")
    inputs, dvs, outputs = _labels(tf, disturbances)
    ny, nc = tf.noutputs, tf.ninputs
    delay = np.asarray(delay, dtype=float)
    if delay.shape != (ny, nc):
        raise ModelFileError(f"transfer function: delay: expected {ny} rows x {nc} columns (seconds), "
                             f"got shape {delay.shape}")
    keys = ("gain", "time_constant", "time_constant2", "lead")
    arrays = {k: np.zeros((ny, nc)) for k in keys}
    integrating = np.zeros((ny, nc), dtype=bool)
    cols = inputs + dvs
    for i in range(ny):
        for j in range(nc):
            el = _continuous_element(tf.num[i][j], tf.den[i][j], f"({outputs[i]}, {cols[j]})")
            for k in keys:
                arrays[k][i, j] = el.get(k, 0.0)
            integrating[i, j] = el.get("integrating", False)
    return PlantModel(sample_time=sample_time, inputs=inputs, outputs=outputs, delay=delay, disturbances=dvs,
                      integrating=integrating, name=name, **arrays)


def _discrete_element(num, den, n: int, where: str):
    """(step response s_1 .. s_n, integrating) of a discrete element in descending powers of z."""
    num, den = _trim(num), _trim(den)
    if not np.any(num != 0):
        return np.zeros(n), False

    def refuse(why: str):
        raise ModelFileError(f"transfer function: element {where}: {_describe(num, den)}: {why}")

    if num.size > den.size:
        refuse("more zeros than poles (not causal)")
    num, den = num / den[0], den / den[0]
    poles = np.roots(den) if den.size > 1 else np.zeros(0)
    near_one = np.abs(poles - 1.0) <= 1e-6
    if near_one.sum() > 1:
        refuse("more than one pole at z = 1 (a step-response model holds at most a ramp)")
    if np.any(np.abs(poles[~near_one]) >= 1.0 - ROOT_TOLERANCE):
        refuse("a pole on or outside the unit circle (other than one integrator at z = 1)")
    # In powers of z^-1: num and den over z^(len(den) - 1).
    num_inv = np.concatenate([np.zeros(den.size - num.size), num])
    pulse = np.zeros(n + 1)
    pulse[0] = 1.0
    step = np.cumsum(lfilter(num_inv, den, pulse))
    if step[0] != 0.0 and abs(step[0]) > ROOT_TOLERANCE * max(1.0, float(np.max(np.abs(step)))):
        refuse("a direct feed-through (the output moves at the sample of the step), which a step-response "
               "model cannot hold")
    return step[1:], bool(near_one.any())


def step_response_model(tf, length: int, disturbances: int = 0, ramp: Optional[Sequence[bool]] = None,
                        name: str = "") -> PlantModel:
    """A step-response model of ``length`` coefficients from a discrete MIMO transfer function.

    Parameters
    ----------
    tf : control.TransferFunction
        Discrete, with a sampling time in seconds (``dt > 0``), ``n_outputs x n_columns``, labels as
        in :func:`from_continuous`; every element causal, without direct feed-through, stable but for
        at most one integrator (a pole at ``z = 1``).
    length : int
        ``N``, coefficients per element (>= 2).
    disturbances : int
        How many of the last system inputs are measured disturbances.
    ramp : sequence of bool, optional
        Per output: continue with the last slope beyond ``N``.  Default: the outputs with an
        integrating element.
    name : str

    Returns
    -------
    PlantModel
        ``step_response[i, j, k]`` the output change ``k + 1`` samples after a unit step of column
        ``j`` at sample 0.

    Raises
    ------
    ModelFileError
        One line naming the element that cannot be a step-response element, a continuous system,
        a system without sampling time, or a bad ``length``.
    """
    dt = tf.dt
    if isinstance(dt, bool) or dt is None or not dt > 0:
        raise ModelFileError(f"transfer function: expected a discrete system with a sampling time in seconds, "
                             f"got dt {dt!r}")
    if isinstance(length, bool) or int(length) != length or length < 2:
        raise ModelFileError(f"step_response_model: length: expected an integer >= 2 samples, got {length!r}")
    n = int(length)
    inputs, dvs, outputs = _labels(tf, disturbances)
    ny, nc = tf.noutputs, tf.ninputs
    cols = inputs + dvs
    coefs = np.zeros((ny, nc, n))
    integrating = np.zeros((ny, nc), dtype=bool)
    for i in range(ny):
        for j in range(nc):
            coefs[i, j], integrating[i, j] = _discrete_element(tf.num[i][j], tf.den[i][j], n,
                                                               f"({outputs[i]}, {cols[j]})")
    if ramp is None:
        ramp = tuple(bool(integrating[i].any()) for i in range(ny))
    return PlantModel.from_step_response(float(dt), inputs, outputs, coefs, ramp=ramp, disturbances=dvs, name=name)
