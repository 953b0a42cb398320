"""The unexplained-disturbance tests of every output's prediction error, as one family: how the repair
tests the residual of the model it repaired (the test of one residual is :mod:`.disturbance`), the tests
computed ahead for the model as given, and the report's entries and warnings."""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from ..logged_data import LoggedData, in_deviations, moving_columns, t_text
from ..model import PlantModel
from ..statistics import holm_adjust
from .disturbance import not_tested, unexplained_disturbance
from .options import RepairOptions
from .record import _Record


def _one_family(tests: dict, alpha: float) -> None:
    """The unexplained-disturbance tests of every output as one family, in place: Holm's adjusted p-value
    (:func:`~mpm_monitor.core.statistics.holm_adjust`) over the outputs tested becomes each test's
    ``p_value`` (its own in ``p_value_raw``), and a test whose adjusted value is not below ``alpha`` no longer
    reports a disturbance.  So a loop without one reports one with probability at most ``alpha`` however
    many outputs it has (each output alone at ``alpha`` reported one on 63 % of 100-output loops).

    Parameters
    ----------
    tests : dict
        ``{output index: test}``, each :func:`unexplained_disturbance`'s result (``detected`` exactly when
        its ``p_value`` is below ``alpha``); an output not tested keeps its test and is not counted.
    alpha : float
        The family-wise level (:attr:`RepairOptions.disturbance_alpha`).
    """
    tested = [i for i, test in tests.items() if test.get("tested")]
    if not tested:
        return
    for i, adjusted in zip(tested, holm_adjust([tests[i]["p_value"] for i in tested])):
        test, adjusted = tests[i], float(adjusted)
        if test["detected"] and not adjusted < alpha:
            tests[i] = test = dict(not_tested(), p_step=test["p_step"], p_drift=test["p_drift"],
                                   p_value=test["p_value"], tested=True)
        test["p_value_raw"], test["p_value"] = test["p_value"], adjusted


def _disturbance_test(d: np.ndarray, segments, scale: float, model: PlantModel, options: RepairOptions,
                      moves: bool, levels=None, calibrate: bool = False) -> dict:
    """:func:`unexplained_disturbance` of one output's prediction error ``d`` (shape (n_samples,)), as the
    repair tests every output: at ``options``' level, trim and AR terms (:attr:`RepairOptions.test_order`), over
    the scored ``segments`` (None: every sample) and their ``levels`` (:attr:`~.record._Record.levels`),
    ``scale`` the output's standard deviation; with ``calibrate``, confirmed on ``options.disturbance_draws``
    simulated records (seeded with ``options.disturbance_seed``).  An output that never moves (``moves`` false: a stuck
    sensor) is not tested: its prediction error is the model's own response."""
    if not moves:
        return not_tested()
    calibrate = calibrate and options.disturbance_draws > 0
    return unexplained_disturbance(d, model.sample_time, options.disturbance_alpha, options.disturbance_trim,
                                   options.test_order, segments=segments, scale=scale, levels=levels,
                                   calibrate=calibrate, draws=options.disturbance_draws,
                                   rng=np.random.default_rng(options.disturbance_seed) if calibrate else None)


def _test_settings_key(model: PlantModel, options: RepairOptions) -> tuple:
    """What a disturbance test depends on besides its prediction error, segments and scale."""
    return (float(model.sample_time), float(options.disturbance_alpha), float(options.disturbance_trim),
            int(options.test_order))


@dataclasses.dataclass
class DisturbanceTests:
    """The unexplained-disturbance tests of every output of a model as given, on a record without gaps,
    computed ahead of :func:`~.model_repair.repair_model` (:func:`disturbance_tests`), which takes each output's test
    whose prediction error it finds unchanged instead of testing it again.

    Attributes
    ----------
    key : tuple
        The sample time, the level, trim and noise order of the tests (:class:`RepairOptions`).
    spread : ndarray, shape (n_outputs,)
        The outputs' standard deviations, the tests' scales (output units).
    d : ndarray, shape (n_samples, n_outputs)
        The prediction errors tested (output units).
    tests : list of dict
        Per output, :func:`~mpm_monitor.core.repair.disturbance.unexplained_disturbance`'s result.
    """

    key: tuple
    spread: np.ndarray
    d: np.ndarray
    tests: list


