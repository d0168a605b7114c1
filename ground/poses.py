"""Camera poses from telemetry alone: GPS position + gimbal attitude + the camera's mount.

The fallback for frames that carry detections but do not register (or carry no image): world(ENU)-
to-camera poses whose error is the telemetry's (GPS metres, attitude fractions of a degree).
"""

from __future__ import annotations

import numpy as np

from onboard.telemetry import read_tlog
from pomar.flight import FlightDir
from pomar.geo import Origin
from pomar.rotations import camera_from_gimbal_attitude, quat_wxyz_to_rotation, world_to_camera


def telemetry_poses(flight: FlightDir, origin: Origin | None = None, clock_offset_s: float = 0.0):
    """(R (F, 3, 3), t (F, 3), flags (F,)) for every frame of a flight, in the ENU frame of `origin`
    (default: the flight's truth origin if any, else its first GPS fix)."""
    meta, cam = flight.meta(), flight.camera()
    tl = read_tlog(flight.tlog)
    t, flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, clock_offset_s)
    s = tl.at(t)
    if origin is None:
        if flight.has_truth:
            origin = flight.origin()
        else:
            ok = np.isfinite(s["lat"])
            if not ok.any():
                raise ValueError(f"{flight.tlog}: no position telemetry at any frame")
            i = int(np.argmax(ok))
            origin = Origin(float(s["lat"][i]), float(s["lon"][i]), float(s["alt"][i]))
    centre = origin.to_enu(s["lat"], s["lon"], s["alt"])
    q = np.where(np.isfinite(s["q_gimbal"]), s["q_gimbal"], [1.0, 0.0, 0.0, 0.0])
    r_enu_cam = camera_from_gimbal_attitude(quat_wxyz_to_rotation(q), cam.r_gimbal_from_camera)
    R, tt = world_to_camera(r_enu_cam, centre)
    return R, tt, flags | s["flags"]
