"""The pose stage: the one pose interface the pipeline hands its frames to, lock-step or live.

Behind it: :class:`ground.poses.tracking.ImageTracking` takes the images in frame order and gives every frame that
carries one a pose from its own pixels against the map (KLT + PnP, milliseconds), proposing *mapping keyframes* to
:mod:`ground.poses.mapper`, which registers them (pycolmap, in its own process when live) and georeferences the
model; :class:`ground.poses.map_frame.MapFrame` is the frame the poses and the association work in. Fed each frame's
telemetry and each image in frame order, it says when a frame's pose can be decided and gives it with its source and
uncertainty:

- ``registered``: a mapping keyframe the model registered;
- ``tracked``: a frame tracked against the map;
- ``interpolated``: a frame without an image (or whose tracking failed, then flagged in
  ``ImageTracking.failed_frames``) between two posed frames at most ``max_interp_gap`` apart (centre linearly,
  rotation by slerp);
- ``extrapolated``: a frame past the last posed frame (the flight's last frames, after its last keyframe) or before
  the first, within ``max_interp_gap`` of the two nearest, carried on from them at their motion: the map poses it,
  whether or not the log reaches it (a log that ends before the video, a once-a-second log's last frames);
- ``telemetry``: GPS + gimbal attitude alone.

Poses come in the *map frame*: the model's coordinates taken through the first good
georeferencing fit, then frozen (so that the frames in the association's window stay consistent
while later fits move a little). ``map_to_enu`` takes points from the map frame to the
current best ENU frame; :attr:`origin` is the ENU origin (the first GPS fix, unless given).
"""

from __future__ import annotations

import bisect
import logging

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ground.poses.georeference import Pose, georeference_poses
from ground.poses.map_frame import MapFrame
from ground.poses.mapper import Mapper
from ground.poses.mapper_process import MapperProcess, MappingWorker
from ground.poses.telemetry_poses import KeyframeTelemetry
from ground.poses.registration import RegistrationSettings
from ground.poses.tracking import ImageTracking, TrackingSettings
from pomar.align import Similarity
from pomar.camera import Camera
from pomar.geo import Origin
from pomar.telemetry.base import Flags

log = logging.getLogger(__name__)


def no_pose_figures() -> dict:
    """:meth:`PoseStage.figures` of a flight whose poses never started (no camera message, no keyframe)."""
    return {"registration": {"keyframes_processed": 0, "registered": 0, "failed": 0, "submodels": 0,
                             "mapper_died": None, "mapper_restarts": [], "in_memory_from_keyframe": None,
                             "revisits": 0, "reanchored": 0, "rejoined": 0, "drift_m": 0.0, "drift_corrected": False,
                             "bend_deg": 0.0, "bend_corrected": False, "seconds_per_keyframe_median": None,
                             "stage_seconds_median": None, "proposals_skipped": 0, "features_extracted_here": 0,
                             "georeference_gps_rms_m": None, "georeference_scale_from": None, "georeference_scale": None,
                             "origin": None},
            "tracking": {"tracked": 0, "failed": 0, "retried_after_mapping": 0, "waits_for_mapper": 0,
                         "failed_frames": []},
            "timings": {"tracking_seconds": 0.0, "inline_mapping_seconds": 0.0, "mapping_seconds": 0.0}}


