"""Georeferencing a structure-from-motion model: the similarity from model coordinates to local ENU.

GPS positions alone cannot fix the roll about a straight flight line (the camera centres are nearly
collinear), so the fit also uses the camera orientation the telemetry gives (vehicle attitude x
gimbal x mount): each frame contributes its GPS position, weighted by 1/sigma_pos^2, and its three
camera axes in ENU, weighted by 1/sigma_att^2 (radians); a frame whose heading the log does not know (a fixed
mount on the track's heading) gives only which way is up, which a stabilised gimbal holds. The cost

    sum_i w_i |s R c_i + t - g_i|^2  +  sum_i,k v_i |R a_ik - b_ik|^2

is minimised exactly in t, and alternately in R (weighted Procrustes over positions and axes together)
and s (closed form), from a start on positions alone.

:class:`AssociationFrame` is the frame the live association works in (the first fit, frozen) and gives each frame's
:class:`Pose` in it; :func:`drift_offsets` takes a long map's bends back to the GPS.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from pomar.align import IDENTITY, Similarity, compose, inverse
from pomar.rotations import camera_rotations

log = logging.getLogger(__name__)


def _procrustes(H: np.ndarray) -> np.ndarray:
    """Rotation R maximising tr(R^T H)."""
    U, _, Vt = np.linalg.svd(H)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt)) or 1.0
    return U @ D @ Vt


@dataclass
class GeoFit:
    similarity: Similarity
    position_rms_m: float  # weighted residual of the GPS term
    axis_rms_deg: float  # residual of the orientation term
    n: int


def fit_similarity(c_model: np.ndarray, g_enu: np.ndarray, sigma_pos: np.ndarray | float,
                   R_model: np.ndarray | None = None, R_tel: np.ndarray | None = None,
                   sigma_att_rad: np.ndarray | float = np.radians(1.0), iterations: int = 20,
                   scale: float | None = None, up_only: np.ndarray | None = None) -> GeoFit:
    """Similarity taking model points to ENU.

    c_model (N, 3) camera centres in the model; g_enu (N, 3) their GPS positions in ENU; sigma_pos (N,)
    or scalar, metres. R_model (N, 3, 3) world(model)-to-camera rotations; R_tel (N, 3, 3) world(ENU)-to-
    camera rotations from the telemetry; without them, positions only (Umeyama, weighted). ``scale``: the
    scale, when something else than the positions gives it (only rotation and translation are fitted). ``up_only``
    (N,) bool: frames whose telemetry knows the camera's tilt but not its heading; only their up direction counts.
    """
    c = np.asarray(c_model, float)
    g = np.asarray(g_enu, float)
    n = len(c)
    if n < 2 or g.shape != c.shape:
        raise ValueError(f"need >= 2 matching (N, 3) point sets, got {c.shape} and {g.shape}")
    w = np.broadcast_to(1.0 / np.asarray(sigma_pos, float) ** 2, (n,)).astype(float)
    cm, gm = (w[:, None] * c).sum(0) / w.sum(), (w[:, None] * g).sum(0) / w.sum()
    cc, gc = c - cm, g - gm
    use_axes = R_model is not None and R_tel is not None
    if use_axes:
        v = np.broadcast_to(1.0 / np.asarray(sigma_att_rad, float) ** 2, (n,)).astype(float)
        # camera axes in world coordinates are the rows of the world-to-camera rotations
        A = np.asarray(R_model, float)  # a_ik = A[i, k, :]
        B = np.asarray(R_tel, float)
        up = np.zeros(n, bool) if up_only is None else np.broadcast_to(np.asarray(up_only, bool), (n,))
        if up.any():
            # a heading the log does not know (a fixed mount turned by the track's heading): only which way is up in
            # the camera counts, as the pair (up in the model, seen through the camera) -> ENU's up
            A, B = A.copy(), B.copy()
            u_cam = B[up, :, 2]  # ENU's up in camera coordinates (the third column of world-to-camera)
            A[up] = np.einsum("nkp,nk->np", A[up], u_cam)[:, None, :] * np.array([0.0, 0.0, 1.0])[None, :, None]
            B[up] = np.array([0.0, 0.0, 1.0])[None, None, :] * np.array([0.0, 0.0, 1.0])[None, :, None]
        Hax = np.einsum("i,ikp,ikq->pq", v, B, A)
    else:
        Hax = np.zeros((3, 3))
    s = scale if scale is not None else np.sqrt((w * (gc**2).sum(1)).sum() / max((w * (cc**2).sum(1)).sum(), 1e-300))
    Hpos = np.einsum("i,ip,iq->pq", w, gc, cc)
    R = _procrustes(Hpos) if not use_axes else _procrustes(Hax + s * Hpos)
    for _ in range(iterations):
        if scale is None:
            s = float((w * np.einsum("ip,ip->i", gc, cc @ R.T)).sum() / max((w * (cc**2).sum(1)).sum(), 1e-300))
        R_new = _procrustes(s * Hpos + Hax)
        if np.allclose(R_new, R, atol=1e-12):
            R = R_new
            break
        R = R_new
    t = gm - s * R @ cm
    sim = Similarity(s, R, t)
    pos_res = np.linalg.norm(sim.apply(c) - g, axis=1)
    ax = 0.0
    if use_axes:
        cosang = np.clip(np.einsum("ikp,ikp->ik", A @ R.T, B), -1, 1)
        used = np.where(up[:, None], np.array([False, False, True])[None, :], True)  # the axes each frame gave
        ang = np.arccos(cosang)[used]
        ax = float(np.degrees(np.sqrt(np.mean(ang ** 2))))
    return GeoFit(sim, float(np.sqrt(np.mean(pos_res**2))), ax, n)


def georeference_poses(R_model: np.ndarray, t_model: np.ndarray, sim: Similarity) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera poses in ENU from model poses: X_enu = s R X_model + t."""
    R_enu = np.asarray(R_model) @ sim.R.T
    t_enu = sim.scale * np.asarray(t_model) - np.einsum("nij,j->ni", R_enu, sim.t)
    return R_enu, t_enu


