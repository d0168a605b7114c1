"""Drone telemetry logs behind one interface (:class:`TelemetryLog`), one reader module per format.

    from pomar.telemetry import read_log
    tl = read_log("flight.bin")              # .tlog, .bin (ArduPilot DataFlash), .ulg (PX4), .SRT (DJI)
    t, flags = tl.frame_times(n_frames, video_start_unix, fps)
    s = tl.at(t)                              # lat, lon, alt, q_attitude, q_gimbal, gps_fix, h_acc, flags
    tl.summary_dict()                         # what `python -m onboard telemetry LOG --json OUT` writes

The format is taken from the file's first bytes (ULog and DataFlash have magic numbers, an SRT is text that
starts with a subtitle number), else from its suffix.
"""

from __future__ import annotations

from pathlib import Path

from pomar.telemetry.base import Flags, Gap, Series, TelemetryError, TelemetryLog, existing

__all__ = ["Flags", "Gap", "Series", "TelemetryError", "TelemetryLog", "FORMATS", "detect_format", "mount_arguments", "read_log"]

#: format -> (reader module, reader function)
FORMATS = {"tlog": ("pomar.telemetry.tlog", "read_tlog"), "dataflash": ("pomar.telemetry.dataflash", "read_dataflash"),
           "ulog": ("pomar.telemetry.ulog", "read_ulog"), "srt": ("pomar.telemetry.srt", "read_srt")}
SUFFIXES = {".tlog": "tlog", ".bin": "dataflash", ".ulg": "ulog", ".srt": "srt"}


def detect_format(path: str | Path) -> str:
    path = existing(path)
    with open(path, "rb") as f:
        head = f.read(64)
    if head.startswith(b"ULog"):
        return "ulog"
    if head[:2] == b"\xa3\x95":
        return "dataflash"
    text = head.lstrip(b"\xef\xbb\xbf").lstrip()
    if text[:1].isdigit() and b"-->" in open(path, "rb").read(512):
        return "srt"
    if path.suffix.lower() in SUFFIXES:
        return SUFFIXES[path.suffix.lower()]
    if len(head) >= 9 and head[8] in (0xFD, 0xFE):  # a .tlog record: 8-byte time, then a MAVLink packet
        return "tlog"
    raise TelemetryError(f"{path}: not a telemetry log this project reads (.tlog, DataFlash .bin, PX4 .ulg, DJI .SRT)")


def read_log(path: str | Path, max_gap_s: float = 1.0, format: str | None = None) -> TelemetryLog:
    """Read any supported log; ``format`` overrides the detection."""
    import importlib

    fmt = format or detect_format(path)
    if fmt not in FORMATS:
        raise TelemetryError(f"{path}: unknown telemetry format {fmt!r} (known: {', '.join(FORMATS)})")
    module, func = FORMATS[fmt]
    return getattr(importlib.import_module(module), func)(path, max_gap_s=max_gap_s)


def mount_arguments(parser) -> None:
    """The command-line options for a camera on a fixed mount (``TelemetryLog.at``'s mount_tilt_deg and
    mount_yaw_deg), for logs without gimbal attitudes: one declaration for every command that reads a log."""
    parser.add_argument("--camera-tilt-deg", type=float,
                        help="for a log without gimbal attitudes: the camera's fixed pitch below the vehicle's horizon "
                             "(90 = straight down); frames are flagged FIXED_MOUNT")
    parser.add_argument("--camera-yaw-deg", type=float, default=0.0,
                        help="with --camera-tilt-deg: the camera's heading from the vehicle's nose, or from the "
                             "direction of flight where the log has no vehicle attitude (90 = looking right of the "
                             "track; default 0)")
