"""Per-frame tracking against the map: the cheap pose for every frame that carries an image.

The mapper (:mod:`ground.poses.mapping`) hands over a :class:`Reference` after each keyframe it registers: the
keyframe's grey image and its keypoints that have a 3-D point. The tracker follows the points of the last
few references into each frame with pyramidal Lucas-Kanade, from the keyframe's own image, started where
a constant-motion prediction of the pose puts them (and back, to drop points that slid), and solves the
frame's pose by PnP with RANSAC, then Levenberg-Marquardt on the inliers. It also says when a frame should become the
next mapping keyframe: when the share of the newest reference's points it still holds falls below
``min_tracked_share`` (the view moved on: parallax for the mapper, and few points left to track with).

    tracker = Tracker(camera)                 # the keyframes' camera (their width)
    tracker.set_reference(ref)                # whenever the mapper registered a newer keyframe
    result = tracker.track(frame, grey)       # TrackResult: R, t (model frame) or None, and why
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from pomar.camera import Camera

log = logging.getLogger(__name__)


@dataclass
class TrackingSettings:
    #: PnP inliers a pose needs; fewer and the frame falls back (interpolated or telemetry pose), flagged.
    min_inliers: int = 40
    #: RANSAC reprojection threshold, keyframe pixels.
    ransac_px: float = 2.0
    #: A point whose backward track lands further than this from where it started is dropped.
    max_fb_px: float = 1.0
    #: A frame is proposed as a mapping keyframe when it holds less than this share of the reference's points.
    min_tracked_share: float = 0.9
    #: Below this share, and with the mapper still busy, the frames wait for the mapper to take this one: the map
    #: must not fall so far behind that the frames can no longer be tracked (live, when mapping is slower than flight).
    min_share_to_go_on: float = 0.5
    win_px: int = 21
    levels: int = 3
    #: At most this many points of each reference are followed (an even sample): KLT's cost grows with them.
    max_points: int = field(default=1500, metadata={"flag": "--track-points"})
    #: The points of the last this many keyframes handed over are followed: more of the image holds points, which
    #: steadies the pose (a narrow lens over points at much the same depth trades rotation for translation).
    references: int = 3


@dataclass
class Reference:
    frame: int
    grey: np.ndarray  # the keyframe's image, 8-bit grey, keyframe size
    xy: np.ndarray  # (n, 2) keypoints with a 3-D point, OpenCV pixel coordinates (top-left centre at 0, 0)
    X: np.ndarray  # (n, 3) their points, model frame
    R: np.ndarray  # the keyframe's world-to-camera pose, model frame
    t: np.ndarray


@dataclass
class TrackResult:
    frame: int
    R: np.ndarray | None  # world(model)-to-camera; None when tracking failed
    t: np.ndarray | None
    inliers: int
    share: float  # of the reference's points still held
    keyframe: bool  # propose this frame to the mapper
    why: str = ""  # why it failed


@dataclass
class _Followed:
    """One reference's points still held: where they were in its keyframe, and their 3-D points."""
    ref: Reference
    xy: np.ndarray
    X: np.ndarray
    n0: int


