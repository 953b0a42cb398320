"""What the repair reports: the verdict on each located element, its change entry, and the result."""

from __future__ import annotations

import dataclasses
import math
from typing import Optional

import numpy as np

from ..model import PlantModel
from .forms import _element_keys, _Form, _public_params
from .options import RepairOptions


@dataclasses.dataclass
class ElementVerdict:
    """What the repair concluded about one located element (output ``i``, input ``j``).

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    changed : list of str
        The tests that found a change, among "missing", "gain", "time_constant" (any lag or the
        lead), "delay", in that order.
    after : dict
        The fitted element, every parametric key (``gain``, ``time_constant`` s, ``delay`` s,
        ``time_constant2`` s, ``lead`` s, ``integrating``); the model's element (as
        :meth:`PlantModel.element` gives it) when the row could not be fitted.
    interval : dict or None
        ``[lo, hi]`` per parameter at ``confidence_level``.
    evidence : dict
        The p-values, the condition number, the samples and the noise model of the row fit (see
        :class:`RepairResult`).
    confidence : float
        In [0, 1]: how clearly the tests lie on their side of the threshold.
    apply : bool
        Whether the repair takes ``after`` into the model.
    reason : str, optional
        Why the element is not changed.
    fitted_kind : str, optional
        The kind found before the held-out validation rejected the repair.
    form : _Form, optional
        The form the element was fitted in.
    reference : dict, optional
        The element its changes were measured from (every parametric key): the model's, or the
        parametric form of a step-response element's old response.
    """

    kind: str
    changed: list
    after: dict
    interval: Optional[dict]
    evidence: dict
    confidence: float
    apply: bool
    reason: Optional[str] = None
    fitted_kind: Optional[str] = None
    form: Optional[_Form] = None
    reference: Optional[dict] = None

    def reject(self, reason: str) -> None:
        """Keep the element as it was: the kind found becomes ``fitted_kind``, the kind "unknown"."""
        self.apply, self.fitted_kind, self.kind, self.confidence, self.reason = False, self.kind, "unknown", 0.0, reason

    def model_keys(self, model: PlantModel, i: int, j: int) -> dict:
        """The keyword arguments of :meth:`PlantModel.with_element` that put ``after`` into ``model``
        in the model's structure (a step-response model: the sampled step response of the same
        length; see :func:`~mpm_monitor.core.repair.forms._element_keys`)."""
        return _element_keys(model, i, j, self.after, self.reference, self.changed)

    def applied_to(self, model: PlantModel, i: int, j: int) -> PlantModel:
        """``model`` with element (i, j) replaced by ``after``."""
        return model.with_element(i, j, **self.model_keys(model, i, j))

    def change_entry(self, model: PlantModel, i: int, j: int) -> dict:
        """The ``changes`` entry of the element (see :class:`RepairResult`): ``before``, ``after`` and
        ``estimate`` with the keys :meth:`PlantModel.element` gives."""
        estimate = self.applied_to(model, i, j).element(i, j)
        entry = {"output": model.outputs[i], "input": model.columns[j], "kind": self.kind,
                 "before": model.element(i, j),
                 "after": estimate if self.apply else model.element(i, j),
                 "estimate": estimate, "confidence": self.confidence,
                 "interval": self.interval, "applied": bool(self.apply), "evidence": self.evidence}
        if model.is_step_response and model.ramp[i]:
            entry["ramp"] = True
        if model.is_step_response and "step_response" not in self.after:
            entry["evidence"] = dict(self.evidence, parametric_after=_public_params(self.after))
        if self.fitted_kind is not None:
            entry["fitted_kind"] = self.fitted_kind
        if self.reason:
            entry["reason"] = self.reason
        return entry


def _unchanged_entry(model: PlantModel, i: int, j: int, reason: str) -> dict:
    """The ``changes`` entry of an element that was not fitted at all (no estimate)."""
    return {"output": model.outputs[i], "input": model.columns[j], "kind": "unknown",
            "before": model.element(i, j), "after": model.element(i, j), "estimate": None,
            "confidence": 0.0, "interval": None, "applied": False, "evidence": {}, "reason": reason}


