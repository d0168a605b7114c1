"""MAVLink telemetry: a ground station's ``.tlog`` (and, through :class:`MavlinkAccumulator`, a live link).

What it reads, as real autopilots send it:

- position: ``GLOBAL_POSITION_INT`` (lat, lon, alt MSL); lat/lon 0, 0 is an autopilot without a position, not
  a place, and is left out. ``GPS_RAW_INT`` (fix type, accuracy).
- vehicle attitude: ``ATTITUDE`` (roll, pitch, yaw in NED).
- gimbal attitude: ``GIMBAL_DEVICE_ATTITUDE_STATUS`` (quaternion; yaw in the vehicle frame is turned into the
  earth frame with the vehicle's yaw, following the flags), or ArduPilot's older ``MOUNT_STATUS`` (left out in
  retract mode: mount_mode 0 with all angles 0 is no attitude).
- per-frame capture records: ``CAMERA_FEEDBACK`` (ArduPilot, ``img_idx``), ``CAMERA_TRIGGER`` (PX4, ``seq``),
  ``CAMERA_IMAGE_CAPTURED`` (``image_index``).

One clock: the vehicle's boot time (the system that sends the positions), mapped to UTC by *that system's*
``SYSTEM_TIME``. Where the vehicle's SYSTEM_TIME carries no UTC, or there is none, its boot time is mapped to
the tlog's receive times (the ground station's clock), and the log says which. A message without a boot time
(GPS_RAW_INT with a unix time_usec is on UTC already; MOUNT_STATUS has none) takes its receive time, moved onto
the same clock by the median offset between the two.
"""

from __future__ import annotations

import logging
import re
import time
from collections import Counter, defaultdict, deque
from pathlib import Path

import numpy as np

from pomar.rotations import ned_euler_to_rotation, quat_wxyz_to_rotation, rotation_to_quat_wxyz
from pomar.telemetry.base import Series, TelemetryError, TelemetryLog, existing, height_fields

log = logging.getLogger(__name__)

_UNIX_USEC = 1e15  # a time_usec above this is unix time (after 2001); below, time since boot


