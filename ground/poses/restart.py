"""Placing a restarted mapper's model in the frame of the map it replaces.

A mapping process that died is started again and first given the last keyframes its predecessor was sent; its new
model is built from them, in a frame of its own. The keyframes both models placed give the similarity from the new
frame to the old: the rotation from their camera orientations (well posed even on a straight flight, where the
centres alone lie on a line and leave a roll about it free), then the scale and offset from their centres. Everything
the new process sends (poses, reference, points, georeference) is then moved into the old frame, so that tracking,
the association and the outputs see one map.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ground.poses.tracking import Reference
from pomar.align import Similarity

#: Keyframes placed by both models, at least, before the new one is placed in the old one's frame.
MIN_COMMON = 3


def centre(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return -R.T @ t


def align_models(old: dict[int, tuple], new: dict[int, tuple]) -> tuple[Similarity, dict] | None:
    """The similarity taking the new model's frame onto the old one's, from the keyframes both placed ((R, t)
    world-to-camera each), with its residuals; None while fewer than MIN_COMMON are shared or their centres
    coincide."""
    common = sorted(set(old) & set(new))
    if len(common) < MIN_COMMON:
        return None
    # R_old = R_new @ S.R^T for each keyframe: S.R is the rotation nearest to the mean of R_old^T @ R_new
    M = sum(old[f][0].T @ new[f][0] for f in common)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    c_old = np.array([centre(*old[f]) for f in common])
    y = np.array([R @ centre(*new[f]) for f in common])
    dy, dc = y - y.mean(0), c_old - c_old.mean(0)
    spread = float((dy ** 2).sum())
    if spread <= 1e-12:
        return None
    s = float((dy * dc).sum() / spread)
    if s <= 0:
        return None
    S = Similarity(s, R, c_old.mean(0) - s * y.mean(0))
    residual = np.linalg.norm(S.apply(np.array([centre(*new[f]) for f in common])) - c_old, axis=1)
    angles = [np.degrees(np.arccos(np.clip((np.trace(old[f][0] @ (new[f][0] @ R.T).T) - 1) / 2, -1, 1)))
              for f in common]
    extent = float(np.linalg.norm(c_old.max(0) - c_old.min(0)))
    return S, {"keyframes": len(common), "centre_residual_max": float(residual.max()),
               "rotation_residual_max_deg": float(max(angles)), "extent": extent}


def move_pose(S: Similarity, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A world-to-camera pose of the new frame, in the old frame (the camera's frame scaled with the world)."""
    R2 = R @ S.R.T
    return R2, S.scale * t - R2 @ S.t


def move_reference(S: Similarity, ref: Reference | None) -> Reference | None:
    if ref is None:
        return None
    R, t = move_pose(S, ref.R, ref.t)
    return replace(ref, X=S.apply(ref.X), R=R, t=t)
