"""The seq gate (service/nodes/seqgate.py): which messages from the network continue their
stream. A start, a jump and a step back are taken only once their successor confirms them; one
forged message never is."""

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from noiselab.nodes.seqgate import HOLD, SeqGate


def offers(gate, messages):
    """Offer ``(seq, dim)`` messages (item: their index) one by one: (taken, dropped items)."""
    taken, dropped = [], []
    for i, (seq, dim) in enumerate(messages):
        t, d = gate.offer(seq, dim, i)
        taken += t
        dropped += [x.item for x in d]
    return taken, dropped


def state(gate):
    return gate.last, gate.dim, [list(h) for h in gate.held]


def test_seq_gate_takes_a_start_a_jump_or_a_restart_once_its_successor_confirms_it():
    """A stream's first message, a jump ahead and a step back are held until their successor
    (seq + 1, same length) comes; then both are taken (a step back is a restart); a message that
    continues the stream is taken at once."""
    gate = SeqGate(1)
    assert gate.offer(0, 1, "a") == ([], []) and gate.last is None
    assert gate.offer(1, 1, "b") == (["a", "b"], []) and (gate.last, gate.dim, gate.restarted) == (1, 1, False)
    assert gate.offer(2, 1, "c") == (["c"], [])
    assert gate.offer(9, 1, "d") == ([], []) and gate.offer(10, 1, "e") == (["d", "e"], [])      # a real gap
    assert gate.offer(0, 1, "f") == ([], []) and gate.offer(1, 1, "g") == (["f", "g"], []) and gate.restarted
    assert gate.offer(2, 1, "h") == (["h"], []) and not gate.restarted
    wide = SeqGate(100, dim=2)                     # a ring of 100 by seq, the model's length
    assert wide.offer(5, 2, "a") == ([], []) and wide.offer(6, 2, "b") == (["a", "b"], [])
    assert wide.offer(60, 2, "c") == (["c"], [])      # within the ring: taken at once


@pytest.mark.parametrize("forged, why", [
    ((0, 2), "y has 2 elements at seq 0; the stream's have 1"),
    ((50, 1), "seq 50 goes back from the stream's last seq 150 and no message followed it"),
    ((0, 1), "seq 0 goes back from the stream's last seq 150 and no message followed it"),
    ((149, 1), "seq 149 goes back from the stream's last seq 150 and no message followed it"),
    ((150, 1), "seq 150 repeats the stream's last seq"),
    ((10**12, 1), "seq 1000000000000 jumps from the stream's last seq 150 and no message followed it"),
])
def test_seq_gate_drops_one_forged_message(forged, why):
    """One forged message after seq 150 (a wrong length, a past seq, seq 0, a seq already taken,
    the last one again, a seq far ahead) is dropped with its reason; every genuine one is taken."""
    gate = SeqGate(1, field="y")
    msgs = [(k, 1) for k in range(151)] + [forged] + [(k, 1) for k in range(151, 200)]
    taken, dropped = offers(gate, msgs)
    assert taken == [i for i in range(len(msgs)) if i != 151] and dropped == [151]
    gate2 = SeqGate(1, field="y")
    texts = []
    for seq, dim in msgs:
        texts += [d.text for d in gate2.offer(seq, dim, None)[1]]
    assert texts == [why]


def test_seq_gate_before_the_stream_starts_and_its_bounds():
    """Before the start: a forged message of another length and a far seq are held and dropped
    once the stream's own start is confirmed or they wait too long; two held messages with the
    seq its successor confirms cannot be told apart: neither is taken. At most HOLD messages are
    held whatever comes; a real jump survives HOLD - 1 hostile messages before its successor."""
    gate = SeqGate(1)
    taken, dropped = offers(gate, [(0, 2), (7, 1), (0, 1), (1, 1), (2, 1)])
    assert taken == [2, 3, 4] and dropped == [0]                 # the forged length: at the start's confirmation
    assert offers(gate, [(3, 1)] * 1)[0] == [0] and gate.held == []   # the seq 7 waited HOLD messages
    twin = SeqGate(1)
    assert offers(twin, [(0, 1), (0, 1), (1, 1), (2, 1)]) == ([2, 3], [0, 1])
    flood = SeqGate(1)
    offers(flood, [(k, 1) for k in range(10)])
    for k in range(1000):
        flood.offer(10**6 + 7 * k, 1, None)
        assert len(flood.held) <= HOLD
    jump = SeqGate(1)
    msgs = [(k, 1) for k in range(10)] + [(50, 1)] + [(10**9 + 7 * k, 1) for k in range(HOLD - 1)] + [(51, 1)]
    taken, _ = offers(jump, msgs)
    assert taken == list(range(11)) + [len(msgs) - 1] and jump.last == 51


