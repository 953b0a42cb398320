"""Which parameters of the located elements of a row changed: likelihood-ratio tests and kinds.

On the whole record (the most evidence) the located elements of a row are fitted with gain, shape
(every lag and the lead) and delay free, each in its form (:func:`_fit_free`; the form of an
element the model lacks or of a step-response element chosen by the data, :func:`_choose_forms`),
and every parameter is tested against its reference (the model's value, or the parametric form of a
step response's old response) by refitting the row with that parameter held (:meth:`_FreeFit.hold_statistic`;
``n ln(SSR_held / SSR_free)`` against chi-square, Ljung, *System Identification*, 2nd ed., 1999,
section 16.5; the delay by its profile over the lag grid).  The parameters judged unchanged are
then held together (:func:`_joint_hold`): gain and time constant, or two elements on inputs that
move together, can each stand in for the other, so that each alone looks unchanged while holding
both does not fit.  The kind of each element follows from what changed (:func:`_verdict`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from ..statistics import chi2_tail, normal_isf
from .fit import _ElementSpec, _lag_lr, _RowEstimate, _RowProblem, _TooShort
from .forms import (
    STEP_READ_EXACT,
    STEP_READ_GAIN,
    _LAG_SHIFT,
    _POLE_MIN,
    _fitted_params,
    _Form,
    _form_of,
    _input_lag,
    _missing_ladder,
    _params_of,
    _pole_of,
    _poles_of,
    _public_params,
    _reads_no_lag,
    _step_ladder,
    _step_reference,
    _step_start_form,
    _tau_of,
)
from .options import RepairOptions, _TestSettings
from .result import ElementVerdict
from .row import _default_skip, _element_summary, _estimate_row, _RowData

#: The parameter a test holds at the model's value ("absent": the whole element at gain 0).
_PARAM_OF_TEST = {"gain": "gain", "time_constant": "pole", "delay": "lag", "missing": "absent"}

#: The order in which changed parameters are listed; the first names the kind of a single change.
_TEST_ORDER = ["missing", "gain", "time_constant", "delay"]

#: The pole of a lag of one sample time: a second lag fitted shorter is tried away (:func:`_reduce_vanished_lags`).
_SUBSAMPLE_POLE = math.exp(-1.0)


def _margin(p, alpha):
    """How clearly a p-value lies on its side of ``alpha``: 0 at the threshold, 1 far from it."""
    if p <= 0:
        return 1.0
    return float(1.0 - min(p / alpha, alpha / p))


@dataclasses.dataclass
class _ElementTests:
    """The tests of one located element.

    Attributes
    ----------
    results : dict
        ``{test: [p-value of "unchanged", change large enough]}``; the tests are "missing" for an
        element the model does not have, else "gain", "time_constant" and "delay".
    changed : set of str
        The tests that found a change (significant and large enough, or freed by the joint test).
    margins : dict
        ``{test: margin}`` (see :func:`_margin`).
    """

    results: dict
    changed: set
    margins: dict

    @classmethod
    def of(cls, results: dict, alpha: float) -> "_ElementTests":
        return cls(results=results, changed={k for k, (p, big) in results.items() if p < alpha and big},
                   margins={k: _margin(p, alpha) for k, (p, _) in results.items()})

    def unchanged(self) -> list:
        """The tests that found no change, in test order."""
        return [k for k in self.results if k not in self.changed]


@dataclasses.dataclass
class _Located:
    """A located element as the fit sees it.

    Attributes
    ----------
    form : _Form
        The form it is fitted in: the declared one, or for an element the model lacks and an element
        of a step-response model the one the data call for (:func:`_choose_forms`).
    reference : dict
        The element its changes are measured from, every parametric key (seconds): the model's
        element, the parametric form of a step-response element's old response
        (:func:`~mpm_monitor.core.repair.forms._step_reference`), or gain 0 for a missing element.
    lag : int
        The reference's input lag (samples).
    missing : bool
        The model lacks the element.
    poles : tuple
        The reference's poles.
    declared : _Form or None
        The form of the reference, where the fit's ``form`` has one lag fewer (:func:`_reduce_vanished_lags`;
        ``poles`` are then the declared form's, and ``lag`` the reference's dead time in ``form``); else None.
    hint : int or None
        The element test's estimate of the lag at which the mismatch ``Delta`` acts (samples), where the
        repair was given one: its lag search reaches it (:func:`_free_spec`).
    feedthrough : bool
        The model's own element acts on ``y(k)`` through ``u(k)`` (a lead over one lag, or a pure gain, with no dead
        time: a parametric element whose input lag in its declared form is 0); its lag search starts at 0
        (:func:`_free_spec`).  Kept apart from ``lag``, which a smaller form's reading may bring to 0 for an element
        the model gives none.
    """

    form: _Form
    reference: dict
    lag: int
    missing: bool
    poles: tuple
    declared: Optional[_Form] = None
    hint: Optional[int] = None
    feedthrough: bool = False

    @property
    def shape_form(self) -> _Form:
        """The form whose shape the ``time_constant`` test holds at the reference's: the declared one."""
        return self.declared or self.form

    @property
    def plain_first_order(self) -> bool:
        """Fitted in the first-order form (a lag or none, not integrating), as declared: the form in which a
        pure gain and an element with a lag read their dead time from the input lag differently
        (:func:`~mpm_monitor.core.repair.forms._reads_no_lag`)."""
        return not self.missing and self.declared is None and self.form.first_order and not self.form.integrating

    def held_lag(self, shape_changed: bool, lost_lag: bool = False) -> int:
        """The input lag (samples) that holds the reference's dead time.

        In the first-order form a pure gain acts at the lag of its dead time, an element with a lag one
        sample later (:func:`~mpm_monitor.core.repair.forms._reads_no_lag`).  So for a
        :attr:`plain_first_order` element the lag depends on whether it is held as a pure gain: its
        reference's shape when that is held (``shape_changed`` False); once its shape has changed, a pure
        gain has gained a lag, and an element with a lag is a pure gain when its fit shows no lag
        (``lost_lag``, :meth:`_FreeFit.lost_lag`).  Any other element: ``lag``.
        """
        if not self.plain_first_order:
            return self.lag
        ref_pure = self.reference.get("time_constant", 0.0) <= 0
        dead = self.lag if ref_pure else self.lag - 1           # the dead time, in samples
        pure = lost_lag if shape_changed else ref_pure
        return dead if pure else dead + 1


