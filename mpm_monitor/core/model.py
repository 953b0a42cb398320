"""The controller's plant model as data: a transfer matrix from the inputs and measured disturbances to the outputs.

Each element is first order plus dead time, or has a lead, a second lag or an integrator, or is given
by its step response (:mod:`mpm_monitor.core.elements`), in deviation variables, as in the model file
(docs/interfaces.md, "Model file", "Richer elements", "Measured disturbances").  This module holds
and validates the model; the YAML file is read and written by :mod:`mpm_monitor.io.model_file`, and
the discrete-time form lives in :mod:`mpm_monitor.core.elements` and :mod:`mpm_monitor.core.discretize`.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import unicodedata

import numpy as np

from .errors import ModelFileError

#: Relative tolerance with which a delay must be a multiple of the sample time.
DELAY_GRID_TOLERANCE = 1e-6
#: Largest dead time in samples (beyond it the sample count no longer fits the integer arithmetic
#: of the analysis, and no window could hold it anyway).
MAX_DELAY_SAMPLES = 2**31 - 1


def _unprintable(name: str) -> bool:
    """Whether a name holds a control character or a line/paragraph separator (it would split a
    one-line message or a CSV header)."""
    return any(unicodedata.category(c) in ("Cc", "Cs", "Zl", "Zp") for c in name)


def name_problem(name) -> "str | None":
    """Why ``name`` cannot be a channel name of a model (``"holds a comma"``, ...), or None when it can: a
    non-empty string without commas, control characters or surrounding spaces."""
    if not isinstance(name, str) or not name:
        return "is empty" if isinstance(name, str) else "is not text"
    if "," in name:
        return "holds a comma"
    if name != name.strip():
        return "has surrounding spaces"
    if _unprintable(name):
        return "holds a control character"
    return None


#: The element structures a model can hold, in the words of the model file.
PARAMETRIC_KEYS = ("gain", "time_constant", "delay", "lead", "time_constant2", "integrating")
#: The keys of the operating points (the columns' and outputs' nominal values), in the model file's order.
NOMINAL_KEYS = ("input_nominal", "output_nominal", "disturbance_nominal")


@dataclasses.dataclass(frozen=True)
class PlantModel:
    """The controller's plant model: a transfer matrix from the inputs and measured disturbances to the outputs.

    Every element (output ``i``, column ``j``) is parametric (:mod:`mpm_monitor.core.elements`)::

        K (lead s + 1) e^{-theta s} / ((tau s + 1)(tau2 s + 1))            self-regulating
        K (lead s + 1) e^{-theta s} / (s (tau s + 1)(tau2 s + 1))          integrating

    or, in a step-response model (``step_response`` given), the output change 1 .. N samples after a
    unit step of the column, the form of DMC-type controllers.  The columns are the manipulated
    inputs, then the measured disturbances (feedforward variables).

    Parameters
    ----------
    sample_time : float
        Seconds per sample, > 0.
    inputs : tuple of str
        Names of the manipulated variables, in column order (length ``n_inputs``).
    outputs : tuple of str
        Names of the controlled variables, in row order (length ``n_outputs``).
    gain : ndarray, shape (n_outputs, n_columns)
        ``K``: output units per input unit (per input unit per second when integrating); 0 means "no
        such effect".  For a step-response model: the final value (the last slope of a ramp row).
    time_constant : ndarray, shape (n_outputs, n_columns)
        ``tau`` in seconds, >= 0 (0 = no lag); 0 in a step-response model.
    delay : ndarray, shape (n_outputs, n_columns)
        Dead time ``theta`` in seconds, >= 0, a multiple of ``sample_time``; in a step-response
        model, the samples before the response first moves.
    input_nominal : ndarray, shape (n_inputs,)
        Operating point of the inputs (default zeros).
    output_nominal : ndarray, shape (n_outputs,)
        Operating point of the outputs (default zeros).
    name : str
        Free-text name.
    disturbances : tuple of str
        Names of the measured disturbances, whose columns follow the inputs (default none).
    lead : ndarray, shape (n_outputs, n_columns)
        ``lead`` in seconds (numerator ``lead s + 1``; negative = inverse response), default 0.
    time_constant2 : ndarray, shape (n_outputs, n_columns)
        Second lag ``tau2`` in seconds, >= 0, only where ``tau > 0``; default 0.
    integrating : ndarray of bool, shape (n_outputs, n_columns)
        Elements with a pole at ``s = 0`` (levels, pressures in closed vessels); default none.
    step_response : ndarray, shape (n_outputs, n_columns, N), optional
        A step-response model instead of the parametric keys (then ``gain``, ``time_constant`` and
        ``delay`` are derived from it, and ``lead``, ``time_constant2``, ``integrating`` stay at
        their defaults).  Use :meth:`from_step_response`.
    ramp : tuple of bool, optional
        Per output, for a step-response model: the response keeps the last slope beyond ``N``
        samples (an integrating output).  Default: no ramp.
    disturbance_nominal : ndarray, shape (n_disturbances,)
        Operating point of the measured disturbances, in their logged units (default zeros): a feed
        temperature logged at 350 acts through its elements as its deviation from this.
    """

    sample_time: float
    inputs: tuple
    outputs: tuple
    gain: np.ndarray
    time_constant: np.ndarray
    delay: np.ndarray
    input_nominal: np.ndarray = None
    output_nominal: np.ndarray = None
    name: str = ""
    disturbances: tuple = ()
    lead: np.ndarray = None
    time_constant2: np.ndarray = None
    integrating: np.ndarray = None
    step_response: np.ndarray = None
    ramp: tuple = None
    disturbance_nominal: np.ndarray = None

    def __post_init__(self):
        for key in ("inputs", "outputs", "disturbances"):
            object.__setattr__(self, key, tuple(getattr(self, key)))
        ny, nu = len(self.outputs), len(self.inputs)
        if self.step_response is not None:
            sr = np.array(self.step_response, dtype=float, copy=True)
            sr.setflags(write=False)
            object.__setattr__(self, "step_response", sr)
            ramp = (False,) * ny if self.ramp is None else tuple(bool(b) for b in self.ramp)
            object.__setattr__(self, "ramp", ramp)
            validate_step_response(self)
            gain, delay = _step_response_summary(sr, ramp, self.sample_time)
            object.__setattr__(self, "gain", gain)
            object.__setattr__(self, "delay", delay)
            object.__setattr__(self, "time_constant", np.zeros_like(gain))
        elif self.ramp is not None and any(self.ramp):
            raise ModelFileError("model: key 'ramp': only a step-response model (key 'step_response') takes a ramp")
        else:
            object.__setattr__(self, "ramp", None)
        for key in ("gain", "time_constant", "delay"):
            arr = np.array(getattr(self, key), dtype=float, copy=True)
            arr.setflags(write=False)
            object.__setattr__(self, key, arr)
        shape = self.gain.shape
        for key, dtype in (("lead", float), ("time_constant2", float), ("integrating", bool)):
            val = getattr(self, key)
            arr = np.zeros(shape, dtype=dtype) if val is None else np.array(val, dtype=dtype, copy=True)
            arr.setflags(write=False)
            object.__setattr__(self, key, arr)
        for key, n in zip(NOMINAL_KEYS, (nu, ny, len(self.disturbances))):
            val = getattr(self, key)
            arr = np.zeros(n) if val is None else np.array(val, dtype=float, copy=True)
            arr.setflags(write=False)
            object.__setattr__(self, key, arr)
        validate_model(self)
        # The sampled forms of the elements, by (i, j), and what is computed from one element alone (keys
        # ending in (i, j), e.g. element_windows.element_onset's): with_element keeps those of the others.
        object.__setattr__(self, "_elements", {})
        object.__setattr__(self, "_derived", {})        # forms computed from the elements (discretize)

    @classmethod
    def from_step_response(cls, sample_time: float, inputs, outputs, coefficients, ramp=None,
                           disturbances=(), **kwargs) -> "PlantModel":
        """A step-response model: ``coefficients`` of shape (n_outputs, n_columns, N) (see the class)."""
        coefficients = np.asarray(coefficients, dtype=float)
        zeros = np.zeros(coefficients.shape[:2]) if coefficients.ndim == 3 else np.zeros((0, 0))
        return cls(sample_time=sample_time, inputs=inputs, outputs=outputs, gain=zeros, time_constant=zeros,
                   delay=zeros, disturbances=disturbances, step_response=coefficients, ramp=ramp, **kwargs)

    # ------------------------------------------------------------------ shape
    @property
    def n_inputs(self) -> int:
        """Number of manipulated inputs (the first columns)."""
        return len(self.inputs)

    @property
    def n_disturbances(self) -> int:
        """Number of measured disturbances (the last columns)."""
        return len(self.disturbances)

    @property
    def n_columns(self) -> int:
        """Number of columns: inputs, then measured disturbances."""
        return len(self.inputs) + len(self.disturbances)

    @property
    def columns(self) -> tuple:
        """Column names: the inputs, then the measured disturbances."""
        return self.inputs + self.disturbances

    @property
    def n_outputs(self) -> int:
        """Number of outputs (rows)."""
        return len(self.outputs)

    def role(self, j: int) -> str:
        """``"input"`` or ``"disturbance"``: what column ``j`` is."""
        return "input" if j < self.n_inputs else "disturbance"

    # ------------------------------------------------------------------ structure
    @property
    def is_step_response(self) -> bool:
        """True for a step-response (DMC-type) model."""
        return self.step_response is not None

    @property
    def step_length(self) -> int:
        """``N``, the number of step-response coefficients (0 for a parametric model)."""
        return 0 if self.step_response is None else int(self.step_response.shape[2])

    @property
    def delay_samples(self) -> np.ndarray:
        """Dead times in samples, integer array of shape (n_outputs, n_columns) (read-only; computed once)."""
        out = self._derived.get("delay_samples")
        if out is None:
            out = np.rint(self.delay / self.sample_time).astype(int)
            out.setflags(write=False)
            self._derived["delay_samples"] = out
        return out

    @property
    def present(self) -> np.ndarray:
        """Elements with an effect, bool array of shape (n_outputs, n_columns) (read-only; computed once)."""
        out = self._derived.get("present")
        if out is None:
            out = np.any(self.step_response != 0, axis=2) if self.step_response is not None else self.gain != 0
            out.setflags(write=False)
            self._derived["present"] = out
        return out

    @property
    def integrating_outputs(self) -> tuple:
        """Per output: True when one of its elements integrates (the output does not settle); for a
        step-response model, a ``ramp`` output, also one whose every element is zero (the model declares a
        level it has no element of yet: a missing element is repaired integrating, its level is arbitrary)."""
        if self.step_response is not None:
            return tuple(bool(b) for b in self.ramp)
        return tuple(bool(np.any(self.integrating[i] & (self.gain[i] != 0))) for i in range(self.n_outputs))

    def discrete_element(self, i: int, j: int):
        """The exact sampled form of element (``i``, ``j``), a :class:`~mpm_monitor.core.elements.DiscreteElement`."""
        cache = self._elements
        key = (i, j)
        if key not in cache:
            from .elements import from_step_response, sample_parametric

            if self.step_response is not None:
                cache[key] = from_step_response(self.step_response[i, j], self.ramp[i])
            else:
                cache[key] = sample_parametric(
                    self.gain[i, j], self.time_constant[i, j], int(self.delay_samples[i, j]), self.sample_time,
                    lead=float(self.lead[i, j]), time_constant2=float(self.time_constant2[i, j]),
                    integrating=bool(self.integrating[i, j]))
        return cache[key]

    def element(self, i: int, j: int) -> dict:
        """Parameters of element (output ``i``, column ``j``) as a dict (seconds).

        Always ``gain``, ``time_constant`` and ``delay``; ``lead``, ``time_constant2`` and
        ``integrating`` where the element has them; ``step_response`` (the N coefficients) in a
        step-response model.
        """
        out = {
            "gain": float(self.gain[i, j]),
            "time_constant": float(self.time_constant[i, j]),
            "delay": float(self.delay[i, j]),
        }
        if self.step_response is not None:
            out["step_response"] = [float(v) for v in self.step_response[i, j]]
            return out
        if self.lead[i, j] != 0:
            out["lead"] = float(self.lead[i, j])
        if self.time_constant2[i, j] != 0:
            out["time_constant2"] = float(self.time_constant2[i, j])
        if self.integrating[i, j]:
            out["integrating"] = True
        return out

    def replace(self, **changes) -> "PlantModel":
        """Return a copy with some fields replaced (validated again).

        New ``disturbances`` without a new ``disturbance_nominal`` start at the origin when the
        model's disturbances are at it (a model with other operating points must say the new ones).
        """
        if "disturbances" in changes and "disturbance_nominal" not in changes \
                and len(changes["disturbances"]) != self.n_disturbances and not np.any(self.disturbance_nominal):
            changes["disturbance_nominal"] = None
        return dataclasses.replace(self, **changes)

    def with_element(self, i: int, j: int, gain=None, time_constant=None, delay=None, lead=None,
                     time_constant2=None, integrating=None, step_response=None) -> "PlantModel":
        """Return a copy in which element (i, j) has new parameters (None keeps the old one).

        A step-response model takes ``step_response`` (N coefficients) only; a parametric model the
        parametric keys.  The copy keeps the sampled forms of the other elements
        (:meth:`discrete_element`), which depend on their own parameters only.
        """
        out = self._with_element(i, j, gain, time_constant, delay, lead, time_constant2, integrating, step_response)
        out._elements.update((key, v) for key, v in self._elements.items() if key[-2:] != (i, j))
        return out

    def _with_element(self, i, j, gain, time_constant, delay, lead, time_constant2, integrating, step_response):
        if self.step_response is not None:
            if any(v is not None for v in (gain, time_constant, delay, lead, time_constant2, integrating)):
                raise ValueError("a step-response model's element is changed through its step_response")
            sr = np.array(self.step_response)
            if step_response is not None:
                sr[i, j] = np.asarray(step_response, dtype=float)
            return self.replace(step_response=sr)
        if step_response is not None:
            raise ValueError("a parametric model's element is changed through its parameters")
        arrays = {k: np.array(getattr(self, k)) for k in PARAMETRIC_KEYS}
        for key, value in (("gain", gain), ("time_constant", time_constant), ("delay", delay), ("lead", lead),
                           ("time_constant2", time_constant2), ("integrating", integrating)):
            if value is not None:
                arrays[key][i, j] = value
        return self.replace(**arrays)

    def to_dict(self) -> dict:
        """The model as plain Python values in the schema of the model file (``docs/interfaces.md``)."""

        def num(x):
            x = float(x)
            return int(x) if x.is_integer() and abs(x) < 2**53 else x

        matrix = _plain

        out = {"sample_time": num(self.sample_time), "inputs": list(self.inputs), "outputs": list(self.outputs)}
        if self.disturbances:
            out["disturbances"] = list(self.disturbances)
        if self.step_response is not None:
            out["step_response"] = {"length": self.step_length,
                                    "coefficients": _plain(self.step_response)}
            if any(self.ramp):
                out["ramp"] = [bool(b) for b in self.ramp]
        else:
            out["gain"] = matrix(self.gain)
            out["time_constant"] = matrix(self.time_constant)
            out["delay"] = matrix(self.delay)
            if np.any(self.lead != 0):
                out["lead"] = matrix(self.lead)
            if np.any(self.time_constant2 != 0):
                out["time_constant2"] = matrix(self.time_constant2)
            if np.any(self.integrating):
                out["integrating"] = [[bool(v) for v in row] for row in self.integrating]
        if np.any(self.input_nominal != 0):
            out["input_nominal"] = _plain(self.input_nominal)
        if np.any(self.output_nominal != 0):
            out["output_nominal"] = _plain(self.output_nominal)
        if np.any(self.disturbance_nominal != 0):
            out["disturbance_nominal"] = _plain(self.disturbance_nominal)
        if self.name:
            out["name"] = self.name
        return out

    def __eq__(self, other):
        """Whether the two models write the same model file (:meth:`to_dict`): the same sample time, names and
        numbers (a step-response model's coefficients and ramps, a parametric model's parameters; the nominal
        values), compared as arrays without building the file's lists."""
        if not isinstance(other, PlantModel):
            return NotImplemented
        if self is other:
            return True
        if (float(self.sample_time) != float(other.sample_time) or (self.name or "") != (other.name or "")
                or (self.inputs, self.outputs, self.disturbances) != (other.inputs, other.outputs, other.disturbances)
                or (self.step_response is None) != (other.step_response is None)):
            return False
        if self.step_response is not None:
            keys = ("step_response",)
            if self.ramp != other.ramp:
                return False
        else:
            keys = PARAMETRIC_KEYS
        return all(np.array_equal(getattr(self, key), getattr(other, key))
                   for key in keys + NOMINAL_KEYS)

    __hash__ = None


