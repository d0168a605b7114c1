"""Places seen again: which earlier keyframes look at the place a new keyframe looks at, and the similarity that
puts a sub-model onto their 3-D points.

A whole-plot flight sees each row from several passes, minutes apart. The chain of sub-models links the passes
only through the turns, and its drift (a few cm and a tenth of a degree per pass) is enough to make an apple seen
from two passes two apples. :class:`Places` indexes every registered keyframe by the point it looks at (the median
of its 3-D points, in the first sub-model's frame) and its optical axis, so that a new keyframe finds the earlier
keyframes of the same place, not only the last few; it keeps each finished sub-model's keypoint -> 3-D point
tables (anchors) on disk, so that memory stays flat over a long flight. :func:`robust_similarity` fits the
sub-model -> first-frame similarity over 3-D points matched through those keyframes.

    places = Places(workdir / "places")
    places.add(name, order, look, axis)                 # a keyframe just registered
    places.near(look, axis, depth, order)               # earlier keyframes of the same place, nearest first
    places.keep_anchors(k, {name: (point2D_idx, X_local)})   # a sub-model finished
    places.anchors(name)                                # (sub-model index, point2D_idx, X_local) or None
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pomar.align import Similarity, umeyama


class Places:
    def __init__(self, folder: str | Path | None, radius: float = 0.2, max_angle_deg: float = 40.0,
                 min_gap: int = 8, max_near: int = 2):
        """folder: where the anchors go (None: they stay in memory); radius: how far apart two keyframes' look points
        may be, as a share of the new one's viewing depth; min_gap: keyframes nearer than this in order are the recent
        chain's, already matched."""
        self.folder = Path(folder) if folder is not None else None
        self._in_memory: dict[int, dict] = {}  # sub-model -> its anchors' arrays, without a folder
        self.radius, self.cos_max, self.min_gap, self.max_near = radius, np.cos(np.radians(max_angle_deg)), min_gap, max_near
        self.names: list[str] = []
        self._row: dict[str, int] = {}
        self._order: list[int] = []
        self._look = np.zeros((0, 3))
        self._axis = np.zeros((0, 3))
        self._file: dict[str, tuple[int, Path | None]] = {}  # keyframe -> (its finished sub-model, its anchors' file)
        self._cache: tuple[Path, dict] | None = None

    def __contains__(self, name: str) -> bool:
        return name in self._row

    def add(self, name: str, order: int, look: np.ndarray, axis: np.ndarray) -> None:
        # a few thousand keyframes per flight: one row each, searched with one vectorised distance
        if name in self._row:
            return
        self._row[name] = len(self.names)
        self.names.append(name)
        self._order.append(order)
        self._look = np.vstack([self._look, np.asarray(look, float).reshape(1, 3)])
        self._axis = np.vstack([self._axis, np.asarray(axis, float).reshape(1, 3)])

    def near(self, look: np.ndarray, axis: np.ndarray, depth: float, order: int, min_gap: int | None = None) -> list[str]:
        """Earlier keyframes (at least ``min_gap`` before ``order``; default the index's) whose look point lies within
        radius * depth of ``look`` and whose axis is within max_angle of ``axis``: at most ``max_near``, nearest
        first."""
        if not self.names:
            return []
        d = np.linalg.norm(self._look - np.asarray(look, float), axis=1)
        ok = (d <= self.radius * depth) & (self._axis @ np.asarray(axis, float) >= self.cos_max)
        ok &= np.asarray(self._order) <= order - (self.min_gap if min_gap is None else min_gap)
        idx = np.nonzero(ok)[0]
        return [self.names[i] for i in idx[np.argsort(d[idx])][: self.max_near]]

    def keep_anchors(self, submodel: int, anchors: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """A finished sub-model's keyframes: their keypoint indices with a 3-D point, and the points (its frame)."""
        arrays = {}
        for name, (idx, X) in anchors.items():
            arrays[f"{name}.idx"] = np.asarray(idx, np.int32)
            arrays[f"{name}.X"] = np.asarray(X, np.float32)
        if self.folder is None:
            self._in_memory[submodel] = arrays
            path = None
        else:
            self.folder.mkdir(parents=True, exist_ok=True)
            path = self.folder / f"{submodel}.npz"
            np.savez(path, **arrays)
        for name in anchors:
            self._file[name] = (submodel, path)

    def anchors(self, name: str) -> tuple[int, np.ndarray, np.ndarray] | None:
        if name not in self._file:
            return None
        k, path = self._file[name]
        if path is None:
            z = self._in_memory[k]
        else:
            if self._cache is None or self._cache[0] != path:
                self._cache = (path, np.load(path))  # lazy: each keyframe's arrays are read when asked for
            z = self._cache[1]
        return k, z[f"{name}.idx"], z[f"{name}.X"].astype(float)


def robust_similarity(src: np.ndarray, dst: np.ndarray, tol: float, iterations: int = 300,
                      seed: int = 0) -> tuple[Similarity, np.ndarray] | None:
    """Similarity taking src (N, 3) onto dst, from 3-point samples (RANSAC, seeded: the same each run), refitted on
    the inliers (within ``tol``). None with fewer than 3 inliers."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    n = len(src)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    best = np.zeros(n, bool)
    for _ in range(iterations):
        s = rng.choice(n, 3, replace=False)
        try:
            S = umeyama(src[s], dst[s])
        except np.linalg.LinAlgError:
            continue
        inl = np.linalg.norm(S.apply(src) - dst, axis=1) < tol
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < 3:
        return None
    for _ in range(2):  # refit on the inliers, then take the inliers of the refit
        S = umeyama(src[best], dst[best])
        inl = np.linalg.norm(S.apply(src) - dst, axis=1) < tol
        if inl.sum() < 3:
            break
        best = inl
    return S, best
