"""Two apples that are one: their views triangulate to one point within tau_geom px (seen on two passes, or a
track split by missed detections), merged into one."""

from __future__ import annotations

import numpy as np

from ground.apples.association import Apple, AssociationParams
from ground.apples.geometry import reprojection_errors, triangulate, triangulate_nonlinear

_SAMPLE_CACHE: dict[tuple[int, int], np.ndarray] = {}


def sample_index(length: int, n: int) -> np.ndarray:
    """At most ``n`` indices of ``length`` items, first, last and evenly between."""
    key = (length, n)
    if key not in _SAMPLE_CACHE:
        _SAMPLE_CACHE[key] = np.unique(np.linspace(0, length - 1, min(length, n)).round().astype(int))
    return _SAMPLE_CACHE[key]


MERGE_VIEWS = 16  # views an apple keeps to test merges


def sample_views(Ps: np.ndarray, xs: np.ndarray, frames) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """At most MERGE_VIEWS of an apple's views (first, last, evenly between): (matrices, pixels), and their frames."""
    sel = sample_index(len(xs), MERGE_VIEWS)
    return (Ps[sel], xs[sel]), np.asarray(frames)[sel]


def joint_point(a: Apple, b: Apple) -> np.ndarray | None:
    """The point both apples' views triangulate to (None without views, or if it does not converge)."""
    if a.views is None or b.views is None:
        return None
    X = triangulate_nonlinear(np.concatenate([a.views[0], b.views[0]]), np.concatenate([a.views[1], b.views[1]]))
    return X if np.isfinite(X).all() else None


def same_apple(a: Apple, b: Apple, tau_geom: float, min_inlier_ratio: float = 0.8,
               max_median_px: float | None = None) -> np.ndarray | None:
    """The point both apples' views triangulate to, if it reprojects within tau_geom in at least
    min_inlier_ratio of each apple's views (a few views of a long track fall outside by noise), and, with
    ``max_median_px``, within that in the median of each apple's views."""
    X = joint_point(a, b)
    if X is None:
        return None
    Ps = np.concatenate([a.views[0], b.views[0]])
    xs = np.concatenate([a.views[1], b.views[1]])
    err = reprojection_errors(Ps, xs, X)
    inl = err < tau_geom
    na = len(a.views[1])
    if inl[:na].mean() < min_inlier_ratio or inl[na:].mean() < min_inlier_ratio:
        return None
    if max_median_px is not None and max(np.median(err[:na]), np.median(err[na:])) > max_median_px:
        return None
    return X


def merge_into(a: Apple, b: Apple, X: np.ndarray | None = None) -> None:
    """Fold apple b into apple a (the same physical apple)."""
    na, nb = a.n_observations, b.n_observations
    a.X = X if X is not None else (a.X * na + b.X * nb) / (na + nb)
    a.reprojection_error = (a.reprojection_error * na + b.reprojection_error * nb) / (na + nb)
    a.observations = sorted(set(a.observations) | set(b.observations))
    a.first_frame, a.last_frame = min(a.first_frame, b.first_frame), max(a.last_frame, b.last_frame)
    if a.views is not None and b.views is not None:
        both = a.view_frames is not None and b.view_frames is not None
        frames = np.concatenate([a.view_frames, b.view_frames]) if both else np.zeros(len(a.views[1]) + len(b.views[1]))
        a.views, frames = sample_views(np.concatenate([a.views[0], b.views[0]]),
                                       np.concatenate([a.views[1], b.views[1]]), frames)
        a.view_frames = frames if both else None


def find_duplicate(apple: Apple, candidates: list[Apple], params: "AssociationParams", strict: bool = False,
                   metres_per_unit: float = 1.0):
    """The candidate that apple duplicates, and their joint position (None: their mean): within merge_m, or within
    merge_search_m and consistent (their views triangulate together within tau_geom; ``strict``: also within
    tau_geom / 2 in the median of each one's views, to a point within max_merge_shift_m of the better-seen one, for
    apples from another pass, which only their views can tell from a neighbour a few cm away). The points are in
    units of ``metres_per_unit`` metres; the distances in params are metres."""
    if not candidates:
        return None, None
    C = np.array([c.X for c in candidates])
    d = np.linalg.norm(C - apple.X, axis=1) * metres_per_unit
    for i in np.argsort(d)[:4]:
        if d[i] > params.merge_search_m:
            break
        c = candidates[i]
        if d[i] < params.merge_m:
            return c, joint_point(c, apple)
        if apple.views is not None and c.views is not None:
            X = same_apple(c, apple, params.tau_geom, max_median_px=params.tau_geom / 2 if strict else None)
            if X is not None and strict and params.max_merge_shift_m > 0:
                better = c if c.n_observations >= apple.n_observations else apple
                if np.linalg.norm(X - better.X) * metres_per_unit > params.max_merge_shift_m:
                    continue
            if X is not None:
                return c, X
    return None, None


def merge_duplicates(apples: list[Apple], params: "AssociationParams") -> list[Apple]:
    """Merge apples that are one apple seen twice (in order, each into an earlier kept apple)."""
    if params.merge_search_m <= 0 or not apples:
        return apples
    from scipy.spatial import cKDTree

    kept: list[Apple] = []
    tree = cKDTree(np.array([a.X for a in apples]))
    alive = np.ones(len(apples), bool)
    for i, a in enumerate(apples):
        near = [j for j in tree.query_ball_point(a.X, params.merge_search_m) if j < i and alive[j]]
        target, X = find_duplicate(a, [apples[j] for j in near], params)
        if target is None:
            kept.append(a)
        else:
            merge_into(target, a, X)
            alive[i] = False
    for i, a in enumerate(kept):
        a.id = i
    return kept
