"""Camera poses for a live flight: the one pose interface the pipeline hands its frames to.

Behind it, two modules: :mod:`ground.poses.tracking` gives every frame that carries an image a pose from its own
pixels against the map (KLT + PnP, milliseconds), and :mod:`ground.poses.mapping` registers the *mapping
keyframes* the tracker proposes (pycolmap, in its own process when live) and georeferences the model. Fed each
frame's telemetry and each image in frame order, it says when a frame's pose can be decided and gives it
with its source and uncertainty:

- ``registered``: a mapping keyframe the model registered;
- ``tracked``: a frame tracked against the map;
- ``interpolated``: a frame without an image (or whose tracking failed, then flagged in
  ``tracking_failed``) between two posed frames at most ``max_interp_gap`` apart (centre linearly,
  rotation by slerp);
- ``telemetry``: GPS + gimbal attitude alone.

Poses come in the *association frame*: the model's coordinates taken through the first good
georeferencing fit, then frozen (so that the frames in the association's window stay consistent
while later fits move a little). :meth:`to_enu` takes points from the association frame to the
current best ENU frame; :attr:`origin` is the ENU origin (the first GPS fix, unless given).
"""

from __future__ import annotations

import bisect
import logging
import time
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ground.poses.georeference import drift_offsets, georeference_poses
from ground.poses.mapping import KeyframeTelemetry, Mapper, MapperProcess, MappingWorker
from ground.poses.telemetry_poses import camera_rotations
from ground.poses.registration import RegistrationSettings
from ground.poses.tracking import Tracker, TrackingSettings
from pomar.align import IDENTITY, Similarity, compose, inverse
from pomar.camera import Camera
from pomar.geo import Origin
from pomar.telemetry.base import Flags

log = logging.getLogger(__name__)


@dataclass
class Pose:
    frame: int
    R: np.ndarray  # association-frame-to-camera rotation
    t: np.ndarray
    source: str  # registered | tracked | interpolated | telemetry
    sigma_m: float
    sigma_deg: float

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t


