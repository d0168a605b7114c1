"""The wire format between the onboard node and the ground, version 1 (both sides import this module).

Key expressions, under ``pomar/<flight_id>/<drone_id>/``:

- ``frames``    one :class:`FrameMessage` per processed frame: telemetry at capture + detections (and the
  scale the frame was resized by for the detector; optional, 1 when absent; and whether a keyframe of this frame
  follows, optional, false when absent)
- ``keyframes`` one :class:`KeyframeMessage` per keyframe: frame index + JPEG bytes
- ``status``    :class:`StatusMessage`: rates, drops, detector latency, heartbeat
- ``camera``    :class:`CameraMessage`: the flight's camera.json, so the ground needs no file from the drone

Payloads are msgpack maps with ``"v"`` (schema version) and ``"type"``; zenoh carries them with the
encoding :data:`ENCODING`. Detection boxes are ``x1, y1, x2, y2`` in pixels, OpenCV convention
(top-left pixel centre at (0, 0)); centres are the boxes' centres.

Every decoder validates every field: its type, a finite value and a plausible range (see the limits
below). Anything else raises :class:`WireError`, whose ``reason`` is one of :data:`REASONS`; no other
exception type leaves a decoder. What a message can only be judged by against the stream so far
(its flight and drone, its frame index against the newest frame, its size against the camera's) is
checked by :class:`StreamFilter`, which the ground puts in front of everything it receives.
"""

from __future__ import annotations

import math
import re
import struct
import time
from dataclasses import dataclass, field

import msgpack
import numpy as np

from pomar.flight import ID_PATTERN, check_id

SCHEMA_VERSION = 1
ENCODING = "application/msgpack"
KINDS = ("frames", "keyframes", "status", "camera")

#: Limits of a valid message.
MAX_BOXES = 5000  # detections in one frame message (the shipped detector keeps at most 300 proposals)
MAX_FRAME = 10_000_000  # frame index (over 90 h of video at 30 fps)
MAX_IMAGE_SIDE = 16384  # pixels
MAX_JPEG_BYTES = 16 << 20
MAX_TEXT = 1000  # characters in a status message's text
QUAT_NORM_TOL = 1e-3  # |q| must be 1 within this
# A box overlaps the image, [-0.5, w - 0.5] in OpenCV's pixel convention, and is no larger than it: an apple cut by
# the image's edge may have its whole box (its centre outside), as the truth-replay stand-in gives.

#: Why a message was refused (``WireError.reason``).
#: What a position's altitude is measured from, as the drone's log says (pomar.telemetry's ``altitude_reference``):
#: sea level ("msl"), the WGS84 ellipsoid ("ellipsoid"), the take-off point ("takeoff"), or a log that does not say
#: above what ("unstated") or gives no altitude ("unknown"). Only the first two place a map above sea level.
ALTITUDE_REFERENCES = ("msl", "ellipsoid", "takeoff", "unstated", "unknown")
ABSOLUTE_ALTITUDES = ("msl", "ellipsoid")


def above_sea_level(reference: str | None) -> bool:
    """Whether altitudes of this reference place a map above sea level (None: not said, taken as MAVLink's MSL)."""
    return reference is None or reference in ABSOLUTE_ALTITUDES


REASONS = ("not_msgpack", "schema_version", "message_type", "malformed", "not_finite", "out_of_range",
           "too_many_boxes", "box_outside_image", "bad_quaternion", "bad_jpeg", "image_size",
           "frame_window", "wrong_flight", "other_drone", "drone_mismatch", "camera_changed")


class WireError(ValueError):
    """A message refused: unknown schema version, wrong type, a missing, malformed or implausible field, or
    (from :class:`StreamFilter`) a message that does not belong to the stream. ``reason`` says which."""

    def __init__(self, message: str, reason: str = "malformed"):
        super().__init__(message)
        self.reason = reason


