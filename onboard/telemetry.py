"""MAVLink telemetry (a .tlog, or later a live link) as time series, sampled at each frame's capture time.

What it reads, as real autopilots send it:

- time: ``SYSTEM_TIME`` maps the autopilot's ``time_boot_ms`` to UTC (the median over the log); without
  it, the .tlog's own record timestamps (the ground station's clock) are used and the log says so.
- position: ``GLOBAL_POSITION_INT`` (lat, lon, alt MSL), ``GPS_RAW_INT`` (fix type, accuracy).
- vehicle attitude: ``ATTITUDE`` (roll, pitch, yaw in NED).
- gimbal attitude: ``GIMBAL_DEVICE_ATTITUDE_STATUS`` (quaternion; yaw in the vehicle frame is turned into
  the earth frame with the vehicle's yaw, following the flags), or ArduPilot's older ``MOUNT_STATUS``.
- per-frame capture records: ``CAMERA_FEEDBACK`` (ArduPilot, ``img_idx``), ``CAMERA_TRIGGER`` (PX4,
  ``seq``), ``CAMERA_IMAGE_CAPTURED`` (``image_index``), each with the capture time on the autopilot clock.

Sampling at a frame time interpolates position linearly and rotations by slerp. A frame that falls in
a gap of a stream (its neighbouring samples more than ``max_gap_s`` apart) or outside it is flagged,
not silently interpolated across: see :class:`Flags`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from enum import IntFlag
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from pomar.rotations import ned_euler_to_rotation, quat_wxyz_to_rotation, rotation_to_quat_wxyz

log = logging.getLogger(__name__)


class Flags(IntFlag):
    """Quality flags of one frame's telemetry sample (0 = all good)."""

    POSITION_GAP = 1  # the frame falls in a gap of the position stream
    ATTITUDE_GAP = 2
    GIMBAL_GAP = 4
    NO_POSITION = 8  # no position sample around the frame (before the first or after the last)
    NO_ATTITUDE = 16
    NO_GIMBAL = 32  # no gimbal attitude around the frame (or none in the log)
    NO_CAPTURE_RECORD = 64  # the frame time comes from the video clock, not an autopilot capture record
    NO_GPS_FIX = 128  # GPS fix type below 3D at the frame


class TelemetryError(ValueError):
    """A telemetry file is missing or holds no usable MAVLink."""


