"""The confirmation of a row's located elements, each tested again with the others' responses free.

In a row with two or more located elements, a slow element's mismatch outlives its column's lag
block and can make another element of the row look mismatched.  :func:`_confirm_with_tails` tests
each located element again with the other located columns' blocks extended to their whole tails
(:func:`tail_lags`, :func:`step_response_tail`); :func:`_confirm_given_responses` (the option
``confirm_responses``) with the other elements' whole modelled responses free.  Both only remove
locations of the element test (:mod:`mpm_monitor.core.element_test`).
"""

from __future__ import annotations

import numpy as np

from .arx import lag_matrix, segment_rows
from .element_windows import element_window
from .elements import pulse_response
from .model import PlantModel
from .noise_polynomial import noise_filter
from .response_test import combined_p_value, element_responses, integrating_element, row_response_tests
from .segments import centred_fill, level_groups, run_lag_matrix, run_positions, segment_labels
from .statistics import N_FAMILIES


#: The tail regressors of a located column cover this many time constants of the row's slowest pole.
TAIL_TIME_CONSTANTS = 6.0
#: ... and at most this fraction of the regression rows.
TAIL_MAX_FRACTION = 0.1
#: The tails of all the other located columns of a row together: at most this fraction of the rows
#: (binds from four located elements in a row on; :func:`_confirm_with_tails`).
TAIL_TOTAL_FRACTION = 0.25
#: Bytes of the regressors of one confirmation fit (rows x columns x 8) at most: a longer window's fit takes
#: its last rows only.  Its QR holds a few copies of them: about 1 GB at most.
TAIL_FIT_BYTES = 200 * 2 ** 20


def tail_lags(model: PlantModel, i: int, n_lag: int, n_rows: int) -> int:
    """Lags of a located column's block in the confirmation of row ``i`` (:func:`_confirm_with_tails`).

    The row's largest dead time plus :data:`TAIL_TIME_CONSTANTS` time constants of its slowest decaying
    pole (the model's elements), at least ``n_lag`` and at most :data:`TAIL_MAX_FRACTION` of the
    ``n_rows`` regression rows.  A step-response model has no poles: there the row's longest
    :func:`step_response_tail` stands for them.
    """
    from .discretize import discretize

    if model.is_step_response:
        want = max((step_response_tail(model, i, j) for j in np.flatnonzero(model.present[i])), default=0)
        return int(max(n_lag, min(want, int(TAIL_MAX_FRACTION * n_rows))))
    poles = discretize(model).lag_poles(i)
    if not poles:
        return n_lag
    tau = -1.0 / np.log(max(poles))
    want = int(model.delay_samples[i].max(initial=0)) + int(np.ceil(TAIL_TIME_CONSTANTS * tau))
    return int(max(n_lag, min(want, int(TAIL_MAX_FRACTION * n_rows))))


def step_response_tail(model: PlantModel, i: int, j: int) -> int:
    """Samples after which a step-response element's response to a pulse has all but died out.

    The impulse response ``h_l = s_l - s_(l-1)`` of element (``i``, ``j``) (on a ramp row, less its
    final slope ``h_N``: the part that dies out); the first ``l`` after which the remaining
    ``sum |h_k|`` is at most ``exp(-TAIL_TIME_CONSTANTS)`` of the whole, the step-response analogue
    of :data:`TAIL_TIME_CONSTANTS` time constants after the dead time (a first-order element's
    remaining mass after ``delay + m tau`` is ``exp(-m)``).  In samples; 0 for an absent element.
    """
    h = pulse_response(model.step_response[i, j])
    if model.ramp[i] and h.size:
        h = h - h[-1]
    mass = np.abs(h)[::-1].cumsum()[::-1]                  # mass[l]: sum of |h_k| for k >= l (0-based)
    total = float(mass[0]) if mass.size else 0.0
    if not total > 0:
        return 0
    above = np.flatnonzero(mass > np.exp(-TAIL_TIME_CONSTANTS) * total)
    return int(above[-1]) + 1 if above.size else 0


def _holm_factors(estimates: dict, keys: list) -> dict:
    """Element key -> its Holm factor ``m - l + 1`` (``l`` its rank among the unadjusted p-values of ``keys``)."""
    order = np.argsort(np.array([estimates[k].p_value for k in keys]), kind="stable")
    return {keys[o]: len(keys) - rank for rank, o in enumerate(order)}


