"""Model-plant mismatch detection: the S_Delta row test and the Delta element test.

For a plant under MPC in internal-model structure (paper, Fig. 1), with ``d = y - Phat u`` and
``eps = r - d``::

    eps = S_Delta (r - v),   S_Delta = (I + Delta C)^-1            (paper eq. 1)
    d   = Delta u + v                                             (paper eq. 9)

**Row test.**  Row ``i`` of ``S_Delta - I`` equals ``-Delta_i C S_Delta``, so it is zero exactly when
row ``i`` of ``Delta`` is zero.  With ``z_i = eps_i - r_i`` the ARX

    A(q) z_i(t) = sum_j C_j(q) r_j(t) + e(t)

has ``C = 0`` under "no mismatch in row i", and since the setpoints are exogenous (independent of
the disturbance) the F test of ``C = 0`` has a known false-alarm rate whatever the disturbance
colour.  The same fit gives the paper's identified row ``S_i = e_i + C/A`` (an ARX of ``eps_i`` on
``r``), whose H-infinity norm over the band is the row's relative sensitivity index (RSI, paper
eq. 8).  Rows are decided with Holm's step-down procedure at family-wise level ``alpha / 2``.

**Element test.**  For every row (the paper: every flagged row), the ARX
``A(q) d_i = sum_j B_ij(q) u_j + e`` (paper eq. 10) with B polynomials covering every lag from 1 to
``max_delay + nb`` (so no delay needs to be known in advance); element ``(i, j)`` is located when
its first ``delay + nb`` B coefficients (where a mismatch of an element the model has must start;
all of them for an element the model lacks) are rejected as zero by their F (Wald) test, with
Holm's procedure across every element tested at level ``alpha / 2``.  Inputs that move together (the
closed loop drives them collinearly) cannot be told apart: they are reported as ambiguous with the
group, never guessed.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from .arx import SharedBlockRegression, estimate_delay_from_lags, lag_matrix
from .errors import ConfigurationError, DataFileError
from .logged_data import LoggedData, check_loop_data
from .model import FopdtModel
from .regressions import regression_layout, window_regressions
from .signals import INITIAL_STATE_CHOICES, LoopSignals, compute_signals
from .statistics import N_FAMILIES, holm_adjust
from .wording import repair_summary_lines

METHODS = ("arx", "xcorr", "pcorr")


@dataclasses.dataclass(frozen=True)
class AnalysisOptions:
    """Options of :func:`analyze`.

    Attributes
    ----------
    na : int
        Order of the ARX ``A`` polynomials (paper: 4).
    nb : int
        Length of the ARX ``B`` polynomials once the delay is known (paper: 4); the tests use
        ``max_delay + nb`` lags so that the delay need not be known.
    alpha : float
        False-alarm rate of the whole analysis, in (0, 0.5): when the model matches the plant, the
        probability that any row or any element is reported mismatched is at most ``alpha``.  It
        is split equally (Bonferroni) between the row tests and the element tests, each family
        controlled by Holm's procedure; the reported ``p_value`` of a row or element is adjusted
        for both, so a finding is reported exactly when ``p_value < alpha``.
    band : tuple of float
        Band ``Omega`` of the RSI in rad/sample, ``0 <= low < high <= pi``.
    n_freq : int
        Frequencies evaluated in the band.
    max_delay : int or None
        Largest dead time (samples) searched; default: the model's largest delay + 5, at least 10.
    initial_state : {"estimate", "zero"}
        How the model output is started (:func:`mpm_monitor.core.signals.compute_signals`).
    method : {"arx", "xcorr", "pcorr"}
        Element test: the ARX Delta test (default), or a baseline: cross-correlation (Webber and
        Gupta 2008) or partial correlation (Badwe et al. 2009).
    repair : bool
        Trace each located element to its kind and re-estimate it (:mod:`mpm_monitor.core.repair`).
    collinearity_threshold : float
        An input is not separable from the others (its elements are reported as ambiguous) when
        the variance-inflation factor of its lag block exceeds ``1 / collinearity_threshold``.
    element_window : {"model", "full"}
        Lags the element test examines: "model" (default) the first ``delay + nb`` lags of an
        element the model has (where any mismatch of that element starts), all lags for an element
        the model lacks; "full" all lags ``1 .. max_delay + nb`` for every element.
    test_all_rows : bool
        Run the element test on every row (default), not only on the rows the S_Delta test flags
        (the paper's order).  The family-wise false-alarm rate stays ``alpha`` (Holm's procedure
        over every element tested); a row in which an element is located counts as mismatched even
        when its S_Delta test, which has less power for a small mismatch, did not reject.
    """

    na: int = 4
    nb: int = 4
    alpha: float = 0.01
    band: tuple = (0.0, math.pi)
    n_freq: int = 256
    max_delay: Optional[int] = None
    initial_state: str = "estimate"
    method: str = "arx"
    repair: bool = True
    collinearity_threshold: float = 1e-2
    test_all_rows: bool = True
    element_window: str = "model"

    def __post_init__(self):
        check_analysis_options(self)


def check_analysis_options(o: AnalysisOptions) -> None:
    """Raise :class:`ConfigurationError` naming the option outside its range."""
    if int(o.na) != o.na or not 0 <= o.na <= 50:
        raise ConfigurationError(f"na: expected an integer in [0, 50], got {o.na!r}")
    if int(o.nb) != o.nb or not 1 <= o.nb <= 50:
        raise ConfigurationError(f"nb: expected an integer in [1, 50], got {o.nb!r}")
    if not (0.0 < o.alpha < 0.5):
        raise ConfigurationError(f"alpha: expected a number in (0, 0.5), got {o.alpha!r}")
    lo, hi = o.band
    if not (0.0 <= lo < hi <= math.pi + 1e-12):
        raise ConfigurationError(f"band: expected 0 <= low < high <= pi rad/sample, got {o.band!r}")
    if int(o.n_freq) != o.n_freq or not 8 <= o.n_freq <= 100000:
        raise ConfigurationError(f"n_freq: expected an integer in [8, 100000], got {o.n_freq!r}")
    if o.max_delay is not None and (int(o.max_delay) != o.max_delay or not 0 <= o.max_delay <= 1000):
        raise ConfigurationError(f"max_delay: expected an integer in [0, 1000] samples, got {o.max_delay!r}")
    if o.initial_state not in INITIAL_STATE_CHOICES:
        raise ConfigurationError(f"initial_state: expected one of {', '.join(INITIAL_STATE_CHOICES)}, got {o.initial_state!r}")
    if o.element_window not in ("model", "full"):
        raise ConfigurationError(f"element_window: expected 'model' or 'full', got {o.element_window!r}")
    if o.method not in METHODS:
        raise ConfigurationError(f"method: expected one of {', '.join(METHODS)}, got {o.method!r}")
    if not (0.0 < o.collinearity_threshold < 1.0):
        raise ConfigurationError(f"collinearity_threshold: expected a number in (0, 1), got {o.collinearity_threshold!r}")


@dataclasses.dataclass
class RowResult:
    """S_Delta row test of one output.

    Attributes
    ----------
    output : str
    rsi : float
        Row H-infinity norm of the identified S_Delta over the band.
    mismatch : bool
        The row differs from the identity row (Holm-adjusted p < alpha).
    p_value : float
        Holm-adjusted p-value of "row equals the identity row".
    p_value_raw : float
        Unadjusted p-value.
    statistic : float
        F statistic.
    df : tuple of int
        Degrees of freedom (numerator, denominator).
    fit_percent : float
        One-step fit of the row's ARX.
    """

    output: str
    rsi: float
    mismatch: bool
    p_value: float
    p_value_raw: float
    statistic: float
    df: tuple
    fit_percent: float


@dataclasses.dataclass
class ElementResult:
    """Delta element test of one (output, input) pair.

    Attributes
    ----------
    output, input : str
    mismatch : bool
        Located as mismatched.
    p_value : float or None
        Holm-adjusted p-value of ``B_ij = 0`` (None when not testable).
    p_value_raw : float or None
    statistic : float or None
    kind : str or None
        ``gain``, ``time_constant``, ``delay``, ``missing``, ``mixed``, ``unknown`` (located
        elements) or None.
    ambiguous : bool
        The input cannot be told apart from others in ``ambiguous_with``.
    ambiguous_with : tuple of str
    delay : int or None
        Estimated dead time of ``Delta_ij`` in samples.
    b : list of float
        ARX ``B_ij`` coefficients at that delay (``nb`` values).
    """

    output: str
    input: str
    mismatch: bool
    p_value: Optional[float]
    p_value_raw: Optional[float]
    statistic: Optional[float]
    kind: Optional[str] = None
    ambiguous: bool = False
    ambiguous_with: tuple = ()
    delay: Optional[int] = None
    b: list = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class RowArxTable:
    """The paper's ARX table of a flagged row (Tables 1 to 5): A, each B with its delay, fit."""

    output: str
    a: list
    b: dict
    delay: dict
    fit_percent: float


