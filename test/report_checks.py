"""Comparison of two analysis reports: identical decisions, numbers to a relative tolerance.

Shared by the tests that check a fast path against its reference (test_fast_paths: the Gram-based
batch path against QR; test_incremental: the sliding-window analyzer against the batch analysis).
"""

import math

import numpy as np

TOL = 1e-8
#: A p-value of 0 (the survival function underflowed) matches only 0 or a p-value below this.
P_UNDERFLOW = 1e-300


def _close(a, b, what, tol=TOL):
    a, b = float(a), float(b)
    if a == b or (math.isnan(a) and math.isnan(b)):
        return
    assert abs(a - b) <= tol * max(abs(a), abs(b), 1.0), f"{what}: {a!r} vs {b!r}"


def _close_log_p(a, b, what):
    if a is None or b is None:
        assert a is None and b is None, what
        return
    if a == 0.0 or b == 0.0:      # underflow: the other side must have underflowed too (or nearly)
        assert max(a, b) < P_UNDERFLOW, f"{what}: {a!r} vs {b!r} (one p-value is 0, the other is not tiny)"
        return
    _close(math.log(a), math.log(b), f"log {what}")


def _close_vec(a, b, what, tol=TOL):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape, what
    scale = max(np.abs(b).max(initial=0.0), 1e-300)
    assert np.all(np.abs(a - b) <= tol * scale), f"{what}: max difference {np.abs(a - b).max()} of {scale}"


def assert_reports_match(new, ref):
    """Decisions identical, numbers to ``TOL`` (relative; p-values compared on their logarithm)."""
    assert new.flagged_rows == ref.flagged_rows
    assert new.located_elements == ref.located_elements
    assert new.ambiguous_elements == ref.ambiguous_elements
    assert new.collinear_groups == ref.collinear_groups
    assert new.warnings == ref.warnings
    assert new.samples == ref.samples
    _close(new.max_variance_inflation, ref.max_variance_inflation, "max VIF")
    assert len(new.rows) == len(ref.rows), f"rows: {len(new.rows)} vs {len(ref.rows)}"
    for a, b in zip(new.rows, ref.rows):
        assert (a.output, a.mismatch, a.df) == (b.output, b.mismatch, b.df)
        _close(a.rsi, b.rsi, f"rsi {b.output}")
        _close(a.statistic, b.statistic, f"row F {b.output}")
        _close_log_p(a.p_value_raw, b.p_value_raw, f"row p {b.output}")
        _close_log_p(a.p_value, b.p_value, f"row adjusted p {b.output}")
        _close(a.fit_percent, b.fit_percent, f"row fit {b.output}")
    _close(new.overall_rsi, ref.overall_rsi, "overall rsi")
    _close_vec(new.sigma_max, ref.sigma_max, "sigma_max")
    _close_vec(new.row_gains, ref.row_gains, "row gains")
    _close_vec(np.abs(new.sdelta_response), np.abs(ref.sdelta_response), "|S_Delta|")
    assert len(new.elements) == len(ref.elements), f"elements: {len(new.elements)} vs {len(ref.elements)}"
    for a, b in zip(new.elements, ref.elements):
        key = f"element ({b.output}, {b.input})"
        assert (a.output, a.input, a.mismatch, a.ambiguous, a.ambiguous_with, a.delay, a.kind) == \
            (b.output, b.input, b.mismatch, b.ambiguous, b.ambiguous_with, b.delay, b.kind), key
        if b.statistic is not None:
            _close(a.statistic, b.statistic, f"F {key}")
        _close_log_p(a.p_value_raw, b.p_value_raw, key)
        _close_log_p(a.p_value, b.p_value, f"adjusted {key}")
        _close_vec(a.b, b.b, f"B {key}")
    assert len(new.arx_tables) == len(ref.arx_tables), f"ARX tables: {len(new.arx_tables)} vs {len(ref.arx_tables)}"
    for a, b in zip(new.arx_tables, ref.arx_tables):
        assert a.output == b.output and a.delay == b.delay, f"ARX table {b.output}"
        _close_vec(a.a + sum(a.b.values(), []), b.a + sum(b.b.values(), []), f"ARX table {b.output}")
        _close(a.fit_percent, b.fit_percent, f"ARX table fit {b.output}")
