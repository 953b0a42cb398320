"""Options of the repair, their check, and the test levels they fix."""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from ..errors import ConfigurationError
from ..signals import INITIAL_STATE_CHOICES
from ..statistics import chi2_isf, normal_isf

#: The kinds of mismatch a located element can be given (``unknown``: no significant change).
KINDS = ("gain", "time_constant", "delay", "missing", "mixed", "unknown")


@dataclasses.dataclass(frozen=True)
class RepairOptions:
    """Options of :func:`repair_model`.

    Attributes
    ----------
    holdout_fraction : float
        Fraction of the record at its end kept out of the fit and used to validate the repair,
        in [0, 0.5].  0 disables the validation (with a warning).
    max_delay_shift : int
        Samples searched on either side of a located element's model delay (>= 0).  For an
        element the model does not have (gain 0) the search runs from 0 to the row's largest
        delay plus this many samples.
    noise_order : int
        Order ``p`` of the AR noise model ``A(q)`` of the prediction-error fit (0 = output error) and of the
        held-out check's one-step errors (and of the disturbance tests, unless ``disturbance_noise_order``).
        :func:`~mpm_monitor.core.pipeline.analyze` sets it to the tests' ``na`` where that is larger
        (:func:`~mpm_monitor.core.pipeline.repair_noise_order`): 4 lags leave a slow drift under white noise
        coloured, and the intervals too narrow.
    confidence_level : float
        Level of the reported intervals and of the "significant change" decisions, in (0.5, 1): a
        parameter changed when the model's value lies outside its interval.  The default 0.999 is
        strict because the gain and the time constant of an element trade off against each other
        when inputs move together, which in a few thousand samples biases them by a fraction of a
        standard error; real mismatches worth a repair lie far outside.
    min_relative_change : float
        Smallest relative change of a gain or time constant that counts as a change, in [0, 1).
    refit_on_all : bool
        After a successful validation, refit the accepted elements on the whole record (delays
        searched again within a few samples of the validated ones).
    disturbance_alpha : float
        False-alarm probability of the unexplained-disturbance checks, all outputs together (Holm's
        procedure over the outputs; each output's check split equally between the step and the drift
        test), in (0, 0.5).
    disturbance_noise_order : int or None
        AR terms of the unexplained-disturbance tests' regressions (None: ``noise_order``), in [0, 50].
        :func:`~mpm_monitor.core.pipeline.analyze` keeps them at 4 when it raises ``noise_order``: their
        confirmation on a longer AR holds what 4 lags leave (:mod:`.disturbance`), and each simulated record's
        regression costs the square of its columns (16 lags: a log with a step on each of 20 outputs took 25.8 s
        where 4 take 10.2 s).
    disturbance_trim : float
        Fraction of the record at each end where a step is not searched (sup-Wald trimming), in
        [0.05, 0.3].
    disturbance_draws : int
        Simulated records with which a disturbance the checks would report is confirmed: both statistics
        are scaled by what they read on the output's own fitted noise against white noise before their
        p-values are taken (:meth:`~mpm_monitor.core.repair.disturbance._Design.null_scale`; with slow
        noise the asymptotic tails are too light), in [0, 100000]; 0: the asymptotic p-values alone (the
        rule before stop 86).
    disturbance_seed : int
        Seed of those simulations (>= 0): the same record gives the same report.
    min_holdout_improvement : float
        Relative reduction of the held-out RMS error that a row repair must achieve, in [0, 1).
    holdout_one_step : bool
        Also accept a row repair whose held-out one-step error under its own AR noise model (order
        ``noise_order`` > 0) falls by ``min_holdout_improvement``, significantly, while its held-out
        simulation error does not rise significantly (each at ``holdout_alpha``) nor by more than
        ``holdout_tolerance``.  In a closed loop the simulation error carries the disturbance the controller
        answered through the same inputs, which can make the right element's simulation error slightly larger
        than the model's; the one-step errors do not.  False: the simulation error alone decides (the rule
        before stop 77; ``bench.holdout_mc`` scores the three rules against the plant).
    holdout_tolerance : float or None
        Largest relative rise of the held-out simulation error over the model's with which the one-step route
        (``holdout_one_step``) accepts a repair, in [0, 1]; None: any rise that is not significant (the route
        as it was before stop 77).  The default 0.05 bounds what a wrong candidate the route lets through can
        cost in simulation: on ``bench.holdout_mc``'s loops the deliberately wrong candidates it adds are no
        farther from the plant than those the simulation error alone accepts, while the unbounded route also
        passed some up to four times the model's distance.
    holdout_alpha : float
        Level of the one-sided tests that the held-out one-step error fell and that the simulation
        error rose (Diebold–Mariano, Newey–West variance), in (0, 0.5).
    initial_state : {"estimate", "zero"}
        How the model's state at the first sample is treated (as in
        :func:`mpm_monitor.core.signals.compute_signals`); with "estimate" the fit also estimates the
        free response of the row.
    max_sweeps : int
        Coordinate sweeps of the delay search over the elements of a row (>= 1).
    max_gap : int or None
        Data with gaps: the longest gap (missing samples) the model is simulated through, its
        columns held (:func:`mpm_monitor.core.signals.segment_signals`), for the prediction errors,
        the held-out check and the errors before and after; None: every segment from its own start.
        The fits take every segment from its own start either way.
    """

    holdout_fraction: float = 0.25
    max_delay_shift: int = 10
    noise_order: int = 4
    confidence_level: float = 0.999
    min_relative_change: float = 0.05
    refit_on_all: bool = True
    disturbance_alpha: float = 0.01
    disturbance_noise_order: Optional[int] = None
    disturbance_trim: float = 0.15
    disturbance_draws: int = 200
    disturbance_seed: int = 0
    min_holdout_improvement: float = 0.0
    holdout_one_step: bool = True
    holdout_tolerance: Optional[float] = 0.05
    holdout_alpha: float = 0.05
    initial_state: str = "estimate"
    max_sweeps: int = 3
    max_gap: Optional[int] = None

    def __post_init__(self):
        check_repair_options(self)

    @property
    def test_order(self) -> int:
        """The AR terms of the disturbance tests: ``disturbance_noise_order``, or ``noise_order``."""
        return self.noise_order if self.disturbance_noise_order is None else int(self.disturbance_noise_order)


