"""The signals the paper's tests work on, recomputed from logged r, u, dv, y and the model.

``yhat = Phat [u | dv]`` (the model simulated from the data's start, on its inputs and measured
disturbances), ``d = y - yhat`` (prediction error) and ``eps = r - d`` (controller input), paper
Fig. 1 and eq. (1), (9).  The model is simulated element by element
(:func:`mpm_monitor.core.discretize.simulate_elements`, the exact ZOH equivalent of
:func:`~mpm_monitor.core.discretize.state_space` at a fraction of the dense simulation's cost),
whatever the structure of its elements.

The model's state at the first logged sample is unknown when the log starts mid-operation.  With
``initial_state="estimate"`` the model is first simulated from rest; once the longest shift
register ``L`` of the model (:attr:`~mpm_monitor.core.discretize.DiscreteElements.memory`: the
longest input lag, or a step-response element's ``N`` coefficients) has passed, every effect of
the unknown state and of the unknown columns before the log is held in the elements' denominator
states, so the rest of the error is a sum of free responses ``k^q p^(k - L)`` per output row, over
the decaying real poles ``p`` of the row's elements (one per first-order element, two for a second
lag, ``q`` up to the multiplicity of a repeated pole).  A step-response element has no free
response beyond its ``N`` samples; an integrator's pole 1 gives a constant, which the tests'
centring removes.  The amplitudes are estimated by least squares, row by row (so a mismatch in one
row can never leak into another), over the model's settling time, and are subtracted only when
they are jointly significant (F test at level 0.001); data that start at rest therefore keep the
exact zero initial state.  Many nearly equal poles (ten lags between 2 and 20 s in one row) make
the free responses almost linearly dependent: least squares then fits the noise or a drift with
huge cancelling amplitudes (~1e5 for a transient of ~1), which distorts the start of the record.
Such an ill-posed estimate (:func:`transient_amplitudes`) is refitted on the basis' leading
singular directions only, with the smallest cut-off that makes it well-posed; a well-posed
estimate is kept exactly as least squares gives it.  With ``"zero"`` the model starts at rest.

Integrating outputs
-------------------
An output with an integrating element (a level) has no fixed operating point: the plant's output
is the model's response plus an arbitrary level.  Under "no mismatch" ``d = y - yhat`` is that
constant plus the disturbance ``v``, stationary, and the tests centre every signal, so they keep
their level.  With an error ``dK`` of an integrator's gain, ``d`` holds ``dK T / (1 - q^-1) u``, a
drift; the ARX of the element test (:mod:`mpm_monitor.core.element_test`) carries the root
``q = 1`` in its ``A`` polynomial (``na = 4`` is enough), so ``B_ij`` stays finite and the element
is located.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .arx import least_squares_ar
from .discretize import discretize, model_columns, settling_samples, simulate_elements
from .errors import ConfigurationError
from .gap_inputs import gap_response
from .logged_data import check_disturbance_signal
from .model import PlantModel
from .segments import GapSegments, held_rows, run_places, run_samples, unknown_span
from .statistics import f_test

INITIAL_STATE_CHOICES = ("estimate", "zero")

#: Level of the F test that decides whether a row's initial transient is subtracted.
TRANSIENT_TEST_LEVEL = 1e-3
#: A transient estimate whose free responses, each at its largest, add up to more than this many
#: times the largest value of the fitted transient is ill-posed (nearly equal poles cancelling).
TRANSIENT_MAX_CANCELLATION = 1e3
#: Relative singular-value cut-offs tried, in turn, on an ill-posed estimate.
TRANSIENT_CUTOFFS = (1e-8, 1e-6, 1e-4, 1e-2)
#: Samples after the transient's span that the AR(2) noise model of its decision is fitted on, at least
#: (fewer: on every sample after the longest shift register, the span's included).
TRANSIENT_NOISE_SAMPLES = 200


@dataclasses.dataclass
class LoopSignals:
    """Model output, prediction error and controller input of a log.

    Attributes
    ----------
    yhat : ndarray, shape (n_samples, n_outputs)
        Model output ``Phat u`` (with the estimated initial transient, if any).
    d : ndarray, shape (n_samples, n_outputs)
        Prediction error ``y - yhat``.
    eps : ndarray, shape (n_samples, n_outputs)
        Controller input ``r - d``.
    transient : ndarray, shape (n_samples, n_outputs)
        The initial-state transient added to ``Phat u`` (zeros when none was significant).
    initial_state : str or None
        The ``initial_state`` of :func:`compute_signals` when it computed them from the data alone
        (None for signals from elsewhere, e.g. a model run continuously since before the window).
    """

    yhat: np.ndarray
    d: np.ndarray
    eps: np.ndarray
    transient: np.ndarray
    initial_state: Optional[str] = dataclasses.field(default=None, compare=False)


def initial_transient(model: PlantModel, d0: np.ndarray, level: float = TRANSIENT_TEST_LEVEL,
                      rows=None, clean: Optional[int] = None) -> np.ndarray:
    """Per-row least-squares estimate of the free response hidden in ``d0`` (see module docstring).

    Parameters
    ----------
    model : PlantModel
    d0 : ndarray, shape (n_samples, n_outputs) (or (n_samples, len(rows)))
        Prediction error of the model simulated from rest.
    level : float
        Significance level below which a row's transient is kept.
    rows : sequence of int, optional
        The outputs of the columns of ``d0`` (default: all of them, in order).
    clean : int, optional
        Data with gaps (a run the model is simulated through, :func:`segment_signals`): the samples
        before the run's first gap.  The noise model that whitens the decision is fitted on them
        when at least :data:`TRANSIENT_NOISE_SAMPLES` of them follow the transient's span: past a gap
        ``d0`` holds held outputs and the model's response to its held columns, which are not the
        disturbance (a single dropped sample moved the decision's p-value from 0.007 to 4e-16).

    Returns
    -------
    ndarray, shape of ``d0``
        The transient to add to the model output (zero for rows where it is not significant).
    """
    n = d0.shape[0]
    rows = range(model.n_outputs) if rows is None else rows
    disc = discretize(model)
    lag = disc.memory
    span = min(n - lag, max(settling_samples(model), 50))
    out = np.zeros_like(d0)
    if span < 20:
        return out
    k = np.arange(n - lag)
    # The noise model's samples: the rest of the record after the span, or of the run before its first gap.
    end = n if clean is None or clean - lag - span < TRANSIENT_NOISE_SAMPLES else min(int(clean), n)
    for c, i in enumerate(rows):
        lag_poles = disc.lag_poles(i)
        if not lag_poles:
            continue
        poles = np.array(list(lag_poles))
        powers = [q for p, mult in lag_poles.items() for q in range(1, mult)]
        repeated = np.array([p for p, mult in lag_poles.items() for _ in range(1, mult)])
        basis = free_responses(poles, repeated, powers, k[:span])     # (span, n_basis); all n - lag rows if kept
        seg = d0[lag:lag + span, c]
        # Decision: F test of the free responses after whitening by an AR(2) noise model fitted on
        # the rest of the record (where no transient is left), so the coloured disturbance (the
        # paper's v is AR(1) with pole 0.95) does not pass for a transient.
        rest = d0[lag + span:end, c] if end - lag - span >= TRANSIENT_NOISE_SAMPLES else d0[lag:, c]
        phi = least_squares_ar(rest - rest.mean(), 2) if rest.shape[0] >= 10 else np.zeros(2)
        white = lambda x: x[2:] - phi[0] * x[1:-1] - phi[1] * x[:-2]  # noqa: E731
        target = white(seg - seg.mean())
        X = np.column_stack([np.ones(span - 2), white(basis)])
        coef, *_ = np.linalg.lstsq(X, target, rcond=1e-10)
        rss_full = float(np.sum((target - X @ coef) ** 2))
        rss_null = float(np.sum((target - target.mean()) ** 2))
        rank = int(np.linalg.matrix_rank(X))
        _, p = f_test(rss_null, rss_full, rank - 1, span - 2 - rank)
        if p < level:
            # Amplitudes from the plain least-squares fit (unbiased under coloured noise).
            coef = transient_amplitudes(basis - basis.mean(axis=0), seg - seg.mean())
            out[lag:, c] = free_responses(poles, repeated, powers, k) @ coef
    return out


def cancellation(X: np.ndarray, coef: np.ndarray) -> float:
    """``sum_k |coef_k| max|X_k|`` over ``max|X coef|``: 1 without cancellation, huge when the terms cancel."""
    fitted = float(np.max(np.abs(X @ coef), initial=0.0))
    terms = float(np.sum(np.abs(coef) * np.max(np.abs(X), axis=0, initial=0.0)))
    return terms / fitted if fitted > 0 else (0.0 if terms == 0 else float("inf"))


def transient_amplitudes(X: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Amplitudes of the free responses ``X`` fitted to ``target`` (least squares, conditioned).

    The plain least-squares solution is returned unless it is ill-posed (its :func:`cancellation`
    exceeds :data:`TRANSIENT_MAX_CANCELLATION`); then the truncated-SVD solution with the first
    cut-off of :data:`TRANSIENT_CUTOFFS` that is well-posed (the last one when none is).

    Parameters
    ----------
    X : ndarray, shape (span, n_basis)
        Centred free responses.
    target : ndarray, shape (span,)
        Centred prediction error over the span.

    Returns
    -------
    ndarray, shape (n_basis,)
    """
    coef, *_ = np.linalg.lstsq(X, target, rcond=1e-10)
    for cutoff in TRANSIENT_CUTOFFS:
        if cancellation(X, coef) <= TRANSIENT_MAX_CANCELLATION:
            break
        coef, *_ = np.linalg.lstsq(X, target, rcond=cutoff)
    return coef


def free_responses(poles: np.ndarray, repeated: np.ndarray, powers: list, k: np.ndarray) -> np.ndarray:
    """Free responses ``p^k`` of every pole, then ``k^q p^k`` of the repeated ones.

    Parameters
    ----------
    poles : ndarray, shape (n_poles,)
    repeated : ndarray, shape (n_extra,)
        The pole of each extra column.
    powers : list of int, length n_extra
        Its ``q >= 1``.
    k : ndarray of int, shape (n,)
        Samples.

    Returns
    -------
    ndarray, shape (n, n_poles + n_extra)
    """
    basis = poles[None, :] ** k[:, None]
    if not powers:
        return basis
    kf = k.astype(float)[:, None]
    return np.hstack([basis, kf ** np.array(powers)[None, :] * repeated[None, :] ** k[:, None]])


def changed_rows(model: PlantModel, other: PlantModel) -> list:
    """Outputs whose elements differ between ``model`` and ``other`` (two models of the same columns)."""
    if model.is_step_response != other.is_step_response:
        return list(range(model.n_outputs))
    if model.is_step_response:
        same = np.all(model.step_response == other.step_response, axis=(1, 2)) & (np.array(model.ramp) == other.ramp)
    else:
        same = np.ones(model.n_outputs, dtype=bool)
        for key in ("gain", "time_constant", "delay", "lead", "time_constant2", "integrating"):
            same &= np.all(getattr(model, key) == getattr(other, key), axis=1)
    return [int(i) for i in np.flatnonzero(~same)]


def _rows_reusable(model: PlantModel, other: PlantModel, n: int) -> bool:
    """Whether the signals of ``other`` hold those of ``model`` on the rows where their elements agree:
    same outputs and columns, the same whole-model spans of the initial transient (memory and
    settling), and no direct feed-through (summed over all rows at once)."""
    if (model.outputs, model.columns, model.sample_time) != (other.outputs, other.columns, other.sample_time):
        return False
    disc, disc_o = discretize(model), discretize(other)
    if not (disc.strictly_proper and disc_o.strictly_proper) or disc.memory != disc_o.memory:
        return False
    return min(n - disc.memory, max(settling_samples(model), 50)) == \
        min(n - disc_o.memory, max(settling_samples(other), 50))


def compute_signals(model: PlantModel, r: np.ndarray, u: np.ndarray, y: np.ndarray,
                    initial_state: str = "estimate", dv: np.ndarray = None, *, like=None, jobs: int = 1,
                    clean: Optional[int] = None) -> LoopSignals:
    """Recompute ``yhat``, ``d`` and ``eps`` from logged data.

    Parameters
    ----------
    model : PlantModel
        The controller's model ``Phat``, any structure.
    r, y : ndarray, shape (n_samples, n_outputs)
        Setpoints and measured outputs.
    u : ndarray, shape (n_samples, n_inputs)
        Plant inputs.
    initial_state : {"estimate", "zero"}
        How to start the model (see the module docstring).
    dv : ndarray, shape (n_samples, n_disturbances), optional
        Measured disturbances, required when the model has some.
    like : tuple (PlantModel, LoopSignals), optional
        Another model and its signals, computed by this function from the same data: when they were
        computed with the same ``initial_state`` and the whole-model spans of the initial transient
        agree, the rows where the other model's elements equal ``model``'s are taken from them (the
        same numbers) and only the others are computed; otherwise every row is computed.
    jobs : int
        With 2 (and no ``like``), a forked child process computes one of two halves of the rows
        (:func:`~mpm_monitor.core.parallel.split_map`): each row is its own simulation and fit, so the
        numbers are the same.  A model with a direct feedthrough is computed in one process (its
        feedthrough is one product of every row).
    clean : int, optional
        The samples before the first gap of a run with held samples (:func:`segment_signals`), for the
        initial transient's noise model (:func:`initial_transient`).

    Returns
    -------
    LoopSignals

    Raises
    ------
    DataFileError
        ``dv`` missing for a model with measured disturbances, of the wrong shape or not finite.
    """
    if initial_state not in INITIAL_STATE_CHOICES:
        raise ConfigurationError(f"initial_state: expected one of {', '.join(INITIAL_STATE_CHOICES)}, got {initial_state!r}")
    r, u, y = (np.asarray(a, dtype=float) for a in (r, u, y))
    if model.n_disturbances or dv is not None:
        dv = check_disturbance_signal(dv, model.n_disturbances, u.shape[0])
    if (like is not None and like[1].initial_state == initial_state and np.shape(like[1].d) == y.shape
            and _rows_reusable(model, like[0], u.shape[0])):
        rows = changed_rows(model, like[0])
        sig = like[1]
        part = _row_signals(model, r[:, rows], u, y[:, rows], initial_state, dv, rows, clean)
        out = LoopSignals(*(np.array(getattr(sig, key), dtype=float) for key in ("yhat", "d", "eps", "transient")),
                          initial_state=initial_state)
        for key in ("yhat", "d", "eps", "transient"):
            getattr(out, key)[:, rows] = getattr(part, key)
        return out
    ny = model.n_outputs
    if jobs > 1 and ny > 1 and not np.any(discretize(model).feedthrough != 0):
        from .parallel import split_map

        half = (ny + 1) // 2
        parts = split_map(lambda rows: _row_signals(model, r[:, rows], u, y[:, rows], initial_state, dv, rows, clean),
                          [list(range(half)), list(range(half, ny))], jobs)
        return LoopSignals(*(np.concatenate([getattr(p, key) for p in parts], axis=1)
                             for key in ("yhat", "d", "eps", "transient")), initial_state=initial_state)
    return _row_signals(model, r, u, y, initial_state, dv, None, clean)


def _row_signals(model, r, u, y, initial_state, dv, rows, clean=None) -> LoopSignals:
    """:func:`compute_signals` of the outputs ``rows`` (all when None); ``r``, ``y`` of those rows."""
    yhat = simulate_elements(model, model_columns(u, dv), rows=rows)
    transient = np.zeros_like(yhat)
    if initial_state == "estimate" and u.shape[0] > 1:
        transient = initial_transient(model, y - yhat, rows=rows, clean=clean)
        yhat = yhat + transient
    d = y - yhat
    return LoopSignals(yhat=yhat, d=d, eps=r - d, transient=transient, initial_state=initial_state)


def segment_signals(model: PlantModel, r: np.ndarray, u: np.ndarray, y: np.ndarray, segments,
                    initial_state: str = "estimate", dv: np.ndarray = None, grid: Optional[np.ndarray] = None,
                    max_gap: Optional[int] = None, fill: Optional[tuple] = None, gap_inputs: bool = True) -> LoopSignals:
    """:func:`compute_signals` of data with gaps: the model runs through a short gap and restarts after a long one.

    The samples of a gap are unknown.  Without ``grid`` every contiguous segment is simulated from
    rest at its first sample with its own initial-transient estimate.  With ``grid`` and
    ``max_gap``, segments separated by gaps of at most ``max_gap`` samples form one run
    (:func:`~mpm_monitor.core.segments.gap_runs`): the model is simulated over the run's whole sample
    grid, its columns held at their last logged values through each gap (what the controller's hold
    does between moves), so
    its state carries across the gap instead of starting from rest; a missing sample whose columns
    were logged and are sound (``fill``: the sample of a spike in an output) takes them instead.
    The initial transient of a run is estimated from its first samples (a held output stands
    in for a missing one in that one fit), its decision whitened by a noise model fitted before the
    run's first gap when enough samples lie there (:func:`initial_transient`).  The plant received the
    columns the log lost inside a short gap, not the held ones: with ``gap_inputs`` the model's
    response to their unknown difference is fitted to the prediction error after the gap, row by row,
    and subtracted (:func:`~mpm_monitor.core.gap_inputs.gap_response`; not on an output with an
    integrating element).  The signals are returned at the logged samples only: no regression row or statistic reads a
    held value.  A run starts at the first segment and after every longer gap.

    Parameters
    ----------
    model : PlantModel
    r, y : ndarray, shape (n_samples, n_outputs)
    u : ndarray, shape (n_samples, n_inputs)
    segments : sequence of (int, int)
        Contiguous runs of rows ``(first, end)``, in order, covering the rows.
    initial_state : {"estimate", "zero"}
    dv : ndarray, shape (n_samples, n_disturbances), optional
    grid : ndarray of int, shape (n_samples,), optional
        Sample number of every row on the sample grid (:attr:`LoggedData.grid_index`).
    max_gap : int, optional
        Longest gap (missing samples) the model runs through; needed with ``grid``.
    fill : tuple (ndarray of int, ndarray), optional
        Grid numbers (as ``grid``) of missing samples with known columns, and those columns ``[u |
        dv]``, shape (m, n_inputs + k) (:meth:`LoggedData.fill_on_grid`); the measured disturbances
        beyond the first ``k`` (candidate channels added to the model since) are held.
    gap_inputs : bool
        Fit and subtract the response to the unknown columns of the short gaps (default); False: the
        model's run with the columns held, as it is.

    Returns
    -------
    LoopSignals
        The segments' signals stacked, shape (n_samples, n_outputs) each.
    """
    runs = [(int(a), int(b), None) for a, b in segments] if grid is None or max_gap is None else \
        GapSegments(segments, grid, max_gap, None if fill is None else fill[0]).runs
    parts = []
    for run in runs:
        a, b, held = run
        if held is None:
            parts.append(compute_signals(model, r[a:b], u[a:b], y[a:b], initial_state,
                                         dv=None if dv is None else dv[a:b]))
            continue
        at = run_places(run)                          # the rows' places on the run's grid, the columns held
        u_run, dv_run = run_samples(u, run), None if dv is None else run_samples(dv, run)
        logged = at                                   # the places whose columns are known: logged, or filled
        if fill is not None:
            where = np.asarray(fill[0], dtype=np.int64) - int(grid[a])
            inside = (where > 0) & (where < at[-1])
            if np.any(inside):
                cols = np.asarray(fill[1], dtype=float)[inside]
                nu = u_run.shape[1]
                u_run = np.array(u_run, dtype=float)
                u_run[where[inside]] = cols[:, :nu]
                known = cols.shape[1] - nu        # columns added since (candidates) stay held
                if dv_run is not None and known > 0:
                    dv_run = np.array(dv_run, dtype=float)
                    dv_run[where[inside], :known] = cols[:, nu:nu + dv_run.shape[1]]
                # A missing sample after a filled one holds the filled columns (the last the controller sent).
                logged = np.union1d(at, where[inside])
                last = logged[held_rows(logged)[0]]
                u_run = u_run[last]
                if dv_run is not None:
                    dv_run = dv_run[last]
        jumps = np.flatnonzero(np.diff(at) > 1)        # the run's first gap: its noise model is fitted before it
        sig = compute_signals(model, run_samples(r, run), u_run, run_samples(y, run), initial_state, dv=dv_run,
                              clean=int(at[jumps[0]]) + 1 if jumps.size else None)
        sig = LoopSignals(**{f.name: getattr(sig, f.name)[at] for f in dataclasses.fields(LoopSignals)
                             if f.name != "initial_state"}, initial_state=sig.initial_state)
        # The response to the columns the log lost in the run's gaps, fitted to the error after them.
        unknown = np.setdiff1d(np.arange(int(at[-1]) + 1), logged, assume_unique=True)
        lost = gap_response(model, sig.d, at, unknown) if gap_inputs else None
        if lost is not None and np.any(lost):
            sig = LoopSignals(yhat=sig.yhat + lost, d=sig.d - lost, eps=sig.eps + lost, transient=sig.transient,
                              initial_state=sig.initial_state)
        parts.append(sig)
    return LoopSignals(**{f.name: np.vstack([getattr(p, f.name) for p in parts])
                          for f in dataclasses.fields(LoopSignals) if f.name != "initial_state"},
                       initial_state=parts[0].initial_state if parts else initial_state)


#: Data with gaps: the samples of a segment after a gap count as settled once the free responses of the
#: state the gap leaves have decayed to this fraction (:func:`scored_segments`).
SETTLED_FRACTION = 0.05


def scored_segments(segments, *models: PlantModel, settled: bool = False, restarts=None) -> list:
    """The segments of data with gaps without the first samples of every segment after a gap that still
    depend on the state the gap leaves.

    The first segment is kept whole (its initial state is that of any record, estimated as without
    gaps).  A later segment loses its first samples: the longest shift register of ``models``
    (:attr:`~mpm_monitor.core.discretize.DiscreteElements.transient_onset`: while the model output still
    depends on the columns inside the gap other than through a decaying response; for a step-response
    element its dead time) and, with ``settled``, also those before the free responses have decayed to
    :data:`SETTLED_FRACTION` (:func:`~mpm_monitor.core.discretize.settling_samples`; the per-segment
    estimate of that state is not exact; a step-response element's whole response).

    Parameters
    ----------
    segments : sequence of (int, int)
        Contiguous runs of rows ``(first, end)`` of the stacked samples, in order.
    *models : PlantModel
        The models whose outputs are compared (the longest memory of them counts).
    settled : bool
    restarts : collection of int, optional
        The segments whose start still carries an unknown (:func:`unknown_starts`: after a long gap,
        or a short one with a held input); default every segment after the first.  The others are
        kept whole.

    Returns
    -------
    list of (int, int)
    """
    segments = [(int(a), int(b)) for a, b in segments]
    skip = max(discretize(m).transient_onset for m in models)
    if settled:
        skip += max(settling_samples(m, SETTLED_FRACTION) for m in models)
    restarts = range(1, len(segments)) if restarts is None else set(restarts)
    return segments[:1] + [(min(a + skip, b) if k in restarts else a, b) for k, (a, b) in enumerate(segments) if k]


def unknown_starts(segments, grid: np.ndarray, max_gap: int, fill: Optional[tuple] = None,
                   model: Optional[PlantModel] = None) -> list:
    """The segments (after the first) whose start still carries an unknown: after a gap longer than
    ``max_gap`` (the model restarts there, :func:`segment_signals`) or after a short gap with a
    sample whose columns are unknown (held through it) when their response is not fitted.  The
    ``restarts`` of :func:`scored_segments`.

    :func:`segment_signals` fits the response to a short gap's unknown columns
    (:func:`~mpm_monitor.core.gap_inputs.gap_response`) on every output without an integrating
    element; an output with one is not fitted (its level moves for good).  So with ``model`` given
    and none of its outputs integrating, a short gap restarts nothing.

    Parameters
    ----------
    segments : sequence of (int, int)
    grid : ndarray of int, shape (n_samples,)
    max_gap : int
    fill : tuple (ndarray of int, ndarray), optional
        Grid numbers of missing samples whose columns are known (:meth:`LoggedData.fill_on_grid`).
    model : PlantModel, optional
        The model run through the short gaps (default: none known, every short gap with an unknown
        sample restarts).

    Returns
    -------
    list of int
    """
    known = None if fill is None else np.unique(np.asarray(fill[0], dtype=np.int64))
    fitted = model is not None and not any(model.integrating_outputs)
    out = []
    for k in range(1, len(segments)):
        span = unknown_span(int(grid[segments[k - 1][1] - 1]), int(grid[segments[k][0]]), known)
        if span > max_gap or (not fitted and span > 0):
            out.append(k)
    return out


def packed(segments) -> list:
    """The runs ``segments`` (``(first, end)``, in order) as runs of their rows taken out and stacked
    (``x[scored_mask(...)]``): ``[(0, b0 - a0), (b0 - a0, ...), ...]``."""
    edges = np.cumsum([0] + [int(b) - int(a) for a, b in segments])
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def scored_mask(segments, n: int, *models: PlantModel, settled: bool = False, restarts=None) -> np.ndarray:
    """:func:`scored_segments` as a mask over the ``n`` stacked samples, shape (n,), bool."""
    return segments_mask(scored_segments(segments, *models, settled=settled, restarts=restarts), n)


def segments_mask(segments, n: int) -> np.ndarray:
    """The rows of ``segments`` (``(first, end)`` runs) as a mask over ``n`` samples, shape (n,), bool."""
    keep = np.zeros(int(n), dtype=bool)
    for a, b in segments:
        keep[a:b] = True
    return keep


def error_rms(model: PlantModel, d: np.ndarray, segments=None) -> dict:
    """``{output name: RMS of its prediction error}``, about its mean on an integrating output.

    An integrating output has no fixed level (see the module docstring): its prediction error holds
    the output's arbitrary level, which no model explains, so its RMS is taken about the mean (of
    every segment of data with gaps: the inputs inside a gap are unknown, and a pulse of them into an
    integrator moves the level for good).  A self-regulating output keeps its offset (a wrong gain
    times the inputs' mean shows there).

    Parameters
    ----------
    model : PlantModel
    d : ndarray, shape (n_samples, n_outputs)
    segments : sequence of (int, int), optional
        Contiguous runs of the rows of ``d`` between gaps (default: one).

    Returns
    -------
    dict
    """
    d = np.asarray(d, dtype=float)
    out = {}
    for i, (name, integrating) in enumerate(zip(model.outputs, model.integrating_outputs)):
        if integrating and d.shape[0] and segments:
            x = np.concatenate([d[a:b, i] - np.mean(d[a:b, i]) for a, b in segments if b > a] or [d[:0, i]])
        else:
            x = d[:, i] - np.mean(d[:, i]) if integrating and d.shape[0] else d[:, i]
        out[name] = float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")
    return out
