"""The experiment that resolves what a window cannot: a PRBS dither per input and how long to run it.

When the closed loop moves some inputs together (an MPC with more inputs than outputs always does)
their elements are ambiguous, and when the excitation is weak no element may be decidable at all.
:func:`design_experiment` then recommends the smallest experiment that resolves it:

* a PRBS dither (``+- amplitude``, switching with probability 1/2 every sample, so white) added to
  some inputs, with an amplitude per input in input units, at most half of the input's standard
  deviation in the window (:data:`MAX_AMPLITUDE`);
* a number of samples to record with it.

The prediction uses the window's own information (:class:`~mpm_monitor.core.detectability.WindowInformation`):
per sample, a white dither of amplitude ``a_j`` on input ``j`` adds ``a_j^2 I`` to the moments of
``j``'s lags (``Z'Z / n``) and ``a_j^2 h_ij(l)`` to the cross moments of lag ``l`` with the target of
element ``(i, j)`` (``h_ij`` the impulse response of ``A_i(q) Phat_ij(q)``); the closed loop's own
excitation stays as it was.  With these moments the detectable gain change of a window of ``N``
samples is the one of :mod:`mpm_monitor.core.detectability` (``q`` grows as ``N``); an element the
model has also gets its whole-response test's, from the window's information of that test per
sample plus the dither's share on the element's input (:meth:`_Predictor.response_rate`), and
takes the smaller of the two (it is located when either test rejects).  The
separation of the inputs is the variance inflation of every lag block (as
:class:`~mpm_monitor.core.input_design.InputDesign` decides it, with a margin of
:data:`SEPARATION_MARGIN`).

The goal: every input whose elements are ambiguous is separated, and a gain error of
:data:`GOAL` (20 %) of every element of those inputs (of every element, when nothing was
decidable at that level) is detected with probability 0.9.  The experiment is the smallest that
reaches it: the fewest dithered inputs, then the smallest ``amplitude x samples`` (the amplitude
relative to its largest allowed value; every dithered input gets the same fraction of it).  It lasts
at least the samples the tests accept and the samples the repair needs to re-estimate the
elements it locates (a fit part of at least 200 samples, ``20 (2 columns + noise
order + 5)`` for a larger model, once the held-out quarter is set apart).
"""

from __future__ import annotations

import dataclasses
import decimal
import itertools
import math
from typing import Optional

import numpy as np

from .detectability import CHUNK, WindowInformation, moment_inverse, required_noncentrality
from .noise_polynomial import undetermined_rows

#: Relative gain error the experiment must detect with probability 0.9.
GOAL = 0.2
#: Largest dither amplitude, as a fraction of the input's standard deviation in the window.
MAX_AMPLITUDE = 0.5
#: Most samples an experiment may last.
MAX_SAMPLES = 20000
#: The predicted variance inflation of a lag block must stay below ``1 / (threshold * margin)``.
SEPARATION_MARGIN = 2.0
#: Fractions of the largest amplitude tried.
AMPLITUDE_FRACTIONS = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
#: Subsets of inputs evaluated per size at most (the best at full amplitude are refined).
REFINED_SUBSETS = 3
#: Subsets of the candidate inputs tried at most, over all sizes (each trial a prediction of the tests): a size
#: with more subsets than are left is not searched, the next larger one is (all the inputs at once is always
#: tried).  Up to 8 candidate inputs every subset is tried; without the bound a window of 12 inputs where no
#: subset reaches the goal took a minute, and 40 inputs did not finish.
MAX_SUBSET_TRIALS = 256
#: Samples are rounded up to a multiple of this.
SAMPLES_STEP = 50
#: Multiples of the largest amplitude tried, in the ``why`` only, when the goal is out of reach within it
#: (the experiment itself stays within :data:`MAX_AMPLITUDE`).
BEYOND_CAP = (1.5, 2.0, 3.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 50.0, 70.0, 100.0)


