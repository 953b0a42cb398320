"""Plant simulator core: a MIMO plant of any element structure with the paper's disturbance and measurement noise.

The measured output is (paper, Fig. 1 and section 3.1)::

    y(k) = P(q) u(k) + P_d(q) dv(k) + v(k) + n(k),   v(k) = p v(k-1) + w(k)   (v = z/(z - p) w)

with ``w`` and ``n`` zero-mean white Gaussian noise, ``P`` the elements of the inputs and ``P_d``
those of the measured disturbances ``dv`` (the model's columns after the inputs; none for most
plants).  Every element structure (first order, lead, second lag, integrator, step response) is
simulated exactly through the state space of :func:`mpm_monitor.core.discretize.state_space`.
``y(k)`` is measured before ``u(k)`` is applied, so the plant must be strictly proper in discrete
time (no element with zero time constant and zero delay, the measured disturbances' included:
``dv(k)``, measured with ``y(k)``, acts from ``y(k+1)`` on).

A plant with more than :data:`DENSE_STATE_LIMIT` states (an industrial unit: 40 inputs and 100
outputs have some 4,400) is stepped with its state space held sparse: a state depends on a few
others only (its element's and one of an input's delay line), so a step costs ``O(n_states)``
instead of ``O(n_states^2)``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.discretize import state_space
from ..core.errors import ConfigurationError
from ..core.model import PlantModel

#: Largest number of model states stepped with dense matrices (plant and MPC).
DENSE_STATE_LIMIT = 1000


@dataclasses.dataclass(frozen=True)
class DisturbanceOptions:
    """The unmeasured output disturbance and the measurement noise (paper section 3.1).

    Attributes
    ----------
    disturbance_std : float
        Standard deviation of the white noise ``w`` driving the disturbance filter (output units).
    disturbance_pole : float
        Pole ``p`` of the first-order filter ``z / (z - p)``, in [0, 1).
    noise_std : float
        Standard deviation of the white measurement noise ``n`` (output units).
    """

    disturbance_std: float = 7.5e-3
    disturbance_pole: float = 0.95
    noise_std: float = 5.0e-3

    def __post_init__(self):
        check_disturbance_options(self)


def check_disturbance_options(opts: DisturbanceOptions) -> None:
    """Raise :class:`ConfigurationError` when an option is outside its range."""
    if not (np.isfinite(opts.disturbance_std) and opts.disturbance_std >= 0):
        raise ConfigurationError(f"disturbance_std: expected a finite number >= 0, got {opts.disturbance_std!r}")
    if not (np.isfinite(opts.noise_std) and opts.noise_std >= 0):
        raise ConfigurationError(f"noise_std: expected a finite number >= 0, got {opts.noise_std!r}")
    if not (0.0 <= opts.disturbance_pole < 1.0):
        raise ConfigurationError(f"disturbance_pole: expected a number in [0, 1), got {opts.disturbance_pole!r}")


def require_strictly_proper(model: PlantModel, what: str = "plant") -> None:
    """Refuse a model with a direct feed-through (an element whose sampled form acts on ``y(k)`` through
    ``u(k)`` or ``dv(k)``: no lag and no delay, or a lead with no delay) for closed-loop use."""
    for i in range(model.n_outputs):
        for j in range(model.n_columns):
            if model.discrete_element(i, j).strictly_proper:
                continue
            el = model.element(i, j)
            why = ("time_constant 0 and delay 0" if el["time_constant"] == 0 and "integrating" not in el
                   else "a lead and delay 0")
            raise ConfigurationError(
                f"{what}: element ({model.outputs[i]}, {model.columns[j]}) has {why}, a direct "
                f"feed-through that a sampled loop cannot close; give it a delay of at least one sample")


class PlantSimulator:
    """A MIMO plant from a model file, with disturbance and measurement noise.

    Parameters
    ----------
    model : PlantModel
        The true plant (strictly proper in discrete time), of any element structure, with or
        without measured disturbances.
    options : DisturbanceOptions
        Disturbance and noise levels.
    rng : numpy.random.Generator
        Source of the noise; the simulation is deterministic for a given generator state.

    Notes
    -----
    Call :meth:`measure` to get ``y(k)`` (giving the measured disturbances ``dv(k)`` when the plant
    has some) and then :meth:`apply` with ``u(k)`` to advance to ``k + 1``.  The components of the
    last measurement are in :attr:`last_disturbance` (``v``), :attr:`last_noise` (``n``) and
    :attr:`last_dv` (``dv``).
    """

    def __init__(self, model: PlantModel, options: DisturbanceOptions, rng: np.random.Generator):
        require_strictly_proper(model)
        self.model = model
        self.options = options
        self._rng = rng
        self._ss = state_space(model)
        self._nd = model.n_disturbances
        self._A, self._C = self._ss.A, self._ss.C
        self._Bu, self._Bd = self._ss.B_inputs, self._ss.B_disturbances
        if self._ss.n_states > DENSE_STATE_LIMIT:
            import scipy.sparse as sp

            self._A, self._Bu, self._Bd, self._C = (sp.csr_matrix(m) for m in (self._A, self._Bu, self._Bd, self._C))
        self.reset()

    def reset(self) -> None:
        """Return to rest: zero state and zero disturbance."""
        self._x = np.zeros(self._ss.n_states)
        self._v = np.zeros(self.model.n_outputs)
        self.last_disturbance = np.zeros(self.model.n_outputs)
        self.last_noise = np.zeros(self.model.n_outputs)
        self.last_dv = np.zeros(self._nd)
        self._pending = True

    @property
    def state(self) -> np.ndarray:
        """Plant state of :func:`mpm_monitor.core.discretize.state_space`, shape (n_states,)."""
        return self._x.copy()

    def measure(self, extra: np.ndarray | None = None, dv: np.ndarray | None = None) -> np.ndarray:
        """Measured output ``y(k)`` of shape (n_outputs,), drawing this sample's noise.

        Parameters
        ----------
        extra : ndarray, shape (n_outputs,), optional
            An additional output disturbance for this sample (e.g. a step), added to ``v``.
        dv : ndarray, shape (n_disturbances,)
            The measured disturbances ``dv(k)`` of this sample (required when the plant has some);
            with ``u(k)`` they act on the next samples (:meth:`apply`).
        """
        if self._nd:
            self.last_dv = self._check_dv(dv)
        ny = self.model.n_outputs
        opts = self.options
        w = self._rng.standard_normal(ny) * opts.disturbance_std
        n = self._rng.standard_normal(ny) * opts.noise_std
        self._v = opts.disturbance_pole * self._v + w
        v = self._v if extra is None else self._v + extra
        self.last_disturbance = v.copy()
        self.last_noise = n
        return self._C @ self._x + v + n

    def apply(self, u: np.ndarray) -> None:
        """Apply ``u(k)`` (shape (n_inputs,), deviation variables) and advance to ``k + 1``.

        The measured disturbances act with the values given to the last :meth:`measure`.
        """
        if self._nd:
            self._x = self._A @ self._x + self._Bu @ np.asarray(u, dtype=float) + self._Bd @ self.last_dv
            return
        self._x = self._A @ self._x + self._Bu @ np.asarray(u, dtype=float)

    def _check_dv(self, dv) -> np.ndarray:
        names = ", ".join(self.model.disturbances)
        if dv is None:
            raise ConfigurationError(f"plant: the plant has measured disturbances ({names}): give dv(k) to measure()")
        arr = np.asarray(dv, dtype=float).reshape(-1)
        if arr.shape != (self._nd,) or not np.all(np.isfinite(arr)):
            raise ConfigurationError(f"plant: dv: expected {self._nd} finite value(s) ({names}), "
                                     f"got {np.asarray(dv)!r}")
        return arr
