"""What a noiselab recording holds once read: devices, their streams, each stream's segments.

A stream whose source restarted is split into stream segments (:func:`split_streams`), each
sorted by seq with every sample once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import McapIoError


def gaps(seq_array) -> list[tuple[int, int]]:
    """Sequence gaps: ``[(after_seq, missing_count), ...]`` in order of appearance.

    ``seq_array`` is a 1-D integer sequence in arrival or sorted order. Every step
    ``s[i+1] - s[i] > 1`` is reported as ``(s[i], s[i+1] - s[i] - 1)``. Repeats and backward
    steps (duplicates, reordering) are not gaps and are not reported; sort first if the
    order may be shuffled. A stream that starts after 0 is not reported either: check
    ``s[0]`` for messages lost before the first one received.
    """
    s = np.asarray(seq_array)
    if s.ndim != 1 or (s.size and s.dtype.kind not in "iu"):
        raise McapIoError(f"gaps() needs a 1-D integer array, got {s.dtype} {s.shape}")
    if s.size < 2:
        return []
    s = s.astype(np.int64, copy=False)
    d = np.diff(s)
    idx = np.flatnonzero(d > 1)
    return [(int(s[i]), int(d[i]) - 1) for i in idx]


@dataclass(frozen=True, eq=False)
class TopicData:
    """One stream of a recording: its stream segments in file order, each sorted by payload seq
    (stable), every sample once.

    ``seq`` int64 (N,) payload seq; ``t`` float64 (N,) payload sample time in s;
    ``publish_ns`` int64 (N,) MCAP publish_time (sample time, ns); ``log_ns`` int64 (N,) MCAP
    log_time (receive time in ns, any clock); ``values`` float64 (N, dim): x, u or y.

    ``starts`` int64: the index where each stream segment begins (``[0]`` for a stream that never
    restarted). A segment begins where the source restarted: its seq stepped back, in file order,
    below every seq of the segment or to one the segment holds with another sample (a restarted
    emulator counts from 0 again; its first samples may be lost), see :func:`split_streams`.
    ``duplicates``: messages dropped as repeats of a sample already read (same seq, same ``t`` and
    values, bit for bit); the first one read is kept.
    """

    topic: str
    kind: str
    seq: np.ndarray
    t: np.ndarray
    publish_ns: np.ndarray
    log_ns: np.ndarray
    values: np.ndarray
    starts: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    duplicates: int = 0

    def __len__(self) -> int:
        return int(self.seq.shape[0])

    @property
    def dim(self) -> int:
        return int(self.values.shape[1])

    @property
    def segments(self) -> list[tuple[int, int]]:
        """``[(start, stop), ...]``: the index range of each stream segment, in file order."""
        ends = [*self.starts.tolist()[1:], len(self)]
        return list(zip(self.starts.tolist(), ends))

    def segment(self, i: int) -> TopicData:
        """Segment ``i`` (0-based) as a TopicData of one segment."""
        a, b = self.segments[i]
        return TopicData(self.topic, self.kind, self.seq[a:b], self.t[a:b], self.publish_ns[a:b],
                         self.log_ns[a:b], self.values[a:b])

    def gaps(self) -> list[tuple[int, int]]:
        """:func:`gaps` of ``seq``, segment by segment (a restart is not a gap)."""
        return [g for a, b in self.segments for g in gaps(self.seq[a:b])]


def split_streams(path: str, topic: str, kind: str, seq: np.ndarray, t: np.ndarray, values: np.ndarray,
             pub: np.ndarray, log: np.ndarray) -> TopicData:
    """The TopicData of one topic's messages in file order: split where the source restarted,
    each segment sorted by seq, exact repeats dropped; a seq that comes twice with different data
    where no restart explains it raises McapIoError (the recording cannot say which sample is the
    real one).

    Messages are taken in file order, each continuing the current segment (one run of the source)
    unless it starts a new one. Only a step back (a seq below the one before it) can: it is

    * a repeat, dropped, when the segment holds that seq with the same sample, bit for bit (``t``
      and values: a re-sent or twice-routed message); except the segment's lowest seq sent again
      and followed by its successor, which is a source restarted that sends the same samples
      again (same seed): a new segment;
    * a late message, sorted into the segment, when the segment lacks that seq but holds a lower
      one (a reordered message fills its gap);
    * a restart, a new segment, when the segment holds that seq with another sample (the source
      counted again and the samples after its restart were lost before this one) or holds only
      higher seqs (it counted from below them): provided the file order tells the two runs apart,
      that is every message between the segment's copy of the seq and this one has a higher seq
      (the first run went on past it before the source counted again), and the message after
      this one does not go beyond every seq of the segment (which would be the first run going
      on, not a new one).

    A seq twice with different data that is not such a restart is ambiguous and refused: at once
    again with other data (no step back), reached again going forward, or two runs advancing side
    by side (two sources publishing on one key: the other run's lower seqs come between the two
    copies, or the first run goes on right after the second one's message). The rule reads only
    the messages, so a finished recording and the same one cut short (a killed recorder, whose
    metadata is never written) read alike.

    Vectorised: a stream without restarts, repeats or reordering (every seq step > 0) costs one
    np.diff; the others a stable sort, and a Python step per step back only (:func:`_restarts`).
    """
    n = seq.size
    d = np.diff(seq)
    if n < 2 or d.min() > 0:
        return TopicData(topic, kind, seq, t, pub, log, values)
    tb = np.ascontiguousarray(t, np.float64).view(np.uint64)
    vb = np.ascontiguousarray(values, np.float64).reshape(n, -1).view(np.uint64)

    def same(a, b):                              # rows a and b hold the same sample, bit for bit
        return (tb[a] == tb[b]) & (vb[a] == vb[b]).all(axis=-1)

    seg = np.zeros(n, np.int64)
    back = np.flatnonzero(d < 0) + 1
    if back.size:
        seg[_restarts(seq, back, same)] = 1
        np.cumsum(seg, out=seg)
    order = np.lexsort((seq, seg))                # stable: equal seqs keep their file order
    s2, g2 = seq[order], seg[order]
    twin = np.flatnonzero((s2[1:] == s2[:-1]) & (g2[1:] == g2[:-1]))
    if twin.size:
        a, b = order[twin], order[twin + 1]
        differ = ~same(a, b)
        if differ.any():
            bad = np.unique(seq[a[differ]])
            more = f" (and {bad.size - 1} more such seqs)" if bad.size > 1 else ""
            raise McapIoError(f"{path}: topic {topic!r}: seq {int(bad[0])} comes twice with different "
                              f"data{more}; the recording is ambiguous (two sources on one key?)")
        keep = np.ones(n, bool)
        keep[twin + 1] = False
        order, g2 = order[keep], g2[keep]
    starts = np.concatenate([[0], np.flatnonzero(np.diff(g2)) + 1]).astype(np.int64)
    return TopicData(topic, kind, seq[order], t[order], pub[order], log[order], values[order],
                     starts=starts, duplicates=int(twin.size))


def _restarts(seq: np.ndarray, back: np.ndarray, same) -> list[int]:
    """The file positions where a new stream segment begins, by :func:`split_streams`' rule; ``back``:
    the positions of the steps back (``seq[i] < seq[i - 1]``), ascending; ``same(a, b)``: whether
    positions a and b hold the same sample.

    Between two steps back the seqs do not decrease, so the lowest seq of a stretch of the segment
    is its first one's or a step back's: the seqs between a copy at ``j`` and a step back at ``i``
    are all higher than ``v`` iff ``seq[j + 1]`` and every step back kept in the segment after
    ``j + 1`` are. The steps back kept are held as suffix minima (values rising with position), so
    that question costs a bisection. A copy of ``v`` in the segment is found in a stable argsort of
    the seqs (the positions of one seq ascending)."""
    from bisect import bisect_right

    n = int(seq.size)
    by_seq = np.argsort(seq, kind="stable")
    sorted_seq = seq[by_seq]
    starts: list[int] = []
    begin = 0                                   # the current segment's first position
    low = high = int(seq[0])                    # its lowest and highest seq so far
    kept_pos: list[int] = []                    # its steps back kept, as suffix minima
    kept_val: list[int] = []
    for i in back.tolist():
        v = int(seq[i])
        high = max(high, int(seq[i - 1]))
        a, b = np.searchsorted(sorted_seq, v, "left"), np.searchsorted(sorted_seq, v, "right")
        k = int(np.searchsorted(by_seq[a:b], i)) - 1      # the last copy of v before i
        j = int(by_seq[a + k]) if k >= 0 and by_seq[a + k] >= begin else None
        nxt = int(seq[i + 1]) if i + 1 < n else None
        if j is None:                           # below every seq of the segment, or a late message
            restart = v < low
        elif same(i, j):                        # a repeat, or the same samples from the start again
            restart = v == low and nxt == v + 1
        else:                                   # another sample: a restart if the runs are apart
            after = bisect_right(kept_pos, j + 1)
            between = min(int(seq[j + 1]), kept_val[after] if after < len(kept_val) else v + 1)
            restart = between > v
        if restart and nxt is not None and nxt > high:
            restart = False                     # the first run goes on after it: side by side
        if restart:
            starts.append(i)
            begin, low, high = i, v, v
            kept_pos.clear()
            kept_val.clear()
        else:
            low = min(low, v)
            while kept_val and kept_val[-1] >= v:
                kept_val.pop()
                kept_pos.pop()
            kept_pos.append(i)
            kept_val.append(v)
    return starts


@dataclass(frozen=True)
class DeviceData:
    """The streams of one device (found by its ``<prefix>/measurement`` topic), per kind."""

    name: str
    prefix: str
    streams: dict[str, TopicData]

    @property
    def measurement(self) -> TopicData:
        return self.streams["measurement"]

    @property
    def command(self) -> TopicData | None:
        return self.streams.get("command")

    @property
    def truth(self) -> TopicData | None:
        return self.streams.get("truth")


@dataclass(frozen=True)
class Recording:
    """What :func:`read_recording` found.

    ``devices`` by device name (``noiselab/<name>/...`` gives ``name``; a foreign prefix such as
    ``/robot/imu/measurement`` gives ``robot/imu``). ``metadata``: metadata records by name.
    ``complete``: the file had a valid footer and summary. ``note``: empty if complete, else
    why not and how far the salvage got. ``messages``: messages read, of every topic.
    """

    path: str
    devices: dict[str, DeviceData]
    metadata: dict[str, dict[str, str]]
    complete: bool
    note: str
    messages: int = 0

    def device(self, name: str | None = None) -> DeviceData:
        """The device ``name``; without a name, the only device (error if there are several)."""
        if name is None:
            if len(self.devices) == 1:
                return next(iter(self.devices.values()))
            raise McapIoError(f"{self.path}: holds {len(self.devices)} devices "
                              f"({', '.join(sorted(self.devices)) or 'none'}); name one")
        try:
            return self.devices[name]
        except KeyError:
            raise McapIoError(f"{self.path}: no device {name!r}; found "
                              f"{', '.join(sorted(self.devices)) or 'none'}") from None

