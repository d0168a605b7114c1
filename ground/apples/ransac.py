"""A path of detections scored as one apple: RANSAC triangulation (3 random views per iteration, inliers within
tau_geom px), then the inliers refined and polished (the paper's path score)."""

from __future__ import annotations

import numpy as np

from ground.apples.association import AssociationParams
from ground.apples.geometry import reprojection_errors, triangulate, triangulate_nonlinear


def _sample_triples(rng: np.random.Generator, lengths: np.ndarray, n: int) -> np.ndarray:
    """(len(lengths), n, 3) distinct indices in [0, L) for each length L >= 3, vectorised."""
    L = lengths[:, None].astype(np.int64)
    r = rng.random((len(lengths), n, 3))
    a = np.floor(r[..., 0] * L).astype(np.int64)
    b = np.floor(r[..., 1] * (L - 1)).astype(np.int64)
    b += b >= a
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    c = np.floor(r[..., 2] * (L - 2)).astype(np.int64)
    c += c >= lo
    c += c >= hi
    return np.stack([a, b, c], axis=-1)


def refine(Ps: np.ndarray, xs: np.ndarray, inliers: np.ndarray, tau_geom: float, min_inliers: int):
    """Least-squares X from the inliers, then the inliers of that X; None if fewer than min_inliers."""
    if inliers.sum() < max(2, min_inliers):
        return None
    X = triangulate(Ps[inliers], xs[inliers])
    err = reprojection_errors(Ps, xs, X)
    inl = err < tau_geom
    if inl.sum() < max(2, min_inliers):
        return None
    X = triangulate(Ps[inl], xs[inl])
    err = reprojection_errors(Ps, xs, X)
    inl = err < tau_geom
    if inl.sum() < max(2, min_inliers) or not np.isfinite(X).all():
        return None
    return X, inl, float(err[inl].mean())


def polish(Ps: np.ndarray, xs: np.ndarray, X: np.ndarray, inl: np.ndarray, tau_geom: float, min_inliers: int):
    """The apple's final (X, inliers, mean error): X minimising the reprojection error over the inliers,
    then the inliers of that X (once more if they changed); the linear result where that leaves too few."""
    X1 = triangulate_nonlinear(Ps[inl], xs[inl], X)
    for _ in range(2):
        err = reprojection_errors(Ps, xs, X1)
        inl1 = err < tau_geom
        if inl1.sum() < max(2, min_inliers):
            err = reprojection_errors(Ps, xs, X)
            return X, inl, float(err[inl].mean())
        if (inl1 == inl).all():
            break
        inl = inl1
        X1 = triangulate_nonlinear(Ps[inl], xs[inl], X1)
    err = reprojection_errors(Ps, xs, X1)
    return X1, inl, float(err[inl].mean())


def ransac_paths(Ps: np.ndarray, xs: np.ndarray, paths: list[list[int]], params: AssociationParams,
                 rng: np.random.Generator):
    """TriangulationRANSAC on a batch of paths (lists of node ids). Returns per path (X, inlier mask, err) or None."""
    lengths = np.array([len(p) for p in paths])
    Lmax = lengths.max()
    idx = np.zeros((len(paths), Lmax), np.int64)
    valid = np.arange(Lmax)[None, :] < lengths[:, None]
    for i, p in enumerate(paths):
        idx[i, : len(p)] = p
    tri = _sample_triples(rng, lengths, params.ransac_iterations)  # (B, n, 3) positions in path
    nodes = np.take_along_axis(idx[:, None, :], tri, axis=2)  # (B, n, 3)
    X = triangulate(Ps[nodes], xs[nodes])  # (B, n, 3)
    err = reprojection_errors(Ps[idx][:, None], xs[idx][:, None], X)  # (B, n, Lmax)
    inl = (err < params.tau_geom) & valid[:, None, :]
    best = inl.sum(-1).argmax(-1)  # first best iteration
    out = []
    for i, p in enumerate(paths):
        res = refine(Ps[p], xs[p], inl[i, best[i], : len(p)], params.tau_geom, params.min_inliers)
        out.append(res)
    return out