@dataclasses.dataclass
class Experiment:
    """A recommended dither experiment (docs/interfaces.md, "Detectability and experiment").

    Attributes
    ----------
    dither : dict
        Input name -> PRBS amplitude in input units (the dither is ``+- amplitude``, switching with
        probability 1/2 every sample).
    samples : int
        Samples to record with the dither on.
    expected_detectable_gain_change : float
        Predicted largest detectable gain change of the elements the experiment is for, on a window
        of ``samples`` dithered samples (at most :data:`GOAL` when the goal is reachable).
    why : str
        What the experiment resolves and why this one, in words.
    beyond : dict or None
        When the goal is out of reach within the allowed amplitudes: the larger dither the ``why`` names,
        ``{"multiple": k, "dither": {input: amplitude}, "samples": N}`` (None when the goal is reached, or
        no multiple up to the last of :data:`BEYOND_CAP` reaches it).  Not in the JSON (:meth:`to_dict`).
    """

    dither: dict
    samples: int
    expected_detectable_gain_change: float
    why: str
    beyond: Optional[dict] = None

    def to_dict(self) -> dict:
        """The JSON object ``{"dither": {...}, "samples": N, "expected_detectable_gain_change": x, "why": "..."}``."""
        x = self.expected_detectable_gain_change
        return {"dither": {k: float(v) for k, v in self.dither.items()}, "samples": int(self.samples),
                "expected_detectable_gain_change": float(x) if x is not None and math.isfinite(x) else None,
                "why": self.why}


@dataclasses.dataclass(frozen=True)
class _Trial:
    inputs: tuple
    fraction: float
    samples: float
    worst: float
    separated: bool

    @property
    def cost(self) -> float:
        return self.fraction * self.samples


def _names(model, cols) -> str:
    return ", ".join(model.columns[j] for j in cols)


def _g(x: float) -> str:
    return f"{x:.3g}"