@dataclasses.dataclass
class AnalysisReport:
    """Everything :func:`analyze` found; ``to_dict()`` gives the JSON of CONTRACTS section 3."""

    sample_time: float
    samples: int
    method: str
    alpha: float
    rows: list
    elements: list
    overall_rsi: float
    warnings: list
    frequencies: np.ndarray
    row_gains: np.ndarray
    sigma_max: np.ndarray
    sdelta_response: np.ndarray
    arx_tables: list
    repair: dict
    repaired_model: FopdtModel
    collinear_groups: list
    max_variance_inflation: float
    signals: Optional[LoopSignals] = None
    repair_result: object = None

    @property
    def flagged_rows(self) -> list:
        """Outputs whose row is flagged."""
        return [r.output for r in self.rows if r.mismatch]

    @property
    def located_elements(self) -> list:
        """(output, input) pairs located as mismatched."""
        return [(e.output, e.input) for e in self.elements if e.mismatch]

    @property
    def ambiguous_elements(self) -> list:
        """(output, input) pairs that could not be told apart."""
        return [(e.output, e.input) for e in self.elements if e.ambiguous]

    def to_dict(self) -> dict:
        """The report as JSON-ready data (NaN and infinity become null)."""
        def clean(x):
            if isinstance(x, float) and not math.isfinite(x):
                return None
            if isinstance(x, (np.floating,)):
                return clean(float(x))
            if isinstance(x, (np.integer,)):
                return int(x)
            if isinstance(x, dict):
                return {k: clean(v) for k, v in x.items()}
            if isinstance(x, (list, tuple)):
                return [clean(v) for v in x]
            if isinstance(x, np.ndarray):
                return clean(x.tolist())
            return x

        doc = {
            "sample_time": self.sample_time,
            "samples": self.samples,
            "method": self.method,
            "alpha": self.alpha,
            "overall_rsi": self.overall_rsi,
            "rows": [dataclasses.asdict(r) for r in self.rows],
            "elements": [dataclasses.asdict(e) for e in self.elements],
            "located": [{"output": o, "input": i} for o, i in self.located_elements],
            "collinearity": {"max_variance_inflation": self.max_variance_inflation,
                             "groups": [list(g) for g in self.collinear_groups]},
            "arx_tables": [dataclasses.asdict(t) for t in self.arx_tables],
            "repair": self.repair,
            "warnings": list(self.warnings),
        }
        return clean(doc)

    def summary_text(self) -> str:
        """A short human-readable summary (rows, located elements, errors, warnings)."""
        lines = [f"{self.samples} samples at {self.sample_time:g} s, method {self.method}, "
                 f"false-alarm rate alpha {self.alpha:g}; overall RSI {self.overall_rsi:.3f}"]
        lines.append(f"{'row':<10} {'RSI':>8} {'p-value':>10}  mismatch")
        for r in self.rows:
            lines.append(f"{r.output:<10} {r.rsi:8.3f} {r.p_value:10.2e}  {'YES' if r.mismatch else 'no'}")
        loc = [e for e in self.elements if e.mismatch]
        if loc:
            lines.append("located elements:")
            for e in loc:
                lines.append(f"  ({e.output}, {e.input})  p={e.p_value:.2e}  kind={e.kind}  delay={e.delay}")
        else:
            lines.append("located elements: none")
        amb = [e for e in self.elements if e.ambiguous]
        if amb:
            lines.append("ambiguous (inputs move together): "
                         + ", ".join(f"({e.output}, {e.input})" for e in amb))
        lines += repair_summary_lines(self.repair)
        for w in self.warnings:
            lines.append(f"warning: {w}")
        return "\n".join(lines)


