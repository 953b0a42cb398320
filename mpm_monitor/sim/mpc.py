"""Model predictive controller in internal-model (IMC) structure, with measured-disturbance feedforward.

The controller keeps its own model output ``yhat = Phat u + Phat_d dv`` (``Phat_d`` the elements of
the measured disturbances ``dv``, when its model has some), forms the prediction error
``d = y - yhat`` and the controller input ``eps = r - d`` (paper, Fig. 1), and at every sample
minimises over the moves ``du(k), ..., du(k + Hc - 1)``::

    J = sum_{i=1}^{Hp} ||eps(k) - yhat(k+i)||_Q^2 + sum_{i=0}^{Hp-1} ||u(k+i) - u_nom||_R^2
        + sum_{i=0}^{Hc-1} ||du(k+i)||_S^2

with ``d`` assumed constant over the horizon (the DMC disturbance model; Maciejowski, *Predictive
Control with Constraints*, 2002, section 2.3) and ``u`` held after ``Hc`` moves.  The measured
disturbances are held at their current value ``dv(k)`` over the horizon: their predicted response
``Gamma_d dv(k)`` (block ``i``: the disturbances' step response ``S^d_{i-1}``) enters the predicted
outputs like the free response, so the moves counteract a measured disturbance before it shows in
``y`` (feedforward); only the inputs are moved.  Without bounds the optimum is the closed form
``dU = H^{-1} (G' Q e0 - M' R g0)``; with bounds on ``u`` and ``du`` the QP is solved exactly by the
dual active-set method of :mod:`mpm_monitor.sim.qp`, started from the previous sample's held bounds
(numpy and scipy only: no QP package is needed).

Every element structure of the model is controlled through its exact state space
(:func:`mpm_monitor.core.discretize.state_space`), integrating outputs included: their predicted
free response keeps the slope of the internal model, and setpoints are tracked without offset.
A constant load on an integrating output that the model does not predict (unmeasured, or measured
with a wrong gain) is a ramp in ``d``, which the constant-``d`` assumption leaves as an offset.

Two set-ups compute the same control law.  A model with at most :data:`DENSE_STATE_LIMIT` states
(every plant of the paper and of the benchmarks up to 20x20) uses the dense matrices of its state
space.  A larger one (an industrial controller: 40 inputs and 100 outputs have some 4,400 states)
keeps the state space sparse, builds ``H`` from the step-response coefficients (``G`` is block
Toeplitz) instead of from ``G``, and never forms the ``Hp n_outputs x n_states`` free-response
matrix: without bounds only the first move's gains are kept, with bounds the free response is run
forward at each sample.  The two agree to rounding (test_plant_mpc).
"""

from __future__ import annotations

import dataclasses
from typing import Optional, Sequence, Union

import numpy as np

from ..core.discretize import state_space
from ..core.errors import ConfigurationError
from ..core.logged_data import MAX_ANALYSIS_SCALE
from ..core.model import PlantModel
from .plant import DENSE_STATE_LIMIT, require_strictly_proper

Weight = Union[float, Sequence[float]]