class _Predictor:
    """The detectability and separation of a window with a dither, predicted from one window's information."""

    def __init__(self, info: WindowInformation, targets: list, alpha: float, threshold: float, layout,
                 testable: list):
        self.info, self.targets, self.alpha = info, targets, alpha
        self.max_vif = 1.0 / (threshold * SEPARATION_MARGIN)
        self.start, self.min_samples = layout.start, layout.min_samples
        self.testable = set(testable)
        self.inputs = sorted({j for _, j in targets})
        self.n_rows_tested = len(info.noise)
        self._lam = {}
        self._energy = {}

    def evaluate(self, amplitudes: dict) -> tuple:
        """(separated, per-sample information of every target, family size) with these dither amplitudes.

        The information is ``{key: (q, rate)}``: the per-sample drop ``q`` of the window test
        (:class:`WindowInformation`) and the per-sample information ``rate`` of the whole-response
        test (0 for a target without one); None when the inputs are not separated.
        """
        info = self.info
        L = info.n_lag
        G = info.G.copy()
        for j, a in amplitudes.items():
            sl = info.block(j)
            G[sl, sl] += a * a * np.eye(L)
        H = moment_inverse(G)
        family = self.n_rows_tested * len(self.testable | set(amplitudes))
        for j in self.inputs:
            sl = info.block(j)
            try:
                Lj = np.linalg.cholesky(G[sl, sl])
            except np.linalg.LinAlgError:
                return False, None, family
            if not np.linalg.eigvalsh(Lj.T @ H[sl, sl] @ Lj)[-1] < self.max_vif:
                return False, None, family
        worse = []
        for a in range(0, len(self.targets), CHUNK):      # the moments of each target once, for both signs
            part = self.targets[a:a + CHUNK]
            st = info.stacked(part, H, amplitudes)
            worse.append(np.minimum(*(info.drops(part, H, [sign * GOAL] * len(part), stacked=st) for sign in (1, -1))))
        drops = np.concatenate(worse).tolist() if worse else []
        return True, {key: (q, self.response_rate(key, amplitudes)) for key, q in zip(self.targets, drops)}, family

    def response_rate(self, key, amplitudes: dict) -> float:
        """Per-sample information of target ``key``'s whole-response test with these dither amplitudes.

        The window's own (``WindowInformation.responses``, 0 when the target had no such test) plus
        the dither's on the target's input: a white dither of amplitude ``a`` adds ``a^2 sum_l h(l)^2``
        to the per-sample energy of the test's regressor ``A_i(q) Phat_ij u_j`` (``h`` the
        target's :attr:`~mpm_monitor.core.detectability.ElementTarget.filtered` impulse response),
        independent of the other regressors, so ``a^2 sum h^2 / sigma_i^2`` to its information.  The
        dither's effect on the other inputs' collinearity with it is left out (it only adds).
        """
        own = self.info.responses.get(key)
        if own is None:
            return 0.0
        a = amplitudes.get(key[1], 0.0)
        if not a:
            return own[0]
        if key not in self._energy:
            h = self.info.targets[key].filtered
            self._energy[key] = float(h @ h)
        return own[0] + a * a * self._energy[key] / self.info.noise[key[0]].sigma2

    def _lambda(self, k: int, rows: float, p: int, na: int, level: float) -> float:
        key = (k, max(int(rows) - p - na, 1), level)
        if key not in self._lam:
            self._lam[key] = required_noncentrality(key[0], key[1], level)
        return self._lam[key]

    def _level(self, key, family: int) -> float:
        """The window test's level for target ``key``: half of it where the element will have the
        whole-response test too (:meth:`WindowInformation.split_of`)."""
        return self.info.level(family, self.alpha, self.info.split_of(key))

    def _need(self, key, q: float, rate: float, family: int, rows: float, p: int) -> float:
        """``delta^2 x`` rows target ``key`` needs for a gain change ``delta`` detected with probability
        0.9: the smaller of its window test's ``lambda sigma^2 / q`` and its whole-response test's
        ``lambda / rate`` (the element is located when either rejects); infinite without information."""
        info = self.info
        nz = info.noise[key[0]]
        level = self._level(key, family)
        need = self._lambda(info.targets[key].tested.size, rows, p, nz.a.size, level) * nz.sigma2 / q \
            if q > 0 else math.inf
        if rate > 0:
            need = min(need, self._lambda(info.responses[key][1], rows, p, nz.a.size, level) / rate)
        return need

    def samples_needed(self, drops: dict, family: int, p: int) -> float:
        """Samples for :data:`GOAL` on every target (infinite when some target gets no information)."""
        rows = 3000.0
        for _ in range(3):
            worst = max((self._need(key, q, rate, family, rows, p) for key, (q, rate) in drops.items()), default=0.0)
            if not math.isfinite(worst):
                return math.inf
            rows = max(worst / GOAL ** 2, p + 60.0)
        return rows + self.start

    def worst_at(self, drops: dict, family: int, samples: int, p: int) -> float:
        """Largest detectable change of the targets on ``samples`` samples."""
        rows = max(samples - self.start, 1)
        worst = max((self._need(key, q, rate, family, rows, p) for key, (q, rate) in drops.items()), default=0.0)
        return math.sqrt(worst / rows) if math.isfinite(worst) else math.inf


def _caps(info: WindowInformation, model, candidates: list) -> tuple:
    """Largest amplitude of every candidate input, and the inputs that did not move."""
    std = info.std
    still = [j for j in candidates if j not in info.testable]
    caps = {j: MAX_AMPLITUDE * float(std[j]) for j in candidates if j in info.testable}
    if still:
        gains = np.abs(model.gain)
        moving = [j for j in info.testable]
        if moving:
            effects = [gains[i, k] * MAX_AMPLITUDE * std[k] for i in range(model.n_outputs) for k in moving
                       if gains[i, k] > 0]
            effect = float(np.median(effects)) if effects else 0.0
        else:
            effect = 0.0
        if effect <= 0:
            sig = [math.sqrt(nz.sigma2) for nz in info.noise.values()]
            effect = 5.0 * float(np.median(sig)) if sig else 1.0
        for j in still:
            col = gains[:, j][gains[:, j] > 0]
            ref = float(np.median(col)) if col.size else float(np.median(gains[gains > 0])) if np.any(gains > 0) else 1.0
            caps[j] = effect / ref
    return caps, still