def drift_offsets(kf_frames: np.ndarray, residuals: np.ndarray, weights: np.ndarray, frames: np.ndarray,
                  sigma_frames: float) -> np.ndarray:
    """ENU offsets (n, 3) at ``frames``: the keyframes' residuals (GPS minus the map's camera centre, (m, 3)) fitted by
    a line around each frame, with Gaussian weights of their distance in frames (``sigma_frames``) times ``weights``
    (1 / GPS variance).

    One similarity takes the whole chain of sub-models into ENU, fitted to its recent keyframes; over minutes of flight
    the chain bends (a 900-m pass: 25 m at its start), and these offsets take each stretch of the map to where the
    GPS around it puts it. A kernel wider than the GPS error's wander keeps that wander out of the map's shape."""
    q = np.asarray(frames, float).reshape(-1)
    out = np.zeros((len(q), 3))
    kf = np.asarray(kf_frames, float).reshape(-1)
    if len(kf) == 0 or len(q) == 0 or not sigma_frames > 0:
        return out
    order = np.argsort(kf)
    kf = kf[order]
    res = np.asarray(residuals, float).reshape(-1, 3)[order]
    w0 = np.asarray(weights, float).reshape(-1)[order]
    by_frame = np.argsort(q)
    for s in range(0, len(q), 256):  # in blocks of 256 frames, against the keyframes within 5 sigma of them
        qi = by_frame[s:s + 256]
        a, b = np.searchsorted(kf, [q[qi].min() - 5 * sigma_frames, q[qi].max() + 5 * sigma_frames], side="left")
        if a == b:
            continue
        d = (kf[None, a:b] - q[qi, None]) / sigma_frames
        w = np.exp(-0.5 * d * d) * w0[None, a:b]
        # a line through the residuals around each frame, not their mean: at the flight's ends, where the keyframes
        # lie on one side only, a mean would lag a drift that is still growing
        s0, s1, s2 = w.sum(1), (w * d).sum(1), (w * d * d).sum(1)
        t0, t1 = w @ res[a:b], (w * d) @ res[a:b]
        det = s0 * s2 - s1 * s1
        line = det > 1e-9 * np.maximum(s0 * s2, 1e-300)
        out[qi] = np.where(line[:, None], (s2[:, None] * t0 - s1[:, None] * t1) / np.where(line, det, 1.0)[:, None],
                           t0 / np.maximum(s0, 1e-300)[:, None])
    return out