def frequency_grid(band: tuple, n: int) -> np.ndarray:
    """Frequencies (rad/sample) in the band: 0 if included, then log-spaced to the top."""
    lo, hi = band
    lo_log = max(lo, hi * 1e-3)
    grid = np.logspace(np.log10(lo_log), np.log10(hi), n - (1 if lo == 0 else 0))
    if lo == 0:
        grid = np.concatenate([[0.0], grid])
    return grid


def analyze(model: FopdtModel, data: LoggedData, options: AnalysisOptions = AnalysisOptions(), *,
            signals: Optional[LoopSignals] = None, regressions=None) -> AnalysisReport:
    """Run the S_Delta row test and the Delta element test on logged closed-loop data.

    Parameters
    ----------
    model : FopdtModel
        The controller's model ``Phat``.
    data : LoggedData
        Setpoints, inputs and outputs, equally spaced at ``model.sample_time``.
    options : AnalysisOptions
    signals : LoopSignals, optional
        ``yhat``, ``d`` and ``eps`` of these samples, e.g. from a model run continuously since
        before the window (:mod:`mpm_monitor.core.sliding`); default: recomputed from the data with
        ``options.initial_state``.
    regressions : object, optional
        Provider of the tests' least-squares fits with the methods of
        :class:`~mpm_monitor.core.regressions.QrRegressions`.  Default:
        :func:`mpm_monitor.core.regressions.window_regressions`, the fits solved from the Gram
        matrices of the window's lagged signals, each regression whose condition bound exceeds
        1e3 (or whose residual is too small a part of its target) refitted by QR; the results equal
        those of :class:`QrRegressions` to about 1e-10.

    Returns
    -------
    AnalysisReport

    Raises
    ------
    DataFileError
        When the data do not fit the model or are too short for the tests.
    """
    ny = model.n_outputs
    src = data.source or "data"
    r, u, y = check_loop_data(model, data)
    n = r.shape[0]
    na, nb, alpha = options.na, options.nb, options.alpha
    layout = regression_layout(model, options)
    n_lag_r, n_lag_u, start = layout.n_lag_r, layout.n_lag_u, layout.start
    need = layout.min_samples
    if n < need:
        raise DataFileError(f"{src}: {n} samples; the tests with na={na}, nb={nb}, max_delay={layout.max_delay} "
                            f"need at least {need} samples")
    warnings = []
    if signals is None:
        sig = compute_signals(model, r, u, y, options.initial_state)
    else:
        sig = signals
        if sig.d.shape != (n, ny) or sig.eps.shape != (n, ny):
            raise DataFileError(f"{src}: signals of shape {sig.d.shape} / {sig.eps.shape}, expected ({n}, {ny})")
    z = sig.eps - r   # = -d: zero-mean noise under "no mismatch"
    if regressions is not None:
        regs = regressions
    else:
        regs = window_regressions(r, u, z, sig.d, layout, na, nb)

    # ---------------------------------------------------------------- S_Delta row test
    r_std = r.std(axis=0)
    r_moving = [j for j in range(ny) if r_std[j] > 0]
    if len(r_moving) < ny:
        still = [model.outputs[j] for j in range(ny) if j not in r_moving]
        warnings.append(f"setpoints of {', '.join(still)} never move: their columns of S_Delta cannot be identified "
                        f"and a mismatch that shows only through them goes unseen")
    reg_r = regs.row_regression(r_moving)
    omega = frequency_grid(options.band, options.n_freq)
    z1 = np.exp(-1j * omega)
    z_pow = z1[:, None] ** np.arange(max(n_lag_r, na + 1))     # z^-l, shape (n_freq, lags)
    S = np.zeros((omega.size, ny, ny), dtype=complex)
    row_raw_p = np.full(ny, np.nan)
    row_stat, row_df, row_fit = np.full(ny, np.nan), [(0, 0)] * ny, np.zeros(ny)
    for i in range(ny):
        fit = regs.row_fit(reg_r, i)
        test = fit.test_all_common_zero()
        row_raw_p[i], row_stat[i], row_df[i] = test.p_value, test.statistic, (test.df_num, test.df_den)
        a = fit.own_theta()
        a_poly = 1.0 + z_pow[:, 1:na + 1] @ a
        S[:, i, i] = 1.0
        for bj, j in enumerate(r_moving):
            c = fit.block_theta(bj)
            S[:, i, j] += (z_pow[:, :n_lag_r] @ c) / a_poly
        # Fit of the paper's ARX of eps_i on r (same model, target eps_i).
        e_i = sig.eps[start:, i] - sig.eps[start:, i].mean()
        row_fit[i] = 100.0 * (1.0 - math.sqrt(fit.rss) / max(np.linalg.norm(e_i), 1e-300))
    row_gains = np.linalg.norm(S, axis=2).T                       # (ny, n_freq)
    sigma_max = np.linalg.svd(S, compute_uv=False)[:, 0]
    row_p = np.minimum(1.0, N_FAMILIES * holm_adjust(row_raw_p))
    rows = []
    for i in range(ny):
        p = row_p[i]
        rows.append(RowResult(output=model.outputs[i], rsi=float(row_gains[i].max()),
                              mismatch=bool(np.isfinite(p) and p < alpha), p_value=float(p) if np.isfinite(p) else 1.0,
                              p_value_raw=float(row_raw_p[i]), statistic=float(row_stat[i]), df=tuple(row_df[i]),
                              fit_percent=float(row_fit[i])))

    # ---------------------------------------------------------------- Delta element test
    test_rows = list(range(ny)) if (options.test_all_rows or options.method != "arx") else \
        [i for i in range(ny) if rows[i].mismatch]
    design = InputDesign(model, u, n_lag_u, start, options.collinearity_threshold, regs.input_regression)
    if design.constant:
        warnings.append(f"inputs {', '.join(design.constant)} never move: their elements cannot be tested")
    if design.groups:
        warnings.append(
            "inputs " + "; ".join("{" + ", ".join(g) + "}" for g in design.groups)
            + f" move together (largest variance inflation {design.max_vif:.3g}, condition number of the "
              f"input regressors {design.regression.condition_number:.3g}): the closed loop drives them "
              "collinearly, so their elements cannot be told apart from these data; add a small dither on the "
              "inputs to separate them")
    elements, arx_tables = [], []
    if options.method == "arx":
        elements, arx_tables, group_hits = _arx_element_test(model, test_rows, options, design, regs)
        for out_name, g, p in group_hits:
            warnings.append(f"row {out_name}: inputs {', '.join(g)} jointly explain part of its prediction error "
                            f"(p={p:.2g}) but cannot be told apart from these data")
    else:
        elements, base_warnings = _baseline_element_test(model, u, sig.d, options)
        warnings.extend(base_warnings)
    for i in range(ny):
        if not rows[i].mismatch and any(e.mismatch for e in elements if e.output == model.outputs[i]):
            rows[i] = dataclasses.replace(rows[i], mismatch=True)
    for i in test_rows:
        out = model.outputs[i]
        row_el = [e for e in elements if e.output == out]
        if rows[i].mismatch and not any(e.mismatch or e.ambiguous for e in row_el):
            warnings.append(f"row {out} differs from the identity but no input explains its prediction error: an "
                            f"unmeasured disturbance, a nonlinearity or too little input excitation")

    # ---------------------------------------------------------------- trace and repair
    located = [(model.outputs.index(e.output), model.inputs.index(e.input)) for e in elements if e.mismatch]
    repair_doc, repaired, repair_result = _repair(model, data, located, sig, options, warnings)
    kinds = getattr(repair_result, "kinds", {}) if repair_result is not None else {}
    for e in elements:
        if e.mismatch:
            key = (model.outputs.index(e.output), model.inputs.index(e.input))
            e.kind = kinds.get(key, "unknown")
    return AnalysisReport(
        sample_time=model.sample_time, samples=n, method=options.method, alpha=alpha, rows=rows,
        elements=elements, overall_rsi=float(sigma_max.max()), warnings=warnings, frequencies=omega,
        row_gains=row_gains, sigma_max=sigma_max, sdelta_response=S, arx_tables=arx_tables, repair=repair_doc,
        repaired_model=repaired, collinear_groups=design.groups, max_variance_inflation=design.max_vif, signals=sig,
        repair_result=repair_result)


