"""What the drone's detector gives the ground, against what the ground needs: the apples' size, frame by frame,
against the smallest it finds reliably; and the score it publishes detections from, against the one its tracks need (pomar.countable.publish_score).

    seen = ApplesSeen()
    seen.take(msg)          # every message: the camera message gives fx, the detector's minimum and its published score
    seen.report()           # median radius (px), the minimum, the frames below it
    seen.detections()       # the score the drone published from, the one the ground needs, and whether it fell short

A frame's apples reach the detector at the radius the telemetry foresees (height above take-off, the camera's angle
off nadir, the lens: pomar.apple_scale) times the scale the frame was resized by. Below the detector's envelope (its
model's ``min_apple_radius_px``, from its recall by size) most apples are missed: such frames are counted, and the log
says so once, with what to change (fly lower, a longer lens).
"""

from __future__ import annotations

import logging

import numpy as np

from pomar import wire
from pomar.apple_scale import expected_radius_px, off_nadir_deg
from pomar.camera import Camera
from pomar.countable import publish_score

log = logging.getLogger(__name__)


class ApplesSeen:
    def __init__(self):
        self.fx = float("nan")
        self.camera: Camera | None = None  # the drone's camera, from its camera message
        self.scales: dict[int, float] = {}  # frame -> the scale it was resized by for the detector
        self.min_px = 0.0  # the detector's smallest reliable apple radius; 0: the drone did not say
        self.radii: list[float] = []  # per frame with a foreseeable size: the radius the detector saw (px)
        self.below: list[int] = []  # frames whose apples reached the detector under min_px
        self._warned = False
        self.published_from: float | None = None  # the drone's published score (None: not said)
        self.needed_from = publish_score(None)  # the score the tracks need views from, for the drone's model

    def take(self, msg) -> None:
        if isinstance(msg, wire.CameraMessage):
            self.camera = Camera.from_dict(msg.camera, source="camera message")  # the wire checked it already
            self.fx = self.camera.fx
            self.min_px = float(msg.min_apple_radius_px or 0.0)
            needed = msg.needed_score if msg.needed_score is not None else publish_score(msg.operating_score)
            if msg.score_thresh is not None and (msg.score_thresh, needed) != (self.published_from, self.needed_from):
                self.published_from, self.needed_from = float(msg.score_thresh), needed
                if self.short():
                    log.warning("the drone publishes detections scored %.2f and more: the tracks need them from %.2f "
                                "(pomar.countable.count_scores), so apples seen weakly in some views may go uncounted "
                                "(start the onboard node without --score-thresh)", self.published_from, needed)
        elif isinstance(msg, wire.FrameMessage) and np.isfinite(self.fx):
            self.scales[int(msg.frame)] = float(msg.scale)
            tel = msg.telemetry
            r = float(np.asarray(expected_radius_px(self.fx, tel.height, off_nadir_deg(tel.q_gimbal))).reshape(-1)[0])
            if not np.isfinite(r):
                return
            r *= float(msg.scale)
            self.radii.append(r)
            if self.min_px > 0 and r < self.min_px:
                self.below.append(int(msg.frame))
                if not self._warned:
                    self._warned = True
                    log.warning("frame %d: apples reach the detector at a radius of %.1f px, below the %.1f px it "
                                "finds reliably: it misses most of them (fly lower, or use a longer lens)", msg.frame,
                                r, self.min_px)

    def short(self) -> bool:
        """Whether the drone left out detections the ground's tracks need."""
        return self.published_from is not None and self.published_from > self.needed_from + 1e-6

    def detections(self) -> dict:
        return {"published_from": self.published_from, "needed_from": self.needed_from, "short": self.short()}

    def report(self) -> dict:
        r = np.asarray(self.radii, float)
        return {"radius_px_median": float(np.median(r)) if len(r) else None,
                "radius_px_min": float(r.min()) if len(r) else None,
                "min_supported_px": self.min_px or None,
                "frames_below": len(self.below), "first_frames_below": self.below[:20]}
