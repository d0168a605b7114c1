"""The size apples should have in a frame, from what the drone knows: its height above the take-off point, the
camera's angle off nadir (gimbal attitude) and the lens's focal length.

The detector works best on apples of the size it was trained on (its metadata's ``apple_radius_px``). The onboard
node rescales each frame by :func:`detector_scale` so that apples reach it at that size: a 4K frame from 12 m is
halved, which also makes it four times cheaper. The ground uses :func:`expected_radius_px` to check detections.

Geometry: the optical axis meets the canopy's middle height at range (height - canopy_mid_m) / cos(off_nadir);
an apple of radius ``apple_radius_m`` there spans fx * radius / range pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


#: Mean radius of an apple (m): 6-9 cm fruit, as the simulator's orchards and ADD256's.
APPLE_RADIUS_M = 0.0375
#: Height (m) of the canopy's middle, where most visible apples hang (trellised trees 0.8-3 m).
CANOPY_MID_M = 1.9
#: The least height above the canopy's middle (m) and the largest angle off nadir (deg) the geometry is trusted at.
MIN_RANGE_M = 2.0
MAX_OFF_NADIR_DEG = 70.0


def off_nadir_deg(q_ned_from_gimbal) -> np.ndarray:
    """Angles (deg) between the camera's optical axis (the gimbal's x axis) and straight down; NaN for NaN input."""
    q = np.atleast_2d(np.asarray(q_ned_from_gimbal, float))
    out = np.full(len(q), np.nan)
    ok = np.isfinite(q).all(1) & (np.linalg.norm(q, axis=1) > 0)
    if ok.any():
        from pomar.rotations import quat_wxyz_to_rotation  # scipy: not needed by the CLI's option parsing

        axis = quat_wxyz_to_rotation(q[ok]).apply([1.0, 0.0, 0.0])  # NED
        out[ok] = np.degrees(np.arccos(np.clip(axis[:, 2], -1.0, 1.0)))
    return out


def expected_radius_px(fx: float, height_m, off_nadir, canopy_mid_m: float = CANOPY_MID_M,
                       apple_radius_m: float = APPLE_RADIUS_M) -> np.ndarray:
    """Radius (px) of an apple where the optical axis meets the canopy; NaN where height or angle is unknown, or the
    height is less than MIN_RANGE_M above the canopy's middle (not a flight over the trees: a take-off point that is
    not the ground, say), so that such frames go at their own size rather than shrunk to nothing."""
    h = np.asarray(height_m, float)
    a = np.radians(np.minimum(np.asarray(off_nadir, float), MAX_OFF_NADIR_DEG))
    above = h - canopy_mid_m
    with np.errstate(invalid="ignore"):
        rng = np.where(above >= MIN_RANGE_M, above, np.nan) / np.cos(a)
    return fx * apple_radius_m / rng


def row_radius_px(camera, height_m: float, q_ned_from_gimbal) -> np.ndarray:
    """Per image row (at the centre column): the radius (px) of an apple where that row's ray meets the canopy's
    middle height, from the camera's intrinsics and mount, the height above take-off and the gimbal's attitude. Rows
    looking at or above the horizon get the radius of a ray 0.1 % below it (very small); NaN where the height is
    not at least MIN_RANGE_M above the canopy's middle or the attitude is unknown."""
    v = np.arange(camera.height) + 0.0
    q = np.asarray(q_ned_from_gimbal, float)
    above = float(height_m) - CANOPY_MID_M
    if not np.isfinite(q).all() or not above >= MIN_RANGE_M:
        return np.full(camera.height, np.nan)
    # OpenCV rows (centres at 0, 1, ...) against the COLMAP-convention principal point
    rays = np.stack([np.zeros_like(v), (v + 0.5 - camera.cy) / camera.fy, np.ones_like(v)], 1)  # camera frame, z = 1
    from pomar.rotations import camera_from_gimbal_attitude, quat_wxyz_to_rotation

    r_enu_from_camera = camera_from_gimbal_attitude(quat_wxyz_to_rotation(q), camera.r_gimbal_from_camera)
    down = -(rays @ r_enu_from_camera[2])  # ENU's z is up
    # a point at depth z along the optical axis spans fx * r / z pixels; the ray meets the canopy at z = above / down
    return camera.fx * APPLE_RADIUS_M * np.clip(down, 1e-3, None) / above


@dataclass
class ScalePolicy:
    """How frames are rescaled before detection: towards the model's apple size (``target_px``), within
    [min_scale, max_scale], in steps of ``step`` (so that small height wobbles keep one input size)."""

    target_px: float | None  # None: no rescaling (a model that does not say its apple size, or rescaling off)
    min_scale: float = 0.25
    max_scale: float = 2.0
    step: float = 0.05
    fixed: float | None = None  # one scale for every frame instead

    def scale(self, expected_px: float) -> float:
        if self.fixed is not None:
            return float(self.fixed)
        if self.target_px is None or not np.isfinite(expected_px) or expected_px <= 0:
            return 1.0
        s = float(np.clip(self.target_px / expected_px, self.min_scale, self.max_scale))
        return round(round(s / self.step) * self.step, 4)

    def pacer(self) -> "Pacer | None":
        """What paces this policy live: a :class:`Pacer` where it foresees scales (``auto``); a scale the user set is
        kept whatever it costs."""
        return Pacer(step=self.step) if self.fixed is None and self.target_px is not None else None


