"""The onboard node: frames + telemetry -> detector -> the wire, over zenoh.

For each processed frame it publishes a :class:`pomar.wire.FrameMessage` (capture time on the
autopilot clock, the telemetry sampled there, the detections); every ``keyframe_every``-th processed
frame also goes as a JPEG keyframe for the ground's structure-from-motion; camera.json goes once;
a status heartbeat goes every ``status_period_s``. A source that fails midway (a truncated video)
ends the run with an error status after everything before it was published.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from onboard.sources import LatestFrame, SourceError, VideoSource
from onboard.telemetry import read_tlog
from pomar import wire
from pomar.flight import FlightDir

log = logging.getLogger(__name__)


@dataclass
class NodeSettings:
    lockstep: bool = True  # every frame (every Nth), none dropped; False = real time, newest frame first
    every: int = 1
    keyframe_every: int = 1  # every Nth processed frame also goes as a JPEG keyframe; 0 = none
    keyframe_width: int = 0  # resize keyframes to this width (0 = native)
    jpeg_quality: int = 85
    status_period_s: float = 1.0
    clock_offset_s: float = 0.0  # camera clock minus autopilot clock, when there are no capture records


def encode_jpeg(img: np.ndarray, width: int, quality: int) -> bytes:
    import cv2

    if width and img.shape[1] != width:
        h = int(round(img.shape[0] * width / img.shape[1]))
        img = cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA)
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
        self.stats = {"frames_read": 0, "frames_processed": 0, "frames_dropped": 0, "keyframes": 0,
                      "detections": 0, "detector_seconds": 0.0, "read_to_publish_seconds": []}

    def _status(self, meta, state: str, t0: float, message: str = "") -> None:
        st = self.stats
        elapsed = max(time.monotonic() - t0, 1e-9)
        lat = st["detector_seconds"] / max(st["frames_processed"], 1)
        self.pub.publish(wire.StatusMessage(meta.flight_id, meta.drone_id, time.time(), st["frames_read"],
                                            st["frames_processed"], st["frames_dropped"],
                                            st["frames_processed"] / elapsed, lat, state, message))

    def run(self) -> dict:
        meta, cam = self.flight.meta(), self.flight.camera()
        tl = read_tlog(self.flight.tlog)
        t_frames, cap_flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, self.s.clock_offset_s)
        tel = tl.at(t_frames)
        tel["flags"] = tel["flags"] | cap_flags
        self.pub.publish(wire.CameraMessage(meta.flight_id, meta.drone_id, cam.to_dict(), meta.fps, meta.video_start_utc))
        source = VideoSource(self.flight.video, self.s.every, expected_frames=meta.frame_count)
        frames = source if self.s.lockstep else LatestFrame(source, fps=meta.fps)
        t0 = last_status = time.monotonic()
        processed = 0
        error = None
        try:
            for i, img in frames:
                t_read = time.perf_counter()
                td = time.perf_counter()
                boxes, scores = self.detector.detect(i, img)
                self.stats["detector_seconds"] += time.perf_counter() - td
                telemetry = wire.Telemetry(float(tel["lat"][i]), float(tel["lon"][i]), float(tel["alt"][i]),
                                           tuple(map(float, tel["q_attitude"][i])), tuple(map(float, tel["q_gimbal"][i])),
                                           int(tel["gps_fix"][i]), float(tel["h_acc"][i]), int(tel["flags"][i]))
                self.pub.publish(wire.FrameMessage(meta.flight_id, meta.drone_id, i, float(t_frames[i]), telemetry,
                                                   img.shape[1], img.shape[0], boxes, scores))
                if self.s.keyframe_every and processed % self.s.keyframe_every == 0:
                    jpeg = encode_jpeg(img, self.s.keyframe_width, self.s.jpeg_quality)
                    self.pub.publish(wire.KeyframeMessage(meta.flight_id, meta.drone_id, i, jpeg))
                    self.stats["keyframes"] += 1
                self.stats["read_to_publish_seconds"].append(time.perf_counter() - t_read)
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
            "read_to_publish_median_s": float(np.median(lat)),
            "bytes_per_message": {k: self.pub.bytes[k] / max(self.pub.sent[k], 1) for k in wire.KINDS},
            "telemetry_flagged_frames": int((tel["flags"] != 0).sum()), "error": str(error) if error else None,
        }
        # what the link must carry at the video's frame rate with these settings
        per_frame = summary["bytes_per_message"]["frames"] + (
            summary["bytes_per_message"]["keyframes"] / self.s.keyframe_every if self.s.keyframe_every else 0)
        summary["link_bytes_per_s_at_video_fps"] = per_frame * meta.fps / self.s.every
        if error:
            raise SourceError(f"{error} — summary: {summary}")
        return summary