def _small_directions(info: WindowInformation, cols: list, threshold: float) -> int:
    """Near-null directions of the inputs' correlation (each needs a dithered input of its own)."""
    if len(cols) < 2:
        return 0
    L = info.n_lag
    idx = [j * L for j in cols]
    C = info.G[np.ix_(idx, idx)]
    s = np.sqrt(np.maximum(np.diag(C), 1e-300))
    w = np.linalg.eigvalsh(C / np.outer(s, s))
    return int(np.sum(w < 10 * threshold * max(w.mean(), 1e-300)))


def design_experiment(model, info: Optional[WindowInformation], elements: list, options,
                      layout) -> Optional[Experiment]:
    """The smallest dither experiment that resolves what the window could not decide (module docstring).

    Parameters
    ----------
    model : PlantModel
    info : WindowInformation or None
        The window's information (None: no ARX element test ran; no experiment).
    elements : list of ElementResult
        The element decisions, with their ``detectable_gain_change``.
    options : AnalysisOptions
        Its ``alpha`` and ``collinearity_threshold``.
    layout : RegressionLayout
        First regression row of a window (``start``) and the fewest samples the tests accept
        (``min_samples``): the experiment lasts at least that long.

    Returns
    -------
    Experiment or None
        None when no element is ambiguous and some element is decidable at :data:`GOAL`.
    """
    if info is None or not info.noise:
        return None
    index = {(model.outputs.index(e.output), model.columns.index(e.input)): e for e in elements}
    located = {k for k, e in index.items() if e.mismatch}
    ambiguous = [k for k, e in index.items() if e.ambiguous and k not in located and k in info.targets]
    values = [e.detectable_gain_change for e in index.values() if not e.ambiguous
              and e.detectable_gain_change is not None and math.isfinite(e.detectable_gain_change)]
    decidable = any(v <= GOAL for v in values)
    if not ambiguous and (decidable or not index):
        return None
    targets = set(ambiguous)
    if not decidable:
        targets |= {k for k in index if k not in located and k in info.targets}
    # Only manipulated inputs can be dithered: a measured disturbance's element is a target only when
    # it moves (a dither on the inputs it moves with separates it from them).
    targets = sorted(k for k in targets if model.role(k[1]) == "input" or k[1] in info.testable)
    with_inputs = {model.columns.index(name) for k in ambiguous for name in index[k].ambiguous_with}
    candidates = sorted(j for j in {j for _, j in targets} | with_inputs if model.role(j) == "input")
    if not targets or not candidates:
        return None
    caps, still = _caps(info, model, candidates)
    testable_c = [j for j in candidates if j not in still]
    pred = _Predictor(info, targets, options.alpha, options.collinearity_threshold, layout, info.testable)
    # Long enough for the repair too (whether or not this analysis repaired: the one of the experiment's log
    # will): an experiment that locates the element and leaves too few samples to re-estimate it ("Only 188
    # samples are available ... at least 260 needed", every 1 x 2 run of an outside check) does not say how to
    # fix the model.
    from .repair.options import RepairOptions
    from .repair.record import samples_for_repair

    pred.min_samples = max(pred.min_samples, samples_for_repair(model, RepairOptions()))
    p = info.G.shape[0]
    lowest = max(_small_directions(info, testable_c, options.collinearity_threshold), 0 if still else 1)
    best = None
    budget = MAX_SUBSET_TRIALS
    for size in range(lowest, len(testable_c) + 1):
        count = math.comb(len(testable_c), size)
        if count > budget and size < len(testable_c):
            continue
        budget -= count
        trials = []
        for extra in itertools.combinations(testable_c, size):
            chosen = tuple(sorted(set(still) | set(extra)))
            if not chosen:
                continue
            trial = _trial(pred, chosen, caps, 1.0, p)
            if trial.separated and trial.samples <= MAX_SAMPLES:
                trials.append(trial)
        if trials:
            trials.sort(key=lambda t: t.cost)
            for t in trials[:REFINED_SUBSETS]:
                prev = t
                for f in reversed(AMPLITUDE_FRACTIONS[:-1]):   # smaller amplitudes while the cost falls
                    tf = _trial(pred, t.inputs, caps, f, p)
                    if not (tf.separated and tf.samples <= MAX_SAMPLES) or tf.cost >= prev.cost:
                        break
                    trials.append(tf)
                    prev = tf
            best = min(trials, key=lambda t: (t.cost, t.samples))
            break
    reached = best is not None
    beyond = None
    if best is None:   # the goal is out of reach: every candidate at its largest amplitude, as long as allowed
        best = _Trial(tuple(candidates), 1.0, MAX_SAMPLES, math.inf, False)
        beyond = _beyond_cap(pred, tuple(candidates), caps, p)
    samples = min(_rounded_samples(best), MAX_SAMPLES)
    separated, drops, family = pred.evaluate({j: best.fraction * caps[j] for j in best.inputs})
    worst = pred.worst_at(drops, family, samples, p) if separated else math.inf
    dither = _dither(model, best, caps)
    larger = None if beyond is None else {"multiple": beyond.fraction, "dither": _dither(model, beyond, caps),
                                          "samples": _rounded_samples(beyond)}
    return Experiment(dither=dither, samples=samples, expected_detectable_gain_change=worst,
                      why=_why(model, info, best, dither, still, ambiguous, decidable, values, targets, samples, worst,
                               reached, larger), beyond=larger)