@dataclass
class Pacer:
    """Live, where the detector cannot keep the video's rate: enlarging a frame by s costs about s² in time, and a
    frame not taken in time is dropped. A scale above 1 is kept only as far as a frame's detection still fits in the
    video's frame period (from the detector's time per input pixel on the frames so far, smoothed); a scale of 1 or
    less is kept as it is (cheaper, and below 1 the apples are larger than the model's). Before the first frame's
    time: at most 1. A fast detector gets the scale the policy asked; a slow one, frames at their own size, more of
    them."""

    smoothing: float = 0.3  # weight of the newest frame in the time per pixel
    step: float = 0.05
    seconds_per_px: float = float("nan")
    capped: int = 0  # frames detected at a smaller scale than the policy asked

    def cap(self, scale: float, width: int, height: int, period_s: float) -> float:
        if scale <= 1.0:
            return scale
        if not np.isfinite(self.seconds_per_px) or not period_s > 0:
            fit = 1.0
        else:
            fit = np.sqrt(period_s / (self.seconds_per_px * width * height))
            fit = max(1.0, np.floor(fit / self.step + 1e-9) * self.step)
        if fit < scale:
            self.capped += 1
            return round(float(fit), 4)
        return scale

    def observe(self, seconds: float, width: int, height: int, scale: float) -> None:
        """A frame's detection time, at the scale it was detected at."""
        per_px = seconds / max(width * height * scale * scale, 1.0)
        a = self.smoothing
        old = self.seconds_per_px
        self.seconds_per_px = per_px if not np.isfinite(old) else (1 - a) * old + a * per_px


def parse_scale(value: str) -> tuple[str, float | None]:
    """A ``--detector-scale`` value: ``auto``, ``off`` or a number -> (mode, fixed scale)."""
    v = str(value).strip().lower()
    if v in ("auto", "off"):
        return v, None
    try:
        s = float(v)
    except ValueError:
        raise ValueError(f"detector scale must be 'auto', 'off' or a number, got {value!r}") from None
    if not 0.05 <= s <= 8.0:
        raise ValueError(f"detector scale {s} is outside 0.05-8")
    return "fixed", s


def telemetry_radius_px(fx: float, tel: dict) -> np.ndarray:
    """:func:`expected_radius_px` of telemetry samples (``TelemetryLog.at``'s dict: height, q_gimbal)."""
    return expected_radius_px(fx, tel["height"], off_nadir_deg(tel["q_gimbal"]))


def held_radius_px(radius: np.ndarray) -> np.ndarray:
    """Foreseen apple radii per frame, a frame without one (past the log's end, in a gap of its heights) given the
    last one before it (else the first after it): the drone's height does not jump between two frames, and a frame at
    its own size would reach the detector at another scale than its neighbours."""
    r = np.asarray(radius, float).copy()
    ok = np.isfinite(r)
    if ok.all() or not ok.any():
        return r
    idx = np.where(ok, np.arange(len(r)), -1)
    last = np.maximum.accumulate(idx)  # the last finite index at or before each frame
    first = np.nonzero(ok)[0][0]
    return r[np.where(last >= 0, last, first)]


def envelope_height_m(fx: float, off_nadir: float, min_px: float, max_scale: float,
                      canopy_mid_m: float = CANOPY_MID_M, apple_radius_m: float = APPLE_RADIUS_M) -> float:
    """The highest flight (m above take-off) at which apples still reach a detector at ``min_px`` (the smallest radius
    it finds reliably), frames enlarged by at most ``max_scale``: the top of the detector's envelope."""
    a = np.radians(min(float(off_nadir), MAX_OFF_NADIR_DEG))
    return float(canopy_mid_m + fx * max_scale * apple_radius_m / min_px * np.cos(a))


def flight_telemetry(flight) -> dict[str, np.ndarray]:
    """Per frame of a flight directory (pomar.flight.FlightDir): its telemetry (``TelemetryLog.at``'s dict)."""
    from pomar.telemetry import read_log

    meta = flight.meta()
    tl = read_log(flight.telemetry_log)
    t, _ = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, 0.0)
    return tl.at(t)


def flight_radius_px(flight) -> np.ndarray:
    """Per frame of a flight directory (pomar.flight.FlightDir): the apple radius (px) foreseen from its telemetry."""
    return telemetry_radius_px(flight.camera().fx, flight_telemetry(flight))


def policy_for(detector, setting: str = "auto") -> ScalePolicy:
    """The scale policy of a ``--detector-scale`` setting for a detector (its ``apple_radius_px``)."""
    mode, fixed = parse_scale(setting)
    if mode == "fixed":
        return ScalePolicy(None, fixed=fixed)
    target = getattr(detector, "apple_radius_px", None) if mode == "auto" else None
    return ScalePolicy(float(target) if target else None)


def scale_summary(scales) -> dict | None:
    """Median and range of the scales frames were detected at (a run's summary)."""
    if not len(scales):
        return None
    a = np.asarray(scales, float)
    return {"median": float(np.median(a)), "min": float(a.min()), "max": float(a.max())}


SCALE_HELP = ("auto (default): resize each frame so that apples reach the model at the size it was trained on, "
              "foreseen from the height above take-off, the camera's tilt and its focal length (pomar/apple_scale.py); "
              "live, enlarged only as far as the node keeps the video's rate; off: native size; or one factor for "
              "every frame")


def scale_argument(value: str) -> str:
    """argparse type of ``--detector-scale``."""
    import argparse

    try:
        parse_scale(value)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return value
