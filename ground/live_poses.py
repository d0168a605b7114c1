"""Camera poses for a live flight: keyframes registered one at a time, georeferenced as the model grows.

:class:`LivePoses` is fed each frame's telemetry and each keyframe's image as they arrive; it says
when a frame's pose can be decided (the next keyframe after it has been through registration, or
the keyframes stopped coming) and gives that pose with its source and uncertainty:

- ``registered``: a keyframe the model registered;
- ``interpolated``: between two registered keyframes at most ``max_interp_gap`` frames apart
  (centre linearly, rotation by slerp);
- ``telemetry``: GPS + gimbal attitude alone.

Poses come in the *association frame*: the model's coordinates taken through the first good
georeferencing fit, then frozen (so that the frames in the association's window stay consistent
while later fits move a little). :meth:`to_enu` takes points from the association frame to the
current best ENU frame; :attr:`origin` is the ENU origin (the first GPS fix, unless given).
"""

from __future__ import annotations

import bisect
import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ground.georeference import fit_similarity, georeference_poses
from ground.poses import camera_rotations
from ground.registration import IncrementalRegistrar, RegistrationSettings
from pomar.align import Similarity
from pomar.camera import Camera
from pomar.geo import Origin

log = logging.getLogger(__name__)

IDENTITY = Similarity(1.0, np.eye(3), np.zeros(3))


def compose(a: Similarity, b: Similarity) -> Similarity:
    """a after b: x -> a(b(x))."""
    return Similarity(a.scale * b.scale, a.R @ b.R, a.scale * a.R @ b.t + a.t)


def inverse(a: Similarity) -> Similarity:
    Rt = a.R.T
    return Similarity(1.0 / a.scale, Rt, -Rt @ a.t / a.scale)


@dataclass
class Pose:
    frame: int
    R: np.ndarray  # association-frame-to-camera rotation
    t: np.ndarray
    source: str  # registered | interpolated | telemetry
    sigma_m: float
    sigma_deg: float

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t


