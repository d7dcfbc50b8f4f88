"""What the recorder tells of a recording: each topic's sequence bookkeeping (first and last seq,
count, gaps, restarts, what its source said it published) and the summary printed on stop and
stored in the file's ``noiselab.recorder`` metadata record (:mod:`.recorder`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..recordings.errors import shown


@dataclass
class TopicBook:
    """Sequence bookkeeping of one topic."""

    first_seq: int | None = None
    last_seq: int | None = None
    count: int = 0
    gaps: list = field(default_factory=list)        # (after_seq, missing)
    restarts: list = field(default_factory=list)    # (from_seq, to_seq)
    expected: int | None = None                      # messages the source says it published
    missing_at_end: int = 0
    end_gap: tuple | None = field(default=None, repr=False)   # the gap end() booked at the tail

    def see(self, seq: int) -> None:
        if self.first_seq is None:
            self.first_seq = seq
        elif seq > self.last_seq + 1:
            self.gaps.append((self.last_seq, seq - self.last_seq - 1))
        elif seq <= self.last_seq:
            self.restarts.append((self.last_seq, seq))
            self.expected, self.missing_at_end = None, 0      # a new stream: its end is to come
        self.last_seq = seq
        self.count += 1

    def see_run(self, seq0: int, n: int) -> None:
        """``n`` consecutive seqs from ``seq0`` (same as ``see`` on each)."""
        self.see(seq0)
        if n > 1:
            self.last_seq = seq0 + n - 1
            self.count += n - 1

    def end(self, expected: int) -> int:
        """The source published ``expected`` messages (seq 0..expected-1): book the tail that
        did not arrive as a gap after the last seq; returns it. A topic of which nothing arrived
        has all of them missing at start (a recorder started late cannot tell a loss from that)."""
        self.expected = expected
        self.missing_at_end = 0 if self.last_seq is None else max(0, expected - 1 - self.last_seq)
        self.end_gap = None
        if self.missing_at_end:
            self.end_gap = (self.last_seq, self.missing_at_end)
            self.gaps.append(self.end_gap)
        return self.missing_at_end

    def unend(self) -> None:
        """Undo :meth:`end`: the stream went on after its end of stream."""
        if self.end_gap is not None:
            self.gaps.remove(self.end_gap)
        self.expected, self.missing_at_end, self.end_gap = None, 0, None

    @property
    def missing(self) -> int:
        """Seqs skipped inside the stream and, once the source has ended, after its last seq."""
        return sum(m for _, m in self.gaps)

    @property
    def missing_at_start(self) -> int:
        return self.first_seq if self.first_seq is not None else (self.expected or 0)

    @property
    def lacks(self) -> int:
        """Every seq from 0 to the last one the source announced (or to the last seen) not recorded."""
        return self.missing_at_start + self.missing

    def as_dict(self) -> dict:
        return {"first_seq": self.first_seq, "last_seq": self.last_seq, "count": self.count,
                "missing_at_start": self.missing_at_start, "gaps": [list(g) for g in self.gaps],
                "missing": self.missing, "restarts": [list(r) for r in self.restarts],
                "expected": self.expected, "missing_at_end": self.missing_at_end}


@dataclass
class RecorderSummary:
    out: str
    topics: dict
    messages: int
    malformed: int
    wall_s: float
    ended: dict = field(default_factory=dict)
    malformed_topics: dict = field(default_factory=dict)   # key -> messages skipped
    unended: dict = field(default_factory=dict)            # prefix -> {kind: last seq}: no end of stream came
    starts: dict = field(default_factory=dict)             # prefix -> {"start_time_ns": int, "stated": bool}
    bad_anchors: int = 0                                   # attachments that broke the contract (ignored)

    def as_dict(self) -> dict:
        return {"node": "record", "out": self.out, "messages": self.messages, "malformed": self.malformed,
                "malformed_topics": self.malformed_topics, "wall_s": self.wall_s,
                "topics": {k: v.as_dict() for k, v in self.topics.items()}, "ended": self.ended,
                "unended": self.unended, "starts": self.starts, "bad_anchors": self.bad_anchors}

    def lines(self) -> list[str]:
        out = [f"recorded {self.messages} messages to {self.out} in {self.wall_s:.1f} s"]
        for topic, b in sorted(self.topics.items()):
            d = b.as_dict()
            text = f"  {topic}: " + (f"{b.count} messages, seq {b.first_seq}..{b.last_seq}" if b.count else
                                     f"no messages (the source published {b.expected})")
            if d["missing_at_start"] and b.count:
                text += f", started at seq {b.first_seq} (seqs 0..{b.first_seq - 1} not recorded)"
            text += f", {b.missing} missing in {len(b.gaps)} gaps" if b.gaps else ", no gaps"
            if b.missing_at_end:
                text += f" ({b.missing_at_end} at the end: the source published {b.expected})"
            if b.restarts:
                text += f", {len(b.restarts)} restarts (seq went back)"
            out.append(text)
        if self.malformed:
            out.append(f"  {self.malformed} malformed payloads skipped ("
                       + ", ".join(f"{n} on {k}" for k, n in sorted(self.malformed_topics.items())) + ")")
        for prefix in sorted(self.unended):
            out.append(f"  {prefix}: {unended_text(self.unended[prefix])}")
        return [shown(line) for line in out]


def unended_text(last: dict) -> str:
    return ("no end of stream (the source vanished, or was still streaming at the stop); last seq "
            + ", ".join(f"{kind} {seq}" for kind, seq in sorted(last.items())))