def key(flight_id: str, drone_id: str, kind: str) -> str:
    """The zenoh key expression of one stream of a flight."""
    if kind not in KINDS and kind != "**":
        raise ValueError(f"unknown stream {kind!r} (one of {KINDS})")
    for name, value in (("flight_id", flight_id), ("drone_id", drone_id)):
        if value != "*":
            check_id(name, value)
    return f"pomar/{flight_id}/{drone_id}/{kind}"


def parse_key(key_expr: str) -> tuple[str, str, str] | None:
    """(flight_id, drone_id, kind) of a stream's key expression, or None."""
    parts = str(key_expr).split("/")
    if len(parts) != 4 or parts[0] != "pomar" or parts[3] not in KINDS:
        return None
    return parts[1], parts[2], parts[3]


# -- field checks: each raises WireError naming the field
def _check(d, type_: str, fields: tuple[str, ...]) -> None:
    if not isinstance(d, dict):
        raise WireError(f"expected a msgpack map, got {type(d).__name__}", "malformed")
    v = d.get("v")
    if v != SCHEMA_VERSION:
        raise WireError(f"unknown schema version {v!r} (this build reads version {SCHEMA_VERSION})", "schema_version")
    if d.get("type") != type_:
        raise WireError(f"expected a {type_!r} message, got {d.get('type')!r}", "message_type")
    missing = [f for f in fields if f not in d]
    if missing:
        raise WireError(f"{type_} message lacks field(s) {missing}", "malformed")


def _int(name: str, x, lo: int, hi: int) -> int:
    if isinstance(x, bool) or not isinstance(x, int):
        raise WireError(f"{name} must be an integer, got {type(x).__name__}", "malformed")
    if not lo <= x <= hi:
        raise WireError(f"{name} {x} is outside [{lo}, {hi}]", "out_of_range")
    return int(x)


def _float(name: str, x, lo: float = -math.inf, hi: float = math.inf, nan: bool = False) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise WireError(f"{name} must be a number, got {type(x).__name__}", "malformed")
    x = float(x)
    if math.isnan(x) and nan:
        return x
    if not math.isfinite(x):
        raise WireError(f"{name} is {x}, not a finite number", "not_finite")
    if not lo <= x <= hi:
        raise WireError(f"{name} {x} is outside [{lo}, {hi}]", "out_of_range")
    return x


def _flag(name: str, x) -> bool:
    if not isinstance(x, bool):
        raise WireError(f"{name} must be true or false, got {type(x).__name__}", "malformed")
    return x


def _str(name: str, x, pattern: re.Pattern | None = ID_PATTERN, max_len: int = 128) -> str:
    if not isinstance(x, str) or len(x) > max_len or (pattern is not None and not pattern.match(x)):
        raise WireError(f"{name} must be a string of at most {max_len} characters"
                        + (" (letters, digits, '_', '-', '.')" if pattern is not None else "") + f", got {x!r:.60}",
                        "malformed")
    return x


def _bytes(name: str, x, max_len: int) -> bytes:
    if not isinstance(x, (bytes, bytearray)):
        raise WireError(f"{name} must be bytes, got {type(x).__name__}", "malformed")
    if len(x) > max_len:
        raise WireError(f"{name} holds {len(x)} bytes, more than {max_len}", "out_of_range")
    return bytes(x)


def _unpack(payload: bytes) -> dict:
    try:
        return msgpack.unpackb(bytes(payload), raw=False)
    except Exception as exc:  # msgpack raises several types for bad bytes
        raise WireError(f"not a msgpack message ({type(exc).__name__}: {exc})", "not_msgpack") from None