def _plain(a) -> list:
    """``a`` (any shape) as nested lists of Python numbers, as the model file writes them: a whole
    number below 2**53 in magnitude as an ``int``, any other value as a ``float``.  The same values as
    converting each entry with ``float`` and then ``int`` where whole, in one pass over the array."""
    a = np.asarray(a, dtype=float)
    values = a.ravel()
    flat = values.tolist()
    with np.errstate(invalid="ignore"):
        whole = np.flatnonzero(np.isfinite(values) & (np.trunc(values) == values) & (np.abs(values) < 2.0 ** 53))
    for k in whole.tolist():
        flat[k] = int(flat[k])
    return _nested(flat, a.shape)


def _nested(flat: list, shape: tuple) -> list:
    """The row-major list ``flat`` as lists nested to ``shape``."""
    if len(shape) <= 1:
        return flat
    step = int(np.prod(shape[1:], dtype=int))
    return [_nested(flat[k * step:(k + 1) * step], shape[1:]) for k in range(shape[0])]


def _step_response_summary(sr: np.ndarray, ramp: tuple, ts: float):
    """(gain, delay in s) of every element of a step-response model: the final value (the last slope
    per second of a ramp row) and the samples before the response first moves
    (:func:`~mpm_monitor.core.elements.dead_time_samples` of each element, taken for all at once); both 0
    for an element without a response."""
    ny, nc, n = sr.shape
    if n == 0:
        return np.zeros((ny, nc)), np.zeros((ny, nc))
    moves = np.any(sr != 0, axis=2)
    last = sr[:, :, -1]
    if n >= 2:
        last = np.where(np.asarray(ramp, dtype=bool)[:, None], (sr[:, :, -1] - sr[:, :, -2]) / ts, last)
    size = np.abs(sr)
    moved = size > 1e-9 * size.max(axis=2, keepdims=True)
    dead = np.argmax(moved, axis=2)                 # the first moved sample (0 where none: no response)
    gain = np.where(moves, last, 0.0)
    delay = np.where(moves, dead * ts, 0.0)
    return gain, delay


