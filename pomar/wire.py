"""The wire format between the onboard node and the ground, version 1 (both sides import this module).

Key expressions, under ``pomar/<flight_id>/<drone_id>/``:

- ``frames``    one :class:`FrameMessage` per processed frame: telemetry at capture + detections
- ``keyframes`` one :class:`KeyframeMessage` per keyframe: frame index + JPEG bytes
- ``status``    :class:`StatusMessage`: rates, drops, detector latency, heartbeat
- ``camera``    :class:`CameraMessage`: the flight's camera.json, so the ground needs no file from the drone

Payloads are msgpack maps with ``"v"`` (schema version) and ``"type"``; zenoh carries them with the
encoding :data:`ENCODING`. Decoding rejects an unknown version or a malformed message with
:class:`WireError`. Detection boxes are ``x1, y1, x2, y2`` in pixels, OpenCV convention (top-left
pixel centre at (0, 0)); centres are the boxes' centres.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import msgpack
import numpy as np

SCHEMA_VERSION = 1
ENCODING = "application/msgpack"
KINDS = ("frames", "keyframes", "status", "camera")
_ID = re.compile(r"^[A-Za-z0-9_.\-]+$")


class WireError(ValueError):
    """A message that cannot be decoded: unknown schema version, wrong type, missing or malformed field."""


def key(flight_id: str, drone_id: str, kind: str) -> str:
    """The zenoh key expression of one stream of a flight."""
    if kind not in KINDS and kind != "**":
        raise ValueError(f"unknown stream {kind!r} (one of {KINDS})")
    for name, value in (("flight_id", flight_id), ("drone_id", drone_id)):
        if value != "*" and not _ID.match(value):
            raise ValueError(f"{name} {value!r} may hold only letters, digits, '_', '-', '.'")
    return f"pomar/{flight_id}/{drone_id}/{kind}"


def _check(d: dict, type_: str, fields: tuple[str, ...]) -> None:
    if not isinstance(d, dict):
        raise WireError(f"expected a msgpack map, got {type(d).__name__}")
    v = d.get("v")
    if v != SCHEMA_VERSION:
        raise WireError(f"unknown schema version {v!r} (this build reads version {SCHEMA_VERSION})")
    if d.get("type") != type_:
        raise WireError(f"expected a {type_!r} message, got {d.get('type')!r}")
    missing = [f for f in fields if f not in d]
    if missing:
        raise WireError(f"{type_} message lacks field(s) {missing}")


def _unpack(payload: bytes) -> dict:
    try:
        return msgpack.unpackb(bytes(payload), raw=False)
    except Exception as exc:  # msgpack raises several types for bad bytes
        raise WireError(f"not a msgpack message ({exc})") from None


@dataclass
class Telemetry:
    """The autopilot's state at a frame's capture time (NaN where unknown; see ``flags``)."""

    lat: float = float("nan")
    lon: float = float("nan")
    alt: float = float("nan")  # m, MSL
    q_attitude: tuple[float, float, float, float] = (float("nan"),) * 4  # wxyz, NED from body
    q_gimbal: tuple[float, float, float, float] = (float("nan"),) * 4  # wxyz, NED from gimbal
    gps_fix: int = 0
    h_acc: float = float("nan")  # m
    flags: int = 0  # onboard.telemetry.Flags

    def to_list(self) -> list:
        return [self.lat, self.lon, self.alt, list(self.q_attitude), list(self.q_gimbal), self.gps_fix, self.h_acc, self.flags]

    @classmethod
    def from_list(cls, x: list) -> "Telemetry":
        if not isinstance(x, list) or len(x) != 8:
            raise WireError("telemetry must be a list of 8 fields")
        return cls(float(x[0]), float(x[1]), float(x[2]), tuple(map(float, x[3])), tuple(map(float, x[4])),
                   int(x[5]), float(x[6]), int(x[7]))


@dataclass
class FrameMessage:
    flight_id: str
    drone_id: str
    frame: int
    t_capture: float  # unix seconds, autopilot clock
    telemetry: Telemetry
    width: int
    height: int
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4), np.float32))  # (N, 4) x1 y1 x2 y2
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))  # (N,)
    camera_id: str = "cam0"

    @property
    def centres(self) -> np.ndarray:
        b = np.asarray(self.boxes, float).reshape(-1, 4)
        return np.stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2], axis=1)

    def encode(self) -> bytes:
        b = np.ascontiguousarray(self.boxes, dtype="<f4").reshape(-1, 4)
        s = np.ascontiguousarray(self.scores, dtype="<f4").reshape(-1)
        if len(b) != len(s):
            raise ValueError(f"frame {self.frame}: {len(b)} boxes but {len(s)} scores")
        return msgpack.packb({
            "v": SCHEMA_VERSION, "type": "frame", "flight": self.flight_id, "drone": self.drone_id,
            "frame": int(self.frame), "t": float(self.t_capture), "tel": self.telemetry.to_list(),
            "w": int(self.width), "h": int(self.height), "cam": self.camera_id,
            "n": len(b), "boxes": b.tobytes(), "scores": s.tobytes(),
        }, use_bin_type=True)

    @classmethod
    def decode(cls, payload: bytes) -> "FrameMessage":
        d = _unpack(payload)
        _check(d, "frame", ("flight", "drone", "frame", "t", "tel", "w", "h", "n", "boxes", "scores"))
        try:
            n = int(d["n"])
            boxes = np.frombuffer(d["boxes"], dtype="<f4").reshape(n, 4)
            scores = np.frombuffer(d["scores"], dtype="<f4").reshape(n)
            return cls(str(d["flight"]), str(d["drone"]), int(d["frame"]), float(d["t"]), Telemetry.from_list(d["tel"]),
                       int(d["w"]), int(d["h"]), boxes, scores, str(d.get("cam", "cam0")))
        except WireError:
            raise
        except (TypeError, ValueError) as exc:
            raise WireError(f"malformed frame message ({exc})") from None


@dataclass
class KeyframeMessage:
    flight_id: str
    drone_id: str
    frame: int
    jpeg: bytes

    def encode(self) -> bytes:
        return msgpack.packb({"v": SCHEMA_VERSION, "type": "keyframe", "flight": self.flight_id, "drone": self.drone_id,
                              "frame": int(self.frame), "jpeg": bytes(self.jpeg)}, use_bin_type=True)

    @classmethod
    def decode(cls, payload: bytes) -> "KeyframeMessage":
        d = _unpack(payload)
        _check(d, "keyframe", ("flight", "drone", "frame", "jpeg"))
        if not isinstance(d["jpeg"], (bytes, bytearray)) or not bytes(d["jpeg"][:2]) == b"\xff\xd8":
            raise WireError(f"keyframe {d.get('frame')}: payload is not a JPEG")
        return cls(str(d["flight"]), str(d["drone"]), int(d["frame"]), bytes(d["jpeg"]))


@dataclass
class StatusMessage:
    flight_id: str
    drone_id: str
    t: float  # unix seconds, heartbeat time
    frames_read: int = 0
    frames_processed: int = 0
    frames_dropped: int = 0
    fps: float = 0.0
    detector_latency_s: float = 0.0
    state: str = "running"  # "running", "finished", "error"
    message: str = ""

    def encode(self) -> bytes:
        d = {"v": SCHEMA_VERSION, "type": "status", **{k: getattr(self, k) for k in self.__dataclass_fields__}}
        return msgpack.packb(d, use_bin_type=True)

    @classmethod
    def decode(cls, payload: bytes) -> "StatusMessage":
        d = _unpack(payload)
        names = tuple(cls.__dataclass_fields__)
        _check(d, "status", ("flight_id", "drone_id", "t"))
        return cls(**{k: d[k] for k in names if k in d})


@dataclass
class CameraMessage:
    flight_id: str
    drone_id: str
    camera: dict  # camera.json's content
    fps: float = 0.0
    video_start_unix: float = 0.0

    def encode(self) -> bytes:
        return msgpack.packb({"v": SCHEMA_VERSION, "type": "camera", "flight": self.flight_id, "drone": self.drone_id,
                              "camera": self.camera, "fps": self.fps, "start": self.video_start_unix}, use_bin_type=True)

    @classmethod
    def decode(cls, payload: bytes) -> "CameraMessage":
        d = _unpack(payload)
        _check(d, "camera", ("flight", "drone", "camera"))
        return cls(str(d["flight"]), str(d["drone"]), dict(d["camera"]), float(d.get("fps", 0.0)), float(d.get("start", 0.0)))


def decode(payload: bytes):
    """Decode any message by its type field."""
    d = _unpack(payload)
    if not isinstance(d, dict):
        raise WireError(f"expected a msgpack map, got {type(d).__name__}")
    types = {"frame": FrameMessage, "keyframe": KeyframeMessage, "status": StatusMessage, "camera": CameraMessage}
    cls = types.get(d.get("type"))
    if cls is None:
        if d.get("v") != SCHEMA_VERSION:
            raise WireError(f"unknown schema version {d.get('v')!r} (this build reads version {SCHEMA_VERSION})")
        raise WireError(f"unknown message type {d.get('type')!r}")
    return cls.decode(payload)
