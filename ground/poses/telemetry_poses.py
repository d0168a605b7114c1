"""Camera poses from telemetry alone: GPS position + gimbal attitude + the camera's mount.

The fallback for frames that carry detections but do not register (or carry no image): world(ENU)-
to-camera poses whose error is the telemetry's (GPS metres, attitude fractions of a degree).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pomar.telemetry.tlog import read_tlog
from pomar.camera import Camera
from pomar.flight import FlightDir
from pomar.geo import Origin
from pomar.rotations import camera_rotations
from pomar.telemetry.base import UNSTATED_H_ACC_M


class KeyframeTelemetry(NamedTuple):
    """A keyframe's telemetry as the mapper uses it (NaN where unknown)."""

    enu: np.ndarray  # position, ENU (m)
    q_gimbal: np.ndarray  # camera attitude, wxyz, NED
    h_acc_stated: float  # horizontal accuracy as the log states it (m)
    height: float = float("nan")  # above the take-off point (m)
    height_acc: float = float("nan")  # its accuracy (m)
    heading_known: bool = True  # False: the camera's heading is the track's (a fixed mount, no attitude in the log)
    t: float = float("nan")  # capture time (unix s, the autopilot's clock)

    @property
    def h_acc(self) -> float:
        """The position's accuracy: the log's, else UNSTATED_H_ACC_M."""
        return self.h_acc_stated if self.h_acc_stated > 0 else UNSTATED_H_ACC_M

    @classmethod
    def unknown(cls) -> "KeyframeTelemetry":
        return cls(np.full(3, np.nan), np.full(4, np.nan), float("nan"))

    def camera_pose(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """The camera's world(ENU)-to-camera pose (R, t) from this telemetry alone."""
        R = camera_rotations(self.q_gimbal[None], camera)[0]
        return R, -R @ self.enu


def frame_telemetry(flight: FlightDir, clock_offset_s: float = 0.0) -> tuple[np.ndarray, dict]:
    """Each frame's capture time and the telemetry sampled there (its flags include the capture-record flag)."""
    meta = flight.meta()
    tl = read_tlog(flight.tlog)
    t, flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, clock_offset_s)
    s = tl.at(t)
    s["flags"] = s["flags"] | flags
    return t, s


def telemetry_origin(flight: FlightDir, sample: dict) -> Origin:
    """The flight's ENU origin: its truth's if it has one, else its first GPS fix (``sample``: frame_telemetry's)."""
    if flight.has_truth:
        return flight.origin()
    ok = np.isfinite(sample["lat"])
    if not ok.any():
        raise ValueError(f"{flight.tlog}: no position telemetry at any frame")
    i = int(np.argmax(ok))
    return Origin(float(sample["lat"][i]), float(sample["lon"][i]), float(sample["alt"][i]))


def telemetry_poses(flight: FlightDir, origin: Origin | None = None, clock_offset_s: float = 0.0,
                    sample: dict | None = None):
    """(R (F, 3, 3), t (F, 3), flags (F,)) for every frame of a flight, in the ENU frame of `origin`
    (default: the flight's truth origin if any, else its first GPS fix). `sample`: the output of
    :func:`frame_telemetry`, when already read."""
    s = sample if sample is not None else frame_telemetry(flight, clock_offset_s)[1]
    origin = origin or telemetry_origin(flight, s)
    centre = origin.to_enu(s["lat"], s["lon"], s["alt"])
    R = camera_rotations(s["q_gimbal"], flight.camera())
    return R, -np.einsum("nij,nj->ni", R, centre), s["flags"]