class MavlinkAccumulator:
    """Collects the telemetry messages of a MAVLink stream (file or live link) and builds a :class:`TelemetryLog`.
    Also reads DataFlash-free MAVLink from any mavutil connection."""

    def __init__(self):
        self.counts: Counter = Counter()
        self.bad = 0
        self.bad_by_type: Counter = Counter()
        self.no_fix_positions = 0
        self.retract_mounts = 0
        self.utc: dict[int, deque] = defaultdict(lambda: deque(maxlen=2000))  # system -> unix - boot (s)
        self.rx: dict[int, deque] = defaultdict(lambda: deque(maxlen=2000))  # system -> receive - boot (s)
        self.sys_time_seen: set[int] = set()
        self.pos, self.gps, self.att, self.gim, self.mount, self.caps = [], [], [], [], [], []
        self.pos_systems: Counter = Counter()
        self.home_alts: deque = deque(maxlen=2000)  # alt - relative_alt (m): the home point's altitude
        self.cap_msg = None
        self.params: dict[str, float] = {}  # PARAM_VALUE: name -> value, the last one sent

    def _bad(self, m) -> None:
        self.bad += 1
        reason = str(getattr(m, "reason", ""))
        hit = re.search(r"msgID (\d+)", reason)
        if hit:
            from pomar.mavlink import dialect

            cls = dialect().mavlink_map.get(int(hit.group(1)))
            self.bad_by_type[cls.msgname if cls else f"msgID {hit.group(1)}"] += 1
        else:
            self.bad_by_type["unparsed bytes"] += 1

    def add(self, m) -> None:
        kind = m.get_type()
        if kind == "BAD_DATA":
            self._bad(m)
            return
        self.counts[kind] += 1
        ts = float(getattr(m, "_timestamp", np.nan) or np.nan)
        src = m.get_srcSystem()
        boot_ms = getattr(m, "time_boot_ms", None)
        if boot_ms is not None and np.isfinite(ts):
            self.rx[src].append(ts - boot_ms / 1e3)
        if kind == "SYSTEM_TIME":
            self.sys_time_seen.add(src)
            if m.time_unix_usec > 0:
                self.utc[src].append(m.time_unix_usec / 1e6 - m.time_boot_ms / 1e3)
        elif kind == "GLOBAL_POSITION_INT":
            if m.lat == 0 and m.lon == 0:  # no position yet, not the Gulf of Guinea
                self.no_fix_positions += 1
                return
            self.pos_systems[src] += 1
            self.pos.append((src, m.time_boot_ms / 1e3, np.nan, ts, m.lat / 1e7, m.lon / 1e7, m.alt / 1e3))
            if m.relative_alt:  # 0 from autopilots that do not fill it
                self.home_alts.append((m.alt - m.relative_alt) / 1e3)
        elif kind == "GPS_RAW_INT":
            boot, unix = (np.nan, m.time_usec / 1e6) if m.time_usec > _UNIX_USEC else (m.time_usec / 1e6, np.nan)
            if not m.time_usec:
                boot = np.nan
            self.gps.append((src, boot, unix, ts, m.fix_type, getattr(m, "h_acc", 0) / 1e3, getattr(m, "v_acc", 0) / 1e3,
                             m.satellites_visible))
        elif kind == "PARAM_VALUE":
            self.params[str(m.param_id).rstrip("\x00")] = float(m.param_value)
        elif kind == "ATTITUDE":
            self.att.append((src, m.time_boot_ms / 1e3, np.nan, ts, m.roll, m.pitch, m.yaw))
        elif kind == "GIMBAL_DEVICE_ATTITUDE_STATUS":
            self.gim.append((src, m.time_boot_ms / 1e3, np.nan, ts, *m.q, m.flags))
        elif kind == "MOUNT_STATUS":
            if m.pointing_a == 0 and m.pointing_b == 0 and m.pointing_c == 0 and getattr(m, "mount_mode", 0) == 0:
                self.retract_mounts += 1  # retracted (or not reporting): no attitude
                return
            self.mount.append((src, np.nan, np.nan, ts, m.pointing_b / 100.0, m.pointing_a / 100.0, m.pointing_c / 100.0))
        elif kind in ("CAMERA_FEEDBACK", "CAMERA_TRIGGER", "CAMERA_IMAGE_CAPTURED"):
            if self.cap_msg is None:
                self.cap_msg = kind
            if kind == self.cap_msg:
                if kind == "CAMERA_FEEDBACK":
                    idx, us = m.img_idx, m.time_usec
                elif kind == "CAMERA_TRIGGER":
                    idx, us = m.seq, m.time_usec
                else:
                    idx, us = m.image_index, m.time_utc
                boot, unix = (np.nan, us / 1e6) if us > _UNIX_USEC else (us / 1e6 if us else np.nan, np.nan)
                self.caps.append((src, boot, unix, ts, idx))

    # -- one clock
    def _clock(self, source: str, quiet: bool, problems: list[str]):
        """(vehicle system, boot_to_unix per system, receive -> log clock offset, clock description)."""
        vehicle = self.pos_systems.most_common(1)[0][0] if self.pos_systems else (
            max(self.rx, key=lambda s: len(self.rx[s])) if self.rx else 1)
        rx_vehicle = float(np.median(self.rx[vehicle])) if self.rx.get(vehicle) else None
        if self.utc.get(vehicle):
            boot_to_unix = float(np.median(self.utc[vehicle]))
            clock = f"SYSTEM_TIME of system {vehicle}"
        else:
            boot_to_unix = rx_vehicle
            if vehicle in self.sys_time_seen:
                msg = (f"system {vehicle}'s SYSTEM_TIME carries no UTC (time_unix_usec 0): its boot clock is mapped "
                       "to the tlog's receive times")
            else:
                msg = f"no SYSTEM_TIME from system {vehicle}: its boot clock is mapped to the tlog's receive times"
            others = sorted(s for s in self.utc if s != vehicle)
            if others:
                msg += f" (system(s) {others} send UTC, but their clocks are not the vehicle's)"
            problems.append(msg)
            if not quiet:
                log.warning("%s: %s", source, msg)
            clock = "tlog receive time"
        offsets = {vehicle: boot_to_unix}
        rx_off = (boot_to_unix - rx_vehicle) if boot_to_unix is not None and rx_vehicle is not None else 0.0
        for s, d in self.rx.items():  # other systems' boot clocks, through their receive times
            if s != vehicle and d:
                offsets[s] = float(np.median(d)) + rx_off
        return vehicle, offsets, rx_off, clock

    def build(self, source: str, max_gap_s: float = 1.0, truncated: int = 0, quiet: bool = False) -> TelemetryLog:
        problems: list[str] = []
        vehicle, offsets, rx_off, clock = self._clock(source, quiet, problems)

        def times(rows, d: int):
            """Rows (src, boot s, unix s, receive s, values...) -> (t on the log's clock, values (n, d))."""
            if not rows:
                return np.zeros(0), np.zeros((0, d))
            a = np.array(rows, float).reshape(len(rows), -1)
            src, boot, unix, rx = a[:, 0], a[:, 1], a[:, 2], a[:, 3]
            off = np.array([offsets.get(int(s), np.nan) if offsets.get(int(s)) is not None else np.nan for s in src])
            t = np.where(np.isfinite(unix), unix, np.where(np.isfinite(boot) & np.isfinite(off), off + boot, rx + rx_off))
            return t, a[:, 4:4 + d]

        position = Series.of(*times(self.pos, 3), 3)
        gps = Series.of(*times(self.gps, 4), 4)
        t, a = times(self.att, 3)
        attitude = (Series.of(t, rotation_to_quat_wxyz(ned_euler_to_rotation(a[:, 0], a[:, 1], a[:, 2], degrees=False)), 4)
                    if len(t) else Series.empty(4))
        gimbal = self._gimbal(times, attitude)
        t, a = times(self.caps, 1)
        captures = {int(i): float(tc) for i, tc in zip(a[:, 0], t) if np.isfinite(tc)}
        if self.no_fix_positions:
            problems.append(f"{self.no_fix_positions} GLOBAL_POSITION_INT at lat/lon 0, 0 (no position yet): left out")
        if self.retract_mounts:
            problems.append(f"{self.retract_mounts} MOUNT_STATUS in retract mode (all angles 0): no gimbal attitude")
        if self.bad:
            types = ", ".join(f"{k} {v}" for k, v in self.bad_by_type.most_common(8))
            problems.append(f"{self.bad} packets failed to decode ({types}); packets of known types that fail their "
                            "CRC come from a dialect pymavlink's ardupilotmega does not define as sent, not corruption")
        if len(gps) and len(position) and (gps.t[-1] - gps.t[0]) < 0.5 * (position.t[-1] - position.t[0]):
            problems.append(f"GPS reports span {gps.t[-1] - gps.t[0]:.0f} s against {position.t[-1] - position.t[0]:.0f} s "
                            "of positions: frames outside them have no fix information")
        tl = TelemetryLog(source, position, gps, attitude, gimbal, captures, self.cap_msg, clock,
                          offsets.get(vehicle), Counter(self.counts), self.bad, truncated, max_gap_s,
                          format="tlog", problems=problems, bad_by_type=Counter(self.bad_by_type),
                          home_alt=float(np.median(self.home_alts)) if self.home_alts else None,
                          # the EKF's height source, where the link sent its parameters
                          **height_fields(self.params, gps.values[:, 2]))
        if not quiet:
            for g in tl.gaps:
                log.warning("%s: %.1f s gap in %s telemetry (frames in it are flagged)", source, g.seconds, g.stream)
        return tl

    def _gimbal(self, times, attitude: Series) -> Series:
        from pomar.mavlink import dialect

        m = dialect()
        if self.gim:
            t, a = times(self.gim, 5)
            q = a[:, :4]
            flags = a[:, 4].astype(int)
            earth = (flags & m.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME) != 0
            vehicle = (flags & m.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME) != 0
            # spec: with neither flag set, YAW_LOCK means earth frame, otherwise the vehicle frame
            in_vehicle = vehicle | (~earth & ((flags & m.GIMBAL_DEVICE_FLAGS_YAW_LOCK) == 0))
            rot = quat_wxyz_to_rotation(q)
            if in_vehicle.any() and len(attitude) > 1:
                yaw = vehicle_yaw(attitude, t[in_vehicle])
                zero = np.zeros(len(yaw))
                fixed = ned_euler_to_rotation(zero, zero, yaw, degrees=False) * rot[in_vehicle]
                q = q.copy()
                q[in_vehicle] = rotation_to_quat_wxyz(fixed)
            return Series.of(t, rotation_to_quat_wxyz(quat_wxyz_to_rotation(q)), 4)
        if self.mount and len(attitude) > 1:
            t, a = times(self.mount, 3)
            yaw = np.degrees(vehicle_yaw(attitude, t))
            return Series.of(t, rotation_to_quat_wxyz(ned_euler_to_rotation(a[:, 0], a[:, 1], a[:, 2] + yaw)), 4)
        return Series.empty(4)


