"""PX4's ``.ulg`` logs, through pyulog (PX4's own parser).

- position: ``vehicle_global_position`` (lat, lon, alt MSL); without it, the GPS topic's own position.
- home: ``home_position`` (alt): heights above the take-off point; their accuracy from the EKF's height source
  (parameters ``EKF2_HGT_REF`` or ``EKF2_HGT_MODE``: a barometer's, or the GPS's epv).
- GPS: ``vehicle_gps_position`` or ``sensor_gps`` (fix type, eph/epv, satellites; old logs give lat/lon in
  1e-7 degrees and alt in mm, new ones ``latitude_deg`` and ``altitude_msl_m``).
- attitude: ``vehicle_attitude`` (q, wxyz, NED from FRD body); gimbal: ``gimbal_device_attitude_status``.
- camera events: ``camera_capture`` (``seq``, with ``timestamp_utc`` where set).

Clock: PX4 stamps every topic with its boot time (µs). UTC comes from the GPS's ``time_utc_usec``: the median
over the log of UTC minus boot time. A log without UTC stays on boot time and says so. A file cut mid-record
keeps what pyulog could read, and says so.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path

import numpy as np

from pomar.telemetry.base import Series, TelemetryError, TelemetryLog, existing, height_fields

log = logging.getLogger(__name__)

TOPICS = ["vehicle_global_position", "vehicle_gps_position", "sensor_gps", "vehicle_attitude",
          "gimbal_device_attitude_status", "camera_capture", "home_position"]


def _topic(ulog, name):
    """The topic's first instance (multi_id 0), or None."""
    found = [d for d in ulog.data_list if d.name == name]
    return min(found, key=lambda d: d.multi_id).data if found else None


def _gps_fields(d) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if "latitude_deg" in d:
        return d["latitude_deg"].astype(float), d["longitude_deg"].astype(float), d["altitude_msl_m"].astype(float)
    return d["lat"] / 1e7, d["lon"] / 1e7, d["alt"] / 1e3


def unread_tail(path: Path) -> int:
    """Bytes at the end of a ULog that do not form a whole record (after the 16-byte header, every record is a
    uint16 size, a uint8 type and ``size`` bytes)."""
    data = path.read_bytes()
    pos, n = 16, len(data)
    while pos + 3 <= n:
        size = int.from_bytes(data[pos:pos + 2], "little")
        if pos + 3 + size > n:
            break
        pos += 3 + size
    return n - pos


def read_ulog(path: str | Path, max_gap_s: float = 1.0) -> TelemetryLog:
    from pyulog import ULog

    path = existing(path)
    t0 = time.perf_counter()
    try:
        u = ULog(str(path), message_name_filter_list=TOPICS, disable_str_exceptions=True)
    except Exception as exc:  # not a ULog at all (pyulog checks the magic first)
        raise TelemetryError(f"{path}: not a readable PX4 .ulg ({exc})") from None
    problems: list[str] = []
    if getattr(u, "file_corruption", False):
        problems.append("the file is corrupt: pyulog kept the records before the damage")
    cut = unread_tail(path)
    if cut:
        problems.append(f"the last {cut} bytes are a record cut short (file cut?): everything before is used")
    gps = next((d for d in (_topic(u, "vehicle_gps_position"), _topic(u, "sensor_gps")) if d is not None), None)
    boot_us_is_unix = u.start_timestamp > 1e15  # SITL logs stamp with unix time already
    boot_to_unix, clock = 0.0, "PX4 boot time (no UTC in the log)"
    if boot_us_is_unix:
        clock = "PX4 timestamps (unix time already)"
    elif gps is not None and (gps["time_utc_usec"] > 0).any():
        ok = gps["time_utc_usec"] > 0
        boot_to_unix = float(np.median(gps["time_utc_usec"][ok] - gps["timestamp"][ok].astype(float))) / 1e6
        clock = "PX4 boot time mapped to UTC by the GPS's time_utc_usec"
    else:
        problems.append("no UTC in the log (no GPS time): times are seconds since the autopilot booted; give the "
                        "video's clock offset to align them")

    def t_of(d) -> np.ndarray:
        return d["timestamp"].astype(float) / 1e6 + boot_to_unix

    counts = Counter({d.name: len(d.data["timestamp"]) for d in u.data_list})
    pos_d = _topic(u, "vehicle_global_position")
    if pos_d is not None:
        lat, lon, alt = pos_d["lat"].astype(float), pos_d["lon"].astype(float), pos_d["alt"].astype(float)
        ok = ~((lat == 0) & (lon == 0))
        position = Series.of(t_of(pos_d)[ok], np.stack([lat, lon, alt], 1)[ok], 3)
    elif gps is not None:
        lat, lon, alt = _gps_fields(gps)
        ok = (gps["fix_type"] >= 2) & ~((lat == 0) & (lon == 0))
        position = Series.of(t_of(gps)[ok], np.stack([lat, lon, alt], 1)[ok], 3)
        problems.append("no vehicle_global_position: positions are the GPS receiver's (2-D fix or better)")
    else:
        position = Series.empty(3)
    gps_s = (Series.of(t_of(gps), np.stack([gps["fix_type"], gps["eph"], gps["epv"], gps["satellites_used"]], 1), 4)
             if gps is not None else Series.empty(4))
    att = _topic(u, "vehicle_attitude")
    attitude = (Series.of(t_of(att), np.stack([att[f"q[{i}]"] for i in range(4)], 1), 4) if att is not None
                else Series.empty(4))
    gim = _topic(u, "gimbal_device_attitude_status")
    gimbal = (Series.of(t_of(gim), np.stack([gim[f"q[{i}]"] for i in range(4)], 1), 4) if gim is not None
              else Series.empty(4))
    captures, cap_msg = {}, None
    cap = _topic(u, "camera_capture")
    if cap is not None:
        cap_msg = "camera_capture"
        utc = cap.get("timestamp_utc", np.zeros(len(cap["timestamp"])))
        tc = np.where(utc > 0, utc / 1e6, t_of(cap))
        captures = {int(s): float(t) for s, t in zip(cap["seq"], tc)}
    else:
        problems.append("no camera_capture events: frame times come from the video's clock")
    if not len(position):
        problems.append("no position (neither vehicle_global_position nor a GPS topic)")
    home = _topic(u, "home_position")
    home_alt = float(np.median(home["alt"])) if home is not None and len(home["alt"]) else None
    # the EKF's height source (EKF2_HGT_REF, EKF2_HGT_MODE before PX4 1.14): the parameters' last values
    params = dict(u.initial_parameters)
    params.update({name: value for _, name, value in u.changed_parameters})
    tl = TelemetryLog(str(path), position, gps_s, attitude, gimbal, captures, cap_msg, clock, boot_to_unix, counts,
                      max_gap_s=max_gap_s, format="ulog", altitude_reference="msl", problems=problems,
                      home_alt=home_alt, **height_fields(params, gps_s.values[:, 2]))
    tl.parse_seconds = time.perf_counter() - t0
    return tl
