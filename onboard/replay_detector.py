"""A stand-in detector that replays a simulated flight's ``truth/detections.csv`` as boxes.

For building and testing the pipeline before (or besides) the real ONNX detector: a diagnostic
source, never the default. Boxes are the true apple discs (centre +- r_px), for apples at least
``min_visible`` visible, each with score 1 (a detector that is sure: the ground counts an apple on
views scored at least its confirm score).
"""

from __future__ import annotations

import numpy as np

from pomar.countable import MIN_VISIBLE
from pomar.flight import FlightDir


class TruthReplayDetector:
    name = "truth-replay"

    def __init__(self, flight_dir, min_visible: float = MIN_VISIBLE):
        d = FlightDir(flight_dir).truth_detections()
        keep = d["visible_fraction"] >= min_visible
        order = np.argsort(d["frame"][keep], kind="stable")
        self._frame = d["frame"][keep][order]
        self._uvr = np.stack([d["u"], d["v"], d["r_px"]], 1)[keep][order]
        self._score = np.ones(int(keep.sum()), np.float32)

    apple_radius_px = None  # the truth needs no rescaling

    def detect(self, frame: int, image: np.ndarray | None = None, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """(boxes (N, 4) x1 y1 x2 y2, OpenCV pixels; scores (N,)) of a frame; ``scale`` changes nothing."""
        lo, hi = np.searchsorted(self._frame, [frame, frame + 1])
        u, v, r = self._uvr[lo:hi].T
        r = np.maximum(r, 1.0)
        return np.stack([u - r, v - r, u + r, v + r], 1).astype(np.float32), self._score[lo:hi].astype(np.float32)