@dataclass
class Pose:
    """A frame's camera in the association frame, with where it came from and how far it can be trusted."""

    frame: int
    R: np.ndarray  # association-frame-to-camera rotation
    t: np.ndarray
    source: str  # registered | tracked | interpolated | apples (ground.apples.landmarks) | telemetry
    sigma_m: float
    sigma_deg: float

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t


def line_noise(kf_frames: np.ndarray, frames: np.ndarray, sigma_frames: float) -> np.ndarray:
    """At each of ``frames``, the standard deviation of :func:`drift_offsets`' line through the keyframes (uniform
    weights) for unit noise on each residual: sqrt(sum of its weights squared), the weights of a local linear fit
    being w_j (s2 - s1 d_j) / (s0 s2 - s1^2)."""
    kf = np.sort(np.asarray(kf_frames, float).reshape(-1))
    at = np.asarray(frames, float).reshape(-1)
    out = np.full(len(at), np.inf)
    for s in range(0, len(at), 256):
        q = at[s:s + 256]
        a, b = np.searchsorted(kf, [q.min() - 5 * sigma_frames, q.max() + 5 * sigma_frames], side="left")
        d = (kf[None, a:b] - q[:, None]) / sigma_frames
        w = np.exp(-0.5 * d * d)
        s0, s1, s2 = w.sum(1), (w * d).sum(1), (w * d * d).sum(1)
        w0, w1, w2 = (w * w).sum(1), (w * w * d).sum(1), (w * w * d * d).sum(1)
        det = s0 * s2 - s1 * s1
        ok = det > 1e-12
        out[s:s + 256][ok] = (np.sqrt(np.maximum(s2 * s2 * w0 - 2 * s2 * s1 * w1 + s1 * s1 * w2, 0.0)) / det)[ok]
    return out


