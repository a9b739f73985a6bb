"""Pairing of time-stamped message streams (a pure-Python stand-in for ROS 2 ``message_filters``).

Two tools with the same matching rule:

* :func:`pair_by_stamp` pairs complete, in-memory streams offline (the reference).
* :class:`StampSynchronizer` does the same online, one message at a time, with bounded memory; the
  bag reader uses it to stream (image, camera_info, pose) samples, and ROS nodes can use it to pair
  live images with, e.g., simulated depth rendered for them.

Matching rule
-------------
One stream is the *primary* (usually the camera images): every primary message becomes at most one
match. For each other (*secondary*) stream, the partner of a primary message stamped ``t`` is the
secondary message whose stamp is nearest to ``t``; an exact stamp match is therefore always
preferred, and ties between an earlier and a later message at the same distance go to the earlier
one. The partner must lie within that stream's tolerance ``max_dt`` (seconds), otherwise the primary
message is dropped and the drop is counted. Secondary messages may be reused by several primary
messages: a ``camera_info`` published at 1 Hz serves every 30 Hz image near it. Among several
messages of one stream with the same stamp, the last one received is used. (This differs from
``message_filters.ApproximateTimeSynchronizer``, which uses each message once and so drops images
whenever the other streams are slower.)

Stamps are integer nanoseconds (``builtin_interfaces/Time`` as ``sec * 10**9 + nanosec``, rclpy's
``Time.nanoseconds``); tolerances are seconds.
"""
from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

__all__ = ["Match", "SyncStats", "pair_by_stamp", "StampSynchronizer", "seconds_to_ns"]


def seconds_to_ns(seconds: float | None) -> int | None:
    """A non-negative tolerance in seconds as integer nanoseconds (``None`` and ``inf`` -> ``None``)."""
    if seconds is None:
        return None
    s = float(seconds)
    if math.isnan(s) or s < 0:
        raise ValueError(f"a time tolerance must be >= 0 seconds (or None for unlimited), got {seconds!r}")
    if math.isinf(s):
        return None
    return int(round(s * 1e9))


def _check_stamp(stamp) -> int:
    if isinstance(stamp, bool) or not isinstance(stamp, (int,)) and not hasattr(stamp, "__index__"):
        raise TypeError(f"stamps must be integer nanoseconds, got {type(stamp).__name__} {stamp!r}")
    return int(stamp)


@dataclass(frozen=True)
class Match:
    """A primary message and its partner in every secondary stream.

    Attributes
    ----------
    stamp_ns : int
        Stamp of the primary message.
    items : tuple
        ``(primary_item, secondary_1_item, ...)`` in stream order.
    stamps_ns : tuple of int
        The stamps of ``items``.
    """

    stamp_ns: int
    items: tuple
    stamps_ns: tuple

    @property
    def dt_ns(self) -> tuple:
        """Signed offset ``stamp(secondary) - stamp(primary)`` of each secondary stream, in ns."""
        return tuple(s - self.stamp_ns for s in self.stamps_ns[1:])


@dataclass
class SyncStats:
    """Counters of a pairing run.

    Attributes
    ----------
    received : list of int
        Messages received per stream (index 0 is the primary stream).
    matched : int
        Primary messages that produced a :class:`Match`.
    exact : int
        Matches in which every secondary stamp equals the primary stamp.
    dropped_no_partner : list of int
        Per secondary stream (index 0 unused, always 0): primary messages dropped because that
        stream had no message within its tolerance. A primary message lacking partners in
        several streams is counted once, under the first such stream.
    forced : int
        Primary messages decided early because more than ``queue_size`` were waiting (their partner
        may not be the best one the stream would eventually have offered).
    secondary_overflow : list of int
        Secondary messages discarded because a buffer exceeded ``buffer_size``.
    max_abs_dt_ns : list of int
        Largest ``|stamp(secondary) - stamp(primary)|`` among the matches, per stream.
    """

    received: list = field(default_factory=list)
    matched: int = 0
    exact: int = 0
    dropped_no_partner: list = field(default_factory=list)
    forced: int = 0
    secondary_overflow: list = field(default_factory=list)
    max_abs_dt_ns: list = field(default_factory=list)

    @classmethod
    def for_streams(cls, n: int) -> "SyncStats":
        return cls([0] * n, 0, 0, [0] * n, 0, [0] * n, [0] * n)

    @property
    def dropped(self) -> int:
        """Total primary messages dropped for lack of a partner."""
        return sum(self.dropped_no_partner)


def _normalize_tolerances(max_dt, n_secondary: int) -> list:
    if isinstance(max_dt, (list, tuple)):
        if len(max_dt) != n_secondary:
            raise ValueError(f"max_dt has {len(max_dt)} entries but there are {n_secondary} secondary streams")
        return [seconds_to_ns(x) for x in max_dt]
    return [seconds_to_ns(max_dt)] * n_secondary