def _quat(name: str, x) -> tuple[float, float, float, float]:
    """A unit quaternion, or all NaN (unknown: the frame's flags say why)."""
    if not isinstance(x, (list, tuple)) or len(x) != 4:
        raise WireError(f"{name} must be a list of 4 numbers", "malformed")
    q = tuple(_float(f"{name}[{i}]", v, nan=True) for i, v in enumerate(x))
    nans = sum(math.isnan(v) for v in q)
    if nans == 4:
        return q
    if nans:
        raise WireError(f"{name} {q} is partly NaN", "not_finite")
    if abs(math.sqrt(sum(v * v for v in q)) - 1.0) > QUAT_NORM_TOL:
        raise WireError(f"{name} {q} is not a unit quaternion", "bad_quaternion")
    return q


def jpeg_size(data: bytes) -> tuple[int, int]:
    """(width, height) from a JPEG's frame header; WireError when the bytes are no complete JPEG."""
    if data[:2] != b"\xff\xd8":
        raise WireError("payload is not a JPEG (no start-of-image marker)", "bad_jpeg")
    if data.rstrip(b"\x00")[-2:] != b"\xff\xd9":
        raise WireError("JPEG is cut short (no end-of-image marker)", "bad_jpeg")
    pos, n = 2, len(data)
    while pos + 4 <= n:
        if data[pos] != 0xFF:
            raise WireError(f"JPEG marker expected at byte {pos}", "bad_jpeg")
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:  # markers without a length
            pos += 2
            continue
        (length,) = struct.unpack_from(">H", data, pos + 2)
        if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
            if pos + 9 > n:
                break
            h, w = struct.unpack_from(">HH", data, pos + 5)
            if not (0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE):
                raise WireError(f"JPEG size {w}x{h} is implausible", "bad_jpeg")
            return w, h
        if marker == 0xDA:  # start of scan before any frame header
            break
        pos += 2 + length
    raise WireError("JPEG has no frame header", "bad_jpeg")


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
    #: m above the take-off point, where the log places it (a DJI .SRT's H, a .tlog's relative_alt); NaN unknown.
    height: float = float("nan")
    #: m, the height's accuracy where the log states it or its source is known (a DJI barometer's); NaN unknown.
    height_acc: float = float("nan")

    def to_list(self) -> list:
        """8 fields, and the height and its accuracy as a 9th and 10th (older nodes and journals send 8)."""
        return [self.lat, self.lon, self.alt, list(self.q_attitude), list(self.q_gimbal), self.gps_fix, self.h_acc,
                self.flags, self.height, self.height_acc]

    @classmethod
    def from_list(cls, x: list) -> "Telemetry":
        """Position in range or all NaN (unknown), unit quaternions or all NaN; never inf."""
        if not isinstance(x, (list, tuple)) or len(x) not in (8, 10):
            raise WireError("telemetry must be a list of 8 or 10 fields", "malformed")
        lat = _float("telemetry lat", x[0], -90.0, 90.0, nan=True)
        lon = _float("telemetry lon", x[1], -180.0, 180.0, nan=True)
        alt = _float("telemetry alt", x[2], -1000.0, 20000.0, nan=True)
        if 0 < sum(math.isnan(v) for v in (lat, lon, alt)) < 3:
            raise WireError(f"telemetry position ({lat}, {lon}, {alt}) is partly NaN", "not_finite")
        return cls(lat, lon, alt, _quat("telemetry q_attitude", x[3]), _quat("telemetry q_gimbal", x[4]),
                   _int("telemetry gps_fix", x[5], 0, 255), _float("telemetry h_acc", x[6], 0.0, 1e6, nan=True),
                   _int("telemetry flags", x[7], 0, 2**31 - 1),
                   *((_float("telemetry height", x[8], -1000.0, 20000.0, nan=True),
                      _float("telemetry height_acc", x[9], 0.0, 1e6, nan=True)) if len(x) == 10 else ()))


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
    #: The factor the frame was resized by before detection (boxes are in the full frame's pixels all the same).
    scale: float = 1.0
    #: A keyframe of this frame follows on the keyframes stream: a lock-step ground waits for it.
    keyframe: bool = False

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
            "n": len(b), "boxes": b.tobytes(), "scores": s.tobytes(), "scale": float(self.scale),
            "kf": bool(self.keyframe),
        }, use_bin_type=True)

    @classmethod
    def decode(cls, payload: bytes) -> "FrameMessage":
        return _decode(payload, cls._from_dict)

    @classmethod
    def _from_dict(cls, d: dict) -> "FrameMessage":
        _check(d, "frame", ("flight", "drone", "frame", "t", "tel", "w", "h", "n", "boxes", "scores"))
        frame = _int("frame", d["frame"], 0, MAX_FRAME)
        where = f"frame {frame}"
        w = _int(f"{where}: width", d["w"], 1, MAX_IMAGE_SIDE)
        h = _int(f"{where}: height", d["h"], 1, MAX_IMAGE_SIDE)
        n = _int(f"{where}: box count", d["n"], 0, 2**31)
        if n > MAX_BOXES:
            raise WireError(f"{where}: {n} boxes, more than the {MAX_BOXES} a frame may carry", "too_many_boxes")
        raw_b, raw_s = _bytes(f"{where}: boxes", d["boxes"], 16 * n), _bytes(f"{where}: scores", d["scores"], 4 * n)
        if len(raw_b) != 16 * n or len(raw_s) != 4 * n:
            raise WireError(f"{where}: {n} boxes announced, {len(raw_b)} box and {len(raw_s)} score bytes sent",
                            "malformed")
        boxes = np.frombuffer(raw_b, dtype="<f4").reshape(n, 4)
        scores = np.frombuffer(raw_s, dtype="<f4").reshape(n)
        if not (np.isfinite(boxes).all() and np.isfinite(scores).all()):
            raise WireError(f"{where}: a box or score is not finite", "not_finite")
        if n and not ((scores >= 0).all() and (scores <= 1).all()):
            raise WireError(f"{where}: a score is outside [0, 1]", "out_of_range")
        if n and not ((boxes[:, 0] <= boxes[:, 2]).all() and (boxes[:, 1] <= boxes[:, 3]).all()
                      and (boxes[:, 2] - boxes[:, 0] <= w).all() and (boxes[:, 3] - boxes[:, 1] <= h).all()
                      and (boxes[:, 2] >= -0.5).all() and (boxes[:, 0] <= w - 0.5).all()
                      and (boxes[:, 3] >= -0.5).all() and (boxes[:, 1] <= h - 0.5).all()):
            raise WireError(f"{where}: a box lies outside the {w}x{h} image, or is inverted or larger than the image",
                            "box_outside_image")
        return cls(_str("flight", d["flight"]), _str("drone", d["drone"]), frame,
                   _float(f"{where}: capture time", d["t"], 0.0, 2.0**33), Telemetry.from_list(d["tel"]), w, h,
                   boxes, scores, _str(f"{where}: camera id", d.get("cam", "cam0")),
                   _float(f"{where}: detector scale", d.get("scale", 1.0), 0.01, 16.0),
                   _flag(f"{where}: keyframe flag", d.get("kf", False)))


