"""Logged closed-loop data in memory: setpoints, inputs, measured disturbances and outputs on a regular time grid.

The CSV file is read and written by :mod:`mpm_monitor.io.csv_log`, bags by :mod:`mpm_monitor.io.bags`,
and the live monitor builds the same object from its window (:mod:`mpm_monitor.monitor.window`).
:func:`check_loop_data`, :func:`check_signals` and :func:`check_disturbance_signal` are the one check
of ``r``, ``u``, ``dv`` and ``y`` against a model (channels, shapes, finite values) before an analysis.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from .errors import DataFileError
from .model import PlantModel

#: Largest |value| x max(1, |gain|) the analysis takes: its fits square the signals, and products of
#: those (variances, determinants, statistics) overflow float64 sooner.  Case 3.2 with every value
#: scaled: the same result up to 1e40; overflow warnings from 1e50; other elements located at 1e80.
MAX_ANALYSIS_SCALE = 1e40
#: Smallest largest |value| of a moving channel kind the analysis takes: the same results down to
#: 1e-150 on case 3.2, a division by zero at 1e-160.
MIN_ANALYSIS_SCALE = 1e-100
#: A topic (a bag's, or the live monitor's) whose vectors arrive before every other topic's vector of the same sample,
#: by at least ``EARLY_SAMPLES`` samples of arrival time and ``EARLY_SECONDS``, in the median of a block of
#: ``EARLY_BLOCK`` samples, has stamps that run ahead of theirs: its clock jumped forward or runs apart, and aligned
#: by stamp its samples would pair with the others' of another time.  A vector that arrives late is no sign of it.
EARLY_SAMPLES = 3
EARLY_SECONDS = 2.0
EARLY_BLOCK = 25


def early_limit_ns(per_sample_ns: float) -> float:
    """How early (ns of arrival time) a topic's vectors must arrive, in a block's median, to have stamps that run
    ahead of the others': :data:`EARLY_SAMPLES` samples of ``per_sample_ns`` (the arrival time per sample) and
    :data:`EARLY_SECONDS`, whichever is longer."""
    return max(EARLY_SAMPLES * per_sample_ns, EARLY_SECONDS * 1e9)


def t_text(t) -> str:
    """A time ``t`` (s) in a message, to 15 significant digits: a wall-clock time (1.7e9 s, a historian's or a
    bag's) keeps its seconds and their fraction (six digits, ``:g``, printed every gap of a day at
    ``1.71235e+09``), and a sum of sample times keeps no rounding tail (``0.30000000000000004`` is ``0.3``)."""
    return f"{float(t):.15g}"


def moving_columns(x: np.ndarray) -> np.ndarray:
    """Whether each column of ``x`` (shape (n_samples, k), or (n_samples,) for one) moves over its samples: its
    standard deviation above 1e-12 of its largest |value| (and above 0).  A column held at a value such as 0.1
    keeps a deviation of about 1e-17 from the rounding of its mean, which a plain ``std > 0`` took for a move.

    Returns
    -------
    ndarray of bool, shape (k,) (a 0-d array for one column)
    """
    x = np.asarray(x, dtype=float)
    if x.shape[0] == 0:
        return np.zeros(x.shape[1:], dtype=bool)
    std = x.std(axis=0)
    return (std > 0) & (std > 1e-12 * np.abs(x).max(axis=0))


def _step_index(t: np.ndarray, sample_time: float) -> np.ndarray:
    """Sample numbers of the increasing times ``t`` (shape (n,)), step by step: each step of about ``m``
    sample times (rounded, at least 1) advances the number by ``m``; int64 array of shape (n,)."""
    steps = np.maximum(np.rint(np.diff(t) / sample_time), 1.0).astype(np.int64)
    return np.concatenate([[0], np.cumsum(steps)])


@dataclasses.dataclass
class LoggedData:
    """Setpoints, inputs, measured disturbances and outputs of a closed-loop run.

    Attributes
    ----------
    t : ndarray, shape (n_samples,)
        Time in seconds, increasing by a whole number of sample times at each step (to a small
        tolerance: a logger's clock may drift; a step of several sample times is a gap, see
        :attr:`grid_index` and :attr:`segments`).
    r : ndarray, shape (n_samples, n_outputs)
        Setpoints, columns in the model's output order.
    u : ndarray, shape (n_samples, n_inputs)
        Plant inputs, columns in the model's input order.
    y : ndarray, shape (n_samples, n_outputs)
        Measured outputs, columns in the model's output order.
    inputs, outputs : tuple of str
        Channel names.
    sample_time : float
        Seconds per sample.
    source : str
        Where the data came from (file name), for messages.
    dv : ndarray, shape (n_samples, n_disturbances)
        Measured disturbances (the model's feedforward columns), in the model's disturbance order;
        default none (shape (n_samples, 0)).
    disturbances : tuple of str
        Their names.
    extra : dict
        Other numeric logged channels, ``name -> ndarray (n_samples,)`` (candidate causes of the
        residual); default none.
    unusable : dict
        Logged channels that cannot be used, ``name -> reason`` (not numeric, constant, partly
        missing); default none.
    deviations : bool
        ``u``, ``y`` and ``r`` are already deviations from the model's operating point
        (:func:`in_deviations`); default False (as logged).
    notes : tuple of str
        What the reader did to the data that the user should know, one sentence each (for example
        messages of a bag left out because their stamp was unset); the analysis puts them first in
        its report's warnings.  Default none.
    column_fill : tuple (ndarray, ndarray) or None
        Samples left out of the rows (the sample of a spike in a setpoint or an output) whose model
        columns were logged and sound: their times ``t`` (shape (m,)) and ``[u | dv]`` (shape
        (m, n_inputs + n_disturbances)).  No test reads them; the model's simulation through a short
        gap takes them instead of holding the columns (:func:`~mpm_monitor.core.signals.segment_signals`).
        Default none.
    """

    t: np.ndarray
    r: np.ndarray
    u: np.ndarray
    y: np.ndarray
    inputs: tuple
    outputs: tuple
    sample_time: float
    source: str = ""
    dv: Optional[np.ndarray] = None
    disturbances: tuple = ()
    extra: dict = dataclasses.field(default_factory=dict)
    unusable: dict = dataclasses.field(default_factory=dict)
    deviations: bool = False
    notes: tuple = ()
    column_fill: Optional[tuple] = None

    def __post_init__(self):
        self.disturbances = tuple(self.disturbances)
        self.notes = tuple(self.notes)
        if self.dv is None:
            self.dv = np.zeros((np.shape(self.t)[0], len(self.disturbances)))

    @property
    def n_samples(self) -> int:
        return int(self.t.shape[0])

    @property
    def columns(self) -> np.ndarray:
        """``[u | dv]``: the model's columns (inputs, then measured disturbances), shape (n_samples, n_columns)."""
        if self.dv.shape[1] == 0:
            return self.u
        return np.hstack([self.u, self.dv])

    @property
    def grid_index(self) -> np.ndarray:
        """Sample number of every row from the first, int array of shape (n_samples,).

        Step by step: a step of ``t`` of about ``m`` sample times (``m >= 1``, rounded) advances it by
        ``m`` (``m - 1`` samples missing), as the CSV reader checks each step (to 0.1 % of the sample
        time).  A logger's clock that runs slightly fast or slow so keeps every row on its own sample,
        where rounding ``(t - t[0]) / sample_time`` would put two rows on one sample, or open a gap
        where none is, once the drift adds up to half a sample (100 ppm over 5,000 samples).
        """
        if self.n_samples == 0:
            return np.zeros(0, dtype=int)
        return _step_index(np.asarray(self.t, dtype=float), self.sample_time)

    def fill_on_grid(self) -> Optional[tuple]:
        """:attr:`column_fill` as ``(grid index, [u | dv])`` (:attr:`grid_index`'s numbering: each sample's
        index from the last row at or before it, the samples before the first row from the first), or None."""
        if self.column_fill is None or self.n_samples == 0:
            return None
        t, cols = self.column_fill
        t = np.asarray(t, dtype=float)
        k = self.grid_index
        row = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, None)
        return k[row] + np.rint((t - self.t[row]) / self.sample_time).astype(np.int64), cols

    @property
    def segments(self) -> list:
        """Contiguous runs of rows (no missing sample inside), as ``(first row, end row)`` pairs."""
        k = self.grid_index
        if k.size == 0:
            return []
        breaks = np.flatnonzero(np.diff(k) != 1) + 1
        edges = np.concatenate([[0], breaks, [k.size]])
        return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]

    def take(self, rows) -> "LoggedData":
        """The rows ``rows`` (indices or a boolean mask, in order) as a new object: dropping rows makes gaps."""
        return dataclasses.replace(self, t=self.t[rows], r=self.r[rows], u=self.u[rows], y=self.y[rows],
                                   dv=self.dv[rows], extra={k: v[rows] for k, v in self.extra.items()})

    def slice(self, start: int, stop: int) -> "LoggedData":
        """Samples ``start:stop`` as a new object."""
        return dataclasses.replace(self, t=self.t[start:stop], r=self.r[start:stop], u=self.u[start:stop],
                                   y=self.y[start:stop], dv=self.dv[start:stop],
                                   extra={k: v[start:stop] for k, v in self.extra.items()})