def is_int(x) -> bool:
    """An integer (Python's or numpy's), not a boolean."""
    return isinstance(x, (int, np.integer)) and not isinstance(x, bool)


def check_repair_options(opts: RepairOptions) -> None:
    """Raise :class:`ConfigurationError` naming the first option outside its range."""

    def is_num(x):
        return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool) and math.isfinite(x)

    if not (is_num(opts.holdout_fraction) and 0.0 <= opts.holdout_fraction <= 0.5):
        raise ConfigurationError(f"holdout_fraction: expected a number in [0, 0.5], got {opts.holdout_fraction!r}")
    if not (is_int(opts.max_delay_shift) and 0 <= opts.max_delay_shift <= 1000):
        raise ConfigurationError(f"max_delay_shift: expected an integer number of samples in [0, 1000], "
                                 f"got {opts.max_delay_shift!r}")
    if not (is_int(opts.noise_order) and 0 <= opts.noise_order <= 50):
        raise ConfigurationError(f"noise_order: expected an integer in [0, 50], got {opts.noise_order!r}")
    if not (opts.disturbance_noise_order is None
            or (is_int(opts.disturbance_noise_order) and 0 <= opts.disturbance_noise_order <= 50)):
        raise ConfigurationError(f"disturbance_noise_order: expected None or an integer in [0, 50], "
                                 f"got {opts.disturbance_noise_order!r}")
    if not (is_num(opts.confidence_level) and 0.5 < opts.confidence_level < 1.0):
        raise ConfigurationError(f"confidence_level: expected a number in (0.5, 1), got {opts.confidence_level!r}")
    if not (is_num(opts.min_relative_change) and 0.0 <= opts.min_relative_change < 1.0):
        raise ConfigurationError(f"min_relative_change: expected a number in [0, 1), got {opts.min_relative_change!r}")
    if not isinstance(opts.refit_on_all, bool):
        raise ConfigurationError(f"refit_on_all: expected true or false, got {opts.refit_on_all!r}")
    if not (is_num(opts.disturbance_alpha) and 0.0 < opts.disturbance_alpha < 0.5):
        raise ConfigurationError(f"disturbance_alpha: expected a number in (0, 0.5), got {opts.disturbance_alpha!r}")
    if not (is_num(opts.disturbance_trim) and 0.05 <= opts.disturbance_trim <= 0.3):
        raise ConfigurationError(f"disturbance_trim: expected a number in [0.05, 0.3], got {opts.disturbance_trim!r}")
    if not (is_int(opts.disturbance_draws) and 0 <= opts.disturbance_draws <= 100000):
        raise ConfigurationError(f"disturbance_draws: expected an integer in [0, 100000], "
                                 f"got {opts.disturbance_draws!r}")
    if not (is_int(opts.disturbance_seed) and opts.disturbance_seed >= 0):
        raise ConfigurationError(f"disturbance_seed: expected an integer >= 0, got {opts.disturbance_seed!r}")
    if not (is_num(opts.min_holdout_improvement) and 0.0 <= opts.min_holdout_improvement < 1.0):
        raise ConfigurationError(f"min_holdout_improvement: expected a number in [0, 1), "
                                 f"got {opts.min_holdout_improvement!r}")
    if not isinstance(opts.holdout_one_step, bool):
        raise ConfigurationError(f"holdout_one_step: expected true or false, got {opts.holdout_one_step!r}")
    if opts.holdout_tolerance is not None and not (is_num(opts.holdout_tolerance)
                                                   and 0.0 <= opts.holdout_tolerance <= 1.0):
        raise ConfigurationError(f"holdout_tolerance: expected None or a number in [0, 1], "
                                 f"got {opts.holdout_tolerance!r}")
    if not (is_num(opts.holdout_alpha) and 0.0 < opts.holdout_alpha < 0.5):
        raise ConfigurationError(f"holdout_alpha: expected a number in (0, 0.5), got {opts.holdout_alpha!r}")
    if opts.initial_state not in INITIAL_STATE_CHOICES:
        raise ConfigurationError(f"initial_state: expected one of {', '.join(INITIAL_STATE_CHOICES)}, "
                                 f"got {opts.initial_state!r}")
    if not (is_int(opts.max_sweeps) and 1 <= opts.max_sweeps <= 20):
        raise ConfigurationError(f"max_sweeps: expected an integer in [1, 20], got {opts.max_sweeps!r}")
    if opts.max_gap is not None and not (is_int(opts.max_gap) and opts.max_gap >= 0):
        raise ConfigurationError(f"max_gap: expected None or an integer number of samples >= 0, got {opts.max_gap!r}")


@dataclasses.dataclass(frozen=True)
class _TestSettings:
    """The levels every test and interval of one repair uses, fixed by the options.

    Attributes
    ----------
    options : RepairOptions
    alpha : float
        ``1 - confidence_level``: the level of the likelihood-ratio tests.
    zcrit : float
        Two-sided standard normal quantile at ``alpha`` (intervals of gains and poles).
    chi_crit : float
        Chi-square(1) quantile at ``alpha`` (profile interval of a delay).
    """

    options: RepairOptions
    alpha: float
    zcrit: float
    chi_crit: float

    @classmethod
    def of(cls, options: RepairOptions) -> "_TestSettings":
        alpha = 1.0 - options.confidence_level
        return cls(options=options, alpha=alpha, zcrit=float(normal_isf(alpha / 2)),
                   chi_crit=float(chi2_isf(alpha, 1)))