@dataclasses.dataclass(frozen=True)
class MpcOptions:
    """Tuning of the MPC (defaults: the common set-up of the paper's cases).

    Attributes
    ----------
    prediction_horizon : int
        ``Hp``, samples (>= 1).
    control_horizon : int
        ``Hc``, samples, 1 <= Hc <= Hp.
    output_weight, input_weight, input_rate_weight : float or sequence of float
        Diagonal weights ``Q`` (per output), ``R`` (per input, on ``u - u_nom``) and ``S`` (per
        input, on ``du``); >= 0.  A scalar applies to every channel.
    input_nominal : sequence of float or None
        ``u_nom`` in deviation variables (default zeros).
    u_min, u_max : float, sequence of float or None
        Bounds on the plant input (deviation variables); None = unbounded.
    du_max : float, sequence of float or None
        Bound on ``|du|`` per sample; None = unbounded.
    qp_tolerance : float
        How far a bound may be exceeded, relative to ``1 + |value|`` (no unit), before the QP's
        active-set solver holds it: its feasibility tolerance (the QP is otherwise solved exactly).
    """

    prediction_horizon: int = 100
    control_horizon: int = 30
    output_weight: Weight = 1.0
    input_weight: Weight = 1.0
    input_rate_weight: Weight = 0.1
    input_nominal: Optional[Sequence[float]] = None
    u_min: Optional[Weight] = None
    u_max: Optional[Weight] = None
    du_max: Optional[Weight] = None
    qp_tolerance: float = 1e-9

    def __post_init__(self):
        hp, hc = self.prediction_horizon, self.control_horizon
        if int(hp) != hp or hp < 1:
            raise ConfigurationError(f"prediction_horizon: expected an integer >= 1 (samples), got {hp!r}")
        if int(hc) != hc or not 1 <= hc <= hp:
            raise ConfigurationError(
                f"control_horizon: expected an integer in [1, prediction_horizon={hp}] (samples), got {hc!r}")
        if not (self.qp_tolerance > 0):
            raise ConfigurationError(f"qp_tolerance: expected a positive number, got {self.qp_tolerance!r}")

    @property
    def constrained(self) -> bool:
        """True when any bound is given."""
        return any(b is not None for b in (self.u_min, self.u_max, self.du_max))


def _weights_text(options: MpcOptions) -> str:
    """``output_weight [1], input_weight [1e+308], input_rate_weight [0.1]``: the weights of ``options`` as a refusal
    names them."""
    return ", ".join(f"{name} [{', '.join(f'{float(v):g}' for v in np.ravel(getattr(options, name)))}]"
                     for name in ("output_weight", "input_weight", "input_rate_weight"))


def _diag(value, n: int, name: str, allow_none=False, fill=None) -> np.ndarray:
    if value is None:
        if allow_none:
            return np.full(n, fill, dtype=float)
        raise ConfigurationError(f"{name}: expected a number or a list of {n} numbers")
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n, float(arr))
    if arr.shape != (n,):
        raise ConfigurationError(f"{name}: expected a number or a list of {n} numbers, got shape {arr.shape}")
    if np.any(np.isnan(arr)):
        raise ConfigurationError(f"{name}: expected numbers, got NaN")
    return arr


def _check_input_scale(model: PlantModel, u_nom: np.ndarray, u_min: np.ndarray, u_max: np.ndarray) -> None:
    """Refuse an input nominal or bound the loop's log could not be analysed at: beyond
    :data:`~mpm_monitor.core.logged_data.MAX_ANALYSIS_SCALE` in magnitude (1e40; an input held there makes
    every output overflow, and a published ``u`` beyond it is refused by every reader), a nominal that is not
    finite, or a bound that excludes every input (``u_min`` of ``+inf``, ``u_max`` of ``-inf``).  Unset bounds
    are ``-inf`` and ``+inf``: none.  Before stop 93 ``u_min: [1e308]`` was taken, and the loop ran to
    "diverged"."""
    for name, v, none in (("input_nominal", u_nom, None), ("u_min", u_min, -np.inf), ("u_max", u_max, np.inf)):
        bad = ~(np.abs(v) <= MAX_ANALYSIS_SCALE)
        if none is not None:
            bad &= v != none
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            what = "a nominal" if none is None else f"a bound, or {none:g} for none"
            raise ConfigurationError(
                f"{name}: {v[k]:g} for input {model.inputs[k]!r} (expected {what}, within {MAX_ANALYSIS_SCALE:g} in "
                f"magnitude in the input's units: the loop cannot be run or analysed beyond it)")