class InputDesign:
    """The lagged-input regressors of the Delta test, factored once and checked for collinearity.

    Parameters
    ----------
    model : FopdtModel
    u : ndarray, shape (n_samples, n_inputs)
    n_lag : int
        Lags ``1 .. n_lag`` of every input.
    start : int
        First sample used.
    threshold : float
        An input is not separable when the largest generalised variance-inflation factor of its
        lag block, ``1 / (1 - rho_max^2)`` with ``rho_max`` its largest canonical correlation with
        the lag blocks of the other inputs, exceeds ``1 / threshold``.
    regression : callable, optional
        ``regression(testable)`` returns the :class:`SharedBlockRegression` of the lags of the
        inputs ``testable`` (default: :meth:`~mpm_monitor.core.regressions.QrRegressions.input_regression`).

    Attributes
    ----------
    testable : list of int
        Inputs that move.
    constant : list of str
        Inputs that never move.
    vif : dict
        Input name -> largest variance-inflation factor of its lag block.
    groups : list of tuple of str
        Inputs that cannot be told apart, grouped.
    """

    def __init__(self, model, u, n_lag, start, threshold, regression=None):
        self.n_lag = n_lag
        std = u.std(axis=0)
        scale = np.maximum(np.abs(u).max(axis=0, initial=0.0), 1.0)
        self.testable = [j for j in range(model.n_inputs) if std[j] > 1e-12 * scale[j]]
        self.constant = [model.inputs[j] for j in range(model.n_inputs) if j not in self.testable]
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
                self.vif[model.inputs[j]] = vif
        bad = [name for name, v in self.vif.items() if not v < 1.0 / threshold]
        self.max_vif = max(self.vif.values(), default=1.0)
        self.groups = _group_inputs(u, bad, model.inputs, threshold)
        self.group_of = {name: g for g in self.groups for name in g}


