"""Sliding-window mismatch analysis from sufficient statistics.

A live monitor analyses the last ``W`` samples every few seconds.  Refitting the tests of
:func:`mpm_monitor.core.pipeline.analyze` from scratch costs ``O(W p^2)`` per analysis, with ``p`` the
number of regressors (about 300 for a 20x20 plant).  :class:`SlidingWindowAnalyzer` instead keeps
cross-product (Gram) matrices of the lagged regressors up to date as samples enter and leave the
window, ``O(p^2)`` per sample, and an analysis solves the tests' least-squares problems from them in
``O(p^3)``, independent of ``W`` (:class:`~mpm_monitor.core.regressions.GramRegressions`, with the
checks and the QR fallback of the batch analysis).

What is kept
------------
Two Gram matrices (:class:`~mpm_monitor.core.lagged_gram.LaggedGram`, with their column sums) over
the regression rows of the window, i.e. the samples ``start .. W - 1`` of the window
(:class:`~mpm_monitor.core.regressions.RegressionLayout`):

* S_Delta row test: the setpoints ``r_c(t - l)``, ``l = 0 .. n_lag_r - 1``, and for every output
  ``z_i(t - l)``, ``l = 0 .. na``, with ``z = eps - r`` (lag 0 is the target, lags >= 1 its own AR
  columns);
* Delta element test: the model's columns ``u_j(t - l)``, ``l = 1 .. n_lag_u`` (the inputs, then
  the measured disturbances), and for every output ``d_i(t - l)``, ``l = 0 .. na``.

Every row's regression is a sub-block of one of them.  Samples are added to and removed from them
by symmetric rank-k updates (:meth:`~mpm_monitor.core.lagged_gram.LaggedGram.update`).

Centring
--------
The tests centre each signal by its mean over the window, which moves as the window slides.  The
Gram matrices hold the raw columns relative to a reference (the window means at the last rebuild;
see :mod:`mpm_monitor.core.regressions`), and are rebuilt from the window buffer every
``refresh_interval`` samples (default: once per window length), when a mean has drifted more than
:data:`MEAN_DRIFT_LIMIT` standard deviations from its reference, and whenever rebuilding is cheaper
than updating.  Rebuilding also bounds the rounding drift of the add/remove updates.

"Same window"
-------------
The analyzer runs the controller's model ``Phat`` continuously from rest at the first pushed sample
(:class:`ModelPredictor`), so ``yhat``, ``d = y - yhat`` and ``eps = r - d`` of a window sample do not
depend on where the window starts -- as in the live loop, and unlike a batch analysis of a window
cut out of a log, which restarts the model at the window's first sample.  The batch analysis of the
same window is therefore ``analyze(model, data, options, signals=signals)`` with the signals of
:func:`mpm_monitor.core.signals.compute_signals` (``initial_state="zero"``) run over every sample pushed
so far and cut to the window; :meth:`SlidingWindowAnalyzer.window_data` returns both.
``options.initial_state`` is not used.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .analysis import AnalysisOptions, AnalysisReport
from .discretize import ModelPredictor, model_columns
from .errors import ConfigurationError, DataFileError
from .gram_fits import DEFAULT_MAX_CONDITION
from .lagged_gram import LaggedGram, SampleBuffer
from .logged_data import LoggedData, check_disturbance_signal, check_signals
from .model import PlantModel
from .pipeline import analyze
from .regressions import GramRegressions, regression_layout
from .signals import LoopSignals

#: A window mean further than this many standard deviations from the Gram reference forces a rebuild.
MEAN_DRIFT_LIMIT = 8.0


# ----------------------------------------------------------------------------------------- analyzer
def _split_signals(ny: int, nu: int):
    """``signals(block)`` for buffer rows ``[r | u | y | yhat]`` (``u``: the ``nu`` model columns):
    r, u, d = y - yhat, z = eps - r."""
    def signals(block):
        r = block[:, :ny]
        u = block[:, ny:ny + nu]
        d = block[:, ny + nu:2 * ny + nu] - block[:, 2 * ny + nu:]
        eps = r - d
        return {"r": r, "u": u, "d": d, "z": eps - r}
    return signals


class SlidingWindowAnalyzer:
    """The S_Delta row test and the Delta element test on a sliding window, from sufficient statistics.

    Parameters
    ----------
    model : PlantModel
        The controller's model ``Phat`` (any structure, with or without measured disturbances); it is
        run from rest at the first pushed sample.
    options : AnalysisOptions
        As for :func:`mpm_monitor.core.pipeline.analyze` (``initial_state`` is not used).
    window : int
        ``W``, the number of most recent samples analysed (at least the tests' minimum for this
        model and these options).
    update_block : int
        Samples are folded into the Gram matrices in blocks of this many (one matrix product per
        block); 1 updates at every sample.  :meth:`analyze` always folds in every pending sample.
    refresh_interval : int or None
        Rebuild the Gram matrices from the window buffer after this many samples (bounds rounding
        drift and re-centres the reference); None: ``window``; 0: only when needed (mean drift,
        or rebuilding cheaper than updating).
    max_condition : float
        Regressions with a larger condition bound are refitted by QR (see the module docstring).

    Notes
    -----
    Memory: the window buffer holds ``window + slack`` rows of ``3 n_outputs + n_columns`` float64
    channels (``slack = max(update_block, window // 4, 64)``), plus two Gram matrices whose size
    depends on the plant and the lags but not on ``window``; :meth:`memory_bytes` reports both.
    """

    def __init__(self, model: PlantModel, options: AnalysisOptions = AnalysisOptions(), window: int = 3000, *,
                 update_block: int = 16, refresh_interval: Optional[int] = None,
                 max_condition: float = DEFAULT_MAX_CONDITION):
        self.model = model
        self.options = options
        self.layout = regression_layout(model, options)
        if isinstance(window, bool) or int(window) != window or window < self.layout.min_samples:
            raise ConfigurationError(f"window: expected an integer >= {self.layout.min_samples} samples (the tests' "
                                     f"minimum with na={options.na}, nb={options.nb}, "
                                     f"max_delay={self.layout.max_delay}), got {window!r}")
        if isinstance(update_block, bool) or int(update_block) != update_block or not 1 <= update_block <= window:
            raise ConfigurationError(f"update_block: expected an integer in [1, window={window}], got {update_block!r}")
        if refresh_interval is not None and (int(refresh_interval) != refresh_interval or refresh_interval < 0):
            raise ConfigurationError(f"refresh_interval: expected an integer >= 0 samples or None, "
                                     f"got {refresh_interval!r}")
        if not (max_condition > 1.0):
            raise ConfigurationError(f"max_condition: expected a number > 1, got {max_condition!r}")
        self.window = int(window)
        self.update_block = int(update_block)
        self.refresh_interval = self.window if refresh_interval is None else int(refresh_interval)
        self.max_condition = float(max_condition)
        ny, nu, na = model.n_outputs, model.n_columns, options.na
        self.ny, self.nu = ny, nu                         # nu: the model's columns (inputs, then disturbances)
        self.n_inputs, self.nd = model.n_inputs, model.n_disturbances
        lay = self.layout
        signals = _split_signals(ny, nu)
        self.row_gram = LaggedGram([("r", ny, range(0, lay.n_lag_r)), ("z", ny, range(0, na + 1))], signals)
        self.input_gram = LaggedGram([("u", nu, range(1, lay.n_lag_u + 1)), ("d", ny, range(0, na + 1))], signals)
        self._slack = max(self.update_block, self.window // 4, 64)
        self.predictor = ModelPredictor(model)
        self.buffer = SampleBuffer(3 * ny + nu, self.window, self._slack)
        self.last_fallbacks: list = []
        self.rebuilds = 0
        self.reset()

    # -------------------------------------------------------------- state
    def reset(self) -> None:
        """Forget every sample and put the model back to rest."""
        self.predictor.reset()
        self.buffer.first = self.buffer.count = 0
        self._pushed = 0
        self._since_rebuild = 0
        self._stale = True
        for g in (self.row_gram, self.input_gram):
            g.clear()
        self._pending = 0

    @property
    def total_samples(self) -> int:
        """Samples pushed since the start (or the last :meth:`reset`)."""
        return self._pushed

    @property
    def n_samples(self) -> int:
        """Samples in the window (``min(total_samples, window)``)."""
        return min(self._pushed, self.window)

    @property
    def ready(self) -> bool:
        """Enough samples for :meth:`analyze`."""
        return self.n_samples >= self.layout.min_samples

    def memory_bytes(self) -> dict:
        """Bytes held: ``buffer`` (grows with the window and the channels) and ``gram`` (does not)."""
        gram = sum(g.gram.nbytes + g.sums.nbytes for g in (self.row_gram, self.input_gram))
        return {"buffer": int(self.buffer.data.nbytes), "gram": int(gram)}

    # -------------------------------------------------------------- input
    def push(self, r, u, y, dv=None) -> None:
        """Add one sample ``r(k)``, ``u(k)``, ``y(k)`` (shapes (n_outputs,), (n_inputs,), (n_outputs,))
        and ``dv(k)`` (shape (n_disturbances,); required when the model has measured disturbances)."""
        r, u, y = check_signals(r, u, y, self.ny, self.n_inputs)
        dv = check_disturbance_signal(dv, self.nd)
        ruy = np.concatenate([r, u, dv, y])
        if self.buffer.free() < 1:
            self.flush()
            self.buffer.compact()
        m = ruy.shape[0]
        row = self.buffer.data[self.buffer.count]
        row[:m] = ruy
        row[m:] = self.predictor.step(u, dv)
        self.buffer.count += 1
        self._after_append(1)

    def push_many(self, r, u, y, dv=None) -> None:
        """Add samples in time order: ``r``, ``y`` of shape (n, n_outputs), ``u`` of shape (n, n_inputs),
        ``dv`` of shape (n, n_disturbances) (required when the model has measured disturbances)."""
        shape = np.shape(r)
        n = shape[0] if len(shape) == 2 else -1
        r, u, y = check_signals(r, u, y, self.ny, self.n_inputs, n)
        u = model_columns(u, check_disturbance_signal(dv, self.nd, n))
        for a in range(0, n, self._slack):
            b = min(a + self._slack, n)
            if self.buffer.free() < b - a:
                self.flush()
                self.buffer.compact()
            yhat = self.predictor.run(u[a:b, :self.n_inputs], u[a:b, self.n_inputs:])
            self.buffer.append(np.hstack([r[a:b], u[a:b], y[a:b], yhat]))
            self._after_append(b - a, flush=False)      # one fold (or rebuild) for the whole call
        if self._pending >= self.update_block:
            self.flush()

    def _after_append(self, k: int, flush: bool = True) -> None:
        self._pushed += k
        self._pending += k
        self._since_rebuild += k
        if flush and self._pending >= self.update_block:
            self.flush()

    # -------------------------------------------------------------- statistics
    def _row_range(self):
        end = self._pushed
        first = max(0, end - self.window)
        lo = first + self.layout.start
        return (lo, end) if end > lo else (lo, lo)

    def _window_means(self):
        first = max(0, self._pushed - self.window)
        block = self.buffer.rows(first, self._pushed)
        return [g.channel_values(block).mean(axis=0) for g in (self.row_gram, self.input_gram)]

    def _rebuild(self) -> None:
        lo, hi = self._row_range()
        means = self._window_means() if self._pushed else [np.zeros(g.n_channels)
                                                          for g in (self.row_gram, self.input_gram)]
        for g, m in zip((self.row_gram, self.input_gram), means):
            g.rebuild(self.buffer, lo, hi, m)
        self._since_rebuild = 0
        self._stale = False
        self.rebuilds += 1

    def flush(self) -> None:
        """Fold every pending sample into the Gram matrices now (or rebuild them)."""
        self._pending = 0
        lo, hi = self._row_range()
        g = self.row_gram
        n_add, n_remove = hi - g.hi, lo - g.lo
        due = self.refresh_interval and self._since_rebuild >= self.refresh_interval
        if self._stale or due or g.hi < lo or n_add + n_remove >= hi - lo:
            self._rebuild()
            return
        for gram in (self.row_gram, self.input_gram):
            gram.update(self.buffer, (gram.hi, hi), (gram.lo, lo))

    def gram_drift(self) -> float:
        """Largest difference between the kept Gram matrices and a rebuild, relative to its largest entry."""
        self.flush()
        out = 0.0
        for g in (self.row_gram, self.input_gram):
            fresh = LaggedGram([(n, c, lags) for n, c, lags in g.groups], g.signals)
            fresh.rebuild(self.buffer, g.lo, g.hi, g.ref)
            kept, ref = g.symmetric(), fresh.symmetric()
            scale = max(np.abs(ref).max(initial=0.0), 1e-300)
            out = max(out, float(np.abs(kept - ref).max(initial=0.0)) / scale)
        return out

    # -------------------------------------------------------------- analysis
    def window_data(self):
        """The current window: (LoggedData, LoopSignals), copies.

        ``LoopSignals.transient`` is zero: the model runs continuously, so there is no initial transient.
        """
        first = max(0, self._pushed - self.window)
        block = self.buffer.rows(first, self._pushed)
        ny, nu = self.ny, self.nu
        r, u, y, yhat = (np.ascontiguousarray(block[:, a:b]) for a, b in
                         ((0, ny), (ny, ny + nu), (ny + nu, 2 * ny + nu), (2 * ny + nu, 3 * ny + nu)))
        d = y - yhat
        eps = r - d
        ts = self.model.sample_time
        nu = self.n_inputs
        data = LoggedData(t=np.arange(first, self._pushed) * ts, r=r, u=np.ascontiguousarray(u[:, :nu]), y=y,
                          inputs=self.model.inputs, outputs=self.model.outputs, sample_time=ts,
                          source="sliding window", dv=np.ascontiguousarray(u[:, nu:]),
                          disturbances=self.model.disturbances)
        return data, LoopSignals(yhat=yhat, d=d, eps=eps, transient=np.zeros_like(d))

    def analyze(self) -> AnalysisReport:
        """The analysis of the current window (see :func:`mpm_monitor.core.pipeline.analyze`).

        Raises
        ------
        DataFileError
            When the window holds fewer samples than the tests need (see :attr:`ready`).
        """
        self.flush()
        data, sig = self.window_data()
        if data.n_samples < self.layout.min_samples:
            raise DataFileError(f"sliding window: {data.n_samples} samples; the tests need at least "
                                f"{self.layout.min_samples} samples")
        z = sig.eps - data.r
        if self._means_drifted(data, sig, z):
            self._rebuild()
        regs = GramRegressions(self.row_gram, self.input_gram, data.r, data.columns, z, sig.d, self.layout,
                               self.options.na, self.options.nb, self.max_condition)
        report = analyze(self.model, data, self.options, signals=sig, regressions=regs)
        self.last_fallbacks = list(regs.fallbacks)
        return report

    def _means_drifted(self, data, sig, z) -> bool:
        for g, arrays in ((self.row_gram, (data.r, z)), (self.input_gram, (data.columns, sig.d))):
            x = np.hstack(arrays)
            mean = x.mean(axis=0)
            shift = np.abs(mean - g.ref)
            if np.any(shift > MEAN_DRIFT_LIMIT * x.std(axis=0) + 1e-9 * (np.abs(mean) + np.abs(g.ref)) + 1e-300):
                return True
        return False
