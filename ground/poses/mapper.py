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
from ground.poses.scale import ScaleEstimate, combine, heights_source, positions_source
from ground.poses.registration import IncrementalRegistrar, RegistrationSettings, Submodel
from ground.poses.telemetry_poses import KeyframeTelemetry
from ground.poses.tracking import Reference
from pomar.align import Similarity, compose
from pomar.camera import Camera
from pomar.rotations import camera_rotations
from pomar.telemetry.base import UNSTATED_HEIGHT_ACC_M

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
        self.scale_source = "positions"  # the source that weighs most in the georeference's scale (_scale)
        self.scale_estimate: ScaleEstimate | None = None  # the map's scale, its uncertainty and sources (_scale)
        self._left_out_said: dict[str, str] = {}  # sources left out now (logged once), and why

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
        est = self._scale(fit, frames, c_m, g, still)
        if est is not None:
            log.debug("georeference from %d keyframes: scale %.4f +- %.2f %% (%s), GPS rms %.2f m", len(frames),
                      est.scale, 100 * est.sigma_rel, self.scale_source, fit.position_rms_m)
            if est.scale != fit.similarity.scale:
                fit = fit_similarity(c_m, g, sig, R_m, R_tel, self.sigma_att, scale=est.scale, up_only=up_only)
        elif still:
            return None
        return fit.similarity, fit.position_rms_m

    def _scale(self, fit, frames, c_m, g, still: bool) -> ScaleEstimate | None:
        """The map's scale from every source these keyframes give (ground.poses.scale), combined by their variances:
        the positions' (unless they stand within their own accuracy of one another: a log's coarse rounding, a drone
        standing), and the cameras' heights above the floor the map sees against the log's heights above take-off.
        Takes the take-off point to be level with the orchard's floor (say how far it is not, and the heights' scale is
        off by that over the height). Sets ``scale_source`` (the heaviest source) and ``scale_estimate``."""
        sources = []
        S = fit.similarity
        tels = [self.tel[f] for f in frames]
        stated = np.array([t.h_acc_stated for t in tels], float)
        if not still:
            # the capture times; where the log gives none, frames 0.1 s apart (the worst over the GPS error's
            # correlation times hardly depends on it)
            t = np.array([x.t for x in tels], float)
            t = t if np.isfinite(t).all() else np.asarray(frames, float) * 0.1
            # the positions' accuracy: the log's, at least their measured scatter about the fit (per axis, for the 7
            # degrees of freedom the fit took)
            n = len(g)
            scatter = fit.position_rms_m / np.sqrt(3.0) * np.sqrt(n / (n - 7)) if n > 7 else np.inf
            sigma = np.maximum(np.array([x.h_acc for x in tels], float), scatter)
            sources.append(positions_source(S.scale, g, t, sigma, bool(np.isfinite(stated).all() and (stated > 0).all())))
        h = np.array([x.height for x in tels], float)
        h_sigma = np.array([x.height_acc for x in tels], float)
        ok = np.isfinite(h) & (h > 0)
        h_stated = bool(np.isfinite(h_sigma[ok]).all())
        h_sigma = np.where(np.isfinite(h_sigma), h_sigma, UNSTATED_HEIGHT_ACC_M)
        if ok.sum() >= 3:
            pts = [compose(S, sm.to_first).apply(np.array([p.xyz for p in sm.rec.points3D.values()
                                                            if p.track.length() >= 3 and p.error <= 2.0],
                                                           float).reshape(-1, 3))
                   for sm in self.registrar.submodels[-2:] if sm.rec is not None and sm.to_first is not None]
            P = np.concatenate(pts) if pts else np.zeros((0, 3))
            floor = floor_plane(P) if len(P) >= 200 else None
            if floor is not None:
                hs = heights_source(S.scale, h[ok], h_sigma[ok], S.apply(c_m)[ok], floor, h_stated)
                if hs is not None:
                    sources.append(hs)
        est = combine(sources)
        if est is not None:
            self.scale_source = est.heaviest
            self.scale_estimate = est
            for name, why in est.left_out.items():  # said once while it stays out, again if it comes back and goes
                if name not in self._left_out_said:
                    log.warning("map scale: the %s left out, %s", name, why)
                self._left_out_said[name] = why
            for name in set(self._left_out_said) - set(est.left_out):
                del self._left_out_said[name]
        return est

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
                "scale": self.scale_estimate.as_dict() if self.scale_estimate is not None else None,
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
