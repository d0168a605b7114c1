"""The onboard node: frames + telemetry -> detector -> the wire, over zenoh.

For each processed frame it publishes a :class:`pomar.wire.FrameMessage` (capture time on the
autopilot clock, the telemetry sampled there, the detections); every ``keyframe_every``-th processed
frame also goes as a JPEG keyframe for the ground's structure-from-motion; camera.json goes once;
a status heartbeat goes every ``status_period_s``. A source that fails midway (a truncated video)
ends the run with an error status after everything before it was published.
"""

from __future__ import annotations

import logging
import resource
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from onboard.sources import LatestFrame, SourceError, VideoSource
from pomar.telemetry import Flags, TelemetryError, read_log
from pomar import wire
from pomar.apple_scale import policy_for, scale_summary, telemetry_radius_px
from pomar.flight import FlightDir

log = logging.getLogger(__name__)


class KeyframePolicy:
    """Which processed frames also go as JPEG keyframes: every D metres flown (by the telemetry's position), every
    S seconds of capture time, or every Nth processed frame, the first of these given; none given, every
    DEFAULT_EVERY_S. The first frame always goes."""

    #: One keyframe per 0.2 s of flight whatever the frame rate (every 2nd frame at 10 fps, every 6th at 30 fps): a
    #: fixed frame count would triple the link's load and the ground's tracking at 30 fps.
    DEFAULT_EVERY_S = 0.2
    #: A frame up to this share of S early counts as due: capture times jitter by a few milliseconds, and a frame
    #: just short of S would otherwise push the keyframe a whole frame later.
    EARLY = 0.1

    def __init__(self, every: int | None = None, every_s: float | None = None, every_m: float | None = None):
        if every is None and every_s is None and every_m is None:
            every_s = self.DEFAULT_EVERY_S
        self.every, self.every_s, self.every_m = every or 0, every_s or 0.0, every_m or 0.0
        self._n = 0
        self._last_t = None
        self._last_pos = None

    @property
    def active(self) -> bool:
        return bool(self.every or self.every_s or self.every_m)

    def due(self, t: float, lat: float = float("nan"), lon: float = float("nan"), alt: float = float("nan")) -> bool:
        n, self._n = self._n, self._n + 1
        if not self.active:
            return False
        if self._last_t is None:
            ok = True
        elif self.every_m:
            from pomar.geo import Origin

            if self._last_pos is None or not np.isfinite([lat, lon, alt]).all():
                ok = self._last_t is not None and t - self._last_t > 2.0  # no position: fall back to time
            else:
                d = Origin(*self._last_pos).to_enu(lat, lon, alt)
                ok = float(np.hypot(d[0], d[1])) >= self.every_m
        elif self.every_s:
            ok = t - self._last_t >= self.every_s * (1.0 - self.EARLY)
        else:
            ok = n % self.every == 0
        if ok:
            self._last_t = t
            if np.isfinite([lat, lon, alt]).all():
                self._last_pos = (float(lat), float(lon), float(alt))
        return ok


@dataclass
class NodeSettings:
    lockstep: bool = True  # every frame (every Nth), none dropped; False = real time, newest frame first
    every: int = 1
    # which frames also go as JPEG keyframes (KeyframePolicy): every Nth processed frame (0 = none), or every S
    # seconds of capture time, or every D metres flown; none set: every KeyframePolicy.DEFAULT_EVERY_S
    keyframe_every: int | None = None
    keyframe_every_s: float | None = None
    keyframe_every_m: float | None = None
    keyframe_width: int = 0  # resize keyframes to this width (0 = native)
    jpeg_quality: int = 85
    status_period_s: float = 1.0
    clock_offset_s: float = 0.0  # camera clock minus autopilot clock, when there are no capture records
    log: str | None = None  # a telemetry log of any supported format, instead of the flight directory's .tlog
    camera_tilt_deg: float | None = None  # for logs without gimbal attitudes: the camera's fixed pitch below horizon
    # with camera_tilt_deg: the camera's heading from the vehicle's nose, or from the track where the log has no
    # vehicle attitude (most DJI .SRTs); 90 = looking right, as when flying along a row and looking across it
    camera_yaw_deg: float = 0.0
    detector_scale: str = "auto"  # frames resized so apples reach the model at its size (pomar.apple_scale); off; or a number


def sent_keyframe_width(width: int, image_width: int) -> int:
    """The width keyframes are sent at: ``width`` (0 = native), never more than the image's own (an enlarged JPEG
    costs link bytes and adds nothing)."""
    return min(width, image_width) if width else image_width


