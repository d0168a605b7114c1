"""A flight directory built from what a user has: a video, a telemetry log of any supported format, and a camera.

    python -m onboard run --video DJI_0001.MP4 --log DJI_0001.SRT --camera phantom-4-pro
    python -m ground replay --video V.MP4 --log 00000042.BIN --camera camera.json

- frame rate and frame count: the container's (OpenCV);
- start time: the log's camera events (frame 0's capture), else the log's own video clock (a DJI .SRT), else the
  container's creation time (the MP4 ``mvhd`` box), else the log's first position, each reported with the clock
  offset between the container and the log where both are known;
- intrinsics: a camera.json, or a built-in camera by name (:data:`CAMERAS`; from published sensor widths and
  focal lengths, scaled to the video's width: approximate, calibrate for best results).

The directory (``flight.json``, ``camera.json``, a link to the video) goes to ``out``; ``flight.json`` names the
log (``telemetry_log``), which the onboard node then reads instead of ``telemetry.tlog``.
"""

from __future__ import annotations

import json
import logging
import os
import re
import struct
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from pomar.camera import Camera, CameraFileError
from pomar.flight import CAMERA, FLIGHT, VIDEO, FlightFormatError, check_id
from pomar.telemetry import TelemetryLog, read_log
from pomar.video import video_info

log = logging.getLogger(__name__)

#: Built-in cameras: name -> (sensor width mm, focal length mm, what). Video uses the sensor's full width (DJI
#: crops the height for 16:9), so fx = focal / sensor width * video width.
CAMERAS = {
    "phantom-4-pro": (13.2, 8.8, "DJI Phantom 4 Pro / Pro V2.0: 1-inch 20 MP, 24 mm equivalent, 84 deg diagonal"),
    "phantom-4-rtk": (13.2, 8.8, "DJI Phantom 4 RTK: 1-inch 20 MP, 24 mm equivalent"),
    "mavic-2-pro": (13.2, 10.26, "DJI Mavic 2 Pro (Hasselblad L1D-20c): 1-inch, 28 mm equivalent"),
    "mavic-3": (17.3, 12.29, "DJI Mavic 3 (Hasselblad L2D-20c): 4/3-inch, 24 mm equivalent"),
    "air-2s": (13.2, 8.38, "DJI Air 2S: 1-inch, 22 mm equivalent"),
    "mini-2": (6.17, 4.49, "DJI Mini 2: 1/2.3-inch, 24 mm equivalent"),
    "mini-3-pro": (9.7, 6.72, "DJI Mini 3 Pro: 1/1.3-inch, 24 mm equivalent"),
}


def _key(name: str) -> str:
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def camera_for(spec: str, width: int, height: int) -> tuple[Camera, str]:
    """A camera.json path or a built-in camera's name -> (Camera for width x height, where it came from)."""
    p = Path(spec)
    if p.suffix.lower() == ".json" or p.exists():
        cam = Camera.load(p)
        if (cam.width, cam.height) != (width, height):
            raise CameraFileError(f"{p} is for {cam.width}x{cam.height} images, but the video is {width}x{height}")
        return cam, str(p)
    key = _key(spec)
    if key not in CAMERAS:
        raise CameraFileError(f"unknown camera {spec!r}: give a camera.json or one of {', '.join(sorted(CAMERAS))}")
    sensor_mm, focal_mm, what = CAMERAS[key]
    f = focal_mm / sensor_mm * width
    return Camera(width, height, f, f, width / 2.0, height / 2.0), f"built-in {key} ({what})"


def mp4_creation_time(path: str | Path) -> float | None:
    """The MP4/MOV container's creation time (``moov/mvhd``, seconds since 1904, UTC by the spec), unix seconds; None
    when absent or zero."""
    epoch_1904 = -2082844800
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return None

    def boxes(start, end):
        pos = start
        while pos + 8 <= end:
            size, kind = struct.unpack(">I4s", data[pos:pos + 8])
            head = 8
            if size == 1:
                size, head = struct.unpack(">Q", data[pos + 8:pos + 16])[0], 16
            elif size == 0:
                size = end - pos
            if size < head:
                return
            yield kind, pos + head, pos + size
            pos += size

    for kind, a, b in boxes(0, len(data)):
        if kind == b"moov":
            for k2, c, _ in boxes(a, b):
                if k2 == b"mvhd":
                    version = data[c]
                    t = struct.unpack(">Q", data[c + 4:c + 12])[0] if version == 1 else struct.unpack(">I", data[c + 4:c + 8])[0]
                    return float(t + epoch_1904) if t else None
    return None


def start_time(tl: TelemetryLog, fps: float, container_unix: float | None, clock_offset_s: float = 0.0):
    """(video start on the log's clock, how it was found, container minus log (s) or None)."""
    if tl.captures:
        i0 = min(tl.captures)
        t0, how = tl.captures[i0] - i0 / fps, f"the log's camera events ({tl.capture_message})"
    elif len(tl.video_clock) >= 2:
        t0, how = float(tl.log_time_of_video(0.0)), "the subtitles' times"
    elif container_unix is not None:
        t0, how = tl.log_clock(container_unix, clock_offset_s), "the container's creation time"
    elif len(tl.position):
        t0, how = float(tl.position.t[0]), "the log's first position (no camera events, no container time)"
    else:
        raise FlightFormatError(f"{tl.path}: no camera events, no positions: the video cannot be placed in time")
    offset = container_unix - t0 if container_unix is not None and not how.startswith("the container") else None
    return t0, how, offset


