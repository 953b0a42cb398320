"""Model-plant mismatch detection: the run of the paper's two tests on one window of logged data.

"A Novel Algorithm for Model-Plant Mismatch Detection for Model Predictive Controllers" decides in
two steps which elements of the controller's model ``Phat`` no longer match the plant:

1. the S_Delta row test (:mod:`mpm_monitor.core.row_test`): which rows of the sensitivity
   ``S_Delta = (I + Delta C)^-1`` differ from the identity, with each row's relative sensitivity
   index (RSI);
2. the Delta element test (:mod:`mpm_monitor.core.element_test`): which elements of
   ``Delta = P - Phat`` are non-zero, from the ARX of the prediction error on the model's columns
   -- the inputs and the measured disturbances -- (or a baseline method,
   :mod:`mpm_monitor.core.baselines`).

Every element structure goes through the same code: the model is only ever seen through its
sampled elements (:mod:`mpm_monitor.core.discretize`), and an element test needs only each
element's dead time.  An integrating output keeps both tests valid (see
:mod:`mpm_monitor.core.signals`, "Integrating outputs").

:func:`detect` runs both on one window of logged data (:class:`AnalysisOptions`) and gathers what
they found in an :class:`AnalysisReport`; the whole analysis -- detection, repair of the located
elements, and the detection run again on the repaired model -- is
:func:`mpm_monitor.core.pipeline.analyze`.  The false-alarm rate ``alpha`` is shared by the two
families of tests (:data:`mpm_monitor.core.statistics.N_FAMILIES`).

The options (:class:`AnalysisOptions`, defined in :mod:`mpm_monitor.core.analysis_options`) and the
report (:class:`AnalysisReport`, defined in :mod:`mpm_monitor.core.analysis_report`) are imported
here, where a caller imports them from; the warnings on what the tests cannot see past in the model
and the log are in :mod:`mpm_monitor.core.data_warnings`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import numpy as np

from .analysis_options import AnalysisOptions
from .analysis_report import AnalysisReport, _Valuation, settle_report
from .data_warnings import (held_tail_warnings, longest_dead_time, offset_warnings, short_max_delay_warnings,
                            still_output_warnings, time_unit_note, unsettled_warnings)
from .errors import ConfigurationError, DataFileError, TooFewSamples
from .logged_data import (
    NUMERICAL_ERRORS,
    LoggedData,
    check_loop_data,
    check_scale,
    divergence,
    in_deviations,
    moving_columns,
    numerical_breakdown,
)
from .model import PlantModel
from .parallel import Forked
from .signals import LoopSignals


#: Samples x outputs x columns of a window below which the stages of a detection are not split over two
#: processes (``AnalysisOptions.jobs``): a fork makes every page of the process copy-on-write, and the
#: page faults after it, with the pickling of the results, cost more than half of a small window's
#: stages.  Measured in one process, medians of 5, split against not: case 3.2 (3x3, 3,000 samples,
#: 27,000) 0.638 against 0.576 s; case 3.3 (5x5, 10,000 samples, 250,000) 3.43 against 3.18 s; the
#: command on a 20x20 window of 10,000 samples (4e6) 1.18 against 1.28 s (one process: 1.36 s).
SPLIT_MIN_WORK = 1_000_000
#: ... and below which the lighter stages (the model run, the Gram matrices' products, the singular
#: values of S_Delta) are not split either: at 20x20 each takes a few hundredths of a second, about what
#: the page faults after a fork cost (the command at 20x20 split everywhere and with these three in one
#: process: the same time, median ratio 1.00 over 15 pairs; three forks fewer).
LIGHT_SPLIT_MIN_WORK = 10_000_000


def row_jobs(jobs: int, n_samples: int, model: PlantModel) -> int:
    """The processes the stages split row by row use on a window of ``n_samples`` (the element test, the
    repair): ``jobs`` from :data:`SPLIT_MIN_WORK` samples x outputs x columns, else 1."""
    return jobs if n_samples * model.n_outputs * model.n_columns >= SPLIT_MIN_WORK else 1


def light_jobs(jobs: int, n_samples: int, model: PlantModel) -> int:
    """The processes the lighter stages use on a window of ``n_samples``: ``jobs`` from
    :data:`LIGHT_SPLIT_MIN_WORK` samples x outputs x columns, else 1."""
    return jobs if n_samples * model.n_outputs * model.n_columns >= LIGHT_SPLIT_MIN_WORK else 1


#: Columns of the row test's setpoint block (moving setpoints x setpoint lags) from which, with two
#: processes, a forked child factors it while this process computes the colour of the element fits and
#: the input design (:func:`_detect`).  Its Gram factorisation takes about 0.27 s at 1,800 columns (100
#: outputs x 18 lags), 0.11 s at 1,260 and 0.04 s at 900, one BLAS thread; the child sends back two
#: matrices of that size (52 MB at 1,800), and below about 1,000 columns the fork and the transfer are
#: not repaid.
ROW_FORK_MIN_COLUMNS = 1000


def detect(model: PlantModel, data: LoggedData, options: AnalysisOptions = AnalysisOptions(), *,
           signals: Optional[LoopSignals] = None, regressions=None,
           previous: Optional["AnalysisReport"] = None, candidates=None, detectability: bool = True,
           rows_only: bool = False, settle: bool = True,
           beside: Optional[Callable[[LoopSignals], None]] = None) -> AnalysisReport:
    """Run the S_Delta row test and the Delta element test on logged closed-loop data (no repair).

    Parameters
    ----------
    model : PlantModel
        The controller's model ``Phat``.
    data : LoggedData
        Setpoints, inputs, measured disturbances (those of the model) and outputs, on the grid of
        ``model.sample_time``; ``t`` may skip samples (the analysis then runs on the segments between
        the gaps, :mod:`mpm_monitor.core.gaps`).
    options : AnalysisOptions
        ``options.repair`` is not used here (:func:`mpm_monitor.core.pipeline.analyze`).
    signals : LoopSignals, optional
        ``yhat``, ``d`` and ``eps`` of these samples, e.g. from a model run continuously since
        before the window (:mod:`mpm_monitor.core.sliding`); default: recomputed from the data with
        ``options.initial_state`` (segment by segment on data with gaps).
    regressions : object, optional
        Provider of the tests' least-squares fits with the methods of
        :class:`~mpm_monitor.core.regressions.QrRegressions`.  Default:
        :func:`mpm_monitor.core.regressions.window_regressions`, the fits solved from the Gram
        matrices of the window's lagged signals, each regression whose condition bound exceeds
        1e3 (or whose residual is too small a part of its target) refitted by QR; the results equal
        those of :class:`~mpm_monitor.core.regressions.QrRegressions` to about 1e-10.
    previous : AnalysisReport, optional
        The detection of another model on the same data (before a repair): with the default
        regressions, the S_Delta row test takes from it the setpoint block and the fits of the rows
        whose prediction error is the same (the same numbers,
        :meth:`~mpm_monitor.core.regressions.GramRegressions.reuse_rows_of`).
    candidates : str, sequence of str or CandidateChannels, optional
        Logged channels the model does not use (``data.extra``), tested as causes of each output's
        prediction error jointly with the model's columns (:mod:`mpm_monitor.core.candidates`):
        ``"all"``, names, or channels already selected.  Their tests join the element tests' family.
        Default: none (the analysis is then exactly that without candidates).
    detectability : bool
        False: no ``detectable_gain_change`` (None) and no ``experiment`` (e.g. for the detection of a
        repaired model, of which only the rows are reported); the tests are the same.
    rows_only : bool
        True: a detection of which only the rows are read (the repaired model's): the identified
        ``S_Delta``'s largest singular values are not computed (``sigma_max`` and ``overall_rsi`` NaN),
        and when no row is to be element-tested (``test_all_rows`` false and no row flagged) the
        element test does not run (no elements, ARX tables or collinearity: ``max_variance_inflation``
        NaN), nor are the input lags' cross products taken.  Every row's test and RSI are the same.
    settle : bool
        False, with ``options.jobs`` 2 and no ``candidates``: the detectable gain changes and the
        experiment are computed in a forked second process, and the report is returned while they are
        (its ``pending``); :func:`settle_report` waits for them and puts them in (the analysis repairs the
        model meanwhile, :func:`~mpm_monitor.core.pipeline.analyze`).  The same numbers either way.
    beside : callable, optional
        Called once with the model's signals on data without gaps, when they were computed here and the
        stages that follow run in this process while the analysis has a second one (``options.jobs`` 2, a
        window that splits row by row but not its lighter stages, :func:`light_jobs`): work for the idle
        second process (:func:`~mpm_monitor.core.pipeline.analyze` forks the repair's disturbance tests
        there).  It must not change what it is given.

    Returns
    -------
    AnalysisReport
        ``samples`` counts the samples used and ``gaps`` says what the gaps cost (data with gaps).
        Its ``repair`` holds the model unchanged (no changes; the prediction error's RMS before and
        after) and every located element has the kind ``unknown``.

    Raises
    ------
    DataFileError
        When the data do not fit the model, are too short for the tests or too large for them
        (:func:`~mpm_monitor.core.logged_data.check_scale`), or when the tests break down numerically
        on them (:func:`~mpm_monitor.core.logged_data.numerical_breakdown`: a loop that diverged),
        the numpy error as its ``__cause__``.
    """
    return _guarded(model, data, options, signals, regressions, previous, candidates, detectability,
                    rows_only=rows_only, settle=settle, beside=beside)


def load_tests(model: Optional[PlantModel] = None) -> None:
    """Import now what a detection imports when it first runs (the tests and ``scipy.special``; the options
    and the report are described without them), and sample ``model``'s elements (kept on it, as its first
    simulation would): the command line does it while a child process parses the CSV, instead of after
    (at 100x40 the 4,000 elements take about 0.08 s)."""
    from . import detectability, element_test, experiment, gaps, regressions, response_moments, row_test  # noqa: F401
    from . import resolution, signals, spikes  # noqa: F401
    from .discretize import discretize
    from .statistics import _special

    _special()
    if model is not None:
        discretize(model)


def longest_delay_note(model: PlantModel, options, layout, enough: Callable) -> str:
    """``; max_delay is the model's longest delay + 5 samples: (y1, u1) 500 s, 500 samples`` when that delay is
    why the data are too short: ``options.max_delay`` not given, and ``enough(least)`` for the layout of the
    tests at their least lags (``max_delay`` 10, a :class:`~mpm_monitor.core.regressions.RegressionLayout`).
    A delay in the wrong unit (500 s for 5 s) otherwise reads as a short log.  '' otherwise."""
    if options.max_delay is not None or model.n_outputs == 0 or layout.max_delay <= 10:
        return ""
    from .regressions import regression_layout

    if not enough(regression_layout(model, dataclasses.replace(options, max_delay=10))):
        return ""
    i, j, longest = longest_dead_time(model)
    return (f"; max_delay is the model's longest delay + 5 samples: ({model.outputs[i]}, {model.columns[j]}) "
            f"{longest * model.sample_time:g} s, {longest} samples")


def _guarded(model: PlantModel, data: LoggedData, *args, **how):
    """:func:`_detect` on ``data`` in deviations, its numerical errors turned into a ``DataFileError``
    (:func:`~mpm_monitor.core.logged_data.numerical_breakdown`)."""
    data = in_deviations(model, data)
    try:
        return _detect(model, data, *args, **how)
    except NUMERICAL_ERRORS as err:
        raise numerical_breakdown(model, data, err) from err


def _detect(model: PlantModel, data: LoggedData, options: AnalysisOptions, signals: Optional[LoopSignals],
            regressions, previous: Optional["AnalysisReport"], candidates, detectability: bool,
            unless_coloured: bool = False, rows_only: bool = False, settle: bool = True, beside=None):
    """:func:`detect` (same arguments), its numerical errors not yet turned into a ``DataFileError``; with
    ``unless_coloured``, :func:`detect_unless_coloured`."""
    # The tests are imported here: the options and the report above are described (the command line's
    # flags, the monitor's parameters) without the scipy they need.
    from .detectability import element_detectability
    from .discretize import model_columns
    from .element_test import ElementTest, arx_element_test, baseline_element_test
    from .input_design import InputDesign
    from .experiment import design_experiment
    from .gaps import plan_gaps
    from .regressions import regression_layout, window_regressions
    from .resolution import column_resolution_warnings, resolution_warnings
    from .response_moments import ResponseMoments
    from .row_test import moving_setpoints, sdelta_row_test
    from .segments import GapSegments, errors_centred_by_level
    from .signals import (compute_signals, error_rms, packed, scored_segments, segment_signals, segments_mask,
                          unknown_starts)

    ny = model.n_outputs
    src = data.source or "data"
    r, u, y = check_loop_data(model, data)
    found = divergence(model.outputs, y)
    diverging, diverged = [warning for _, warning in found], [name for name, _ in found]
    check_scale(model, data)
    dv = np.asarray(data.dv, dtype=float)
    layout = regression_layout(model, options)
    plan = plan_gaps(data, layout.start, options.max_gap)
    restarts = fill = None
    if plan is not None:          # data with gaps: the segments long enough for a regression row, stacked
        check_gap_rows(plan, layout, options, src, model, notes=data.notes)
        check_gap_run(plan, data.n_samples, options, src)
        # The segments too short for a row are left out, but the model runs on their logged columns.
        fill = plan.left_out_fill(data)
        r, u, y, dv = (plan.take(x) for x in (r, u, y, dv))
        grid = plan.take(data.grid_index)     # the model runs through a short gap (segment_signals)
        restarts = unknown_starts(plan.local_segments, grid, plan.max_gap, fill, model)
        # The regressions' segments, and the runs the element responses are simulated through (as the model).
        segments = GapSegments(plan.local_segments, grid, plan.max_gap, None if fill is None else fill[0],
                               None if fill is None else fill[1])
    columns = model_columns(u, dv)            # the inputs, then the measured disturbances
    n = r.shape[0]
    # Two processes: the detectable gain changes beside the repair (settle) whenever asked for; the stages split
    # row by row only for a window large enough that half of their work outweighs what a fork costs.
    two = options.jobs > 1
    if two and row_jobs(options.jobs, n, model) == 1:
        options = dataclasses.replace(options, jobs=1)
    split_light = light_jobs(options.jobs, n, model)     # the model run, Gram products, SVD
    if n < layout.min_samples and plan is None:
        raise TooFewSamples(f"{src}: {n} samples; the tests with na={options.na}, nb={options.nb}, "
                            f"max_delay={layout.max_delay} need at least {layout.min_samples} samples"
                            f"{longest_delay_note(model, options, layout, lambda least: n >= least.min_samples)}")
    if signals is None:
        sig = compute_signals(model, r, u, y, options.initial_state, dv=dv, jobs=split_light) if plan is None else \
            segment_signals(model, r, u, y, plan.local_segments, options.initial_state, dv=dv, grid=grid,
                            max_gap=plan.max_gap, fill=fill)
        if beside is not None and plan is None and options.jobs > 1 and split_light == 1:
            beside(sig)
    else:
        sig = signals
        n_given = data.n_samples
        if sig.d.shape != (n_given, ny) or sig.eps.shape != (n_given, ny):
            raise DataFileError(f"{src}: signals of shape {sig.d.shape} / {sig.eps.shape}, expected ({n_given}, {ny})")
        if plan is not None:
            sig = LoopSignals(*(plan.take(x) for x in (sig.yhat, sig.d, sig.eps, sig.transient)))
    if regressions is None and plan is None:
        z = sig.eps - r   # = -d: zero-mean noise under "no mismatch"
        regressions = window_regressions(r, columns, z, sig.d, layout, options.na, options.nb, jobs=split_light,
                                         previous=None if previous is None else previous.regressions)
    elif regressions is None:
        # d centred over each level group (segments.level_groups): a row without an integrating element keeps one
        # level through the short gaps the model runs through; a row with one, and every row after a long gap
        # (its model output restarts), a level per segment.
        d = errors_centred_by_level(sig.d, segments, model.integrating_outputs)
        regressions = window_regressions(r, columns, -d, d, layout, options.na, options.nb,
                                         segments=segments, jobs=split_light)

    # A fit that leaves at most EXACT_FIT of its output's spread is exact (a log without noise): its tests
    # decide outright instead of on the rounding of its residual.  The spread is the larger of the
    # output's and of its prediction error's (the signal the tests fit): an output that never moves
    # (a flat, noise-free log) still leaves the rounding of a moving model output.  A diverging
    # output's spread (its last samples') is no scale for that rounding: there only a residual of
    # exactly 0 is exact.
    error_std = np.std(sig.d, axis=0)
    spread = np.maximum(np.std(y, axis=0), error_std)
    spread[[model.outputs.index(name) for name in diverged]] = 0.0
    probe = unless_coloured and options.method == "arx"
    # With two processes, when the rows to element-test do not depend on the row test (every row, arx), the
    # row test runs in this process after the element test's child has started on the rows (its
    # ``meanwhile``), and this process then takes its share of the rows: the same numbers.
    overlap = options.jobs > 1 and options.method == "arx" and options.test_all_rows and not rows_only
    # Then a large setpoint block (ROW_FORK_MIN_COLUMNS) is factored in a forked child while this process
    # computes the colour, the input design and the element responses' set-up below, and the element test's
    # child starts on its rows; the row test reads the factor (the same numbers).
    factoring = None
    if overlap and hasattr(regressions, "factored_row_regression"):
        r_moving = moving_setpoints(r)
        if len(r_moving) * layout.n_lag_r >= ROW_FORK_MIN_COLUMNS and regressions.row_regression_pending(r_moving):
            factoring = Forked(lambda: regressions.factored_row_regression(r_moving))
    # An output that never moves (a stuck sensor or a held value) has a prediction error that is the model's own
    # response: its row's elements are not tested (the element test would locate every one of them, and the
    # repair would take the row's gains to zero for a fault of the measurement).
    still = np.flatnonzero(~moving_columns(y)).tolist()
    colour = None
    if probe and options.test_all_rows:       # the rows tested do not depend on the row test: before it
        colour = _ElementColour(model, _moving_rows(range(ny), still), columns, layout, regressions, options, spread)
        if colour.noise_order["coloured"]:
            return Coloured(colour.noise_order, sig, None if plan is None else plan.to_dict())
    row_tests = []

    def run_row_test(jobs: int) -> None:
        nonlocal factoring
        if factoring is not None:        # the child's factor of the setpoint block, read once the row test needs it
            factored, factoring = factoring.result(), None
            if factored is not None:
                regressions.keep_row_regression(r_moving, factored)
        row_tests.append(sdelta_row_test(model, r, sig.eps, regressions, layout, options, output_spread=spread,
                                         singular_values=not rows_only, jobs=jobs))
    if not overlap:
        run_row_test(split_light)
    test_rows = list(range(ny)) if (options.test_all_rows or options.method != "arx") else \
        [i for i in range(ny) if row_tests[0].rows[i].mismatch]
    element_rows = _moving_rows(test_rows, still)
    if probe and colour is None:
        colour = _ElementColour(model, element_rows, columns, layout, regressions, options, spread)
        if colour.noise_order["coloured"]:
            return Coloured(colour.noise_order, sig, None if plan is None else plan.to_dict())
    untested = rows_only and not test_rows and options.method == "arx"
    if untested:                  # nothing to element-test, and only the rows are read: no design either
        design = None
    else:
        design = colour.design if colour is not None else \
            InputDesign(model, columns, layout.n_lag_u, layout.start, options.collinearity_threshold,
                        regressions.input_regression)
    # On a loop that diverged every moment is of signals that grow without bound: no detectable change
    # and no experiment means anything there (the warnings already say the tests' results do not).
    valued = options.method == "arx" and detectability and not diverging and not untested
    moments = None
    if valued:
        # The element responses and their products with the input lags, taken once for the
        # whole-response tests and the detectability.
        moments = ResponseMoments(model, columns, sig.d, design.testable, layout.n_lag_u, layout.start, options.na,
                                  None if plan is None else segments)
    later_warnings = []
    if untested:
        element_test = ElementTest(elements=[])
    elif options.method == "arx":
        element_test = arx_element_test(model, element_rows, design, regressions, options, moments,
                                        output_spread=spread, fits=None if colour is None else colour.fits,
                                        whiteness=None if colour is None else colour.whiteness,
                                        meanwhile=(lambda: run_row_test(1)) if overlap else None)
    elif plan is None:
        try:
            element_test = baseline_element_test(model, columns, sig.d, options)
        except TooFewSamples as exc:
            raise TooFewSamples(f"{src}: {str(exc).removeprefix('d and u: ')}") from None
    else:                         # the baselines' correlations need one contiguous span: the longest
        a, b = max(plan.local_segments, key=lambda s: s[1] - s[0])
        try:
            element_test = baseline_element_test(model, columns[a:b], sig.d[a:b], options)
        except TooFewSamples as exc:
            # Reported, not waited for (TooFewSamples): a window's gaps may keep every span this short.
            raise DataFileError(f"{src}: {str(exc).removeprefix('d and u: ')} in the longest span between the gaps "
                                f"({len(plan.segments)} spans, {n} samples used): its correlations need one contiguous "
                                f"span (--method arx stacks the spans)") from None
        later_warnings.append(f"the {options.method} element test ran on the longest span without a gap "
                              f"({b - a} samples)")
    row_test = row_tests[0]
    rows = row_test.rows
    t_used = data.t if plan is None else plan.take(data.t)
    warnings = still_output_warnings(model, still) + held_tail_warnings(model, y, t_used, still) \
        + unsettled_warnings(model) + short_max_delay_warnings(model, options.max_delay) + diverging \
        + list(row_test.warnings) \
        + offset_warnings(model, sig.d, y, diverged, t_used) + resolution_warnings(model.outputs, y, error_std, still) \
        + column_resolution_warnings(model.columns, model.outputs, columns, model.gain,
                                     np.asarray(model.integrating_outputs, dtype=bool)[:, None] | model.integrating,
                                     error_std, still) \
        + ([] if design is None else design.warnings()) + later_warnings
    warnings += element_test.warnings
    # (The baselines test every row: their results on a still output's row are set aside as well.)
    still_names = [model.outputs[i] for i in still]
    elements = with_untested_rows(model, [e for e in element_test.elements if e.output not in still_names],
                                  [i for i in test_rows if i not in element_rows])
    valuation = None
    if valued:
        # The detectable gain changes and the experiment: with settle False and two processes, computed in a
        # forked child while the caller goes on (the repair and the repaired model's detection), and put into
        # the report by settle_report.
        later = not settle and candidates is None and two
        value_options = dataclasses.replace(options, jobs=1) if later else options

        def values_and_experiment():
            info, detectable, why = element_detectability(model, columns, sig.d, design, element_test.noise, layout,
                                                          value_options, None if plan is None else segments,
                                                          responses=element_test.responses, moments=moments)
            values = [detectable.get((model.outputs.index(e.output), model.columns.index(e.input))) for e in elements]
            for e, v in zip(elements, values):
                e.detectable_gain_change = v
            return values, why, design_experiment(model, info, elements, options, layout)
        handle = Forked(values_and_experiment, inline=not later)
        if handle.forked:
            moments.forget()      # only the child reads them now (this process again only if the child dies)
        valuation = _Valuation(handle, elements, warnings)
    elif options.method == "arx" and detectability:
        warnings.append(f"the loop diverged ({', '.join(diverged)}): the smallest gain "
                        "change this window detects is not computed (detectable_gain_change null) and no experiment "
                        "is designed; the model needs repairing before the loop can be probed")
    elif detectability:
        warnings.append(f"method {options.method}: the smallest gain change this window detects is computed for the "
                        f"arx element test only (detectable_gain_change null)")
    experiment = design_experiment(model, None, elements, options, layout) if detectability and not valued else None
    candidate_report = None
    if candidates is not None:
        from .candidates import CandidateChannels, run_candidate_tests, select_candidates

        if options.method != "arx":
            raise ConfigurationError(f"candidates: tested by the arx element test only, not by method {options.method}")
        cdata = data
        if plan is not None:      # the rows of the segments used, as the other tests
            cdata = data.take(np.concatenate([np.arange(a, b) for a, b in plan.used]))
        if isinstance(candidates, CandidateChannels):
            chosen = candidates if plan is None else dataclasses.replace(candidates, values=plan.take(candidates.values))
        else:
            chosen = select_candidates(cdata, candidates, model)
        tested = run_candidate_tests(model, cdata, chosen, columns, sig.d, elements, layout, options,
                                     output_spread=spread, still_outputs=still)
        elements = tested.elements + tested.candidate_elements
        candidate_report = tested.report
        warnings += candidate_report.warnings()
        if tested.candidate_elements and detectability:
            warnings.append("candidate channels: the smallest gain change this window detects is computed for the "
                            "model's own columns only (detectable_gain_change null for the candidates' elements)")

    # A row in which an element is located is mismatched, even when its S_Delta test did not reject.
    for i in range(ny):
        if not rows[i].mismatch and any(e.mismatch for e in elements if e.output == model.outputs[i]):
            rows[i] = dataclasses.replace(rows[i], mismatch=True)
    for i in element_rows:
        out = model.outputs[i]
        row_el = [e for e in elements if e.output == out]
        if rows[i].mismatch and not any(e.mismatch or e.ambiguous for e in row_el):
            what = "no input or measured disturbance" if model.n_disturbances else "no input"
            warnings.append(f"row {out} differs from the identity but {what} explains its prediction error: an "
                            f"unmeasured disturbance, a nonlinearity or too little input excitation")
    for e in elements:
        if e.mismatch:
            e.kind = "missing" if e.role == "candidate" else "unknown"
    # With gaps: over the samples settled from the state each gap leaves, as the repair takes its errors.
    if plan is None:
        rms = error_rms(model, sig.d)
    else:
        scored = scored_segments(plan.local_segments, model, settled=True, restarts=restarts)
        rms = error_rms(model, sig.d[segments_mask(scored, n)], segments=packed(scored))
    unrepaired = {"model": model.to_dict(), "changes": [], "error_before": rms, "error_after": dict(rms)}
    if plan is not None:
        warnings.insert(0, plan.warning())
    warnings[:0] = data.notes
    noise_order = _noise_order(model, options, element_test.whiteness) if options.method == "arx" else None
    report = AnalysisReport(
        sample_time=model.sample_time, samples=n, method=options.method, alpha=options.alpha, rows=rows,
        elements=elements, overall_rsi=float("nan") if rows_only else float(row_test.sigma_max.max()),
        warnings=warnings,
        frequencies=row_test.frequencies, row_gains=row_test.row_gains, sigma_max=row_test.sigma_max,
        sdelta_response=row_test.response, arx_tables=element_test.arx_tables, repair=unrepaired,
        repaired_model=model, collinear_groups=[] if untested else design.groups,
        max_variance_inflation=float("nan") if untested else design.max_vif, signals=sig,
        gaps=None if plan is None else plan.to_dict(), experiment=experiment, candidates=candidate_report,
        regressions=regressions.row_test_part() if getattr(regressions, "batch", False) else None,
        noise_order=noise_order, pending=valuation,
        still_outputs=still_names)
    if settle:
        settle_report(report)
    return report

def _moving_rows(rows, still) -> list:
    """The rows of ``rows`` (output indices) whose output moves (not in ``still``)."""
    return [i for i in rows if i not in still]


def with_untested_rows(model: PlantModel, elements: list, rows: list) -> list:
    """``elements`` with an untested entry for every column of each row of ``rows`` (output indices, of
    outputs that never move), in the order of the rows (then of the columns) as the element test lists them.

    An untested entry has ``mismatch`` false, no p-value and no statistic, and is not ambiguous."""
    if not rows:
        return elements
    from .element_test import ElementResult

    added = [ElementResult(output=model.outputs[i], input=name, mismatch=False, p_value=None, p_value_raw=None,
                           statistic=None, role=model.role(j))
             for i in rows for j, name in enumerate(model.columns)]
    order = {name: i for i, name in enumerate(model.outputs)}
    return sorted(elements + added, key=lambda e: order.get(e.output, len(order)))



def _noise_order(model: PlantModel, options: AnalysisOptions, white: dict) -> dict:
    """The report's ``noise_order`` from the element test's whiteness (row -> Ljung-Box p-value)."""
    from .noise_order import coloured_rows

    return {"na": options.na, "requested": options.na, "max_na": options.max_na,
            "coloured": [model.outputs[i] for i in coloured_rows(white)],
            "p_values": {model.outputs[i]: float(p) for i, p in white.items()}}


class _ElementColour:
    """The unrestricted element fits of ``rows``, their residuals' whiteness and the report's ``noise_order``
    (:func:`detect_unless_coloured`); the fits and the design go on to the element test when white."""

    def __init__(self, model: PlantModel, rows: list, columns: np.ndarray, layout, regressions,
                 options: AnalysisOptions, spread: np.ndarray):
        from .element_test import unrestricted_fits
        from .input_design import InputDesign

        self.design = InputDesign(model, columns, layout.n_lag_u, layout.start, options.collinearity_threshold,
                                  regressions.input_regression)
        self.fits, self.whiteness = unrestricted_fits(rows, self.design, regressions, spread)
        self.noise_order = _noise_order(model, options, self.whiteness)


@dataclasses.dataclass
class Coloured:
    """What :func:`detect_unless_coloured` returns instead of a report: a row's residual is coloured.

    Attributes
    ----------
    noise_order : dict
        As :attr:`AnalysisReport.noise_order` (``coloured`` not empty).
    signals : LoopSignals
        The model run of the data (on the samples used, as :attr:`AnalysisReport.signals`).
    gaps : dict or None
        As :attr:`AnalysisReport.gaps`.
    """

    noise_order: dict
    signals: LoopSignals
    gaps: Optional[dict]


def detect_unless_coloured(model: PlantModel, data: LoggedData, options: AnalysisOptions = AnalysisOptions(), *,
                           signals: Optional[LoopSignals] = None, regressions=None,
                           previous: Optional["AnalysisReport"] = None, candidates=None, detectability: bool = True,
                           settle: bool = True, beside: Optional[Callable[[LoopSignals], None]] = None):
    """:func:`detect`, or only the noise order when a row's element-test residual is coloured.

    The element test's unrestricted fits of every row it tests come first (for ``test_all_rows``, before
    the row test); when a row's residual is coloured (:mod:`mpm_monitor.core.noise_order`) the tests
    are not run and a :class:`Coloured` is returned: :func:`~mpm_monitor.core.pipeline.analyze` would
    discard that detection for one with a larger ``na``.  Otherwise the detection goes on with those
    fits: the report is :func:`detect`'s, the same numbers.  Arguments as :func:`detect`; a method
    other than ``arx`` (no noise order) always detects.

    Returns
    -------
    AnalysisReport or Coloured
    """
    return _guarded(model, data, options, signals, regressions, previous, candidates, detectability,
                    unless_coloured=True, settle=settle, beside=beside)


def check_gap_run(plan, n_logged: int, options, src: str) -> None:
    """Refuse data whose short gaps (at most ``plan.max_gap`` samples, which the model runs through with its
    columns held and the response to their unknown values fitted, :func:`~mpm_monitor.core.signals.segment_signals`)
    miss more samples than the ``n_logged`` samples logged.

    The model's run and that fit grow with the samples run through, not with the log: ``--max-gap 1000000`` on a
    log of 1,000 rows with one gap of a million samples ran out of memory (at 1e8, 23 GB before the kernel
    killed it), where a gap longer than ``max_gap`` splits the data at no cost.  By default (``max_gap`` the
    tests' longest lag) no data the tests accept reaches the bound.

    Raises
    ------
    DataFileError
    """
    short = plan.gap_lengths[plan.gap_lengths <= plan.max_gap]
    through = int(short.sum())
    if through <= n_logged:
        return
    bound = "max_gap" if options.max_gap is not None else "max_gap, by default the tests' longest lag"
    raise DataFileError(f"{src}: {through} samples missing in {short.size} gap{'s' if short.size != 1 else ''} of at "
                        f"most {plan.max_gap} samples ({bound}), more than the {n_logged} logged: the model would run "
                        f"through them with its columns held; expected a max_gap below {int(short.max())} samples (a "
                        f"longer gap splits the data)")


def check_gap_rows(plan, layout, options, src: str, model: PlantModel, notes=()) -> None:
    """Refuse data with gaps whose segments give fewer regression rows than the tests need.

    The tests need ``layout.min_samples`` samples of one contiguous span, that is
    ``min_samples - start`` regression rows; data with gaps must give as many rows from its segments.
    ``model`` names the delay that sets ``max_delay`` (:func:`longest_delay_note`); ``notes`` (the data's: rows
    the reader left out for bad values or spikes, which made gaps too) end the refusal.

    Raises
    ------
    DataFileError
        Naming the rows kept, the segments and the gaps.
    """
    need = layout.min_samples - layout.start
    if plan.rows_kept >= need:
        return
    n_seg, n_gaps = len(plan.segments), plan.gap_lengths.size

    def enough(least) -> bool:     # whether the rows would do for the tests at their least lags
        return plan.rows_kept >= least.min_samples - least.start
    # A row after most gaps: t in other units, or the model's sample time wrong (time_unit_note).  Gaps
    # closer together than the rows a span needs first: too many samples missing for these lags.
    # Rows the reader left out (``notes``) made the gaps themselves: t then advances by more than a sample between
    # the rows kept because rows were left out, not because of the time's unit.
    unit = "" if notes else time_unit_note(plan, model.sample_time)
    span = int(np.median([b - a for a, b in plan.segments]))
    close = "" if unit or span > layout.start else \
        f"; the gaps come too close together: half the spans hold {span} sample{'s' if span != 1 else ''} or fewer"
    raise TooFewSamples(f"{src}: {plan.rows_kept} regression rows from {len(plan.used)} of {n_seg} spans between "
                        f"{n_gaps} gap{'s' if n_gaps != 1 else ''} ({plan.samples_missing} samples missing; a span "
                        f"gives rows after its first {layout.start} samples); the tests with na={options.na}, "
                        f"nb={options.nb}, max_delay={layout.max_delay} need at least {need} rows"
                        + (" (is the sample time right?)" + unit if unit else close)
                        + longest_delay_note(model, options, layout, enough) + "".join(f"; {x}" for x in notes))