@dataclass
class KeyframeMessage:
    flight_id: str
    drone_id: str
    frame: int
    jpeg: bytes

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) from the JPEG's header."""
        return jpeg_size(self.jpeg)

    def encode(self) -> bytes:
        return msgpack.packb({"v": SCHEMA_VERSION, "type": "keyframe", "flight": self.flight_id, "drone": self.drone_id,
                              "frame": int(self.frame), "jpeg": bytes(self.jpeg)}, use_bin_type=True)

    @classmethod
    def decode(cls, payload: bytes) -> "KeyframeMessage":
        return _decode(payload, cls._from_dict)

    @classmethod
    def _from_dict(cls, d: dict) -> "KeyframeMessage":
        _check(d, "keyframe", ("flight", "drone", "frame", "jpeg"))
        frame = _int("keyframe frame", d["frame"], 0, MAX_FRAME)
        jpeg = _bytes(f"keyframe {frame}: jpeg", d["jpeg"], MAX_JPEG_BYTES)
        try:
            jpeg_size(jpeg)
        except WireError as exc:
            raise WireError(f"keyframe {frame}: {exc}", exc.reason) from None
        return cls(_str("flight", d["flight"]), _str("drone", d["drone"]), frame, jpeg)


STATES = ("running", "finished", "error")


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
    state: str = "running"  # one of STATES
    message: str = ""
    #: The first frame index this node sent: a node restarted mid-flight counts its frames from there (optional on the
    #: wire; 0 where a sender does not say).
    first_frame: int = 0

    def encode(self) -> bytes:
        d = {"v": SCHEMA_VERSION, "type": "status", **{k: getattr(self, k) for k in self.__dataclass_fields__}}
        return msgpack.packb(d, use_bin_type=True)

    @classmethod
    def decode(cls, payload: bytes) -> "StatusMessage":
        return _decode(payload, cls._from_dict)

    @classmethod
    def _from_dict(cls, d: dict) -> "StatusMessage":
        _check(d, "status", ("flight_id", "drone_id", "t"))
        state = d.get("state", "running")
        if state not in STATES:
            raise WireError(f"status state {state!r:.40} is not one of {STATES}", "malformed")
        return cls(_str("flight_id", d["flight_id"]), _str("drone_id", d["drone_id"]),
                   _float("status t", d["t"], 0.0, 2.0**33),
                   *(_int(f"status {k}", d.get(k, 0), 0, 2**31 - 1)
                     for k in ("frames_read", "frames_processed", "frames_dropped")),
                   _float("status fps", d.get("fps", 0.0), 0.0, 1e6),
                   _float("status detector_latency_s", d.get("detector_latency_s", 0.0), 0.0, 1e6),
                   state, _str("status message", d.get("message", ""), None, MAX_TEXT),
                   _int("status first_frame", d.get("first_frame", 0), 0, 2**31 - 1))