def vehicle_yaw(attitude: Series, t: np.ndarray) -> np.ndarray:
    """The vehicle's yaw (radians, NED) at the nearest attitude sample at or after each time."""
    veh = quat_wxyz_to_rotation(attitude.values[np.clip(np.searchsorted(attitude.t, t), 0, len(attitude) - 1)])
    return veh.as_euler("ZYX")[:, 0]


def read_tlog(path: str | Path, max_gap_s: float = 1.0) -> TelemetryLog:
    """Read a .tlog (MAVLink 1 or 2). Bad packets are skipped and counted by type; a packet cut off at the end
    is reported; nothing read before either is lost."""
    from pomar.mavlink import dialect

    dialect()
    from pymavlink import mavutil

    path = existing(path)
    t0 = time.perf_counter()
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega", robust_parsing=True)
    acc = MavlinkAccumulator()
    stopped = None
    try:
        while True:
            try:
                m = conn.recv_match()
            except Exception as exc:  # a corrupt record pymavlink cannot step over: keep what was read
                stopped = f"stopped reading at a corrupt record ({exc}); everything before it is used"
                log.warning("%s: %s", path, stopped)
                break
            if m is None:
                break
            acc.add(m)
    finally:
        conn.close()
    if sum(acc.counts.values()) == 0:
        raise TelemetryError(f"{path}: no MAVLink messages could be read (not a .tlog?)")
    if not (acc.pos or acc.gps or acc.att or acc.gim or acc.mount or acc.caps):
        raise TelemetryError(f"{path}: no position, GPS, attitude, gimbal or camera message among its "
                             f"{sum(acc.counts.values())} MAVLink packets ({acc.bad} more failed to decode): not a "
                             "flight's telemetry log")
    try:
        truncated = unread_tail(path)
    except OSError:
        truncated = 0
    if truncated:
        log.warning("%s: the last %d bytes are a cut-off packet (file truncated?); everything before is used",
                    path, truncated)
    if acc.bad:
        log.warning("%s: skipped %d bad packets (%s)", path, acc.bad,
                    ", ".join(f"{k} {v}" for k, v in acc.bad_by_type.most_common(5)))
    tl = acc.build(str(path), max_gap_s, truncated)
    if truncated:
        tl.problems.append(f"the last {truncated} bytes are a cut-off packet (file cut short?): everything before "
                           "is used")
    if stopped:
        tl.problems.append(stopped)
    tl.parse_seconds = time.perf_counter() - t0
    return tl


def unread_tail(path: Path) -> int:
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
