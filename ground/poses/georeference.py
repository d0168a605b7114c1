"""Georeferencing a structure-from-motion model: the similarity from model coordinates to local ENU.

GPS positions alone cannot fix the roll about a straight flight line (the camera centres are nearly
collinear), so the fit also uses the camera orientation the telemetry gives (vehicle attitude x
gimbal x mount): each frame contributes its GPS position, weighted by 1/sigma_pos^2, and its three
camera axes in ENU, weighted by 1/sigma_att^2 (radians); a frame whose heading the log does not know (a fixed
mount on the track's heading) gives only which way is up, which a stabilised gimbal holds. The cost

    sum_i w_i |s R c_i + t - g_i|^2  +  sum_i,k v_i |R a_ik - b_ik|^2

is minimised exactly in t, and alternately in R (weighted Procrustes over positions and axes together)
and s (closed form), from a start on positions alone.

:class:`Pose` is a frame's camera in the map frame (ground.poses.map_frame, the first fit frozen); :func:`drift_offsets`
takes a long map's bends back to the GPS.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from pomar.align import Similarity


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
    """A frame's camera in the map frame, with where it came from and how far it can be trusted."""

    frame: int
    R: np.ndarray  # map-frame-to-camera rotation
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
    sigma = float(np.std(samples[best, 2] - A @ coef))
    # a cell's low tenth lies below its ground by about 1.3 times the points' roughness: the plane is then fitted
    # through the points themselves within FLOOR_INLIER_M of it (twice, the band following the plane), not their
    # percentiles, so that the cameras' heights above it are not that much too high
    for _ in range(2):
        near = np.abs(P[:, 2] - np.c_[P[:, :2], np.ones(len(P))] @ coef) < FLOOR_INLIER_M
        if near.sum() < 3 * FLOOR_CELL_POINTS:
            break
        coef = np.linalg.lstsq(np.c_[P[near, :2], np.ones(int(near.sum()))], P[near, 2], rcond=None)[0]
    normal = np.array([-coef[0], -coef[1], 1.0])
    normal /= np.linalg.norm(normal)
    return FloorPlane(normal, np.array([0.0, 0.0, coef[2]]), max(sigma, 0.02))
