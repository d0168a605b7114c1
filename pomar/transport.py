"""Zenoh transport of the wire format (eclipse-zenoh >= 1.0, advanced publisher/subscriber).

Defaults: peer mode, multicast and gossip scouting off, so a session talks only to the endpoints it
is given: the onboard node listens on ``tcp/127.0.0.1:7447`` and the ground connects to it. A session
given no listen endpoint (by argument or in its config file) listens on none, never on zenoh's default
of a random port on every interface. Real links (drone <-> laptop over a radio) pass their own
``listen`` / ``connect`` endpoints, and a config file with TLS and user/password authentication
(``docs/zenoh/``, README's "On a real link").

The publisher keeps a cache of its samples and announces them (sample-miss detection, publisher
detection); the subscriber asks for that history, also from publishers that appear later, and
recovers missed samples, so a late or restarted ground still gets every frame the cache holds.
Frames may then arrive twice: :class:`FlightSubscriber` drops repeats by frame index.
"""

from __future__ import annotations

import json
import logging
import time
from collections import deque

import zenoh
import zenoh.ext as zext

from pomar import wire
from pomar.cli import InputError

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


class TransportError(InputError, RuntimeError):
    """A zenoh session that cannot be set up: its config file or endpoints."""


def session_config(listen: list[str] | None = None, connect: list[str] | None = None, mode: str = "peer",
                   config_file: str | None = None) -> zenoh.Config:
    try:
        cfg = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    except Exception as exc:  # zenoh raises its own error type for a missing or malformed file
        raise TransportError(f"{config_file}: not a usable zenoh config ({exc})") from None
    if not config_file:
        cfg.insert_json5("mode", json.dumps(mode))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("scouting/gossip/enabled", "false")
        cfg.insert_json5("timestamping/enabled", "true")
    if listen is not None:
        cfg.insert_json5("listen/endpoints", json.dumps(listen))
    elif isinstance(json.loads(cfg.get_json("listen/endpoints")), dict):
        # zenoh's default would listen on a random port on every interface: a session told nothing listens
        # nowhere (it connects); one that must listen says where (--listen, or listen/endpoints in its config)
        cfg.insert_json5("listen/endpoints", "[]")
    if connect is not None:
        cfg.insert_json5("connect/endpoints", json.dumps(connect))
    return cfg


def open_session(listen=None, connect=None, mode="peer", config_file=None) -> zenoh.Session:
    cfg = session_config(listen, connect, mode, config_file)
    try:
        return zenoh.open(cfg)
    except Exception as exc:  # a port in use, a certificate that does not load, ...
        where = f" (config {config_file})" if config_file else ""
        raise TransportError(f"zenoh session could not open{where}: listen {listen}, connect {connect}: {exc}") from None


class FlightPublisher:
    """Publishes one flight's streams with zenoh's advanced publisher (cache of ``history`` samples each)."""

    def __init__(self, session: zenoh.Session, flight_id: str, drone_id: str, history: int = 100_000):
        self.flight_id, self.drone_id = flight_id, drone_id
        self._session = session
        enc = zenoh.Encoding(wire.ENCODING)
        self._pubs = {
            kind: zext.declare_advanced_publisher(
                session, wire.key(flight_id, drone_id, kind), encoding=enc,
                cache=zext.CacheConfig(max_samples=history if kind != "status" else 10),
                sample_miss_detection=zext.MissDetectionConfig(heartbeat=0.5),
                publisher_detection=True,
            )
            for kind in wire.KINDS
        }
        self.sent = {kind: 0 for kind in wire.KINDS}
        self.bytes = {kind: 0 for kind in wire.KINDS}

    def wait_for_subscriber(self, timeout_s: float) -> bool:
        """Wait until a subscriber matches every stream of the flight (at most timeout_s); whether one did.

        A lock-step replay waits for its ground: the history of a publisher whose first samples go out while
        a new subscriber's interest is still on its way can miss them (seen as a ground without the first few
        frames), and a replay has no reason to start before its ground listens."""
        session = self._session
        probes = [session.declare_publisher(wire.key(self.flight_id, self.drone_id, kind)) for kind in wire.KINDS]
        try:
            t0 = time.monotonic()
            while time.monotonic() - t0 < timeout_s:
                if all(p.matching_status.matching for p in probes):
                    return True
                time.sleep(0.05)
            return False
        finally:
            for p in probes:
                p.undeclare()

    def put(self, kind: str, payload: bytes) -> None:
        self._pubs[kind].put(payload)
        self.sent[kind] += 1
        self.bytes[kind] += len(payload)

    def publish(self, msg) -> None:
        self.put(wire.kind_of(msg), msg.encode())

    def close(self) -> None:
        for p in self._pubs.values():
            p.undeclare()