def _group_inputs(u, bad, names, threshold):
    """Group the non-separable inputs by the near-null directions of their correlation matrix."""
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


def _element_window(model, i, j, options, design):
    """Leading input lags the element test of (i, j) tests (None: all of them).

    ``Delta_ij = P_ij - Phat_ij`` is non-zero from lag ``min(theta_plant, theta_model) + 1`` on,
    so for an element the model has (gain != 0) its first ``theta_model + nb`` lags hold the onset
    of any mismatch; the later lags stay in the fit as nuisance (under "no mismatch" every lag is
    zero, so the test keeps its level).  Fewer tested lags means more power.  Elements the model
    does not have (gain 0) have no known delay: all lags are tested.
    """
    if options.element_window == "full" or model.gain[i, j] == 0:
        return None
    return int(model.delay_samples[i, j]) + options.nb


def _arx_element_test(model, test_rows, options, design, regs):
    """The Delta element test on the rows ``test_rows`` (see the module docstring)."""
    nb, alpha = options.nb, options.alpha
    nu = model.n_inputs
    testable, group_of = design.testable, design.group_of
    raw, info, tables, group_hits = {}, {}, [], []
    for i in test_rows:
        fit = regs.element_fit(design.regression, i)
        tests = fit.test_each_block_zero([_element_window(model, i, j, options, design) for j in testable])
        stds = fit.block_stds()
        for bj, j in enumerate(testable):
            coef = fit.block_theta(bj)
            lag0 = estimate_delay_from_lags(coef, stds[bj], nb, first_lag=1)
            raw[(i, j)] = tests[bj]
            info[(i, j)] = (lag0, coef[lag0 - 1:lag0 - 1 + nb].tolist())
        for g in design.groups:
            blocks = [testable.index(model.inputs.index(x)) for x in g]
            jt = fit.test_blocks_zero(blocks)
            if np.isfinite(jt.p_value) and \
                    N_FAMILIES * jt.p_value * max(len(test_rows) * len(design.groups), 1) < alpha:
                group_hits.append((model.outputs[i], g, jt.p_value))
        # The paper's table (Tables 1 to 5): a short ARX at the estimated delays, for reporting.
        nk = np.array([info[(i, j)][0] if (i, j) in info else 1 for j in range(nu)])
        short = regs.short_arx(i, nk)
        tables.append(RowArxTable(output=model.outputs[i], a=short.a.tolist(),
                                  b={model.inputs[j]: short.b[j].tolist() for j in range(nu)},
                                  delay={model.inputs[j]: int(nk[j]) for j in range(nu)},
                                  fit_percent=short.fit_percent))
    keys = [k for k in raw if model.inputs[k[1]] not in group_of]
    adj = dict(zip(keys, holm_adjust(np.array([raw[k].p_value for k in keys])))) if keys else {}
    elements = []
    for i in test_rows:
        for j in range(nu):
            name, out = model.inputs[j], model.outputs[i]
            if (i, j) not in raw:   # the input never moves
                elements.append(ElementResult(output=out, input=name, mismatch=False, p_value=None,
                                              p_value_raw=None, statistic=None, ambiguous=True))
                continue
            t = raw[(i, j)]
            delay, b = info[(i, j)]
            if name in group_of:
                elements.append(ElementResult(
                    output=out, input=name, mismatch=False, p_value=None, p_value_raw=t.p_value,
                    statistic=t.statistic, ambiguous=True,
                    ambiguous_with=tuple(x for x in group_of[name] if x != name), delay=int(delay), b=b))
                continue
            p = min(1.0, N_FAMILIES * adj[(i, j)])
            elements.append(ElementResult(
                output=out, input=name, mismatch=bool(np.isfinite(p) and p < alpha),
                p_value=float(p) if np.isfinite(p) else 1.0, p_value_raw=t.p_value, statistic=t.statistic,
                delay=int(delay), b=b))
    return elements, tables, group_hits


