"""A simulated flight's telemetry in the other formats real drones write, beside its ``telemetry.tlog``:

- ``telemetry.bin``: ArduPilot's on-board DataFlash log, the same samples as the tlog's messages (GLOBAL_POSITION_INT
  -> POS, GPS_RAW_INT -> GPS with GPS week and ms, ATTITUDE -> ATT, the gimbal -> MNT with an earth-frame yaw,
  CAMERA_FEEDBACK -> CAM with Img = frame + 1, PARAM_VALUE -> PARM), timed by the autopilot's boot clock. Written
  with pymavlink's DataFlash support (``DFReader.DFFormat`` and ``DFMessage.get_msgbuf``), with an FMT record for
  each type.
- ``telemetry.ulg``: PX4's ULog of the same samples (GLOBAL_POSITION_INT -> vehicle_global_position and home_position,
  GPS_RAW_INT -> vehicle_gps_position with its accuracy in metres, ATTITUDE -> vehicle_attitude, the gimbal ->
  gimbal_device_attitude_status, the camera's events -> camera_capture; the EKF's height source as the initial
  parameter EKF2_HGT_REF), read back by pyulog.
- ``video.SRT``: a DJI subtitle per video frame, in the Mavic 3 layout (date, ``[latitude: …] [longitude: …]
  [rel_alt: … abs_alt: …] [gb_yaw: … gb_pitch: … gb_roll: …]``), from the tlog's samples at each frame's capture
  time; ``--srt-layout`` writes another DJI layout (``SRT_LAYOUTS``, each as a real file has it), and
  ``--no-attitude`` leaves out the layout's attitude fields, as most DJI drones write none.

    python -m sim logs FLIGHT_DIR          # writes all three
"""

from __future__ import annotations

import logging
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from pomar.rotations import quat_wxyz_to_rotation
from pomar.telemetry.base import height_source, height_source_param
from sim.telemetry import BARO_DRIFT_M  # a barometer's drift: one definition, the EKF's and a DJI SRT's

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
    # the receiver's stated accuracy beside each GPS record (centimetres: C is uint16 x 100 of metres)
    "GPA": (134, "QBCCCCfBIH", "TimeUS,I,VDop,HAcc,VAcc,SAcc,YAcc,VV,SMS,Delta"),
    "PARM": (135, "QNff", "TimeUS,Name,Value,Default"),
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


def tlog_messages(tlog: Path, kind: str) -> tuple[list, float]:
    """The tlog's messages, and its autopilot's boot clock in unix seconds (its first SYSTEM_TIME with UTC; without
    one a ValueError: a ``kind`` log's boot clock cannot be placed)."""
    from pomar.mavlink import dialect

    dialect()
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    msgs, boot_to_unix = [], None
    while (m := conn.recv_match()) is not None:
        if m.get_type() == "SYSTEM_TIME" and m.time_unix_usec and boot_to_unix is None:
            boot_to_unix = m.time_unix_usec / 1e6 - m.time_boot_ms / 1e3
        msgs.append(m)
    conn.close()
    if boot_to_unix is None:
        raise ValueError(f"{tlog}: no SYSTEM_TIME with UTC: cannot place a {kind} log's boot clock")
    return msgs, boot_to_unix


def write_dataflash(tlog: Path, out: Path) -> dict:
    """The tlog's samples as an ArduPilot DataFlash .bin; returns message counts."""
    msgs, boot_to_unix = tlog_messages(tlog, "DataFlash")
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
            if getattr(m, "h_acc", 0):  # ArduPilot logs GPA with each GPS record: HAcc, VAcc in cm, SAcc in cm/s
                w.write("GPA", [int(round(t_boot * 1e6)), 0, int(m.epv), int(round(m.h_acc / 10)),
                                int(round(m.v_acc / 10)), int(round(getattr(m, "vel_acc", 0) / 10)), 0.0, 1, ms // 1000,
                                200])
                counts["GPA"] = counts.get("GPA", 0) + 1
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
        elif kind == "PARAM_VALUE":  # ArduPilot logs its parameters as the log starts
            w.write("PARM", [0, m.param_id.encode(), m.param_value, m.param_value])
            name = "PARM"
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


#: topic -> fields (ULog type, name), as PX4 logs them (the fields pomar's reader takes, in PX4's names and units)
ULOG_TOPICS = {
    "vehicle_global_position": [("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"), ("float", "alt")],
    "vehicle_gps_position": [("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec"), ("int32_t", "lat"),
                             ("int32_t", "lon"), ("int32_t", "alt"), ("float", "eph"), ("float", "epv"),
                             ("uint8_t", "fix_type"), ("uint8_t", "satellites_used")],
    "vehicle_attitude": [("uint64_t", "timestamp"), ("float[4]", "q")],
    "gimbal_device_attitude_status": [("uint64_t", "timestamp"), ("float[4]", "q")],
    "camera_capture": [("uint64_t", "timestamp"), ("uint64_t", "timestamp_utc"), ("uint32_t", "seq")],
    "home_position": [("uint64_t", "timestamp"), ("float", "alt")],
}