class Tracker:
    def __init__(self, camera: Camera, settings: TrackingSettings | None = None):
        self.cam = camera
        self.s = settings or TrackingSettings()
        self.K = camera.K_opencv
        self.refs: list[_Followed] = []  # the last ``references`` keyframes handed over, oldest first
        # the last poses known (frame, R, t): tracked frames and keyframes handed over; two give the motion
        self._poses: list[tuple[int, np.ndarray, np.ndarray]] = []
        self.tracked = self.failed = 0

    @property
    def ref(self) -> Reference | None:
        return self.refs[-1].ref if self.refs else None

    def set_reference(self, ref: Reference) -> None:
        """Follow this keyframe's points too from now on (a newer keyframe than the last one handed over); the oldest
        of the last ``references`` is let go."""
        if self.refs and ref.frame <= self.refs[-1].ref.frame:
            return
        n = len(ref.xy)
        keep = np.linspace(0, n - 1, self.s.max_points).astype(int) if n > self.s.max_points else slice(None)
        self.refs = (self.refs + [_Followed(ref, ref.xy[keep].astype(np.float32), ref.X[keep], len(ref.X[keep]))])
        self.refs = self.refs[-self.s.references:]
        self._remember(ref.frame, ref.R, ref.t)

    def _remember(self, frame: int, R: np.ndarray, t: np.ndarray) -> None:
        self._poses = sorted([p for p in self._poses if p[0] != frame] + [(frame, R, t)], key=lambda p: p[0])[-2:]

    def predict(self, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
        """The pose at ``frame`` by constant motion from the last two poses known (the last one alone when there is
        one)."""
        if not self._poses:
            return None
        f1, R1, t1 = self._poses[-1]
        if len(self._poses) < 2 or frame == f1:
            return R1, t1
        f0, R0, t0 = self._poses[0]
        w = (frame - f1) / (f1 - f0)
        rv, _ = cv2.Rodrigues(R1 @ R0.T)
        dR, _ = cv2.Rodrigues(rv * w)
        c0, c1 = -R0.T @ t0, -R1.T @ t1
        R = dR @ R1
        return R, -R @ (c1 + w * (c1 - c0))

    def _follow(self, fo: _Followed, grey: np.ndarray, rvec0, t0) -> np.ndarray:
        """KLT from the reference keyframe's own patches (no drift along a chain of frames), started where the
        predicted pose puts the points; returns which points were followed there and back, and where."""
        guess, _ = cv2.projectPoints(fo.X.astype(np.float64), rvec0, t0.astype(np.float64), self.K, None)
        lk = dict(winSize=(self.s.win_px, self.s.win_px), maxLevel=self.s.levels,
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        p0 = fo.xy.reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(fo.ref.grey, grey, p0, guess.reshape(-1, 1, 2).astype(np.float32), **lk)
        p0b, st_b, _ = cv2.calcOpticalFlowPyrLK(grey, fo.ref.grey, p1, p0.copy(), **lk)
        ok = (st.ravel() == 1) & (st_b.ravel() == 1) & (np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1) < self.s.max_fb_px)
        return ok, p1.reshape(-1, 2)

    def track(self, frame: int, grey: np.ndarray) -> TrackResult:
        if not self.refs:
            return self._fail(frame, "no map to track against")
        ref_grey = self.refs[-1].ref.grey
        if grey.shape != ref_grey.shape:
            grey = cv2.resize(grey, (ref_grey.shape[1], ref_grey.shape[0]), interpolation=cv2.INTER_AREA)
        R0, t0 = self.predict(frame)
        rvec0, _ = cv2.Rodrigues(R0)
        followed = [self._follow(fo, grey, rvec0, t0) if len(fo.X) else (np.zeros(0, bool), np.zeros((0, 2)))
                    for fo in self.refs]
        xy = np.concatenate([p[ok] for ok, p in followed]).reshape(-1, 2)
        X = np.concatenate([fo.X[ok] for fo, (ok, _) in zip(self.refs, followed)]).reshape(-1, 3)
        if len(xy) < self.s.min_inliers:
            return self._fail(frame, f"{len(xy)} points followed from keyframes {[fo.ref.frame for fo in self.refs]}")
        found, rvec, tvec, inl = cv2.solvePnPRansac(
            X.astype(np.float64), xy.astype(np.float64), self.K, None, rvec0.copy(), t0.reshape(3, 1).astype(np.float64),
            useExtrinsicGuess=True, iterationsCount=100, reprojectionError=self.s.ransac_px, confidence=0.999,
            flags=cv2.SOLVEPNP_ITERATIVE)
        n_in = 0 if inl is None else len(inl)
        if not found or n_in < self.s.min_inliers:
            return self._fail(frame, f"PnP: {n_in} inliers of {len(xy)} points")
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(X[inl].astype(np.float64), xy[inl].astype(np.float64), self.K, None, rvec, tvec)
        R, _ = cv2.Rodrigues(rvec)
        # each reference keeps the points that were inliers here
        is_in = np.zeros(len(xy), bool)
        is_in[inl] = True
        start = 0
        for fo, (ok, _) in zip(self.refs, followed):
            n = int(ok.sum())
            keep = np.flatnonzero(ok)[is_in[start:start + n]]
            fo.xy, fo.X = fo.xy[keep], fo.X[keep]
            start += n
        self._remember(frame, R, tvec.ravel())
        log.debug("frame %d: %d inliers of %d points from keyframes %s", frame, n_in, len(xy),
                  [(fo.ref.frame, int(ok.sum())) for fo, (ok, _) in zip(self.refs, followed)])
        newest = self.refs[-1]
        share = len(newest.X) / max(newest.n0, 1)
        self.tracked += 1
        return TrackResult(frame, R, tvec.ravel(), n_in, share, share < self.s.min_tracked_share)

    def _fail(self, frame: int, why: str) -> TrackResult:
        self.failed += 1
        # the references' points are kept (a frame that cannot be tracked, e.g. blurred, may be followed by one that
        # can); the motion goes on from the last poses known
        return TrackResult(frame, None, None, 0, 0.0, True, why)
