"""Which leading lags the element test of one element tests.

:func:`element_window`: for an element the model has, its lags up to where the model element's
response has set in (:func:`element_onset`) plus ``nb - 1``; all of them for an element the model
lacks and for a measured disturbance's.  The element test, its confirmation and the detectability
read it.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from .model import PlantModel


#: An element's response has set in at the first lag where its impulse response reaches this fraction of
#: its largest absolute value (:func:`element_window`).
ONSET_FRACTION = 0.5
#: Samples of an element's impulse response searched for its onset.
ONSET_HORIZON = 1000


def element_window(model: PlantModel, i: int, j: int, nb: int, window: str = "model") -> Optional[int]:
    """Leading column lags the element test of (i, j) tests (None: all of them).

    ``Delta_ij = P_ij - Phat_ij`` is non-zero from lag ``min(theta_plant, theta_model) + 1`` on,
    and a mismatch shows where the element's own response has set in: for an element the model has
    (:attr:`~mpm_monitor.core.model.PlantModel.present`) the test covers its lags up to the onset
    ``k_on`` (the first lag at which the model element's impulse response reaches
    :data:`ONSET_FRACTION` of its largest absolute value) plus ``nb - 1`` more, and at least the first
    ``theta_model + nb``.  For a first-order element with dead time ``theta`` the impulse response
    is largest at lag ``theta + 1``, so the window is the first ``theta + nb`` lags; a second lag, an
    integrator or a lead that builds up slowly moves the onset later (a short window would see
    almost nothing of such an element, and its later lags, left free, would absorb the mismatch).
    The later lags stay in the fit as nuisance (under "no mismatch" every lag is zero, so the test
    keeps its level); fewer tested lags means more power.  Elements the model does not have have no
    known delay, and a measured disturbance's column is typically slow and step-like (its later
    lags would absorb a wrong gain): all lags are tested for them, as with ``window="full"``.
    """
    if window == "full" or not model.present[i, j] or model.role(j) == "disturbance":
        return None
    return max(int(model.delay_samples[i, j]) + nb, element_onset(model, i, j) + nb - 1)


def element_onset(model: PlantModel, i: int, j: int) -> int:
    """The first lag at which element (i, j)'s impulse response reaches :data:`ONSET_FRACTION` of its peak.

    Kept with the model's sampled elements (:meth:`~mpm_monitor.core.model.PlantModel.discrete_element`),
    so that it is computed once per model and element: every row's element test, its confirmation and
    the detectability ask for it (at 100 outputs x 40 inputs, 8,000 impulse responses of 1,000 samples
    per analysis otherwise).  A copy of the model with the element changed
    (:meth:`~mpm_monitor.core.model.PlantModel.with_element`) computes it again.

    A first-order element ``b z^-(delay+1) / (1 - a z^-1)`` with ``|a| <= 1`` needs no simulation: its
    impulse response is 0 up to lag ``delay``, ``b`` at ``delay + 1`` and then ``a`` times the previous
    value, rounded, which is never larger in magnitude; so its onset is ``delay + 1`` (the value the
    simulation gives, when ``delay + 1`` is inside :data:`ONSET_HORIZON` and the threshold is not 0).
    """
    key = ("onset", i, j)
    cache = model._elements
    if key not in cache:
        el = model.discrete_element(i, j)
        num, den = el.num, el.den
        if num.size == 2 and num[0] == 0 and den.size == 2 and abs(den[1]) <= 1 \
                and el.delay + 1 < ONSET_HORIZON and ONSET_FRACTION * abs(num[1]) > 0:
            cache[key] = el.delay + 1
        else:
            h = np.abs(el.impulse_response(ONSET_HORIZON))
            cache[key] = int(np.flatnonzero(h >= ONSET_FRACTION * h.max())[0]) if h.max() > 0 else 0
    return cache[key]