def in_deviations(model: PlantModel, data: LoggedData) -> LoggedData:
    """``data`` in the deviation variables of ``model``: the inputs minus ``model.input_nominal``, the
    outputs and setpoints minus ``model.output_nominal``, the measured disturbances minus
    ``model.disturbance_nominal``.

    The model's elements act on deviations from its operating point (the model file's
    ``input_nominal``, ``output_nominal`` and ``disturbance_nominal``, zero by default); a log holds
    the values as measured.
    Every analysis entry point (:func:`~mpm_monitor.core.analysis.detect`,
    :func:`~mpm_monitor.core.pipeline.analyze`, the repair) takes the log through here once: data
    already converted (:attr:`LoggedData.deviations`), a model at the origin, or data whose shapes
    do not fit the model (refused later with their own message) are returned as they are.

    Parameters
    ----------
    model : PlantModel
    data : LoggedData
        As logged: ``u`` (n_samples, n_inputs), ``y`` and ``r`` (n_samples, n_outputs).

    Returns
    -------
    LoggedData
        A copy with ``deviations`` set, or ``data`` itself.
    """
    u0 = np.asarray(model.input_nominal, dtype=float)
    y0 = np.asarray(model.output_nominal, dtype=float)
    d0 = np.asarray(model.disturbance_nominal, dtype=float)
    if data.deviations or not (np.any(u0 != 0) or np.any(y0 != 0) or np.any(d0 != 0)):
        return data
    shapes = (np.shape(data.u), np.shape(data.y), np.shape(data.r))
    n = data.n_samples
    if shapes != ((n, u0.size), (n, y0.size), (n, y0.size)):
        return data
    dv = np.asarray(data.dv, dtype=float)
    if dv.shape != (n, d0.size):          # refused later, with its own message
        d0 = np.zeros(dv.shape[1:])
    where = data.source or "data"
    for key, nominal, x, names in (("input_nominal", u0, data.u, data.inputs), ("output_nominal", y0, data.y, data.outputs),
                                   ("disturbance_nominal", d0, dv, data.disturbances)):
        _check_nominal_precision(where, key, nominal, np.asarray(x, dtype=float), names)
    fill = data.column_fill
    if fill is not None:
        cols = np.array(fill[1], dtype=float)
        cols[:, :u0.size] -= u0
        cols[:, u0.size:u0.size + d0.size] -= d0
        fill = (fill[0], cols)
    return dataclasses.replace(data, u=np.asarray(data.u, dtype=float) - u0, y=np.asarray(data.y, dtype=float) - y0,
                               r=np.asarray(data.r, dtype=float) - y0, dv=dv - d0, deviations=True,
                               column_fill=fill)