@dataclass
class CameraMessage:
    flight_id: str
    drone_id: str
    camera: dict  # camera.json's content
    fps: float = 0.0
    video_start_unix: float = 0.0
    #: The width of the keyframes' images (px; 0: not said, as by nodes before it): a ground that must start before
    #: the first image comes sizes its keyframe camera from it.
    keyframe_width: int = 0
    #: True: frames come at the video's own pace, and the drone drops those it has no time for (live); False: every
    #: frame, as fast as they are taken (lock-step); None: not said. The ground takes its profile from it.
    paced: bool | None = None
    #: The smallest apple radius (px, as the detector sees it) the drone's detector finds reliably: its model's
    #: envelope (``min_apple_radius_px``); 0: not said. The ground counts the frames whose apples reached it smaller.
    min_apple_radius_px: float = 0.0
    #: The drone publishes detections scored at least this (pomar.countable.publish_score unless told otherwise);
    #: None: not said (a truth stand-in, or a node before it).
    score_thresh: float | None = None
    #: What the frames' altitudes are measured from (one of ALTITUDE_REFERENCES); None: not said (a node before it;
    #: taken as sea level, as a MAVLink position's).
    altitude_reference: str | None = None
    #: How the detector's boxes answer an apple's size: box half-size = slope x radius + intercept (px, as the
    #: detector sees them), from its model's metadata; None: not said (boxes taken as the apples' size, as the truth's).
    box_response: tuple[float, float] | None = None
    #: The score the drone's model operates at in the count (pomar.countable.count_scores: its metadata's count
    #: confirm score, else its ``score_thresh``): a view at or above it confirms an apple. None: not said (a truth
    #: stand-in, or a node before it).
    operating_score: float | None = None
    #: The score the drone's model's count wants detections published from (its metadata's, pomar.countable.
    #: count_scores), whatever the node was started with: the ground says when it was given fewer. None: not said
    #: (then pomar.countable.publish_score of operating_score).
    needed_score: float | None = None

    def encode(self) -> bytes:
        return msgpack.packb({"v": SCHEMA_VERSION, "type": "camera", "flight": self.flight_id, "drone": self.drone_id,
                              "camera": self.camera, "fps": self.fps, "start": self.video_start_unix,
                              "kfw": int(self.keyframe_width),
                              **({} if self.paced is None else {"paced": bool(self.paced)}),
                              **({"minr": float(self.min_apple_radius_px)} if self.min_apple_radius_px else {}),
                              **({} if self.score_thresh is None else {"pubs": float(self.score_thresh)}),
                              **({} if self.altitude_reference is None else {"altref": self.altitude_reference}),
                              **({} if self.box_response is None else {"boxr": [float(v) for v in self.box_response]}),
                              **({} if self.operating_score is None else {"ops": float(self.operating_score)}),
                              **({} if self.needed_score is None else {"pubn": float(self.needed_score)})},
                             use_bin_type=True)

    @property
    def size(self) -> tuple[int, int]:
        return int(self.camera["width"]), int(self.camera["height"])

    @classmethod
    def decode(cls, payload: bytes) -> "CameraMessage":
        return _decode(payload, cls._from_dict)

    @classmethod
    def _from_dict(cls, d: dict) -> "CameraMessage":
        from pomar.camera import Camera, CameraFileError

        _check(d, "camera", ("flight", "drone", "camera", "fps"))
        if not isinstance(d["camera"], dict):
            raise WireError("camera message: camera must be a map (camera.json's content)", "malformed")
        try:
            cam = Camera.from_dict(d["camera"], source="camera message")
        except CameraFileError as exc:
            raise WireError(str(exc), "malformed") from None
        if not (0 < cam.width <= MAX_IMAGE_SIDE and 0 < cam.height <= MAX_IMAGE_SIDE
                and np.isfinite(cam.params()).all()):
            raise WireError(f"camera message: camera {cam.width}x{cam.height} {cam.params()} is implausible",
                            "out_of_range")
        fps = _float("camera message: fps", d["fps"], 0.0, 10000.0)
        if not fps > 0:
            raise WireError("camera message: fps must be > 0", "out_of_range")
        paced = d.get("paced")
        if paced is not None and not isinstance(paced, bool):
            raise WireError(f"camera message: paced must be true or false, got {paced!r}", "malformed")
        ref = d.get("altref")
        if ref is not None and ref not in ALTITUDE_REFERENCES:
            raise WireError(f"camera message: altitude reference must be one of {', '.join(ALTITUDE_REFERENCES)}, got "
                            f"{ref!r:.40}", "out_of_range")
        return cls(_str("flight", d["flight"]), _str("drone", d["drone"]), dict(d["camera"]), fps,
                   _float("camera message: start", d.get("start", 0.0), 0.0, 2.0**33),
                   _int("camera message: keyframe width", d.get("kfw", 0), 0, MAX_IMAGE_SIDE), paced,
                   _float("camera message: min apple radius", d.get("minr", 0.0), 0.0, 1000.0),
                   None if d.get("pubs") is None else _float("camera message: published score", d["pubs"], 0.0, 1.0),
                   ref, box_response_of(d.get("boxr")),
                   None if d.get("ops") is None else _float("camera message: operating score", d["ops"], 0.0, 1.0),
                   None if d.get("pubn") is None else _float("camera message: score needed", d["pubn"], 0.0, 1.0))