@dataclasses.dataclass
class _FreeFit:
    """The whole-record fit of a row's located elements with every parameter free.

    Attributes
    ----------
    row : _RowData
    js : list of int
        Column indices of the located elements, sorted (element ``m`` of the fit is ``js[m]``).
    specs : dict
        ``{j: _ElementSpec}`` of the fit: everything free, lags searched around the reference's.
    located : dict
        ``{j: _Located}``: the form and the reference of each element.
    problem : _RowProblem
    est : _RowEstimate
    settings : _TestSettings
        The tests' settings (:meth:`lost_lag` tests at their ``alpha``).
    widened : dict
        ``{j: (first, last)}``: the lag ranges :func:`_widen_lag_ranges` widened (input lags, samples),
        which the refits of an element in another form keep (:func:`_refit_element`).
    """

    row: _RowData
    js: list
    specs: dict
    located: dict
    problem: _RowProblem
    est: _RowEstimate
    settings: _TestSettings
    widened: dict = dataclasses.field(default_factory=dict)
    _lost: dict = dataclasses.field(default_factory=dict, repr=False)
    _reference_stat: dict = dataclasses.field(default_factory=dict, repr=False)

    def lost_lag(self, m: int) -> bool:
        """Whether element ``m``, a :attr:`_Located.plain_first_order` element whose reference has a lag, was
        fitted without one: its fitted pole reads as no lag (:func:`~mpm_monitor.core.repair.forms._reads_no_lag`),
        or holding it at no lag (the pole at its bound, the same input lag) does not fit significantly worse
        (likelihood ratio, one degree of freedom, at the settings' ``alpha``).  A lag well under a sample is
        not told from none by the data: the pole's reading alone (at ``2 _POLE_MIN``, a lag of ``T / 8.5``)
        read an element that the data show as a pure gain as a lag of ``T / 8`` one sample earlier."""
        if m not in self._lost:
            loc = self.located[self.js[m]]
            poles = self.est.fit.poles[self.problem.slices[m]]
            lost = False
            if (loc.plain_first_order and loc.reference.get("time_constant", 0.0) > 0 and len(poles)
                    and self.specs[self.js[m]].pole_free):
                lost = _reads_no_lag(float(poles[0]))
                if not lost:
                    stat = self.hold_statistic({m: {"no_lag"}}, self.settings.options)
                    lost = float(chi2_tail(stat, 1)) >= self.settings.alpha
            self._lost[m] = lost
        return self._lost[m]

    @property
    def lag_orig(self) -> dict:
        """``{j: input lag of the reference}`` (samples)."""
        return {j: loc.lag for j, loc in self.located.items()}

    def hold_statistic(self, holds: dict, options: RepairOptions) -> float:
        """Likelihood-ratio statistic of holding parameters of located elements at their references.

        The row is refitted with, for each element index ``m`` in ``holds``, the parameters named
        in ``holds[m]`` ("gain", "pole": the shape, every lag and the lead; "lag", or "absent": no
        effect at all) held at the reference's values, or "no_lag": a first-order element's pole held at its
        bound (no lag) at its fitted input lag, the other lags at their optimum and
        everything else free; the statistic is ``n ln(SSR_held / SSR_free)``, chi-square with as
        many degrees of freedom as parameters held when they did not change (Ljung 1999, section
        16.5).  Unlike a Wald test on the Jacobian it does not depend on the parametrization, which
        matters along the ridge where gain and time constant trade off.  The input lag of an element is held
        at the free fit's unless "lag" is held; where a held shape ("pole" without "lag") meets a free fit
        that took another lag than the reference's (a lead or a lag traded against the dead time, within the
        noise: holding the reference's lag alone does not fit significantly worse, :meth:`_reference_lag_fits`),
        the refit is also made at the reference's lag and the better of the two taken: the reference's shape is
        the reference's at its own dead time, not at another.
        """
        est = self.est
        ssr = self._held_ssr(holds, options)
        # A shape held at the reference's with the input lag left at the free fit's: where the free fit took another
        # lag (within the noise, traded against its shape), the reference's shape is tried at its own lag too.
        moved = frozenset(m for m, what in holds.items()
                          if "pole" in what and "lag" not in what
                          and est.fit.lags[m] != self.located[self.js[m]].held_lag(False)
                          and self._reference_lag_fits(m))
        if moved:
            ssr = min(ssr, self._held_ssr(holds, options, at_reference=moved))
        return max(est.fit.n_resid * math.log(max(ssr, 1e-300) / max(est.fit.ssr, 1e-300)), 0.0)

    def lag_p(self, m: int, lag: int) -> float:
        """p-value of holding element ``m``'s input lag at ``lag``, its shape free (the profile likelihood ratio
        against chi-square with one degree of freedom); 0 for a lag outside the searched window.

        The profile's shape at ``lag`` is searched from the free fit's.  Where that rejects at the settings'
        ``alpha`` and ``lag`` is the reference's own, the reference's shape there is a candidate too
        (:meth:`_reference_statistic`), and the better of the two is taken: from the free fit's shape the search
        can stop short of it.  An integrator with lags of 2.9 s and 1.0 s (a step-response element), fitted with lags
        of 2.4 s and 0.38 s a sample later, found no shape at the model's dead time within p = 0.0005 of the fit,
        while the model's own shape there fitted within p = 0.13 (one degree of freedom).  Only where the profile
        rejects: a p-value it passes stays the profile's, and the repair makes no extra fit for it.
        """
        w = self.specs[self.js[m]].window
        if not w[0] <= lag <= w[1]:
            return 0.0
        p = float(chi2_tail(_lag_lr(self.est, m, lag), 1))
        loc = self.located[self.js[m]]
        if p < self.settings.alpha and not loc.missing and lag == loc.held_lag(False):
            p = max(p, float(chi2_tail(self._reference_statistic(m), 1)))
        return p

    def _reference_statistic(self, m: int) -> float:
        """``n ln(SSR / SSR_free)`` of element ``m`` with its shape and input lag held at the reference's (its gain
        free; :meth:`hold_statistic`), computed once."""
        if m not in self._reference_stat:
            self._reference_stat[m] = self.hold_statistic({m: {"pole", "lag"}}, self.settings.options)
        return self._reference_stat[m]

    def _reference_lag_fits(self, m: int) -> bool:
        """Whether element ``m``'s input lag held at its reference's (its shape free) does not fit significantly
        worse than the free fit (:meth:`lag_p` at the settings' ``alpha``): the data do not tell that lag from the
        free fit's."""
        return self.lag_p(m, self.located[self.js[m]].held_lag(False)) >= self.settings.alpha

    def _held_ssr(self, holds: dict, options: RepairOptions, at_reference: frozenset = frozenset()) -> float:
        """The residual sum of squares of :meth:`hold_statistic`'s refit; the elements of ``at_reference`` (indices
        ``m`` whose shape is held and lag not) at their reference's input lag instead of the free fit's."""
        est = self.est
        held, lags = {}, {}
        for m, j in enumerate(self.js):
            sp, loc = self.specs[j], self.located[j]
            lag = est.fit.lags[m]
            what = holds.get(m, set())
            if "lag" in what:
                lag = loc.held_lag("pole" not in what, "pole" not in what and self.lost_lag(m))
            elif m in at_reference:
                lag = loc.held_lag(False)
            sp_new = _ElementSpec(sp.gain_free, sp.pole_free, float(est.fit.gains[m]),
                                  tuple(float(a) for a in est.fit.poles[self.problem.slices[m]]), (lag, lag),
                                  form=sp.form, lead=float(est.fit.leads[m]))
            if "gain" in what:
                sp_new.gain_free, sp_new.gain = False, loc.reference["gain"]
            if "pole" in what:
                sp_new.pole_free, sp_new.poles, sp_new.lead = False, loc.poles, loc.reference["lead"]
                if loc.declared is not None:      # the reference's shape, at the same dead time
                    sp_new.form = loc.declared
                    lag += loc.declared.offset - loc.form.offset
                    sp_new.window = (lag, lag)
            if "no_lag" in what:
                sp_new.pole_free, sp_new.poles = False, (_POLE_MIN,)
            if "absent" in what:
                sp_new.gain_free, sp_new.gain, sp_new.pole_free = False, 0.0, False
            held[j] = sp_new
            lags[j] = lag
        skip = self.problem.start - self.problem.p
        _, est_h = _estimate_row(self.row, held, lags, self.row.n_samples, options, 1, skip=skip, ar0=est.ar)
        return est_h.fit.ssr


