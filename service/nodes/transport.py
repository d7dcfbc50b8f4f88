"""Zenoh sessions for every node, configured in one place (STYLE 11: shared transport flags).

Defaults are safe (DESIGN.md): endpoints on 127.0.0.1 only, multicast scouting off. A data
*source* (emulator, replay) listens on :data:`DEFAULT_ENDPOINT`; a *sink* (recorder, analyzer,
controller) connects to it; a router listens. Reaching other hosts takes an explicit
``--connect``/``--listen`` or a Zenoh config file (``--config``; command-line endpoints still
override its endpoints). An endpoint that cannot be bound, or an explicit ``--connect`` that
cannot be reached at start, is a one-line :class:`TransportError` (exit 2): explicit connects
give up after ``--connect-timeout`` seconds instead of retrying forever (Zenoh's default for
peers). A sink on the *default* endpoint waits for its source instead (start the recorder first,
then the emulator). A config file keeps the safe defaults for what it does not set itself. Once
connected, Zenoh reconnects by itself if the other side restarts.
"""

from __future__ import annotations

import argparse
import json
import re
import threading
import time
from pathlib import Path

import zenoh

from .. import wire
from ..args import DEFAULT_ENDPOINT, DEFAULT_PORT, add_transport_args  # noqa: F401  (the flags: stdlib only)
from ..recordings.errors import shown

ROLES = ("source", "sink", "router")


class TransportError(ValueError):
    """A Zenoh endpoint, key expression or config that does not work (one-line message)."""


def _one_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    m = re.search(r'msg: "([^"]*)', text)               # Json5Err(Message { msg: "..." })
    if m:
        text = m.group(1)
    text = re.sub(r"\s+at /\S+$", "", text)          # drop the Rust source location
    text = re.sub(r"\s+at /root/\S+.*$", "", text)
    return text.rstrip(". !")


def _insert(conf: "zenoh.Config", key: str, value) -> None:
    try:
        conf.insert_json5(key, json.dumps(value))
    except zenoh.ZError as exc:
        raise TransportError(f"zenoh config {key} = {value!r}: {_one_line(exc)}") from None


def _set_by(conf: "zenoh.Config", key: str) -> bool:
    """Whether ``conf`` (read from a config file) sets ``key``: its value differs from a default
    zenoh.Config's. Zenoh leaves an option the file does not name null (multicast scouting's
    ``enabled``, ``connect/retry``) and gives its own defaults for the endpoints; a file that spells
    out exactly zenoh's defaults (listen on ``tcp/[::]:0``, connect to nothing) is taken as silent."""
    return conf.get_json(key) != zenoh.Config().get_json(key)


def build_config(args: argparse.Namespace, role: str) -> "zenoh.Config":
    """The session configuration of a node of ``role`` from the shared transport flags.

    The safe defaults (multicast scouting off; a source or router listens on
    :data:`DEFAULT_ENDPOINT`, a sink connects to it) hold for every setting that neither the command
    line nor the ``--config`` file sets: a file that only tunes something else does not turn
    scouting or listening on every interface back on."""
    if role not in ROLES:
        raise ValueError(role)
    from_file = bool(getattr(args, "config", None))
    if from_file:
        path = Path(args.config)
        if not path.is_file():
            raise TransportError(f"--config {args.config}: no such file")
        try:
            conf = zenoh.Config.from_file(str(path))
        except zenoh.ZError as exc:
            raise TransportError(f"--config {args.config}: {_one_line(exc)}") from None
    else:
        conf = zenoh.Config()

    def in_file(key: str) -> bool:
        return from_file and _set_by(conf, key)

    mode = "router" if role == "router" else (getattr(args, "mode", None) or "peer")
    _insert(conf, "mode", mode)
    if not in_file("scouting/multicast/enabled"):
        _insert(conf, "scouting/multicast/enabled", False)
    connect = list(getattr(args, "connect", None) or [])
    listen = list(getattr(args, "listen", None) or [])
    explicit_connect = bool(connect)
    file_listen, file_connect = in_file("listen/endpoints"), in_file("connect/endpoints")
    if not (connect or listen or file_listen or file_connect):
        if role == "sink":
            connect = [DEFAULT_ENDPOINT]      # default: wait for the source to appear
            if not in_file("connect/retry"):
                _insert(conf, "connect/retry", {"period_init_ms": 100, "period_max_ms": 1000,
                                                "period_increase_factor": 2})
        else:
            listen = [DEFAULT_ENDPOINT]
    if listen or not file_listen:
        _insert(conf, "listen/endpoints", listen)
    if connect or not file_connect:
        _insert(conf, "connect/endpoints", connect)
    if explicit_connect:
        timeout_ms = int(max(0.0, float(getattr(args, "connect_timeout", 5.0))) * 1000)
        _insert(conf, "connect/timeout_ms", timeout_ms)
        _insert(conf, "connect/exit_on_failure", True)
    if listen:
        _insert(conf, "listen/exit_on_failure", True)
    return conf


