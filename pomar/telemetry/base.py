"""The telemetry interface every reader fills: time series on one clock, sampled at each frame's capture time.

A reader (``.tlog``, DataFlash ``.bin``, PX4 ``.ulg``, DJI ``.SRT``) returns a :class:`TelemetryLog`:

- position: lat, lon (degrees), alt (m; MSL, or above take-off where ``altitude_reference`` says so);
- gps: fix type, horizontal and vertical accuracy (m), satellites;
- attitude: the vehicle's, quaternion wxyz, NED from body;
- gimbal: the camera's, quaternion wxyz, NED from gimbal (yaw in the earth frame);
- captures: frame index -> capture time, from the log's camera events.

Every series is on one clock, unix seconds as the autopilot (or camera) knew them; ``clock`` says how that
clock was found. What a reader could not read, and why, is in ``problems``. Sampling at a frame time
interpolates position linearly and rotations by slerp; a frame that falls in a gap of a stream (its
neighbouring samples further apart than the stream's own rate allows, see :func:`gap_limit`) or outside it
is flagged, not silently interpolated across: see :class:`Flags`.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from dataclasses import dataclass, field
from enum import IntFlag

import numpy as np
from scipy.spatial.transform import Slerp

from pomar.cli import InputError
from pomar.rotations import ned_euler_to_rotation, quat_wxyz_to_rotation, rotation_to_quat_wxyz


class Flags(IntFlag):
    """Quality flags of one frame's telemetry sample (0 = all good)."""

    POSITION_GAP = 1  # the frame falls in a gap of the position stream
    ATTITUDE_GAP = 2
    GIMBAL_GAP = 4
    NO_POSITION = 8  # no position sample around the frame (before the first or after the last)
    NO_ATTITUDE = 16
    NO_GIMBAL = 32  # no gimbal attitude around the frame (or none in the log)
    NO_CAPTURE_RECORD = 64  # the frame time comes from the video clock, not a camera event of the log
    NO_GPS_FIX = 128  # GPS fix type below 3D at the frame, or no GPS report around it
    FIXED_MOUNT = 256  # the camera's attitude is the vehicle's plus a fixed mount tilt, not a gimbal report
    POSITION_JUMP = 512  # the frame lies between two positions further apart than a drone can fly: no position

    @classmethod
    def incomplete(cls) -> int:
        """The flags that leave a frame short of what its map pose needs from telemetry: a position, the camera's
        attitude (gimbal or fixed mount) and a GPS fix. The vehicle's attitude and a capture record are not."""
        return int(cls.POSITION_GAP | cls.NO_POSITION | cls.POSITION_JUMP | cls.GIMBAL_GAP | cls.NO_GIMBAL
                   | cls.NO_GPS_FIX)