class LivePoses:
    def __init__(self, camera: Camera, workdir, keyframe_width: int | None = None,
                 settings: RegistrationSettings | None = None, origin: Origin | None = None,
                 max_interp_gap: int = 10,
                 sigma_att_deg: float = 0.5):
        self.cam = camera
        self.kf_cam = camera if not keyframe_width else self._scaled(camera, keyframe_width)
        self.registrar = IncrementalRegistrar(self.kf_cam, workdir, settings)
        self.origin = origin
        self.max_interp_gap = max_interp_gap
        self.sigma_att = np.radians(sigma_att_deg)
        self.tel: dict[int, tuple[np.ndarray, np.ndarray, float]] = {}  # frame -> (enu, q_gimbal, h_acc)
        self.model_pose: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # registered keyframes, model coords
        self.kf_processed = -1  # index of the newest keyframe through registration
        self.fit: Similarity | None = None  # model -> ENU, current
        self.frozen: Similarity | None = None  # model -> association frame (a fit frozen), or None
        self.assoc_from_enu: Similarity | None = None  # set when the association frame is ENU itself
        self.fit_residual_m = float("nan")
        self._kf_sorted: list[int] = []  # the keys of model_pose, in order (kept, not re-sorted per frame)

    @staticmethod
    def _scaled(cam: Camera, width: int) -> Camera:
        s = width / cam.width
        return Camera(int(round(cam.width * s)), int(round(cam.height * s)), cam.fx * s, cam.fy * s, cam.cx * s, cam.cy * s)

    # -- inputs
    def add_telemetry(self, frame: int, lat: float, lon: float, alt: float, q_gimbal, h_acc: float) -> None:
        if self.origin is None and np.isfinite([lat, lon, alt]).all():
            self.origin = Origin(float(lat), float(lon), float(alt))
        enu = (np.asarray(self.origin.to_enu(lat, lon, alt), float).reshape(3) if self.origin is not None
               else np.full(3, np.nan))
        self.tel[frame] = (enu, np.asarray(q_gimbal, float), float(h_acc) if np.isfinite(h_acc) and h_acc > 0 else 2.0)

    def add_keyframe(self, frame: int, image_bgr: np.ndarray) -> bool:
        """Register a keyframe (in frame order); returns whether it has a pose."""
        if frame <= self.kf_processed:
            log.warning("keyframe %d arrived after keyframe %d was registered: skipped", frame, self.kf_processed)
            return False
        if image_bgr.shape[1] != self.kf_cam.width:
            import cv2

            image_bgr = cv2.resize(image_bgr, (self.kf_cam.width, self.kf_cam.height), interpolation=cv2.INTER_AREA)
        try:
            ok = self.registrar.add_keyframe(frame, image_bgr)
        except Exception as exc:  # one keyframe that breaks the mapper must not stop the flight
            log.warning("keyframe %d failed to register: %s", frame, exc)
            self.registrar.failed.append(frame)
            ok = False
        self.kf_processed = frame
        if ok:
            self._refresh_model_poses()
            self._refit()
        return ok

    def _refresh_model_poses(self):
        """Poses of the current sub-model's recent keyframes (local refinement moves them a little)."""
        reg = self.registrar
        sm = reg.submodels[-1]
        names = sm.names if len(self.model_pose) < 3 * reg.s.init_frames else sm.names[-(reg.s.match_window + 2):]
        for name in names:
            m = sm.rec.find_image_with_name(name).cam_from_world().matrix()
            R, t = georeference_poses(m[None, :, :3], m[None, :, 3], sm.to_first)
            f = reg.frame_of[name]
            if f not in self.model_pose:
                bisect.insort(self._kf_sorted, f)
            self.model_pose[f] = (R[0], t[0])

    def _refit(self):
        frames = [f for f in self._kf_sorted[-400:] if f in self.tel and np.isfinite(self.tel[f][0]).all()
                  and np.isfinite(self.tel[f][1]).all()]
        if len(frames) < 3:
            return
        # bounded cost: the recent stretch of the flight (the last 400 registered keyframes)
        R_m = np.array([self.model_pose[f][0] for f in frames])
        t_m = np.array([self.model_pose[f][1] for f in frames])
        c_m = -np.einsum("nji,nj->ni", R_m, t_m)
        g = np.array([self.tel[f][0] for f in frames])
        sig = np.array([self.tel[f][2] for f in frames])
        R_tel = camera_rotations(np.array([self.tel[f][1] for f in frames]), self.cam)
        fit = fit_similarity(c_m, g, sig, R_m, R_tel, self.sigma_att)
        self.fit, self.fit_residual_m = fit.similarity, fit.position_rms_m

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

    def to_enu(self, X: np.ndarray) -> np.ndarray:
        return self.assoc_to_enu().apply(np.asarray(X, float).reshape(-1, 3))

    # -- decisions
    def ready(self, frame: int, final: bool = False, stalled: bool = False) -> bool:
        """Whether frame's pose can be decided now: the keyframe at or after it went through registration
        (and the model exists, or bootstrapping had its chances), or the keyframes stopped coming (``stalled``)."""
        if final or stalled:
            return True
        if frame > self.kf_processed:
            return False
        if self.model_pose or self.frozen is not None or self.assoc_from_enu is not None:
            return True
        return len(self.registrar.seconds) >= 3 * self.registrar.s.init_frames

    def pose(self, frame: int) -> Pose | None:
        """The frame's pose in the association frame (call once :meth:`ready`); None without telemetry either."""
        self._freeze()
        m2a = self.model_to_assoc()
        if m2a is not None and self.model_pose:
            if frame in self.model_pose:
                R, t = georeference_poses(self.model_pose[frame][0][None], self.model_pose[frame][1][None], m2a)
                return Pose(frame, R[0], t[0], "registered", 0.01, 0.05)
            kf = self._kf_sorted
            k = bisect.bisect_left(kf, frame)
            if 0 < k < len(kf) and kf[k] - kf[k - 1] <= self.max_interp_gap:
                a, b = int(kf[k - 1]), int(kf[k])
                R2, t2 = georeference_poses(np.array([self.model_pose[a][0], self.model_pose[b][0]]),
                                            np.array([self.model_pose[a][1], self.model_pose[b][1]]), m2a)
                C = -np.einsum("nji,nj->ni", R2, t2)
                w = (frame - a) / (b - a)
                R = Slerp([0.0, 1.0], Rotation.from_matrix(R2))([w]).as_matrix()[0]
                c = (1 - w) * C[0] + w * C[1]
                return Pose(frame, R, -R @ c, "interpolated", 0.02, 0.1)
        # telemetry alone
        if frame not in self.tel or not np.isfinite(self.tel[frame][0]).all():
            return None
        enu, qg, h_acc = self.tel[frame]
        R_enu = camera_rotations(qg[None], self.cam)[0]
        e2a = inverse(self.assoc_to_enu())
        R, t = georeference_poses(R_enu[None], (-R_enu @ enu)[None], e2a)
        return Pose(frame, R[0], t[0], "telemetry", h_acc, np.degrees(self.sigma_att))

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

    def forget_before(self, frame: int):
        """Drop telemetry older than ``frame`` (memory stays bounded over long flights)."""
        for f in [f for f in self.tel if f < frame]:
            if f not in self.model_pose:
                del self.tel[f]
