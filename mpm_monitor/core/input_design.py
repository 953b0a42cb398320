"""The element test's input design: the lagged columns, factored once per window and checked for collinearity.

:class:`InputDesign` holds the lag blocks of the model's columns (the inputs, then the measured
disturbances) shared by every row's element fit; the columns whose blocks cannot be separated are
grouped (:func:`group_inputs`), and the element test reports their elements as ambiguous with their
group, never guessed.
"""

from __future__ import annotations

import numpy as np

from .arx import SharedBlockRegression, lag_matrix
from .logged_data import moving_columns
from .model import PlantModel


class InputDesign:
    """The lagged-column regressors of the Delta test, factored once and checked for collinearity.

    The columns are the model's inputs, then its measured disturbances; "input" below means any of
    them (:attr:`~mpm_monitor.core.model.PlantModel.columns`).

    Parameters
    ----------
    model : PlantModel
    u : ndarray, shape (n_samples, n_columns)
    n_lag : int
        Lags ``1 .. n_lag`` of every column.
    start : int
        First sample used.
    threshold : float
        An input is not separable when the largest generalised variance-inflation factor of its
        lag block, ``1 / (1 - rho_max^2)`` with ``rho_max`` its largest canonical correlation with
        the lag blocks of the other inputs, exceeds ``1 / threshold``.
    regression : callable, optional
        ``regression(testable)`` returns the :class:`~mpm_monitor.core.arx.SharedBlockRegression` of
        the lags of the inputs ``testable`` (default: built here as
        :meth:`~mpm_monitor.core.regressions.QrRegressions.input_regression` builds it).

    Attributes
    ----------
    testable : list of int
        Inputs that move.
    constant : list of str
        Inputs that never move.
    vif : dict
        Input name -> largest variance-inflation factor of its lag block.
    max_vif : float
        The largest of them (1 when no input moves).
    groups : list of tuple of str
        Inputs that cannot be told apart, grouped (:func:`group_inputs`).
    group_of : dict
        Input name -> its group, for the inputs in a group.
    regression : SharedBlockRegression
        The factored lag blocks of the inputs ``testable``.
    """

    def __init__(self, model, u, n_lag, start, threshold, regression=None):
        self.n_lag = n_lag
        moves = moving_columns(u)        # a column that moves relative to its own size, in any units
        names = model.columns
        self._disturbances = set(model.disturbances)
        self.testable = [j for j in range(model.n_columns) if moves[j]]
        self.constant = [names[j] for j in range(model.n_columns) if j not in self.testable]
        if regression is None:
            u_c = u - u.mean(axis=0)
            X = lag_matrix(u_c[:, self.testable], range(1, n_lag + 1), start) if self.testable else \
                np.zeros((u.shape[0] - start, 0))
            self.regression = SharedBlockRegression(X, [n_lag] * len(self.testable))
        else:
            self.regression = regression(self.testable)
        self.vif = {}
        R = self.regression.R
        p = R.shape[1]
        if p:
            rinv = self.regression.rinv()             # pseudo-inverse when rank-deficient
            blocks = np.arange(p).reshape(len(self.testable), n_lag)
            r_blocks = np.swapaxes(R.T[blocks], 1, 2)                     # R[:, sl] of every block
            gram = np.swapaxes(r_blocks, 1, 2) @ r_blocks                 # X_j' X_j, scaled columns
            ri = rinv[blocks]
            inv = ri @ np.swapaxes(ri, 1, 2)                              # blocks of (X'X)^-1
            eigenvalues = np.linalg.eigvals(gram @ inv).real
            for b, j in enumerate(self.testable):
                sl = slice(b * n_lag, (b + 1) * n_lag)
                ev = eigenvalues[b]
                vif = float(ev.max()) if np.all(np.isfinite(ev)) else float("inf")
                if not self.regression.full_rank:
                    # A dependent lag block makes (X'X) singular: the pseudo-inverse hides it.
                    sub = R[:, [c for c in range(p) if c < sl.start or c >= sl.stop]]
                    if np.linalg.matrix_rank(np.hstack([sub, R[:, sl]])) < np.linalg.matrix_rank(sub) + n_lag:
                        vif = float("inf")
                self.vif[names[j]] = vif
        bad = [name for name, v in self.vif.items() if not v < 1.0 / threshold]
        self.max_vif = max(self.vif.values(), default=1.0)
        self.groups = group_inputs(u, bad, names, threshold)
        self.group_of = {name: g for g in self.groups for name in g}

    def warnings(self) -> list:
        """What the design limits: inputs that never move, inputs that move together."""
        out = []
        still_u = [c for c in self.constant if c not in self._disturbances]
        still_dv = [c for c in self.constant if c in self._disturbances]
        if still_u:
            out.append(f"inputs {', '.join(still_u)} never move: their elements cannot be tested")
        if still_dv:
            out.append(f"measured disturbances {', '.join(still_dv)} never move: their elements cannot be tested")
        if self.groups:
            grouped = {c for g in self.groups for c in g}
            what = ("measured disturbances " if grouped <= self._disturbances else
                    "inputs and measured disturbances " if grouped & self._disturbances else "inputs ")
            if all(len(g) == 1 for g in self.groups):     # each moves with a combination of the others
                if len(self.groups) == 1:
                    name = self.groups[0][0]
                    kind = "measured disturbance" if name in self._disturbances else "input"
                    head = f"{kind} {name} moves with the other columns "
                else:
                    head = what + ", ".join(g[0] for g in self.groups) + " each move with the other columns "
            else:
                # A column alone in its group moves with a combination of the others' lags, not with one group
                # (its dependence is dynamic): "{feed}" read as a group of one that moves together.
                together = [g for g in self.groups if len(g) > 1]
                alone = [g[0] for g in self.groups if len(g) == 1]
                head = what + "; ".join("{" + ", ".join(g) + "}" for g in together) + " move together"
                if alone:
                    head += f", and {', '.join(alone)} {'moves' if len(alone) == 1 else 'each move'} with a " \
                            f"combination of the other columns"
                head += " "
            if grouped <= self._disturbances:      # measured disturbances alone: no dither of the inputs helps
                why = ("the controller does not move them, so their elements cannot be told apart from these data "
                       "and no dither of the inputs separates them: data where they move apart would")
            else:
                why = ("the closed loop drives them collinearly, so their elements cannot be told apart from these "
                       "data; add a small dither on the inputs to separate them")
            out.append(head + f"(largest variance inflation {self.max_vif:.3g}, condition number of the "
                       f"input regressors {self.regression.condition_number:.3g}): " + why)
        return out


