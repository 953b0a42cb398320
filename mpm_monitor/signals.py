"""The signals the paper's tests work on, recomputed from logged r, u, y and the model.

``yhat = Phat u`` (the model simulated from the data's start), ``d = y - yhat`` (prediction error)
and ``eps = r - d`` (controller input), paper Fig. 1 and eq. (1), (9).

The model's state at the first logged sample is unknown when the log starts mid-operation.  With
``initial_state="estimate"`` it is estimated by least squares from the first ``settling_samples``
samples of ``y - yhat_0`` (``yhat_0`` simulated from rest): the free response ``C A^k x0`` is linear
in ``x0``.  With ``"zero"`` the model starts at rest (exact for data that start at rest).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .discretize import settling_samples, simulate_state_space, state_space
from .errors import ConfigurationError
from .model import FopdtModel

INITIAL_STATE_CHOICES = ("estimate", "zero")


@dataclasses.dataclass
class LoopSignals:
    """Model output, prediction error and controller input of a log.

    Attributes
    ----------
    yhat : ndarray, shape (n_samples, n_outputs)
        Model output ``Phat u``.
    d : ndarray, shape (n_samples, n_outputs)
        Prediction error ``y - yhat``.
    eps : ndarray, shape (n_samples, n_outputs)
        Controller input ``r - d``.
    x0 : ndarray, shape (n_states,)
        Initial model state used.
    """

    yhat: np.ndarray
    d: np.ndarray
    eps: np.ndarray
    x0: np.ndarray


def free_response_matrix(ss, n: int) -> np.ndarray:
    """Observability-type matrix ``[C; C A; ...; C A^{n-1}]`` of shape (n * n_outputs, n_states)."""
    ny, nx = ss.C.shape
    out = np.zeros((n * ny, nx))
    ca = ss.C.copy()
    for k in range(n):
        out[k * ny:(k + 1) * ny] = ca
        ca = ca @ ss.A
    return out


def compute_signals(model: FopdtModel, r: np.ndarray, u: np.ndarray, y: np.ndarray,
                    initial_state: str = "estimate") -> LoopSignals:
    """Recompute ``yhat``, ``d`` and ``eps`` from logged data.

    Parameters
    ----------
    model : FopdtModel
        The controller's model ``Phat``.
    r, y : ndarray, shape (n_samples, n_outputs)
        Setpoints and measured outputs.
    u : ndarray, shape (n_samples, n_inputs)
        Plant inputs.
    initial_state : {"estimate", "zero"}
        How to start the model (see the module docstring).

    Returns
    -------
    LoopSignals
    """
    if initial_state not in INITIAL_STATE_CHOICES:
        raise ConfigurationError(f"initial_state: expected one of {', '.join(INITIAL_STATE_CHOICES)}, got {initial_state!r}")
    r, u, y = (np.asarray(a, dtype=float) for a in (r, u, y))
    ss = state_space(model)
    x0 = np.zeros(ss.n_states)
    yhat = simulate_state_space(ss, u, x0)
    if initial_state == "estimate" and ss.n_states > 0 and u.shape[0] > 1:
        n_fit = min(u.shape[0], max(settling_samples(model), 10))
        obs = free_response_matrix(ss, n_fit)
        resid = (y[:n_fit] - yhat[:n_fit]).reshape(-1)
        x0, *_ = np.linalg.lstsq(obs, resid, rcond=1e-8)
        yhat = simulate_state_space(ss, u, x0)
    d = y - yhat
    return LoopSignals(yhat=yhat, d=d, eps=r - d, x0=x0)
