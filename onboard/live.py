"""The onboard node live: a camera (or stream) + a live MAVLink link -> detector -> zenoh.

    python -m onboard live --camera 0 --mavlink udpin:127.0.0.1:14550 --camera-json camera.json --flight-id F

Frames come from OpenCV (a camera index, a stream URL, or a file played at its own rate); the node
always takes the newest frame and counts the ones it had no time for. Each frame's capture time is
the companion computer's clock when the frame was read, plus ``clock_offset_s`` (camera minus
autopilot clock); its telemetry is sampled there from the live link, once every stream has a sample
after the capture (at most ``telemetry_max_wait_s`` after it; the frame's flags say what was missing). Keyframes go every N frames, S seconds or D
metres (:class:`onboard.node.KeyframePolicy`).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from onboard.node import KeyframePolicy, encode_jpeg, sent_keyframe_width
from onboard.sources import LatestFrame, VideoSource
from pomar import wire
from pomar.camera import Camera
from pomar.apple_scale import policy_for, scale_summary, telemetry_radius_px

log = logging.getLogger(__name__)


class StampedFrames(LatestFrame):
    """:class:`LatestFrame` that also tells when (wall clock, unix s) each handed-out frame was read."""

    def __init__(self, source, fps=None):
        self.read_time: dict[int, float] = {}
        super().__init__(source, fps)

    def _run(self):
        src = self.source

        def stamped():
            for i, img in src:
                self.read_time[i] = time.time()
                for old in [k for k in self.read_time if k < i - 100]:
                    del self.read_time[old]
                yield i, img

        self.source = stamped()
        super()._run()


def sample_when_bracketed(telemetry, t: float, deadline: float) -> dict:
    """The telemetry at time t, once every stream has a sample after t (interpolation, not extrapolation),
    or at the deadline (wall clock) with whatever there is: the sample's flags say what was missing."""
    while True:
        snap = telemetry.snapshot()
        streams = [x for x in (snap.position, snap.attitude, snap.gimbal) if len(x)]
        if (streams and all(x.t[-1] >= t for x in streams)) or time.time() >= deadline:
            return snap.at(np.array([t]))
        time.sleep(0.02)


def run_live(camera_url, telemetry, camera: dict, flight_id: str, drone_id: str, publisher, detector,
             keyframes: KeyframePolicy, keyframe_width: int = 960, jpeg_quality: int = 85, clock_offset_s: float = 0.0,
             telemetry_max_wait_s: float = 1.0, play_fps: float | None = None, max_frames: int | None = None,
             duration_s: float | None = None, status_period_s: float = 1.0, detector_scale: str = "auto") -> dict:
    """Run until the source ends, ``max_frames`` frames were processed or ``duration_s`` passed."""
    cam = Camera.from_dict(camera)
    publisher.publish(wire.CameraMessage(flight_id, drone_id, camera, play_fps or 0.0, time.time(),
                                         sent_keyframe_width(keyframe_width, cam.width)))
    camera_fx = cam.fx
    frames = StampedFrames(VideoSource(camera_url), fps=play_fps)
    t0 = last_status = time.monotonic()
    processed = kf = detections = 0
    det_s = 0.0
    scaling = policy_for(detector, detector_scale)
    pacer = scaling.pacer()  # frames enlarged only while the node keeps the camera's rate
    expected = float("nan")  # the last frame's foreseen apple radius (px): this frame's scale (height changes slowly)
    scales = []
    flagged = 0
    latencies = []

    def status(state, message=""):
        elapsed = max(time.monotonic() - t0, 1e-9)
        publisher.publish(wire.StatusMessage(flight_id, drone_id, time.time(), frames.read, processed, frames.dropped,
                                             processed / elapsed, det_s / max(processed, 1), state, message))

    try:
        for i, img in frames:
            t_read = frames.read_time.get(i, time.time())
            t_capture = t_read + clock_offset_s
            # the camera's frame period: the rate asked for, else the rate frames have come at so far
            period_s = 1.0 / play_fps if play_fps else (time.monotonic() - t0) / max(frames.read - 1, 1)
            scale = scaling.scale(expected)
            if pacer is not None:
                scale = pacer.cap(scale, img.shape[1], img.shape[0], period_s)
            td = time.perf_counter()
            boxes, scores = detector.detect(i, img, scale)
            frame_det_s = time.perf_counter() - td
            det_s += frame_det_s
            scales.append(scale)
            s = sample_when_bracketed(telemetry, t_capture, t_read + telemetry_max_wait_s)
            expected = float(telemetry_radius_px(camera_fx, s)[0])
            tel = wire.Telemetry(float(s["lat"][0]), float(s["lon"][0]), float(s["alt"][0]),
                                 tuple(map(float, s["q_attitude"][0])), tuple(map(float, s["q_gimbal"][0])),
                                 int(s["gps_fix"][0]), float(s["h_acc"][0]), int(s["flags"][0]), float(s["height"][0]),
                                 float(s["height_acc"][0]))
            flagged += tel.flags != 0
            due = keyframes.due(t_capture, tel.lat, tel.lon, tel.alt)
            publisher.publish(wire.FrameMessage(flight_id, drone_id, i, t_capture, tel, img.shape[1], img.shape[0],
                                                boxes, scores, scale=scale, keyframe=due))
            if due:
                publisher.publish(wire.KeyframeMessage(flight_id, drone_id, i, encode_jpeg(img, keyframe_width, jpeg_quality)))
                kf += 1
            latencies.append(time.time() - t_read)
            if pacer is not None:
                pacer.observe(frame_det_s, img.shape[1], img.shape[0], scale)
            processed += 1
            detections += len(boxes)
            if time.monotonic() - last_status >= status_period_s:
                status("running")
                last_status = time.monotonic()
            if (max_frames and processed >= max_frames) or (duration_s and time.monotonic() - t0 >= duration_s):
                break
    except KeyboardInterrupt:
        log.info("interrupted")
    status("error" if frames.error else "finished", str(frames.error or ""))
    elapsed = time.monotonic() - t0
    return {"flight": flight_id, "frames_read": frames.read, "frames_processed": processed,
            "frames_dropped": frames.dropped, "keyframes": kf, "detections": detections,
            "telemetry_flagged_frames": int(flagged), "seconds": elapsed, "frames_per_s": processed / max(elapsed, 1e-9),
            "detector_latency_s": det_s / max(processed, 1), "detector_scale": scale_summary(scales),
            "detector_scale_capped": pacer.capped if pacer is not None else 0,
            "read_to_publish_median_s": float(np.median(latencies)) if latencies else None,
            "error": str(frames.error) if frames.error else None}