class AssociationFrame:
    """The frame the association works in: the model's coordinates taken through the first good georeferencing fit,
    then frozen (the frames in the association's window stay consistent while later fits move a little); ENU itself
    while there is no model. Reads the mapper's fit and registered keyframes (``model_pose``), and the frames'
    telemetry (frame -> KeyframeTelemetry) for the drift correction."""

    #: The drift correction applies once the map has drifted this many times the GPS's stated accuracy (the spread
    #: of the corrections along the flight): below, what it would follow is mostly the GPS error's own wander.
    DRIFT_MIN_GPS_SIGMAS = 4.0

    def __init__(self, mapper, telemetry: dict, camera=None, sigma_att_deg: float = 0.5):
        self.mapper = mapper
        self.tel = telemetry
        self.camera = camera  # its mount turns the gimbal's attitudes into the camera's (the bend correction)
        self.sigma_att = np.radians(sigma_att_deg)
        self.bend_deg = 0.0  # how far the map turns from the attitudes along the flight (deg), see bend
        self.bend_corrected = False
        self.frozen: Similarity | None = None  # model -> association frame (a fit frozen), or None
        self.assoc_from_enu: Similarity | None = None  # set when the association frame is ENU itself
        self.drift_m = 0.0  # how far the drift corrections spread along the flight (m), see correction
        self.drift_corrected = False
        self._key: tuple | None = None  # what the similarities below were composed from
        self._cached: tuple[Similarity | None, Similarity] = (None, IDENTITY)

    @property
    def fixed(self) -> bool:
        """Whether the association frame has been fixed (by a fit, or as ENU)."""
        return self.frozen is not None or self.assoc_from_enu is not None

    def fix(self) -> None:
        """Fix the association frame, once: the mapper's fit if there is one, else ENU."""
        if self.fixed:
            return
        fit = self.mapper.fit
        if fit is not None:
            self.frozen = fit
            log.info("association frame fixed by georeferencing %d registered keyframes (GPS residual %.2f m)",
                     len(self.mapper.model_pose), self.mapper.fit_residual_m)
        else:
            self.assoc_from_enu = IDENTITY
            log.warning("no registered model yet: the association runs on telemetry poses in ENU")

    def _similarities(self) -> tuple[Similarity | None, Similarity]:
        """(model -> association frame, None before a fit; association frame -> ENU), composed again only when the
        mapper's fit or the frame changed: every frame's pose and every table row reads them."""
        key = (self.mapper.fit, self.frozen, self.assoc_from_enu)
        if self._key is None or any(a is not b for a, b in zip(key, self._key)):
            fit, frozen, from_enu = key
            if frozen is not None:
                m2a, a2e = frozen, compose(fit, inverse(frozen))
            else:
                m2a = compose(from_enu, fit) if fit is not None and from_enu is not None else None
                a2e = inverse(from_enu) if from_enu is not None else IDENTITY
            self._key, self._cached = key, (m2a, a2e)
        return self._cached

    def model_to_assoc(self) -> Similarity | None:
        return self._similarities()[0]

    def assoc_to_enu(self) -> Similarity:
        return self._similarities()[1]

    def metres_per_unit(self) -> float:
        """The association frame's unit in metres, as the map's georeference knows it now: the frame was fixed by
        the first fit, from a few keyframes' GPS, and the later fits scale it (tens of percent with a DJI log's)."""
        return float(self.assoc_to_enu().scale)

    def to_enu(self, X: np.ndarray) -> np.ndarray:
        return self.assoc_to_enu().apply(np.asarray(X, float).reshape(-1, 3))

    def frame_pose(self, frame: int, own, between, tel, camera, sigma_att_deg: float) -> Pose | None:
        """The frame's pose in the association frame from the best source it has: its own model pose (R, t, source:
        registered or tracked), else one interpolated between the model poses of its nearest posed frames (``between``:
        a, (R, t) at a, b, (R, t) at b; rotation by slerp, centre linearly; carried on past them where the frame lies
        outside a..b: ``extrapolated``), else its telemetry (``tel``, a
        KeyframeTelemetry: GPS and gimbal, through ``camera``'s mount). The model's poses count once the model is
        georeferenced; the association frame is fixed at the first frame posed. None without a model pose or position
        telemetry."""
        self.fix()
        m2a, a2e = self._similarities()
        if m2a is not None and own is not None:
            R, t = georeference_poses(own[0][None], own[1][None], m2a)
            return Pose(frame, R[0], t[0], own[2], 0.01 if own[2] == "registered" else 0.015, 0.05)
        if m2a is not None and between is not None:
            a, pa, b, pb = between
            R2, t2 = georeference_poses(np.array([pa[0], pb[0]]), np.array([pa[1], pb[1]]), m2a)
            C = -np.einsum("nji,nj->ni", R2, t2)
            w = (frame - a) / (b - a)
            if 0.0 <= w <= 1.0:
                R = Slerp([0.0, 1.0], Rotation.from_matrix(R2))([w]).as_matrix()[0]
                c = (1 - w) * C[0] + w * C[1]
                return Pose(frame, R, -R @ c, "interpolated", 0.02, 0.1)
            # past a..b: carried on at their motion (turn and velocity), as uncertain as the step is long
            R = R2[0] @ Rotation.from_rotvec(w * Rotation.from_matrix(R2[0].T @ R2[1]).as_rotvec()).as_matrix()
            c = (1 - w) * C[0] + w * C[1]
            far = max(abs(w), abs(w - 1.0))
            return Pose(frame, R, -R @ c, "extrapolated", 0.02 * far, 0.1 * far)
        log.debug("frame %d: telemetry pose (model georeferenced: %s)", frame, m2a is not None)
        if tel is None or not np.isfinite(tel.enu).all():
            return None
        R_enu, t_enu = tel.camera_pose(camera)
        R, t = georeference_poses(R_enu[None], t_enu[None], inverse(a2e))
        return Pose(frame, R[0], t[0], "telemetry", tel.h_acc, sigma_att_deg)

    def correction(self, frames, sigma_frames: float) -> tuple[np.ndarray, np.ndarray]:
        """(ENU offsets (n, 3), ENU rotations (n, 3, 3)) at these frames, to apply to what :meth:`to_enu` gives: a
        camera's centre moves by the offset and its axes turn by the rotation; a point seen from it moves with it
        (turned about its centre). The map's turn taken back out (:meth:`_bend`), then its drift from the GPS
        (:meth:`_drift`)."""
        q = np.asarray(frames, float).reshape(-1)
        off, rot = np.zeros((len(q), 3)), np.broadcast_to(np.eye(3), (len(q), 3, 3)).copy()
        self.bend_corrected = self.drift_corrected = False
        S = self.mapper.fit
        if S is None or self.frozen is None or not sigma_frames > 0:
            return off, rot
        model_pose = self.mapper.model_pose
        kf = np.array(sorted(f for f in model_pose if f in self.tel), int)
        if len(kf) < 3:
            return off, rot
        R = np.array([model_pose[f][0] for f in kf]) @ S.R.T  # ENU-to-camera, as the map has them
        C = S.apply(-np.einsum("nji,nj->ni", np.array([model_pose[f][0] for f in kf]),
                               np.array([model_pose[f][1] for f in kf])))
        bent = self._bend(kf, R, C, q, sigma_frames)
        if bent is not None:
            (off_kf, _), (off, rot) = bent
            C = C + off_kf
        return off + self._drift(kf, C, q, sigma_frames), rot

    def _bend(self, kf, R, C, q, sigma_frames):
        """((offsets, rotations) at the keyframes, (offsets, rotations) at ``q``), or None where it does not apply.

        Incremental reconstruction along a long pass turns slowly (about 0.4 degrees at each end of a 184-m pass),
        and the map bends with it (0.25 m at the ends). The gimbal's tilt does not drift (gravity holds it): its
        disagreement with the map's cameras, fitted by a line around each frame (Gaussian, ``sigma_frames``), is the
        map's tilt there, known to the attitudes' accuracy over the keyframes the fit takes in. The turn about the
        vertical is left: a compass's heading wanders. Each stretch of the map is turned back by the share of that
        turn which stands out of its noise (a Wiener gain, 1 - noise²/turn², none where the turn is within its noise),
        and the path is laid again from the turned steps between keyframes; on keyframes whose heading the log knows.
        ``bend_deg``: the fitted turn's largest departure from its mean along the flight."""
        if self.camera is None:
            return None
        ok = np.array([np.isfinite(self.tel[f].q_gimbal).all() and self.tel[f].heading_known for f in kf])
        if ok.sum() < 10:
            return None
        kf_a, R_a = kf[ok], R[ok]
        R_tel = camera_rotations(np.array([self.tel[f].q_gimbal for f in kf_a]), self.camera)
        # the map's turn in ENU: G with R G^T = R_tel, as a rotation vector (a fraction of a degree). Its tilt only:
        # a gimbal's tilt is held to gravity, its heading to a compass that may wander as much as the map
        turn = Rotation.from_matrix(np.einsum("nji,njk->nik", R_tel, R_a)).as_rotvec() * [1.0, 1.0, 0.0]
        # the line, and its noise, on a grid an eighth of sigma apart (it bends on the scale of sigma), read between
        # its points: every map refresh computes it, and a 10-minute flight has thousands of keyframes
        grid = np.arange(kf_a[0], kf_a[-1] + sigma_frames / 8, max(sigma_frames / 8, 1.0))
        line = drift_offsets(kf_a, turn, np.ones(len(kf_a)), grid, sigma_frames)

        def at(frames):
            return np.column_stack([np.interp(frames, grid, line[:, i]) for i in range(3)])
        at_a = at(kf_a)
        mean = at_a.mean(0)  # a turn the whole flight shares is the mount's, or the similarity's: not the map's shape
        dev = np.linalg.norm(at_a - mean, axis=1)
        self.bend_deg = float(np.degrees(dev.max()))
        # each keyframe's fitted turn against its own noise (the attitudes' accuracy through the line's weights)
        noise = self.sigma_att * np.interp(kf_a, grid, line_noise(kf_a, grid, sigma_frames))
        # each stretch is turned back by the share of its fitted turn that stands out of the noise (a Wiener gain:
        # the turn's power over the turn's and the noise's), not all or nothing
        gain_a = np.clip(1.0 - (noise / np.maximum(dev, 1e-12)) ** 2, 0.0, 1.0)
        if not (gain_a > 0).any():
            return None
        self.bend_corrected = True

        def turn_at(frames):
            return (at(frames) - mean) * np.interp(frames, kf_a, gain_a)[:, None]
        G = Rotation.from_rotvec(turn_at(kf)).as_matrix()
        # the path laid again from its turned steps (each turned by its ends' mean turn), then put back where it was
        # on average: the similarity's placement stays
        steps = np.einsum("nij,nj->ni", 0.5 * (G[1:] + G[:-1]), np.diff(C, axis=0))
        off_kf = np.vstack([C[:1], C[0] + np.cumsum(steps, axis=0)]) - C
        off_kf -= off_kf.mean(0)
        off = np.column_stack([np.interp(q, kf, off_kf[:, i]) for i in range(3)])
        rot = Rotation.from_rotvec(turn_at(q)).as_matrix()
        return (off_kf, G), (off, rot)

    def _drift(self, kf, C, q, sigma_frames) -> np.ndarray:
        """ENU offsets (n, 3) at frames ``q``: where the GPS of the registered keyframes around them (Gaussian,
        ``sigma_frames``) disagrees with the map's camera centres ``C`` at keyframes ``kf`` (:func:`drift_offsets`).
        Zero while the corrections spread less than DRIFT_MIN_GPS_SIGMAS x the GPS accuracy along the flight
        (``drift_m``)."""
        ok = np.array([np.isfinite(self.tel[f].enu).all() for f in kf])
        if ok.sum() < 3:
            return np.zeros((len(q), 3))
        kf, C = kf[ok], C[ok]
        res = np.array([self.tel[f].enu for f in kf]) - C
        sigma = np.array([self.tel[f].h_acc for f in kf])
        w = 1.0 / sigma**2
        at_kf = drift_offsets(kf, res, w, kf, sigma_frames)
        self.drift_m = float(np.linalg.norm(at_kf - np.average(at_kf, axis=0, weights=w), axis=1).max())
        self.drift_corrected = self.drift_m >= self.DRIFT_MIN_GPS_SIGMAS * float(np.median(sigma))
        return drift_offsets(kf, res, w, q, sigma_frames) if self.drift_corrected else np.zeros((len(q), 3))