#: An operating point is refused when subtracting it rounds a channel's values to steps larger than this fraction of
#: the channel's standard deviation (:func:`_check_nominal_precision`).
NOMINAL_ROUNDING_LIMIT = 1e-3


def _check_nominal_precision(where: str, key: str, nominal: np.ndarray, x: np.ndarray, names) -> None:
    """Refuse an operating point so far from a channel's logged values that 64-bit floats lose the channel's moves
    when it is subtracted.

    The deviation ``x - nominal`` is rounded to the spacing of floats at its size: with ``output_nominal`` 1e17 and
    values of order 1, every deviation is -1e17 exactly, and a moving output would read as stuck.  A channel is
    refused when that spacing is larger than :data:`NOMINAL_ROUNDING_LIMIT` of its standard deviation and larger
    than the spacing its logged values already have (a log that holds large values loses nothing more).  A deviation
    beyond :data:`MAX_ANALYSIS_SCALE` is left to the scale's own refusal.

    Parameters
    ----------
    where : str
        The data's source, for the message.
    key : str
        The model file's key (``input_nominal``, ``output_nominal`` or ``disturbance_nominal``).
    nominal : ndarray, shape (k,)
        The operating point, in the channels' units.
    x : ndarray, shape (n_samples, k)
        The logged values (NaN where missing), in the same units.
    names : sequence of str, length k

    Raises
    ------
    DataFileError
        Naming the source, the key, the channel, the operating point and the channel's spread.
    """
    if x.ndim != 2 or x.shape[1] != nominal.size or x.shape[0] < 2:
        return
    for i in np.flatnonzero(nominal != 0):
        col = x[:, i]
        col = col[np.isfinite(col)]
        if col.size < 2:
            continue
        spread = float(np.std(col))
        if not moving_columns(col):
            continue
        largest = float(np.max(np.abs(col - nominal[i])))
        if largest > MAX_ANALYSIS_SCALE:        # refused later as too large, with its own message
            continue
        step = float(np.spacing(largest))
        if step > NOMINAL_ROUNDING_LIMIT * spread and step > float(np.spacing(np.max(np.abs(col)))):
            name = names[i] if i < len(names) else f"column {i}"
            raise DataFileError(
                f"{where}: the model's {key} of {name} ({float(nominal[i]):g}) is so far from its logged values "
                f"(standard deviation {spread:.3g}) that subtracting it rounds them to steps of {step:.3g} in 64-bit "
                f"floats, and its moves are lost; expected the operating point of the logged values (0 if they are "
                f"deviations already)")