@dataclasses.dataclass
class RepairResult:
    """What :func:`repair_model` found and changed.

    Attributes
    ----------
    model : PlantModel
        The repaired model: the input model with only accepted located elements changed.
    changes : list of dict
        One entry per located element: ``output``, ``input`` (names), ``kind``, ``before`` and
        ``after`` (the element's keys as :meth:`PlantModel.element` gives them: ``gain``,
        ``time_constant`` s, ``delay`` s, and ``lead``, ``time_constant2``, ``integrating`` where
        set, or ``step_response`` in a step-response model; ``after`` equals ``before`` when not
        applied), ``estimate`` (the same keys, also when not applied), ``confidence`` in [0, 1],
        ``interval`` (``[lo, hi]`` per fitted parameter at ``confidence_level``: gain, time
        constant, delay, and time_constant2, lead where fitted), ``applied``, ``evidence``
        (``p_gain``, ``p_time_constant``, ``p_delay``: likelihood-ratio p-values of "unchanged",
        the time constant's of every lag and the lead at once; ``p_unchanged_jointly``;
        ``condition_number`` of the row fit; ``samples``; ``noise_model`` ``[alpha_1 .. alpha_p]``;
        for a step-response element ``parametric_before`` and ``parametric_after``, the parametric
        forms of its old and new responses), ``ramp`` (true) for a step-response element of a
        ramp output (its ``gain`` is then the last slope per second), and when not applied
        ``reason`` (and ``fitted_kind`` when the held-out validation rejected it).
    kinds : dict
        ``{(i, j): kind}`` for every located element (indices).
    error_before, error_after : dict
        ``{output name: RMS of d}`` over the whole record with the model as given / as repaired
        (about its mean on an integrating output, whose level is arbitrary:
        :func:`~mpm_monitor.core.signals.error_rms`).
    fit_before, fit_after : dict
        ``{output name: fit %}``, ``100 (1 - ||y - yhat|| / ||y - mean y||)`` (``y - yhat`` about its
        mean on an integrating output).
    holdout_error_before, holdout_error_after : dict
        ``{output name: RMS of d about its level}`` over the held-out last part (its mean there
        removed: the level is no element's to explain, and on an integrating output it is arbitrary),
        with the model as given / with the candidate fitted on the first part only (empty when
        ``holdout_fraction`` is 0).  On a row re-estimated with an unexplained step or drift, both
        are taken with that disturbance projected out too.
    holdout_one_step_error_before, holdout_one_step_error_after : dict
        ``{output name: RMS of the one-step errors}`` over the held-out last part under each model's own
        AR noise model of order ``noise_order``, fitted on the first part (the model as given / the
        candidate), for the rows whose re-estimation the held-out check compared (empty otherwise).
    disturbances : list of dict
        Outputs whose residual holds a step or drift no input explains (``output``, ``kind``
        "step"/"drift", ``size`` in output units, ``time`` in seconds, ``p_value``, ``statistic``, ``null_scale``:
        what the statistic was divided by for the output's own noise before its p-value was taken, 1 when the
        noise is as white as the asymptotic law assumes).
    warnings : list of str
        What limits the conclusions, in words.
    n_samples, n_fit : int
        Samples in the record and in the fit part.
    signals : LoopSignals or None
        :func:`~mpm_monitor.core.signals.compute_signals` of the repaired ``model`` on the record (with
        the options' ``initial_state``), for a detection of the repaired model on the same data.
    """

    model: PlantModel
    changes: list
    kinds: dict
    error_before: dict
    error_after: dict
    fit_before: dict
    fit_after: dict
    holdout_error_before: dict
    holdout_error_after: dict
    disturbances: list
    warnings: list
    n_samples: int = 0
    n_fit: int = 0
    options: RepairOptions = RepairOptions()
    holdout_one_step_error_before: dict = dataclasses.field(default_factory=dict)
    holdout_one_step_error_after: dict = dataclasses.field(default_factory=dict)
    signals: object = dataclasses.field(default=None, compare=False, repr=False)

    def to_dict(self) -> dict:
        """The ``repair`` object of the analysis report, plain JSON values.

        See ``docs/interfaces.md``, section "analyze and its JSON report".
        """
        return _jsonable({
            "model": self.model.to_dict(),
            "changes": self.changes,
            "error_before": self.error_before,
            "error_after": self.error_after,
            "fit_before": self.fit_before,
            "fit_after": self.fit_after,
            "holdout_error_before": self.holdout_error_before,
            "holdout_error_after": self.holdout_error_after,
            "holdout_one_step_error_before": self.holdout_one_step_error_before,
            "holdout_one_step_error_after": self.holdout_one_step_error_after,
            "disturbances": self.disturbances,
            "warnings": list(self.warnings),
            "samples": self.n_samples,
            "fit_samples": self.n_fit,
            "holdout_fraction": self.options.holdout_fraction,
            "confidence_level": self.options.confidence_level,
            "noise_order": self.options.noise_order,
        })


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        kinds = set(map(type, x))
        if kinds <= {int, float}:           # plain numbers (a model's rows): kept as they are unless not finite
            try:
                if float not in kinds or all(map(math.isfinite, x)):
                    return list(x)
            except OverflowError:           # an int beyond the float range: each entry as below
                pass
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return x if math.isfinite(x) else None
    return x
