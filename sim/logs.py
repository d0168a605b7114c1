"""A simulated flight's telemetry in the other formats real drones write, beside its ``telemetry.tlog``:

- ``telemetry.bin``: ArduPilot's on-board DataFlash log, the same samples as the tlog's messages (GLOBAL_POSITION_INT
  -> POS, GPS_RAW_INT -> GPS with GPS week and ms, ATTITUDE -> ATT, the gimbal -> MNT with an earth-frame yaw,
  CAMERA_FEEDBACK -> CAM with Img = frame + 1), timed by the autopilot's boot clock. Written with pymavlink's
  DataFlash support (``DFReader.DFFormat`` and ``DFMessage.get_msgbuf``), with an FMT record for each type.
- ``video.SRT``: a DJI subtitle per video frame, in the Mavic 3 layout (date, ``[latitude: …] [longitude: …]
  [rel_alt: … abs_alt: …] [gb_yaw: … gb_pitch: … gb_roll: …]``), from the tlog's samples at each frame's capture
  time.

    python -m sim logs FLIGHT_DIR          # writes both
"""

from __future__ import annotations

import logging
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from pomar.rotations import quat_wxyz_to_rotation

log = logging.getLogger(__name__)

GPS_EPOCH_UNIX = 315964800  # 1980-01-06
LEAP_S = 18  # GPS - UTC, as DFReader assumes

#: name -> (type id, format, columns), as ArduPilot 4.4 logs them
DF_FORMATS = {
    "FMT": (128, "BBnNZ", "Type,Length,Name,Format,Columns"),
    "POS": (129, "QLLfff", "TimeUS,Lat,Lng,Alt,RelHomeAlt,RelOriginAlt"),
    "GPS": (130, "QBBIHBcLLeffffB", "TimeUS,I,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    "ATT": (131, "QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),
    "MNT": (132, "QBffffffff", "TimeUS,I,DesRoll,Roll,DesPitch,Pitch,DesYawB,YawB,DesYawE,YawE"),
    "CAM": (133, "QBHIHLLeefccC", "TimeUS,I,Img,GPSTime,GPSWeek,Lat,Lng,Alt,RelAlt,GPSAlt,R,P,Y"),
}


class DataFlashWriter:
    """DataFlash records through pymavlink's own encoder: an FMT record per type, then the messages (raw values:
    degrees x 1e7 for L, centi-units for c/C/e)."""

    def __init__(self, path):
        from pymavlink import DFReader

        self._DF = DFReader
        self._f = open(path, "wb")
        self._fmts = {}
        fmt_type, fmt_fmt, fmt_cols = DF_FORMATS["FMT"]
        self._fmt_fmt = DFReader.DFFormat(fmt_type, "FMT", 89, fmt_fmt, fmt_cols)
        for name, (t, f, cols) in DF_FORMATS.items():
            size = 3 + DFReader.struct.calcsize(DFReader.DFFormat(t, name, 0, f, cols).msg_struct)
            self._fmts[name] = DFReader.DFFormat(t, name, size, f, cols)
            self._write(self._fmt_fmt, [t, size, name, f, cols])

    def _write(self, fmt, values):
        # raw values; get_msgbuf scales by the multiplier and back, so the message must apply it
        buf = self._DF.DFMessage(fmt, list(values), True, None).get_msgbuf()
        if buf is None:
            raise ValueError(f"DataFlash {fmt.name}: values {values} do not fit {fmt.format}")
        self._f.write(buf)

    def write(self, name: str, values) -> None:
        self._write(self._fmts[name], values)

    def close(self):
        self._f.close()


