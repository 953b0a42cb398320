"""The options of the analysis, each declared once with its default, description and range.

:class:`AnalysisOptions` holds them for :func:`mpm_monitor.core.analysis.detect` and
:func:`mpm_monitor.core.pipeline.analyze`; :data:`ANALYSIS_PARAMS` gives their specs by name, the one
source of the command line's analysis flags and the monitor node's analysis parameters.  Callers
import :class:`AnalysisOptions` from :mod:`mpm_monitor.core.analysis`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

from .errors import ConfigurationError
from .options import check_options, option, option_specs
from .signals import INITIAL_STATE_CHOICES

METHODS = ("arx", "xcorr", "pcorr")
ELEMENT_WINDOWS = ("model", "full")


@dataclasses.dataclass(frozen=True)
class AnalysisOptions:
    """Options of the analysis (:func:`~mpm_monitor.core.analysis.detect`, :func:`mpm_monitor.core.pipeline.analyze`).

    Each field is declared with its default, description and range once
    (:func:`mpm_monitor.core.options.option`); :data:`ANALYSIS_PARAMS` holds them as
    :class:`~mpm_monitor.core.options.ParamSpec` and every value is checked by them on creation
    (:func:`check_analysis_options`), a number converted to the field's type.

    Attributes
    ----------
    na : int
        Order of the ARX ``A`` polynomials (paper: 4): the first order tried, see ``max_na``.
    max_na : int
        Largest ARX order :func:`~mpm_monitor.core.pipeline.analyze` raises ``na`` to when the element
        test's residuals are not white (:mod:`mpm_monitor.core.noise_order`: a slow drift under the
        measurement noise needs more own lags than the paper's 4, and a coloured residual in closed loop
        gives false alarms): ``na`` doubles (4, 8, 16) while some row's residual is coloured, at most to
        ``max_na`` (default 16; at most ``na`` keeps ``na`` whatever the residuals).
    nb : int
        Length of the ARX ``B`` polynomials once the delay is known (paper: 4); the tests use
        ``max_delay + nb`` lags so that the delay need not be known.
    alpha : float
        False-alarm rate of the whole analysis, in (0, 0.5): when the model matches the plant, the
        probability that any row or any element is reported mismatched is at most ``alpha``.  It
        is split equally (Bonferroni) between the row tests and the element tests, each family
        controlled by Holm's procedure; the reported ``p_value`` of a row or element is adjusted
        for both, so a finding is reported exactly when ``p_value < alpha``.
    band : tuple of float
        Band ``Omega`` of the RSI in rad/sample, ``0 <= low < high <= pi``.
    n_freq : int
        Frequencies evaluated in the band.
    max_delay : int or None
        Largest dead time (samples) searched, in [0, 1000]; None (default): the model's largest
        delay + 5, at least 10.
    initial_state : {"estimate", "zero"}
        How the model output is started (:func:`mpm_monitor.core.signals.compute_signals`).
    method : {"arx", "xcorr", "pcorr"}
        Element test: the ARX Delta test (default), or a baseline: cross-correlation (Webber and
        Gupta 2008) or partial correlation (Badwe et al. 2009).
    repair : bool
        Trace each located element to its kind and re-estimate it (:mod:`mpm_monitor.core.repair`).
    collinearity_threshold : float
        An input is not separable from the others (its elements are reported as ambiguous) when
        the variance-inflation factor of its lag block exceeds ``1 / collinearity_threshold``.
    element_window : {"model", "full"}
        Lags the element test examines: "model" (default) the first ``delay + nb`` lags of an
        element the model has (where any mismatch of that element starts), later up to the
        element's onset for slow structures (:func:`mpm_monitor.core.element_windows.element_window`),
        all lags for an element the model lacks and for a measured disturbance's; "full" all lags
        ``1 .. max_delay + nb`` for every element.
    element_response : bool
        Also test every element the model has against its whole modelled response, one regressor
        ``A(q) Phat_ij u_j`` in place of the column's lag block
        (:mod:`mpm_monitor.core.response_test`), combined with the lag-window test by Bonferroni
        (default True).  It sees a mismatch of a slow element that the window's lags miss.
    test_all_rows : bool
        Run the element test on every row (default), not only on the rows the S_Delta test flags
        (the paper's order).  The family-wise false-alarm rate stays ``alpha`` (Holm's procedure
        over every element tested); a row in which an element is located counts as mismatched even
        when its S_Delta test, which has less power for a small mismatch, did not reject.
    confirm_responses : bool
        Re-test every located element with the whole modelled responses (and an integrating element's
        time-constant sensitivity) of its row's other elements as free regressors, at its Holm step, and
        keep it located only if it still rejects (default False; needs ``element_response``;
        :func:`mpm_monitor.core.response_test.given_other_responses`).  A slow or integrating element's
        mismatch outlives its column's lags and, through the controller, reaches another column's test;
        but in closed loop the other columns' responses also carry part of the element's own mismatch
        (the controller moves them against it), so the test loses true elements too: on
        ``bench.structures_mc`` (seed 0) it removed 3 false locations and 6 true ones.
    release_explained : bool
        When two or more elements of a row are located, re-estimate them jointly, each in its
        structure, and release (no longer report as located) an element none of whose parameters
        differs significantly from the model while another located element's do: its finding was
        that element's mismatch leaking into its test (default True;
        :func:`mpm_monitor.core.repair.explained_elements`).  This runs the repair's
        classification of those rows also when ``repair`` is off, so the located elements do not
        depend on ``repair``.
    release_quiet_rows : bool
        An element located in a row the S_Delta row test does not flag (its unadjusted p-value at least
        ``alpha``) is tested again with ``max_na`` own lags, and released (no longer reported as located;
        ``unlocated_at_na``) when that test does not confirm it: the detection with ``max_na`` does not
        locate it, and its p-value there is not below ``alpha`` under Holm's procedure over the elements so
        checked (times the ``N_FAMILIES`` families; default True; False: a warning only).  A
        disturbance's colour that ``na`` own lags leave, under measurement noise large against the loop's
        excitation, is taken up by the inputs' lags (the controller moves them in answer to the noise) and
        located as elements; the row test, which regresses on the setpoints, keeps its level there
        (:func:`mpm_monitor.core.pipeline.analyze`).
    repair_again : bool
        Where the detection of the repaired model locates, in a row whose repair was applied, an element
        the first detection did not (``repair.located_after``, at the first detection's level: a mismatch the
        located elements' larger one hid), run the repair once more from the model as given, with those
        elements added to the located ones, and report that repair (its new elements in
        ``repair.second_round``; default True), unless that repair no longer applies a change the first one
        applied (the first then stands, with a warning).  The detection's own findings (``elements``) are not
        changed.
    drop_spikes : bool
        :func:`~mpm_monitor.core.pipeline.analyze` leaves out the samples of the log's spikes (one to
        three samples that leave a channel by more than 10 robust standard deviations of its
        sample-to-sample changes and come back; :mod:`mpm_monitor.core.spikes`) as missing samples,
        and its report's warnings name them (default True).  One such sample dominates every
        least-squares fit of the tests.  :func:`~mpm_monitor.core.analysis.detect` alone does not screen.
    max_gap : int or None
        Data with gaps (docs/interfaces.md, "Gaps") are analysed segment by segment, stacked, however
        long the gaps; a gap longer than ``max_gap`` samples (default None: the longest lag of the
        tests, ``max_delay + nb``) splits the data the same way and is only named louder in the
        warning (:mod:`mpm_monitor.core.gaps`).
    jobs : int
        Processes the analysis uses (default 1).  With 2 or more, a forked second process
        (:mod:`mpm_monitor.core.parallel`) shares the element test's rows and the detectable gain changes'
        chunks with this one, each taking the next as it is free (this process runs the row test first when
        every row is element-tested, after a child has factored a large setpoint block,
        :data:`~mpm_monitor.core.analysis.ROW_FORK_MIN_COLUMNS`), and on large windows takes one of two halves
        of the model run's rows, of the Gram matrices' products, of S_Delta's singular values and of the
        channels searched for spikes (:data:`~mpm_monitor.core.analysis.SPLIT_MIN_WORK`,
        :data:`~mpm_monitor.core.analysis.LIGHT_SPLIT_MIN_WORK`); in
        :func:`~mpm_monitor.core.pipeline.analyze` it computes the detectable gain changes and the experiment
        while the model is repaired and the repaired model detected, and on a window of at least
        :data:`~mpm_monitor.core.analysis.SPLIT_MIN_WORK` takes rows to repair, each whole
        (:func:`~mpm_monitor.core.analysis.row_jobs`).  The results are the same bit for bit, since each part
        is computed by the same code on the same numbers.  A process that runs other threads (a ROS node)
        never forks: it computes everything itself.  At most 2 are used.
    """

    na: int = option(4, "ARX order of A (the first tried; see max_na).", low=0, high=50)
    max_na: int = option(16, "Largest ARX order of A: while a row's element-test residual is not white "
                             "(Ljung-Box), na doubles up to this and the detection runs again (at most na: "
                             "never raised).", low=0, high=50)
    nb: int = option(4, "ARX order of each B.", low=1, high=50)
    alpha: float = option(0.01, "False-alarm rate of a whole analysis (split between the row tests and the element "
                                "tests, each with Holm's procedure).", low=0.0, high=0.5, open_low=True, open_high=True)
    band: tuple = option((0.0, math.pi), "RSI band, rad/sample.", low=0.0, high=math.pi, length=2)
    n_freq: int = option(256, "Frequencies evaluated in the band.", low=8, high=100000)
    max_delay: Optional[int] = option(None, "Largest dead time searched, samples.", low=0, high=1000)
    initial_state: str = option("estimate", "Model state at the first sample analysed: estimated by least squares or zero.",
                                choices=INITIAL_STATE_CHOICES)
    method: str = option("arx", "Element test: arx (paper), xcorr or pcorr (baselines).", choices=METHODS)
    repair: bool = option(True, "Also trace each located element to its kind and re-estimate it, for a suggested "
                                "repaired model (about 0.15 s more per analysis of a 3x3 or 5x5 window of 3,000 "
                                "samples with two to five located elements).")
    collinearity_threshold: float = option(1e-2, "Inputs are not separable when the variance inflation of a lag "
                                                 "block exceeds 1 / this.", low=0.0, high=1.0, open_low=True,
                                           open_high=True)
    test_all_rows: bool = option(True, "Run the element test on every row, not only on the rows the S_Delta test "
                                       "flags.")
    element_response: bool = option(True, "Also test each element the model has against its whole modelled "
                                          "response (one regressor), combined with the lag-window test.")
    element_window: str = option("model", "Lags the element test examines: model (an element the model has: "
                                          "delay + nb, wider for a slow onset; a measured disturbance's and an "
                                          "absent element's: all) or full (all).", choices=ELEMENT_WINDOWS)
    confirm_responses: bool = option(False, "Stricter: keep a located element only if it still rejects with the whole "
                                            "modelled responses of its row's other elements free (fewer elements "
                                            "located through another's mismatch, and fewer true ones).")
    release_explained: bool = option(True, "Where a row has several located elements, re-estimate them jointly and "
                                           "release one that does not differ from the model while another does "
                                           "(its finding was the other's mismatch).")
    release_quiet_rows: bool = option(True, "Release an element located in a row the S_Delta row test does not flag "
                                            "when the element test with max_na own lags does not confirm it (a "
                                            "disturbance's colour the inputs' lags took up); off: a warning only.")
    repair_again: bool = option(True, "Where the repaired model's detection locates, in a row whose repair was "
                                      "applied, an element the first detection did not (at the first detection's "
                                      "level), repair again from the model as given with it and the located "
                                      "elements (once).")
    drop_spikes: bool = option(True, "Leave out as missing samples the spikes of the log (one to three samples that "
                                     "leave a channel by more than 10 robust standard deviations of its changes and "
                                     "come back), with a warning naming them.")
    max_gap: Optional[int] = option(None, "Longest gap in the data (missing samples) called short, samples; longer "
                                          "gaps are named louder in the warning (None: the longest lag of the "
                                          "tests).", low=0, high=10**9)
    jobs: int = option(1, "Processes the analysis uses: with 2, a forked second process takes part of the rows' "
                          "work, row by row as each is free (the same results, bit for bit).", low=1, high=64)

    def __post_init__(self):
        for name, value in check_analysis_options(self).items():
            object.__setattr__(self, name, value)


def check_analysis_options(o: AnalysisOptions) -> dict:
    """Check every option against its :class:`~mpm_monitor.core.options.ParamSpec` (:data:`ANALYSIS_PARAMS`).

    Returns
    -------
    dict
        Option name -> value converted to the option's type.

    Raises
    ------
    ConfigurationError
        Naming the option outside its range (or a band whose low edge is not below its high edge).
    """
    values = check_options(o)
    lo, hi = values["band"]
    if not lo < hi:
        raise ConfigurationError(f"parameter band: expected 0 <= low < high <= pi rad/sample, got {o.band!r}")
    return values


#: The :class:`~mpm_monitor.core.options.ParamSpec` of every analysis option, by name: the one source
#: of the command line's analysis flags and the monitor node's analysis parameters.
ANALYSIS_PARAMS = {spec.name: spec for spec in option_specs(AnalysisOptions)}