def _confirm_given_responses(model: PlantModel, estimates: dict, keys: list, elements: list, alpha: float) -> list:
    """Re-test every located element with the whole modelled responses of its row's other elements free.

    Each located element's p-value given those responses
    (:func:`~mpm_monitor.core.response_test.given_other_responses`, computed with its row's tests) is
    adjusted at its Holm step; an element that no longer rejects is not located.  Its ``p_value`` is
    the larger of the two.  ``elements`` is updated in place.

    A slow or integrating element's mismatch outlives its column's lag block, and in closed loop its
    remainder correlates with another column's lags and modelled response: a well-modelled element of
    the same row was located through it, sometimes alone (an integrator's gain error made the row's
    well-modelled integrating disturbance element the only one located in 4 of 8 probe runs).  Most of
    that remainder is the mismatched element's own modelled response, which this test leaves free.
    But the controller also moves the other columns against the element's own mismatch, so their
    responses carry part of it, and true elements are dropped too: the option
    (``AnalysisOptions.confirm_responses``) is off by default.

    Returns
    -------
    list of str
        A warning for each element no longer located.
    """
    names = model.columns
    by_key = {(model.outputs.index(e.output), names.index(e.input)): e for e in elements}
    factor = _holm_factors(estimates, keys)
    warnings = []
    for k in keys:
        e, given = by_key[k], estimates[k].given_responses
        if not e.mismatch or given is None:
            continue
        p = min(1.0, N_FAMILIES * factor[k] * given) if np.isfinite(given) else 1.0
        e.p_value = max(e.p_value, p)
        if not p < alpha:
            e.mismatch = False
            warnings.append(f"row {e.output}: element ({e.output}, {e.input}) is not located: its test rejects "
                            f"(p={N_FAMILIES * factor[k] * estimates[k].p_value:.2g}) but not with the modelled "
                            f"responses of the row's other elements free (p={p:.2g}): another element's mismatch may "
                            f"reach it")
    return warnings


