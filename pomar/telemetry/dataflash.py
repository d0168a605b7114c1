"""ArduPilot's on-board DataFlash log (``.bin``), through pymavlink's DFReader (``mavutil``).

- position: ``POS`` (Lat, Lng, Alt MSL); without it, ``GPS`` (Lat, Lng, Alt).
- GPS: ``GPS`` (Status = fix type, NSats) and, where logged, ``GPA`` (HAcc, VAcc: the receiver's stated accuracy in
  metres, the last at or before each GPS record of the same instance). HDop is no accuracy in metres: without GPA the
  accuracy is unstated.
- attitude: ``ATT`` (Roll, Pitch, Yaw in degrees, NED).
- gimbal: ``MNT`` (newer firmware: Roll, Pitch, YawE = yaw in the earth frame; older: ActRoll, ActPitch, ActYaw
  relative to the vehicle) or ``GIMB``.
- camera events: ``CAM`` (camera feedback, ``Img`` = image number from 1) or ``TRIG`` (trigger), by instance 0.

Clock: every message carries TimeUS, the autopilot's boot time; DFReader maps it to UTC with the GPS
messages' week and milliseconds (GWk, GMS). A log without GPS time stays on boot time and says so. A file cut
mid-record keeps every whole record before the cut, and says so.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from pathlib import Path

import numpy as np

from pomar.rotations import ned_euler_to_rotation, rotation_to_quat_wxyz
from pomar.telemetry.base import Series, TelemetryError, TelemetryLog, existing, height_fields

log = logging.getLogger(__name__)

TYPES = ["POS", "GPS", "GPA", "ATT", "MNT", "GIMB", "CAM", "TRIG", "PARM"]


def read_dataflash(path: str | Path, max_gap_s: float = 1.0) -> TelemetryLog:
    from pymavlink import DFReader

    path = existing(path)
    t0 = time.perf_counter()
    try:
        df = DFReader.DFReader_binary(str(path), zero_time_base=False)
    except Exception as exc:
        raise TelemetryError(f"{path}: not a readable DataFlash log ({exc})") from None
    problems: list[str] = []
    rows: dict[str, list] = {k: [] for k in TYPES}
    counts: Counter = Counter()
    params: dict[str, float] = {}
    try:
        while True:
            m = df.recv_match(type=TYPES)
            if m is None:
                break
            kind = m.get_type()
            counts[kind] += 1
            if getattr(m, "I", 0) not in (0, None) and kind in ("GPS", "GPA", "CAM", "TRIG", "MNT"):
                continue  # the first instance of each (GPS 0, camera 0, mount 0)
            if kind == "PARM":
                params[m.Name] = m.Value  # the last value logged (a parameter set in flight is logged again)
                continue
            rows[kind].append((m._timestamp, m))
    except Exception as exc:  # a damaged record DFReader cannot step over: keep what was read
        problems.append(f"stopped at a damaged record ({exc}): everything before it is used")
    left = unread_tail(path.read_bytes(), {k: f.len for k, f in df.formats.items()})
    if left > 0:
        problems.append(f"the last {left} bytes are no whole record (a record cut short: file cut?): everything "
                        "before is used")
    if not any(rows.values()):
        raise TelemetryError(f"{path}: no position, attitude or camera messages (not an ArduPilot DataFlash log?)")
    gps = rows["GPS"]
    has_utc = any(getattr(m, "GWk", 0) for _, m in gps)
    clock = "ArduPilot boot time mapped to UTC by GPS week and ms (DFReader)" if has_utc else "ArduPilot boot time"
    if not has_utc:
        problems.append("no GPS time in the log: times are seconds since the autopilot booted")

    def series(kind, fields, d, scale=None, keep=None):
        r = [(t, [getattr(m, f) for f in fields]) for t, m in rows[kind] if keep is None or keep(m)]
        if not r:
            return Series.empty(d)
        v = np.array([x for _, x in r], float)
        return Series.of([t for t, _ in r], v if scale is None else scale(v), d)

    def not_origin(m):
        return not (m.Lat == 0 and m.Lng == 0)

    position = series("POS", ["Lat", "Lng", "Alt"], 3, keep=not_origin)
    if not len(position):
        position = series("GPS", ["Lat", "Lng", "Alt"], 3, keep=lambda m: m.Status >= 2 and not_origin(m))
        if len(position):
            problems.append("no POS messages: positions are the GPS receiver's")
        else:
            problems.append("no position (no POS, no GPS with a fix)")
    gps_s = series("GPS", ["Status", "NSats", "NSats", "NSats"], 4)
    if len(gps_s):  # fix, h_acc, v_acc, satellites: the accuracies from GPA where logged, else unstated (NaN)
        v = gps_s.values.copy()
        v[:, 1:3] = np.nan
        acc = [(t, m.HAcc, m.VAcc) for t, m in rows["GPA"]]
        if acc:  # ArduPilot logs GPA with each GPS record, at its time: the last one at or before it, within 0.5 s
            at, hv = np.array([a[0] for a in acc]), np.array([a[1:] for a in acc], float)
            k = np.searchsorted(at, gps_s.t, side="right") - 1
            near = (k >= 0) & (gps_s.t - at[np.clip(k, 0, None)] <= 0.5)
            v[near, 1:3] = hv[k[near]]
        gps_s = Series.of(list(gps_s.t), v, 4)
    attitude = series("ATT", ["Roll", "Pitch", "Yaw"], 4,
                      scale=lambda v: rotation_to_quat_wxyz(ned_euler_to_rotation(v[:, 0], v[:, 1], v[:, 2])))
    gimbal = Series.empty(4)
    if rows["MNT"]:
        m0 = rows["MNT"][0][1]
        if "YawE" in m0.get_fieldnames():
            gimbal = series("MNT", ["Roll", "Pitch", "YawE"], 4,
                            scale=lambda v: rotation_to_quat_wxyz(ned_euler_to_rotation(v[:, 0], v[:, 1], v[:, 2])))
        else:
            problems.append("MNT without an earth-frame yaw (old firmware): mount angles not used")
    elif rows["GIMB"]:
        problems.append("GIMB messages (Solo gimbal) are not read")
    cap_kind = "CAM" if rows["CAM"] else ("TRIG" if rows["TRIG"] else None)
    captures = {}
    if cap_kind:
        for k, (t, m) in enumerate(rows[cap_kind]):
            idx = getattr(m, "Img", None)
            captures[int(idx) - 1 if idx else k] = float(t)  # Img counts from 1; frames from 0
    else:
        problems.append("no CAM or TRIG events: frame times come from the video's clock")
    # POS's RelHomeAlt beside its Alt gives the home point's altitude
    home = [m.Alt - m.RelHomeAlt for _, m in rows["POS"] if "RelHomeAlt" in m.get_fieldnames() and m.RelHomeAlt]
    # the EKF's height source, by its parameters: how far the height above take-off can be trusted
    tl = TelemetryLog(str(path), position, gps_s, attitude, gimbal, captures, cap_kind, clock, None, counts,
                      max_gap_s=max_gap_s, format="dataflash", altitude_reference="msl", problems=problems,
                      home_alt=float(np.median(home)) if home else None, **height_fields(params, gps_s.values[:, 2]))
    tl.parse_seconds = time.perf_counter() - t0
    return tl


def unread_tail(data: bytes, lengths: dict[int, int]) -> int:
    """Bytes after the end of the last whole record (header A3 95, a known type, its format's length); bytes that
    are no record in the middle are stepped over, as DFReader does. DFReader's own offset does not say this: it
    stops short of, or past, a header cut 1-3 bytes in."""
    n, pos, end = len(data), 0, 0
    while pos + 3 <= n:
        if data[pos] == 0xA3 and data[pos + 1] == 0x95 and data[pos + 2] in lengths:
            if pos + lengths[data[pos + 2]] > n:
                break
            pos += lengths[data[pos + 2]]
            end = pos
        else:
            pos += 1
    return n - end