SIGNAL_NAMES = ("setpoint", "input", "output")


def check_signals(r, u, y, n_outputs: int, n_inputs: int, n_samples: Optional[int] = None, where: str = ""):
    """``r``, ``u``, ``y`` as float arrays of the expected shapes with finite values.

    Parameters
    ----------
    r, u, y : array_like
        Setpoints, inputs and outputs: shapes (n_samples, n_outputs), (n_samples, n_inputs) and
        (n_samples, n_outputs), or one sample, (n_outputs,), (n_inputs,), (n_outputs,), when
        ``n_samples`` is None.
    n_outputs, n_inputs : int
    n_samples : int, optional
    where : str
        Prefix of the messages (e.g. ``"log.csv: "``).

    Returns
    -------
    list of ndarray
        ``[r, u, y]``.

    Raises
    ------
    DataFileError
        Naming the signal (``setpoint``, ``input`` or ``output``) and its shape against the
        expected one, or the signal that holds NaN or infinity.
    """
    out = []
    for name, value, width in zip(SIGNAL_NAMES, (r, u, y), (n_outputs, n_inputs, n_outputs)):
        arr = np.asarray(value, dtype=float)
        shape = (width,) if n_samples is None else (n_samples, width)
        if arr.shape != shape:
            raise DataFileError(f"{where}{name}: expected shape {shape}, got {arr.shape}")
        out.append(arr)
    for name, arr in zip(SIGNAL_NAMES, out):
        if not np.isfinite(arr).all():
            raise DataFileError(f"{where}{name}: values contain NaN or infinity")
    return out