@dataclass
class Series:
    t: np.ndarray  # unix seconds, autopilot clock
    values: np.ndarray  # (n, d)

    def __len__(self):
        return len(self.t)


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
    position: Series  # lat, lon, alt (MSL, m)
    gps: Series  # fix_type, h_acc (m), v_acc (m), satellites
    attitude: Series  # quaternion wxyz, NED from body
    gimbal: Series  # quaternion wxyz, NED from gimbal (yaw in the earth frame)
    captures: dict[int, float]  # frame index -> capture time (unix s, autopilot clock)
    capture_message: str | None
    clock: str  # "SYSTEM_TIME" or "tlog"
    boot_to_unix: float | None
    counts: Counter
    bad_packets: int
    truncated_bytes: int
    max_gap_s: float = 1.0
    gaps: list[Gap] = field(default_factory=list)
    parse_seconds: float = 0.0

    def summary(self) -> str:
        lines = [f"{self.path}: {sum(self.counts.values())} MAVLink messages read in {self.parse_seconds:.2f} s "
                 f"({sum(self.counts.values()) / max(self.parse_seconds, 1e-9):,.0f} msg/s); clock {self.clock}"]
        for name, s in (("position", self.position), ("gps", self.gps), ("attitude", self.attitude), ("gimbal", self.gimbal)):
            rate = (len(s) - 1) / (s.t[-1] - s.t[0]) if len(s) > 1 and s.t[-1] > s.t[0] else 0.0
            lines.append(f"  {name:<9} {len(s):>6} samples" + (f", {rate:5.1f} Hz" if len(s) > 1 else ""))
        lines.append(f"  captures  {len(self.captures):>6} ({self.capture_message or 'none'})")
        if self.bad_packets or self.truncated_bytes:
            lines.append(f"  {self.bad_packets} bad packets skipped, {self.truncated_bytes} bytes of a cut-off packet at the end")
        for g in self.gaps:
            lines.append(f"  gap in {g.stream}: {g.seconds:.1f} s from {g.start:.3f} to {g.end:.3f}")
        return "\n".join(lines)

    # -- frame times and samples
    def frame_times(self, n_frames: int, video_start_unix: float, fps: float, clock_offset_s: float = 0.0):
        """Capture time (autopilot clock) of each frame: the capture record when there is one, else the
        video clock corrected by clock_offset_s (camera clock minus autopilot clock). Returns (t, flags)."""
        t = video_start_unix - clock_offset_s + np.arange(n_frames) / fps
        flags = np.full(n_frames, int(Flags.NO_CAPTURE_RECORD), np.int64)
        for i, tc in self.captures.items():
            if 0 <= i < n_frames:
                t[i] = tc
                flags[i] = 0
        return t, flags

    def at(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """Telemetry at times t (unix s, autopilot clock): lat, lon, alt, q_attitude, q_gimbal (wxyz), gps_fix,
        h_acc, flags. Values outside a stream are NaN; frames in a gap are interpolated and flagged."""
        t = np.atleast_1d(np.asarray(t, float))
        flags = np.zeros(len(t), np.int64)
        out: dict[str, np.ndarray] = {}
        pos = self._linear(self.position, t, flags, Flags.POSITION_GAP, Flags.NO_POSITION)
        out["lat"], out["lon"], out["alt"] = pos[:, 0], pos[:, 1], pos[:, 2]
        out["q_attitude"] = self._slerp(self.attitude, t, flags, Flags.ATTITUDE_GAP, Flags.NO_ATTITUDE)
        out["q_gimbal"] = self._slerp(self.gimbal, t, flags, Flags.GIMBAL_GAP, Flags.NO_GIMBAL)
        if len(self.gps):
            i = np.clip(np.searchsorted(self.gps.t, t, side="right") - 1, 0, len(self.gps) - 1)
            out["gps_fix"] = self.gps.values[i, 0].astype(int)
            out["h_acc"] = self.gps.values[i, 1]
            flags |= np.where(out["gps_fix"] < 3, int(Flags.NO_GPS_FIX), 0)
        else:
            out["gps_fix"] = np.zeros(len(t), int)
            out["h_acc"] = np.full(len(t), np.nan)
        out["flags"] = flags
        return out

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
            flags |= np.where(inside & (span > self.max_gap_s), int(gap_flag), 0)
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


def _strictly_increasing(t: np.ndarray, values: np.ndarray):
    """Sort by time and drop repeated timestamps (autopilots resend)."""
    order = np.argsort(t, kind="stable")
    t, values = t[order], values[order]
    keep = np.concatenate([[True], np.diff(t) > 0]) if len(t) else np.zeros(0, bool)
    return t[keep], values[keep]


def _gaps(name: str, t: np.ndarray, max_gap_s: float) -> list[Gap]:
    if len(t) < 2:
        return []
    d = np.diff(t)
    return [Gap(name, float(t[i]), float(t[i + 1])) for i in np.nonzero(d > max_gap_s)[0]]


class _Accumulator:
    """Collects the telemetry messages of a stream (file or live link) and builds a :class:`TelemetryLog`."""

    def __init__(self):
        self.counts: Counter = Counter()
        self.bad = 0
        self.sys_time, self.pos, self.gps, self.att, self.gim, self.mount, self.caps = [], [], [], [], [], [], []
        self.cap_msg = None

    def add(self, m) -> None:
        kind = m.get_type()
        if kind == "BAD_DATA":
            self.bad += 1
            return
        self.counts[kind] += 1
        ts = getattr(m, "_timestamp", np.nan)
        if kind == "SYSTEM_TIME" and m.time_unix_usec > 0:
            self.sys_time.append(m.time_unix_usec / 1e6 - m.time_boot_ms / 1e3)
        elif kind == "GLOBAL_POSITION_INT":
            self.pos.append((m.time_boot_ms, ts, m.lat / 1e7, m.lon / 1e7, m.alt / 1e3))
        elif kind == "GPS_RAW_INT":
            self.gps.append((np.nan, ts, m.fix_type, getattr(m, "h_acc", 0) / 1e3, getattr(m, "v_acc", 0) / 1e3,
                             m.satellites_visible))
        elif kind == "ATTITUDE":
            self.att.append((m.time_boot_ms, ts, m.roll, m.pitch, m.yaw))
        elif kind == "GIMBAL_DEVICE_ATTITUDE_STATUS":
            self.gim.append((m.time_boot_ms, ts, *m.q, m.flags))
        elif kind == "MOUNT_STATUS":
            self.mount.append((np.nan, ts, m.pointing_b / 100.0, m.pointing_a / 100.0, m.pointing_c / 100.0))
        elif kind in ("CAMERA_FEEDBACK", "CAMERA_TRIGGER", "CAMERA_IMAGE_CAPTURED"):
            if self.cap_msg is None:
                self.cap_msg = kind
            if kind == self.cap_msg:
                if kind == "CAMERA_FEEDBACK":
                    self.caps.append((m.img_idx, m.time_usec / 1e6))
                elif kind == "CAMERA_TRIGGER":
                    self.caps.append((m.seq, m.time_usec / 1e6))
                else:
                    self.caps.append((m.image_index, m.time_utc / 1e6 if m.time_utc else np.nan))

    def build(self, source: str, max_gap_s: float, truncated: int = 0, quiet: bool = False) -> TelemetryLog:
        if self.sys_time:
            boot, clock = float(np.median(self.sys_time)), "SYSTEM_TIME"
        else:
            boot, clock = None, "tlog"
            if not quiet:
                log.warning("%s: no SYSTEM_TIME: timing telemetry by the records' receive timestamps", source)

        def times(rows):
            if not len(rows):  # nothing of this stream (yet, on a live link)
                return np.zeros(0), np.zeros((0, 8))
            a = np.array(rows, float).reshape(len(rows), -1)
            if boot is not None and np.isfinite(a[:, 0]).all():
                return boot + a[:, 0] / 1e3, a
            return a[:, 1], a

        t, a = times(self.pos)
        position = Series(*_strictly_increasing(t, a[:, 2:5])) if len(a) else Series(np.zeros(0), np.zeros((0, 3)))
        t, a = times(self.gps)
        gps_s = Series(*_strictly_increasing(t, a[:, 2:6])) if len(a) else Series(np.zeros(0), np.zeros((0, 4)))
        t, a = times(self.att)
        if len(a):
            q = rotation_to_quat_wxyz(ned_euler_to_rotation(a[:, 2], a[:, 3], a[:, 4], degrees=False))
            attitude = Series(*_strictly_increasing(t, q))
        else:
            attitude = Series(np.zeros(0), np.zeros((0, 4)))
        gimbal = _gimbal_series(self.gim, self.mount, times, attitude)
        captures = {int(i): float(tc) for i, tc in self.caps if np.isfinite(tc)}
        tl = TelemetryLog(source, position, gps_s, attitude, gimbal, captures, self.cap_msg, clock, boot,
                          Counter(self.counts), self.bad, truncated, max_gap_s)
        for name, s in (("position", position), ("attitude", attitude), ("gimbal", gimbal)):
            tl.gaps += _gaps(name, s.t, max_gap_s)
        if not quiet:
            for g in tl.gaps:
                log.warning("%s: %.1f s gap in %s telemetry (frames in it are flagged)", source, g.seconds, g.stream)
        return tl


def read_tlog(path: str | Path, max_gap_s: float = 1.0) -> TelemetryLog:
    """Read a .tlog (MAVLink 1 or 2). Bad packets are skipped and counted; a packet cut off at the end
    is reported; nothing read before either is lost."""
    from pomar.mavlink import dialect

    dialect()
    from pymavlink import mavutil

    path = Path(path)
    if not path.exists():
        raise TelemetryError(f"{path}: file not found")
    t0 = time.perf_counter()
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega", robust_parsing=True)
    acc = _Accumulator()
    try:
        while True:
            try:
                m = conn.recv_match()
            except Exception as exc:  # a corrupt record pymavlink cannot step over: keep what was read
                log.warning("%s: stopped reading at a corrupt record (%s)", path, exc)
                break
            if m is None:
                break
            acc.add(m)
    finally:
        conn.close()
    if sum(acc.counts.values()) == 0:
        raise TelemetryError(f"{path}: no MAVLink messages could be read (not a .tlog?)")
    try:
        truncated = _unread_tail(path)
    except OSError:
        truncated = 0
    if truncated:
        log.warning("%s: the last %d bytes are a cut-off packet (file truncated?); everything before is used",
                    path, truncated)
    if acc.bad:
        log.warning("%s: skipped %d bad packets", path, acc.bad)
    tl = acc.build(str(path), max_gap_s, truncated)
    tl.parse_seconds = time.perf_counter() - t0
    return tl


class LiveTelemetry:
    """Telemetry from a live MAVLink link (``udpin:127.0.0.1:14550``, ``/dev/ttyUSB0,57600``, ...).

    A thread reads the link; :meth:`snapshot` gives a :class:`TelemetryLog` of everything so far. The
    node identifies itself as a companion computer (MAV_COMP_ID_ONBOARD_COMPUTER, 191) with a 1 Hz
    HEARTBEAT.
    """

    COMPONENT_ID = 191

    def __init__(self, url: str, system_id: int = 1, max_gap_s: float = 1.0, heartbeat_s: float = 1.0):
        from pomar.mavlink import dialect

        self._m = dialect()
        from pymavlink import mavutil

        self.url, self.max_gap_s = url, max_gap_s
        self._conn = mavutil.mavlink_connection(url, dialect="ardupilotmega", source_system=system_id,
                                                source_component=self.COMPONENT_ID, autoreconnect=True)
        self._acc = _Accumulator()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._read, daemon=True),
                         threading.Thread(target=self._beat, args=(heartbeat_s,), daemon=True)]
        for t in self._threads:
            t.start()

    def _read(self):
        while not self._stop.is_set():
            try:
                m = self._conn.recv_match(blocking=True, timeout=0.2)
            except Exception as exc:  # a broken link: keep what was received, say why
                log.warning("%s: %s", self.url, exc)
                time.sleep(0.2)
                continue
            if m is not None:
                with self._lock:
                    self._acc.add(m)

    def _beat(self, period):
        m = self._m
        while not self._stop.wait(period):
            try:
                self._conn.mav.heartbeat_send(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE)
            except Exception as exc:  # no peer yet (udpin before the first packet): try again
                log.debug("heartbeat not sent: %s", exc)

    def snapshot(self) -> TelemetryLog:
        with self._lock:
            return self._acc.build(self.url, self.max_gap_s, quiet=True)

    def close(self):
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2)
        self._conn.close()


