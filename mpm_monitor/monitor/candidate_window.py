"""The candidate channels of the live monitor: stamped vectors of extra logged variables, kept beside the window.

Candidate channels (docs/interfaces.md, "Candidate channels") arrive on their own stamped-vector topic
(``candidate_topic``), each message naming its channels.  They never hold up a sample of the
:class:`~mpm_monitor.monitor.window.SampleWindow`: :class:`CandidateWindow` keeps the latest vectors by
stamp, and :meth:`CandidateWindow.attach` puts them on the window's samples when an analysis is
taken -- a channel with a value at every sample of the window into ``LoggedData.extra``, one missing
at some samples (or not finite there) into ``LoggedData.unusable`` with the reason.
"""

from __future__ import annotations

import collections
import dataclasses
from typing import Optional, Sequence

import numpy as np

from ..core.errors import ConfigurationError
from ..core.logged_data import LoggedData
from ..core.model import name_problem
from .window import NS_PER_S, names_text, seconds_text

#: Most candidate channels the vectors kept may name together: each is tested against every output at
#: every analysis, and the vectors kept hold a value of each (a vector of a few hundred thousand names once
#: took the window's memory with it).
MAX_CANDIDATE_CHANNELS = 64


class CandidateWindow:
    """The latest candidate vectors by stamp (see the module docstring).

    Parameters
    ----------
    sample_time : float
        Seconds per sample.
    capacity : int
        Vectors kept (the window's length plus some slack: older ones are forgotten).
    stamp_tolerance : float
        Largest distance between a candidate stamp and a sample's, fraction of the sample time.
    reserved : sequence of str
        The model's own channels (inputs, measured disturbances, outputs): a vector naming one is
        refused, since the analysis would refuse it as a candidate on every window it falls in.
    late_samples : int
        Most samples at the end of a window that :meth:`attach` leaves out because no candidate vector
        has come for them yet (the window's ``reorder_samples``): a vector stamped like a sample that
        arrives after that sample's output vector (another publisher, or the executor serving the output
        first) is waited for, not counted missing.
    """

    def __init__(self, sample_time: float, capacity: int, stamp_tolerance: float = 0.25, reserved: Sequence[str] = (),
                 late_samples: int = 0):
        if not (np.isfinite(sample_time) and sample_time > 0):
            raise ConfigurationError(f"sample_time: expected a finite number > 0 (seconds), got {sample_time!r}")
        if int(capacity) != capacity or capacity < 1:
            raise ConfigurationError(f"capacity: expected an integer >= 1, got {capacity!r}")
        self._period = int(round(sample_time * NS_PER_S))
        self._tol = int(stamp_tolerance * self._period)
        self._vectors: collections.deque = collections.deque(maxlen=int(capacity))
        # The channels of the vectors kept, in order of first appearance, with how many vectors name
        # each: a channel leaves with its last vector, so that channels come and go for months
        # without the list growing.
        self._names: dict = {}
        self._reserved = frozenset(reserved)
        self._late = int(late_samples)
        self.received = 0

    @property
    def names(self) -> tuple:
        """The candidate channels named by the vectors kept (at most the last ``capacity``)."""
        return tuple(self._names)

    def add(self, stamp_ns: int, names: Sequence[str], values) -> Optional[str]:
        """Keep one vector; returns None, or why it was refused (names and values differ in length, a
        name is empty, repeated, one of the model's channels or no name a model's channel may have).

        A channel's name follows the rule of a model's channel names
        (:func:`~mpm_monitor.core.model.name_problem`): no comma, control character (tab, line break)
        or surrounding space.  The statuses join channel names with commas, and the offline analysis
        finds a candidate so named unusable, so a vector naming one is refused whole.

        Parameters
        ----------
        stamp_ns : int
            Its stamp, nanoseconds.
        names : sequence of str
            The channels.
        values : array_like, shape (len(names),)
            Their values (a non-finite value makes its channel unusable over the windows it falls in).
        """
        names = tuple(str(n) for n in names)
        v = np.asarray(values, dtype=float).reshape(-1)
        t = f"t = {seconds_text(int(stamp_ns))} s"
        if v.shape[0] != len(names):
            return f"candidate: {v.shape[0]} value(s) for {len(names)} name(s) at {t} (one value per name expected)"
        if any(not n for n in names) or len(set(names)) != len(names):
            return f"candidate: empty or repeated channel names at {t}: {names_text(names)}"
        for n in names:
            why = name_problem(n)
            if why is not None:
                return (f"candidate: channel name {names_text([n])} at {t} {why}: expected a channel name without "
                        f"commas, control characters (tabs, line breaks) or surrounding spaces, as a model's channel")
        clash = [n for n in names if n in self._reserved]
        if clash:
            return (f"candidate: {names_text(clash)} at {t} "
                    f"{'is a channel' if len(clash) == 1 else 'are channels'} of the model, not a candidate")
        new = [n for n in names if n not in self._names]
        if len(self._names) + len(new) > MAX_CANDIDATE_CHANNELS:
            return (f"candidate: {len(names)} channel(s) at {t} ({names_text(names)}) would make "
                    f"{len(self._names) + len(new)} candidate channels in the window: expected at most "
                    f"{MAX_CANDIDATE_CHANNELS}")
        if len(self._vectors) == self._vectors.maxlen:             # the oldest vector leaves
            for n in self._vectors[0][1]:
                self._names[n] -= 1
                if not self._names[n]:
                    del self._names[n]
        for n in names:
            self._names[n] = self._names.get(n, 0) + 1
        self._vectors.append((int(stamp_ns), dict(zip(names, v))))
        self.received += 1
        return None

    def attach(self, data: LoggedData) -> LoggedData:
        """``data`` with the candidate channels on its samples (``extra``; ``unusable`` where a channel
        has no finite value at some samples).  The channels the data already has are left alone.

        The samples at the end of ``data`` stamped after every vector kept, when there are at most
        ``late_samples`` of them (and fewer than all), are left out: their vectors have not come yet.
        More of them (a candidate publisher that stopped) are kept, and the channels are missing there."""
        if not self._names:              # else some vector kept names a channel: ``got`` below is not empty
            return data
        stamps = np.rint(np.asarray(data.t, dtype=float) * NS_PER_S).astype(np.int64)
        got = np.array([s for s, _ in self._vectors], dtype=np.int64)
        order = np.argsort(got, kind="stable")
        got = got[order]
        vectors = [self._vectors[k][1] for k in order]
        n = stamps.shape[0]
        late = int(np.count_nonzero(stamps > got[-1] + self._tol))
        if 0 < late <= self._late and late < n:
            n -= late
            data, stamps = data.slice(0, n), stamps[:n]
        match = np.full(n, -1)
        pos = np.clip(np.searchsorted(got, stamps), 0, got.size - 1)
        for cand in (pos, np.maximum(pos - 1, 0)):
            close = (np.abs(got[cand] - stamps) <= self._tol) & (match < 0)
            match[close] = cand[close]
        extra, unusable = dict(data.extra), dict(data.unusable)
        for name in self._names:
            if name in extra or name in unusable:
                continue
            x = np.array([vectors[m].get(name, np.nan) if m >= 0 else np.nan for m in match], dtype=float)
            bad = int(np.count_nonzero(~np.isfinite(x)))
            if bad:
                unusable[name] = f"partly missing: no finite value at {bad} of the window's {n} samples"
            else:
                extra[name] = x
        return dataclasses.replace(data, extra=extra, unusable=unusable)