def box_response_of(x, name: str = "camera message: box response") -> tuple[float, float] | None:
    """A detector's box response [slope, intercept px], checked (a slope of 0.2-5, an intercept within 20 px): the
    camera message's, and the model metadata's the drone reads it from (``name`` says which); WireError otherwise."""
    if x is None:
        return None
    if not isinstance(x, (list, tuple)) or len(x) != 2:
        raise WireError(f"{name} must be [slope, intercept], got {x!r:.40}", "malformed")
    return _float(f"{name} slope", x[0], 0.2, 5.0), _float(f"{name} intercept", x[1], -20.0, 20.0)


_TYPES = {"frame": FrameMessage, "keyframe": KeyframeMessage, "status": StatusMessage, "camera": CameraMessage}


def _decode(payload: bytes, from_dict):
    d = _unpack(payload)
    try:
        return from_dict(d)
    except WireError:
        raise
    except Exception as exc:  # a decoder bug or a field shape not foreseen: still a refused message
        raise WireError(f"malformed message ({type(exc).__name__}: {exc})", "malformed") from None


_KIND_OF = {FrameMessage: "frames", KeyframeMessage: "keyframes", StatusMessage: "status", CameraMessage: "camera"}


def kind_of(msg) -> str:
    """The stream (key suffix, one of KINDS) a message goes on."""
    return _KIND_OF[type(msg)]


