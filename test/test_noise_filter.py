"""The row's noise polynomial where the element fit cannot tell the plant from the controller.

In a loop whose setpoints never move and that has no dither, the inputs move only with the
controller's feedback of the noise; their lags and the prediction error's own lags are then nearly
collinear, and the element fit's own coefficients come out as 1e4 to 1e11.  The detectable gain
changes and the whole-response test must not filter by such an ``A(q)``
(:func:`mpm_monitor.core.noise_polynomial.noise_filter`).  The Monte-Carlo figures are
``python -m bench.detectability --still``.
"""

import dataclasses

import numpy as np
import pytest

from mpm_monitor.core.analysis import AnalysisOptions, detect
from mpm_monitor.core.arx import SharedBlockRegression
from mpm_monitor.core.gram_fits import GramBlockRegression, GramFit
from mpm_monitor.core.noise_polynomial import MAX_NOISE_FILTER_SE, noise_filter
from mpm_monitor.sim.cases import paper_case
from mpm_monitor.sim.closed_loop import run_closed_loop


def _problem(rng, collinear: bool, n: int = 1500, p: int = 6, po: int = 3):
    X = rng.standard_normal((n, p))
    own = rng.standard_normal((n, po))
    if collinear:            # the own columns a combination of the common ones, but for a trace
        own = X @ rng.standard_normal((p, po)) + 1e-3 * own
    y = X[:, 0] * 0.3 + own @ np.array([0.5, -0.2, 0.1])[:po] + rng.standard_normal(n)
    return X, own, y


def _fits(X, own, y):
    n, p = X.shape
    shared = SharedBlockRegression(X, [p]).fit(y, own)
    gram = GramFit(GramBlockRegression(X.T @ X, [p]), X.T @ own, own.T @ own, X.T @ y, own.T @ y, float(y @ y),
                   float(y.sum()), n, max_condition=1e30)
    return shared, gram


@pytest.mark.parametrize("collinear", [False, True])
def test_own_only_coefficients_and_standard_errors_equal_numpy_least_squares(collinear):
    rng = np.random.default_rng(4)
    X, own, y = _problem(rng, collinear)
    W = np.column_stack([X, own])
    theta, *_ = np.linalg.lstsq(W, y, rcond=None)
    resid = y - W @ theta
    sigma2 = resid @ resid / (W.shape[0] - W.shape[1])
    se_ref = np.sqrt(np.diag(sigma2 * np.linalg.inv(W.T @ W)))[X.shape[1]:]
    own_only_ref, *_ = np.linalg.lstsq(own, y, rcond=None)
    for fit in _fits(X, own, y):
        np.testing.assert_allclose(fit.own_only_theta(), own_only_ref, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fit.own_standard_errors(), se_ref, rtol=1e-5 if collinear else 1e-9)


def test_the_fits_own_coefficients_unless_they_are_undetermined():
    rng = np.random.default_rng(5)
    for fit in _fits(*_problem(rng, collinear=False)):
        a, undetermined = noise_filter(fit)
        assert undetermined is None
        np.testing.assert_array_equal(a, fit.own_theta())
        assert np.max(fit.own_standard_errors()) < 0.1
    for fit in _fits(*_problem(rng, collinear=True)):
        a, undetermined = noise_filter(fit)
        assert undetermined > MAX_NOISE_FILTER_SE
        assert undetermined == pytest.approx(np.max(fit.own_standard_errors()))
        np.testing.assert_array_equal(a, fit.own_only_theta())
        a2, _ = noise_filter(fit, na=2)                    # the first na of the own columns
        np.testing.assert_array_equal(a2, fit.own_only_theta()[:2])


def test_a_still_loop_reports_no_detectable_change_below_an_error_it_misses():
    """Case 3.1 with every setpoint held at 0 and no dither, the plant's (y1, u1) gain 30 % above the model's.

    Nothing is located; the element fit's own coefficients were about 1e5 there, and the reported
    detectable gain change of (y1, u1) was 1.9e-5 (printed "0 %"), with no experiment recommended.
    """
    case = paper_case("3.1")
    model = case.model
    gain = np.array(model.gain, dtype=float)
    gain[0, 0] *= 1.3
    plant = dataclasses.replace(model, gain=gain)
    n = 3000
    log = run_closed_loop(plant, model, n, seed=1, mpc=case.mpc, excitation=case.excitation,
                          disturbance=case.disturbance, setpoints=np.zeros((n, model.n_outputs)))
    rep = detect(model, log.as_logged_data(), AnalysisOptions(repair=False))
    assert ("y1", "u1") not in [tuple(e) for e in rep.located_elements]
    values = {(e.output, e.input): e.detectable_gain_change for e in rep.elements}
    # Every row's inputs move only with the feedback (a square loop): no value is claimed, the rows are
    # named, and the experiment is recommended, its why saying so.
    assert values[("y1", "u1")] is None
    assert all(v is None for v in values.values())
    warning = [w for w in rep.warnings if "own lags are nearly collinear here" in w]
    assert len(warning) == 1 and warning[0].startswith("rows y1, y2, y3:")
    assert rep.experiment is not None and "own lags are nearly collinear in rows y1, y2, y3" in rep.experiment.why
    # Its inputs barely move, so half their spread is too small a dither: the why gives the multiple that is
    # predicted to do (10 times, for 10,150 samples: in a check of 4 seeds that dither gave a largest
    # detectable change of 0.21 to 0.22, and a 20 % error of the hardest element was located in 20 of 20).
    import re

    beyond = re.search(r"A dither (\S+) times as large \((u1 \S+, u2 \S+, u3 \S+)\) is predicted to reach it in "
                       r"(\d+) samples", rep.experiment.why)
    assert beyond is not None and 1.0 < float(beyond.group(1)) <= 100.0 and int(beyond.group(3)) <= 20000


def test_first_order_values_of_a_still_loop_are_not_tiny(monkeypatch):
    """The same loop with its rows valued (as ``bench.detectability --first-order`` does): from the own lags'
    noise polynomial, no element's first-order value is below the 30 % error that went unseen."""
    import mpm_monitor.core.detectability as det

    monkeypatch.setattr(det, "undetermined_rows", lambda noise: [])
    case = paper_case("3.1")
    model = case.model
    gain = np.array(model.gain, dtype=float)
    gain[0, 0] *= 1.3
    n = 3000
    log = run_closed_loop(dataclasses.replace(model, gain=gain), model, n, seed=1, mpc=case.mpc,
                          excitation=case.excitation, disturbance=case.disturbance,
                          setpoints=np.zeros((n, model.n_outputs)))
    rep = detect(model, log.as_logged_data(), AnalysisOptions(repair=False))
    values = [e.detectable_gain_change for e in rep.elements]
    assert all(v is not None for v in values)
    assert min(values) > 0.3