def _step_reading(row: _RowData, j: int, form: _Form) -> tuple:
    """:func:`~mpm_monitor.core.repair.forms._step_reference` of the row's step-response element ``j`` in ``form``,
    computed once per row (``row.shared``): the start form's choice and the ladder read the same forms."""
    readings = row.shared.setdefault("step_readings", {})
    key = (j, form)
    if key not in readings:
        readings[key] = _step_reference(row.model.step_response[row.i, j], form, row.model.sample_time)
    return readings[key]


def _step_start(row: _RowData, j: int) -> _Form:
    """The form the row's step-response element ``j`` starts in: the one that reads its old response
    (:func:`~mpm_monitor.core.repair.forms._step_start_form`)."""
    return _step_start_form(lambda form: _step_reading(row, j, form)[3], _step_ladder(row.model, row.i, j))


def _step_reading_form(row: _RowData, j: int, smaller: _Form, fitted: _Form) -> _Form:
    """The form whose reading of the row's step-response element ``j`` a fit in the ``smaller`` form is measured
    from: ``smaller``, unless the start form (:func:`_step_start`) or the form the element was ``fitted`` in reads
    the old response at most :data:`~mpm_monitor.core.repair.forms.STEP_READ_GAIN` as far off (the closer of the
    two; :func:`~mpm_monitor.core.repair.forms._step_start_form`'s rule for a larger form) and the smaller form's
    reading is not exact (off by more than :data:`~mpm_monitor.core.repair.forms.STEP_READ_EXACT`).

    A lag and a lead of 34.4 s over lags of 59.1 s and 35.3 s read first order within 0.2 %; the plant lost the
    35.3 s lag and the data called for a lead.  Read in one lag and a lead, the old response took a lead of 0.8 s and
    a sample more dead time, which the fit (the plant's 8 s) then seemed to have changed (``mixed``): its reading in
    two lags and a lead, where the data had fitted it, is exact.
    """
    error = _step_reading(row, j, smaller)[3]
    if error <= STEP_READ_EXACT:
        return smaller
    closest = min(dict.fromkeys((_step_start(row, j), fitted)), key=lambda f: _step_reading(row, j, f)[3])
    return closest if _step_reading(row, j, closest)[3] <= STEP_READ_GAIN * error else smaller


def _locate(row: _RowData, j: int, form: Optional[_Form] = None) -> _Located:
    """The :class:`_Located` of element ``j`` of the row (in ``form`` for a missing or step-response element)."""
    model, i = row.model, row.i
    ts = model.sample_time
    present = bool(model.present[i, j])
    hint = row.delays.get(j)
    if model.is_step_response and present:
        form = form or _step_start(row, j)
        ref, lag, poles, _ = _step_reading(row, j, form)
        return _Located(form=form, reference=ref, lag=lag, missing=False, poles=poles, hint=hint)
    if not present:
        form = form or _missing_ladder(model, i)[0]
        ref = _fitted_params(form, 0.0, (_POLE_MIN,) * form.n_lags, 0.0, 0, ts)
        ref["delay"] = float(model.delay[i, j])
        return _Located(form=form, reference=ref, lag=int(model.delay_samples[i, j]), missing=True,
                        poles=_poles_of(form, ref, ts), hint=hint)
    form = _form_of(model, i, j)
    ref = _params_of(model, i, j)
    lag = _input_lag(form, ref, ts)
    return _Located(form=form, reference=ref, lag=lag, missing=False, poles=_poles_of(form, ref, ts), hint=hint,
                    feedthrough=lag == 0)


def _row_start(row: _RowData):
    """``(base_tau, max_row_lag)``: the row's median time constant (s; 10 samples without one) and the
    largest input lag of its elements (samples; 1 without one), where an element the model lacks starts."""
    model, i = row.model, row.i
    ts = model.sample_time
    present = model.present[i]
    taus = model.time_constant[i][present & (model.time_constant[i] > 0)]
    base_tau = float(np.median(taus)) if taus.size else 10.0 * ts
    max_row_lag = max([model.discrete_element(i, j).input_lag for j in range(model.n_columns) if present[j]],
                      default=1)
    return base_tau, max_row_lag


def _free_spec(row: _RowData, loc: _Located, options: RepairOptions, start=None):
    """The spec of the free fit of a located element and its start lag.

    An element the model has is searched within ``max_delay_shift`` of its reference's lag; an
    element the model lacks starts at the row's median time constant and largest input lag
    (:func:`_row_start`), searched from 1 to that lag plus ``max_delay_shift``.  Where the element
    test's estimate of the mismatch's lag (``loc.hint``) lies outside that range, the range is
    widened to reach within ``max_delay_shift`` of it (unless ``max_delay_shift`` is 0): a plant whose
    dead time is far shorter than the model's has its mismatch ``Delta`` act first at the plant's lag,
    which the element test sees, and without it the fit of a model delay of 20 samples to a plant's
    2 settled at 20 with the gain cut to a twenty-fifth.  ``start`` (``(gain, poles, lead, lag)``)
    overrides the start values.
    """
    ts = row.model.sample_time
    s = options.max_delay_shift
    base_tau, max_row_lag = _row_start(row)
    form, ref = loc.form, loc.reference
    if loc.missing:
        taus = (base_tau, 0.3 * base_tau)[:form.n_lags]
        gain, poles, lead, lag = 0.0, tuple(_pole_of(t, ts) for t in taus), 0.0, max_row_lag
        window = (1, max_row_lag + s)
    else:
        poles = loc.poles
        if form.first_order and ref["time_constant"] <= 0:
            poles = (_pole_of(base_tau, ts),)
        gain, lead = ref["gain"], ref["lead"]
    # The input acts one sample after it is applied at the earliest (lag 1): at lag 0 an element with a
    # lead and no lag beyond it (its form biproper, offset 0) would act on y(k) through u(k), a direct
    # feed-through that no sampled loop closes (the repair wrote such elements, which the MPC refused).  Only
    # an element the model itself gives a feed-through is searched from lag 0: held at 1, its dead time
    # could not be held at all (its delay test rejected outright), and a gain change came out ``mixed``.
    floor = 0 if loc.feedthrough else 1
    if not loc.missing:
        lag = max(floor, loc.lag)
        window = (max(floor, lag - s), lag + s)
    if loc.hint is not None and s > 0 and not window[0] <= loc.hint <= window[1]:
        window = (max(floor, min(window[0], loc.hint - s)), max(window[1], loc.hint + s))
    if start is not None:
        gain, poles, lead, lag = start
    spec = _ElementSpec(True, form.n_shape > 0, gain, tuple(poles), window, form=form, lead=lead)
    return spec, lag