def element_where(outputs, columns, i: int, j: int) -> str:
    """``row 2 (y2), column 1 (u1)`` for messages: the entry ``(i, j)`` (0-based) of an outputs x columns matrix,
    with its channels' names (``?`` beyond the names given)."""
    return (f"row {i + 1} ({outputs[i] if i < len(outputs) else '?'}), "
            f"column {j + 1} ({columns[j] if j < len(columns) else '?'})")


def _where(model, i: int, j: int) -> str:
    """``row 2 (y2), column 1 (u1)`` for messages."""
    return element_where(model.outputs, model.columns, i, j)


def _check_names(source: str, key: str, names, allow_empty: bool = False) -> None:
    if len(names) == 0 and not allow_empty:
        raise ModelFileError(f"{source}: key '{key}': expected a non-empty list of names")
    for n in names:
        if name_problem(n) is not None:
            raise ModelFileError(
                f"{source}: key '{key}': expected names as non-empty strings without commas, "
                f"control characters or surrounding spaces, got {n!r}")
    if len(set(names)) != len(names):
        dup = sorted(n for n, k in collections.Counter(names).items() if k > 1)
        raise ModelFileError(f"{source}: key '{key}': names must be unique, repeated: {', '.join(dup)}")


def validate_model(model: PlantModel, source: str = "model") -> None:
    """Check a model's shapes and values; raise :class:`ModelFileError` naming the key and the element.

    Parameters
    ----------
    model : PlantModel
        The model to check.
    source : str
        Name of the file or object, used as the message prefix.
    """
    ts = model.sample_time
    if not isinstance(ts, (int, float, np.floating)) or not math.isfinite(ts) or ts <= 0:
        raise ModelFileError(f"{source}: key 'sample_time': expected a positive finite number of seconds, got {ts!r}")
    ny, nu, nc = len(model.outputs), len(model.inputs), model.n_columns
    _check_names(source, "inputs", model.inputs)
    _check_names(source, "outputs", model.outputs)
    _check_names(source, "disturbances", model.disturbances, allow_empty=True)
    for (ka, a), (kb, b) in ((("inputs", model.inputs), ("outputs", model.outputs)),
                             (("disturbances", model.disturbances), ("inputs", model.inputs)),
                             (("disturbances", model.disturbances), ("outputs", model.outputs))):
        overlap = set(a) & set(b)
        if overlap:
            raise ModelFileError(
                f"{source}: keys '{ka}' and '{kb}': a name cannot be both, found {', '.join(sorted(overlap))}")
    # Every channel must be its own column of the CSV log (docs/interfaces.md, "Logged data (CSV)").
    columns = ([("t", None)] + [(f"r_{o}", "outputs") for o in model.outputs] + [(c, "inputs") for c in model.inputs]
               + [(c, "disturbances") for c in model.disturbances] + [(c, "outputs") for c in model.outputs])
    count = collections.Counter(c for c, _ in columns)
    clash = sorted(c for c, n in count.items() if n > 1)
    if clash:
        keys = list(dict.fromkeys(k for c, k in columns if c == clash[0] and k is not None))
        raise ModelFileError(
            f"{source}: key{'s' if len(keys) > 1 else ''} {' and '.join(repr(k) for k in keys)}: name {clash[0]!r} "
            f"would be two columns of the CSV log (t, r_<output>, <input>, <disturbance>, <output>): rename the "
            f"channel")
    what = "outputs x inputs" if not model.disturbances else "outputs x (inputs, then disturbances)"
    for key in ("gain", "time_constant", "delay", "lead", "time_constant2", "integrating"):
        arr = getattr(model, key)
        if arr.shape != (ny, nc):
            raise ModelFileError(
                f"{source}: key '{key}': expected {ny} rows x {nc} columns ({what}), got shape "
                f"{'x'.join(str(s) for s in arr.shape) or 'scalar'}")
        if arr.dtype != bool and not np.all(np.isfinite(arr)):
            i, j = np.argwhere(~np.isfinite(arr))[0]
            raise ModelFileError(f"{source}: key '{key}': {_where(model, i, j)}: expected a finite number, "
                                 f"got {arr[i, j]}")
    for key in ("time_constant", "time_constant2", "delay"):
        arr = getattr(model, key)
        if np.any(arr < 0):
            i, j = np.argwhere(arr < 0)[0]
            raise ModelFileError(f"{source}: key '{key}': {_where(model, i, j)}: expected >= 0 seconds, "
                                 f"got {arr[i, j]:g}")
    present = model.gain != 0
    bad = (model.time_constant2 > 0) & (model.time_constant == 0)
    if np.any(bad):
        i, j = np.argwhere(bad)[0]
        raise ModelFileError(
            f"{source}: key 'time_constant2': {_where(model, i, j)}: a second lag of {model.time_constant2[i, j]:g} s "
            f"without a first one (time_constant 0): give the lag as time_constant")
    bad = present & (model.lead != 0) & (model.time_constant == 0) & ~model.integrating
    if np.any(bad):
        i, j = np.argwhere(bad)[0]
        raise ModelFileError(
            f"{source}: key 'lead': {_where(model, i, j)}: a lead of {model.lead[i, j]:g} s needs a lag "
            f"(time_constant > 0) or an integrator: (lead s + 1) alone is a derivative, not a process")
    with np.errstate(over="ignore"):
        ratio = model.delay / ts
    if np.any(ratio > MAX_DELAY_SAMPLES):
        i, j = np.argwhere(ratio > MAX_DELAY_SAMPLES)[0]
        raise ModelFileError(
            f"{source}: key 'delay': {_where(model, i, j)}: expected at most {MAX_DELAY_SAMPLES} samples of "
            f"sample_time {ts:g} s, got {model.delay[i, j]:g} s")
    off = np.abs(ratio - np.rint(ratio)) > DELAY_GRID_TOLERANCE * np.maximum(1.0, np.abs(ratio))
    if np.any(off):
        i, j = np.argwhere(off)[0]
        raise ModelFileError(
            f"{source}: key 'delay': {_where(model, i, j)}: expected a multiple of sample_time {ts:g} s, "
            f"got {model.delay[i, j]:g} s")
    for key, arr, names in (("input_nominal", model.input_nominal, model.inputs),
                            ("output_nominal", model.output_nominal, model.outputs),
                            ("disturbance_nominal", model.disturbance_nominal, model.disturbances)):
        n = len(names)
        if arr.shape != (n,):
            got = f"{arr.shape[0]} number{'s' if arr.shape[0] != 1 else ''}" if arr.ndim == 1 else \
                f"shape {arr.shape}"
            raise ModelFileError(f"{source}: key '{key}': expected a list of {n} numbers (one per channel of "
                                 f"{', '.join(names) or 'none'}), got {got}")
        if not np.all(np.isfinite(arr)):
            k = int(np.flatnonzero(~np.isfinite(arr))[0])
            raise ModelFileError(f"{source}: key '{key}': entry {k + 1} ({names[k]}): expected a finite number, "
                                 f"got {arr[k]:g}")


def validate_step_response(model: PlantModel, source: str = "model") -> None:
    """Check the ``step_response`` and ``ramp`` of a step-response model (one line naming the element)."""
    sr = model.step_response
    ny, nc = len(model.outputs), len(model.inputs) + len(model.disturbances)
    if sr.ndim != 3 or sr.shape[:2] != (ny, nc) or sr.shape[2] < 1:
        raise ModelFileError(
            f"{source}: key 'step_response': expected coefficients of {ny} rows x {nc} columns x N >= 1 values, "
            f"got shape {'x'.join(str(s) for s in sr.shape) or 'scalar'}")
    if not np.all(np.isfinite(sr)):
        i, j, k = np.argwhere(~np.isfinite(sr))[0]
        raise ModelFileError(
            f"{source}: key 'step_response': {_where(model, i, j)}, "
            f"coefficient {k + 1}: expected a finite number, got {sr[i, j, k]}")
    if len(model.ramp) != ny:
        raise ModelFileError(f"{source}: key 'ramp': expected one true/false per output ({ny}), got {len(model.ramp)}")
