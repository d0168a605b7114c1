"""The onboard node: frames + telemetry -> detector -> the wire, over zenoh.

For each processed frame it publishes a :class:`pomar.wire.FrameMessage` (capture time on the
autopilot clock, the telemetry sampled there, the detections); a processed frame every 0.2 s of capture time (or
as :class:`KeyframePolicy` is told) also goes as a JPEG keyframe for the ground's structure-from-motion; camera.json
goes once;
a status heartbeat goes every ``status_period_s``. A source that fails midway (a truncated video)
ends the run with an error status after everything before it was published.
"""

from __future__ import annotations

import logging
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from onboard.loop import Capture, camera_message, publish_frames, telemetry_record
from onboard.sources import LatestFrame, SourceError, VideoSource
from pomar.telemetry import Flags, TelemetryError, read_log
from pomar import wire
from pomar.apple_scale import held_radius_px, policy_for, scale_argument, telemetry_radius_px
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
    #: Play at the video's frame rate, newest frame first, counting the frames dropped (off: lock-step, every frame).
    realtime: bool = False
    #: Process every Nth frame (lock-step).
    every: int = 1
    #: With realtime: play the video as a camera that started at this unix time, skipping the frames whose time has
    #: passed (a node restarted mid-flight takes up the frames its camera takes from then on). None: now.
    camera_started_at: float | None = field(default=None, metadata={"type": float})
    #: Send every Nth processed frame as a JPEG keyframe (0 = none); or one of the next two; none of the three set:
    #: a keyframe every KeyframePolicy.DEFAULT_EVERY_S (0.2 s) of capture time, about 0.7 MB/s at 1280x720.
    keyframe_every: int | None = field(default=None, metadata={"type": int})
    #: Or: a keyframe every this many seconds of capture time.
    keyframe_every_s: float | None = field(default=None, metadata={"type": float})
    #: Or: a keyframe every this many metres flown.
    keyframe_every_m: float | None = field(default=None, metadata={"type": float})
    #: Keyframe width in pixels, never more than the frame's (0 = native).
    keyframe_width: int = 960
    #: JPEG quality of the keyframes (0-100).
    jpeg_quality: int = 85
    #: Seconds between the node's status messages.
    status_period_s: float = 1.0
    #: Camera clock (live: the companion computer's) minus the log's clock, for logs without camera events.
    clock_offset_s: float = 0.0
    #: The flight's telemetry from another log of any supported format (.tlog, ArduPilot DataFlash .bin, PX4 .ulg, DJI
    #: .SRT) instead of the flight directory's telemetry.tlog.
    log: str | None = None
    #: For logs without gimbal attitudes: the camera's fixed pitch below the horizon (pomar.telemetry.mount_arguments).
    camera_tilt_deg: float | None = None
    #: With camera_tilt_deg: the camera's heading from the vehicle's nose, or from the track where the log has no
    #: vehicle attitude (most DJI .SRTs); 90 = looking right, as when flying along a row and looking across it.
    camera_yaw_deg: float = 0.0
    #: How frames are resized before detection: auto (apples at the model's size, foreseen from the height above
    #: take-off, the tilt and the focal length; live, enlarged only as far as the node keeps the video's rate), off, or
    #: one factor for every frame (pomar.apple_scale).
    detector_scale: str = field(default="auto", metadata={"type": scale_argument})