def test_seq_gate_vouch():
    """An end of stream counting ``n`` vouches for the one held message that can be the stream's
    last (a jump ahead below n, or a start not yet confirmed); none when there are two, nor for
    a step back."""
    gate = SeqGate(1)
    offers(gate, [(0, 1), (1, 1), (5, 1)])
    assert gate.vouch(5) == ([], []) and gate.vouch(6) == ([2], []) and gate.last == 5
    lone = SeqGate(1)
    offers(lone, [(8, 1)])
    assert lone.vouch(21) == ([0], []) and (lone.last, lone.dim) == (8, 1)
    back = SeqGate(1)
    offers(back, [(0, 1), (1, 1), (2, 1), (0, 1)])
    assert back.vouch(10) == ([], [])
    two = SeqGate(1)
    offers(two, [(0, 1), (1, 1), (5, 1), (7, 1)])
    assert two.vouch(10) == ([], [])


history = st.lists(st.tuples(st.integers(0, 40), st.integers(1, 2)), max_size=12)


@settings(max_examples=400)
@given(before=history, seq0=st.integers(0, 40), n=st.integers(1, 6), dim=st.integers(1, 2),
       ahead=st.sampled_from([1, 5]))
def test_seq_gate_take_run_equals_offers_one_by_one(before, seq0, n, dim, ahead):
    """take_run takes a run of consecutive seqs whole exactly when offer, one message at a time,
    would take every one of them, leaving the gate in the same state; otherwise it changes
    nothing."""
    a, b = SeqGate(ahead), SeqGate(ahead)
    offers(a, before)
    offers(b, before)
    was = state(a)
    if a.take_run(seq0, n, dim):
        taken, dropped = offers(b, [(seq0 + i, dim) for i in range(n)])
        assert (taken, dropped) == (list(range(n)), []) and state(a) == state(b)
    else:
        assert state(a) == was


@settings(max_examples=400)
@given(runs=st.lists(st.tuples(st.integers(0, 60), st.integers(2, 8)), min_size=1, max_size=6),
       where=st.integers(0, 100), fseq=st.integers(0, 70), fdim=st.integers(1, 2))
def test_seq_gate_never_takes_one_forged_message(runs, where, fseq, fdim):
    """A genuine stream of runs of consecutive seqs (each at least two long: a start, gaps,
    restarts) with one forged message put anywhere: the forged one is never taken, unless its
    seq fits the genuine stream where it arrives (the next seq, or the one before a run start
    waiting for its successor: the limitation SeqGate's docstring names); the genuine ones are
    all taken unless the forged seq is a run start's (which of the two is genuine cannot be
    told)."""
    for (a, n), (b, _) in zip(runs, runs[1:]):
        assume(b < a + n - 1 or b > a + n)          # a run after another steps back or jumps ahead
    genuine = [s for s0, n in runs for s in range(s0, s0 + n)]
    starts = {s0 for s0, _ in runs}
    p = where % (len(genuine) + 1)
    nxt = genuine[p] if p < len(genuine) else None
    before = SeqGate(1)
    offers(before, [(s, 1) for s in genuine[:p]])      # the last seq taken where the forged one comes
    if fdim == 1 and (fseq == nxt or (before.last is not None and fseq == before.last + 1) or fseq + 1 in starts):
        return                                         # a forged seq that fits: no rule on seqs can tell
    msgs = [(s, 1) for s in genuine[:p]] + [(fseq, fdim)] + [(s, 1) for s in genuine[p:]]
    taken, _ = offers(SeqGate(1), msgs)
    assert p not in taken
    if fdim == 2 or fseq not in starts:
        assert taken == [i for i in range(len(msgs)) if i != p]