def _fit_free(row: _RowData, js, settings: _TestSettings) -> _FreeFit:
    """Fit the located elements ``js`` of the row on the whole record with everything free, each in
    its form (:func:`_choose_forms` for the elements whose form the data decide).

    A step-response element whose fit in its start form took one of two lags below a sample has that lag tried away
    (:func:`_reduce_vanished_lags`) before the ladder climbs from it: from such a fit (a lag of 38 s, the other gone,
    the gain 27 % short, of a plant that lost its second lag) the ladder took a lead and two lags of 300 s and 30 s,
    which fitted significantly better than it but not than one lag, and whose reading was 17 % off
    (``bench.step_models --lost-lag`` seed 4 run 63; a parametric element has no ladder)."""
    options = settings.options
    located = {j: _locate(row, j) for j in js}
    specs, lags0 = {}, {}
    for j in js:
        specs[j], lags0[j] = _free_spec(row, located[j], options)
    def skip_of(specs):
        # Room for the lags of the larger forms (the references' lags may move a few samples).
        return _default_skip(row, specs) + _LAG_SHIFT if row.model.is_step_response else None
    problem, est = _estimate_row(row, specs, lags0, row.n_samples, options, options.max_sweeps, skip=skip_of(specs))
    first = specs
    specs, problem, est = _widen_lag_ranges(row, specs, problem, est, options, skip_of, settings.alpha)
    widened = {j: specs[j].window for j in specs if specs[j].window != first[j].window}
    free = _FreeFit(row=row, js=list(js), specs=specs, located=located, problem=problem, est=est, settings=settings,
                    widened=widened)
    if row.model.is_step_response:     # a lag vanished in the start form goes before the ladder climbs from it
        free = _reduce_vanished_lags(free, settings)
    chosen = _choose_forms(free, settings)
    if chosen is not free or not row.model.is_step_response:
        free = _reduce_vanished_lags(chosen, settings)
    return _grow_gained_lags(_reduce_cancelled_leads(free, settings), settings)


#: How many times :func:`_widen_lag_ranges` widens a lag range.
MAX_WIDENINGS = 4
#: The fewest lags (samples) at which :func:`_widen_lag_ranges` probes the residual's correlation with an input.
MIN_PROBED_LAGS = 100