#: Faster than any multirotor flies (the DJI FPV's top speed is 39 m/s): two positions further apart than this
#: speed allows, plus JUMP_FLOOR_M, are a jump (a cut-off number, two flights in one file), not a flight.
MAX_SPEED_MPS = 45.0
#: Beyond GNSS wander and the rounding of positions written to 5 decimals (1.1 m), even between 50-Hz samples.
JUMP_FLOOR_M = 10.0
#: The span (s) of positions a track's heading is taken over, at least: at a survey's 2-5 m/s, 4-10 m of track against
#: positions off by a metre (a DJI log's 5 decimals, GNSS wander), so a few degrees rather than any direction.
TRACK_HEADING_S = 2.0
#: The horizontal accuracy (m) taken for a position whose log states none (DJI's do not); the ground weighs such
#: positions by it. A position rounded to D decimals is off by (111 km x 10^-D) / sqrt(12) besides.
UNSTATED_H_ACC_M = 2.0
#: The accuracy (m) taken for a height above take-off whose log states none (a tlog's EKF height may come from the
#: GPS's vertical as well as from a barometer): a GPS's vertical error, so that such heights scale the map only where
#: the positions know it worse (ground.poses.scale).
UNSTATED_HEIGHT_ACC_M = 1.5
#: The accuracy (m) of a barometer's height above take-off: its drift over a flight's minutes. A DJI's height (the
#: SRT's) and an autopilot's EKF height where its parameters say it is the barometer's (:func:`height_source`).
BARO_HEIGHT_SIGMA_M = 0.1
#: Where an autopilot's EKF takes its height from, by the parameter that says it: parameter -> {value: source}.
#: ArduPilot's EKF3 and EKF2 (the one AHRS_EKF_TYPE names; EKF3 where it names none), PX4's EKF2 (HGT_REF since 1.14,
#: HGT_MODE before). Heights from a rangefinder or vision are not above the take-off point: not a source here.
HEIGHT_SOURCE_PARAMS = {
    "EK3_SRC1_POSZ": {1: "baro", 2: "rangefinder", 3: "gps", 4: "beacon", 6: "external"},
    "EK2_ALT_SOURCE": {0: "baro", 1: "rangefinder", 2: "gps", 3: "beacon"},
    "EKF2_HGT_REF": {0: "baro", 1: "gps", 2: "rangefinder", 3: "vision"},
    "EKF2_HGT_MODE": {0: "baro", 1: "gps", 2: "rangefinder", 3: "vision"},
}


def height_source(params: dict) -> tuple[str, str] | None:
    """(source, the parameter that says it, as "NAME = value") of an autopilot's EKF height, from the log's parameters
    (name -> value); None where none of HEIGHT_SOURCE_PARAMS is there."""
    ardupilot = ["EK3_SRC1_POSZ", "EK2_ALT_SOURCE"]
    if params.get("AHRS_EKF_TYPE") == 2:  # EKF2 is the one running
        ardupilot.reverse()
    for name in ardupilot + ["EKF2_HGT_REF", "EKF2_HGT_MODE"]:
        if name in params and params[name] is not None and np.isfinite(float(params[name])):
            value = int(round(float(params[name])))
            return HEIGHT_SOURCE_PARAMS[name].get(value, "other"), f"{name} = {value}"
    return None


def height_source_param(source: str, autopilot: str) -> tuple[str, int]:
    """The parameter (name, value) by which an autopilot ("ardupilot" or "px4") says its EKF takes its height from
    ``source``: what a log of it carries (the simulator writes it)."""
    name = {"ardupilot": "EK3_SRC1_POSZ", "px4": "EKF2_HGT_REF"}[autopilot]
    return name, next(v for v, s in HEIGHT_SOURCE_PARAMS[name].items() if s == source)


def height_sigma(source: str | None, v_acc) -> float | None:
    """The accuracy (m) of an autopilot's height above take-off from its EKF's height source: a barometer's
    BARO_HEIGHT_SIGMA_M; the GPS's stated vertical accuracy (median of ``v_acc``, metres; 0 or NaN: none stated);
    None (unstated) otherwise."""
    if source == "baro":
        return BARO_HEIGHT_SIGMA_M
    if source == "gps":
        v = np.asarray(v_acc, float).ravel()
        v = v[np.isfinite(v) & (v > 0)]
        return float(np.median(v)) if len(v) else None
    return None


def height_fields(params: dict, v_acc) -> dict:
    """TelemetryLog's ``height_sigma_m`` and ``height_from`` for an autopilot's log, from its parameters (name ->
    value) and its receiver's stated vertical accuracies (m): both None where the parameters do not say."""
    src = height_source(params)
    if src is None:
        return {"height_sigma_m": None, "height_from": None}
    return {"height_sigma_m": height_sigma(src[0], v_acc), "height_from": ", ".join(src)}


class TelemetryError(InputError, ValueError):
    """A telemetry file is missing, unreadable, or holds nothing usable."""


