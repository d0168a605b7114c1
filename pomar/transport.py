"""Zenoh transport of the wire format (eclipse-zenoh >= 1.0, advanced publisher/subscriber).

Defaults: peer mode, multicast and gossip scouting off, so a session talks only to the endpoints it
is given: the onboard node listens on ``tcp/127.0.0.1:7447`` and the ground connects to it. Real
links (drone <-> laptop over a radio) pass their own ``listen`` / ``connect`` endpoints.

The publisher keeps a cache of its samples and announces them (sample-miss detection, publisher
detection); the subscriber asks for that history, also from publishers that appear later, and
recovers missed samples, so a late or restarted ground still gets every frame the cache holds.
Frames may then arrive twice: :class:`FlightSubscriber` drops repeats by frame index.
"""

from __future__ import annotations

import json
import logging
import time

import zenoh
import zenoh.ext as zext

from pomar import wire

log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def session_config(listen: list[str] | None = None, connect: list[str] | None = None, mode: str = "peer",
                   config_file: str | None = None) -> zenoh.Config:
    cfg = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    if not config_file:
        cfg.insert_json5("mode", json.dumps(mode))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("scouting/gossip/enabled", "false")
        cfg.insert_json5("timestamping/enabled", "true")
    if listen is not None:
        cfg.insert_json5("listen/endpoints", json.dumps(listen))
    if connect is not None:
        cfg.insert_json5("connect/endpoints", json.dumps(connect))
    return cfg


def open_session(listen=None, connect=None, mode="peer", config_file=None) -> zenoh.Session:
    return zenoh.open(session_config(listen, connect, mode, config_file))


class FlightPublisher:
    """Publishes one flight's streams with zenoh's advanced publisher (cache of ``history`` samples each)."""

    def __init__(self, session: zenoh.Session, flight_id: str, drone_id: str, history: int = 100_000):
        self.flight_id, self.drone_id = flight_id, drone_id
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

    def put(self, kind: str, payload: bytes) -> None:
        self._pubs[kind].put(payload)
        self.sent[kind] += 1
        self.bytes[kind] += len(payload)

    def publish(self, msg) -> None:
        kind = {wire.FrameMessage: "frames", wire.KeyframeMessage: "keyframes", wire.StatusMessage: "status",
                wire.CameraMessage: "camera"}[type(msg)]
        self.put(kind, msg.encode())

    def close(self) -> None:
        for p in self._pubs.values():
            p.undeclare()


class FlightSubscriber:
    """Receives a flight's messages (all drones by default), decoded, frames and keyframes de-duplicated.

    Messages that fail to decode are counted and logged, never raised: one bad message does not
    stop the ground.
    """

    def __init__(self, session: zenoh.Session, flight_id: str, drone_id: str = "*", capacity: int = 1_000_000,
                 on_accept=None, seen: dict | None = None):
        self._sub = zext.declare_advanced_subscriber(
            session, wire.key(flight_id, drone_id, "**"), zenoh.handlers.FifoChannel(capacity),
            history=zext.HistoryConfig(detect_late_publishers=True),
            recovery=zext.RecoveryConfig(heartbeat=True),
            subscriber_detection=True,
        )
        # (kind, drone) -> frame indices already accepted; a restarted ground passes what its journal holds
        self._seen: dict[tuple[str, str], set[int]] = seen if seen is not None else {}
        self.duplicates = 0
        self.errors: list[str] = []
        self.on_accept = on_accept  # called with the raw bytes of each accepted message (e.g. a journal)

    def _accept(self, sample) -> object | None:
        payload = bytes(sample.payload.to_bytes())
        try:
            msg = wire.decode(payload)
        except wire.WireError as exc:
            self.errors.append(f"{sample.key_expr}: {exc}")
            log.warning("dropped a message on %s: %s", sample.key_expr, exc)
            return None
        if isinstance(msg, (wire.FrameMessage, wire.KeyframeMessage)):
            k = ("frame" if isinstance(msg, wire.FrameMessage) else "keyframe", msg.drone_id)
            seen = self._seen.setdefault(k, set())
            if msg.frame in seen:
                self.duplicates += 1
                return None
            seen.add(msg.frame)
        if self.on_accept is not None:
            self.on_accept(payload)
        return msg

    def recv(self, timeout: float | None = None):
        """The next new message, or None after timeout seconds (None = wait)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            sample = self._sub.try_recv()
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
