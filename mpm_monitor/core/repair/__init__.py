"""Trace the prediction error to the effect the model lacks, re-estimate it, and show the gain.

After the analysis has located mismatched elements (paper section 2.2), this package answers the
control engineer's next questions (paper section 4, "type and severity" of each mismatch):

1. **Residual.**  ``d = y - Phat u`` of the model as given (paper eq. 9: ``d = Delta u + v``).
2. **Re-estimate.**  For each output row ``i`` with located elements ``J``, the elements
   ``j in J`` are fitted jointly to ``z_i = y_i - sum_{j not in J} Phat_ij u_j`` (the rest of the
   row held fixed, columns ``u`` being the inputs and measured disturbances) by a prediction-error
   method with an AR noise model ``A(q)`` of order ``noise_order`` (4; :func:`~mpm_monitor.core.pipeline.analyze`
   gives it the tests' ``na`` where that was raised, :func:`~mpm_monitor.core.pipeline.repair_noise_order`) (Ljung,
   *System Identification*, 2nd ed., 1999, sections 7.2 and 13.4)::

       e(k) = A(q) [ z_i(k) - sum_{j in J} G_j(q) u_j(k) - c' phi(k) ]
       G_j  = q^{-L_j} (K_j G_a(q; poles_j) + K_j lead_j G_b(q; poles_j))

   each element in its structure (:mod:`.forms`): ``G_a``, ``G_b`` the zero-order-hold samplings of
   ``1 / den(s)`` and ``s / den(s)``, ``den(s)`` its lag(s) ``(tau s + 1)(tau2 s + 1)`` (times ``s``
   for an integrator), the poles ``a = exp(-T / tau)``; the first-order element is
   ``K (1 - a) q^-L / (1 - a q^-1)``.  An element the model has keeps its declared structure; one it
   lacks is fitted first order, with a second lag where a likelihood-ratio test says the data call
   for it; an element of a step-response model in the parametric form the data choose (first
   order, second order, second order with a lead; integrating on a ``ramp`` output) and written back
   as its sampled step response of the same length.
   ``A(q) = 1 + alpha_1 q^-1 + ... + alpha_p q^-p`` whitens the coloured disturbance (the paper's
   ``v = w / (1 - 0.95 q^-1)`` plus white measurement noise), which makes the estimate consistent
   in closed loop where ``u`` is correlated with ``v`` (Ljung section 13.4, the "direct approach").
   ``phi`` holds the free responses of the row's states (the data may start mid-operation; every
   pole of the held elements, ``k a^k`` for a repeated one) and an offset.  The gains, the lead
   coefficients ``K lead`` and ``c`` enter linearly and are eliminated by variable projection
   (Golub and Pereyra, 1973); the poles are found by a bounded nonlinear least squares
   (:func:`~mpm_monitor.core.repair.lsq.least_squares_bounded`, a trust-region Levenberg-Marquardt
   method, numpy only) with ``A(q)`` held, alternating with a least-squares fit of ``A(q)`` to the
   output error (generalized least squares, Ljung section 10.2); the input lag ``L_j`` (the delay
   plus one sample for a strictly proper element) by a coordinate search on the integer grid
   around the model's value.
3. **Kind.**  On the whole record, every parameter of a located element is tested against its
   reference (the model's value; for a step-response element, the parametric form of its old
   response) by a likelihood-ratio test: the row is refitted with that parameter held and
   ``n ln(SSR_held / SSR_free)`` compared with chi-square (Ljung section 16.5); the shape (every
   lag and the lead) is held at once, with as many degrees of freedom; the delay by its profile
   over the lag grid.  A parameter changed when the test rejects at ``1 - confidence_level`` *and*
   the change exceeds ``min_relative_change``.  The kind follows: one changed parameter -> gain
   (an integrator's gain too), time_constant (any lag or the lead) or delay; several -> mixed; an
   element the model lacks with a significant fitted gain -> missing; nothing -> unknown (the
   element is kept).  The parameters judged unchanged are then held together; while that joint
   test rejects, the held parameter whose release fits best (Akaike's criterion) is freed too, and a
   warning says so, naming any other release within 2 of that criterion.  The likelihood ratio,
   unlike a Wald test on the Jacobian, does not depend on the parametrization, which matters along
   the ridge where gain and time constant trade off (inputs that move together).  The verdict's
   ``confidence`` is ``min over the tests of 1 - min(p/alpha, alpha/p)``: 0 when a p-value sits on
   the threshold, near 1 when every test is clear.
4. **Repair and validation.**  Only the changed parameters are refitted (all of them for a missing
   element), on the first ``1 - holdout_fraction`` of the record; intervals at
   ``confidence_level`` come from the Jacobian of the full residual (``cov = s^2 (J'J)^-1``) for
   gain, time constants and lead, from the profile statistic for the delay.  The repair is
   accepted when the row's RMS simulation error on the held-out last part, about its level (the
   mean of the fit part: a level is no element's to explain, and on an integrating output it is
   arbitrary), is lower than with the model as given, or (option ``holdout_one_step``, on by default)
   when its RMS one-step error there under its own AR noise model is significantly lower while the
   simulation error rises neither significantly nor by more than ``holdout_tolerance`` (5 %) of the
   model's, on a loop that did not diverge (:mod:`.holdout`, :mod:`.validation`); then it is refitted on
   the whole record.
   A step-response element whose gain or delay alone changed keeps its old response, scaled and
   shifted; one whose shape changed takes the sampled response of its fitted form.
5. **Unexplained disturbances.**  On every output, the (repaired) residual is tested for a level
   shift (sup-Wald test over the break date, Andrews 1993, p-values from the approximation of
   Estrella 2003) and for a linear drift (Wald test), each in a regression with AR(p) terms that
   absorb the coloured noise.  These are reported and never turned into element changes; when one
   shows on a repaired row, that row is re-estimated with the step (ramp) as a nuisance regressor
   so that it does not bias the elements.

Where each step lives:

- :mod:`.options`: :class:`RepairOptions` and their check, the test levels they fix.
- :mod:`.forms`: the structure of a fitted element (lags, lead, integrator), its sampled basis,
  the parametric form of a step response and the write-back into the model's structure.
- :mod:`.fit`: the prediction-error fit of one row (step 2), model-free: the row problem, the
  search over lags, poles and noise model, the lag profiles.
- :mod:`.lsq`: the bounded nonlinear least-squares solver of the pole fits (of :mod:`.fit` and of
  the parametric form of a step response in :mod:`.forms`).
- :mod:`.row`: from a row of the model to its fit and back (parameters in seconds, intervals).
- :mod:`.classify`: the likelihood-ratio tests and the kinds (step 3).
- :mod:`.refit`: the fit of what changed, and the refit on the whole record (step 4).
- :mod:`.disturbance`: the step and drift tests of a residual (step 5).
- :mod:`.holdout`: the statistics of the held-out check (one-step errors, the test of a rise).
- :mod:`.residual_tests`: the tests of step 5 on every output as one family, and their report.
- :mod:`.validation`: the held-out check of a row's repair (step 4).
- :mod:`.record`: the record as every step reads it (the data, the model's signals, the split).
- :mod:`.explained`: the located elements another located element of their row explains.
- :mod:`.model_repair`: :func:`repair_model`, which runs the steps row by row, validates on the
  held-out part and assembles the :class:`RepairResult` (:mod:`.result`).
"""

from .disturbance import sup_wald_p_value, unexplained_disturbance
from .explained import JointClassification, explained_elements
from .model_repair import repair_model
from .options import KINDS, RepairOptions, check_repair_options
from .residual_tests import DisturbanceTests, disturbance_tests
from .result import RepairResult

__all__ = ["KINDS", "DisturbanceTests", "JointClassification", "RepairOptions", "RepairResult", "check_repair_options",
           "disturbance_tests", "explained_elements", "repair_model",
           "sup_wald_p_value", "unexplained_disturbance"]