def open_session(args: argparse.Namespace, role: str) -> "zenoh.Session":
    """Open the node's Zenoh session (use it as a context manager: an unclosed session hangs the
    process at exit). A bind or connect failure becomes a one-line TransportError."""
    conf = build_config(args, role)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        raise TransportError(_one_line(exc)) from None


def wait_matching(publishers, timeout: float, stop=None, *, every: bool = True) -> bool:
    """Wait up to ``timeout`` seconds until every publisher (``every=False``: any of them) has a
    matching subscriber, or ``stop`` is set; True when matched. (``Publisher.matching_status`` is
    an object whose truth value is always True: use .matching.)"""
    import time

    publishers = list(publishers)
    test = all if every else any
    t_end = time.monotonic() + timeout
    while not test(p.matching_status.matching for p in publishers):
        if time.monotonic() >= t_end or (stop is not None and stop.is_set()):
            return False
        time.sleep(0.002)
    return True


def wait_peers(session, n: int, timeout: float, stop=None) -> bool:
    """Wait up to ``timeout`` seconds until ``n`` peers are connected to ``session``."""
    import time

    t_end = time.monotonic() + timeout
    while len(list(session.info.peers_zid())) < n:
        if time.monotonic() >= t_end or (stop is not None and stop.is_set()):
            return False
        time.sleep(0.002)
    return True


DATA_QOS = dict(congestion_control=zenoh.CongestionControl.BLOCK)
"""Publisher options of recorded data streams: BLOCK (a slow subscriber slows the source instead of
losing data). No ``express``: it makes zenoh send every message in its own write, which tripled
the cost of a put with a subscriber attached and bought no latency (tests/bench/RESULTS.md)."""


def declare_stream(session, key_expr: str, kind: str, **options) -> zenoh.Publisher:
    """A publisher of ``kind`` payloads on ``key_expr`` whose puts say the wire's Zenoh encoding,
    ``application/json;<schema name>`` (:func:`wire.zenoh_encoding`), so generic Zenoh tools
    decode them. ``options``: the publisher's QoS (e.g. :data:`DATA_QOS`)."""
    return session.declare_publisher(key_expr, encoding=wire.zenoh_encoding(kind), **options)


def end_stream(session, publisher, payload: bytes, timeout: float) -> dict:
    """End a stream without losing its tail: publish ``payload`` (a :func:`wire.encode_end`
    message) on ``publisher`` (``noiselab/<name>/end``), then query that key and wait, at most
    ``timeout`` seconds, until every recorder whose key expression covers it has answered.

    Why: a publisher that closed its session right after its last put lost what was still
    queued or in flight (0..49,276 of 300,000 messages, tests/bench/RESULTS.md). A query travels on the same
    links, at the same priority and behind the data, so a recorder sees it only once it has
    received every message before it, and answers once it has written them: after the answers
    the session can be closed. Subscribers that are not recorders do not answer (nothing to wait
    for). Any peer may answer: an answer is taken only in the shape of a recorder's
    (:func:`recorder_ack`); any other is an error. Returns ``{"acks": [the recorders' answers],
    "errors": [one line each], "timed_out": bool, "wait_s": s}``."""
    t0 = time.monotonic()
    publisher.put(payload)
    got = ask_recorders(session, publisher.key_expr, payload, timeout)
    return {**got, "wait_s": time.monotonic() - t0}


def ask_recorders(session, key_expr, payload: bytes | None, timeout: float) -> dict:
    """Query ``key_expr`` (a ``noiselab/<name>/end`` key) and wait, at most ``timeout`` seconds,
    until every recorder whose key expression covers it has answered with what it holds
    (:func:`end_stream` after its end of stream). Without an end before it, the query only
    flushes: a recorder answers once it has written everything that reached it before the
    query on the same link, so a node that publishes a few messages and then closes its session
    (a controller) loses none of them at the close. Returns ``{"acks", "errors", "timed_out",
    "wait_s"}`` as :func:`end_stream` does."""
    t0 = time.monotonic()
    acks, errors = [], []
    if timeout > 0:
        replies = session.get(key_expr, payload=payload, target=zenoh.QueryTarget.ALL,
                              consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout,
                              priority=zenoh.Priority.DATA, **DATA_QOS)
        for reply in replies:                 # ends when every queryable has answered, or at timeout
            ok = reply.ok
            if ok is None:
                errors.append(_cut(reply.err.payload.to_string()))
                continue
            try:
                ack = wire.loads(ok.payload.to_bytes(), "end-of-stream acknowledgement")
            except ValueError:
                errors.append("an acknowledgement that is not JSON")
                continue
            if recorder_ack(ack):
                acks.append(ack)
            else:
                errors.append("an acknowledgement that is not a recorder's answer")
    return {"acks": acks, "errors": errors, "timed_out": "Timeout" in errors,
            "wait_s": time.monotonic() - t0}


def recorder_ack(ack) -> bool:
    """``ack`` has the shape of a recorder's answer to an end-of-stream query (what
    ``recorder.Ingest.ack`` sends): an object with ``out`` (str), ``complete`` (bool) and
    ``topics`` ({kind: {"missing": int >= 0, ...}}), the fields the source reads."""
    if not isinstance(ack, dict) or not isinstance(ack.get("out"), str) or type(ack.get("complete")) is not bool:
        return False
    topics = ack.get("topics")
    return isinstance(topics, dict) and all(
        isinstance(t, dict) and type(t.get("missing")) is int and t["missing"] >= 0 for t in topics.values())