def encode_jpeg(img: np.ndarray, width: int, quality: int) -> bytes:
    import cv2

    w = sent_keyframe_width(width, img.shape[1])
    if w < img.shape[1]:
        img = cv2.resize(img, (w, int(round(img.shape[0] * w / img.shape[1]))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


class OnboardNode:
    def __init__(self, flight_dir, publisher, detector, settings: NodeSettings | None = None):
        self.flight = FlightDir(flight_dir)
        self.pub = publisher
        self.detector = detector
        self.s = settings or NodeSettings()
        self.inputs = None  # check_inputs()'s result
        self.stats = {"frames_read": 0, "frames_processed": 0, "frames_dropped": 0, "keyframes": 0,
                      "detections": 0, "detector_seconds": 0.0, "read_to_publish_seconds": [], "scales": []}

    def _status(self, meta, state: str, t0: float, message: str = "") -> None:
        st = self.stats
        elapsed = max(time.monotonic() - t0, 1e-9)
        lat = st["detector_seconds"] / max(st["frames_processed"], 1)
        self.pub.publish(wire.StatusMessage(meta.flight_id, meta.drone_id, time.time(), st["frames_read"],
                                            st["frames_processed"], st["frames_dropped"],
                                            st["frames_processed"] / elapsed, lat, state, message))

    def check_inputs(self):
        """Read and cross-check the flight's files before anything is published: flight.json, camera.json against
        the video's size, and a telemetry log with positions over the video. Raises FlightFormatError,
        CameraFileError, VideoError or TelemetryError naming the file."""
        from pomar.flight import FlightFormatError
        from pomar.video import video_size

        meta, cam = self.flight.meta(), self.flight.camera()
        w, h = video_size(self.flight.video)
        if (cam.width, cam.height) != (w, h):
            raise FlightFormatError(f"{self.flight.path / 'camera.json'} is for {cam.width}x{cam.height} images, but "
                                    f"{self.flight.video} is {w}x{h}")
        log_path = Path(self.s.log) if self.s.log else self.flight.telemetry_log
        tl = read_log(log_path)
        if not len(tl.position):
            raise TelemetryError(f"{log_path}: no position in the log; frames cannot be placed")
        t_frames, cap_flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, self.s.clock_offset_s)
        tel = tl.at(t_frames, self.s.camera_tilt_deg, self.s.camera_yaw_deg)
        tel["flags"] = tel["flags"] | cap_flags
        # the wire takes a position whole or not at all (pomar.wire): a part of one is none
        part = ~np.isfinite(np.column_stack([tel["lat"], tel["lon"], tel["alt"]])).all(1)
        for k in ("lat", "lon", "alt", "height"):
            tel[k] = np.where(part, np.nan, tel[k])
        tel["flags"] = tel["flags"] | np.where(part, int(Flags.NO_POSITION), 0)
        if meta.frame_count and (tel["flags"] & Flags.NO_POSITION).all():
            raise TelemetryError(f"{log_path}: its positions span {tl.position.t[0]:.1f}-{tl.position.t[-1]:.1f} "
                                 f"(unix s), the video's frames {t_frames[0]:.1f}-{t_frames[-1]:.1f}: no frame falls "
                                 f"within the log")
        if meta.frame_count and (tel["flags"] & Flags.NO_GIMBAL).all():
            log.warning("%s has no camera attitude (no gimbal reports): frames get poses from the images alone; "
                        "give the camera's mount tilt (--camera-tilt-deg) to use the vehicle's attitude", log_path)
        tel["expected_radius_px"] = telemetry_radius_px(cam.fx, tel)
        if self.s.detector_scale == "auto" and not np.isfinite(tel["expected_radius_px"]).any():
            log.warning("%s places no take-off point (no relative altitude) or no camera attitude: the apple size "
                        "cannot be foreseen, and frames go to the detector at their own size (--detector-scale N sets "
                        "one scale)", log_path)
        self.inputs = (meta, cam, t_frames, tel)
        return self.inputs

    def run(self) -> dict:
        meta, cam, t_frames, tel = self.inputs or self.check_inputs()
        scaling = policy_for(self.detector, self.s.detector_scale)  # the detector may come after check_inputs()
        self.pub.publish(wire.CameraMessage(meta.flight_id, meta.drone_id, cam.to_dict(), meta.fps, meta.video_start_utc,
                                            sent_keyframe_width(self.s.keyframe_width, cam.width)))
        source = VideoSource(self.flight.video, self.s.every, expected_frames=meta.frame_count)
        frames = source if self.s.lockstep else LatestFrame(source, fps=meta.fps)
        t0 = last_status = time.monotonic()
        processed = 0
        policy = KeyframePolicy(self.s.keyframe_every, self.s.keyframe_every_s, self.s.keyframe_every_m)
        pacer = None if self.s.lockstep else scaling.pacer()  # live: enlarge frames only while there is time
        period_s = self.s.every / meta.fps if meta.fps else 0.0
        error = None
        try:
            for i, img in frames:
                t_read = time.perf_counter()
                scale = scaling.scale(float(tel["expected_radius_px"][i]))
                if pacer is not None:
                    scale = pacer.cap(scale, img.shape[1], img.shape[0], period_s)
                td = time.perf_counter()
                boxes, scores = self.detector.detect(i, img, scale)
                det_s = time.perf_counter() - td
                self.stats["detector_seconds"] += det_s
                self.stats["scales"].append(scale)
                telemetry = wire.Telemetry(float(tel["lat"][i]), float(tel["lon"][i]), float(tel["alt"][i]),
                                           tuple(map(float, tel["q_attitude"][i])), tuple(map(float, tel["q_gimbal"][i])),
                                           int(tel["gps_fix"][i]), float(tel["h_acc"][i]), int(tel["flags"][i]),
                                           float(tel["height"][i]), float(tel["height_acc"][i]))
                due = policy.due(float(t_frames[i]), telemetry.lat, telemetry.lon, telemetry.alt)
                self.pub.publish(wire.FrameMessage(meta.flight_id, meta.drone_id, i, float(t_frames[i]), telemetry,
                                                   img.shape[1], img.shape[0], boxes, scores, scale=scale,
                                                   keyframe=due))
                if due:
                    jpeg = encode_jpeg(img, self.s.keyframe_width, self.s.jpeg_quality)
                    self.pub.publish(wire.KeyframeMessage(meta.flight_id, meta.drone_id, i, jpeg))
                    self.stats["keyframes"] += 1
                self.stats["read_to_publish_seconds"].append(time.perf_counter() - t_read)
                if pacer is not None:
                    pacer.observe(det_s, img.shape[1], img.shape[0], scale)
                processed += 1
                self.stats["frames_processed"] = processed
                self.stats["detections"] += len(boxes)
                if self.s.lockstep:
                    self.stats["frames_read"] = processed
                else:
                    self.stats["frames_read"], self.stats["frames_dropped"] = frames.read, frames.dropped
                if time.monotonic() - last_status >= self.s.status_period_s:
                    self._status(meta, "running", t0)
                    last_status = time.monotonic()
        except SourceError as exc:
            error = exc
            log.error("%s", exc)
        self._status(meta, "error" if error else "finished", t0, str(error) if error else "")
        elapsed = time.monotonic() - t0
        lat = np.array(self.stats["read_to_publish_seconds"]) if self.stats["read_to_publish_seconds"] else np.zeros(1)
        summary = {
            "flight": meta.flight_id, "frames_processed": processed, "frames_dropped": self.stats["frames_dropped"],
            "keyframes": self.stats["keyframes"], "detections": self.stats["detections"],
            "seconds": elapsed, "frames_per_s": processed / max(elapsed, 1e-9),
            "detector_latency_s": self.stats["detector_seconds"] / max(processed, 1),
            "detector_scale": scale_summary(self.stats["scales"]),
            "detector_scale_capped": pacer.capped if pacer is not None else 0,  # frames the pace kept smaller
            "read_to_publish_median_s": float(np.median(lat)),
            "bytes_per_message": {k: self.pub.bytes[k] / max(self.pub.sent[k], 1) for k in wire.KINDS},
            "telemetry_flagged_frames": int((tel["flags"] != 0).sum()), "error": str(error) if error else None,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        }
        # what the link must carry at the video's frame rate with these settings
        kf_share = self.stats["keyframes"] / max(processed, 1)
        per_frame = summary["bytes_per_message"]["frames"] + summary["bytes_per_message"]["keyframes"] * kf_share
        summary["link_bytes_per_s_at_video_fps"] = per_frame * meta.fps / self.s.every
        if error:
            exc = SourceError(f"{error} (after {processed} frames)")
            exc.summary = summary
            raise exc
        return summary