def _gps_week_ms(t_unix: float) -> tuple[int, int]:
    g = t_unix - GPS_EPOCH_UNIX + LEAP_S
    week = int(g // 604800)
    return week, int(round((g - week * 604800) * 1000))


def _euler_deg(q_wxyz: np.ndarray) -> np.ndarray:
    """(n, 3) roll, pitch, yaw (degrees, NED, ZYX) of NED-from-body quaternions."""
    return np.degrees(quat_wxyz_to_rotation(q_wxyz).as_euler("ZYX")[:, ::-1])


def write_dataflash(tlog: Path, out: Path) -> dict:
    """The tlog's samples as an ArduPilot DataFlash .bin; returns message counts."""
    from pomar.mavlink import dialect

    dialect()
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    msgs = []
    boot_to_unix = None
    while (m := conn.recv_match()) is not None:
        if m.get_type() == "SYSTEM_TIME" and m.time_unix_usec and boot_to_unix is None:
            boot_to_unix = m.time_unix_usec / 1e6 - m.time_boot_ms / 1e3
        msgs.append(m)
    conn.close()
    if boot_to_unix is None:
        raise ValueError(f"{tlog}: no SYSTEM_TIME with UTC: cannot place a DataFlash log's boot clock")
    w = DataFlashWriter(out)
    counts: dict[str, int] = {}

    def us(boot_ms):
        return int(round(boot_ms * 1000))

    for m in msgs:
        kind = m.get_type()
        if kind == "GLOBAL_POSITION_INT":
            w.write("POS", [us(m.time_boot_ms), m.lat, m.lon, m.alt / 1e3, m.relative_alt / 1e3, m.relative_alt / 1e3])
            name = "POS"
        elif kind == "GPS_RAW_INT":
            t_boot = m.time_usec / 1e6 if m.time_usec < 1e15 else m.time_usec / 1e6 - boot_to_unix
            week, ms = _gps_week_ms(boot_to_unix + t_boot)
            w.write("GPS", [int(round(t_boot * 1e6)), 0, m.fix_type, ms, week, m.satellites_visible,
                            int(round(m.eph)), m.lat, m.lon, int(round(m.alt / 10)), m.vel / 100, m.cog / 100, 0.0,
                            0.0, 1])
            name = "GPS"
        elif kind == "ATTITUDE":
            r, p, y = np.degrees([m.roll, m.pitch, m.yaw])
            w.write("ATT", [us(m.time_boot_ms), int(round(r * 100)), int(round(r * 100)), int(round(p * 100)),
                            int(round(p * 100)), int(round((y % 360) * 100)), int(round((y % 360) * 100)), 0, 0, 3])
            name = "ATT"
        elif kind == "GIMBAL_DEVICE_ATTITUDE_STATUS":
            r, p, y = _euler_deg(np.array([m.q]))[0]
            w.write("MNT", [us(m.time_boot_ms), 0, r, r, p, p, 0.0, 0.0, y % 360, y % 360])
            name = "MNT"
        elif kind == "CAMERA_FEEDBACK":
            t_boot = m.time_usec / 1e6 - boot_to_unix
            week, ms = _gps_week_ms(m.time_usec / 1e6)
            w.write("CAM", [int(round(t_boot * 1e6)), 0, m.img_idx + 1, ms, week, m.lat, m.lng,
                            int(round(m.alt_msl * 100)), int(round(m.alt_rel * 100)), m.alt_msl,
                            int(round(m.roll * 100)), int(round(m.pitch * 100)), int(round((m.yaw % 360) * 100))])
            name = "CAM"
        else:
            continue
        counts[name] = counts.get(name, 0) + 1
    w.close()
    log.info("wrote %s: %s", out, counts)
    return counts


def write_srt(tlog: Path, frame_count: int, fps: float, video_start_unix: float, out: Path,
              clock_offset_s: float = 0.0) -> int:
    """A DJI (Mavic 3 layout) subtitle per frame, from the tlog sampled at each frame's capture time; returns the
    number written."""
    from pomar.telemetry.tlog import read_tlog

    tl = read_tlog(tlog)
    t, _ = tl.frame_times(frame_count, video_start_unix, fps, clock_offset_s)
    s = tl.at(t)
    # rel_alt is above the take-off point, as DJI's: the ground where the tlog says so, else the first position
    home_alt = tl.home_alt if tl.home_alt is not None else float(tl.position.values[0, 2])
    gimbal = _euler_deg(np.where(np.isfinite(s["q_gimbal"]), s["q_gimbal"], [1.0, 0, 0, 0]))
    lines = []
    for i in range(frame_count):
        a, b = i / fps, (i + 1) / fps
        stamp = datetime.fromtimestamp(t[i], timezone.utc)
        date = stamp.strftime("%Y-%m-%d %H:%M:%S.") + f"{stamp.microsecond // 1000:03d}"
        r, p, y = gimbal[i]
        lines.append(f"{i + 1}\n{_srt_time(a)} --> {_srt_time(b)}\n"
                     f'<font size="28">FrameCnt: {i + 1}, DiffTime: {1000 / fps:.0f}ms\n{date}\n'
                     f"[iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [ev: 0] [color_md: default] [focal_len: 24.00] "
                     f"[latitude: {s['lat'][i]:.7f}] [longitude: {s['lon'][i]:.7f}] "
                     f"[rel_alt: {s['alt'][i] - home_alt:.3f} abs_alt: {s['alt'][i]:.3f}] "
                     f"[gb_yaw: {y:.2f} gb_pitch: {p:.2f} gb_roll: {r:.2f}] </font>\n")
    Path(out).write_text("\n".join(lines), encoding="utf-8")
    log.info("wrote %s: %d subtitles", out, frame_count)
    return frame_count


def _srt_time(t: float) -> str:
    ms = int(round(t * 1000))
    return f"{ms // 3600000:02d}:{ms // 60000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"