#: The most a camera's clock and its log's may differ and still be one flight: the widest time-zone offset (14 h:
#: DJI writes local time without a zone) and an hour's drift.
MAX_CLOCK_DIFFERENCE_S = 15 * 3600.0


def check_same_flight(log_path, video: Path, t0: float, offset: float | None, clock_offset_s: float) -> None:
    """Refuse a log whose clock puts the video's start ``t0`` further than MAX_CLOCK_DIFFERENCE_S from the container's
    creation time (``offset``: container minus log): a log of another flight, refused as a .tlog whose positions
    miss the video is. FlightFormatError names the file, both times and the way out."""
    if offset is None or abs(offset - clock_offset_s) <= MAX_CLOCK_DIFFERENCE_S:
        return

    def when(t):
        return datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%d %H:%M")

    raise FlightFormatError(f"{log_path}: the log puts the video's start at {when(t0)}, its container "
                            f"({video.name}) says {when(t0 + offset)} ({offset / 86400.0:+.1f} days): a log of another "
                            "flight? If the camera's clock was wrong, give the difference, container minus log, as "
                            f"--clock-offset-s {offset:.0f}")


def describe(report: dict) -> str:
    """One line on a built flight: frames, start and how it was found, the clock offset, the camera."""
    offset = report["container_minus_log_s"]
    return (f"flight {report['flight_id']}: {report['frames']} frames at {report['fps']:.3f} fps, start from "
            f"{report['start_from']}" + (f" (container - log {offset:+.2f} s)" if offset is not None else "")
            + f"; camera {report['camera']}; directory {report['flight_dir']}")


def assemble_flight(video: str | Path, log_path: str | Path, camera: str, out: str | Path,
                    flight_id: str | None = None, drone_id: str = "drone-1", clock_offset_s: float = 0.0) -> dict:
    """Write the flight directory ``out`` for ``video`` + ``log_path`` + ``camera``; returns what was found (start
    time and how, clock offset, camera source, the log's problems)."""
    video, log_path, out = Path(video).resolve(), Path(log_path).resolve(), Path(out)
    fps, n, w, h = video_info(video)
    cam, cam_source = camera_for(camera, w, h)
    tl = read_log(log_path)
    if not len(tl.position):
        raise FlightFormatError(f"{log_path}: no position in the log: the frames cannot be placed")
    container = mp4_creation_time(video)
    t0, how, offset = start_time(tl, fps, container, clock_offset_s)
    check_same_flight(log_path, video, t0, offset, clock_offset_s)
    t_end = t0 + (n - 1) / fps
    if tl.position.t[-1] < t0 or tl.position.t[0] > t_end:
        raise FlightFormatError(f"{log_path}: its positions span {tl.position.t[0]:.1f}-{tl.position.t[-1]:.1f} (unix s), "
                                f"the video ({video.name}, start from {how}) {t0:.1f}-{t_end:.1f}: they do not overlap")
    flight_id = check_id("flight_id", flight_id or _key(video.stem) or "flight")
    out.mkdir(parents=True, exist_ok=True)
    link = out / VIDEO
    if link.is_symlink() or link.exists():
        link.unlink()
    os.symlink(video, link)
    cam_d = cam.to_dict()
    cam_d["source"] = cam_source
    (out / CAMERA).write_text(json.dumps(cam_d, indent=2) + "\n")
    meta = {"flight_id": flight_id, "drone_id": check_id("drone_id", drone_id),
            "video_start_utc": datetime.fromtimestamp(t0, timezone.utc).isoformat(timespec="microseconds"),
            "video_start_unix": t0, "fps": fps, "frame_count": n, "width": w, "height": h,
            "telemetry_log": str(log_path), "telemetry_format": tl.format, "start_from": how,
            "container_minus_log_s": offset, "camera_source": cam_source}
    (out / FLIGHT).write_text(json.dumps(meta, indent=2) + "\n")
    covered = float(np.clip((min(tl.position.t[-1], t_end) - max(tl.position.t[0], t0)) / max(t_end - t0, 1e-9), 0, 1))
    if covered < 0.99:
        tl.problems.append(f"the log's positions cover {covered:.0%} of the video: frames outside them are flagged "
                           "NO_POSITION and get poses from the images alone")
    report = {"flight_dir": str(out), "flight_id": flight_id, "start_unix": t0, "start_from": how,
              "container_minus_log_s": offset, "camera": cam_source, "fps": fps, "frames": n, "size": [w, h],
              "log_format": tl.format, "video_covered_by_positions": covered, "problems": list(tl.problems)}
    log.info("flight %s: %d frames at %.3f fps, start %s from %s%s; camera %s", flight_id, n, fps,
             meta["video_start_utc"], how, f", container - log {offset:+.2f} s" if offset is not None else "", cam_source)
    return report
