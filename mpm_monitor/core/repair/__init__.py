"""Trace the prediction error to the effect the model lacks, re-estimate it, and show the gain.

After the analysis has located mismatched elements (paper section 2.2), this package answers the
control engineer's next questions (paper section 4, "type and severity" of each mismatch):

1. **Residual.**  ``d = y - Phat u`` of the model as given (paper eq. 9: ``d = Delta u + v``).
2. **Re-estimate.**  For each output row ``i`` with located elements ``J``, the elements
   ``(K_ij, tau_ij, theta_ij), j in J`` are fitted jointly to
   ``z_i = y_i - sum_{j not in J} Phat_ij u_j`` (the rest of the row held fixed) by a
   prediction-error method with an AR noise model (Ljung, *System Identification*, 2nd ed., 1999,
   sections 7.2 and 13.4)::

       e(k) = A(q) [ z_i(k) - sum_{j in J} G_j(q; K_j, a_j, L_j) u_j(k) - c' phi(k) ]
       G_j  = K_j (1 - a_j) q^{-L_j} / (1 - a_j q^{-1}),   a_j = exp(-T / tau_j)

   ``A(q) = 1 + alpha_1 q^-1 + ... + alpha_p q^-p`` whitens the coloured disturbance (the paper's
   ``v = w / (1 - 0.95 q^-1)`` plus white measurement noise), which makes the estimate consistent
   in closed loop where ``u`` is correlated with ``v`` (Ljung section 13.4, the "direct approach").
   ``phi`` holds the free responses of the row's states (the data may start mid-operation) and an
   offset.  The gains and ``c`` enter linearly and are eliminated by variable projection (Golub and
   Pereyra, 1973); the poles ``a_j`` are found by ``scipy.optimize.least_squares`` with ``A(q)``
   held, alternating with a least-squares fit of ``A(q)`` to the output error (generalized least
   squares, Ljung section 10.2); the input lag ``L_j`` (delay plus one sample for a lagged
   element) by a coordinate search on the integer grid around the model's value.
3. **Kind.**  On the whole record, every parameter of a located element is tested against the
   model's value by a likelihood-ratio test: the row is refitted with that parameter held and
   ``n ln(SSR_held / SSR_free)`` compared with chi-square(1) (Ljung section 16.5); the delay by
   its profile over the lag grid.  A parameter changed when the test rejects at
   ``1 - confidence_level`` *and* the change exceeds ``min_relative_change``.  The kind follows:
   one changed parameter -> gain, time_constant or delay; several -> mixed; a model gain of 0 with
   a significant fitted gain -> missing; nothing -> unknown (the element is kept).  The likelihood
   ratio, unlike a Wald test on the Jacobian, does not depend on the parametrization, which
   matters along the ridge where gain and time constant trade off (inputs that move together).
   The verdict's ``confidence`` is ``min over the tests of 1 - min(p/alpha, alpha/p)``: 0 when a
   p-value sits on the threshold, near 1 when every test is clear.
4. **Repair and validation.**  Only the changed parameters are refitted (all three for a missing
   element), on the first ``1 - holdout_fraction`` of the record; intervals at
   ``confidence_level`` come from the Jacobian of the full residual (``cov = s^2 (J'J)^-1``) for
   gain and time constant, from the profile statistic for the delay.  The repair is accepted only
   when the row's RMS prediction error on the held-out last part is lower than with the model as
   given; then it is refitted on the whole record.
5. **Unexplained disturbances.**  On every output, the (repaired) residual is tested for a level
   shift (sup-Wald test over the break date, Andrews 1993, p-values from the approximation of
   Estrella 2003) and for a linear drift (Wald test), each in a regression with AR(p) terms that
   absorb the coloured noise.  These are reported and never turned into element changes; when one
   shows on a repaired row, that row is re-estimated with the step (ramp) as a nuisance regressor
   so that it does not bias the elements.

Where each step lives:

- :mod:`.options`: :class:`RepairOptions` and their check, the test levels they fix.
- :mod:`.fit`: the prediction-error fit of one row (step 2), model-free: the row problem, the
  search over lags, poles and noise model, the lag profiles.
- :mod:`.row`: from a row of the model to its fit and back (parameters in seconds, intervals).
- :mod:`.classify`: the likelihood-ratio tests and the kinds (step 3).
- :mod:`.refit`: the fit of what changed, and the refit on the whole record (step 4).
- :mod:`.disturbance`: the step and drift tests of a residual (step 5).
- :mod:`.model_repair`: :func:`repair_model`, which runs the steps row by row, validates on the
  held-out part and assembles the :class:`RepairResult` (:mod:`.result`).
"""

from .disturbance import sup_wald_p_value, unexplained_disturbance
from .model_repair import repair_model
from .options import KINDS, RepairOptions, check_repair_options
from .result import RepairResult

__all__ = ["KINDS", "RepairOptions", "RepairResult", "check_repair_options", "repair_model",
           "sup_wald_p_value", "unexplained_disturbance"]