class PoseStage:
    """The ground's poses, wired: the frames' telemetry, the images in order (:class:`ImageTracking`: the tracker and
    the mapper), the map frame (:class:`MapFrame`), and which pose each frame gets."""

    def __init__(self, camera: Camera, workdir, keyframe_width: int | None = None,
                 settings: RegistrationSettings | None = None, origin: Origin | None = None,
                 max_interp_gap: int = 10, sigma_att_deg: float = 0.5, tracking: TrackingSettings | None = None,
                 init_spacing_s: float = 0.0, mapping_worker: MappingWorker | None = None):
        self.cam = camera
        self.kf_cam = camera if not keyframe_width else self._scaled(camera, keyframe_width)
        self.tel: dict[int, KeyframeTelemetry] = {}  # frame -> its telemetry
        # live (a mapping worker given), mapping runs in its own process: pycolmap holds the GIL, and tracking must
        # not wait for it; otherwise on this thread (lock-step)
        self.mapper = (MapperProcess(self.kf_cam, camera, workdir, settings, sigma_att_deg, worker=mapping_worker)
                       if mapping_worker is not None else Mapper(self.kf_cam, camera, workdir, settings, sigma_att_deg))
        self.tracking = ImageTracking(self.kf_cam, self.mapper, self.tel, tracking, init_spacing_s)
        self.map_frame = MapFrame(self.mapper, self.tel, camera, sigma_att_deg)
        self.origin = origin
        self.max_interp_gap = max_interp_gap
        self.sigma_att = np.radians(sigma_att_deg)

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

    @property
    def has_model(self) -> bool:
        return self.mapper.has_model

    def submodels(self):
        """The mapper's sub-models (for their model files)."""
        return self.mapper.submodels()

    # the map frame, as the apples and the map files read it
    def metres_per_unit(self) -> float:
        return self.map_frame.metres_per_unit()

    def map_to_enu(self) -> Similarity:
        """The map frame -> ENU similarity."""
        return self.map_frame.map_to_enu()

    def to_enu(self, X: np.ndarray) -> np.ndarray:
        return self.map_frame.to_enu(X)

    def correction(self, frames, sigma_frames: float):
        """The map's bend and drift corrections at ``frames`` (:meth:`MapFrame.correction`)."""
        return self.map_frame.correction(frames, sigma_frames)

    # the images, as the pipeline hands them over
    def add_image(self, frame: int, jpeg: bytes, t_capture: float) -> bool:
        """A keyframe's JPEG, to tracking (and through it to the mapper); False where it does not decode."""
        return self.tracking.add_jpeg(frame, jpeg, t_capture)

    def drop_waiting(self) -> None:
        """Told to stop: the images not yet tracked are left out."""
        self.tracking.drop_waiting()

    def settle(self) -> None:
        """The flight's end: track what waits on the mapper."""
        self.tracking.settle()

    def wait_for_mapping(self, timeout_s: float) -> None:
        self.mapper.wait(timeout_s)

    def figures(self) -> dict:
        """What report.json says of the poses: ``registration`` and ``tracking``, and their ``timings``."""
        reg = self.mapper.stats()
        m, t, a = self.mapper, self.tracking, self.map_frame
        return {
            "registration": {
                "keyframes_processed": reg["keyframes_processed"],
                "registered": len(self.model_pose),
                "failed": reg["failed"],
                "submodels": reg["submodels"],
                # the mapping process died by itself (exit code, keyframes mapped and lost); each restart, and how its
                # new model was placed in the map's frame (keyframes shared, residuals) or null if it never was
                "mapper_died": m.died,
                "mapper_restarts": list(m.restarts),
                # the keyframe from which the mapping folder refused writes (a full disk): mapped in memory since,
                # and those sub-models' model files are not written
                "in_memory_from_keyframe": reg.get("in_memory_from"),
                # across passes: keyframes matched to earlier keyframes of the same place, re-anchorings of a
                # sub-model onto earlier passes' points, sub-models placed by telemetry after the chain broke
                "revisits": reg["revisits"],
                "reanchored": reg["reanchored"],
                "rejoined": reg["rejoined"],
                # the map's drift from the GPS along the flight, and whether the outputs were corrected for it
                "drift_m": a.drift_m,
                "drift_corrected": a.drift_corrected,
                # the map's turn from the gimbal's attitudes along the flight, and whether it was taken back out
                "bend_deg": a.bend_deg,
                "bend_corrected": a.bend_corrected,
                "seconds_per_keyframe_median": float(np.median(reg["seconds"])) if reg["seconds"] else None,
                "stage_seconds_median": reg["stage_seconds_median"],
                # proposals the mapping process replaced with a newer one before it was free
                "proposals_skipped": m.skipped,
                # keyframes before the first model whose SIFT features this process extracted, the mapper being busy
                "features_extracted_here": m.early_extracted,
                "georeference_gps_rms_m": self.fit_residual_m,
                # what scales the map most: the GPS positions, or the heights above take-off against the floor it sees
                "georeference_scale_from": reg.get("scale_from", "positions"),
                # the map's scale (metres per model unit), its 1-sigma in %, and each source's estimate and weight
                # (ground.poses.scale)
                "georeference_scale": reg.get("scale"),
                "origin": self.origin.as_dict() if self.origin else None,
            },
            "tracking": {"tracked": t.tracker.tracked,
                         # frames that tracking could not place, even after the mapper had mapped them (flagged)
                         "failed": len(t.failed_frames),
                         # frames tracked once the mapper, handed them when tracking failed, had mapped them
                         "retried_after_mapping": t.retried,
                         # times the frames waited for a busy mapper to take a keyframe (mapping behind the flight)
                         "waits_for_mapper": t.waits_for_mapper,
                         "failed_frames": t.failed_frames[-100:]},
            "timings": {"tracking_seconds": t.seconds["tracking"],
                        "inline_mapping_seconds": t.seconds["mapping_inline"],
                        "mapping_seconds": float(sum(reg["seconds"]))},
        }

    def scale_estimate(self) -> dict | None:
        """The map's scale, its 1-sigma and its sources (ground.poses.scale.ScaleEstimate.as_dict); None before the map
        is scaled."""
        return self.mapper.stats().get("scale")

    # -- inputs
    def add_telemetry(self, frame: int, lat: float, lon: float, alt: float, q_gimbal, h_acc: float,
                      height: float = float("nan"), height_acc: float = float("nan"), flags: int = 0,
                      t: float = float("nan")) -> None:
        """A frame's telemetry: its ENU position, gimbal attitude, horizontal accuracy (2 m where unknown), height
        above the take-off point and its accuracy (NaN where the log does not say), and its flags (a fixed mount
        without the vehicle's attitude: the camera's heading is only the track's)."""
        if self.origin is None and np.isfinite([lat, lon, alt]).all():
            self.origin = Origin(float(lat), float(lon), float(alt))
        enu = (np.asarray(self.origin.to_enu(lat, lon, alt), float).reshape(3) if self.origin is not None
               else np.full(3, np.nan))
        track_heading = int(Flags.FIXED_MOUNT | Flags.NO_ATTITUDE)
        self.tel[frame] = KeyframeTelemetry(enu, np.asarray(q_gimbal, float), float(h_acc), float(height),
                                            float(height_acc), (int(flags) & track_heading) != track_heading, float(t))

    def add_frame(self, msg) -> None:
        """A frame message's telemetry (:class:`pomar.wire.FrameMessage`)."""
        t = msg.telemetry
        self.add_telemetry(msg.frame, t.lat, t.lon, t.alt, t.q_gimbal, t.h_acc, t.height, t.height_acc, t.flags,
                           msg.t_capture)

    @staticmethod
    def keyframe_width(jpegs) -> int | None:
        """The width of the first of these JPEG images that decodes (None if none does)."""
        for jpeg in jpegs:
            img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
            if img is not None:
                return img.shape[1]
        return None

    def close(self, timeout_s: float = 600.0) -> None:
        """Stop the mapper (within ``timeout_s``)."""
        self.mapper.close(timeout_s=timeout_s)

    # -- decisions
    def ready(self, frame: int, final: bool = False, stalled: bool = False) -> bool:
        """Whether frame's pose can be decided now: the image at or after it went through tracking, and the model
        exists and is georeferenced (or bootstrapping had its chances), or the images stopped coming (``stalled``).
        The first frame posed fixes the map frame: a model the log cannot georeference yet (a Phantom 4 Pro's first
        second, whose positions are one rounded point; its heights scale it once the map sees the floor) would leave
        the whole flight on telemetry poses in ENU, so the frames wait for its fit, for as many keyframes as the first
        model had tries."""
        self.tracking.catch_up()
        if final or stalled:
            return True
        if frame > self.tracking.processed:
            return False
        if self.map_frame.fixed:
            return True
        tries = self.mapper.settings.first_model_tries
        if self.mapper.has_model:
            return self.mapper.fit is not None or len(self.mapper.model_pose) >= tries
        return self.mapper.attempts >= tries

    def _model_frame_pose(self, frame: int, model_pose) -> tuple[np.ndarray, np.ndarray, str] | None:
        """A registered frame's pose in the model now; a tracked frame's, carried along as the mapper has since moved
        the keyframe it was tracked from (its pose relative to that keyframe kept): a frame given its pose after a
        correction round must agree with the frames that round corrected, or the tracks across them split."""
        if frame in model_pose:
            return (*model_pose[frame], "registered")
        if frame in self.tracking.tracked:
            R, t = self.tracking.tracked[frame]
            if self._carried(frame, model_pose):
                k, R_then, t_then = self.tracking.anchors[frame]
                R_now, t_now = model_pose[k]
                rel = R @ R_then.T  # the keyframe's camera to the frame's
                R, t = rel @ R_now, rel @ (t_now - t_then) + t
            return (R, t, "tracked")
        return None

    def _carried(self, frame: int, model_pose) -> bool:
        """Whether a tracked frame's pose follows the keyframe it was tracked from (that keyframe is in the map)."""
        anchor = self.tracking.anchors.get(frame)
        return anchor is not None and anchor[0] in model_pose

    def _neighbours(self, frame: int, kf_sorted: list[int]) -> tuple[int, int] | None:
        """The nearest posed frames (registered or tracked) before and after ``frame``, within max_interp_gap."""
        lo = hi = None
        tracked = self.tracking.tracked
        for f in range(frame - 1, frame - self.max_interp_gap - 1, -1):
            if f in tracked or self._has(kf_sorted, f):
                lo = f
                break
        if lo is None:
            return None
        for f in range(frame + 1, lo + self.max_interp_gap + 1):
            if f in tracked or self._has(kf_sorted, f):
                hi = f
                break
        return None if hi is None else (lo, hi)

    @staticmethod
    def _has(sorted_frames: list[int], f: int) -> bool:
        k = bisect.bisect_left(sorted_frames, f)
        return k < len(sorted_frames) and sorted_frames[k] == f

    def _beside(self, frame: int, kf_sorted: list[int]) -> tuple[int, int] | None:
        """The two nearest posed frames on one side of ``frame`` (a frame with none on the other side within
        max_interp_gap), the nearer within max_interp_gap of it: (farther, nearer)."""
        tracked = self.tracking.tracked
        for step in (-1, 1):
            near = [f for f in range(frame + step, frame + step * (self.max_interp_gap + 1), step)
                    if f in tracked or self._has(kf_sorted, f)][:1]
            if not near:
                continue
            far = [f for f in range(near[0] + step, near[0] + step * (self.max_interp_gap + 1), step)
                   if f in tracked or self._has(kf_sorted, f)][:1]
            return (far[0], near[0]) if far else None
        return None

    def pose(self, frame: int) -> Pose | None:
        """The frame's pose in the map frame (call once :meth:`ready`): its own if it was registered or
        tracked, else interpolated between its nearest posed frames, else carried on from the two nearest on one side
        (:meth:`_beside`), else its telemetry's; None without any."""
        model_pose, kf_sorted, _ = self.mapper.registered()
        own = self._model_frame_pose(frame, model_pose)
        between = self._between(frame, model_pose, kf_sorted) if own is None else None
        return self.map_frame.frame_pose(frame, own, between, self.tel.get(frame), self.cam,
                                     float(np.degrees(self.sigma_att)))

    def _between(self, frame: int, model_pose, kf_sorted):
        """(a, pose at a, b, pose at b) of the nearest posed frames around ``frame`` (:meth:`_neighbours`), else of
        the two nearest on one side (:meth:`_beside`, the frame then outside a..b), or None."""
        ab = self._neighbours(frame, kf_sorted)
        if ab is None and self.mapper.has_model:
            ab = self._beside(frame, kf_sorted)
        return None if ab is None else (ab[0], self._model_frame_pose(ab[0], model_pose),
                                        ab[1], self._model_frame_pose(ab[1], model_pose))

    # -- corrections of poses already given
    #: A frame is corrected by keyframes at most this many frames away.
    MAX_CORRECTION_GAP = 40
    #: Smaller corrections are left out (the association would redo its triangulations for nothing).
    MIN_CORRECTION_M = 1e-3
    MIN_CORRECTION_RAD = 2e-4

    def take_moved(self) -> list[int]:
        """The keyframes the mapper placed or moved since the last call."""
        return self.mapper.take_moved()

    def _held_pose(self, frame: int, source: str, model_pose, kf_sorted) -> Pose | None:
        """The pose ``frame`` (given from ``source``) would be given now, from what is still held of it: a keyframe's
        in the model, a tracked frame's carried along with the keyframe it was tracked from, an interpolated frame's
        between its neighbours as they are now. None once that is forgotten (:meth:`forget_before`)."""
        own = self._model_frame_pose(frame, model_pose)
        between = None
        if own is None and source in ("interpolated", "extrapolated"):
            between = self._between(frame, model_pose, kf_sorted)
            if between is None or any(p is None or (p[2] == "tracked" and not self._carried(f, model_pose))
                                      for f, p in ((between[0], between[1]), (between[2], between[3]))):
                return None
        elif own is None or (own[2] == "tracked" and not self._carried(frame, model_pose)):
            return None
        return self.map_frame.frame_pose(frame, own, between, None, self.cam, float(np.degrees(self.sigma_att)))

    def corrected(self, given: dict[int, Pose], frames) -> dict[int, Pose]:
        """The poses given earlier for ``frames`` (from ``given``), moved as the mapper has since moved the keyframes
        about them (bundle adjustment, a re-anchoring on an earlier pass): each to the pose it would be given now
        (:meth:`_held_pose`), so that a tracked frame keeps the pose relative to its keyframe that tracking measured
        (the keyframe after it, placed later and moved by its own errors, has no say). A frame whose tracking is
        forgotten moves by the corrections of the keyframes on either side of it, interpolated (rotation by slerp,
        centre linearly), or of the nearest one. Telemetry poses, and any pose before the map frame was fixed,
        stay as they were; only the poses that changed are returned."""
        if self.map_frame.frozen is None:
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
                                          np.array([model_pose[k][1] for k in kfs]), self.map_frame.frozen)
        C_now = -np.einsum("nji,nj->ni", R_now, t_now)
        R_was = np.array([given[k].R for k in kfs])
        dC = C_now - np.array([given[k].centre for k in kfs])
        Q = Rotation.from_matrix(np.einsum("nji,njk->nik", R_was, R_now))  # R_now = R_was @ Q
        unit = self.metres_per_unit()  # the poses are in the map frame's units, the least correction in metres
        out = {}
        for f in frames:
            p = given[f]
            held = self._held_pose(f, p.source, model_pose, kf_sorted) if p.source != "apples" else None
            if held is not None:
                dc, turn = held.centre - p.centre, Rotation.from_matrix(p.R.T @ held.R).magnitude()
                if np.linalg.norm(dc) * unit >= self.MIN_CORRECTION_M or turn >= self.MIN_CORRECTION_RAD:
                    out[f] = Pose(f, held.R, held.t, p.source, p.sigma_m, p.sigma_deg)
                continue
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
            R = p.R @ q.as_matrix()
            c = p.centre + dc
            if np.linalg.norm(dc) * unit < self.MIN_CORRECTION_M and q.magnitude() < self.MIN_CORRECTION_RAD:
                continue
            out[f] = Pose(f, R, -R @ c, p.source, p.sigma_m, p.sigma_deg)
        return out

    def sparse_points(self, **kw) -> dict[int, np.ndarray]:
        return self.mapper.sparse_points(**kw)

    def forget_before(self, frame: int):
        """Drop telemetry and tracked poses older than ``frame`` (memory stays bounded over long flights)."""
        for f in [f for f in self.tel if f < frame]:
            if f not in self.mapper.model_pose:
                del self.tel[f]
        self.tracking.forget_before(frame)