def _dither(model, trial: _Trial, caps: dict) -> dict:
    """Input name -> amplitude (three significant digits) of ``trial``'s dither.  Within the caps (``fraction``
    at most 1, the recommended dither) never above its input's cap: an amplitude at the cap rounded to the
    nearest (0.3747 to 0.375, over a cap of 0.37465) is rounded down; a multiple beyond them (the ``beyond``
    of an experiment out of reach) is rounded to the nearest."""
    out = {}
    for j in trial.inputs:
        x = trial.fraction * caps[j]
        a = float(f"{x:.3g}")
        out[model.inputs[j]] = a if a <= caps[j] or trial.fraction > 1 else _three_digits_down(x)
    return out


def _three_digits_down(x: float) -> float:
    """``x`` > 0 cut to three significant digits (rounded towards 0)."""
    d = decimal.Decimal(repr(float(x)))
    exponent = d.adjusted() - 2
    return float(d.scaleb(-exponent).to_integral_value(rounding=decimal.ROUND_DOWN).scaleb(exponent))


def _rounded_samples(trial: _Trial) -> int:
    """``trial``'s samples rounded up to a multiple of :data:`SAMPLES_STEP`."""
    return int(math.ceil(trial.samples / SAMPLES_STEP) * SAMPLES_STEP)


def _beyond_cap(pred: _Predictor, inputs: tuple, caps: dict, p: int) -> Optional[_Trial]:
    """The smallest multiple of the largest amplitudes (:data:`BEYOND_CAP`) on ``inputs`` predicted to reach the
    goal within :data:`MAX_SAMPLES`, or None up to the last: for the ``why`` of an experiment out of reach.

    The multiples are searched by bisection (more dither never needs more samples): at most five evaluations.
    """
    def reaches(k: int) -> Optional[_Trial]:
        t = _trial(pred, inputs, caps, BEYOND_CAP[k], p)
        return t if t.separated and t.samples <= MAX_SAMPLES else None

    found = reaches(len(BEYOND_CAP) - 1)
    if found is None:
        return None
    lo, hi = -1, len(BEYOND_CAP) - 1          # BEYOND_CAP[hi] reaches; BEYOND_CAP[lo] (or the cap itself) does not
    while hi - lo > 1:
        mid = (lo + hi) // 2
        t = reaches(mid)
        if t is None:
            lo = mid
        else:
            hi, found = mid, t
    return found


def _trial(pred: _Predictor, inputs: tuple, caps: dict, fraction: float, p: int) -> _Trial:
    separated, drops, family = pred.evaluate({j: fraction * caps[j] for j in inputs})
    if not separated:
        return _Trial(inputs, fraction, math.inf, math.inf, False)
    return _Trial(inputs, fraction, max(pred.samples_needed(drops, family, p), pred.min_samples), GOAL, True)


