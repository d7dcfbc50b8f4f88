"""Which messages of a topic continue its stream: the rule the recorder and the live analyzer
share to take a message from the network only when its seq and vector length fit the stream
(DESIGN.md "Wire contract": seq from 0, consecutive, per topic; one vector length per stream).

The wire decoders (:mod:`.wire`) check what one payload's bytes can tell; this gate checks what
only the stream can: where a seq stands against the last one taken, and the stream's length.
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = ["HOLD", "Dropped", "SeqGate"]


HOLD = 4
"""Messages a :class:`SeqGate` holds for confirmation per topic, and how many later messages of
the topic each one waits for its successor: a real jump survives a few hostile messages between
it and its successor, and a flood of forged seqs costs bounded memory."""


class Dropped(NamedTuple):
    """A message a :class:`SeqGate` did not take: ``reason`` is ``"length"`` or ``"seq"``,
    ``text`` says why in one line (without the topic)."""

    seq: int
    item: object
    reason: str
    text: str


class SeqGate:
    """Which messages of a topic continue its stream, judged by their seq and vector length (one
    gate per topic; the recorder and the live analyzer share it).

    A stream's seq counts from 0 by one and its vectors have one length. A message is taken at
    once when it continues the stream: its seq is past the last one taken by at most ``ahead``
    (1: the very next; a node that keeps samples by seq may take a short jump) and it has the
    stream's length. Any other message is held until a later one confirms it, which must be its
    successor (seq + 1, the same length):

    * the stream's first message: a stream's start and its length are trusted only once
      confirmed (unless the length is given, ``dim``: a model's);
    * a seq more than ``ahead`` past the last one (messages lost on the way: the gap is real);
    * a seq before the last one (a source that restarted: it sends 0, then 1, ...); a repeat of
      the last seq is dropped at once (its successor would continue the stream anyway).

    A held message and its confirming successor are both taken; a confirmed step back is a
    restart (:attr:`restarted`). A held message is dropped when none of the next ``hold``
    messages of the topic is its successor, when another message with its seq is held too (which
    one the successor confirms cannot be told), or when the stream's length turns out to be
    another. At most ``hold`` messages are held, whatever a peer sends. Once the stream's length
    is known, a message of another length is dropped at once.

    So a single message with a forged seq or length is not taken: it would need a successor.
    What no rule on seqs can tell, without authenticating the source (Zenoh's access control,
    TLS with client certificates), is a forged message whose seq fits the genuine stream where
    it arrives: the very next seq, ahead of the genuine message, or the seq just before a
    genuine start, jump or restart that waits for its successor; nor a forged pair of
    consecutive messages from a restart.

    :meth:`offer` (one message) and :meth:`take_run` (a run of consecutive ones) say what to
    take; the caller keeps the items (payloads, decoded samples), the gate only seqs and
    lengths."""

    def __init__(self, ahead: int = 1, dim: int | None = None, *, field: str = "vector", hold: int = HOLD):
        self.ahead, self.dim, self.field, self.hold = ahead, dim, field, hold
        self.last: int | None = None          # the last seq taken
        self.restarted = False                # the last offer/take_run began a new stream (a step back)
        self.held: list[list] = []            # [seq, dim, item, why, messages waited]

    def _drop_length(self, seq: int, dim: int, item) -> Dropped:
        return Dropped(seq, item, "length", f"{self.field} has {dim} elements at seq {seq}; the stream's have {self.dim}")

    def _trust(self, dim: int) -> list[Dropped]:
        """The stream's length is ``dim`` from now on: held messages of another length go."""
        self.dim = dim
        gone = [h for h in self.held if h[1] != dim]
        self.held = [h for h in self.held if h[1] == dim]
        return [self._drop_length(h[0], h[1], h[2]) for h in gone]

    def offer(self, seq: int, dim: int, item) -> tuple[list, list[Dropped]]:
        """The next message of the topic (``dim``: its vector's length): ``(items to take now, in
        order; messages dropped)``."""
        self.restarted = False
        take, dropped = [], []
        last = self.last
        if self.dim is not None and dim != self.dim:
            dropped.append(self._drop_length(seq, dim, item))
        elif last is not None and last < seq <= last + self.ahead:
            self.last = seq
            take.append(item)
        else:
            match = [h for h in self.held if h[0] == seq - 1 and h[1] == dim]
            if len(match) == 1:
                h = match[0]
                self.held.remove(h)
                self.restarted = last is not None and h[0] <= last
                self.last = seq
                take += [h[2], item]
                if self.dim is None:
                    dropped += self._trust(dim)
            else:
                for h in match:
                    self.held.remove(h)
                    dropped.append(Dropped(h[0], h[2], "seq", f"seq {h[0]} came twice before its successor: "
                                           "which one the stream sent cannot be told"))
                if last is not None and seq == last:
                    dropped.append(Dropped(seq, item, "seq", f"seq {seq} repeats the stream's last seq"))
                else:
                    why = (f"seq {seq} would start the stream" if last is None else
                           f"seq {seq} {'jumps from' if seq > last else 'goes back from'} the stream's last seq {last}")
                    self.held.append([seq, dim, item, why, -1])
        for h in self.held:                   # each held message waits for at most `hold` more
            h[4] += 1
        old = [h for h in self.held if h[4] >= self.hold]
        if old:
            self.held = [h for h in self.held if h[4] < self.hold]
            dropped += [Dropped(h[0], h[2], "seq", f"{h[3]} and no message followed it") for h in old]
        return take, dropped

    def take_run(self, seq0: int, n: int, dim: int) -> bool:
        """A run of ``n`` messages with consecutive seqs from ``seq0`` and length ``dim``: True (the
        gate has taken it, the caller writes it) when :meth:`offer` would take every one of them
        with nothing held before; False (nothing changed) otherwise: offer them one by one."""
        last = self.last
        if self.held or n < 1 or (self.dim is not None and dim != self.dim):
            return False
        if last is not None and last < seq0 <= last + self.ahead:
            self.restarted = False
        elif n >= 2 and seq0 != last:         # the first is held and its successor, the second, confirms it
            self.restarted = last is not None and seq0 <= last
        else:
            return False
        self.last = seq0 + n - 1
        self.dim = dim
        return True

    def vouch(self, count: int) -> tuple[list, list[Dropped]]:
        """The source says it published ``count`` messages (seq 0..count-1): take the one held
        message that can be the stream's last (the start of a stream not yet confirmed, or a jump
        ahead, below ``count``); nothing when there is none, or more than one. Returns ``(items
        to take, messages dropped)`` as :meth:`offer` does."""
        last = self.last
        can = [h for h in self.held if h[0] < count and (last is None or h[0] > last)]
        if len(can) != 1:
            return [], []
        h = can[0]
        self.held.remove(h)
        self.last = h[0]
        self.restarted = False
        return [h[2]], (self._trust(h[1]) if self.dim is None else [])

    def flush(self) -> list[Dropped]:
        """The stream is over: the messages still held had no successor, so they are dropped."""
        held, self.held = self.held, []
        return [Dropped(h[0], h[2], "seq", f"{h[3]} and no message followed it") for h in held]