def _confirm_with_tails(model, rows, design, regressions, options, estimates, keys, elements,
                        output_spread=None) -> list:
    """Re-test the located elements of every row with two or more, each given the others' whole tails.

    The ARX of a row holds ``n_lag`` lags of every column.  A located element's ``Delta_ij`` of a slow
    element lasts far longer; in closed loop the part beyond ``n_lag`` correlates with the other
    columns' lags and can make one of them look mismatched too (a time-constant error of a slow
    element made a well-modelled element of the same row "located" at ``p`` ~ 1e-7).  So each located
    element of such a row is tested again with the blocks of the row's other located columns extended
    to :func:`tail_lags` lags (nuisance: under "no mismatch" of the element tested they are free, so
    the test keeps its level), at its Holm step's level; an element that no longer rejects is not
    located (its ``p_value`` is the larger of the two).  ``elements`` is updated in place.  No tail
    carries an integrating element's gain error (its response never dies out), so the responses of
    the other located integrating elements (lags 0 .. na, for any ``A(q)``) are free beside the test too.

    When that drops every located element of the row, the free tails (hundreds of lags each) stand in
    for one another: the row holds a mismatch among these columns, which each column's own test
    showed, but the tails cannot attribute it.  Then the row is confirmed step by step instead: the
    element with the smallest unadjusted p-value is kept, and each next one (in the order of their
    p-values) is tested with the tails of the elements kept so far only, and kept when it rejects.
    Such rows are named in a warning.  Only removes locations of the Holm-adjusted test.

    A window so long that a fit's regressors would exceed :data:`TAIL_FIT_BYTES` is confirmed on its last
    rows only, and a warning says how many.

    Data with gaps: the fit takes the regression rows whose tails stay inside their run of segments
    (:class:`~mpm_monitor.core.segments.GapSegments`: the model runs through a short gap with its columns
    held, or at their logged values where a segment left out or a spike has them, and a tail reads them so,
    :func:`~mpm_monitor.core.segments.run_lag_matrix`), with a free level
    per level group (the prediction error is centred over each: a run of segments the model runs through for a
    row without an integrating element, else a segment, :func:`~mpm_monitor.core.segments.level_groups`).  No
    row's own lags or tested lags reach across a gap.

    Returns
    -------
    list of str
        The warnings of the rows confirmed step by step or on their last rows.
    """
    from .arx import SharedBlockRegression

    segments = getattr(regressions, "segments", None)
    nb, alpha, na = options.nb, options.alpha, options.na
    names = model.columns
    by_key = {(model.outputs.index(e.output), names.index(e.input)): e for e in elements}
    factor = _holm_factors(estimates, keys)
    u = np.asarray(regressions.u, dtype=float)
    d = np.asarray(regressions.d, dtype=float)
    n_lag, testable = design.n_lag, design.testable
    start0 = regressions.layout.start
    u_c = u - u.mean(axis=0)
    d_c = d - d.mean(axis=0)
    # The known columns inside the gaps (a segment left out, a spike) as u_c is: the tails and responses run on them.
    segments = centred_fill(segments, u.mean(axis=0))
    # With gaps: the regression rows of every segment, and each one's place on its run's sample grid (a tail
    # reads the columns held through the short gaps, as the model runs, segments.run_lag_matrix).
    place = None if segments is None else run_positions(start0, segments)
    n_rows = u.shape[0] - start0 if segments is None else place.size
    stepwise = []
    for i in rows:
        located = [j for j in testable if by_key[(i, j)].mismatch]
        if len(located) < 2:
            continue
        tail = tail_lags(model, i, n_lag, n_rows)
        # Many located columns (a row whose model is wrong throughout): their tails together at most
        # TAIL_TOTAL_FRACTION of the rows, or the fits become as wide as the record (and take minutes).
        budget = int(TAIL_TOTAL_FRACTION * n_rows)
        if (len(located) - 1) * tail > budget:
            tail = max(n_lag, budget // (len(located) - 1))
        if tail <= n_lag:
            continue
        start = max(start0, tail)
        # The rows of the fit: without gaps from sample ``start`` on; with gaps, the regression rows whose tails
        # stay inside their run.
        keep = None if segments is None else place >= tail
        n_fit = u.shape[0] - start if segments is None else int(keep.sum())
        # A long window (days of samples) would make the fit's regressors as long as the record and hundreds of
        # columns wide: gigabytes.  Its last rows stand for it then, as many as TAIL_FIT_BYTES holds.
        width = (len(located) - 1) * tail + (len(testable) - len(located) + 1) * n_lag + na + (na + 1) * len(located)
        most = max(TAIL_FIT_BYTES // (8 * width), 1)
        if n_fit > most:
            stepwise.append(f"row {model.outputs[i]}: the confirmation of its located elements with the others' slow "
                            f"tails used the last {most} of its {n_fit} regression rows (its regressors "
                            f"{width} columns wide held within {TAIL_FIT_BYTES // 2 ** 20} MB)")
            if segments is None:
                start = u.shape[0] - most
            else:
                keep[:np.flatnonzero(keep)[-most]] = False
        if keep is not None and not keep.any():
            continue
        di = d[:, i] - d[:, i].mean()
        # An integrating element's gain error never dies out: no tail carries it, its response does.
        responses = element_responses(model, i, [k for k in located if integrating_element(model, i, k)], u_c,
                                      segments)
        levels = None
        if segments is None:
            def lagged(x, lags, column=None):
                return lag_matrix(x, lags, start)
            target = di[start:]
        else:
            def lagged(x, lags, column=None):
                return run_lag_matrix(x, lags, start0, segments, column)[keep]
            target = segment_rows(di, start0, segments)[keep]
            # d is centred over each level group (a run the model runs through, or a segment: level_groups): a free
            # level per group here too, or the tails' own levels, which d no longer has, would stay in the residual.
            labels = segment_labels(start0, segments)
            groups = level_groups(segments, not model.integrating_outputs[i])
            labels = (labels if groups is None else groups[labels])[keep]
            levels = (labels[:, None] == np.unique(labels)[None, :]).astype(float)
        own = -lagged(di, range(1, na + 1)) if na else None
        response_lags = {k: lagged(x, range(na + 1)) for k, x in responses.items()}

        def confirmed(j, given):
            """Holm-adjusted p-value of element (i, j) with the tails of the columns ``given``."""
            sizes = [tail if (k in given and k != j) else n_lag for k in testable]
            X = np.hstack([lagged(u_c[:, k], range(1, size + 1), k) for k, size in zip(testable, sizes)])
            free = [response_lags[k] for k in given if k != j and k in response_lags] \
                + ([] if levels is None else [levels])
            extra = np.hstack(free) if free else None
            nuisance = [m for m in (own, extra) if m is not None]
            fit = SharedBlockRegression(X, sizes).fit(target, np.hstack(nuisance) if nuisance else None)
            if output_spread is not None:
                fit.set_output_spread(output_spread[i])
            test = fit.test_blocks_zero([testable.index(j)], element_window(model, i, j, nb, options.element_window))
            response = None
            if estimates[(i, j)].response is not None:
                a = noise_filter(fit, na)[0]
                # With gaps the fit's rows are those ``keep`` picks among the segments' regression rows.
                response = row_response_tests(model, i, fit, testable, X, sizes, u_c, d_c,
                                              start if segments is None else start0, na, segments, columns=[j],
                                              a=a, extra=extra, rows=keep).get(j)
            p_raw = combined_p_value(test.p_value, None if response is None else response.p_value)
            return min(1.0, N_FAMILIES * factor[(i, j)] * p_raw) if np.isfinite(p_raw) else 1.0

        decided = {j: confirmed(j, located) for j in located}
        if not any(p < alpha for p in decided.values()):
            by_strength = sorted(located, key=lambda j: estimates[(i, j)].p_value)
            kept = [by_strength[0]]
            decided = {by_strength[0]: by_key[(i, by_strength[0])].p_value}
            for j in by_strength[1:]:
                decided[j] = confirmed(j, kept)
                if decided[j] < alpha:
                    kept.append(j)
            stepwise.append(f"row {model.outputs[i]}: its located elements "
                            f"{', '.join(names[j] for j in by_strength)} cannot each be confirmed given the others' slow "
                            f"tails; confirmed step by step from the strongest: {', '.join(names[j] for j in kept)}")
        for j, p in decided.items():
            e = by_key[(i, j)]
            e.p_value = max(e.p_value, p)
            if not p < alpha:
                e.mismatch = False
    return stepwise