@dataclass
class Series:
    t: np.ndarray  # unix seconds, on the log's one clock
    values: np.ndarray  # (n, d)

    def __len__(self):
        return len(self.t)

    @classmethod
    def empty(cls, d: int) -> "Series":
        return cls(np.zeros(0), np.zeros((0, d)))

    @classmethod
    def of(cls, t, values, d: int) -> "Series":
        """Sorted by time, repeated times dropped (autopilots resend); empty when there is nothing."""
        t = np.asarray(t, float)
        if not len(t):
            return cls.empty(d)
        return cls(*strictly_increasing(t, np.asarray(values, float).reshape(len(t), d)))


@dataclass
class Gap:
    stream: str
    start: float
    end: float

    @property
    def seconds(self) -> float:
        return self.end - self.start


@dataclass
class TelemetryLog:
    path: str
    position: Series  # lat, lon, alt
    gps: Series  # fix_type, h_acc (m), v_acc (m), satellites
    attitude: Series  # quaternion wxyz, NED from body
    gimbal: Series  # quaternion wxyz, NED from gimbal (yaw in the earth frame)
    captures: dict[int, float]  # frame index -> capture time (unix s, the log's clock)
    capture_message: str | None
    clock: str  # how the log's times were put on one clock
    boot_to_unix: float | None
    counts: Counter
    bad_packets: int = 0
    truncated_bytes: int = 0
    max_gap_s: float = 1.0  # the least gap flagged; a slower stream's own limit is larger (gap_limit)
    gaps: list[Gap] = field(default_factory=list)
    parse_seconds: float = 0.0
    format: str = "tlog"
    altitude_reference: str = "msl"  # "msl", "ellipsoid", "takeoff", or "unstated"/"unknown" (SRTs that do not say)
    problems: list[str] = field(default_factory=list)
    bad_by_type: Counter = field(default_factory=Counter)
    #: Per-frame video times from the log itself (a DJI .SRT has one entry per frame or per second): seconds
    #: from the video's start -> unix time. Empty for logs that know nothing of the video.
    video_clock: Series = field(default_factory=lambda: Series.empty(1))
    #: The take-off (home) point's altitude in ``alt``'s reference, where the log says it (a relative altitude
    #: beside the absolute one): the height above the ground is alt - home_alt. None where the log does not say.
    home_alt: float | None = None
    #: The accuracy (m) of the height above take-off where the log states it or its source is known (a DJI
    #: barometer's, an autopilot's EKF height by its parameters); None: unstated.
    height_sigma_m: float | None = None
    #: Where the height above take-off comes from and what says so ("baro, EK3_SRC1_POSZ = 1"); None: not said.
    height_from: str | None = None
    #: Steps of the position stream further than a drone can fly (see MAX_SPEED_MPS): (start, end) times.
    jumps: list[Gap] = field(default_factory=list)

    def __post_init__(self):
        if self.home_alt is None and self.altitude_reference == "takeoff":
            self.home_alt = 0.0
        self.find_gaps()
        self.find_jumps()

    def find_jumps(self) -> None:
        """Steps of the position stream no drone can fly: a named problem each, and the frames between their two
        positions get none (flagged POSITION_JUMP) rather than a point on a line between two places."""
        self.jumps = []
        p = self.position
        if len(p) < 2:
            return
        step = step_m(p.values)
        limit = MAX_SPEED_MPS * np.diff(p.t) + JUMP_FLOOR_M
        for i in np.nonzero(step > limit)[0]:
            self.jumps.append(Gap("position", float(p.t[i]), float(p.t[i + 1])))
            if len(self.jumps) <= 3:
                self.problems.append(
                    f"the position jumps {step[i]:.0f} m in {p.t[i + 1] - p.t[i]:.3f} s (from {p.values[i, 0]:.6f}, "
                    f"{p.values[i, 1]:.6f} to {p.values[i + 1, 0]:.6f}, {p.values[i + 1, 1]:.6f}), faster than a "
                    f"drone flies: frames between them are flagged POSITION_JUMP and get no position")
        if len(self.jumps) > 3:
            self.problems.append(f"{len(self.jumps)} position jumps in all (the first 3 above)")

    def height_above_home(self, alt) -> np.ndarray:
        """Heights (m) above the take-off point of altitudes in this log's reference; NaN where home is unknown."""
        a = np.asarray(alt, float)
        return a - self.home_alt if self.home_alt is not None else np.full_like(a, np.nan)

    def find_gaps(self) -> None:
        self.gaps = []
        for name, s in (("position", self.position), ("attitude", self.attitude), ("gimbal", self.gimbal)):
            self.gaps += stream_gaps(name, s.t, gap_limit(s.t, self.max_gap_s))

    def summary(self) -> str:
        lines = [f"{self.path}: {self.format}, {sum(self.counts.values())} messages read in {self.parse_seconds:.2f} s; "
                 f"clock {self.clock}; altitude {self.altitude_reference}"]
        if self.height_from:
            sigma = f"{self.height_sigma_m:.2f} m" if self.height_sigma_m is not None else "accuracy unstated"
            lines.append(f"  height above take-off: {self.height_from} ({sigma})")
        for name, s in (("position", self.position), ("gps", self.gps), ("attitude", self.attitude), ("gimbal", self.gimbal)):
            rate = (len(s) - 1) / (s.t[-1] - s.t[0]) if len(s) > 1 and s.t[-1] > s.t[0] else 0.0
            lines.append(f"  {name:<9} {len(s):>6} samples" + (f", {rate:5.1f} Hz" if len(s) > 1 else ""))
        lines.append(f"  captures  {len(self.captures):>6} ({self.capture_message or 'none'})")
        if self.bad_packets or self.truncated_bytes:
            by = ", ".join(f"{k} {v}" for k, v in self.bad_by_type.most_common(6))
            lines.append(f"  {self.bad_packets} bad packets skipped ({by}), {self.truncated_bytes} bytes of a cut-off "
                         "record at the end")
        for g in self.gaps:
            lines.append(f"  gap in {g.stream}: {g.seconds:.1f} s from {g.start:.3f} to {g.end:.3f}")
        for p in self.problems:
            lines.append(f"  problem: {p}")
        return "\n".join(lines)

    def summary_dict(self) -> dict:
        """What ``onboard telemetry LOG --json`` writes."""
        pos = self.position
        ok = np.isfinite(pos.values[:, :2]).all(1) if len(pos) else np.zeros(0, bool)
        span = [float(min(s.t[0] for s in self._streams())), float(max(s.t[-1] for s in self._streams()))] \
            if self._streams() else None
        return {
            "path": self.path, "format": self.format, "clock": self.clock, "altitude_reference": self.altitude_reference,
            "home_alt": self.home_alt, "height_from": self.height_from, "height_sigma_m": self.height_sigma_m,
            "positions": int(len(pos)),
            "lat_range": [float(pos.values[ok, 0].min()), float(pos.values[ok, 0].max())] if ok.any() else None,
            "lon_range": [float(pos.values[ok, 1].min()), float(pos.values[ok, 1].max())] if ok.any() else None,
            "start_unix": span[0] if span else None, "span_s": span[1] - span[0] if span else 0.0,
            "attitudes": int(len(self.attitude)), "gimbal_attitudes": int(len(self.gimbal)),
            "gps_reports": int(len(self.gps)),
            "camera_events": int(len(self.captures)), "camera_event_message": self.capture_message,
            "max_jump_m": max_jump_m(pos),
            "gaps": [{"stream": g.stream, "start": g.start, "seconds": g.seconds} for g in self.gaps],
            "position_jumps": [{"start": g.start, "seconds": g.seconds} for g in self.jumps],
            "bad_packets": int(self.bad_packets), "bad_packets_by_type": dict(self.bad_by_type),
            "truncated_bytes": int(self.truncated_bytes),
            "messages": dict(self.counts.most_common()),
            "problems": list(self.problems),
        }

    def _streams(self) -> list[Series]:
        return [s for s in (self.position, self.attitude, self.gimbal, self.gps) if len(s)]

    # -- frame times and samples
    @staticmethod
    def log_clock(t_camera, clock_offset_s: float = 0.0):
        """A time of the camera's clock (the video's, or the companion computer's that reads the camera) on the log's:
        ``clock_offset_s`` is the camera's clock minus the log's. The one place the offset's sign is written."""
        return t_camera - clock_offset_s

    def frame_times(self, n_frames: int, video_start_unix: float, fps: float, clock_offset_s: float = 0.0):
        """Capture time (the log's clock) of each frame: the camera event when there is one, else the log's own
        video clock (a DJI .SRT), else the video clock corrected by clock_offset_s (camera clock minus the log's).
        Returns (t, flags)."""
        t = self.log_clock(video_start_unix, clock_offset_s) + np.arange(n_frames) / fps
        flags = np.full(n_frames, int(Flags.NO_CAPTURE_RECORD), np.int64)
        if len(self.video_clock) >= 2:
            t = self.log_time_of_video(np.arange(n_frames) / fps)
            flags[:] = 0
        for i, tc in self.captures.items():
            if 0 <= i < n_frames:
                t[i] = tc
                flags[i] = 0
        return t, flags

    def log_time_of_video(self, video_s) -> np.ndarray:
        """The log's time of moments in the video (seconds from its start), by the log's own video clock (a DJI
        .SRT): interpolated between its entries and carried on at the video's rate past either end (a video longer
        than its log, a first subtitle after the start), so that those frames fall outside the log, not on its
        ends."""
        v = np.asarray(video_s, float)
        vt, lt = self.video_clock.t, self.video_clock.values[:, 0]
        out = np.interp(v, vt, lt)
        out = np.where(v < vt[0], lt[0] + (v - vt[0]), out)
        return np.where(v > vt[-1], lt[-1] + (v - vt[-1]), out)

    def at(self, t: np.ndarray, mount_tilt_deg: float | None = None,
           mount_yaw_deg: float = 0.0) -> dict[str, np.ndarray]:
        """Telemetry at times t (unix s, the log's clock): lat, lon, alt, height (above home; NaN where the log does
        not place home), height_acc (its accuracy, where the log states it), q_attitude, q_gimbal (wxyz), gps_fix,
        h_acc, flags. Values outside a stream are NaN; frames in a gap are interpolated and flagged.

        A log without gimbal attitudes gives the camera's attitude only with ``mount_tilt_deg`` (the camera's
        pitch below the vehicle's horizon, 90 = straight down) and ``mount_yaw_deg`` (the camera's heading from the
        vehicle's nose, or from the track where the log has no vehicle attitude; 90 = looking right): the vehicle's
        attitude turned by them, or, without vehicle attitudes either (most DJI .SRTs), the track's heading, level,
        turned by them; those frames are flagged FIXED_MOUNT."""
        t = np.atleast_1d(np.asarray(t, float))
        flags = np.zeros(len(t), np.int64)
        out: dict[str, np.ndarray] = {}
        pos = self._linear(self.position, t, flags, Flags.POSITION_GAP, Flags.NO_POSITION)
        for j in self.jumps:  # between two positions no drone could join: no position
            inside = (t > j.start) & (t < j.end)
            pos[inside] = np.nan
            flags[inside] |= int(Flags.POSITION_JUMP)
        out["lat"], out["lon"], out["alt"] = pos[:, 0], pos[:, 1], pos[:, 2]
        out["height"] = self.height_above_home(out["alt"])
        out["height_acc"] = np.where(np.isfinite(out["height"]), self.height_sigma_m or np.nan, np.nan)
        out["q_attitude"] = self._slerp(self.attitude, t, flags, Flags.ATTITUDE_GAP, Flags.NO_ATTITUDE)
        out["q_gimbal"] = self._slerp(self.gimbal, t, flags, Flags.GIMBAL_GAP, Flags.NO_GIMBAL)
        out["gps_fix"] = np.zeros(len(t), int)
        out["h_acc"] = np.full(len(t), np.nan)
        if len(self.gps):
            # the last report before each time, within the GPS stream's own gap limit (a stream that stopped is
            # not repeated for the rest of the flight)
            i = np.searchsorted(self.gps.t, t, side="right") - 1
            near = (i >= 0) & (t - self.gps.t[np.clip(i, 0, None)] <= gap_limit(self.gps.t, self.max_gap_s))
            out["gps_fix"][near] = self.gps.values[i[near], 0].astype(int)
            out["h_acc"][near] = self.gps.values[i[near], 1]
        flags |= np.where(out["gps_fix"] < 3, int(Flags.NO_GPS_FIX), 0)
        if not len(self.gimbal) and mount_tilt_deg is not None:
            out["q_gimbal"] = self._fixed_mount(t, out, float(mount_tilt_deg), float(mount_yaw_deg or 0.0))
            ok = np.isfinite(out["q_gimbal"]).all(1)
            flags[ok] = (flags[ok] & ~int(Flags.NO_GIMBAL)) | int(Flags.FIXED_MOUNT)
        out["flags"] = flags
        return out

    def _fixed_mount(self, t, out, tilt_deg: float, yaw_deg: float = 0.0) -> np.ndarray:
        # the camera turned yaw_deg right, then pitched tilt_deg down, in the vehicle's (or the track's) frame
        mount = ned_euler_to_rotation(0.0, -tilt_deg, yaw_deg)
        if len(self.attitude):
            q = out["q_attitude"]
            ok = np.isfinite(q).all(1)
            res = np.full_like(q, np.nan)
            if ok.any():
                res[ok] = rotation_to_quat_wxyz(quat_wxyz_to_rotation(q[ok]) * mount)
            return res
        # no attitude at all: the heading of the track (north, east from the positions around each time), over
        # TRACK_HEADING_S at least: neighbouring positions rounded to 5 decimals (1.1 m) at 10 Hz point anywhere
        p = self.position
        if len(p) < 2:
            return np.full((len(t), 4), np.nan)
        dt = 0.5 * max(gap_limit(p.t, 0.0), TRACK_HEADING_S)
        a, b = self._linear(p, t - dt, np.zeros(len(t), np.int64), 0, 0), self._linear(p, t + dt, np.zeros(len(t), np.int64), 0, 0)
        a = np.where(np.isfinite(a), a, np.column_stack([out["lat"], out["lon"], out["alt"]]))
        b = np.where(np.isfinite(b), b, np.column_stack([out["lat"], out["lon"], out["alt"]]))
        north, east = b[:, 0] - a[:, 0], (b[:, 1] - a[:, 1]) * np.cos(np.radians(out["lat"]))
        yaw = np.arctan2(east, north)
        # standing still (or positions that did not change): no heading there; the nearest moving time's, or north
        # where the log never moves (the tilt still holds; the ground takes only the tilt from a track's heading)
        still = ~(np.hypot(north, east) > 0)
        if still.all():
            yaw[:] = 0.0
        elif still.any():
            # the nearest moving time (O(n log n): a long hover at 30 fps is tens of thousands of frames)
            order = np.argsort(t[~still], kind="stable")
            tm, ym, ts = t[~still][order], yaw[~still][order], t[still]
            j = np.clip(np.searchsorted(tm, ts), 1, len(tm) - 1) if len(tm) > 1 else np.zeros(len(ts), int)
            lo = np.maximum(j - 1, 0)
            yaw[still] = ym[np.where(np.abs(ts - tm[lo]) <= np.abs(tm[j] - ts), lo, j)]
        res = np.full((len(t), 4), np.nan)
        ok = np.isfinite(yaw)
        if ok.any():
            zero = np.zeros(int(ok.sum()))
            res[ok] = rotation_to_quat_wxyz(ned_euler_to_rotation(zero, zero, yaw[ok], degrees=False) * mount)
        return res

    def _bracket(self, s: Series, t, flags, gap_flag, none_flag):
        """Index of the sample before each t, and a mask of the t inside the stream; flags gaps and outsides."""
        if len(s) == 0:
            flags |= int(none_flag)
            return None, np.zeros(len(t), bool)
        inside = (t >= s.t[0]) & (t <= s.t[-1])
        flags |= np.where(inside, 0, int(none_flag))
        i = np.clip(np.searchsorted(s.t, t, side="right") - 1, 0, max(len(s) - 2, 0))
        if len(s) > 1:
            span = s.t[i + 1] - s.t[i]
            flags |= np.where(inside & (span > gap_limit(s.t, self.max_gap_s)), int(gap_flag), 0)
        return i, inside

    def _linear(self, s: Series, t, flags, gap_flag, none_flag):
        i, inside = self._bracket(s, t, flags, gap_flag, none_flag)
        out = np.full((len(t), 3), np.nan)
        if i is not None and inside.any():
            for k in range(3):
                out[inside, k] = np.interp(t[inside], s.t, s.values[:, k])
        return out

    def _slerp(self, s: Series, t, flags, gap_flag, none_flag):
        i, inside = self._bracket(s, t, flags, gap_flag, none_flag)
        out = np.full((len(t), 4), np.nan)
        if i is None or not inside.any():
            return out
        if len(s) == 1:
            out[inside] = s.values[0]
            return out
        rots = quat_wxyz_to_rotation(s.values)
        out[inside] = rotation_to_quat_wxyz(Slerp(s.t, rots)(t[inside]))
        return out


