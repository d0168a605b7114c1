"""The onboard node live: a camera (or stream) + a live MAVLink link -> detector -> zenoh.

    python -m onboard live --camera 0 --mavlink udpin:127.0.0.1:14550 --camera-json camera.json --flight-id F

Frames come from OpenCV (a camera index, a stream URL, or a file played at its own rate); the node
always takes the newest frame and counts the ones it had no time for. Each frame's capture time is
the companion computer's clock when the frame was read, put on the autopilot's clock by ``clock_offset_s``
(the companion's clock minus the autopilot's, as for a recorded flight); its telemetry is sampled there from the live link, once every stream has a sample
after the capture (at most ``telemetry_max_wait_s`` after it; the frame's flags say what was missing). Keyframes go every N frames, S seconds or D
metres (:class:`onboard.node.KeyframePolicy`).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from onboard.loop import Capture, camera_message, publish_frames, telemetry_record
from pomar.telemetry import TelemetryLog
from onboard.node import KeyframePolicy
from onboard.numbering import FrameNumbers
from onboard.sources import LatestFrame, VideoSource
from pomar import wire
from pomar.camera import Camera
from pomar.apple_scale import policy_for, telemetry_radius_px

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


class LiveFrames:
    """A camera or stream as a frame source (onboard.loop): the newest frame, its capture time this computer's clock
    when it was read, on the autopilot's clock (``clock_offset_s``: this computer's clock minus the autopilot's), its
    telemetry sampled from the live link
    once every stream has a sample after the capture (at most ``telemetry_max_wait_s``); the apple size each frame
    is detected at is the one the previous frame's telemetry foresaw (the height changes slowly)."""

    def __init__(self, camera_url, telemetry, camera_fx: float, clock_offset_s: float = 0.0,
                 telemetry_max_wait_s: float = 1.0, play_fps: float | None = None,
                 numbers: FrameNumbers | None = None):
        self._frames = StampedFrames(VideoSource(camera_url), fps=play_fps)
        self.numbers = numbers or FrameNumbers(None)  # frame indices kept across a restart of the node
        self.telemetry_link, self.fx = telemetry, camera_fx
        self.clock_offset_s, self.max_wait_s, self.play_fps = clock_offset_s, telemetry_max_wait_s, play_fps
        self._expected = float("nan")

    read = property(lambda self: self._frames.read)
    dropped = property(lambda self: self._frames.dropped)
    error = property(lambda self: self._frames.error)

    def __iter__(self):
        try:
            for i, img in self._frames:
                t_read = self._frames.read_time.get(i, time.time())
                yield Capture(self.numbers(i, t_read), img, t_read, TelemetryLog.log_clock(t_read, self.clock_offset_s),
                              source_index=i)
        finally:
            self.numbers.save()

    def period_s(self, t0: float) -> float:
        """The camera's frame period: the rate asked for, else the rate frames have come at so far."""
        return 1.0 / self.play_fps if self.play_fps else (time.monotonic() - t0) / max(self._frames.read - 1, 1)

    def expected_radius(self, i: int) -> float:
        return self._expected

    def telemetry(self, c: Capture) -> wire.Telemetry:
        s = sample_when_bracketed(self.telemetry_link, c.t_capture, c.t_read + self.max_wait_s)
        r = float(telemetry_radius_px(self.fx, s)[0])
        self._expected = r if np.isfinite(r) else self._expected  # a sample without a height keeps the last size
        return telemetry_record(s)


def run_live(camera_url, telemetry, camera: dict, flight_id: str, drone_id: str, publisher, detector,
             keyframes: KeyframePolicy, keyframe_width: int = 960, jpeg_quality: int = 85, clock_offset_s: float = 0.0,
             telemetry_max_wait_s: float = 1.0, play_fps: float | None = None, max_frames: int | None = None,
             duration_s: float | None = None, status_period_s: float = 1.0, detector_scale: str = "auto",
             state_dir: Path | None = None) -> dict:
    """Run until the source ends, ``max_frames`` frames were processed or ``duration_s`` passed. ``state_dir``: where
    the frame numbers are kept across a restart of the node (onboard.numbering); None: not kept."""
    cam = Camera.from_dict(camera)
    publisher.publish(camera_message(flight_id, drone_id, camera, cam.width, play_fps or 0.0, time.time(),
                                     keyframe_width, True, detector, "msl"))  # MAVLink's positions are above MSL
    numbers = FrameNumbers(Path(state_dir) / f"{flight_id}-{drone_id}.json" if state_dir else None)
    frames = LiveFrames(camera_url, telemetry, cam.fx, clock_offset_s, telemetry_max_wait_s, play_fps, numbers)
    scaling = policy_for(detector, detector_scale)
    summary = publish_frames(frames, flight_id, drone_id, publisher, detector, scaling, scaling.pacer(), keyframes,
                             keyframe_width, jpeg_quality, status_period_s, max_frames, duration_s)
    summary["resumed_after_frame"] = numbers.resumed_from  # a node of this flight ran before: its last frame
    return summary
