"""The located elements whose mismatch another located element of their row explains
(:func:`explained_elements`), by the repair's classification of the row's located elements jointly."""

from __future__ import annotations

import dataclasses
from typing import Mapping, Optional, Sequence

from ..errors import ConfigurationError
from ..logged_data import LoggedData, in_deviations
from ..model import PlantModel
from ..signals import LoopSignals
from .classify import _classify_row
from .fit import _TooShort
from .options import RepairOptions
from .record import _check_delays, _check_inputs, _located_in_row, _min_fit, _set_up
from .row import _RowData


@dataclasses.dataclass
class JointClassification:
    """What :func:`explained_elements` found.

    Attributes
    ----------
    released : dict
        ``{(i, j): [k, ...]}``: the located element ``(i, j)`` (output index, column index) whose
        mismatch the located elements ``k`` of its row explain (those the row keeps).
    rows : dict
        ``{i: (js, (free, verdicts, warnings)))}``: the last classification of row ``i``'s located
        elements ``js`` (a tuple: those kept after the releases when the last one released nothing),
        which :func:`~.model_repair.repair_model` takes instead of classifying again when they are the row's
        located elements.
    """

    released: dict
    rows: dict

    def of_row(self, i: int, js) -> Optional[tuple]:
        """``(free, verdicts, warnings)`` of row ``i`` when its last classification was of the
        elements ``js``, else None."""
        done = self.rows.get(i)
        return done[1] if done is not None and done[0] == tuple(js) else None


def explained_elements(model: PlantModel, data: LoggedData, located: Sequence[tuple],
                       options: RepairOptions = RepairOptions(),
                       signals: Optional[LoopSignals] = None,
                       delays: Optional[Mapping] = None) -> JointClassification:
    """The located elements whose mismatch another located element of their row explains.

    The element test locates each element on its own statistic, with the row's other columns free
    as lag windows.  In closed loop a mismatch that a lag window does not hold whole (a slow or
    shifted response) leaves a remainder that the other columns, correlated with the mismatched
    one through the controller, can pick up: a second element of the row is then located for the
    first one's mismatch.  The classification of the repair settles it.  It fits the row's located
    elements jointly, each in its structure, and tests every parameter of each against the model
    (likelihood-ratio tests at ``1 - options.confidence_level``, a change counted only above
    ``options.min_relative_change``, and the joint hold of every parameter found unchanged;
    :mod:`.classify`).  An element none of whose parameters differs from the model there (its kind
    "unknown"), in a row where another located element's do, adds nothing to the row
    once those are re-estimated: it is released, with the elements that explain it.  The row's
    remaining elements are then classified again, and released in turn, until none is: the
    result is the rule applied to its own outcome, and the classification of the elements kept is
    the one the repair takes over.  An element alone in its row is never released, nor are the
    elements of a row where none changed.

    Parameters
    ----------
    model : PlantModel
        The controller's model as given.
    data : LoggedData
        The record the repair fits (:func:`~.model_repair.repair_model`).
    located : sequence of (int, int)
        (output index, column index) of the located elements.
    options : RepairOptions
    signals : LoopSignals, optional
        :func:`~mpm_monitor.core.signals.compute_signals` of ``model`` on ``data``.
    delays : mapping, optional
        ``{(output index, column index): lag}``: the element test's estimate of the lag (samples) at which
        each located element's mismatch acts (``ElementResult.delay``), as :func:`~.model_repair.repair_model`
        takes it.

    Returns
    -------
    JointClassification
        Empty when no row has two located elements (nothing is fitted then) or the record is too
        short for the repair.
    """
    if not isinstance(options, RepairOptions):
        raise ConfigurationError(f"options: expected RepairOptions, got {type(options).__name__}")
    data = in_deviations(model, data)
    located = _check_inputs(model, data, located, signals)
    result = JointClassification(released={}, rows={})
    rows = {i: tuple(_located_in_row(located, i)) for i in sorted({i for i, _ in located})}
    rows = {i: js for i, js in rows.items() if len(js) > 1}
    if not rows:
        return result
    rec = _set_up(model, data, options, signals, _check_delays(delays, located))
    if rec.n_fit < _min_fit(model, options):
        return result
    for i, js in rows.items():
        row = _RowData(model=model, u=rec.u, y=rec.y, i=i, extra=None, segments=rec.segments, bridge=rec.bridge,
                       delays=rec.row_delays(i))
        gone = []
        while len(js) > 1:          # until the row's classification releases nothing more
            try:
                free, verdicts, warnings = _classify_row(row, js, rec.settings)
            except _TooShort:
                break
            result.rows[i] = (js, (free, verdicts, list(warnings)))
            known = tuple(j for j in js if verdicts[j].kind != "unknown")
            if not known or len(known) == len(js):
                break
            gone += [j for j in js if j not in known]
            js = known
        # The elements the row keeps in the end explain every element released from it.
        result.released.update({(i, j): list(js) for j in gone})
    return result