class ULogWriter:
    """A PX4 ULog (version 1): header, flag bits, a format and a subscription per topic, then data records in time
    order. The record types and the header are pyulog's; each record is a uint16 size, a uint8 type, its bytes."""

    def __init__(self, path, start_us: int = 0, params: dict | None = None):
        import struct

        from pyulog import ULog

        self._U, self._struct = ULog, struct
        self._records: list[tuple[int, int, bytes]] = []  # (timestamp, order, record)
        self._f = open(path, "wb")
        self._f.write(bytes(ULog.HEADER_BYTES) + struct.pack("<BQ", 1, start_us))
        self._put(ULog.MSG_TYPE_FLAG_BITS, bytes(16) + struct.pack("<3Q", 0, 0, 0))
        self._packers = {}
        for name, fields in ULOG_TOPICS.items():
            self._put(ULog.MSG_TYPE_FORMAT, (name + ":" + "".join(f"{t} {n};" for t, n in fields)).encode())
            codes = "".join(ULog._UNPACK_TYPES[t.split("[")[0]][0] * (int(t[t.index("[") + 1:-1]) if "[" in t else 1)
                            for t, _ in fields)
            self._packers[name] = (len(self._packers), struct.Struct("<H" + codes))
        for name, value in (params or {}).items():  # the initial parameters (int32), in the definitions section
            key = f"int32_t {name}".encode()
            self._put(ULog.MSG_TYPE_PARAMETER, struct.pack("<B", len(key)) + key + struct.pack("<i", int(value)))
        for name, (msg_id, _) in self._packers.items():
            self._put(ULog.MSG_TYPE_ADD_LOGGED_MSG, struct.pack("<BH", 0, msg_id) + name.encode())

    def _put(self, kind: int, data: bytes):
        self._f.write(self._struct.pack("<HB", len(data), kind) + data)

    def write(self, topic: str, timestamp_us: int, *values):
        msg_id, packer = self._packers[topic]
        flat = [v for x in values for v in (x if isinstance(x, (list, tuple, np.ndarray)) else [x])]
        data = packer.pack(msg_id, int(timestamp_us), *flat)
        self._records.append((int(timestamp_us), len(self._records),
                              self._struct.pack("<HB", len(data), self._U.MSG_TYPE_DATA) + data))

    def close(self):
        for _, _, rec in sorted(self._records):
            self._f.write(rec)
        self._f.close()


def write_ulog(tlog: Path, out: Path) -> dict:
    """The tlog's samples as a PX4 .ulg (boot-time stamps; UTC in the GPS's time_utc_usec and the captures'
    timestamp_utc); returns record counts."""
    from pomar.rotations import ned_euler_to_rotation, rotation_to_quat_wxyz

    msgs, boot_to_unix = tlog_messages(tlog, "ULog")

    def boot_us(us):  # a MAVLink time_usec (boot or unix) as PX4's boot-time stamp
        return int(round(us - boot_to_unix * 1e6)) if us > 1e15 else int(us)

    def unix_us(t_boot_us):  # ... and that stamp in UTC, as PX4's GPS and camera topics carry it
        return int(round(t_boot_us + boot_to_unix * 1e6))

    # the EKF's height source, as PX4 names it, from whichever autopilot's parameter the tlog carries
    src = height_source({str(m.param_id): m.param_value for m in msgs if m.get_type() == "PARAM_VALUE"})
    w = ULogWriter(out, params=dict([height_source_param(src[0], "px4")]) if src else None)
    counts: dict[str, int] = {}
    home = False
    for m in msgs:
        kind = m.get_type()
        if kind == "GLOBAL_POSITION_INT":
            t = m.time_boot_ms * 1000
            if m.lat == 0 and m.lon == 0:
                continue
            w.write("vehicle_global_position", t, m.lat / 1e7, m.lon / 1e7, m.alt / 1e3)
            if not home and m.relative_alt:  # PX4 logs its home once it is set
                w.write("home_position", t, (m.alt - m.relative_alt) / 1e3)
                home = True
                counts["home_position"] = 1
            topic = "vehicle_global_position"
        elif kind == "GPS_RAW_INT":
            t = boot_us(m.time_usec)
            eph = getattr(m, "h_acc", 0) / 1e3 or m.eph / 100  # PX4's eph is metres; MAVLink's eph is HDOP x 100
            epv = getattr(m, "v_acc", 0) / 1e3 or m.epv / 100
            w.write("vehicle_gps_position", t, unix_us(t), m.lat, m.lon, m.alt, eph, epv, m.fix_type,
                    m.satellites_visible)
            topic = "vehicle_gps_position"
        elif kind == "ATTITUDE":
            q = rotation_to_quat_wxyz(ned_euler_to_rotation(m.roll, m.pitch, m.yaw, degrees=False))
            w.write("vehicle_attitude", m.time_boot_ms * 1000, np.asarray(q, float).reshape(4))
            topic = "vehicle_attitude"
        elif kind == "GIMBAL_DEVICE_ATTITUDE_STATUS":  # the simulator's yaw is in the earth frame, as PX4 logs it
            w.write("gimbal_device_attitude_status", m.time_boot_ms * 1000, list(m.q))
            topic = "gimbal_device_attitude_status"
        elif kind in ("CAMERA_FEEDBACK", "CAMERA_TRIGGER"):
            idx = m.img_idx if kind == "CAMERA_FEEDBACK" else m.seq
            t = boot_us(m.time_usec)
            w.write("camera_capture", t, unix_us(t), idx)
            topic = "camera_capture"
        else:
            continue
        counts[topic] = counts.get(topic, 0) + 1
    w.close()
    log.info("wrote %s: %s", out, counts)
    return counts