class OnboardNode:
    def __init__(self, flight_dir, publisher, detector, settings: NodeSettings | None = None):
        self.flight = FlightDir(flight_dir)
        self.pub = publisher
        self.detector = detector
        self.s = settings or NodeSettings()
        self.inputs = None  # check_inputs()'s result
        self.altitude_reference = "msl"  # what the log's altitudes are measured from (check_inputs() reads it)

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
        tel["expected_radius_px"] = held_radius_px(telemetry_radius_px(cam.fx, tel))
        if self.s.detector_scale == "auto" and not np.isfinite(tel["expected_radius_px"]).any():
            log.warning("%s places no take-off point (no relative altitude) or no camera attitude: the apple size "
                        "cannot be foreseen, and frames go to the detector at their own size (--detector-scale N sets "
                        "one scale)", log_path)
        self.inputs = (meta, cam, t_frames, tel)
        self.altitude_reference = tl.altitude_reference
        return self.inputs

    def run(self) -> dict:
        meta, cam, t_frames, tel = self.inputs or self.check_inputs()
        scaling = policy_for(self.detector, self.s.detector_scale)  # the detector may come after check_inputs()
        self.pub.publish(camera_message(meta.flight_id, meta.drone_id, cam.to_dict(), cam.width, meta.fps,
                                        meta.video_start_utc, self.s.keyframe_width, self.s.realtime, self.detector,
                                        self.altitude_reference))
        frames = RecordedFrames(self.flight.video, t_frames, tel, self.s.every, meta.frame_count, meta.fps,
                                not self.s.realtime, started_at=self.s.camera_started_at)
        pacer = scaling.pacer() if self.s.realtime else None  # live: enlarge frames only while there is time
        policy = KeyframePolicy(self.s.keyframe_every, self.s.keyframe_every_s, self.s.keyframe_every_m)
        summary = publish_frames(frames, meta.flight_id, meta.drone_id, self.pub, self.detector, scaling, pacer, policy,
                                 self.s.keyframe_width, self.s.jpeg_quality, self.s.status_period_s)
        summary["bytes_per_message"] = {k: self.pub.bytes[k] / max(self.pub.sent[k], 1) for k in wire.KINDS}
        summary["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        # what the link must carry at the video's frame rate with these settings
        kf_share = summary["keyframes"] / max(summary["frames_processed"], 1)
        per_frame = summary["bytes_per_message"]["frames"] + summary["bytes_per_message"]["keyframes"] * kf_share
        summary["link_bytes_per_s_at_video_fps"] = per_frame * meta.fps / self.s.every
        if summary["error"]:
            exc = SourceError(f"{summary['error']} (after {summary['frames_processed']} frames)")
            exc.summary = summary
            raise exc
        return summary


class RecordedFrames:
    """A flight's video as a frame source (onboard.loop): every frame (every Nth) in lock-step, or played at the
    video's rate taking the newest (``lockstep`` False); each frame's capture time and telemetry from the log, read
    once before the flight (``t_frames``, ``tel``: TelemetryLog.at's dict with ``expected_radius_px``)."""

    def __init__(self, video, t_frames: np.ndarray, tel: dict, every: int, frame_count: int, fps: float,
                 lockstep: bool = True, started_at: float | None = None):
        self.t_frames, self.tel, self.every, self.fps = t_frames, tel, every, fps
        source = VideoSource(video, every, expected_frames=frame_count)
        self._frames = source if lockstep else LatestFrame(source, fps=fps, started_at=started_at)
        self.lockstep = lockstep
        self._taken = 0
        self.error = None  # a failure is raised by the iteration itself (SourceError)

    @property
    def read(self) -> int:
        return self._taken if self.lockstep else self._frames.read

    @property
    def dropped(self) -> int:
        return 0 if self.lockstep else self._frames.dropped

    @property
    def skipped(self) -> int:
        """Frames taken before the node started (``started_at``)."""
        return 0 if self.lockstep else self._frames.skipped

    def __iter__(self):
        for i, img in self._frames:
            self._taken += 1
            yield Capture(i, img, time.time(), float(self.t_frames[i]))

    def period_s(self, t0: float) -> float:
        return self.every / self.fps if self.fps else 0.0

    def expected_radius(self, i: int) -> float:
        return float(self.tel["expected_radius_px"][i])

    def telemetry(self, c: Capture) -> wire.Telemetry:
        return telemetry_record(self.tel, c.index)
