"""Excitation core: PRBS setpoints, step/hold setpoints, an additive input dither and measured disturbances.

A pseudo-random binary sequence with switching probability 1/2 at every sample has a flat
spectrum from 0 to the Nyquist frequency (Ljung, *System Identification*, 2nd ed., section 13.3);
a smaller switching probability or a minimum hold time moves its power to lower frequencies.

Measured disturbances (:class:`MeasuredDisturbanceGenerator`) are what a feed rate or an ambient
temperature does: slowly varying steps between random levels plus low-pass filtered noise.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..core.errors import ConfigurationError


@dataclasses.dataclass(frozen=True)
class PrbsOptions:
    """Options of a PRBS signal.

    Attributes
    ----------
    amplitude : float
        Half the peak-to-peak level; the signal takes values ``offset +- amplitude``.
    switch_probability : float
        Probability of a switch at each sample once ``min_hold`` has elapsed, in (0, 1].
        0.5 gives a flat spectrum up to the Nyquist frequency.
    min_hold : int
        Minimum number of samples between switches (>= 1).
    offset : float
        Centre value.
    """

    amplitude: float = 1.0
    switch_probability: float = 0.5
    min_hold: int = 1
    offset: float = 0.0

    def __post_init__(self):
        check_prbs_options(self)


def check_prbs_options(opts: PrbsOptions) -> None:
    """Raise :class:`ConfigurationError` when an option is outside its range."""
    if not (np.isfinite(opts.amplitude) and opts.amplitude >= 0):
        raise ConfigurationError(f"amplitude: expected a finite number >= 0, got {opts.amplitude!r}")
    _check_switching(opts)


def _check_switching(opts) -> None:
    """``switch_probability``, ``min_hold`` and ``offset``, shared by the PRBS and the measured disturbances."""
    if not (0.0 < opts.switch_probability <= 1.0):
        raise ConfigurationError(f"switch_probability: expected a number in (0, 1], got {opts.switch_probability!r}")
    if int(opts.min_hold) != opts.min_hold or opts.min_hold < 1:
        raise ConfigurationError(f"min_hold: expected an integer >= 1 (samples), got {opts.min_hold!r}")
    if not np.isfinite(opts.offset):
        raise ConfigurationError(f"offset: expected a finite number, got {opts.offset!r}")


class PrbsGenerator:
    """Independent PRBS channels, one value per channel per call.

    Parameters
    ----------
    n_channels : int
        Number of channels.
    options : PrbsOptions
    rng : numpy.random.Generator
        Source of the switching decisions and of the initial signs.
    """

    def __init__(self, n_channels: int, options: PrbsOptions, rng: np.random.Generator):
        self.n_channels = int(n_channels)
        self.options = options
        self._rng = rng
        self._sign = np.where(rng.random(self.n_channels) < 0.5, -1.0, 1.0)
        self._held = np.zeros(self.n_channels, dtype=int)
        self._first = True

    def next(self) -> np.ndarray:
        """The next sample, shape (n_channels,)."""
        opts = self.options
        draw = self._rng.random(self.n_channels)
        if self._first:
            self._first = False
        else:
            switch = (self._held >= opts.min_hold) & (draw < opts.switch_probability)
            self._sign = np.where(switch, -self._sign, self._sign)
            self._held = np.where(switch, 0, self._held)
        self._held += 1
        return opts.offset + opts.amplitude * self._sign

    def generate(self, n_samples: int) -> np.ndarray:
        """``n_samples`` consecutive samples, shape (n_samples, n_channels)."""
        return np.array([self.next() for _ in range(int(n_samples))]).reshape(int(n_samples), self.n_channels)


class StepHoldGenerator:
    """Setpoints that step through a list of levels, holding each for ``hold_samples``.

    Parameters
    ----------
    levels : ndarray, shape (n_levels, n_channels)
        Successive setpoint vectors; the sequence repeats.
    hold_samples : int
        Samples each level is held (>= 1).
    """

    def __init__(self, levels, hold_samples: int):
        levels = np.atleast_2d(np.asarray(levels, dtype=float))
        if levels.size == 0 or not np.all(np.isfinite(levels)):
            raise ConfigurationError("levels: expected a non-empty list of finite setpoint vectors")
        if int(hold_samples) != hold_samples or hold_samples < 1:
            raise ConfigurationError(f"hold_samples: expected an integer >= 1, got {hold_samples!r}")
        self.levels = levels
        self.n_channels = levels.shape[1]
        self.hold_samples = int(hold_samples)
        self._k = 0

    def next(self) -> np.ndarray:
        """The next sample, shape (n_channels,)."""
        idx = (self._k // self.hold_samples) % self.levels.shape[0]
        self._k += 1
        return self.levels[idx].copy()

    def generate(self, n_samples: int) -> np.ndarray:
        """``n_samples`` consecutive samples, shape (n_samples, n_channels)."""
        return np.array([self.next() for _ in range(int(n_samples))]).reshape(int(n_samples), self.n_channels)


class ZeroGenerator:
    """A generator of zeros (no dither)."""

    def __init__(self, n_channels: int):
        self.n_channels = int(n_channels)

    def next(self) -> np.ndarray:
        return np.zeros(self.n_channels)

    def generate(self, n_samples: int) -> np.ndarray:
        return np.zeros((int(n_samples), self.n_channels))


class TimedDither:
    """A PRBS dither on some inputs for a fixed number of samples: an experiment that stops by itself.

    Each dithered input gets its own PRBS channel (switching probability 1/2, so a flat spectrum up
    to the Nyquist frequency) of values ``+- amplitude``; the other inputs get 0.

    Parameters
    ----------
    amplitudes : array_like, shape (n_inputs,)
        PRBS amplitude of every input, input units (0 = not dithered; none negative).
    samples : int
        Samples the dither lasts (>= 1).
    rng : numpy.random.Generator
        Source of the PRBS (injected, so that a seeded node gives the same dither again).
    """

    def __init__(self, amplitudes, samples: int, rng: np.random.Generator):
        a = np.asarray(amplitudes, dtype=float).reshape(-1)
        if not np.all(np.isfinite(a)) or np.any(a < 0) or not np.any(a > 0):
            raise ConfigurationError(f"amplitudes: expected finite numbers >= 0, at least one > 0, got {a.tolist()!r}")
        if int(samples) != samples or samples < 1:
            raise ConfigurationError(f"samples: expected an integer >= 1, got {samples!r}")
        self.amplitudes = a
        self.samples = int(samples)
        self.samples_left = int(samples)
        self._active = np.flatnonzero(a > 0)
        self._prbs = PrbsGenerator(len(self._active), PrbsOptions(amplitude=1.0), rng)

    @property
    def running(self) -> bool:
        """True while samples are left."""
        return self.samples_left > 0

    def next(self) -> np.ndarray:
        """The dither of the next sample, shape (n_inputs,); zeros once the samples are used up."""
        out = np.zeros(self.amplitudes.shape[0])
        if self.samples_left > 0:
            out[self._active] = self.amplitudes[self._active] * self._prbs.next()
            self.samples_left -= 1
        return out

    def stop(self) -> None:
        """End the dither now."""
        self.samples_left = 0


@dataclasses.dataclass(frozen=True)
class MeasuredDisturbanceOptions:
    """Measured disturbances: random steps plus first-order filtered noise, on every channel alike.

    Each channel is ``dv(k) = offset + level(k) + e(k)``: ``level`` holds a value drawn uniformly in
    ``[-step_amplitude, step_amplitude]`` and steps to a new one with probability
    ``switch_probability`` per sample once it has held ``min_hold`` samples (mean hold
    ``min_hold - 1 + 1 / switch_probability`` samples); ``e(k) = p e(k-1) + sqrt(1 - p^2) noise_std w(k)``
    with ``w`` white and unit-variance, started stationary, so that ``e`` has the standard deviation
    ``noise_std`` and the lag-1 correlation ``p = noise_pole``.  A size of 0 turns that kind off.

    Attributes
    ----------
    step_amplitude : float
        Largest step level, disturbance units (>= 0; 0 = no steps).
    switch_probability : float
        Probability of a step per sample once ``min_hold`` samples have passed, in (0, 1].
    min_hold : int
        Fewest samples between two steps (>= 1).
    noise_std : float
        Standard deviation of the filtered noise, disturbance units (>= 0; 0 = no noise).
    noise_pole : float
        Pole ``p`` of the noise filter, in [0, 1).
    offset : float
        Centre value, disturbance units.
    """

    step_amplitude: float = 1.0
    switch_probability: float = 0.01
    min_hold: int = 50
    noise_std: float = 0.05
    noise_pole: float = 0.95
    offset: float = 0.0

    def __post_init__(self):
        check_measured_disturbance_options(self)


def check_measured_disturbance_options(opts: MeasuredDisturbanceOptions) -> None:
    """Raise :class:`ConfigurationError` when an option is outside its range."""
    for key in ("step_amplitude", "noise_std"):
        v = getattr(opts, key)
        if not (np.isfinite(v) and v >= 0):
            raise ConfigurationError(f"{key}: expected a finite number >= 0 (disturbance units), got {v!r}")
    if not (0.0 <= opts.noise_pole < 1.0):
        raise ConfigurationError(f"noise_pole: expected a number in [0, 1), got {opts.noise_pole!r}")
    _check_switching(opts)


class MeasuredDisturbanceGenerator:
    """Independent measured-disturbance channels (:class:`MeasuredDisturbanceOptions`), one value per channel per call.

    Parameters
    ----------
    n_channels : int
        Number of measured disturbances.
    options : MeasuredDisturbanceOptions
    rng : numpy.random.Generator
        Source of the levels, the step times and the noise (injected: the same generator state
        gives the same signal, sample by sample or in a block).

    Notes
    -----
    Every sample draws the same numbers whatever happens (a uniform for the step decision, a
    uniform for a new level, a normal for the noise, per channel), so :meth:`next` and
    :meth:`generate` give the same signal.
    """

    def __init__(self, n_channels: int, options: MeasuredDisturbanceOptions, rng: np.random.Generator):
        self.n_channels = int(n_channels)
        self.options = options
        self._rng = rng
        n, o = self.n_channels, options
        self._level = o.step_amplitude * rng.uniform(-1.0, 1.0, n)
        self._noise = o.noise_std * rng.standard_normal(n)
        self._held = np.zeros(n, dtype=int)
        self._first = True

    def next(self) -> np.ndarray:
        """The next sample, shape (n_channels,)."""
        o, rng, n = self.options, self._rng, self.n_channels
        switch_draw = rng.random(n)
        new_level = o.step_amplitude * rng.uniform(-1.0, 1.0, n)
        w = rng.standard_normal(n)
        if self._first:
            self._first = False
        else:
            switch = (self._held >= o.min_hold) & (switch_draw < o.switch_probability)
            self._level = np.where(switch, new_level, self._level)
            self._held = np.where(switch, 0, self._held)
            p = o.noise_pole
            self._noise = p * self._noise + np.sqrt(1.0 - p * p) * o.noise_std * w
        self._held += 1
        return o.offset + self._level + self._noise

    def generate(self, n_samples: int) -> np.ndarray:
        """``n_samples`` consecutive samples, shape (n_samples, n_channels)."""
        return np.array([self.next() for _ in range(int(n_samples))]).reshape(int(n_samples), self.n_channels)