def _columns_word(model: PlantModel, names) -> str:
    """``inputs``, ``measured disturbances`` or ``inputs and measured disturbances``: what the columns ``names`` are."""
    index = {c: j for j, c in enumerate(model.columns)}
    roles = {model.role(index[n]) if n in index else "input" for n in names}
    return {frozenset({"input"}): "inputs", frozenset({"disturbance"}): "measured disturbances"}.get(
        frozenset(roles), "inputs and measured disturbances")


def group_inputs(u: np.ndarray, bad: list, names, threshold: float) -> list:
    """Group the non-separable inputs by the near-null directions of their correlation matrix.

    Parameters
    ----------
    u : ndarray, shape (n_samples, n_columns)
    bad : list of str
        The inputs whose lag block is not separable from the others'.
    names : sequence of str
        Every input's name, in the columns' order.
    threshold : float
        The collinearity threshold of :class:`InputDesign`.

    Returns
    -------
    list of tuple of str
        Inputs joined when they share a direction of small variance of their correlation matrix;
        all of ``bad`` in one group when none is small (the collinearity is only dynamic).
    """
    if not bad:
        return []
    idx = [list(names).index(b) for b in bad]
    z = u[:, idx] - u[:, idx].mean(axis=0)
    z = z / np.maximum(z.std(axis=0), 1e-300)
    w, v = np.linalg.eigh(z.T @ z / z.shape[0])
    parent = list(range(len(idx)))

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    small = [k for k in range(len(w)) if w[k] < 10 * threshold * max(w.mean(), 1e-300)]
    for k in small:
        members = [m for m in range(len(idx)) if abs(v[m, k]) > 0.1]
        for m in members[1:]:
            parent[find(m)] = find(members[0])
    if not small:  # dynamic collinearity only: the inputs cannot be separated from each other
        for m in range(1, len(idx)):
            parent[find(m)] = find(0)
    groups = {}
    for m in range(len(idx)):
        groups.setdefault(find(m), []).append(bad[m])
    return [tuple(g) for g in groups.values()]