def _gimbal_series(gim, mount, times, attitude: Series) -> Series:
    from pomar.mavlink import dialect

    m = dialect()
    if gim:
        t, a = times(gim)
        q = a[:, 2:6]
        flags = a[:, 6].astype(int)
        earth = (flags & m.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME) != 0
        vehicle = (flags & m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME) != 0
        # spec: with neither flag set, YAW_LOCK means earth frame, otherwise the vehicle frame
        in_vehicle = vehicle | (~earth & ((flags & m.GIMBAL_DEVICE_FLAGS_YAW_LOCK) == 0))
        rot = quat_wxyz_to_rotation(q)
        if in_vehicle.any() and len(attitude) > 1:
            veh = quat_wxyz_to_rotation(attitude.values[np.clip(np.searchsorted(attitude.t, t[in_vehicle]), 0, len(attitude) - 1)])
            yaw = veh.as_euler("ZYX")[:, 0]
            fixed = Rotation.from_euler("Z", yaw) * rot[in_vehicle]
            q = q.copy()
            q[in_vehicle] = rotation_to_quat_wxyz(fixed)
        return Series(*_strictly_increasing(t, rotation_to_quat_wxyz(quat_wxyz_to_rotation(q))))
    if mount and len(attitude) > 1:
        t, a = times(mount)
        veh = quat_wxyz_to_rotation(attitude.values[np.clip(np.searchsorted(attitude.t, t), 0, len(attitude) - 1)])
        yaw = np.degrees(veh.as_euler("ZYX")[:, 0])
        q = rotation_to_quat_wxyz(ned_euler_to_rotation(a[:, 2], a[:, 3], a[:, 4] + yaw))
        return Series(*_strictly_increasing(t, q))
    return Series(np.zeros(0), np.zeros((0, 4)))


def _unread_tail(path: Path) -> int:
    """Bytes at the end of a .tlog that do not form a whole record (8-byte time + MAVLink packet)."""
    data = path.read_bytes()
    pos, n = 0, len(data)
    while pos + 8 < n:
        start = pos + 8
        magic = data[start]
        if magic == 0xFD:  # MAVLink 2: 10-byte header, payload, 2-byte CRC, optional 13-byte signature
            if start + 3 > n:
                break
            length = 10 + data[start + 1] + 2 + (13 if data[start + 2] & 0x01 else 0)
        elif magic == 0xFE:  # MAVLink 1
            if start + 2 > n:
                break
            length = 6 + data[start + 1] + 2
        else:
            return 0  # not a clean record stream; pymavlink's resync handled it
        if start + length > n:
            break
        pos = start + length
    return n - pos if pos < n else 0
