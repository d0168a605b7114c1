"""Two- and multi-view geometry for the association (Hartley & Zisserman), vectorised with numpy.

Projection matrices map world points to pixels in the project's detection convention (OpenCV:
top-left pixel centre at (0, 0)); build them with :meth:`pomar.camera.Camera.projection_matrix`.
"""

from __future__ import annotations

import numpy as np


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x, the cross-product matrix of a 3-vector."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def camera_centre(P: np.ndarray) -> np.ndarray:
    """Homogeneous centre C (4,) with P C = 0 (the right null vector of P)."""
    _, _, vt = np.linalg.svd(P)
    c = vt[-1]
    return c / c[3] if abs(c[3]) > 1e-12 else c


def fundamental_from_projections(P_i: np.ndarray, P_j: np.ndarray) -> np.ndarray:
    """F_ij = [e_j]x P_j P_i^+ with e_j = P_j C_i: maps a point of frame i to its epipolar line in frame j."""
    e_j = P_j @ camera_centre(P_i)
    F = skew(e_j) @ P_j @ np.linalg.pinv(P_i)
    return F / np.linalg.norm(F)


def homogeneous(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, float)
    return np.concatenate([x, np.ones(x.shape[:-1] + (1,))], axis=-1)


def epipolar_distances(F: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """(N, M) pixel distances of the M points x_j to the epipolar lines F x_i of the N points x_i."""
    lines = homogeneous(x_i) @ F.T  # (N, 3): l = F x
    norm = np.hypot(lines[:, 0], lines[:, 1])
    num = lines @ homogeneous(x_j).T  # (N, M)
    return np.abs(num) / np.maximum(norm, 1e-300)[:, None]


def triangulate(Ps: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Linear least-squares triangulation from n >= 2 views, batched.

    Ps: (..., n, 3, 4) projection matrices; xs: (..., n, 2) pixels. Returns (..., 3) points.
    Each view gives the rows x P3 - P1 and y P3 - P2 (Hartley & Sturm's linear method), normalised
    to unit length; the solution is the singular vector of the smallest singular value. The world is
    first moved to the first view's camera centre: the algebraic error depends on the coordinates,
    and with the origin tens of metres away the depth of a point seen over a short baseline is
    biased (on the bundled flight, 0.11 m median error for apples seen in 5-9 frames against 0.04 m).
    """
    Ps, xs = np.asarray(Ps, float), np.asarray(xs, float)
    c = _first_centre(Ps)
    A = triangulation_rows(Ps, xs, c[..., None, :])  # (..., n, 2, 4)
    A = A.reshape(A.shape[:-3] + (-1, 4))  # (..., 2n, 4)
    # only V is needed: the full U, 2n x 2n, cost 20x the rest for a track of 80 views (one view: V's last row needs
    # the full decomposition, 2 rows for 4 unknowns)
    _, _, vt = np.linalg.svd(A, full_matrices=A.shape[-2] < 4)
    X = vt[..., -1, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        return X[..., :3] / X[..., 3:4] + c


def triangulation_rows(Ps: np.ndarray, xs: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """The two rows (x P3 - P1, y P3 - P2) each view (..., 3, 4) with pixel (..., 2) gives for the
    homogeneous point [X - origin; 1], unit length: (..., 2, 4). origin (..., 3) broadcasts."""
    rows = np.stack([xs[..., 0:1] * Ps[..., 2, :] - Ps[..., 0, :], xs[..., 1:2] * Ps[..., 2, :] - Ps[..., 1, :]], axis=-2)
    rows[..., 3] += np.einsum("...ri,...i->...r", rows[..., :3], np.asarray(origin, float))
    return rows / np.linalg.norm(rows, axis=-1, keepdims=True)


def _first_centre(Ps: np.ndarray) -> np.ndarray:
    """Camera centre (..., 3) of the first view of Ps (..., n, 3, 4); zeros for a camera at infinity."""
    try:
        return -np.linalg.solve(Ps[..., 0, :, :3], Ps[..., 0, :, 3:4])[..., 0]
    except np.linalg.LinAlgError:
        return np.zeros(Ps.shape[:-3] + (3,))


def project(Ps: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project points X (..., 3) with Ps (..., 3, 4): pixels (..., 2) and depths (...,)."""
    xh = np.einsum("...ij,...j->...i", Ps, homogeneous(X))
    with np.errstate(divide="ignore", invalid="ignore"):
        return xh[..., :2] / xh[..., 2:3], xh[..., 2]


def reprojection_errors(Ps: np.ndarray, xs: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Pixel distance between xs (..., n, 2) and the projections of X (..., 3) by Ps (..., n, 3, 4).

    Points behind a camera get an infinite error.
    """
    uv, depth = project(Ps, np.asarray(X)[..., None, :])
    err = np.linalg.norm(uv - xs, axis=-1)
    return np.where(depth > 0, err, np.inf)


def triangulate_nonlinear(Ps: np.ndarray, xs: np.ndarray, X0: np.ndarray | None = None) -> np.ndarray:
    """The point minimising the reprojection error over n >= 2 views (Levenberg-Marquardt from the
    linear solution, or from X0). Ps: (n, 3, 4), xs: (n, 2); returns (3,).

    The linear method minimises an algebraic error, not the pixel error; over the short baselines
    of a track seen in a few consecutive frames the two differ in depth (a perfect association of
    the bundled flight's jittered detections scores F1 0.915 triangulated linearly, 0.926 with this).
    """
    from scipy.optimize import least_squares

    Ps, xs = np.asarray(Ps, float), np.asarray(xs, float)
    X0 = triangulate(Ps, xs) if X0 is None else np.asarray(X0, float)
    if not np.isfinite(X0).all() or len(xs) < 2:
        return X0
    A, b = Ps[:, :, :3], Ps[:, :, 3]

    def residuals(X):
        h = A @ X + b
        return (h[:, :2] / h[:, 2:3] - xs).ravel()

    def jacobian(X):
        h = A @ X + b
        w = h[:, 2, None, None]
        return ((A[:, :2, :] * w - A[:, 2, None, :] * h[:, :2, None]) / w**2).reshape(-1, 3)

    if np.any((A @ X0 + b)[:, 2] <= 0):  # behind a camera: the linear solution stays
        return X0
    res = least_squares(residuals, X0, jac=jacobian, method="lm", xtol=1e-10, max_nfev=50)
    return res.x if np.isfinite(res.x).all() else X0