def existing(path) -> Path:
    """The log's path, or TelemetryError naming it when there is no such file (or it is a folder)."""
    path = Path(path)
    if path.is_dir():
        raise TelemetryError(f"{path}: is a folder, not a log file (give the log inside it)")
    if not path.is_file():
        raise TelemetryError(f"{path}: file not found")
    return path


def strictly_increasing(t: np.ndarray, values: np.ndarray):
    """Sort by time and drop repeated timestamps (autopilots resend)."""
    order = np.argsort(t, kind="stable")
    t, values = t[order], values[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
    return t[keep], values[keep]


def gap_limit(t: np.ndarray, least_s: float = 1.0) -> float:
    """The longest step a stream may take without a gap: 2.5 times its median step, and at least ``least_s`` (a
    1-Hz stream is not a gap at every sample)."""
    if len(t) < 3:
        return least_s
    return max(least_s, 2.5 * float(np.median(np.diff(t))))


def stream_gaps(name: str, t: np.ndarray, limit_s: float) -> list[Gap]:
    if len(t) < 2:
        return []
    d = np.diff(t)
    return [Gap(name, float(t[i]), float(t[i + 1])) for i in np.nonzero(d > limit_s)[0]]


def step_m(latlon: np.ndarray) -> np.ndarray:
    """Horizontal steps (m) between consecutive positions (lat, lon in degrees), on a local flat earth."""
    v = np.asarray(latlon, float)
    dn = np.diff(v[:, 0]) * 111_320.0
    de = np.diff(v[:, 1]) * 111_320.0 * np.cos(np.radians(v[1:, 0]))
    return np.hypot(dn, de)


def max_jump_m(position: Series) -> float | None:
    """The largest horizontal step between consecutive positions (m), on a local flat earth."""
    v = position.values
    ok = np.isfinite(v[:, :2]).all(1) if len(v) else np.zeros(0, bool)
    v = v[ok]
    if len(v) < 2:
        return None
    return float(step_m(v).max())