def _why(model, info, best: _Trial, dither: dict, still, ambiguous, decidable, values, targets, samples, worst,
         reached, beyond: Optional[dict] = None) -> str:
    """The ``why`` of an experiment; ``dither`` is its amplitudes as recommended (:func:`_dither`), which the text
    quotes as they are (a dither at its cap is rounded down there, and the text said the nearest)."""
    parts = []
    amb_inputs = sorted({j for _, j in ambiguous})
    moving_amb = [j for j in amb_inputs if j not in still]
    if moving_amb:
        together = "with the other inputs" if len(moving_amb) == 1 else "together"
        parts.append(f"the closed loop moves {_names(model, moving_amb)} {together}, so the elements of "
                     f"{'that input' if len(moving_amb) == 1 else 'these inputs'} cannot be told apart from these data")
    if still:
        parts.append(f"{_names(model, still)} did not move at all in this window, so "
                     f"{'its' if len(still) == 1 else 'their'} elements cannot be tested")
    feedback = undetermined_rows(info.noise)
    if feedback:
        parts.append(f"the input lags and the prediction error's own lags are nearly collinear in "
                     f"row{'s' if len(feedback) > 1 else ''} {', '.join(model.outputs[i] for i in feedback)} (inputs "
                     "that move only with the controller's feedback, or a prediction error without noise), so these "
                     "data cannot value a gain error there")
    if not decidable:
        low = min(values) if values else math.inf
        # The ambiguous elements' values are left out (not calibrated: they may read below 20 %).
        which = "no element that these data tell apart" if ambiguous else "no element"
        parts.append(f"{which} is decidable at the 20% level in this window"
                     + (f" (the smallest detectable gain change is {_g(low)})" if math.isfinite(low) else ""))
    dith = ", ".join(f"{model.inputs[j]} ({_g(dither[model.inputs[j]])}"
                     + (f", {_g(best.fraction * MAX_AMPLITUDE)} of its standard deviation {_g(info.std[j])})"
                        if j not in still else ")") for j in best.inputs)
    text = "; ".join(parts) + ". " if parts else ""
    target_inputs = sorted({j for _, j in targets})
    text += (f"A PRBS dither (+- amplitude, switching with probability 1/2 every sample) on {dith} for {samples} "
             f"samples ")
    goal = (f"detect a {GOAL:.0%} gain error of every element of {_names(model, target_inputs)} with probability "
            f"0.9 (predicted detectable gain change {_g(worst)})")
    if reached:
        text += ("is predicted to separate the inputs and " if moving_amb else "is predicted to ") + goal + \
            "; it is the smallest experiment that does (fewest inputs, then smallest amplitude times samples)."
    else:
        cap = "half of each input's standard deviation" if not still else \
            "half of each moving input's standard deviation, the still ones' as below"
        text += (f"is the largest allowed ({cap}, {MAX_SAMPLES} samples) and still does not reach the goal: predicted "
                 f"detectable gain change {_g(worst)}.")
        if beyond is not None:
            more = ", ".join(f"{name} {_g(a)}" for name, a in beyond["dither"].items())
            text += (f" A dither {beyond['multiple']:g} times as large ({more}) is predicted to reach it in "
                     f"{beyond['samples']} samples; the recommended one stays within what the data show the inputs "
                     "move, so check whether the process allows more.")
        else:
            text += (f" No dither up to {BEYOND_CAP[-1]:g} times as large is predicted to reach it within "
                     f"{MAX_SAMPLES} samples.")
    if still:
        basis = ("the effect on the outputs of a dither of half the standard deviation of the inputs that moved"
                 if info.testable else "five times the noise of the prediction error on the outputs (no input moved)")
        text += (f" {_names(model, still)} did not move, so {'its' if len(still) == 1 else 'their'} amplitude is not "
                 f"bounded by an observed spread: it is chosen so that its effect on the outputs matches {basis}; "
                 "check that the process allows it.")
    return text