def _nearest(stamps: Sequence[int], t: int):
    """Index of the stamp nearest to ``t`` in the sorted list ``stamps``, or None if it is empty.

    Between an earlier and a later stamp at the same distance the earlier wins; among messages with
    the same stamp the last one (the most recently received) wins.
    """
    if not stamps:
        return None
    i = bisect.bisect_left(stamps, t)
    if i == len(stamps):
        best = stamps[-1]
    elif stamps[i] == t or i == 0:
        best = stamps[i]
    else:
        best = stamps[i - 1] if t - stamps[i - 1] <= stamps[i] - t else stamps[i]
    return bisect.bisect_right(stamps, best) - 1


def pair_by_stamp(primary: Iterable, *secondaries: Iterable, max_dt=0.05, stats: SyncStats | None = None) -> list:
    """Pair complete streams of ``(stamp_ns, item)`` by nearest stamp (offline reference).

    Parameters
    ----------
    primary : iterable of (int, object)
        The stream every match is built around (e.g. images), in any order.
    *secondaries : iterable of (int, object)
        The other streams (e.g. camera_info, poses), in any order.
    max_dt : float or None or sequence of (float or None)
        Largest allowed ``|stamp(secondary) - stamp(primary)|`` in seconds, one value for all
        secondary streams or one per stream; ``None`` means unlimited.
    stats : SyncStats, optional
        Filled in with counters if given.

    Returns
    -------
    list of Match
        One match per primary message that has a partner in every secondary stream, sorted by
        primary stamp (stable for equal stamps).

    Notes
    -----
    See the module docstring for the matching rule. Cost is ``O((n + m) log m)``.
    """
    tol = _normalize_tolerances(max_dt, len(secondaries))
    prim = sorted(((_check_stamp(s), x) for s, x in primary), key=lambda p: p[0])
    secs = []
    for stream in secondaries:
        pairs = sorted(((_check_stamp(s), x) for s, x in stream), key=lambda p: p[0])
        secs.append(([s for s, _ in pairs], [x for _, x in pairs]))
    st = SyncStats.for_streams(1 + len(secondaries))
    st.received = [len(prim)] + [len(s[0]) for s in secs]
    out = []
    for t, item in prim:
        items, stamps = [item], [t]
        for k, (stamps_k, items_k) in enumerate(secs, start=1):
            i = _nearest(stamps_k, t)
            if i is None or (tol[k - 1] is not None and abs(stamps_k[i] - t) > tol[k - 1]):
                st.dropped_no_partner[k] += 1
                break
            items.append(items_k[i])
            stamps.append(stamps_k[i])
        else:
            out.append(_record_match(st, t, items, stamps))
    if stats is not None:
        stats.__dict__.update(st.__dict__)
    return out


def _record_match(st: SyncStats, t: int, items: list, stamps: list) -> Match:
    st.matched += 1
    if all(s == t for s in stamps):
        st.exact += 1
    for k in range(1, len(stamps)):
        st.max_abs_dt_ns[k] = max(st.max_abs_dt_ns[k], abs(stamps[k] - t))
    return Match(t, tuple(items), tuple(stamps))


