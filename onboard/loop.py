"""The onboard node's one loop, whatever the frames come from: a frame -> the detector, at the scale that brings its
apples to the model's size -> the frame's telemetry -> a frame message, and a keyframe when one is due -> zenoh.

    stats = publish_frames(frames, ids, publisher, detector, scaling, pacer, keyframes, keyframe_width, jpeg_quality)

``frames`` is a frame source (:class:`onboard.node.RecordedFrames`: a flight's video in lock-step or played in real
time; :class:`onboard.live.LiveFrames`: a camera or stream with a live telemetry link). It yields :class:`Capture`
and gives each frame's telemetry (as the wire carries it) and foreseen apple size; ``read``, ``dropped`` and ``error`` say how the reading
went.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from pomar import wire
from pomar.apple_scale import scale_summary
from pomar.countable import count_scores

log = logging.getLogger(__name__)


@dataclass
class Capture:
    """One frame as a source hands it out: its index, image (BGR), when it was read (unix s, this computer's clock)
    and its capture time (unix s, the autopilot's clock)."""

    index: int
    image: np.ndarray
    t_read: float
    t_capture: float
    #: the frame's number in its source, where it is not the index (a live node restarted goes on numbering its
    #: frames; a detector that replays a simulated flight's truth looks the frame up by this)
    source_index: int | None = None


def sent_keyframe_width(width: int, image_width: int) -> int:
    """The width keyframes are sent at: ``width`` (0 = native), never more than the image's own (an enlarged JPEG
    costs link bytes and adds nothing)."""
    return min(width, image_width) if width else image_width


def camera_message(flight_id: str, drone_id: str, camera: dict, image_width: int, fps: float, start_unix: float,
                   keyframe_width: int, paced: bool, detector, altitude_reference: str) -> wire.CameraMessage:
    """The message that opens a drone's stream, the same from every source: its camera (camera.json's content), frame
    rate, start, the keyframes' width, whether frames come at the video's pace, the detector's envelope (the
    smallest apple radius it finds reliably, 0 where its model does not say) and how its boxes answer an apple's
    size, the score it publishes from and the one its model operates at, and what the telemetry's altitudes are
    measured from (wire.ALTITUDE_REFERENCES)."""
    meta = getattr(detector, "meta", None)
    count = count_scores(meta) if meta else (None, None)  # a truth stand-in has no model to say them
    return wire.CameraMessage(flight_id, drone_id, camera, fps, start_unix,
                              sent_keyframe_width(keyframe_width, image_width), paced=paced,
                              min_apple_radius_px=getattr(detector, "min_apple_radius_px", None) or 0.0,
                              score_thresh=getattr(detector, "score_thresh", None),
                              altitude_reference=altitude_reference,
                              box_response=getattr(detector, "box_response", None),
                              operating_score=count[0], needed_score=count[1])


def encode_jpeg(img: np.ndarray, width: int, quality: int) -> bytes:
    import cv2

    w = sent_keyframe_width(width, img.shape[1])
    if w < img.shape[1]:
        img = cv2.resize(img, (w, int(round(img.shape[0] * w / img.shape[1]))), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()


def telemetry_record(s: dict, i: int = 0) -> wire.Telemetry:
    """The i-th sample of a telemetry dict (pomar.telemetry's ``TelemetryLog.at``) as the wire carries it."""
    return wire.Telemetry(float(s["lat"][i]), float(s["lon"][i]), float(s["alt"][i]),
                          tuple(map(float, s["q_attitude"][i])), tuple(map(float, s["q_gimbal"][i])),
                          int(s["gps_fix"][i]), float(s["h_acc"][i]), int(s["flags"][i]), float(s["height"][i]),
                          float(s["height_acc"][i]))


def publish_frames(frames, flight_id: str, drone_id: str, publisher, detector, scaling, pacer, keyframes,
                   keyframe_width: int, jpeg_quality: int, status_period_s: float = 1.0, max_frames: int | None = None,
                   duration_s: float | None = None) -> dict:
    """Run until the source ends (or ``max_frames`` frames, ``duration_s`` seconds, Ctrl-C); returns the run's
    statistics. A source that fails part way (a truncated video) ends the loop with its error in ``error``."""
    from onboard.sources import SourceError

    t0 = last_status = time.monotonic()
    processed = kf = detections = flagged = 0
    det_s = 0.0
    scales, latencies = [], []
    error = None
    first = None  # the first frame this node sent (a node restarted mid-flight starts later)

    def status(state, message=""):
        elapsed = max(time.monotonic() - t0, 1e-9)
        publisher.publish(wire.StatusMessage(flight_id, drone_id, time.time(), frames.read, processed, frames.dropped,
                                             processed / elapsed, det_s / max(processed, 1), state, message,
                                             first_frame=first if first is not None else 0))

    try:
        for c in frames:
            img = c.image
            scale = scaling.scale(frames.expected_radius(c.index))
            if pacer is not None:
                scale = pacer.cap(scale, img.shape[1], img.shape[0], frames.period_s(t0))
            td = time.perf_counter()
            boxes, scores = detector.detect(c.index if c.source_index is None else c.source_index, img, scale)
            frame_det_s = time.perf_counter() - td
            det_s += frame_det_s
            scales.append(scale)
            # after the detection: a live link's samples after the capture have had time to come
            tel = frames.telemetry(c)
            flagged += tel.flags != 0
            due = keyframes.due(c.t_capture, tel.lat, tel.lon, tel.alt)
            publisher.publish(wire.FrameMessage(flight_id, drone_id, c.index, c.t_capture, tel, img.shape[1],
                                                img.shape[0], boxes, scores, scale=scale, keyframe=due))
            first = c.index if first is None else first
            if due:
                publisher.publish(wire.KeyframeMessage(flight_id, drone_id, c.index,
                                                       encode_jpeg(img, keyframe_width, jpeg_quality)))
                kf += 1
            latencies.append(time.time() - c.t_read)
            if pacer is not None:
                pacer.observe(frame_det_s, img.shape[1], img.shape[0], scale)
            processed += 1
            detections += len(boxes)
            if time.monotonic() - last_status >= status_period_s:
                status("running")
                last_status = time.monotonic()
            if (max_frames and processed >= max_frames) or (duration_s and time.monotonic() - t0 >= duration_s):
                break
    except SourceError as exc:
        error = exc
        log.error("%s", exc)
    except KeyboardInterrupt:
        log.info("interrupted")
    error = error or frames.error
    status("error" if error else "finished", str(error or ""))
    elapsed = time.monotonic() - t0
    return {"flight": flight_id, "frames_read": frames.read, "frames_processed": processed,
            "frames_dropped": frames.dropped, "frames_skipped": getattr(frames, "skipped", 0), "keyframes": kf,
            "detections": detections,
            "telemetry_flagged_frames": int(flagged), "seconds": elapsed, "frames_per_s": processed / max(elapsed, 1e-9),
            "detector_latency_s": det_s / max(processed, 1), "detector_scale": scale_summary(scales),
            "detector_scale_capped": pacer.capped if pacer is not None else 0,  # frames the pace kept smaller
            "read_to_publish_median_s": float(np.median(latencies)) if latencies else None,
            "error": str(error) if error else None}
