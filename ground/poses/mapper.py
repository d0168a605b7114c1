"""Mapping keyframes: pycolmap registration (:class:`ground.poses.registration.IncrementalRegistrar`) and the
georeferencing fit, on the caller's thread (:class:`Mapper`: lock-step replays, deterministic), or in a process of
its own through the same interface (:class:`ground.poses.mapper_process.MapperProcess`: live).

    mapper = Mapper(kf_camera, camera, workdir, settings)    # or MapperProcess(...): the same interface
    mapper.add(frame, image_bgr, telemetry)   # a keyframe proposed by the tracker (or, before a model, any)
    mapper.reference()                        # the newest registered keyframe to track against (Reference)
    mapper.registered()                       # registered keyframes (model frame), in order, model -> ENU
"""

from __future__ import annotations

import bisect
import logging

import cv2
import numpy as np

from ground.poses.georeference import fit_similarity, floor_plane, georeference_poses
from ground.poses.registration import IncrementalRegistrar, RegistrationSettings, Submodel
from ground.poses.telemetry_poses import KeyframeTelemetry
from ground.poses.tracking import Reference
from pomar.align import Similarity, compose
from pomar.camera import Camera
from pomar.rotations import camera_rotations

log = logging.getLogger(__name__)


class Mapper:
    #: The reference handed to tracking holds the keyframe's points seen in at least min_track keyframes within
    #: max_point_error_px (all of its points when fewer than 100 are).
    min_track = 2
    max_point_error_px = 1.5
    #: Mapping in this process never dies apart from the ground (see MapperProcess.died).
    died: dict | None = None
    restarts: tuple = ()  # nor is restarted

    def __init__(self, kf_camera: Camera, camera: Camera, workdir, settings: RegistrationSettings | None = None,
                 sigma_att_deg: float = 0.5):
        self.kf_cam, self.cam = kf_camera, camera
        self.registrar = IncrementalRegistrar(kf_camera, workdir, settings, sigma_att_deg)
        self.settings = self.registrar.s
        self.sigma_att = np.radians(sigma_att_deg)
        self.tel: dict[int, KeyframeTelemetry] = {}
        self.model_pose: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # registered keyframes, model frame
        self.kf_sorted: list[int] = []
        self.fit: Similarity | None = None  # model -> ENU
        self.fit_residual_m = float("nan")
        self._ref: Reference | None = None
        self.processed = -1  # the newest keyframe through registration
        self.attempts = 0
        self.skipped = 0  # always 0 here: only the process replaces proposals
        self.early_extracted = 0  # always 0 here: only the process shares SIFT with the ground
        self.changed: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # poses the last keyframe moved
        # the keyframes' images until the first model: it places all of them at once, and tracking the frames
        # between them needs their points (first_references)
        self._early: dict[int, np.ndarray] = {}
        self.first_references: list[Reference] = []
        self._moved_all = (0, 0)  # the registrar's re-anchorings and global refinements, as last seen
        self.moved: set[int] = set()  # keyframes whose poses changed since take_moved
        self.scale_source = "positions"  # what scales the georeference: the GPS positions, or the heights (_refit)

    # -- inputs
    def busy(self) -> bool:
        return False

    alive = True  # mapping on the caller's thread cannot have died without it

    def wait(self, timeout_s: float = 0.0) -> None:
        """Nothing to wait for: mapping is done on the caller's thread."""

    def add(self, frame: int, image_bgr: np.ndarray, tel, features=None) -> bool:
        """Map this keyframe now; returns whether it registered. ``features``: its SIFT features, if extracted
        elsewhere (:class:`ground.poses.sift.SiftExtractor`)."""
        return self._map(frame, image_bgr, tel, features)

    def close(self, timeout_s: float | None = None) -> None:
        """Write what the registrar holds (here, in this process: nothing to wait for)."""
        self.registrar.close()

    # -- mapping
    def _map(self, frame: int, image_bgr: np.ndarray, tel, features=None) -> bool:
        if frame <= self.processed:
            log.warning("keyframe %d came after keyframe %d was mapped: skipped", frame, self.processed)
            return False
        if image_bgr.shape[1] != self.kf_cam.width:
            image_bgr = cv2.resize(image_bgr, (self.kf_cam.width, self.kf_cam.height), interpolation=cv2.INTER_AREA)
        tel = tel if isinstance(tel, KeyframeTelemetry) else KeyframeTelemetry(*tel)  # (enu, q_gimbal, h_acc) too
        self.tel[frame] = tel
        self.attempts += 1
        if not self.model_pose:
            self._early[frame] = image_bgr
            for f in sorted(self._early)[:-2 * self.settings.init_frames]:
                del self._early[f]
        self.changed = {}
        q = np.asarray(tel.q_gimbal, float)
        prior = (tel.enu, camera_rotations(q[None], self.cam)[0], tel.h_acc) if np.isfinite(q).all() else None
        try:
            ok = self.registrar.add_keyframe(frame, image_bgr, prior, features)
        except Exception as exc:  # one keyframe that breaks the mapper must not stop the flight
            log.warning("keyframe %d failed to register: %s", frame, exc)
            self.registrar.failed.append(frame)
            ok = False
        self.processed = frame
        if not ok:
            return False
        first = not self.model_pose
        self.changed = self._model_poses()
        self._update(self.changed, self._refit({**self.model_pose, **self.changed}), self._reference(frame, image_bgr))
        if first:
            refs = [self._reference(f, self._early[f]) for f in sorted(self._early) if f in self.changed and f != frame]
            self.first_references = [r for r in refs if r is not None] + ([self._ref] if self._ref else [])
            self._early.clear()
        return True

    def take_moved(self) -> list[int]:
        """The keyframes whose poses changed (or came) since the last call, in order."""
        out, self.moved = sorted(self.moved), set()
        return out

    def _update(self, poses, fit, ref) -> None:
        self.moved.update(poses)
        for f in poses:
            if f not in self.model_pose:
                bisect.insort(self.kf_sorted, f)
        self.model_pose.update(poses)
        if fit is not None:
            self.fit, self.fit_residual_m = fit
        if ref is not None:
            self._ref = ref

    def _model_poses(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Poses of the current sub-model's recent keyframes (local refinement moves them a little)."""
        reg = self.registrar
        sm = reg.submodels[-1]
        # all of the sub-model's keyframes when it was just re-anchored or globally refined (it moved as a whole), else
        # the recent ones
        now = (reg.reanchored, reg.global_adjustments)
        moved, self._moved_all = now != self._moved_all, now
        names = (sm.names if moved or len(self.model_pose) < 3 * reg.s.init_frames
                 else sm.names[-(reg.s.match_window + 2):])
        out = {}
        for name in names:
            m = sm.rec.find_image_with_name(name).cam_from_world().matrix()
            R, t = georeference_poses(m[None, :, :3], m[None, :, 3], sm.to_first)
            out[reg.frame_of[name]] = (R[0], t[0])
        return out

    def _reference(self, frame: int, image_bgr: np.ndarray) -> Reference | None:
        """The keyframe just registered, as tracking needs it: grey image, keypoints with a 3-D point (model frame)."""
        sm = self.registrar.submodels[-1]
        im = sm.rec.find_image_with_name(f"{frame:06d}.jpg")
        if im is None or not im.has_pose:
            return None
        pts = sm.rec.points3D
        obs = [(p.xy, pts[p.point3D_id]) for p in im.get_observation_points2D()]
        # points seen in few keyframes have poorly known depth, and would pull the tracked poses off the model's
        good = [(xy, q) for xy, q in obs if q.track.length() >= self.min_track and q.error <= self.max_point_error_px]
        obs = good if len(good) >= 100 else obs
        if not obs:
            return None
        xy = np.array([o[0] for o in obs], float) - 0.5  # COLMAP's pixel centres to OpenCV's
        X = sm.to_first.apply(np.array([o[1].xyz for o in obs], float))
        m = im.cam_from_world().matrix()
        R, t = georeference_poses(m[None, :, :3], m[None, :, 3], sm.to_first)
        grey = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
        return Reference(frame, grey, xy, X, R[0], t[0])

    def _refit(self, model_pose) -> tuple[Similarity, float] | None:
        """The model -> ENU similarity from the recent registered keyframes (the last 400: a bounded cost)."""
        frames = [f for f in sorted(model_pose)[-400:] if f in self.tel and np.isfinite(self.tel[f].enu).all()
                  and np.isfinite(self.tel[f].q_gimbal).all()]
        if len(frames) < 3:
            return None
        R_m = np.array([model_pose[f][0] for f in frames])
        t_m = np.array([model_pose[f][1] for f in frames])
        c_m = -np.einsum("nji,nj->ni", R_m, t_m)
        g = np.array([self.tel[f].enu for f in frames])
        sig = np.array([self.tel[f].h_acc for f in frames])
        R_tel = camera_rotations(np.array([self.tel[f].q_gimbal for f in frames]), self.cam)
        # positions within their own accuracy of one another (a log's coarse rounding: a Phantom 4 Pro's first second
        # is one point rounded to 11 m; a drone standing): the scale they give is off by more than itself (its relative
        # error is their accuracy over their spread), so only the heights can scale the map (a fit at scale 1 places
        # and turns it; the heights' factor is then the scale)
        spread = float(np.sqrt(((g - g.mean(0)) ** 2).sum()))
        still = spread < float(np.median(sig))
        up_only = np.array([not self.tel[f].heading_known for f in frames])
        fit = fit_similarity(c_m, g, sig, R_m, R_tel, self.sigma_att, scale=1.0 if still else None, up_only=up_only)
        if not (np.isfinite(fit.similarity.scale) and fit.similarity.scale > 0):
            return None
        k = self._height_scale(fit.similarity, frames, c_m, g, fit.position_rms_m, positions_scale=not still)
        log.debug("georeference from %d keyframes: scale %.4f from %s (factor %s), GPS rms %.2f m", len(frames),
                  fit.similarity.scale * (k or 1.0), self.scale_source, k, fit.position_rms_m)
        if k is not None:
            fit = fit_similarity(c_m, g, sig, R_m, R_tel, self.sigma_att, scale=fit.similarity.scale * k,
                                 up_only=up_only)
        elif still:
            return None
        return fit.similarity, fit.position_rms_m

    def _height_scale(self, fit: Similarity, frames, c_m, g, residual_m: float,
                      positions_scale: bool = True) -> float | None:
        """The factor that brings the cameras' heights above the floor the map sees (a plane: floor_plane) to the log's
        heights above the take-off point, where those tell the map's scale better than the positions do: positions
        rounded coarsely (a Phantom 4 Pro's SRT: 4 decimals, 11 m) over a short flight scale it by tens of percent, the
        heights (to 0.01 m) against the floor by about the floor's own spread over the height. None where the log gives
        no heights, the map sees too little ground, or the positions know the scale better. Takes the take-off point to
        be level with the orchard's floor (say how far it is not, and the scale is off by that over the height)."""
        h = np.array([self.tel[f].height for f in frames], float)
        h_sigma = np.array([self.tel[f].height_acc for f in frames], float)
        ok = np.isfinite(h) & (h > 0) & np.isfinite(h_sigma)  # a height whose accuracy the log does not say: unused
        self.scale_source = "positions"
        if ok.sum() < 3:
            return None
        pts = [compose(fit, sm.to_first).apply(np.array([p.xyz for p in sm.rec.points3D.values()
                                                          if p.track.length() >= 3 and p.error <= 2.0], float).reshape(-1, 3))
               for sm in self.registrar.submodels[-2:] if sm.rec is not None and sm.to_first is not None]
        P = np.concatenate(pts) if pts else np.zeros((0, 3))
        floor = floor_plane(P) if len(P) >= 200 else None
        if floor is None:
            return None
        floor_sigma = floor.sigma_m
        h_map = (fit.apply(c_m)[ok] - floor.point) @ floor.normal  # the cameras' heights above the floor plane
        if not np.median(h_map) > 0:
            return None
        # the scale's relative error from each: the positions' error over their spread, and the floor's spread with
        # the heights' own accuracy, over the height. The positions' error: their scatter about the fit (measured,
        # for the 7 degrees of freedom the fit took), and at least the accuracy the log states (a 4-decimal SRT's
        # rounding, which a short flight's fit absorbs); not the 2 m assumed where it states none
        n = len(g)
        scatter = residual_m / np.sqrt(3.0) * np.sqrt(n / (n - 7)) if n > 7 else np.inf  # per axis
        stated = np.array([self.tel[f].h_acc_stated for f in frames], float)
        if np.isfinite(stated).any():
            scatter = max(scatter, float(np.nanmedian(stated)))
        rel_pos = scatter / max(float(np.sqrt(((g - g.mean(0)) ** 2).sum(1).sum())), 1e-9)
        rel_height = float(np.hypot(floor_sigma, np.median(h_sigma[ok]))) / float(np.median(h[ok]))
        if positions_scale and rel_height >= rel_pos:
            return None
        self.scale_source = "heights"
        return float(np.median(h[ok]) / np.median(h_map))

    # -- reading
    @property
    def has_model(self) -> bool:
        return bool(self.model_pose)

    def reference(self) -> Reference | None:
        return self._ref

    def registered(self) -> tuple[dict, list[int], Similarity | None]:
        """(frame -> (R, t) in the model frame, the frames in order, the fit model -> ENU)."""
        return self.model_pose, self.kf_sorted, self.fit

    def stats(self) -> dict:
        reg = self.registrar
        st = np.asarray(reg.stage_seconds, float).reshape(-1, 3)
        return {"keyframes_processed": len(reg.seconds), "failed": len(reg.failed), "submodels": len(reg.submodels),
                "revisits": reg.revisits, "reanchored": reg.reanchored, "rejoined": reg.rejoined,
                "scale_from": self.scale_source,
                "in_memory_from": reg.in_memory_from,
                "seconds": list(reg.seconds),
                "stage_seconds_median": dict(zip(("features", "matching", "mapping"),
                                                 np.median(st, 0).tolist() if len(st) else [None] * 3))}

    def submodels(self) -> list[Submodel]:
        return self.registrar.submodels

    def sparse_points(self, max_points: int = 4000, min_track: int = 3, max_error_px: float = 2.0,
                      seed: int = 0) -> dict[int, np.ndarray]:
        """The structure-from-motion points of the sub-models still in memory, in ENU: sub-model index -> (n, 3),
        points seen in at least ``min_track`` keyframes within ``max_error_px``, at most ``max_points`` (an even
        random sample) per sub-model."""
        out: dict[int, np.ndarray] = {}
        if self.fit is None:
            return out
        rng = np.random.default_rng(seed)
        for k, sm in enumerate(self.registrar.submodels):
            if sm.rec is None or sm.to_first is None:
                continue
            pts = [p for p in sm.rec.points3D.values() if p.track.length() >= min_track and p.error <= max_error_px]
            if len(pts) > max_points:
                pts = [pts[i] for i in np.sort(rng.choice(len(pts), max_points, replace=False))]
            xyz = np.array([p.xyz for p in pts], float).reshape(-1, 3)
            out[k] = compose(self.fit, sm.to_first).apply(xyz)
        return out