def _cut(text: str, n: int = 200) -> str:
    """A peer's error text as one line of at most ``n`` characters."""
    text = shown(text)
    return text if len(text) <= n else text[:n] + "..."


JOIN = "@join"
"""Last chunk of a source's join queryable, ``noiselab/<name>/@join`` (a verbatim chunk: no
wildcard matches it, so recorders' ``noiselab/**`` queryables and subscribers never see it)."""
JOIN_TIMEOUT_S = 2.0


def serve_join(session, name: str, first_seqs) -> "zenoh.Queryable":
    """Declare source ``name``'s join queryable. ``first_seqs()`` returns {topic key: the first
    seq not yet started}; every query gets it as a JSON reply. See :func:`join_points`."""
    key = f"{wire.PREFIX}/{wire.check_name(name)}/{JOIN}"

    def on_query(query) -> None:
        try:
            query.reply(key, json.dumps(first_seqs()).encode())
        except zenoh.ZError:                   # the querier gave up or went away
            pass

    return session.declare_queryable(key, on_query)


class JoinRequest:
    """An asynchronous :func:`join_points` query: :attr:`done` is set when every source has
    answered (or at the timeout); :attr:`points` is then the answer."""

    def __init__(self, session, key_expr: str, timeout: float = JOIN_TIMEOUT_S):
        self.base = zenoh.KeyExpr(key_expr)
        self.points: dict[str, int] = {}
        self.done = threading.Event()
        session.get(f"{wire.PREFIX}/*/{JOIN}", zenoh.handlers.Callback(self._on_reply, self.done.set),
                    target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout,
                    priority=zenoh.Priority.DATA, **DATA_QOS)

    def _on_reply(self, reply) -> None:
        ok = reply.ok
        if ok is None:
            return
        try:                                   # a source answers for its own topics only
            name = wire.check_name(str(ok.key_expr).split("/")[1])
            got = wire.loads(ok.payload.to_bytes(), "join point answer")
        except (ValueError, IndexError):
            return
        if str(ok.key_expr) != f"{wire.PREFIX}/{name}/{JOIN}" or not isinstance(got, dict):
            return
        for topic, seq in got.items():
            if not (isinstance(topic, str) and type(seq) is int and 0 < seq <= wire.SEQ_MAX):
                continue
            try:
                if wire.parse_key(topic)[0] == name and self.base.intersects(zenoh.KeyExpr(topic)):
                    self.points[topic] = max(seq, self.points.get(topic, 0))
            except (wire.WireError, zenoh.ZError):
                continue


def join_points(session, key_expr: str, timeout: float = JOIN_TIMEOUT_S) -> dict:
    """{topic key: first seq} a sink that has just declared its subscriber on ``key_expr`` can
    rely on: from that seq on, every sample of the topic is routed to it.

    Why: a Zenoh peer routes everything to a newly connected peer until that peer's answer to its
    interest (its declarations so far, then a final mark) arrives, and from then on only what the
    peer subscribed to. A sink's subscriber is declared after its session has connected, so its
    final mark can reach the source before its subscriber: the sink may then receive a few samples
    from the first phase, none until the subscriber arrives, then all of them: a gap right after
    its first samples (seen as 1 to 3 samples missing 4 samples after a recorder's first, under
    load; tests/e2e/test_live.py). A query sent after the subscriber is processed by the source after
    it: a link's messages are handled in order, and the sender never lets a lower priority (the
    query's, DATA) pass a message queued before it at a higher or equal one (declarations: DATA or
    above, by zenoh version). So a source's answer, the first seq it had not started when the
    query came, marks where the sink's stream is complete. Only a source's own topics count (the
    reply's key names the source). Sources that do not serve ``@join`` (not noiselab's) give
    nothing: nothing to rely on and nothing dropped. A sink whose subscriber existed before a
    source connected needs none (its declarations come before its final mark). Blocks until
    every source has answered (at most ``timeout``); :class:`JoinRequest` does not block."""
    req = JoinRequest(session, key_expr, timeout)
    req.done.wait(timeout + 1.0)
    return dict(req.points)


def check_key_expr(text: str) -> str:
    """A valid Zenoh key expression, or a one-line TransportError."""
    try:
        zenoh.KeyExpr(text)
    except zenoh.ZError as exc:
        raise TransportError(f"invalid key expression {text!r}: {_one_line(exc)}") from None
    return text


def endpoints_of(args: argparse.Namespace, role: str) -> dict:
    """Listen/connect endpoints as they will be used (for messages and summaries): the command
    line's, else the config file's, else the defaults (:func:`build_config`)."""
    conf = build_config(args, role)
    mode = json.loads(conf.get_json("mode"))
    out = {}
    for what in ("listen", "connect"):
        ends = json.loads(conf.get_json(f"{what}/endpoints"))
        out[what] = list((ends.get(mode) or []) if isinstance(ends, dict) else ends)
    return out