class LivePoses:
    #: Images kept while the first model is made; beyond, they are dropped (their frames get telemetry poses).
    MAX_WAITING = 300
    #: How long an image that could not be tracked waits for the mapper's answer on it, at most.
    MAX_RETRY_WAIT_S = 30.0

    def __init__(self, camera: Camera, workdir, keyframe_width: int | None = None,
                 settings: RegistrationSettings | None = None, origin: Origin | None = None,
                 max_interp_gap: int = 10, sigma_att_deg: float = 0.5, tracking: TrackingSettings | None = None,
                 init_spacing_s: float = 0.0, mapping_worker: MappingWorker | None = None):
        self.cam = camera
        self.kf_cam = camera if not keyframe_width else self._scaled(camera, keyframe_width)
        # live (a mapping worker given), mapping runs in its own process: pycolmap holds the GIL, and tracking must
        # not wait for it; otherwise on this thread (lock-step)
        self.mapper = (MapperProcess(self.kf_cam, camera, workdir, settings, sigma_att_deg, worker=mapping_worker)
                       if mapping_worker is not None else Mapper(self.kf_cam, camera, workdir, settings, sigma_att_deg))
        self.tracker = Tracker(self.kf_cam, tracking)
        self.origin = origin
        self.max_interp_gap = max_interp_gap
        self.init_spacing_s = init_spacing_s
        self._t_init = float("-inf")  # capture time of the last image handed to the mapper for the first model
        self.sigma_att = np.radians(sigma_att_deg)
        self.tel: dict[int, KeyframeTelemetry] = {}  # frame -> its telemetry
        self.tracked: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # tracked frames, model frame
        self.tracking_failed: list[int] = []  # frames with an image that tracking could not place
        self.kf_processed = -1  # the newest frame whose image went through tracking
        self._last_image = -1
        self._untracked: deque[tuple[int, np.ndarray]] = deque()  # images waiting to be tracked, in frame order
        self._refs: deque = deque()  # keyframes handed over that the images have not reached yet
        self._first_ref = self._last_ref = None  # frames of the first and the newest keyframe handed over
        self._retry: int | None = None  # an image that could not be tracked, waiting for the mapper to map it
        self._retry_since = 0.0
        self.retried = 0  # images tracked again once the mapper had mapped them
        self._due: tuple[int, np.ndarray] | None = None  # a keyframe waiting for the mapper to be free
        self.waits_for_mapper = 0  # times the frames waited for the mapper (it fell behind the flight)
        self.frozen: Similarity | None = None  # model -> association frame (a fit frozen), or None
        self.assoc_from_enu: Similarity | None = None  # set when the association frame is ENU itself
        self.seconds = {"tracking": 0.0, "mapping_inline": 0.0}
        self.drift_m = 0.0  # how far the drift corrections spread along the flight (m), see drift_correction
        self.drift_corrected = False

    @staticmethod
    def _scaled(cam: Camera, width: int) -> Camera:
        s = width / cam.width
        return Camera(int(round(cam.width * s)), int(round(cam.height * s)), cam.fx * s, cam.fy * s, cam.cx * s, cam.cy * s)

    # the mapper's state, as the rest of the ground reads it
    @property
    def model_pose(self):
        return self.mapper.model_pose

    @property
    def fit(self) -> Similarity | None:
        return self.mapper.fit

    @property
    def fit_residual_m(self) -> float:
        return self.mapper.fit_residual_m

    # -- inputs
    def add_telemetry(self, frame: int, lat: float, lon: float, alt: float, q_gimbal, h_acc: float,
                      height: float = float("nan"), height_acc: float = float("nan"), flags: int = 0) -> None:
        """A frame's telemetry: its ENU position, gimbal attitude, horizontal accuracy (2 m where unknown), height
        above the take-off point and its accuracy (NaN where the log does not say), and its flags (a fixed mount
        without the vehicle's attitude: the camera's heading is only the track's)."""
        if self.origin is None and np.isfinite([lat, lon, alt]).all():
            self.origin = Origin(float(lat), float(lon), float(alt))
        enu = (np.asarray(self.origin.to_enu(lat, lon, alt), float).reshape(3) if self.origin is not None
               else np.full(3, np.nan))
        track_heading = int(Flags.FIXED_MOUNT | Flags.NO_ATTITUDE)
        self.tel[frame] = KeyframeTelemetry(enu, np.asarray(q_gimbal, float), float(h_acc), float(height),
                                            float(height_acc), (int(flags) & track_heading) != track_heading)

    def add_frame(self, msg) -> None:
        """A frame message's telemetry (:class:`pomar.wire.FrameMessage`)."""
        t = msg.telemetry
        self.add_telemetry(msg.frame, t.lat, t.lon, t.alt, t.q_gimbal, t.h_acc, t.height, t.height_acc, t.flags)

    def add_jpeg(self, frame: int, jpeg: bytes, t_capture: float = float("nan")) -> bool:
        """A frame's image as the stream sends it (JPEG); False, and nothing done, if it does not decode."""
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            return False
        self.add_image(frame, img, t_capture)
        return True

    @staticmethod
    def keyframe_width(jpegs) -> int | None:
        """The width of the first of these JPEG images that decodes (None if none does)."""
        for jpeg in jpegs:
            img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
            if img is not None:
                return img.shape[1]
        return None

    def add_image(self, frame: int, image_bgr: np.ndarray, t_capture: float = float("nan")) -> None:
        """A frame's image, in frame order: tracked against the map once there is one (until then it waits, and goes
        to the mapper if it was taken ``init_spacing_s`` or more after the last one it went: the first model needs a
        baseline); proposed to the mapper when the tracker asks for a keyframe."""
        if frame <= self._last_image:
            log.warning("image of frame %d arrived after frame %d's: skipped", frame, self._last_image)
            return
        self._last_image = frame
        if image_bgr.shape[1] != self.kf_cam.width:
            image_bgr = cv2.resize(image_bgr, (self.kf_cam.width, self.kf_cam.height), interpolation=cv2.INTER_AREA)
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
            self._first_ref = ref.frame if self._first_ref is None else self._first_ref
            self._last_ref = ref.frame
            self._refs.append(ref)

    def catch_up(self) -> None:
        """Track the images waiting, in order, once the mapper has handed over a keyframe; drop them if the first
        model never came (their frames then get telemetry poses). An image is tracked against the keyframes handed
        over up to its own frame, never a later one (the motion prediction would run backwards)."""
        self._collect_references()
        if self._first_ref is None:
            tried = self.mapper.attempts >= self.mapper.settings.first_model_tries
            if tried or len(self._untracked) > self.MAX_WAITING:
                while self._untracked:
                    self.kf_processed = self._untracked.popleft()[0]
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
            if frame < self._first_ref:  # before the first keyframe handed over: tracked against the first model's nearest
                self.kf_processed = frame
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
            self.kf_processed = frame
            if frame == self._retry:
                self._retry = None
                self.retried += 1
            self._record(r)
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
        if not refs or frame in self.model_pose:
            return
        # the nearest keyframe before and after it: their points, and a motion between them to start from
        before = [r for r in refs if r.frame < frame]
        after = [r for r in refs if r.frame > frame]
        near = ([max(before, key=lambda r: r.frame)] if before else []) + ([min(after, key=lambda r: r.frame)]
                                                                             if after else [])
        tracker = Tracker(self.kf_cam, self.tracker.s)
        for ref in near:
            tracker.set_reference(ref)
        grey = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
        self._record(tracker.track(frame, grey))

    def _record(self, r) -> None:
        """A frame's tracking result: its pose, or a flag (the frame then gets an interpolated or telemetry pose)."""
        if r.R is not None:
            self.tracked[r.frame] = (r.R, r.t)
        else:
            self.tracking_failed.append(r.frame)
            log.info("frame %d: tracking failed (%s)", r.frame, r.why)

    def settle(self) -> None:
        """The end of the flight: let the mapper finish what it was handed, and track the images still waiting."""
        while True:
            self.mapper.wait()
            if self._first_ref is None:
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

    def close(self, timeout_s: float = 600.0) -> None:
        """Stop the mapper (within ``timeout_s``)."""
        self.mapper.close(timeout_s=timeout_s)

    def drop_waiting(self) -> None:
        """A ground told to stop: the images waiting to be tracked are dropped (their frames take interpolated or
        telemetry poses), so that what is left takes no time."""
        while self._untracked:
            self.kf_processed = self._untracked.popleft()[0]

    # -- the association frame
    def _freeze(self):
        if self.frozen is not None or self.assoc_from_enu is not None:
            return
        if self.fit is not None:
            self.frozen = self.fit
            log.info("association frame fixed by georeferencing %d registered keyframes (GPS residual %.2f m)",
                     len(self.model_pose), self.fit_residual_m)
        else:
            self.assoc_from_enu = IDENTITY
            log.warning("no registered model yet: the association runs on telemetry poses in ENU")

    def model_to_assoc(self) -> Similarity:
        if self.frozen is not None:
            return self.frozen
        return compose(self.assoc_from_enu, self.fit) if self.fit is not None else None

    def assoc_to_enu(self) -> Similarity:
        if self.frozen is not None:
            return compose(self.fit, inverse(self.frozen))
        return inverse(self.assoc_from_enu) if self.assoc_from_enu is not None else IDENTITY

    def metres_per_unit(self) -> float:
        """The association frame's unit in metres, as the map's georeference knows it now: the frame was fixed by
        the first fit, from a few keyframes' GPS, and the later fits scale it (tens of percent with a DJI log's)."""
        return float(self.assoc_to_enu().scale)

    def to_enu(self, X: np.ndarray) -> np.ndarray:
        return self.assoc_to_enu().apply(np.asarray(X, float).reshape(-1, 3))

    #: The drift correction applies once the map has drifted this many times the GPS's stated accuracy (the spread
    #: of the corrections along the flight): below, what it would follow is mostly the GPS error's own wander.
    DRIFT_MIN_GPS_SIGMAS = 4.0

    def drift_correction(self, frames, sigma_frames: float) -> np.ndarray:
        """ENU offsets (n, 3) to add at these frames to what :meth:`to_enu` gives: where the GPS of the registered
        keyframes around them (Gaussian, ``sigma_frames``) disagrees with the map after its one similarity
        (:func:`ground.poses.georeference.drift_offsets`). Zero without a model, with ``sigma_frames`` 0, or while the
        corrections spread less than DRIFT_MIN_GPS_SIGMAS x the GPS accuracy along the flight (``drift_m``)."""
        zeros = np.zeros((len(np.atleast_1d(frames)), 3))
        S = self.fit
        if S is None or self.frozen is None or not sigma_frames > 0:
            return zeros
        kf = np.array([f for f in self.model_pose if f in self.tel and np.isfinite(self.tel[f].enu).all()], int)
        if len(kf) < 3:
            return zeros
        R = np.array([self.model_pose[f][0] for f in kf])
        t = np.array([self.model_pose[f][1] for f in kf])
        res = np.array([self.tel[f].enu for f in kf]) - S.apply(-np.einsum("nji,nj->ni", R, t))
        sigma = np.array([self.tel[f].h_acc for f in kf])
        w = 1.0 / sigma**2
        at_kf = drift_offsets(kf, res, w, kf, sigma_frames)
        self.drift_m = float(np.linalg.norm(at_kf - np.average(at_kf, axis=0, weights=w), axis=1).max())
        self.drift_corrected = self.drift_m >= self.DRIFT_MIN_GPS_SIGMAS * float(np.median(sigma))
        return drift_offsets(kf, res, w, frames, sigma_frames) if self.drift_corrected else zeros

    # -- decisions
    def ready(self, frame: int, final: bool = False, stalled: bool = False) -> bool:
        """Whether frame's pose can be decided now: the image at or after it went through tracking, and the model
        exists (or bootstrapping had its chances), or the images stopped coming (``stalled``)."""
        self.catch_up()
        if final or stalled:
            return True
        if frame > self.kf_processed:
            return False
        if self.mapper.has_model or self.frozen is not None or self.assoc_from_enu is not None:
            return True
        return self.mapper.attempts >= self.mapper.settings.first_model_tries

    def _model_frame_pose(self, frame: int, model_pose) -> tuple[np.ndarray, np.ndarray, str] | None:
        if frame in model_pose:
            return (*model_pose[frame], "registered")
        if frame in self.tracked:
            return (*self.tracked[frame], "tracked")
        return None

    def _neighbours(self, frame: int, kf_sorted: list[int]) -> tuple[int, int] | None:
        """The nearest posed frames (registered or tracked) before and after ``frame``, within max_interp_gap."""
        lo = hi = None
        for f in range(frame - 1, frame - self.max_interp_gap - 1, -1):
            if f in self.tracked or self._has(kf_sorted, f):
                lo = f
                break
        if lo is None:
            return None
        for f in range(frame + 1, lo + self.max_interp_gap + 1):
            if f in self.tracked or self._has(kf_sorted, f):
                hi = f
                break
        return None if hi is None else (lo, hi)

    @staticmethod
    def _has(sorted_frames: list[int], f: int) -> bool:
        k = bisect.bisect_left(sorted_frames, f)
        return k < len(sorted_frames) and sorted_frames[k] == f

    def pose(self, frame: int) -> Pose | None:
        """The frame's pose in the association frame (call once :meth:`ready`); None without telemetry either."""
        self._freeze()
        m2a = self.model_to_assoc()
        model_pose, kf_sorted, _ = self.mapper.registered()
        if m2a is not None and (model_pose or self.tracked):
            own = self._model_frame_pose(frame, model_pose)
            if own is not None:
                R, t = georeference_poses(own[0][None], own[1][None], m2a)
                return Pose(frame, R[0], t[0], own[2], 0.01 if own[2] == "registered" else 0.015, 0.05)
            ab = self._neighbours(frame, kf_sorted)
            if ab is not None:
                a, b = ab
                pa, pb = self._model_frame_pose(a, model_pose), self._model_frame_pose(b, model_pose)
                R2, t2 = georeference_poses(np.array([pa[0], pb[0]]), np.array([pa[1], pb[1]]), m2a)
                C = -np.einsum("nji,nj->ni", R2, t2)
                w = (frame - a) / (b - a)
                R = Slerp([0.0, 1.0], Rotation.from_matrix(R2))([w]).as_matrix()[0]
                c = (1 - w) * C[0] + w * C[1]
                return Pose(frame, R, -R @ c, "interpolated", 0.02, 0.1)
        # telemetry alone
        log.debug("frame %d: telemetry pose (model %s, %d registered, %d tracked, first reference %s)", frame,
                  m2a is not None, len(model_pose), len(self.tracked), self._first_ref)
        if frame not in self.tel or not np.isfinite(self.tel[frame].enu).all():
            return None
        enu, qg, h_acc = self.tel[frame].enu, self.tel[frame].q_gimbal, self.tel[frame].h_acc
        R_enu = camera_rotations(qg[None], self.cam)[0]
        e2a = inverse(self.assoc_to_enu())
        R, t = georeference_poses(R_enu[None], (-R_enu @ enu)[None], e2a)
        return Pose(frame, R[0], t[0], "telemetry", h_acc, np.degrees(self.sigma_att))

    # -- corrections of poses already given
    #: A frame is corrected by keyframes at most this many frames away.
    MAX_CORRECTION_GAP = 40
    #: Smaller corrections are left out (the association would redo its triangulations for nothing).
    MIN_CORRECTION_M = 1e-3
    MIN_CORRECTION_RAD = 2e-4

    def take_moved(self) -> list[int]:
        """The keyframes the mapper placed or moved since the last call."""
        return self.mapper.take_moved()

    def corrected(self, given: dict[int, Pose], frames) -> dict[int, Pose]:
        """The poses given earlier for ``frames`` (from ``given``), moved as the mapper has since moved the keyframes
        about them (bundle adjustment, a re-anchoring on an earlier pass): a keyframe to its pose now, another frame by
        the corrections of the keyframes on either side of it, interpolated (rotation by slerp, centre linearly), or
        of the nearest one. Telemetry poses, and any pose before the association frame was fixed, stay as they were;
        only the poses that changed are returned."""
        if self.frozen is None:
            return {}
        model_pose, kf_sorted, _ = self.mapper.registered()
        frames = sorted(f for f in frames if f in given and given[f].source != "telemetry")
        if not frames:
            return {}
        lo = bisect.bisect_left(kf_sorted, frames[0] - self.MAX_CORRECTION_GAP)
        hi = bisect.bisect_right(kf_sorted, frames[-1] + self.MAX_CORRECTION_GAP)
        kfs = [k for k in kf_sorted[lo:hi] if k in given and given[k].source != "telemetry"]
        if not kfs:
            return {}
        R_now, t_now = georeference_poses(np.array([model_pose[k][0] for k in kfs]),
                                          np.array([model_pose[k][1] for k in kfs]), self.frozen)
        C_now = -np.einsum("nji,nj->ni", R_now, t_now)
        R_was = np.array([given[k].R for k in kfs])
        dC = C_now - np.array([given[k].centre for k in kfs])
        Q = Rotation.from_matrix(np.einsum("nji,njk->nik", R_was, R_now))  # R_now = R_was @ Q
        out = {}
        for f in frames:
            j = bisect.bisect_left(kfs, f)
            a, b = (j, j) if j < len(kfs) and kfs[j] == f else (j - 1, j)
            near = [i for i in dict.fromkeys((a, b)) if 0 <= i < len(kfs) and abs(kfs[i] - f) <= self.MAX_CORRECTION_GAP]
            if not near:
                continue
            if len(near) == 2:
                w = (f - kfs[a]) / (kfs[b] - kfs[a])
                q = Slerp([0.0, 1.0], Q[[a, b]])([w])[0]
                dc = (1 - w) * dC[a] + w * dC[b]
            else:
                q, dc = Q[near[0]], dC[near[0]]
            p = given[f]
            R = p.R @ q.as_matrix()
            c = p.centre + dc
            if np.linalg.norm(dc) < self.MIN_CORRECTION_M and q.magnitude() < self.MIN_CORRECTION_RAD:
                continue
            out[f] = Pose(f, R, -R @ c, p.source, p.sigma_m, p.sigma_deg)
        return out

    def sparse_points(self, **kw) -> dict[int, np.ndarray]:
        return self.mapper.sparse_points(**kw)

    def forget_before(self, frame: int):
        """Drop telemetry and tracked poses older than ``frame`` (memory stays bounded over long flights)."""
        for f in [f for f in self.tel if f < frame]:
            if f not in self.model_pose:
                del self.tel[f]
        for f in [f for f in self.tracked if f < frame]:
            del self.tracked[f]