#: The DJI subtitle layouts ``write_srt`` writes, each as a real file of ``shared/datasets/logs/dji-srt`` has it:
#: name -> (subtitles a second (0 = one a frame), decimals of lat/lon, can carry attitudes, the real file).
SRT_LAYOUTS = {
    "mavic3": (0, 5, True, "mavic3.srt: FrameCnt, date.ms, [latitude] [longitude] [rel_alt abs_alt] ([gb_yaw ...])"),
    "air2s": (0, 6, False, "air2s.srt: SrtCnt, date,ms,us, [latitude] [longitude] [altitude] (absolute)"),
    "mavic2": (1, 4, False, "mavic_2_style.SRT: no timing lines, date, [latitude :] [longtitude :], no altitude"),
    "p4p": (1, 4, True, "p4p_sample.SRT: GPS (lon, lat, sats), D, H (above take-off); with attitudes the Phantom 4 "
                        "RTK's (mix_p4rtk_mavic2pro.srt): 6 decimals, HOME, F.PRY, G.PRY"),
    "home": (1, 4, False, "mavic_pro.SRT: HOME(lon,lat) date, GPS(lon,lat,sats) BAROMETER:h"),
    "m300": (1, 4, False, "matrice_300.srt: date, GPS(lat,lon,0.0M) BAROMETER:hM"),
}