class InternalModelMpc:
    """Unconstrained or bounded MPC in internal-model structure.

    Parameters
    ----------
    model : PlantModel
        The controller's plant model ``Phat`` (strictly proper in discrete time).
    options : MpcOptions
        Horizons, weights and bounds.
    structured : bool, optional
        The set-up for large models (see the module docstring); default: when the model has more
        than :data:`DENSE_STATE_LIMIT` states.

    Notes
    -----
    Call :meth:`step` once per sample with the setpoint ``r(k)``, the measurement ``y(k)`` and, when
    the model has measured disturbances, their values ``dv(k)``; it returns the plant input ``u(k)``
    and advances the internal model with it (and ``dv(k)``).  The signals of the last step are in
    :attr:`yhat`, :attr:`prediction_error` and :attr:`controller_input`.
    """

    def __init__(self, model: PlantModel, options: MpcOptions = MpcOptions(), structured: Optional[bool] = None):
        require_strictly_proper(model, what="controller model")
        self.model = model
        self.options = options
        ny, nu = model.n_outputs, model.n_inputs
        self._ss = state_space(model)
        self._nd = model.n_disturbances
        self.q = _diag(options.output_weight, ny, "output_weight")
        self.r = _diag(options.input_weight, nu, "input_weight")
        self.s = _diag(options.input_rate_weight, nu, "input_rate_weight")
        for name, w in (("output_weight", self.q), ("input_weight", self.r), ("input_rate_weight", self.s)):
            if np.any(w < 0) or not np.all(np.isfinite(w)):
                raise ConfigurationError(f"{name}: expected finite numbers >= 0")
        self.u_nom = _diag(options.input_nominal, nu, "input_nominal", allow_none=True, fill=0.0)
        self.u_min = _diag(options.u_min, nu, "u_min", allow_none=True, fill=-np.inf)
        self.u_max = _diag(options.u_max, nu, "u_max", allow_none=True, fill=np.inf)
        self.du_max = _diag(options.du_max, nu, "du_max", allow_none=True, fill=np.inf)
        _check_input_scale(model, self.u_nom, self.u_min, self.u_max)
        if np.any(self.u_min > self.u_max):
            raise ConfigurationError("u_min, u_max: expected u_min <= u_max for every input")
        if np.any(self.du_max <= 0):
            raise ConfigurationError("du_max: expected positive numbers")
        self.structured = self._ss.n_states > DENSE_STATE_LIMIT if structured is None else bool(structured)
        with np.errstate(all="ignore"):
            try:
                if self.structured:
                    self._build_structured()
                else:
                    self._A, self._C = self._ss.A, self._ss.C
                    self._Bu, self._Bd = self._ss.B_inputs, self._ss.B_disturbances
                    self._build()
            except np.linalg.LinAlgError:       # weights far apart in scale (input_weight: [1e308])
                raise ConfigurationError(f"MPC weights {_weights_text(options)} give a control problem that cannot be "
                                         f"solved (expected weights of a moderate scale)") from None
            # The moves of a unit controller input, state, previous input (and dv) use every gain: one that
            # overflowed shows here (output_weight: [1e308] gave NaN inputs at the first sample).
            moves = self.unconstrained_moves(np.ones(ny), np.ones(self._ss.n_states), np.ones(nu),
                                             np.ones(self._nd) if self._nd else None)
        if not np.all(np.isfinite(moves)):
            raise ConfigurationError(f"MPC weights {_weights_text(options)} overflow floating point (expected "
                                     f"weights of a moderate scale)")
        self._qp = None
        self.reset()

    # ------------------------------------------------------------------ set-up
    def _build(self) -> None:
        ss, opts = self._ss, self.options
        ny, nu, nx = self.model.n_outputs, self.model.n_inputs, ss.n_states
        hp, hc = opts.prediction_horizon, opts.control_horizon
        nd = self._nd
        # Step-response coefficients S_n = sum_{m<=n} C A^m B, n = 0..Hp-1, and Phi_i = C A^i; those
        # of the measured disturbances S^d_n (from their feed-through D_d, zero for a closed loop).
        step = np.zeros((hp, ny, nu))
        step_d = np.zeros((hp, ny, nd))
        phi = np.zeros((hp * ny, nx))
        ca = ss.C.copy()  # C A^m
        acc = np.zeros((ny, nu))
        acc_d = np.array(ss.D_disturbances, dtype=float)
        b_u, b_d = ss.B_inputs, ss.B_disturbances
        for m in range(hp):
            acc = acc + ca @ b_u
            step[m] = acc
            if nd:
                acc_d = acc_d + ca @ b_d
                step_d[m] = acc_d
            ca = ca @ ss.A
            phi[m * ny:(m + 1) * ny] = ca  # row block i = m + 1: C A^{m+1}
        # G = Gamma M: block (i, t) = S_{i-1-t} for i-1 >= t (i = 1..Hp, t = 0..Hc-1).
        G = np.zeros((hp * ny, hc * nu))
        for i in range(1, hp + 1):
            for t in range(min(i, hc)):
                G[(i - 1) * ny:i * ny, t * nu:(t + 1) * nu] = step[i - 1 - t]
        gamma_e = step.reshape(hp * ny, nu)  # Gamma E: block i = S_{i-1}
        Qb = np.tile(self.q, hp)
        # M' Rbar M: block (t, t') = (Hp - max(t, t')) R; M' Rbar E: block t = (Hp - t) R.
        tt = np.arange(hc)
        cnt = hp - np.maximum.outer(tt, tt)
        MRM = np.kron(cnt, np.diag(self.r))
        MRE = np.kron((hp - tt)[:, None], np.diag(self.r))
        H = G.T @ (Qb[:, None] * G) + MRM + np.diag(np.tile(self.s, hc))
        H = 0.5 * (H + H.T)
        GQ = G.T * Qb  # (Hc nu, Hp ny)
        try:
            chol = np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            raise ConfigurationError(
                "MPC weights give a singular problem: use a positive input_rate_weight or input_weight") from None

        def solve(rhs):
            return np.linalg.solve(chol.T, np.linalg.solve(chol, rhs))

        ones = np.tile(np.eye(ny), (hp, 1))
        self._K_eps = solve(GQ @ ones)                  # (Hc nu, ny)
        self._K_x = -solve(GQ @ phi)                    # (Hc nu, nx)
        self._K_u = -solve(GQ @ gamma_e + MRE)          # (Hc nu, nu)
        self._K_nom = solve(MRE)                        # (Hc nu, nu)
        # Gamma_d: block i = S^d_{i-1}, the predicted response to dv(k) held over the horizon.
        self._K_dv = -solve(GQ @ step_d.reshape(hp * ny, nd)) if nd else None   # (Hc nu, nd)
        self._H = H
        # Cumulative-sum matrix for u(k+t) = u_prev + sum_{t'<=t} du(k+t'), t < Hc.
        self._Mc = np.kron(np.tril(np.ones((hc, hc))), np.eye(nu))
        self._nu, self._hc = nu, hc

    def _build_structured(self) -> None:
        """The set-up of :meth:`_build` for a large model (see the module docstring).

        With ``S_n`` the step-response coefficients, ``G' Q G`` has the blocks
        ``(t, t') = sum_{n=0}^{Hp-1-max(t,t')} S_{n+|t-t'|}' Q S_n`` (transposed for ``t > t'``), and
        ``G' Q`` the blocks ``(t, i) = S_{i-1-t}' Q``; the gains are built from these blocks.
        """
        import scipy.sparse as sp

        ss, opts = self._ss, self.options
        ny, nu = self.model.n_outputs, self.model.n_inputs
        hp, hc = opts.prediction_horizon, opts.control_horizon
        nd = self._nd
        self._A, self._Bu, self._Bd, self._C = (sp.csr_matrix(m) for m in (ss.A, ss.B_inputs, ss.B_disturbances, ss.C))
        step = np.zeros((hp, ny, nu))
        step_d = np.zeros((hp, ny, nd))
        ca = self._C
        acc = np.zeros((ny, nu))
        acc_d = np.array(ss.D_disturbances, dtype=float)
        for m in range(hp):
            acc = acc + ca @ self._Bu
            step[m] = acc
            if nd:
                acc_d = acc_d + ca @ self._Bd
                step_d[m] = acc_d
            ca = ca @ self._A
        q = self.q
        qs = q[None, :, None] * step                        # Q S_n, (hp, ny, nu)
        H = np.zeros((hc * nu, hc * nu))
        for d in range(hc):
            # cum[N] = sum_{n<=N} S_{n+d}' Q S_n, N = 0 .. hp-1-d
            cum = np.cumsum(np.matmul(np.swapaxes(step[d:], 1, 2), qs[:hp - d]), axis=0)
            for t in range(hc - d):
                block = cum[hp - 1 - (t + d)]               # t' = t + d
                H[t * nu:(t + 1) * nu, (t + d) * nu:(t + d + 1) * nu] = block
                if d:
                    H[(t + d) * nu:(t + d + 1) * nu, t * nu:(t + 1) * nu] = block.T
        tt = np.arange(hc)
        cnt = hp - np.maximum.outer(tt, tt)
        MRM = np.kron(cnt, np.diag(self.r))
        MRE = np.kron((hp - tt)[:, None], np.diag(self.r))
        H = H + MRM + np.diag(np.tile(self.s, hc))
        H = 0.5 * (H + H.T)
        try:
            chol = np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            raise ConfigurationError(
                "MPC weights give a singular problem: use a positive input_rate_weight or input_weight") from None
        self._chol = chol
        # G' Q times the stacked identities (block t: sum_{n<=Hp-1-t} S_n' Q) and times Gamma E
        # (block t: sum_{n<=Hp-1-t} S_n' Q S_{n+t}).
        sq_cum = np.cumsum(np.swapaxes(qs, 1, 2), axis=0)                                # (hp, nu, ny)
        gq_ones = np.vstack([sq_cum[hp - 1 - t] for t in range(hc)])
        gq_gamma = np.vstack([np.tensordot(qs[:hp - t], step[t:], axes=([0, 1], [0, 1])) for t in range(hc)])
        self._K_eps = self._solve_h(gq_ones)
        self._K_u = -self._solve_h(gq_gamma + MRE)
        self._K_nom = self._solve_h(MRE)
        # G' Q Gamma_d (block t: sum_{n<=Hp-1-t} S_n' Q S^d_{n+t}): the measured disturbances' feedforward.
        self._K_dv = (-self._solve_h(np.vstack([np.tensordot(qs[:hp - t], step_d[t:], axes=([0, 1], [0, 1]))
                                                for t in range(hc)])) if nd else None)
        self._step, self._qs = step, qs
        # First move's gain on the state: -(H^-1 G' Q)[:nu] Phi, Phi's block i = C A^i (i = 1..Hp).
        hinv1 = self._solve_h(np.eye(hc * nu, nu)).T.reshape(nu, hc, nu)     # (H^-1)[:nu] (H symmetric)
        w1 = np.zeros((nu, hp, ny))                         # (H^-1 G' Q)[:nu], block i-1 for i = 1..Hp
        for t in range(hc):
            w1[:, t:] += np.matmul(qs[:hp - t], hinv1[:, t].T).transpose(2, 0, 1)
        kx1 = np.zeros((nu, ss.n_states))
        ca = self._C
        for i in range(hp):
            ca = ca @ self._A
            kx1 -= (ca.T @ w1[:, i].T).T
        self._K_x1 = kx1
        self._K_x = None
        self._H = H
        self._Mc = np.kron(np.tril(np.ones((hc, hc))), np.eye(nu))
        self._nu, self._hc = nu, hc

    def _solve_h(self, rhs):
        """``H^-1 rhs`` (structured set-up), from the Cholesky factor."""
        import scipy.linalg as sla

        return sla.cho_solve((self._chol, True), rhs, check_finite=False)

    def _free_moves(self, x: np.ndarray) -> np.ndarray:
        """``K_x x``: the moves' response to the state, shape (Hc * n_inputs,)."""
        if self._K_x is not None:
            return self._K_x @ x
        hp, hc = self.options.prediction_horizon, self._hc
        free = np.empty((hp, self.model.n_outputs))         # C A^i x, i = 1..Hp
        z = x
        for i in range(hp):
            z = self._A @ z
            free[i] = self._C @ z
        # G' Q free: block t = sum_{n <= Hp-1-t} S_n' Q free_{n+t}
        gq = np.concatenate([np.einsum("nya,ny->a", self._qs[:hp - t], free[t:]) for t in range(hc)])
        return -self._solve_h(gq)

    def _first_move_x(self, x: np.ndarray) -> np.ndarray:
        """The first move's response to the state, shape (n_inputs,)."""
        if self._K_x is not None:
            return self._K_x[:self._nu] @ x
        return self._K_x1 @ x

    def reset(self, u0: Optional[np.ndarray] = None) -> None:
        """Reset the internal model to rest and the previous move to ``u0`` (default ``u_nom``)."""
        self._x = np.zeros(self._ss.n_states)
        self._u_prev = self.u_nom.copy() if u0 is None else np.asarray(u0, dtype=float).copy()
        self._last_du = None
        self._last_active = None
        ny = self.model.n_outputs
        self.yhat = np.zeros(ny)
        self.prediction_error = np.zeros(ny)
        self.controller_input = np.zeros(ny)
        self.qp_solves = 0
        self.qp_fallbacks = 0

    # ------------------------------------------------------------------ control law
    def unconstrained_moves(self, eps: np.ndarray, x: np.ndarray, u_prev: np.ndarray,
                            dv: Optional[np.ndarray] = None) -> np.ndarray:
        """Closed-form optimal moves ``dU`` of shape (Hc * n_inputs,) without bounds.

        ``dv`` (n_disturbances,): the measured disturbances, held over the horizon (required when
        the model has some).
        """
        du = self._K_eps @ eps + self._free_moves(x) + self._K_u @ u_prev + self._K_nom @ self.u_nom
        if self._nd:
            du = du + self._K_dv @ self._check_dv(dv)
        return du

    def solve_qp(self, eps: np.ndarray, x: np.ndarray, u_prev: np.ndarray,
                 dv: Optional[np.ndarray] = None) -> np.ndarray:
        """Optimal moves ``dU`` of shape (Hc * n_inputs,) with the bounds (``dv`` as
        :meth:`unconstrained_moves`).

        Solved exactly by the dual active-set method of :mod:`mpm_monitor.sim.qp`, its working set
        guessed from the bounds held at the previous sample, shifted by one move; should the guessed
        start reach the method's iteration limit, it starts again from the unconstrained minimum.
        When the bounds cannot all be met (an input that starts outside its range further than
        ``du_max`` can bring it back over the horizon), or the limit is reached from that start too,
        the unconstrained moves are returned, :meth:`step` clips them, and :attr:`qp_fallbacks`
        counts it.
        """
        from .qp import ActiveSetQp

        q, lo, hi, du_unc = self.qp_problem(eps, x, u_prev, dv)
        nu, hc = self._nu, self._hc
        if self._qp is None:
            self._qp = ActiveSetQp(self._H, self.qp_rows)
        self.qp_solves += 1
        guess = upper = None
        if self._last_active is not None:
            rows, upper = self._last_active
            move = rows % (hc * nu) // nu        # rows: u(k+t) then du(k+t), t = 0..Hc-1, input fastest
            keep = move >= 1
            guess, upper = rows[keep] - nu, upper[keep]
        tol = self.options.qp_tolerance
        sol = self._qp.solve(q, lo, hi, guess, upper, tolerance=tol)
        if sol is None and guess is not None and self._qp.last_failure == "iteration_limit":
            sol = self._qp.solve(q, lo, hi, tolerance=tol)
        if sol is not None:
            self._last_active = (sol.active, sol.upper)
            return sol.x
        self._last_active = None
        self.qp_fallbacks += 1
        return du_unc

    def qp_problem(self, eps: np.ndarray, x: np.ndarray, u_prev: np.ndarray, dv: Optional[np.ndarray] = None):
        """The bounded QP of one sample (arguments as :meth:`unconstrained_moves`): minimise
        ``1/2 dU' H dU + q' dU`` subject to ``lo <= R dU <= hi``, ``R`` the rows :attr:`qp_rows`.

        Returns
        -------
        q : ndarray, shape (Hc * n_inputs,)
            The linear term, ``-H dU_unc`` (the cost up to a constant).
        lo, hi : ndarray, shape (2 Hc * n_inputs,)
            The bounds of the input path's change from ``u_prev`` (``u_min - u_prev``, ``u_max - u_prev``),
            then of the moves (``-du_max``, ``du_max``); infinite where there is none.
        du_unc : ndarray, shape (Hc * n_inputs,)
            The unconstrained moves ``dU_unc``.
        """
        du_unc = self.unconstrained_moves(eps, x, u_prev, dv)
        hc = self._hc
        lo = np.concatenate([np.tile(self.u_min, hc) - np.tile(u_prev, hc), -np.tile(self.du_max, hc)])
        hi = np.concatenate([np.tile(self.u_max, hc) - np.tile(u_prev, hc), np.tile(self.du_max, hc)])
        return -self._H @ du_unc, lo, hi, du_unc

    @property
    def qp_rows(self) -> np.ndarray:
        """The QP's constraint rows ``R``, shape (2 Hc * n_inputs, Hc * n_inputs): the input path's change
        ``u(k+t) - u_prev`` (cumulative moves), then the moves ``du(k+t)``; t = 0..Hc-1, input fastest."""
        return np.vstack([self._Mc, np.eye(self._nu * self._hc)])

    def _check_dv(self, dv) -> np.ndarray:
        if dv is None:
            raise ConfigurationError(f"controller model: it has measured disturbances "
                                     f"({', '.join(self.model.disturbances)}): give dv(k)")
        arr = np.asarray(dv, dtype=float).reshape(-1)
        if arr.shape != (self._nd,) or not np.all(np.isfinite(arr)):
            raise ConfigurationError(f"controller model: dv: expected {self._nd} finite value(s) "
                                     f"({', '.join(self.model.disturbances)}), got {np.asarray(dv)!r}")
        return arr

    def step(self, r: np.ndarray, y: np.ndarray, dither: Optional[np.ndarray] = None,
             dv: Optional[np.ndarray] = None) -> np.ndarray:
        """One control step.

        Parameters
        ----------
        r : ndarray, shape (n_outputs,)
            Setpoint ``r(k)``.
        y : ndarray, shape (n_outputs,)
            Measured output ``y(k)``.
        dither : ndarray, shape (n_inputs,), optional
            Additive excitation on the plant input (the paper's second experiment); the internal
            model is driven by the total input so that ``yhat = Phat u`` holds for the applied ``u``.
        dv : ndarray, shape (n_disturbances,)
            The measured disturbances ``dv(k)``, measured with ``y(k)`` (required when the model has
            some): they drive the internal model and the feedforward.

        Returns
        -------
        ndarray, shape (n_inputs,)
            The plant input ``u(k)`` (within the bounds).
        """
        if self._nd:
            dv = self._check_dv(dv)
            self.yhat = self._C @ self._x + self._ss.D_disturbances @ dv
        else:
            dv = None
            self.yhat = self._C @ self._x
        self.prediction_error = np.asarray(y, dtype=float) - self.yhat
        self.controller_input = np.asarray(r, dtype=float) - self.prediction_error
        eps = self.controller_input
        nu = self._nu
        if not self.options.constrained:
            du0 = (self._K_eps[:nu] @ eps + self._first_move_x(self._x) + self._K_u[:nu] @ self._u_prev
                   + self._K_nom[:nu] @ self.u_nom)
            if dv is not None:
                du0 = du0 + self._K_dv[:nu] @ dv
            u_ctrl = self._u_prev + du0
        else:
            du = self.unconstrained_moves(eps, self._x, self._u_prev, dv)
            u_path = self._Mc @ du + np.tile(self._u_prev, self._hc)
            ok = (np.all(u_path >= np.tile(self.u_min, self._hc) - 1e-12)
                  and np.all(u_path <= np.tile(self.u_max, self._hc) + 1e-12)
                  and np.all(np.abs(du) <= np.tile(self.du_max, self._hc) + 1e-12))
            if not ok:
                du = self.solve_qp(eps, self._x, self._u_prev, dv)
            self._last_du = du
            du0 = np.clip(du[:nu], -self.du_max, self.du_max)
            u_ctrl = np.clip(self._u_prev + du0, self.u_min, self.u_max)
        self._u_prev = u_ctrl
        u = u_ctrl if dither is None else np.clip(u_ctrl + dither, self.u_min, self.u_max)
        if dv is not None:
            self._x = self._A @ self._x + self._Bu @ u + self._Bd @ dv
        else:
            self._x = self._A @ self._x + self._Bu @ u
        return u