def _widen_lag_ranges(row: _RowData, specs: dict, problem, est, options: RepairOptions, skip_of,
                  alpha: float = 1e-3):
    """The free fit with the lag ranges widened where the data show the input acting outside them.

    A plant whose dead time lies more than ``max_delay_shift`` samples beyond the model's is not found by
    the element test's estimate of where the mismatch acts (the model's own response, which the plant
    lacks there, acts first).  Two signs widen an element's range, the first taken where both show:

    - its best lag sits at an end of the range: that end moves out by ``max_delay_shift`` (at the lower
      end not below 1);
    - the fit's residual correlates with the element's input at a lag outside the range
      (:meth:`~.fit._RowProblem.input_correlation` above the normal quantile of ``alpha`` shared over the
      lags probed: Bonferroni), at lags up to the largest of the range's end, the row's samples left out
      (``skip``), the model's longest input lag and :data:`MIN_PROBED_LAGS`, plus ``max_delay_shift``
      (at most a quarter of the fit's samples): the range grows to reach within ``max_delay_shift`` of the
      most correlated such lag.  An element the model lacks whose plant acts after 40 samples, on a row
      whose longest lag is 8, was fitted at lag 15 with two lags of 44 s.  In closed loop the best lag within
      the model's range can lie inside it (the fit bends the gain and the lag), with no end reached.

    The row is refitted after each widening, up to :data:`MAX_WIDENINGS` times, while the record leaves
    enough samples beyond the longest lag.  Returns ``(specs, problem, est)``: unchanged when neither sign shows.
    """
    s = options.max_delay_shift
    present = row.model.present
    longest = int(np.max(row.model.delay_samples[present])) + 1 if present.any() else 1
    for _ in range(MAX_WIDENINGS if s > 0 else 0):
        wider = dict(specs)
        lags = {}
        skip = problem.start - problem.p
        for m, j in enumerate(sorted(specs)):
            lag, (lo, hi) = int(est.fit.lags[m]), specs[j].window
            lags[j] = lag
            if not specs[j].lag_free:
                continue
            if est.edge[m]:
                wider[j] = dataclasses.replace(specs[j], window=(max(min(lo, 1), lo - s), hi) if lag == lo
                                               else (lo, hi + s))
                continue
            reach = min(max(hi, skip, longest, MIN_PROBED_LAGS) + s, max(hi, problem.n_fit // 4))
            z = problem.input_correlation(est.fit, m, reach)
            taus = np.arange(1, reach + 1)
            outside = (taus < lo) | (taus > hi)
            if outside.any() and np.max(z[outside]) > normal_isf(alpha / (2.0 * reach)):
                tau = int(taus[np.argmax(np.where(outside, z, -1.0))])
                wider[j] = dataclasses.replace(specs[j], window=(max(min(lo, 1), min(lo, tau - s)), max(hi, tau + s)))
        if wider == specs:
            break
        try:
            problem_w, est_w = _estimate_row(row, wider, lags, row.n_samples, options, options.max_sweeps,
                                             skip=skip_of(wider))
        except _TooShort:
            break
        specs, problem, est = wider, problem_w, est_w
    return specs, problem, est


def _grow_gained_lags(free: _FreeFit, settings: _TestSettings) -> _FreeFit:
    """The free fit with a lag for a pure integrator (a declared integrating element without a lag) whose
    plant gained one, where the data call for it.

    A pure integrator ``K / s`` fitted in its own form can only move its gain and dead time: a plant that
    gained a lag ``K / (s (tau s + 1))`` was repaired as ``tau`` more dead time (the same ramp, another
    transient; the row stayed mismatched) and classified ``delay``.  So each such element is refitted
    with one lag, every parameter free on the same samples, and that form is kept when it fits
    significantly better: the likelihood-ratio test ``n ln(SSR_none / SSR_one)`` against chi-square with
    one degree of freedom at ``alpha`` (as :func:`_choose_forms` chooses a larger form).  Its reference
    keeps the model's lag of 0, at the lower bound of the fitted poles, so the ``time_constant`` test
    holds the lag there: the pure integrator, to a tenth of a sample.  A pure gain is fitted first order
    from the start (:func:`~mpm_monitor.core.repair.forms._form_of`).

    Where a row holds several such elements, each growth that is kept is followed by another try of those not
    grown yet, and the ones still left are then grown together (the test with as many degrees of freedom).  In a
    closed loop whose row has two pure integrators that both gained a lag, the fit in the declared forms let the
    noise model take a unit root and the gains fall to a twentieth (a drift in place of the inputs' ramps); grown
    alone from that fit, one element's lag fitted no better while the other stayed such a collapsed integrator
    (``bench.structures_mc --gained-lag`` seed 4, runs 80, 164 and 178: both elements ``unknown``, and the model
    kept).
    """
    row = free.row
    ts = row.model.sample_time

    def grown_of(free: _FreeFit, m: int, j: int) -> tuple:
        loc = free.located[j]
        form = dataclasses.replace(loc.form, n_lags=1)
        grown = dataclasses.replace(loc, form=form, lag=_input_lag(form, loc.reference, ts),
                                    poles=_poles_of(form, loc.reference, ts))
        # Start where the fit in the declared form put the dead time: the lag it stood in for.
        lag_fit = int(free.est.fit.lags[m]) - (loc.form.offset - form.offset)
        start = (float(free.est.fit.gains[m]), (_pole_of(max(lag_fit - grown.lag, 1) * ts, ts),),
                 float(free.est.fit.leads[m]), grown.lag)
        return grown, start

    if row.model.is_step_response:
        return free
    located = free.located
    left = [(m, j) for m, j in enumerate(free.js)
            if not (located[j].missing or located[j].declared is not None or located[j].form.n_lags != 0
                    or not located[j].form.integrating)]
    while left:
        for m, j in left:
            larger = _refit_element(free, j, *grown_of(free, m, j), settings)
            if _larger_form_p(free.est.fit.n_resid, free.est.fit.ssr, larger.est.fit.ssr, _form_df(free, 1, 1)) \
                    < settings.alpha:
                free = larger
                left.remove((m, j))
                break
        else:
            break
    if len(left) > 1:
        larger = _refit_elements(free, {j: grown_of(free, m, j) for m, j in left}, settings)
        if _larger_form_p(free.est.fit.n_resid, free.est.fit.ssr, larger.est.fit.ssr,
                          _form_df(free, len(left), len(left))) < settings.alpha:
            free = larger
    return free


def _reduce_vanished_lags(free: _FreeFit, settings: _TestSettings) -> _FreeFit:
    """The free fit with one lag fewer for an element whose fit took one of its two lags below a sample.

    A plant that has lost one of an element's two lags leaves that lag at the fit's bound (a pole of
    ``_POLE_MIN``, a lag of ``T / 9.2``) or near it.  There the two-lag form is not the one-lag form: its
    lag of a tenth of a sample shifts the response, and the gain, the lead and the dead time bend to make up
    for it (the gain and delay tests found changes the plant did not have, the kind came out ``mixed``, and
    the repair kept the row mismatched).  The one-lag form is the limit of the two-lag form as that lag goes
    to 0 (``time_constant2`` 0).  So an element whose smaller fitted lag is shorter than one sample time is
    refitted in it, every parameter free on the same samples, and that form is kept unless the two-lag form
    fits significantly better: the likelihood-ratio test ``n ln(SSR_one / SSR_two)`` against chi-square with
    one degree of freedom at ``alpha`` (as :func:`_choose_forms` chooses a larger form).  Its tests measure
    the changes from the reference's dead time in that form (:class:`_Located`'s ``declared``), also for a
    step-response element whose old response reads as two lags (its start form, :func:`_step_start`); one
    whose two lags the data called for (:func:`_choose_forms`) from its old response read in the one-lag form
    (:func:`~mpm_monitor.core.repair.forms._step_reference`).  An element the model lacks keeps the form its
    ladder chose.

    A lag is tried away only where the reference's shape and dead time, held together, do not fit (the
    likelihood-ratio test of both held, as many degrees of freedom as the shape's parameters and one, at
    ``alpha``): where they fit, the data do not tell the reference's lag from a sample of dead time, and
    nothing of its shape or dead time has changed.  An integrator's second lag of one sample (2.9 s and
    1.0 s) whose gain alone changed was fitted with that lag at a seventh of a sample and a sample more
    dead time, not significantly better than the model's shape and dead time (p = 0.26); taken away, the
    lag and the dead time both seemed to have changed (``mixed``).
    """
    for m, j in enumerate(free.js):
        loc = free.located[j]
        poles = free.est.fit.poles[free.problem.slices[m]]
        if loc.missing or loc.declared is not None or loc.form.n_lags != 2 or min(poles) > _SUBSAMPLE_POLE:
            continue
        held = free._reference_statistic(m)                   # the reference's shape and dead time held
        if float(chi2_tail(held, loc.form.n_shape + 1)) >= settings.alpha:
            continue
        form = dataclasses.replace(loc.form, n_lags=1)
        start = (float(free.est.fit.gains[m]), (float(max(poles)),), float(free.est.fit.leads[m]),
                 int(free.est.fit.lags[m]) - (loc.form.offset - form.offset))
        free = _try_smaller_form(free, j, form, start, 1, settings)
    return free


def _try_smaller_form(free: _FreeFit, j: int, form: _Form, start, df: int, settings: _TestSettings) -> _FreeFit:
    """The free fit with element ``j`` refitted in the smaller ``form`` from ``start`` (:func:`_refit_element`),
    kept unless the larger form fits significantly better (:func:`_larger_form_p` with ``df`` degrees of freedom
    at ``alpha``); else ``free``.  The smaller form's tests measure the changes from the reference read in it: a
    parametric element's reference keeps its declared form (``declared``).  A step-response element has its old
    response read in the smaller form (:func:`_step_reading_form`; a lag and a lead read in the two-lag form took a
    second lag of a tenth of a sample and one sample less dead time, which the fit in one lag then seemed to have
    changed), unless the form it starts in or the form it was fitted in reads it at least twice as closely: then
    the old response has a shape the smaller form lacks (a plant that lost a second lag the old response has), and
    that reading is held as a declared form is."""
    row, loc = free.row, free.located[j]
    ts = row.model.sample_time
    if row.model.is_step_response and loc.declared is None:
        read_in = _step_reading_form(row, j, form, loc.form)
        if read_in == form:                     # the smaller form reads the old response as well: read in it
            reduced = _locate(row, j, form)
        else:                                   # the old response has a shape the smaller form lacks: held in it
            read = _locate(row, j, read_in)
            reduced = dataclasses.replace(read, form=form, lag=_input_lag(form, read.reference, ts), declared=read_in)
    else:
        reduced = dataclasses.replace(loc, form=form, lag=_input_lag(form, loc.reference, ts),
                                      declared=loc.declared or loc.form)
    smaller = _refit_element(free, j, reduced, start, settings)
    df = _form_df(free, df, loc.form.n_lags - form.n_lags)
    return smaller if _larger_form_p(free.est.fit.n_resid, smaller.est.fit.ssr, free.est.fit.ssr, df) >= settings.alpha \
        else free


#: A lead and a lag of an element whose fitted values lie within this factor of each other nearly cancel
#: (:func:`_reduce_cancelled_leads`).
CANCEL_RATIO = 1.5
#: A lead fitted shorter than this fraction of a sample time is no lead (:func:`_reduce_cancelled_leads`; a fitted
#: lag's bound is a tenth of a sample too, ``T / 9.2``).
VANISHED_LEAD = 0.1
#: A lead or a lag longer than this fraction of the compared samples' duration is too slow for the record to
#: resolve (:func:`_reduce_cancelled_leads`).
SLOW_FRACTION = 0.25


def _reduce_cancelled_leads(free: _FreeFit, settings: _TestSettings) -> _FreeFit:
    """The free fit without a lead the data do not call for: with the lag it cancels, or alone when it vanished.

    A lead ``(L s + 1)`` over a lag ``(T s + 1)`` is a gain of 1 at low frequencies and of ``L / T`` above
    ``1 / T``.  Where the lead and a lag nearly cancel (within :data:`CANCEL_RATIO` of each other), or either
    is longer than :data:`SLOW_FRACTION` of the record, the data hardly tell the pair from a change of gain:
    a first-order plant ``1.2 / (4 s + 1)`` under a model ``(5 s + 1) / ((5 s + 1)^2)`` was repaired with the
    gain held at 1, a second lag of 2,000 s and a lead of 2,400 s (the pair making up the gain within the
    record, and its intervals unbounded), marked applied.  So such an element is refitted without the pair
    (one lag fewer, no lead; two degrees of freedom), where its form keeps a lag or an integrator.  A lead
    fitted shorter than :data:`VANISHED_LEAD` of a sample time (:func:`_reduce_vanished_lags` may have taken the
    lag it cancelled) is refitted away alone (one degree of freedom).

    The pair may be the fit's own rather than the plant's: an integrator with an inverse response,
    ``(1 - 2.5 s) / (s (12.2 s + 1)(5.7 s + 1))`` in the model, whose plant lost the 5.7 s lag, was fitted in the
    model's form at a lead of 1,781 s over a lag of 2,000 s (the search started from the model's lead of -2.5 s
    came to rest there), and without the pair it took a sample more dead time and a lag of 10.2 s, its kind
    ``mixed``, where one lag and the model's lead fit the record far better (``bench.structures_mc --lost-lag``
    seed 7 run 126).  So an element whose form has two lags and whose reference has a lead (at least
    :data:`VANISHED_LEAD` of a sample time) is first refitted
    with the lead kept over the other lag, from the reference's lead (one degree of freedom fewer); where that
    form is kept, the lead is then dropped too only where it does not fit significantly better (one degree of
    freedom).  Every parameter is free on the same samples, and the smaller
    form is kept unless the larger one fits significantly better: the likelihood-ratio test
    ``n ln(SSR_smaller / SSR_larger)`` against chi-square at ``alpha`` (as :func:`_choose_forms` chooses a
    larger form).  Its tests measure the changes from the reference in that form (:class:`_Located`'s
    ``declared``, as :func:`_reduce_vanished_lags`, also a step-response element in the form its old response
    reads in); a step-response element in a larger form the data called for, from its old response read in the
    smaller form (:func:`_try_smaller_form`).
    """
    ts = free.row.model.sample_time
    duration = free.est.fit.n_resid * ts
    for m, j in enumerate(free.js):
        loc = free.located[j]
        form = loc.form
        if loc.missing or not form.lead:
            continue
        lead = float(free.est.fit.leads[m])
        poles = [float(a) for a in free.est.fit.poles[free.problem.slices[m]]]
        taus = [_tau_of(a, ts) for a in poles]
        smaller_form = None
        if abs(lead) < VANISHED_LEAD * ts:                  # a lead at the scale of no lead: away alone
            smaller_form, df, dropped = dataclasses.replace(form, lead=False), 1, None
        elif lead > 0 and taus and form.n_lags + int(form.integrating) >= 2:
            q = min(range(len(taus)), key=lambda k: abs(math.log(lead / max(taus[k], 1e-300))))
            pair = (min(lead, taus[q]), max(lead, taus[q]))
            if pair[1] <= CANCEL_RATIO * pair[0] or pair[1] > SLOW_FRACTION * duration:
                smaller_form, df, dropped = dataclasses.replace(form, n_lags=form.n_lags - 1, lead=False), 2, q
        if smaller_form is None:
            continue
        # Start from the pair's gain within the record (K L / T) and the other lags.
        gain = float(free.est.fit.gains[m]) * (1.0 if dropped is None else lead / taus[dropped])
        start = (gain, tuple(a for k, a in enumerate(poles) if k != dropped), 0.0,
                 int(free.est.fit.lags[m]) - (form.offset - smaller_form.offset))
        ref_lead = float(loc.reference.get("lead", 0.0))
        if dropped is not None and form.n_lags >= 2 and abs(ref_lead) >= VANISHED_LEAD * ts:
            # The pair may be the fit's own: the lead kept with the other lags, from the reference's lead.
            kept_form = dataclasses.replace(form, n_lags=form.n_lags - 1)
            kept_start = (gain, start[1], ref_lead, int(free.est.fit.lags[m]) - (form.offset - kept_form.offset))
            kept = _try_smaller_form(free, j, kept_form, kept_start, 1, settings)
            if kept is not free:        # the lead then goes only where the data do not call for it
                free = _try_smaller_form(kept, j, smaller_form, start, 1, settings)
                continue
        free = _try_smaller_form(free, j, smaller_form, start, df, settings)
    return free


def _ladder(row: _RowData, j: int) -> tuple:
    """The forms the data choose from for element ``j`` (empty: its form is the declared one)."""
    model, i = row.model, row.i
    if model.is_step_response and model.present[i, j]:
        return _step_ladder(model, i, j)
    if not model.present[i, j]:
        return _missing_ladder(model, i)
    return ()


def _choose_forms(free: _FreeFit, settings: _TestSettings) -> _FreeFit:
    """The forms of the elements the model lacks and of step-response elements, chosen by the data.

    An element the model lacks starts in the first form of its ladder (first order), a step-response
    element in the first that reads its old response (:func:`~mpm_monitor.core.repair.forms._step_start_form`:
    first order for most, two lags for a two-lag response); a larger form replaces
    the current one when the likelihood-ratio test ``n ln(SSR_current / SSR_larger)`` against
    chi-square with the difference of shape parameters rejects at ``1 - confidence_level`` (Ljung
    1999, section 16.5): a second lag (and a lead, for a step-response element) only where the data
    call for it.  Every fit compared uses the same samples.
    """
    row = free.row
    ts = row.model.sample_time
    for m, j in enumerate(free.js):
        for form in _ladder(row, j)[1:]:
            cur = free.located[j]
            if form.n_shape <= cur.form.n_shape:
                continue
            loc = _locate(row, j, form)
            start = None
            if loc.missing:
                tau = _tau_of(float(free.est.fit.poles[free.problem.slices[m]][0]), ts)
                start = (float(free.est.fit.gains[m]), (_pole_of(tau, ts), _pole_of(0.3 * tau, ts))[:form.n_lags],
                         0.0, int(free.est.fit.lags[m]))
            larger = _refit_element(free, j, loc, start, settings)
            if _larger_form_p(larger.est.fit.n_resid, free.est.fit.ssr, larger.est.fit.ssr,
                              _form_df(free, form.n_shape - cur.form.n_shape, form.n_lags - cur.form.n_lags)) \
                    < settings.alpha:
                free = larger
    return free


def _form_df(free: _FreeFit, shape_df: int, poles: int) -> int:
    """Degrees of freedom of the likelihood-ratio test of a form with ``shape_df`` shape parameters and ``poles``
    lags more than another, fitted as ``free``'s problem is: on a record fitted in segments (data with gaps), each
    pole's free response is a column of every segment's own (:meth:`~.fit._RowProblem._spread`), so a lag more
    brings one more nuisance parameter per segment beyond the first (as on one record, where it brings none
    counted).  Without them a second lag at the fit's bound, whose free response is an impulse at the first sample
    of each segment, took those samples out of the cost and was chosen "significantly" (an element the model lacks
    came out with ``time_constant2`` 0 -> 0.1086 s on 10 of 10 records with 1 % of their samples dropped, 0 of 10
    whole)."""
    problem = free.problem
    if not problem.free or poles <= 0:
        return shape_df
    return shape_df + poles * (problem.n_segments - 1)


def _larger_form_p(n_resid: int, ssr_smaller: float, ssr_larger: float, df: int) -> float:
    """p-value of the likelihood-ratio test ``n ln(SSR_smaller / SSR_larger)`` of a larger form against chi-square with
    ``df`` degrees of freedom (Ljung 1999, section 16.5): small where the larger form fits significantly better."""
    stat = n_resid * math.log(max(ssr_smaller, 1e-300) / max(ssr_larger, 1e-300))
    return chi2_tail(max(stat, 0.0), df)


def _refit_element(free: _FreeFit, j: int, loc: _Located, start, settings: _TestSettings) -> _FreeFit:
    """The free fit with element ``j`` fitted anew as ``loc`` says (its form and reference), from ``start``
    (:func:`_free_spec`), the other elements from their fitted lags, on the same samples as ``free`` (its lag
    search kept within them): what :func:`_choose_forms` and :func:`_reduce_vanished_lags` compare ``free`` with."""
    return _refit_elements(free, {j: (loc, start)}, settings)


def _refit_elements(free: _FreeFit, new: dict, settings: _TestSettings) -> _FreeFit:
    """:func:`_refit_element` of several elements at once: ``new`` is ``{j: (loc, start)}``, each element ``j``
    fitted anew as its ``loc`` says from its ``start``, together, the others from their fitted lags."""
    row, options = free.row, settings.options
    specs = dict(free.specs)
    lags0 = {jj: int(free.est.fit.lags[k]) for k, jj in enumerate(free.js)}
    skip = free.problem.start - free.problem.p
    located = dict(free.located)
    for j, (loc, start) in new.items():
        spec, lag0 = _free_spec(row, loc, options, start)
        if j in free.widened:          # the range the free fit had to widen (_widen_lag_ranges), kept
            lo, hi = free.widened[j]
            spec.window = (min(spec.window[0], lo), max(spec.window[1], hi))
        spec.window = (min(spec.window[0], skip), min(spec.window[1], skip))   # the samples compared
        specs[j] = spec
        lags0[j] = min(max(lag0, spec.window[0]), spec.window[1])
        located[j] = loc
    problem, est = _estimate_row(row, specs, lags0, row.n_samples, options, options.max_sweeps, skip=skip)
    return _FreeFit(row=row, js=free.js, specs=specs, located=located, problem=problem, est=est, settings=settings,
                    widened=free.widened)


def _shape_changed(after: dict, reference: dict, form: _Form, ts: float, min_change: float) -> bool:
    """Whether a lag or the lead moved by more than ``min_change`` (relative to the reference's value,
    at least one sample time)."""
    keys = ["time_constant", "time_constant2"][:max(form.n_lags, 1)] + (["lead"] if form.lead else [])
    return any(abs(after[k] - reference[k]) > min_change * max(abs(reference[k]), ts) for k in keys)


def _single_tests(free: _FreeFit, settings: _TestSettings):
    """The fitted parameters of each element and the test of each of its parameters alone.

    The ``time_constant`` test holds the whole shape (every lag and the lead, as many degrees of
    freedom); an element without lag or lead (a pure integrator) has none.

    Returns
    -------
    summaries : dict
        ``{j: (after, interval)}`` (see :func:`_element_summary`).
    tests : dict
        ``{j: _ElementTests}``.
    """
    ts = free.row.model.sample_time
    options = settings.options
    summaries, tests = {}, {}
    for m, j in enumerate(free.js):
        loc = free.located[j]
        after, interval = _element_summary(free.problem, free.est, m, ts, settings, loc.reference)
        summaries[j] = (after, interval)
        before, form = loc.reference, loc.shape_form
        t = {}
        if loc.missing:
            t["missing"] = [float(chi2_tail(free.hold_statistic({m: {"absent"}}, options), 1)), True]
        else:
            t["gain"] = [float(chi2_tail(free.hold_statistic({m: {"gain"}}, options), 1)),
                         abs(after["gain"] - before["gain"]) > options.min_relative_change * abs(before["gain"])]
            if form.n_shape:
                p_t = float(chi2_tail(free.hold_statistic({m: {"pole"}}, options), form.n_shape))
                # Read as the pure gain it was fitted as: a lag that vanished, or a pure gain's lag that the data do
                # not show (its fitted pole a hair above the bound read as a lag of T / 8 a sample earlier, and a
                # dead time one sample longer came out a ``time_constant`` change, bench.structures_mc --pure-gains
                # seed 4 runs 22 and 255).
                no_lag = free.lost_lag(m) if p_t < settings.alpha else \
                    loc.plain_first_order and loc.reference.get("time_constant", 0.0) <= 0
                if no_lag:
                    after, interval = _element_summary(free.problem, free.est, m, ts, settings, loc.reference,
                                                       no_lag=True)
                    summaries[j] = (after, interval)
                t["time_constant"] = [p_t, _shape_changed(after, before, form, ts, options.min_relative_change)]
            # The dead time held, the shape free: a sample later for a pure gain whose time-constant test
            # found a lag, a sample earlier for a lag whose fit shows none (:meth:`_Located.held_lag`).
            p_t, big_t = t.get("time_constant", (1.0, False))
            shape_changed = p_t < settings.alpha and big_t
            lag = loc.held_lag(shape_changed, shape_changed and free.lost_lag(m))
            t["delay"] = [free.lag_p(m, lag), after["delay"] != before["delay"]]
        tests[j] = _ElementTests.of(t, settings.alpha)
    return summaries, tests


def _joint_hold(free: _FreeFit, tests: dict, settings: _TestSettings, warnings: list):
    """Test the parameters judged unchanged held together; free the likeliest changed while it rejects.

    While the joint likelihood-ratio test of every held parameter rejects at ``alpha``, the held
    parameter whose release fits best is added to its element's ``changed`` (its margin becomes that of
    the joint test) and a warning says so; ``tests`` (``{j: _ElementTests}``) and ``warnings`` are updated
    in place.  "Fits best": the smallest Akaike criterion of the row with it released (the joint
    statistic of the parameters still held plus twice the number of parameters released: a shape of two
    lags counts two), ties to the smallest single p-value.  The single p-values cannot choose it: each
    holds its parameter with every other one free, where the joint test holds the others too
    (``bench.structures_mc`` run 262: u2's time constant, the smallest single p-value, explained none of
    the misfit that u1's time constant did).  Where releasing another parameter instead also passes the
    joint test and comes within :data:`_AIC_INDISTINCT` of the criterion, the warning names it.

    Returns
    -------
    float or None
        The p-value of the last joint test (None when nothing was held).
    """
    alpha, js, options = settings.alpha, free.js, settings.options
    joint_p = None
    known = None            # the statistic of the holds left by the last release (computed among the releases)
    while True:
        holds = {m: {_PARAM_OF_TEST[k] for k in tests[j].unchanged()} for m, j in enumerate(js)}
        stat, n_held = known if known is not None else _joint_statistic(free, holds, options)
        if n_held == 0:
            break
        joint_p = float(chi2_tail(stat, n_held))
        if joint_p >= alpha:
            break
        statistics = {(j, k): _joint_statistic(free, {**holds, m: holds[m] - {_PARAM_OF_TEST[k]}}, options)
                      for m, j in enumerate(js) for k in tests[j].unchanged()}
        # Each release's Akaike criterion (the parameters it frees counted twice) and the p-value of the rest held.
        released = {jk: (s + 2.0 * (n_held - n), float(chi2_tail(s, n)) if n else 1.0)
                    for jk, (s, n) in statistics.items()}
        j_free, k_free = min(released, key=lambda jk: (released[jk][0], tests[jk[0]].results[jk[1]][0]))
        known = statistics[(j_free, k_free)]
        tests[j_free].changed.add(k_free)
        tests[j_free].margins[k_free] = _margin(joint_p, alpha)
        warnings.append(f"{free.row.name(j_free)}: its {k_free.replace('_', ' ')} alone does not show a "
                        f"significant change, but holding it together with the other unchanged parameters of the "
                        f"row does not fit the data (p = {joint_p:.2g}); it is re-estimated too."
                        + _other_releases(free, released, (j_free, k_free), alpha))
    return joint_p


#: Akaike criteria closer than this (Burnham and Anderson, *Model Selection and Multimodel Inference*, 2nd ed., 2002,
#: section 2.6: "substantial support" for both) leave two releases of the joint test undecided by the data.
_AIC_INDISTINCT = 2.0


def _other_releases(free: _FreeFit, released: dict, chosen: tuple, alpha: float) -> str:
    """`` Freeing ... instead fits almost as well (...): the data do not tell these changes apart, ...`` when
    releasing another held parameter than ``chosen`` also lets the joint test of the rest pass at ``alpha`` and
    its Akaike criterion lies within :data:`_AIC_INDISTINCT` of the chosen one's (``released``:
    ``{(j, test): (criterion, p-value of the rest)}``); else empty."""
    aic, p_chosen = released[chosen]
    others = [(j, k, a - aic, p) for (j, k), (a, p) in released.items()
              if (j, k) != chosen and p >= alpha and a - aic <= _AIC_INDISTINCT]
    if not others:
        return ""
    names = " or ".join(f"the {k.replace('_', ' ')} of {free.row.name(j)} (p = {p:.2g}, criterion {d:.2g} higher)"
                        for j, k, d, p in others)
    return (f" Freeing {names} instead fits almost as well (Akaike's criterion within {_AIC_INDISTINCT:g} of this "
            f"one's, p = {p_chosen:.2g}): the data do not tell these changes apart, and the kind named may be the "
            f"wrong one.")


def _joint_statistic(free: _FreeFit, holds: dict, options: RepairOptions) -> tuple:
    """``(statistic, n_held)`` of holding ``holds`` (``{m: set of "gain", "pole", "lag"}``) together
    (:meth:`_FreeFit.hold_statistic`; ``n_held`` its degrees of freedom, as many as parameters held, a
    shape as many as its lags and lead); ``(0.0, 0)`` when nothing is held."""
    n_held = sum(free.located[free.js[m]].shape_form.n_shape if k == "pole" else 1
                 for m, h in holds.items() for k in h)
    return (free.hold_statistic(holds, options), n_held) if n_held else (0.0, 0)


def _verdict(est: _RowEstimate, summary: tuple, tests: _ElementTests, joint_p, alpha: float,
             loc: _Located, step_response: bool = False) -> ElementVerdict:
    """The kind, the confidence and the evidence of an element from its tests.

    One changed parameter names the kind (gain, time_constant -- any lag or the lead -- or delay;
    an integrator's gain is a gain), several give "mixed", a significant element the model does not
    have "missing", nothing "unknown".  A parameter that the joint test freed although its estimate
    moved by less than ``min_relative_change`` (a delay: not at all) is re-estimated but names no kind
    beside a parameter whose change is that large.  The confidence is the smallest margin of the tests,
    including the joint test when the element has a parameter held in it.  For an element of a
    step-response model (``step_response``) the evidence holds the parametric forms of its old and
    new responses (``parametric_before``, ``parametric_after``), from which the kind was decided.
    """
    after, interval = summary
    results = tests.results
    hits = sorted(tests.changed, key=_TEST_ORDER.index)
    named = [k for k in hits if results[k][1]] or hits       # the changes of material size, where there are any
    if "missing" in hits:
        kind = "missing"
    elif not hits:
        kind = "unknown"
    else:
        kind = named[0] if len(named) == 1 else "mixed"
    confidence = min(tests.margins.values())
    if joint_p is not None and tests.unchanged():
        confidence = min(confidence, _margin(joint_p, alpha))
    evidence = {"p_gain": results.get("gain", results.get("missing"))[0],
                "p_time_constant": results["time_constant"][0] if "time_constant" in results else None,
                "p_delay": results["delay"][0] if "delay" in results else None,
                "p_unchanged_jointly": joint_p, "condition_number": est.cond, "samples": est.fit.n_resid,
                "noise_model": [float(v) for v in est.ar]}
    if step_response:
        evidence["parametric_before"] = _public_params(loc.reference)
    return ElementVerdict(kind=kind, changed=hits, after=after, interval=interval, evidence=evidence,
                          confidence=confidence, apply=kind != "unknown", form=loc.shape_form,
                          reference=loc.reference)


def _verdict_warnings(free: _FreeFit, m: int, verdict: ElementVerdict, alpha: float) -> list:
    """What limits the verdict on element ``m``: a best delay at the edge of its range, no change found."""
    name = free.row.name(free.js[m])
    out = []
    if free.est.edge[m]:
        lo, hi = free.specs[free.js[m]].window
        out.append(f"{name}: the best delay lies at the edge of the searched range (input lags {lo} to {hi} "
                   f"samples); the true delay may lie outside it (the repair searches RepairOptions.max_delay_shift "
                   f"samples either side of the model's delay, widened {MAX_WIDENINGS} times at most while the "
                   f"record is long enough).")
    if verdict.kind == "unknown":
        form = free.located[free.js[m]].shape_form
        shape = "first-order-plus-dead-time form" if form.first_order else f"the element's form ({form.describe()})"
        out.append(
            f"{name}: located as mismatched, but no parameter of the element differs "
            f"significantly from the model (at {100 * (1 - alpha):.4g}% confidence); the element is kept. "
            f"The mismatch may be too small for these data or not of {shape}.")
    return out


def _classify_row(row: _RowData, js, settings: _TestSettings):
    """Classify the located elements ``js`` of the row on the whole record.

    Returns
    -------
    free : _FreeFit
        The fit with everything free (the start of the repair fit).
    verdicts : dict
        ``{j: ElementVerdict}``, ``after`` and ``interval`` from the free fit.
    warnings : list of str
    """
    alpha = settings.alpha
    free = _fit_free(row, js, settings)
    warnings = []
    summaries, tests = _single_tests(free, settings)
    joint_p = _joint_hold(free, tests, settings, warnings)
    verdicts = {}
    for m, j in enumerate(free.js):
        verdicts[j] = _verdict(free.est, summaries[j], tests[j], joint_p, alpha, free.located[j],
                               row.model.is_step_response)
        warnings.extend(_verdict_warnings(free, m, verdicts[j], alpha))
    if free.est.cond > 1e3 and len(free.js) > 1:
        names_u = row.model.columns
        warnings.append(
            f"{row.name()}: the inputs {', '.join(names_u[j] for j in free.js)} move together in these data "
            f"(condition number {free.est.cond:.3g}); their elements are hard to tell apart. More independent "
            f"excitation of these inputs (dither) would help.")
    return free, verdicts, warnings