class FloorPlane(NamedTuple):
    normal: np.ndarray  # unit, pointing up (+z)
    point: np.ndarray  # a point of the plane
    sigma_m: float  # the floor samples' spread about it


#: The floor's samples: the low tenth of the map's points in each FLOOR_CELL_M square that holds FLOOR_CELL_POINTS.
FLOOR_CELL_M = 2.0
FLOOR_CELL_POINTS = 10
#: A floor sample within this of the plane is floor (the ground's roughness); the canopy stands 0.8 m and more above.
FLOOR_INLIER_M = 0.1


def floor_plane(points: np.ndarray, min_cells: int = 6) -> FloorPlane | None:
    """The orchard floor the map sees, as a plane: the low tenth of the points of each 2-m cell is a sample (the ground
    seen between the rows, or the canopy where a cell sees only that), and a RANSAC plane through the samples keeps the
    ground's (within FLOOR_INLIER_M; the canopy's lie a metre higher), refined by least squares. A plane, not one
    level: a map tilted a degree (a fixed mount's stated tilt against the gimbal's real one) puts the floor the cameras
    look at, metres across, a decimetre higher or lower, and the cameras' heights above it are what scale the map.
    None with fewer than ``min_cells`` samples, or fewer than half of them on the plane."""
    P = np.asarray(points, float).reshape(-1, 3)
    if len(P) < min_cells * FLOOR_CELL_POINTS:
        return None
    key = np.floor(P[:, :2] / FLOOR_CELL_M).astype(np.int64)
    _, cell, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    by_cell = np.split(P[np.argsort(cell.reshape(-1), kind="stable")], np.cumsum(count)[:-1])
    samples = np.array([[*c[:, :2].mean(0), np.percentile(c[:, 2], 10)] for c in by_cell
                        if len(c) >= FLOOR_CELL_POINTS]).reshape(-1, 3)
    if len(samples) < min_cells:
        return None
    rng = np.random.default_rng(0)  # the same plane each run
    best = np.zeros(len(samples), bool)
    for _ in range(200):
        a, b, c = samples[rng.choice(len(samples), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-9:
            continue
        n = n / np.linalg.norm(n)
        inl = np.abs((samples - a) @ n) < FLOOR_INLIER_M
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < max(3, len(samples) // 2):
        return None
    A = np.c_[samples[best, :2], np.ones(int(best.sum()))]
    coef = np.linalg.lstsq(A, samples[best, 2], rcond=None)[0]  # z = ax + by + c
    normal = np.array([-coef[0], -coef[1], 1.0])
    normal /= np.linalg.norm(normal)
    sigma = float(np.std(samples[best, 2] - A @ coef))
    return FloorPlane(normal, np.array([0.0, 0.0, coef[2]]), max(sigma, 0.02))