def decode(payload: bytes):
    """Decode and validate any message by its type field."""
    d = _unpack(payload)
    if not isinstance(d, dict):
        raise WireError(f"expected a msgpack map, got {type(d).__name__}", "malformed")
    cls = _TYPES.get(d.get("type")) if isinstance(d.get("type"), str) else None
    if cls is None:
        if d.get("v") != SCHEMA_VERSION:
            raise WireError(f"unknown schema version {d.get('v')!r:.40} (this build reads version {SCHEMA_VERSION})",
                            "schema_version")
        raise WireError(f"unknown message type {d.get('type')!r:.40}", "message_type")
    return _decode(payload, cls._from_dict)


def decoded_size(msg: KeyframeMessage) -> tuple[int, int]:
    """(width, height) of a keyframe's JPEG as OpenCV decodes it; WireError when it does not decode or its pixels
    disagree with its header. (OpenCV is needed here, as on the ground that maps the keyframes.)"""
    import cv2

    img = cv2.imdecode(np.frombuffer(msg.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    if img is None or (img.shape[1], img.shape[0]) != msg.size:
        raise WireError(f"keyframe {msg.frame}: the JPEG does not decode", "bad_jpeg")
    return img.shape[1], img.shape[0]


class StreamFilter:
    """What the ground lets in: decodes each payload, checks it against the flight so far, drops repeats.

    - The flight: its flight id, from its key expression and its payload alike.
    - The drones: those in ``drone_ids``; with none given, the first drone a valid message comes from.
      Other drones' messages are refused (``other_drone``).
    - A frame or keyframe index at most ``max_ahead_s`` of video ahead of the newest frame (plus the time
      since that frame arrived, so that a stream resumes after a link outage): a message from far in the
      future would hold back every real frame after it (``frame_window``).
    - A frame's size is the camera's; a keyframe's JPEG decodes (``bad_jpeg``), keeps the camera's aspect and the
      first keyframe's size (``image_size``).
    - Frames and keyframes already accepted are repeats (zenoh's history and recovery resend them).

    :meth:`accept` returns the message, or None for a repeat, or raises :class:`WireError`; ``rejected``
    counts refusals by reason and ``errors`` keeps the last ones' texts.
    """

    def __init__(self, flight_id: str, drone_ids=None, max_ahead_s: float = 60.0, clock=time.monotonic):
        self.flight_id = check_id("flight_id", flight_id)
        self.drone_ids = {check_id("drone_id", d) for d in drone_ids} if drone_ids else set()
        self.max_ahead_s = max_ahead_s
        self.clock = clock
        self.seen: dict[tuple[str, str], set[int]] = {}
        self.duplicates = 0
        self.rejected: dict[str, int] = {}
        self.errors: list[str] = []
        self.fps: float | None = None
        self.camera_size: tuple[int, int] | None = None
        self.keyframe_size: tuple[int, int] | None = None
        self.newest: int | None = None
        self._newest_at = 0.0

    def accept(self, payload: bytes, key_expr: str | None = None, check_window: bool = True):
        """The decoded message if it is new and belongs to the flight; None for a repeat; WireError otherwise.
        ``check_window=False`` for a journal read back (its records passed the window when they came)."""
        try:
            msg = decode(payload)
            self._check(msg, key_expr, check_window)
        except WireError as exc:
            self.rejected[exc.reason] = self.rejected.get(exc.reason, 0) + 1
            self.errors = self.errors[-49:] + [f"{key_expr or 'journal'}: {exc}"]
            raise
        if isinstance(msg, (FrameMessage, KeyframeMessage)):
            seen = self.seen.setdefault(("frame" if isinstance(msg, FrameMessage) else "keyframe", msg.drone_id), set())
            if msg.frame in seen:
                self.duplicates += 1
                return None
            seen.add(msg.frame)
            if isinstance(msg, FrameMessage) and (self.newest is None or msg.frame > self.newest):
                self.newest, self._newest_at = msg.frame, self.clock()
        return msg

    def _check(self, msg, key_expr, check_window) -> None:
        flight, drone = (msg.flight_id, msg.drone_id)
        if key_expr is not None:
            parsed = parse_key(key_expr)
            if parsed is None or parsed[0] != self.flight_id:
                raise WireError(f"key {key_expr!r} is not a stream of flight {self.flight_id!r}", "wrong_flight")
            if parsed[1] != drone:
                raise WireError(f"key {key_expr!r} carries a message of drone {drone!r}", "drone_mismatch")
        if flight != self.flight_id:
            raise WireError(f"message of flight {flight!r}, not {self.flight_id!r}", "wrong_flight")
        if not self.drone_ids:
            self.drone_ids.add(drone)  # the first drone heard is the flight's
        elif drone not in self.drone_ids:
            raise WireError(f"message of drone {drone!r}, not of {sorted(self.drone_ids)}", "other_drone")
        if isinstance(msg, CameraMessage):
            # the first camera message is the flight's: a later one that differs (a smaller fps would narrow the
            # frame window to nothing) is refused
            if self.camera_size is not None and (msg.size != self.camera_size or msg.fps != self.fps):
                raise WireError(f"camera message says {msg.size[0]}x{msg.size[1]} at {msg.fps:g} fps, the flight's "
                                f"camera is {self.camera_size[0]}x{self.camera_size[1]} at {self.fps:g} fps",
                                "camera_changed")
            self.camera_size, self.fps = msg.size, msg.fps
        elif isinstance(msg, FrameMessage):
            if self.camera_size is not None and (msg.width, msg.height) != self.camera_size:
                raise WireError(f"frame {msg.frame} is {msg.width}x{msg.height}, the camera "
                                f"{self.camera_size[0]}x{self.camera_size[1]}", "image_size")
        if isinstance(msg, (FrameMessage, KeyframeMessage)) and check_window and self.newest is not None:
            fps = self.fps or 60.0
            ahead = fps * (self.max_ahead_s + max(self.clock() - self._newest_at, 0.0))
            if msg.frame > self.newest + ahead:
                raise WireError(f"{type(msg).__name__} {msg.frame} is {msg.frame - self.newest} frames ahead of the "
                                f"newest frame {self.newest} (at most {ahead:.0f})", "frame_window")
        if isinstance(msg, KeyframeMessage):
            w, h = decoded_size(msg)
            if self.camera_size is not None:
                cw, ch = self.camera_size
                if abs(h - ch * w / cw) > 1.0:
                    raise WireError(f"keyframe {msg.frame} is {w}x{h}: not the camera's {cw}x{ch} nor a scaled copy",
                                    "image_size")
            if self.keyframe_size is not None and (w, h) != self.keyframe_size:
                raise WireError(f"keyframe {msg.frame} is {w}x{h}, the flight's keyframes "
                                f"{self.keyframe_size[0]}x{self.keyframe_size[1]}", "image_size")
            self.keyframe_size = (w, h)