def linger_and_close(session: zenoh.Session, publisher: FlightPublisher, seconds: float) -> None:
    """Keep serving the publisher's history for ``seconds`` (or until Ctrl-C / SIGINT), then close: closing a session
    with data still queued loses it."""
    try:
        time.sleep(seconds)
    except KeyboardInterrupt:
        pass
    publisher.close()
    session.close()


class FlightSubscriber:
    """Receives one flight's messages through a :class:`pomar.wire.StreamFilter`: decoded, validated, from the
    flight's drones only, frames and keyframes de-duplicated.

    A message the filter refuses is counted by reason and logged, never raised: one bad message does not
    stop the ground. ``on_accept`` gets the raw bytes of each message let in (e.g. a journal).
    """

    def __init__(self, session: zenoh.Session, flight_id: str, stream: wire.StreamFilter | None = None,
                 capacity: int = 100_000, on_accept=None):
        self.stream = stream or wire.StreamFilter(flight_id)
        self._session, self._flight_id, self._capacity = session, flight_id, capacity
        self._sub = self._declare()
        self.on_accept = on_accept
        self.refreshes = 0
        self._queued: deque = deque()  # samples taken from a replaced subscriber, delivered first

    def _declare(self):
        # every drone of the flight: those not the flight's are counted as they are refused
        return zext.declare_advanced_subscriber(
            self._session, wire.key(self._flight_id, "*", "**"), zenoh.handlers.FifoChannel(self._capacity),
            history=zext.HistoryConfig(detect_late_publishers=True),
            recovery=zext.RecoveryConfig(heartbeat=True),
            subscriber_detection=True,
        )

    def refresh(self) -> None:
        """Ask the publishers for their whole history again: a new subscriber in place of this one. For a stream that
        says it sent more than arrived (zenoh's history and recovery may leave a gap); what arrives again is dropped
        as repeats. Messages still queued in the old one are taken first."""
        old = self._sub
        self._sub = self._declare()
        while (sample := old.try_recv()) is not None:
            self._queued.append(sample)
        old.undeclare()
        self.refreshes += 1

    duplicates = property(lambda self: self.stream.duplicates)
    errors = property(lambda self: self.stream.errors)
    rejected = property(lambda self: self.stream.rejected)

    def _accept(self, sample) -> object | None:
        payload = bytes(sample.payload.to_bytes())
        try:
            msg = self.stream.accept(payload, str(sample.key_expr))
        except wire.WireError as exc:
            log.warning("dropped a message on %s (%s): %s", sample.key_expr, exc.reason, exc)
            return None
        if msg is not None and self.on_accept is not None:
            self.on_accept(payload)
        return msg

    def recv(self, timeout: float | None = None):
        """The next new message, or None after timeout seconds (None = wait)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            sample = self._queued.popleft() if self._queued else self._sub.try_recv()
            if sample is None:
                if deadline is not None and time.monotonic() >= deadline:
                    return None
                time.sleep(0.002)
                continue
            msg = self._accept(sample)
            if msg is not None:
                return msg

    def close(self) -> None:
        self._sub.undeclare()