def check_disturbance_signal(dv, n_disturbances: int, n_samples: Optional[int] = None, where: str = "") -> np.ndarray:
    """``dv`` (the measured disturbances) as a float array of the expected shape with finite values.

    Parameters
    ----------
    dv : array_like or None
        Shape (n_samples, n_disturbances), or one sample, (n_disturbances,), when ``n_samples`` is
        None.  None stands for no measured disturbance (accepted only when ``n_disturbances`` is 0).
    n_disturbances : int
    n_samples : int, optional
    where : str
        Prefix of the messages.

    Raises
    ------
    DataFileError
        ``measured disturbance: expected shape (...), got (...)`` (or ``got none``), or its values
        are not finite.
    """
    shape = (n_disturbances,) if n_samples is None else (n_samples, n_disturbances)
    if dv is None:
        if n_disturbances:
            raise DataFileError(f"{where}measured disturbance: expected shape {shape}, got none")
        return np.zeros(shape)
    arr = np.asarray(dv, dtype=float)
    if arr.shape != shape:
        raise DataFileError(f"{where}measured disturbance: expected shape {shape}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise DataFileError(f"{where}measured disturbance: values contain NaN or infinity")
    return arr


def check_loop_data(model: PlantModel, data: LoggedData):
    """The data's ``[r, u, y]`` (:func:`check_signals`) once its channels are the model's and its
    measured disturbances fit the model's (:func:`check_disturbance_signal`).

    Raises
    ------
    DataFileError
        Naming the data's source: channels that differ from the model's inputs, outputs and
        disturbances, or what :func:`check_signals` and :func:`check_disturbance_signal` refuse.
    """
    src = data.source or "data"
    if tuple(data.outputs) != tuple(model.outputs) or tuple(data.inputs) != tuple(model.inputs):
        raise DataFileError(f"{src}: channels {list(data.inputs)} / {list(data.outputs)} do not match the model's "
                            f"inputs {list(model.inputs)} / outputs {list(model.outputs)}")
    if tuple(data.disturbances) != tuple(model.disturbances):
        raise DataFileError(f"{src}: measured disturbances {list(data.disturbances)} do not match the model's "
                            f"disturbances {list(model.disturbances)}")
    n = np.shape(data.r)[0] if np.ndim(data.r) else 0
    out = check_signals(data.r, data.u, data.y, model.n_outputs, model.n_inputs, n, where=f"{src}: ")
    check_disturbance_signal(data.dv, model.n_disturbances, n, where=f"{src}: ")
    return out


#: An output is named as growing without bound when its spread in the last tenth of the log is more
#: than this many times its spread in the first tenth and in the middle one (:func:`divergence_warnings`).
DIVERGENCE_RATIO = 1e3


def divergence_warnings(names, y: np.ndarray) -> list:
    """Name the outputs that grow without bound over the log: a loop that diverged.

    A closed loop whose controller's model is badly wrong can go unstable; its outputs then grow
    geometrically.  The tests assume a bounded loop, so their p-values mean nothing there (or the
    linear algebra breaks down).  The spread of every output about its mean over the first tenth
    of the log is compared in three tenths: the first, the middle one and the last.  An output is
    named when the last tenth's spread exceeds :data:`DIVERGENCE_RATIO` times both others (the
    middle one guards against a first tenth that is merely quiet, such as a loop at rest before its
    first setpoint change).

    Parameters
    ----------
    names : sequence of str
        The outputs' names, shape (n_outputs,).
    y : ndarray, shape (n_samples, n_outputs)
        Measured outputs (output units).  NaN samples are ignored; an infinite value in the last
        tenth (a loop that overflowed) names its output.

    Returns
    -------
    list of str
        One warning per diverging output (none for a log shorter than 30 samples).
    """
    return [warning for _, warning in divergence(names, y)]


def divergence(names, y: np.ndarray) -> list:
    """``(name, warning)`` of every output :func:`divergence_warnings` names (same arguments), in order."""
    y = np.asarray(y, dtype=float)
    n = y.shape[0]
    if n < 30:
        return []
    k = n // 10
    first, middle, last = y[:k], y[(n - k) // 2:(n - k) // 2 + k], y[n - k:]
    out = []
    with np.errstate(over="ignore", invalid="ignore"):
        for c, name in enumerate(names):
            ref = np.nanmean(first[:, c]) if np.any(np.isfinite(first[:, c])) else 0.0
            spread = [float(np.sqrt(np.nanmean((part[:, c] - ref) ** 2))) if np.any(np.isfinite(part[:, c]))
                      else 0.0 for part in (first, middle, last)]
            a, b, z = spread
            if not np.isfinite(z) or z > DIVERGENCE_RATIO * max(a, b, 1e-300):
                out.append((name, f"output '{name}' grows without bound: its spread about its early mean is {a:.3g} in the "
                           f"first tenth of the log, {b:.3g} in the middle one and {z:.3g} in the last; the loop "
                           f"looks unstable (diverging), and the tests assume a bounded loop, so their results on "
                           f"this log are not reliable"))
    return out


def check_scale(model: PlantModel, data: LoggedData, model_source: str = "the model") -> None:
    """Refuse data (or model gains) so large that the squares in the analysis overflow float64, or so
    small that they underflow.

    Beyond :data:`MAX_ANALYSIS_SCALE` the fits break down (a ``LinAlgError``) or, worse, return a
    confident all-clear; a sensor's "bad value" sentinel such as 1e308 gets there.  A kind of channel
    (setpoints, inputs, measured disturbances, outputs) whose largest |value| is not 0 but below
    :data:`MIN_ANALYSIS_SCALE` is refused too.

    Parameters
    ----------
    model : PlantModel
    data : LoggedData
    model_source : str
        Where the model came from, for the message.  When outputs grow without bound
        (:func:`diverging_outputs`), the message says that the loop diverged instead of asking to
        rescale the units.

    Raises
    ------
    DataFileError
        Naming the source, the channel and the time of the largest value.
    """
    gain = float(np.max(np.abs(model.gain))) if model.gain.size else 0.0
    gain_words = "gains"
    if model.gain.size and not model.is_step_response and np.any(model.lead != 0):
        # A lead over its lags raises the element's gain at high frequency to |K| |lead| / (tau + tau2).
        lags = np.maximum(model.time_constant + model.time_constant2, model.sample_time)
        with np.errstate(over="ignore", invalid="ignore"):
            high = np.abs(model.gain) * np.maximum(1.0, np.abs(model.lead) / lags)
        if float(np.max(high)) > gain:
            i, j = np.unravel_index(int(np.argmax(high)), high.shape)
            gain_words = (f"the high-frequency gain of element ({model.outputs[i]}, {model.columns[j]})'s lead "
                          f"(gain x |lead| / its lags)")
        gain = max(gain, float(np.max(high)))
    if model.is_step_response and model.step_response.size:
        gain = max(gain, float(np.max(np.abs(model.step_response))))
    nominal = {"setpoint": ("output_nominal", model.output_nominal), "input": ("input_nominal", model.input_nominal),
               "measured disturbance": ("disturbance_nominal", model.disturbance_nominal),
               "output": ("output_nominal", model.output_nominal)}
    for name, arr, names in (("setpoint", data.r, model.outputs), ("input", data.u, model.inputs),
                             ("measured disturbance", data.dv, model.disturbances),
                             ("output", data.y, model.outputs)):
        arr = np.abs(np.asarray(arr, dtype=float))
        if arr.size == 0:
            continue
        k, j = np.unravel_index(int(np.argmax(arr)), arr.shape)
        peak = float(arr[k, j])
        if 0.0 < peak < MIN_ANALYSIS_SCALE:
            raise DataFileError(f"{data.source or 'data'}: the {name}s are at most {peak:.3g} (largest: '{names[j]}' "
                                f"at t = {t_text(data.t[k])} s): too small for the analysis (at least "
                                f"{MIN_ANALYSIS_SCALE:g}); rescale the units")
        if not peak * max(1.0, gain) <= MAX_ANALYSIS_SCALE:
            why = "" if peak > MAX_ANALYSIS_SCALE else f" with {gain_words} up to {gain:.3g} in {model_source}"
            key, values = nominal[name]
            if data.deviations and j < np.size(values) and values[j] != 0:
                # In deviations from the model's operating point: a huge nominal value is the model file's.
                why += f" (the logged value minus {key} {float(values[j]):g} of {model_source})"
            head = (f"{data.source or 'data'}: {name} '{names[j]}' at t = {t_text(data.t[k])} s is {peak:.3g}{why}: "
                    f"too large for the analysis (|value| x max(1, |gain|) at most {MAX_ANALYSIS_SCALE:g})")
            over = np.flatnonzero(~(arr[:, j] * max(1.0, gain) <= MAX_ANALYSIS_SCALE))
            rest = np.delete(arr[:, j], over)
            if over.size <= max(1, arr.shape[0] // 100) and over[-1] < arr.shape[0] - 1 and rest.size \
                    and np.all(np.isfinite(rest)) \
                    and float(rest.max()) * max(1.0, gain) <= MAX_ANALYSIS_SCALE / 1e3:
                # A few values far out of the rest's range: a sensor's bad-value sentinel, not a loop that diverged.
                raise DataFileError(f"{head}, while its other values stay within {float(rest.max()):.3g} "
                                    f"({over.size} such value{'s' if over.size > 1 else ''}): a bad-value sentinel? "
                                    f"Leave those rows out of the log (the analysis goes around missing rows)")
            diverging = diverging_outputs(model.outputs, data.y)
            raise DataFileError(f"{head}; {_diverged_hint(diverging) if diverging else 'rescale the units'}")


#: The errors of numpy and scipy with which the analysis's linear algebra breaks down on a log that
#: diverged or on degenerate values (:func:`numerical_breakdown`).
NUMERICAL_ERRORS = (np.linalg.LinAlgError, FloatingPointError, OverflowError)


def diverging_outputs(names, y: np.ndarray) -> list:
    """The names of the outputs that :func:`divergence_warnings` names (same arguments), in order; none
    when ``y`` does not have one column per name (a log refused elsewhere)."""
    y = np.asarray(y, dtype=float)
    if y.ndim != 2 or y.shape[1] != len(names):
        return []
    return [name for name, _ in divergence(names, y)]


def _diverged_hint(diverging) -> str:
    """The end of a message on a log whose outputs ``diverging`` grow without bound."""
    many = len(diverging) > 1
    return (f"the loop diverged (output{'s' if many else ''} {', '.join(repr(n) for n in diverging)} "
            f"grow{'' if many else 's'} without bound); the tests need a bounded loop: analyze the samples "
            f"logged before it diverged")


def numerical_breakdown(model: PlantModel, data: LoggedData, err: BaseException) -> DataFileError:
    """The error to raise when the analysis of ``data`` breaks down numerically with ``err``.

    The least-squares fits and the factorizations of the analysis fail (one of
    :data:`NUMERICAL_ERRORS`) mostly on a loop that diverged, whose outputs grow geometrically
    up to values too large for float64 squares to stay accurate.

    Parameters
    ----------
    model : PlantModel
    data : LoggedData
        The data analysed (its outputs are checked for divergence, :func:`diverging_outputs`).
    err : BaseException
        The numerical error (raise the result ``from err``).

    Returns
    -------
    DataFileError
        A one-line message naming the source and ``err``, then the first diverging output, its
        largest value and its time, or, on a bounded log, the general hint.
    """
    src = data.source or "data"
    cause = " ".join(str(err).split())[:200] or type(err).__name__
    y = np.asarray(data.y, dtype=float)
    diverging = diverging_outputs(model.outputs, y)
    if not diverging:
        return DataFileError(f"{src}: the analysis broke down numerically ({cause}): values or model parameters "
                             f"too large or degenerate?")
    c = list(model.outputs).index(diverging[0])
    size = np.abs(y[:, c])
    k = int(np.argmax(np.where(np.isnan(size), -1.0, size)))
    return DataFileError(f"{src}: the analysis broke down numerically ({cause}): output '{diverging[0]}' reaches "
                         f"{float(y[k, c]):.3g} at t = {t_text(data.t[k])} s; {_diverged_hint(diverging)}")
