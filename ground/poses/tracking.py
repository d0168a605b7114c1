"""Per-frame tracking against the map: the cheap pose for every frame that carries an image.

The mapper (:mod:`ground.poses.mapper`) hands over a :class:`Reference` after each keyframe it registers: the
keyframe's grey image and its keypoints that have a 3-D point. The tracker follows the points of the last
few references into each frame with pyramidal Lucas-Kanade, from the keyframe's own image, started where
a constant-motion prediction of the pose puts them (and back, to drop points that slid), and solves the
frame's pose by PnP with RANSAC, then Levenberg-Marquardt on the inliers. It also says when a frame should become the
next mapping keyframe: when the share of the newest reference's points it still holds falls below
``min_tracked_share`` (the view moved on: parallax for the mapper, and few points left to track with).

    tracker = Tracker(camera)                 # the keyframes' camera (their width)
    tracker.set_reference(ref)                # whenever the mapper registered a newer keyframe
    result = tracker.track(frame, grey)       # TrackResult: R, t (model frame) or None, and why

:class:`ImageTracking` feeds it: the frames' images in frame order, each tracked against the keyframes handed over up
to its frame, proposed to the mapper when the tracker asks for a keyframe, held while the mapper answers for one it
could not track.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from ground.poses.telemetry_poses import KeyframeTelemetry
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


class ImageTracking:
    """The frames' images, in frame order, to the tracker and the mapper: each image is tracked against the
    keyframes the mapper has handed over up to its frame, and proposed to the mapper when the tracker asks for a
    keyframe; until the first model, images go to the mapper ``init_spacing_s`` apart in capture time (its baseline).
    ``telemetry`` maps a frame to its :class:`KeyframeTelemetry`, as the mapper is handed it."""

    #: Images kept while the first model is made; beyond, they are dropped (their frames get telemetry poses).
    MAX_WAITING = 300
    #: How long an image that could not be tracked waits for the mapper's answer on it, at most.
    MAX_RETRY_WAIT_S = 30.0

    def __init__(self, camera: Camera, mapper, telemetry: dict, settings: TrackingSettings | None = None,
                 init_spacing_s: float = 0.0):
        self.cam = camera  # the keyframes' camera: images are taken to its size
        self.mapper = mapper
        self.tel = telemetry
        self.tracker = Tracker(camera, settings)
        self.init_spacing_s = init_spacing_s
        self._t_init = float("-inf")  # capture time of the last image handed to the mapper for the first model
        self.tracked: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # tracked frames, model frame
        # each tracked frame's newest reference then: (its frame, R, t) as handed over, to carry the frame along when
        # the mapper moves that keyframe (bundle adjustment, a re-anchoring) before the frame's pose is given
        self.anchors: dict[int, tuple[int, np.ndarray, np.ndarray]] = {}
        self.failed_frames: list[int] = []  # frames with an image that tracking could not place
        self.processed = -1  # the newest frame whose image went through tracking
        self._last_image = -1
        self._untracked: deque[tuple[int, np.ndarray]] = deque()  # images waiting to be tracked, in frame order
        self._refs: deque = deque()  # keyframes handed over that the images have not reached yet
        self.first_ref = self._last_ref = None  # frames of the first and the newest keyframe handed over
        self._retry: int | None = None  # an image that could not be tracked, waiting for the mapper to map it
        self._retry_since = 0.0
        self.retried = 0  # images tracked again once the mapper had mapped them
        self._due: tuple[int, np.ndarray] | None = None  # a keyframe waiting for the mapper to be free
        self.waits_for_mapper = 0  # times the frames waited for the mapper (it fell behind the flight)
        self.seconds = {"tracking": 0.0, "mapping_inline": 0.0}

    def add_jpeg(self, frame: int, jpeg: bytes, t_capture: float = float("nan")) -> bool:
        """A frame's image as the stream sends it (JPEG); False, and nothing done, if it does not decode."""
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            return False
        self.add_image(frame, img, t_capture)
        return True

    def add_image(self, frame: int, image_bgr: np.ndarray, t_capture: float = float("nan")) -> None:
        """A frame's image, in frame order: tracked against the map once there is one (until then it waits, and goes
        to the mapper if it was taken ``init_spacing_s`` or more after the last one it went: the first model needs a
        baseline); proposed to the mapper when the tracker asks for a keyframe."""
        if frame <= self._last_image:
            log.warning("image of frame %d arrived after frame %d's: skipped", frame, self._last_image)
            return
        self._last_image = frame
        if image_bgr.shape[1] != self.cam.width:
            image_bgr = cv2.resize(image_bgr, (self.cam.width, self.cam.height), interpolation=cv2.INTER_AREA)
        self._untracked.append((frame, image_bgr))
        if self.mapper.reference() is None and not t_capture - self._t_init < self.init_spacing_s:  # NaN: mapped
            self._t_init = t_capture
            self._map(frame, image_bgr)
        self.catch_up()

    def _map(self, frame: int, image_bgr: np.ndarray) -> None:
        t0 = time.perf_counter()
        self.mapper.add(frame, image_bgr, self.tel.get(frame, KeyframeTelemetry.unknown()))
        self.seconds["mapping_inline"] += time.perf_counter() - t0

    def _collect_references(self) -> None:
        """Keep each keyframe the mapper hands over, in order, until the images reach it."""
        ref = self.mapper.reference()
        if ref is not None and (self._last_ref is None or ref.frame > self._last_ref):
            self.first_ref = ref.frame if self.first_ref is None else self.first_ref
            self._last_ref = ref.frame
            self._refs.append(ref)

    def catch_up(self) -> None:
        """Track the images waiting, in order, once the mapper has handed over a keyframe; drop them if the first
        model never came (their frames then get telemetry poses). An image is tracked against the keyframes handed
        over up to its own frame, never a later one (the motion prediction would run backwards)."""
        self._collect_references()
        if self.first_ref is None:
            tried = self.mapper.attempts >= self.mapper.settings.first_model_tries
            if tried or len(self._untracked) > self.MAX_WAITING:
                while self._untracked:
                    self.processed = self._untracked.popleft()[0]
            return
        while self._untracked:
            if self._due is not None:  # a keyframe the mapper was too busy to take: the frames wait until it can
                if self.mapper.busy():
                    return
                self._map(*self._due)
                self._due = None
            frame, image_bgr = self._untracked[0]
            if frame == self._retry and self._waiting_for_mapper(frame):
                return  # the frames after it wait too: they are tracked in order
            self._untracked.popleft()
            if frame < self.first_ref:  # before the first keyframe handed over: tracked against the first model's nearest
                self.processed = frame
                self._track_early(frame, image_bgr)
                continue
            t0 = time.perf_counter()
            self._collect_references()
            while self._refs and self._refs[0].frame <= frame:
                self.tracker.set_reference(self._refs.popleft())
            grey = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
            r = self.tracker.track(frame, grey)
            self.seconds["tracking"] += time.perf_counter() - t0
            if r.R is None and frame != self._retry and frame > self.mapper.processed:
                # the map did not reach this frame (mapping fell behind, or the view changed fast): the frame goes to
                # the mapper, and it and the frames after it wait for the answer, then it is tracked again
                self._map(frame, image_bgr)
                self._retry, self._retry_since = frame, time.monotonic()
                self._untracked.appendleft((frame, image_bgr))
                log.info("frame %d: tracking failed (%s); waiting for the mapper", frame, r.why)
                continue
            self.processed = frame
            if frame == self._retry:
                self._retry = None
                self.retried += 1
            self._record(r, self.tracker)
            # while the mapper is at work on the last proposal, a frame is not proposed, unless the map is falling
            # behind (then it is due, and the frames after it wait); never one older than what it has mapped already
            if r.R is not None and r.keyframe and frame > self.mapper.processed:
                if not self.mapper.busy():
                    self._map(frame, image_bgr)
                elif r.share < self.tracker.s.min_share_to_go_on:
                    self._due = (frame, image_bgr)
                    self.waits_for_mapper += 1

    def _waiting_for_mapper(self, frame: int) -> bool:
        """Whether the mapper has yet to answer for the frame it was handed when tracking failed (at most
        MAX_RETRY_WAIT_S: a mapping process that died must not hold the flight)."""
        self._collect_references()
        if self.mapper.processed >= frame or not self.mapper.alive:
            return False
        if time.monotonic() - self._retry_since > self.MAX_RETRY_WAIT_S:
            log.warning("frame %d: no answer from the mapper in %.0f s; the frame goes on untracked", frame,
                        self.MAX_RETRY_WAIT_S)
            return False
        return True

    def _track_early(self, frame: int, image_bgr: np.ndarray) -> None:
        """A frame before the first reference: tracked from the keyframes of the first model on either side of it
        (the pose between them is where tracking starts)."""
        refs = self.mapper.first_references
        if not refs or frame in self.mapper.model_pose:
            return
        # the nearest keyframe before and after it: their points, and a motion between them to start from
        before = [r for r in refs if r.frame < frame]
        after = [r for r in refs if r.frame > frame]
        near = ([max(before, key=lambda r: r.frame)] if before else []) + ([min(after, key=lambda r: r.frame)]
                                                                             if after else [])
        tracker = Tracker(self.cam, self.tracker.s)
        for ref in near:
            tracker.set_reference(ref)
        grey = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
        self._record(tracker.track(frame, grey), tracker)

    def _record(self, r: TrackResult, tracker: Tracker) -> None:
        """A frame's tracking result: its pose and the reference it was tracked from, or a flag (the frame then gets an
        interpolated or telemetry pose)."""
        if r.R is not None:
            self.tracked[r.frame] = (r.R, r.t)
            ref = tracker.ref
            if ref is not None:
                self.anchors[r.frame] = (ref.frame, ref.R, ref.t)
        else:
            self.failed_frames.append(r.frame)
            log.info("frame %d: tracking failed (%s)", r.frame, r.why)

    def settle(self) -> None:
        """The end of the flight: let the mapper finish what it was handed, and track the images still waiting."""
        while True:
            self.mapper.wait()
            if self.first_ref is None:
                self._bootstrap_rest()
            waiting = len(self._untracked)
            self.catch_up()
            if not self._untracked or (len(self._untracked) == waiting and not self.mapper.busy()):
                return

    def _bootstrap_rest(self) -> None:
        """The flight ended before the first model: the images the mapper had no time for go to it now, in order, one
        at a time, until it makes one (or has had its chances)."""
        for frame, image_bgr in list(self._untracked):
            if self.mapper.reference() is not None or self.mapper.attempts >= self.mapper.settings.first_model_tries:
                break
            if frame > self.mapper.processed:
                self._map(frame, image_bgr)
                self.mapper.wait()

    def drop_waiting(self) -> None:
        """A ground told to stop: the images waiting to be tracked are dropped (their frames take interpolated or
        telemetry poses), so that what is left takes no time."""
        while self._untracked:
            self.processed = self._untracked.popleft()[0]

    def forget_before(self, frame: int) -> None:
        """Drop the tracked poses older than ``frame`` (memory stays bounded over long flights)."""
        for f in [f for f in self.tracked if f < frame]:
            del self.tracked[f]
            self.anchors.pop(f, None)