def _baseline_element_test(model, u, d, options):
    """Element decisions of a baseline method on every row."""
    from .baselines import cross_correlation_test, partial_correlation_test

    fn = cross_correlation_test if options.method == "xcorr" else partial_correlation_test
    res = fn(d, u, alpha=options.alpha / N_FAMILIES)
    adjusted = N_FAMILIES * (res.adjusted_p_values if res.adjusted_p_values is not None else res.p_values)
    elements = []
    for i in range(model.n_outputs):
        for j in range(model.n_inputs):
            amb = bool(res.ambiguous[i, j]) if res.ambiguous is not None else False
            p_raw, p_adj = float(res.p_values[i, j]), float(adjusted[i, j])
            elements.append(ElementResult(output=model.outputs[i], input=model.inputs[j],
                                          mismatch=bool(res.mismatch[i, j]) and not amb,
                                          p_value=None if amb or not np.isfinite(p_adj) else p_adj,
                                          p_value_raw=p_raw if np.isfinite(p_raw) else None,
                                          statistic=float(res.statistic[i, j]), ambiguous=amb))
    return elements, list(res.warnings or [])


def _rms(d: np.ndarray, names) -> dict:
    return {name: float(np.sqrt(np.mean(d[:, k] ** 2))) for k, name in enumerate(names)}


def _repair(model, data, located, sig, options, warnings):
    """Call the repair (if enabled and available); return (repair dict, repaired model, result)."""
    base = {"model": model.to_dict(), "changes": [], "error_before": _rms(sig.d, model.outputs),
            "error_after": _rms(sig.d, model.outputs)}
    if not options.repair:
        return base, model, None
    from .repair import RepairOptions, repair_model

    result = repair_model(model, data, located, RepairOptions(initial_state=options.initial_state), signals=sig)
    warnings.extend(w for w in result.warnings if w not in warnings)
    doc = result.to_dict()
    if result.model != model:
        # The relative sensitivity of the repaired model on the same data (issue 5, item 4).
        after = analyze(result.model, data, dataclasses.replace(options, repair=False, test_all_rows=False))
        doc["rsi_after"] = {r.output: r.rsi for r in after.rows}
        doc["rows_flagged_after"] = after.flagged_rows
    return doc, result.model, result