class StampSynchronizer:
    """Online nearest-stamp pairing of one primary stream with secondary streams.

    Feed messages as they arrive with :meth:`add`; it returns the matches that became final. Call
    :meth:`flush` when the input ends. In-order input gives the same matches as
    :func:`pair_by_stamp`.

    Parameters
    ----------
    n_streams : int
        Number of streams, >= 2. Stream 0 is the primary stream.
    max_dt : float or None or sequence of (float or None)
        Tolerance in seconds, for all secondary streams or one per secondary stream (``None``:
        unlimited, e.g. for a slow ``camera_info``).
    lateness : float
        How far (seconds) a stream's stamps may run backwards relative to the newest stamp seen on
        that stream (out-of-order delivery). A primary message is decided only once every secondary
        stream has moved far enough past it that no closer partner can still arrive. Messages
        later than this may be paired sub-optimally.
    queue_size : int
        Most primary messages kept waiting for their partners; beyond it the oldest is decided with
        what is there (counted in ``stats.forced``).
    buffer_size : int
        Most messages kept per secondary stream; beyond it the oldest is discarded (counted in
        ``stats.secondary_overflow``). Old secondary messages that can no longer be anyone's
        nearest partner are discarded anyway, so this only matters when the primary stream stalls.

    Notes
    -----
    A pending primary message stamped ``t`` whose best partner so far in stream ``k`` is at distance
    ``d`` is final for stream ``k`` once ``newest_k - lateness >= t + min(d, max_dt_k)``: every
    message still to come on stream ``k`` is then at least as far from ``t`` as the best one.
    """

    def __init__(self, n_streams: int, max_dt=0.05, lateness: float = 0.0, queue_size: int = 100,
                 buffer_size: int = 1000):
        if int(n_streams) < 2:
            raise ValueError(f"need at least 2 streams (a primary and a secondary), got {n_streams}")
        if int(queue_size) < 1 or int(buffer_size) < 1:
            raise ValueError(f"queue_size and buffer_size must be >= 1, got {queue_size}, {buffer_size}")
        self.n = int(n_streams)
        self._tol = _normalize_tolerances(max_dt, self.n - 1)
        lat = seconds_to_ns(lateness)
        if lat is None:
            raise ValueError("lateness must be finite")
        self._late = lat
        self.queue_size = int(queue_size)
        self.buffer_size = int(buffer_size)
        self._pending: deque = deque()  # (stamp, item) of primary messages, in arrival order
        self._stamps = [[] for _ in range(self.n)]  # sorted stamps of each secondary buffer
        self._items = [[] for _ in range(self.n)]
        self._newest = [None] * self.n
        self.stats = SyncStats.for_streams(self.n)

    def add(self, stream: int, stamp_ns: int, item: Any) -> list:
        """Add a message to ``stream``; return the list of :class:`Match` decided by it (may be empty)."""
        if not 0 <= int(stream) < self.n:
            raise IndexError(f"stream index {stream} out of range for {self.n} streams")
        t = _check_stamp(stamp_ns)
        self.stats.received[stream] += 1
        self._newest[stream] = t if self._newest[stream] is None else max(self._newest[stream], t)
        if stream == 0:
            self._pending.append((t, item))
        else:
            stamps, items = self._stamps[stream], self._items[stream]
            i = bisect.bisect_right(stamps, t)
            stamps.insert(i, t)
            items.insert(i, item)
            if len(stamps) > self.buffer_size:
                del stamps[0], items[0]
                self.stats.secondary_overflow[stream] += 1
        out = self._decide(final=False)
        self._prune()
        return out

    def flush(self) -> list:
        """Decide every waiting primary message with the messages received so far (end of input)."""
        out = self._decide(final=True)
        self._prune()
        return out

    @property
    def pending(self) -> int:
        """Number of primary messages waiting for partners."""
        return len(self._pending)

    def _ready(self, t: int) -> bool:
        for k in range(1, self.n):
            newest = self._newest[k]
            if newest is None:
                return False
            i = _nearest(self._stamps[k], t)
            d = None if i is None else abs(self._stamps[k][i] - t)
            if d == 0:
                continue
            tol = self._tol[k - 1]
            reach = d if tol is None else (tol if d is None else min(d, tol))
            if reach is None or newest - self._late < t + reach:
                return False
        return True

    def _decide(self, final: bool) -> list:
        out = []
        while self._pending:
            t, item = self._pending[0]
            forced = len(self._pending) > self.queue_size
            if not (final or forced or self._ready(t)):
                # Primary messages decide in arrival order so matches come out in that order.
                break
            self._pending.popleft()
            if forced and not final:
                self.stats.forced += 1
            match = self._match(t, item)
            if match is not None:
                out.append(match)
        return out

    def _match(self, t: int, item: Any):
        items, stamps = [item], [t]
        for k in range(1, self.n):
            i = _nearest(self._stamps[k], t)
            tol = self._tol[k - 1]
            if i is None or (tol is not None and abs(self._stamps[k][i] - t) > tol):
                self.stats.dropped_no_partner[k] += 1
                return None
            items.append(self._items[k][i])
            stamps.append(self._stamps[k][i])
        return _record_match(self.stats, t, items, stamps)

    def _prune(self) -> None:
        # Earliest stamp any present or future primary message can need a partner for.
        candidates = [t for t, _ in self._pending]
        if self._newest[0] is not None:
            candidates.append(self._newest[0] - self._late)
        if not candidates:
            return
        lo = min(candidates)
        for k in range(1, self.n):
            stamps, items = self._stamps[k], self._items[k]
            # Message j is useless if a later message j+1 is at or before lo (j+1 is always nearer).
            j = bisect.bisect_right(stamps, lo) - 1  # last message at or before lo
            if j > 0:
                del stamps[:j], items[:j]
            tol = self._tol[k - 1]
            if tol is not None and stamps and stamps[0] < lo - tol:
                # The only message at or before lo is too old for anyone anyway.
                cut = bisect.bisect_left(stamps, lo - tol)
                del stamps[:cut], items[:cut]