def write_srt(tlog: Path, frame_count: int, fps: float, video_start_unix: float, out: Path,
              clock_offset_s: float = 0.0, layout: str = "mavic3", attitude: bool = True,
              truth_heights: tuple[np.ndarray, np.ndarray] | None = None, seed: int = 0) -> int:
    """A DJI subtitle file from the tlog sampled at each subtitle's time, in one of SRT_LAYOUTS: one subtitle a
    frame (mavic3, air2s) or a second (the older layouts, their first at 0 s); with ``attitude`` the layout's
    attitude fields where it has them (the gimbal's, and the Phantom 4 RTK's vehicle angles). The height above
    take-off is a barometer's where ``truth_heights`` ((unix times, true heights above take-off)) are given: the
    true height plus a slow drift of BARO_DRIFT_M; else the tlog's (its GPS altitude's error with it). Returns the
    number of subtitles written."""
    from pomar.telemetry.tlog import read_tlog

    if layout not in SRT_LAYOUTS:
        raise ValueError(f"unknown SRT layout {layout!r} (known: {', '.join(SRT_LAYOUTS)})")
    per_s, dec, has_att, _ = SRT_LAYOUTS[layout]
    attitude = attitude and has_att
    tl = read_tlog(tlog)
    t_frames, _ = tl.frame_times(frame_count, video_start_unix, fps, clock_offset_s)
    if per_s:  # one a second over the video, at the frames' capture clock
        video_t = np.arange(0.0, frame_count / fps, 1.0 / per_s)
        t = np.interp(video_t, np.arange(frame_count) / fps, t_frames)
        ends = video_t + 1.0 / per_s
    else:
        video_t, t = np.arange(frame_count) / fps, t_frames
        ends = video_t + 1.0 / fps
    s = tl.at(t)
    # altitudes above the take-off point, as DJI's: the ground where the tlog says so, else the first position
    home_alt = tl.home_alt if tl.home_alt is not None else float(tl.position.values[0, 2])
    height = s["alt"] - home_alt
    if truth_heights is not None:
        from sim.trajectory import smooth_noise

        drift = smooth_noise(np.random.default_rng([seed, 37]), len(t), 20.0, BARO_DRIFT_M, rate_hz=per_s or fps)
        height = np.interp(t, truth_heights[0], truth_heights[1]) + drift
    home_lat, home_lon = float(tl.position.values[0, 0]), float(tl.position.values[0, 1])
    gimbal = _euler_deg(np.where(np.isfinite(s["q_gimbal"]), s["q_gimbal"], [1.0, 0, 0, 0]))
    vehicle = _euler_deg(np.where(np.isfinite(s["q_attitude"]), s["q_attitude"], [1.0, 0, 0, 0]))
    blocks = []
    for i in range(len(t)):
        stamp = datetime.fromtimestamp(t[i], timezone.utc)
        lat, lon = f"{s['lat'][i]:.{dec}f}", f"{s['lon'][i]:.{dec}f}"
        rel, absolute = height[i], s["alt"][i]
        r, p, y = gimbal[i]
        timing = f"{_srt_time(video_t[i])} --> {_srt_time(ends[i])}\n"
        if layout == "mavic3":
            body = (f'<font size="28">FrameCnt: {i + 1}, DiffTime: {1000 / fps:.0f}ms\n'
                    f"{stamp:%Y-%m-%d %H:%M:%S}.{stamp.microsecond // 1000:03d}\n"
                    f"[iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [ev: 0] [ct: 5500] [color_md : default] "
                    f"[focal_len: 24.00] [latitude: {lat}] [longitude: {lon}] [rel_alt: {rel:.3f} abs_alt: {absolute:.3f}]"
                    + (f" [gb_yaw: {y:.1f} gb_pitch: {p:.1f} gb_roll: {r:.1f}]" if attitude else "") + " </font>")
        elif layout == "air2s":
            body = (f'<font size="36">SrtCnt : {i + 1}, DiffTime : {1000 / fps:.0f}ms\n'
                    f"{stamp:%Y-%m-%d %H:%M:%S},{stamp.microsecond // 1000:03d},{stamp.microsecond % 1000:03d}\n"
                    f"[iso : 100] [shutter : 1/1000.0] [fnum : 280] [ev : 0] [ct : 5500] [color_md : default] "
                    f"[focal_len : 240] [latitude: {lat}] [longitude: {lon}] [altitude: {absolute:.6f}] </font>")
        elif layout == "mavic2":
            timing = ""
            body = (f"{stamp:%Y.%m.%d %H:%M:%S},{stamp.microsecond // 1000:03d},{stamp.microsecond % 1000:03d}\n"
                    f"[latitude : {lat}] [longtitude : {lon}] [iso : 100] [shutter : 1/60.0] [ev : 0] [fnum : 220]")
        elif layout == "p4p" and attitude:  # the Phantom 4 RTK's
            vr, vp, vy = vehicle[i]
            body = (f"F/5.6, SS 400, ISO 100, EV +0.7, GPS ({s['lon'][i]:.6f}, {s['lat'][i]:.6f}, 16), "
                    f"HOME ({home_lon:.6f}, {home_lat:.6f}, {home_alt:.2f}m), D 10.00m, H {rel:.2f}m, H.S 2.00m/s, "
                    f"V.S 0.00m/s, F.PRY ({vp:.1f}°, {vr:.1f}°, {vy:.1f}°), G.PRY ({p:.1f}°, {r:.1f}°, {y:.1f}°)")
        elif layout == "p4p":
            body = (f"F/3.2, SS 160, ISO 100, EV 0, GPS ({lon}, {lat}, 18), D 10.00m, H {rel:.2f}m, H.S 2.00m/s, "
                    "V.S 0.00m/s ")
        elif layout == "home":
            body = (f"HOME({home_lon:.4f},{home_lat:.4f}) {stamp:%Y.%m.%d %H:%M:%S}\n"
                    f"GPS({lon},{lat},16) BAROMETER:{rel:.1f}\nISO:100 Shutter:60 EV: Fnum:2.2")
        else:  # m300
            body = f"{stamp:%Y.%m.%d %H:%M:%S}\nGPS({lat},{lon},0.0M) BAROMETER:{rel:.1f}M"
        blocks.append(f"{i + 1}\n{timing}{body}\n")
    Path(out).write_text("\n".join(blocks), encoding="utf-8")
    log.info("wrote %s: %d subtitles, layout %s%s", out, len(blocks), layout, " with attitudes" if attitude else "")
    return len(blocks)


def _srt_time(t: float) -> str:
    ms = int(round(t * 1000))
    return f"{ms // 3600000:02d}:{ms // 60000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"