def disturbance_tests(model: PlantModel, data: LoggedData, d: np.ndarray,
                      options: RepairOptions = RepairOptions()) -> DisturbanceTests:
    """The tests :func:`~.model_repair.repair_model` runs on every output of ``model`` as given, computed ahead.

    The repair tests the prediction error of every output of the repaired model for an unexplained
    step or drift; an output whose row it does not repair keeps the prediction error of the model as
    given.  :func:`~mpm_monitor.core.pipeline.analyze` computes these tests in its second process
    while the detection's first stages run in one (the second core is idle then), and gives them to
    :func:`~.model_repair.repair_model` (its ``disturbance_tests``): the same numbers.

    Parameters
    ----------
    model : PlantModel
        The model as given.
    data : LoggedData
        The record the repair fits, without gaps (the scales are the standard deviations of its ``y``).
    d : ndarray, shape (n_samples, n_outputs)
        ``model``'s prediction error on ``data`` (output units).
    options : RepairOptions
        The repair's options.

    Returns
    -------
    DisturbanceTests
    """
    d = np.asarray(d, float)
    y = np.asarray(in_deviations(model, data).y, float)
    spread, moving = np.std(y, axis=0), moving_columns(y)
    return DisturbanceTests(key=_test_settings_key(model, options), spread=spread, d=d,
                            tests=[_disturbance_test(d[:, i], None, float(spread[i]), model, options, bool(moving[i]))
                                   for i in range(model.n_outputs)])


def _seed_tests(rec: _Record, given: Optional[DisturbanceTests]) -> None:
    """Put the tests ``given`` (:func:`disturbance_tests`) into :attr:`_Record.tests` when they were taken with
    the record's settings and scales (without gaps); :func:`~.model_repair._evaluate` uses each one whose prediction error it
    finds unchanged."""
    if given is None or rec.segments is not None or given.key != _test_settings_key(rec.model, rec.options):
        return
    if given.d.shape != rec.d0.shape or not np.array_equal(given.spread, rec.spread):
        return
    for i, test in enumerate(given.tests):
        rec.tests[i] = (given.d[:, i], None, test)


def _disturbance_findings(rec: _Record, tests: dict):
    """The ``disturbances`` entries and their warnings, in output order."""
    disturbances, warnings = [], []
    for i, name in enumerate(rec.model.outputs):
        test = tests[i]
        if not test["detected"]:
            continue
        disturbances.append({"output": name, "kind": test["kind"], "size": test["size"],
                             "time": test["time"], "rate": test["rate"], "p_value": test["p_value"],
                             "p_value_raw": test["p_value_raw"], "statistic": test["statistic"],
                             "null_scale": test["null_scale_step" if test["kind"] == "step" else "null_scale_drift"]})
        if test["kind"] == "step":
            # At the log's own time (the stamp of the sample the step is at): ``time`` counts from the first sample,
            # which read as 1164 s beside the gap warnings' 1700001664 s in a live window.
            k, t = test.get("index"), np.asarray(rec.data.t)
            when = t_text(float(t[k])) if k is not None and 0 <= k < t.shape[0] else f"{test['time']:.0f}"
            warnings.append(
                f"{name}: the prediction error shifts by {test['size']:+.3g} at about t = {when} s "
                f"(p = {test['p_value']:.2g}) and no input explains it: an unmeasured disturbance or a change "
                f"in the process, not an error of one model element; no element was changed for it.")
        else:
            warnings.append(
                f"{name}: the prediction error drifts by {test['size']:+.3g} over the record "
                f"({test['rate']:+.3g} per second, p = {test['p_value']:.2g}) and no input explains it: an "
                f"unmeasured disturbance or a slow process change; no element was changed for it.")
    return disturbances, warnings
