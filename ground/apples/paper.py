"""The paper's association, offline (Santos & Gebler 2021, Algorithms 1 and 2): an epipolar graph over all
detections, one vertex each (edge i -> j when j is in the next k frames and lies within tau_epipolar of the epipolar
line), then for each vertex in frame order a DFS to all paths, RANSAC triangulation of each path
(:mod:`ground.apples.ransac`), the path with the best inlier ratio (longest first) becomes an apple, its edges are
removed, its vertices kept. DFS is bounded by ``max_paths`` per vertex (the number of paths grows exponentially with
track length and k); how often the bound binds is reported in :attr:`FruitAssociation.stats`."""

from __future__ import annotations

import numpy as np

from ground.apples.association import Apple, AssociationParams, FrameDetections
from ground.apples.geometry import epipolar_distances, fundamental_from_projections
from ground.apples.merging import merge_duplicates, sample_views
from ground.apples.ransac import polish, ransac_paths


def _stack_frames(frames: list[FrameDetections]):
    counts = [len(f.xy) for f in frames]
    vertex_frame = np.repeat(np.arange(len(frames)), counts)
    vertex_det = np.concatenate([np.arange(c) for c in counts]) if counts else np.zeros(0, int)
    xs = np.concatenate([f.xy for f in frames]) if counts else np.zeros((0, 2))
    Ps = np.stack([f.P for f in frames])[vertex_frame] if len(vertex_frame) else np.zeros((0, 3, 4))
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return vertex_frame, vertex_det, xs, Ps, offsets


class FruitAssociation:
    """Faithful offline association (Algorithms 1 and 2 of the paper)."""

    def __init__(self, params: AssociationParams | None = None):
        self.params = params or AssociationParams()
        self.stats: dict = {}

    def build_graph(self, frames: list[FrameDetections], offsets: np.ndarray) -> list[dict[int, float]]:
        """Adjacency: for each vertex, its successors and their epipolar distances (px)."""
        p = self.params
        n = int(offsets[-1])
        adj: list[dict[int, float]] = [{} for _ in range(n)]
        edges = 0
        for i, fi in enumerate(frames):
            if len(fi.xy) == 0:
                continue
            for j in range(i + 1, min(i + p.k, len(frames) - 1) + 1):
                fj = frames[j]
                if len(fj.xy) == 0:
                    continue
                D = epipolar_distances(fundamental_from_projections(fi.P, fj.P), fi.xy, fj.xy)
                a, b = np.nonzero(D <= p.tau_epipolar)
                for u, w, d in zip((a + offsets[i]).tolist(), (b + offsets[j]).tolist(), D[a, b].tolist()):
                    adj[u][w] = d
                edges += len(a)
        self.stats["edges"] = edges
        return adj

    def dfs_paths(self, adj: list[dict[int, float]], v: int, vertex_frame: np.ndarray) -> tuple[list[list[int]], bool]:
        """All maximal paths from v, stopping at max_paths. Best first: successors in the nearest frame
        first, then nearest their epipolar line, so that a bound keeps the most plausible paths.
        Returns the paths and whether the bound was hit."""

        def successors(u):
            return iter(sorted(adj[u], key=lambda w: (vertex_frame[w], adj[u][w])))

        paths: list[list[int]] = []
        stack = [successors(v)]
        path = [v]
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                stack.pop()
                path.pop()
                continue
            path.append(nxt)
            if adj[nxt]:
                stack.append(successors(nxt))
            else:
                paths.append(list(path))
                path.pop()
                if len(paths) >= self.params.max_paths:
                    return paths, True
        return paths, False

    def run(self, frames: list[FrameDetections]) -> list[Apple]:
        p = self.params
        rng = np.random.default_rng(p.seed)
        vertex_frame, vertex_det, xs, Ps, offsets = _stack_frames(frames)
        adj = self.build_graph(frames, offsets)
        apples: list[Apple] = []
        bound_hits = vertices_with_paths = 0
        for v in range(len(xs)):  # vertices in frame order
            if not adj[v]:
                continue
            paths, hit = self.dfs_paths(adj, v, vertex_frame)
            paths = [q for q in paths if len(q) >= max(3, p.min_inliers)]
            if not paths:
                continue
            vertices_with_paths += 1
            bound_hits += hit
            paths.sort(key=len, reverse=True)  # longest first; ties keep the earlier (longer) path
            best, best_r = None, 0.0
            for q, res in zip(paths, ransac_paths(Ps, xs, paths, p, rng)):
                if res is None:
                    continue
                r = res[1].sum() / len(q)
                if r > best_r:
                    best, best_r = (q, res), r
            if best is None:
                continue
            q, (X, inl, err) = best
            if p.nonlinear:
                X, inl, err = polish(Ps[q], xs[q], X, inl, p.tau_geom, p.min_inliers)
            inliers = [q[i] for i in np.nonzero(inl)[0]]
            inset = set(inliers)
            for u in inliers:
                for w in inset.intersection(adj[u]):
                    del adj[u][w]
            obs = [frames[vertex_frame[u]].detection(int(vertex_det[u])) for u in inliers]
            views, frames_ = sample_views(Ps[inliers], xs[inliers], [o.frame for o in obs])
            apples.append(Apple(len(apples), X, obs, err, views=views, view_frames=frames_))
        n_found = len(apples)
        apples = merge_duplicates(apples, p)
        self.stats.update(vertices=len(xs), vertices_with_paths=vertices_with_paths, dfs_bound_hits=bound_hits,
                          dfs_bound_hit_rate=bound_hits / max(vertices_with_paths, 1), apples=len(apples),
                          merged=n_found - len(apples))
        return apples
