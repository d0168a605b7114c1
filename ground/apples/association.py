"""The paper's association (Santos & Gebler 2021, Section 2.1.3): detections + camera matrices -> apples in 3-D.

Two implementations over the same geometry:

* :class:`FruitAssociation` — faithful offline version of Algorithms 1 and 2: an epipolar graph over
  all detections (edge i -> j when j is in the next k frames and lies within tau_epipolar of the
  epipolar line), then for each node in frame order a DFS to all paths, RANSAC triangulation of
  each path (3 random nodes per iteration, inliers within tau_geom), the path with the best inlier
  ratio (longest first) becomes an apple, its edges are removed, its nodes kept. DFS is bounded by
  ``max_paths`` per node (the number of paths grows exponentially with track length and k); how
  often the bound binds is reported in :attr:`FruitAssociation.stats`.

* :class:`WindowedAssociation` — streaming version fed one frame at a time. Each open track is a
  path of the graph grown frame by frame: a young track extends along the epipolar line of its
  last node (within tau_epipolar, branching into every candidate, at most ``max_branches`` per
  root), a track with a 3-D estimate extends to the detection nearest its reprojection (within
  tau_geom). Tracks not extended for k frames can no longer grow and are closed: their inliers
  are re-estimated and, with at least ``min_inliers``, emitted as an apple. Time per frame and
  memory depend on the open tracks only, not on the flight's length.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from ground.apples.geometry import (camera_centre, epipolar_distances, fundamental_from_projections, reprojection_errors, skew,
                             triangulate, triangulate_nonlinear, triangulation_rows)

log = logging.getLogger(__name__)


@dataclass
class AssociationParams:
    k: int = 5  # frames ahead linked in the graph (tolerates k-1 missed detections)
    tau_epipolar: float = 4.0  # px, point-to-epipolar-line gate
    tau_geom: float = 3.0  # px, RANSAC inlier reprojection threshold
    ransac_iterations: int = 50  # RANSAC hypotheses tried per track
    min_inliers: int = 3  # views an apple needs (inliers of its RANSAC triangulation)
    max_paths: int = 500  # offline DFS bound per node
    max_branches: int = 8  # windowed: young hypotheses kept per root detection
    #: One apple seen twice (hidden for more than k frames, then seen again) gives two estimates.
    #: They are merged when their views triangulate together within tau_geom and the estimates are
    #: within merge_search_m (short tracks are uncertain in depth); 0 = off (the paper as is).
    merge_search_m: float = 1.0
    #: Estimates closer than this are one apple, whatever their views say: two apples' centres are at least the sum
    #: of their radii (>= 6 cm) apart, and this is half that. It catches one apple seen from both sides of its row,
    #: whose two caps' centres the views' test can keep apart.
    merge_m: float = 0.03
    #: Windowed: how long (frames) an emitted apple stays a candidate for such a merge.
    merge_window: int = 600
    #: Windowed: every apple of the map stays a candidate (found through a spatial index, so the cost stays flat
    #: as the map grows): an apple seen again from a later pass, minutes after, merges into the first estimate.
    #: False = only apples of the last merge_window frames (one pass's worth).
    cross_pass: bool = True
    #: An apple from another pass (beyond merge_window), or one merging after a pose correction, merges only if the
    #: joint point stays within this of the better-seen of the two (more observations): one apple's two estimates
    #: differ by a cap's offset (at most its radius) and the poses' disagreement (a few cm), while a glimpse of a
    #: neighbour along the other apple's rays can triangulate with its views by pulling it 10 cm or more along them.
    #: 0 = off. Not applied to the other merges within merge_window, where it refused true ones (docs/benchmarks.md).
    max_merge_shift_m: float = 0.08
    #: An apple's final position minimises the reprojection error over its inliers (the linear
    #: solution's depth is biased over the short baselines of a few frames); False = linear only.
    nonlinear: bool = True
    seed: int = 0


@dataclass(frozen=True, order=True)
class Detection:
    """One detection, as an apple keeps it (norfair's ``Detection``): the association frame it was seen in, its
    index there, and the detector's box (xyxy, px; NaN where only the centre is known) and score. Two detections are
    the same when frame and index are."""

    frame: int
    index: int
    box: tuple = field(default=(np.nan,) * 4, compare=False, repr=False)
    score: float = field(default=float("nan"), compare=False)


@dataclass
class FrameDetections:
    """One frame fed to the association: its index (the association counts frames in the order they come), 3x4
    camera matrix, detection centres (N, 2), and the detector's boxes (N, 4) and scores (N,) where known."""

    frame: int
    P: np.ndarray
    xy: np.ndarray
    boxes: np.ndarray | None = None
    scores: np.ndarray | None = None

    def __post_init__(self):
        self.P = np.asarray(self.P, float)
        if self.P.shape != (3, 4) or not np.isfinite(self.P).all():
            raise ValueError(f"frame {self.frame}: P must be a finite 3x4 matrix, got shape {self.P.shape}")
        xy = np.asarray(self.xy, float)
        if xy.size and (xy.ndim != 2 or xy.shape[1] != 2):
            raise ValueError(f"frame {self.frame}: detections must be (N, 2) centres, got shape {xy.shape}")
        self.xy = xy.reshape(-1, 2)
        n = len(self.xy)
        self.boxes = np.full((n, 4), np.nan) if self.boxes is None else np.asarray(self.boxes, float).reshape(n, 4)
        self.scores = np.full(n, np.nan) if self.scores is None else np.asarray(self.scores, float).reshape(n)
        self._records: list[Detection] | None = None

    def detection(self, i: int) -> Detection:
        """The i-th detection's record (made once per frame, shared by every track that takes it)."""
        if self._records is None:
            self._records = [Detection(self.frame, k, tuple(map(float, b)), float(s))
                             for k, (b, s) in enumerate(zip(self.boxes, self.scores))]
        return self._records[i]


@dataclass
class Apple:
    """One apple found: 3-D position (world frame of the P_i) and the detections it was seen as."""

    id: int
    X: np.ndarray
    observations: list[Detection]  # the inliers, in frame order
    reprojection_error: float  # mean over inliers, px
    #: Views kept to test a merge: (V, 3, 4) camera matrices and (V, 2) pixels, a sample of the inliers.
    views: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    #: The frames of those views (V,): how a view's camera matrix is found again when the frame's pose is corrected.
    view_frames: np.ndarray | None = field(default=None, repr=False)
    first_frame: int = field(init=False)
    last_frame: int = field(init=False)

    def __post_init__(self):
        frames = [o.frame for o in self.observations]
        self.first_frame, self.last_frame = min(frames), max(frames)

    @property
    def n_observations(self) -> int:
        return len(self.observations)


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


def _stack_frames(frames: list[FrameDetections]):
    counts = [len(f.xy) for f in frames]
    node_frame = np.repeat(np.arange(len(frames)), counts)
    node_det = np.concatenate([np.arange(c) for c in counts]) if counts else np.zeros(0, int)
    xs = np.concatenate([f.xy for f in frames]) if counts else np.zeros((0, 2))
    Ps = np.stack([f.P for f in frames])[node_frame] if len(node_frame) else np.zeros((0, 3, 4))
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return node_frame, node_det, xs, Ps, offsets


class FruitAssociation:
    """Faithful offline association (Algorithms 1 and 2 of the paper)."""

    def __init__(self, params: AssociationParams | None = None):
        self.params = params or AssociationParams()
        self.stats: dict = {}

    def build_graph(self, frames: list[FrameDetections], offsets: np.ndarray) -> list[dict[int, float]]:
        """Adjacency: for each node, its successors and their epipolar distances (px)."""
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

    def dfs_paths(self, adj: list[dict[int, float]], v: int, node_frame: np.ndarray) -> tuple[list[list[int]], bool]:
        """All maximal paths from v, stopping at max_paths. Best first: successors in the nearest frame
        first, then nearest their epipolar line, so that a bound keeps the most plausible paths.
        Returns the paths and whether the bound was hit."""

        def successors(u):
            return iter(sorted(adj[u], key=lambda w: (node_frame[w], adj[u][w])))

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
        node_frame, node_det, xs, Ps, offsets = _stack_frames(frames)
        adj = self.build_graph(frames, offsets)
        apples: list[Apple] = []
        bound_hits = nodes_with_paths = 0
        for v in range(len(xs)):  # nodes in frame order
            if not adj[v]:
                continue
            paths, hit = self.dfs_paths(adj, v, node_frame)
            paths = [q for q in paths if len(q) >= max(3, p.min_inliers)]
            if not paths:
                continue
            nodes_with_paths += 1
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
            obs = [frames[node_frame[u]].detection(int(node_det[u])) for u in inliers]
            views, frames_ = sample_views(Ps[inliers], xs[inliers], [o.frame for o in obs])
            apples.append(Apple(len(apples), X, obs, err, views=views, view_frames=frames_))
        n_found = len(apples)
        apples = merge_duplicates(apples, p)
        self.stats.update(nodes=len(xs), nodes_with_paths=nodes_with_paths, dfs_bound_hits=bound_hits,
                          dfs_bound_hit_rate=bound_hits / max(nodes_with_paths, 1), apples=len(apples),
                          merged=n_found - len(apples))
        return apples


MERGE_VIEWS = 16  # views an apple keeps to test merges


def sample_views(Ps: np.ndarray, xs: np.ndarray, frames) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """At most MERGE_VIEWS of an apple's views (first, last, evenly between): (matrices, pixels), and their frames."""
    sel = _sample_index(len(xs), MERGE_VIEWS)
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


class SpatialIndex:
    """Apples by grid cell (``cell_m`` = the merge search radius): the apples near a point, from the 27 cells around
    it, in time independent of the map's size."""

    def __init__(self, cell_m: float):
        self.cell = float(cell_m)
        self._cells: dict[tuple[int, int, int], dict[int, Apple]] = {}
        self._where: dict[int, tuple[int, int, int]] = {}

    def _key(self, X) -> tuple[int, int, int]:
        return tuple(int(v) for v in np.floor(np.asarray(X, float)[:3] / self.cell))

    def __len__(self) -> int:
        return len(self._where)

    def put(self, a: Apple) -> None:
        """Add an apple, or move it to the cell of its (updated) position."""
        new = self._key(a.X)
        old = self._where.get(a.id)
        if old == new:
            return
        if old is not None:
            self._cells[old].pop(a.id, None)
            if not self._cells[old]:
                del self._cells[old]
        self._cells.setdefault(new, {})[a.id] = a
        self._where[a.id] = new

    def remove(self, a: Apple) -> None:
        key = self._where.pop(a.id, None)
        if key is not None:
            self._cells[key].pop(a.id, None)
            if not self._cells[key]:
                del self._cells[key]

    def near(self, X, r: float) -> list[Apple]:
        kx, ky, kz = self._key(X)
        X = np.asarray(X, float)
        out = []
        n = max(1, int(np.ceil(r / self.cell)))  # a radius beyond one cell (the map's units changed): more cells
        span = range(-n, n + 1)
        for dx in span:
            for dy in span:
                for dz in span:
                    for a in self._cells.get((kx + dx, ky + dy, kz + dz), {}).values():
                        if np.linalg.norm(a.X - X) <= r:
                            out.append(a)
        return out


_SAMPLE_CACHE: dict[tuple[int, int], np.ndarray] = {}


def _sample_index(length: int, n: int) -> np.ndarray:
    key = (length, n)
    if key not in _SAMPLE_CACHE:
        _SAMPLE_CACHE[key] = np.unique(np.linspace(0, length - 1, min(length, n)).round().astype(int))
    return _SAMPLE_CACHE[key]


class _Track:
    __slots__ = ("obs", "Ps", "xs", "M", "_X", "_views", "root", "last", "mature", "origin")

    def __init__(self, root: int, origin: np.ndarray):
        self.obs: list[Detection] = []
        self.Ps: list[np.ndarray] = []
        self.xs: list[np.ndarray] = []
        # normal matrix of the linear triangulation, accumulated, about the root's camera centre (the
        # algebraic error depends on the coordinates: see ground.apples.geometry.triangulate)
        self.M = np.zeros((4, 4))
        self.origin = np.asarray(origin, float)[:3]
        self._X: np.ndarray | None = None
        self._views = None
        self.root = root
        self.last = -1
        self.mature = False

    def add(self, det: Detection, P: np.ndarray, x: np.ndarray, rows: np.ndarray | None = None):
        """Append an observation; rows = its two triangulation rows about the track's origin, unit length,
        if already computed."""
        self.obs.append(det)
        self.Ps.append(P)
        self.xs.append(x)
        if rows is None:
            rows = triangulation_rows(P, x, self.origin)
        self.M = self.M + rows.T @ rows
        self.last = det.frame
        self._X = None
        self._views = None

    @property
    def X(self) -> np.ndarray | None:
        """Least-squares point of all observations (computed when asked)."""
        if self._X is None and len(self.obs) >= 2:
            h = np.linalg.eigh(self.M)[1][:, 0]
            self._X = h[:3] / h[3] + self.origin if abs(h[3]) > 1e-12 else None
        return self._X

    def views(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """At most n of the track's views (first, last, evenly between), cached until the next add."""
        if self._views is None:
            sel = _sample_index(len(self.obs), n)
            self._views = (np.array([self.Ps[i] for i in sel]), np.array([self.xs[i] for i in sel]))
        return self._views

    def repose(self, P: dict[int, np.ndarray]) -> None:
        """Take the corrected camera matrices of its frames (frame -> P), and its normal matrix again from them."""
        self.Ps = [P.get(o.frame, Pk) for o, Pk in zip(self.obs, self.Ps)]
        self.M = np.zeros((4, 4))
        for Pk, x in zip(self.Ps, self.xs):
            rows = triangulation_rows(Pk, x, self.origin)
            self.M = self.M + rows.T @ rows
        self._X = None
        self._views = None

    def copy(self) -> "_Track":
        t = _Track(self.root, self.origin)
        t.obs, t.Ps, t.xs = list(self.obs), list(self.Ps), list(self.xs)
        t.M, t._X, t._views, t.last, t.mature = self.M, self._X, self._views, self.last, self.mature
        return t


class WindowedAssociation:
    """Streaming association: feed frames in order with :meth:`add_frame`; apples come out as they close.

    ``add_frame`` returns the apples whose tracks can no longer grow (no detection for k frames);
    :meth:`finish` closes the rest at the end of the flight. ``metres_per_unit``: the size of the frames' unit, as
    well as it is known now (a map georeferenced from a few keyframes' GPS is off by tens of percent); the params'
    distances are metres.
    """

    def __init__(self, params: AssociationParams | None = None):
        self.params = params or AssociationParams()
        self.tracks: list[_Track] = []
        self._next_root = 0
        self._next_id = 0
        self._recent: list[Apple] = []  # emitted apples that a later track may turn out to duplicate
        self._index = SpatialIndex(max(self.params.merge_search_m, 0.1))  # every apple, with cross_pass
        self.metres_per_unit = 1.0
        self._geom: dict[int, tuple] = {}  # recent frames' (P, centre, pseudo-inverse)
        self._apples: dict[int, Apple] = {}  # every apple emitted and not merged away, by id
        self._by_frame: dict[int, set[int]] = {}  # frame -> ids of the apples with a view in it
        self.stats = {"frames": 0, "branch_bound_hits": 0, "roots": 0, "tracks_closed": 0, "apples": 0, "merged": 0,
                      "merged_across_passes": 0, "reposed": 0, "merged_after_repose": 0}

    # -- helpers
    def landmarks(self) -> np.ndarray:
        """The apples mapped about the newest frames, (n, 3): those emitted within the merge window, and the open
        tracks' points (the longest of each root's hypotheses, once mature)."""
        best: dict[int, _Track] = {}
        for t in self.tracks:
            if t.mature and len(t.obs) > len(best[t.root].obs if t.root in best else ()):
                best[t.root] = t
        pts = [a.X for a in self._recent] + [t.X for t in best.values() if t.X is not None]
        return np.asarray(pts, float).reshape(-1, 3)

    def _emit(self, t: _Track) -> Apple | None:
        p = self.params
        Ps, xs = np.stack(t.Ps), np.stack(t.xs)
        res = refine(Ps, xs, np.ones(len(xs), bool), p.tau_geom, p.min_inliers)
        if res is None:
            return None
        X, inl, err = res
        if p.nonlinear:
            X, inl, err = polish(Ps, xs, X, inl, p.tau_geom, p.min_inliers)
        obs = [o for o, keep in zip(t.obs, inl) if keep]
        views, frames = sample_views(Ps[inl], xs[inl], [o.frame for o in obs])
        return Apple(-1, X, obs, err, views=views, view_frames=frames)

    def _close(self, frame: int, final: bool = False) -> list[Apple]:
        p = self.params
        out, keep = [], []
        for t in self.tracks:
            if not final and frame - t.last < p.k:
                keep.append(t)
                continue
            self.stats["tracks_closed"] += 1
            if t.mature:
                a = self._emit(t)
                if a is not None:
                    out.append(self._merge_or_add(a))
        self.tracks = keep
        self._recent = [a for a in self._recent if frame - a.last_frame <= p.merge_window] if not final else self._recent
        return out

    def _merge_or_add(self, a: Apple) -> Apple:
        """A new apple, or the earlier apple it duplicates (updated, same id)."""
        p = self.params
        if p.merge_search_m > 0:
            unit = self.metres_per_unit
            target, X = find_duplicate(a, self._recent, p, metres_per_unit=unit)
            if target is None and p.cross_pass:
                # the whole map: an apple seen again from another pass. Its views still triangulate with the first
                # ones: the caps seen from two sides are offset along each pass's own rays, which the joint point
                # (the apple's centre) absorbs; the stricter test keeps apples a few cm apart two.
                recent = {id(r) for r in self._recent}
                older = [c for c in self._index.near(a.X, p.merge_search_m / unit) if id(c) not in recent]
                target, X = find_duplicate(a, older, p, strict=True, metres_per_unit=unit)
                if target is not None:
                    self.stats["merged_across_passes"] += 1
            if target is not None:
                merge_into(target, a, X)
                self.stats["merged"] += 1
                if p.cross_pass:
                    self._index.put(target)
                self._note_views(target)
                return target
        a.id = self._next_id
        self._next_id += 1
        self.stats["apples"] += 1
        self._recent.append(a)
        if p.cross_pass:
            self._index.put(a)
        self._apples[a.id] = a
        self._note_views(a)
        return a

    def _note_views(self, a: Apple) -> None:
        for f in ([] if a.view_frames is None else a.view_frames.tolist()):
            self._by_frame.setdefault(f, set()).add(a.id)

    def repose(self, P: dict[int, np.ndarray]) -> tuple[list[Apple], list[tuple[int, int]]]:
        """Frames whose camera matrices were corrected (frame -> new P; the mapper refined the keyframes about them,
        or re-anchored them on an earlier pass): the open tracks take the new matrices, and every apple with a view in
        those frames is triangulated again from its views. Where two apples then triangulate together (one apple,
        seen on two passes whose poses only now agree), the younger merges into the elder. Returns the apples that
        moved or grew, and (id merged away, id it merged into) pairs."""
        p = self.params
        for t in self.tracks:
            if any(o.frame in P for o in t.obs):
                t.repose(P)
        for f in P:
            self._geom.pop(f, None)
        ids = set().union(*(self._by_frame.get(f, ()) for f in P)) if P else set()
        moved = []
        for i in sorted(ids):
            a = self._apples.get(i)
            if a is None or a.view_frames is None:
                continue
            Ps = a.views[0].copy()
            for k, f in enumerate(a.view_frames.tolist()):
                if f in P:
                    Ps[k] = P[f]
            X = triangulate_nonlinear(Ps, a.views[1], a.X)
            if not np.isfinite(X).all():
                continue
            err = reprojection_errors(Ps, a.views[1], X)
            a.X, a.views = X, (Ps, a.views[1])
            a.reprojection_error = float(err[err < p.tau_geom].mean()) if (err < p.tau_geom).any() else float(err.mean())
            if p.cross_pass:
                self._index.put(a)
            moved.append(a)
        self.stats["reposed"] += len(moved)
        gone: dict[int, int] = {}
        kept: dict[int, Apple] = {a.id: a for a in moved}
        if p.merge_search_m > 0:
            for a in moved:
                if a.id in gone:
                    continue
                near = self._index.near(a.X, p.merge_search_m / self.metres_per_unit) if p.cross_pass else self._recent
                target, X = find_duplicate(a, [c for c in near if c is not a and c.id not in gone], p, strict=True,
                                           metres_per_unit=self.metres_per_unit)
                if target is None:
                    continue
                keep, drop = (target, a) if target.id < a.id else (a, target)
                merge_into(keep, drop, X)
                self._forget(drop)
                if p.cross_pass:
                    self._index.put(keep)
                self._note_views(keep)
                gone[drop.id] = keep.id
                kept[keep.id] = keep
                self.stats["merged"] += 1
                self.stats["merged_after_repose"] += 1
        return [a for i, a in kept.items() if i not in gone], list(gone.items())

    def _forget(self, a: Apple) -> None:
        """An apple merged into another: out of the index, the recent list and the frame lists."""
        self._apples.pop(a.id, None)
        self._index.remove(a)
        self._recent = [r for r in self._recent if r is not a]
        for f in ([] if a.view_frames is None else a.view_frames.tolist()):
            s = self._by_frame.get(f)
            if s is not None:
                s.discard(a.id)
                if not s:
                    del self._by_frame[f]

    _VERIFY_VIEWS = 12  # views of a track checked when verifying an extension (first, last, evenly between)

    def _frame_geometry(self, frame: int, P: np.ndarray):
        """(P, centre, pseudo-inverse) of a recent frame, computed once."""
        g = self._geom.get(frame)
        if g is None:
            g = self._geom[frame] = (P, camera_centre(P), np.linalg.pinv(P))
            for f in [f for f in self._geom if f < frame - self.params.k - 1]:
                del self._geom[f]
        return g

    def _candidates(self, frame: int, P: np.ndarray, xy: np.ndarray):
        """(track, detection) pairs within tau_epipolar of the epipolar line of the track's last node,
        each verified: the track's views plus the candidate triangulate to a point that reprojects
        within tau_geom in every checked view. Returns track idx, detection idx, cost (px), and the
        candidates' triangulation rows."""
        p = self.params
        by_last: dict[int, list[int]] = {}
        for ti, t in enumerate(self.tracks):
            by_last.setdefault(t.last, []).append(ti)
        pt, pd = [], []
        for last_frame, tis in by_last.items():
            Pi, Ci, Pi_pinv = self._frame_geometry(last_frame, self.tracks[tis[0]].Ps[-1])
            F = skew(P @ Ci) @ P @ Pi_pinv
            last = np.array([self.tracks[ti].xs[-1] for ti in tis])
            a, b = np.nonzero(epipolar_distances(F, last, xy) <= p.tau_epipolar)
            pt.append(np.asarray(tis)[a])
            pd.append(b)
        pt, pd = np.concatenate(pt), np.concatenate(pd)
        if len(pt) == 0:
            return pt, pd, np.zeros(0), np.zeros((0, 2, 4))
        # verify every pair at once: X' from the track's normal matrix plus the candidate's rows
        origin = np.stack([self.tracks[ti].origin for ti in pt])
        rows = triangulation_rows(P, xy[pd], origin)  # (n, 2, 4)
        M = np.stack([self.tracks[ti].M for ti in pt]) + np.einsum("nri,nrj->nij", rows, rows)
        h = np.linalg.eigh(M)[1][..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            Xn = h[:, :3] / h[:, 3:4] + origin
        V = self._VERIFY_VIEWS
        Pv = np.zeros((len(pt), V + 1, 3, 4))
        xv = np.zeros((len(pt), V + 1, 2))
        valid = np.zeros((len(pt), V + 1), bool)
        for n, ti in enumerate(pt.tolist()):
            tp, tx = self.tracks[ti].views(V)
            k = len(tx)
            Pv[n, :k], xv[n, :k], valid[n, :k] = tp, tx, True
        Pv[:, V], xv[:, V], valid[:, V] = P, xy[pd], True
        err = np.where(valid, reprojection_errors(Pv, xv, Xn), 0.0)
        ok = np.isfinite(Xn).all(1) & (err.max(1) < p.tau_geom)
        return pt[ok], pd[ok], err[ok, V], rows[ok]

    def add_frame(self, fd: FrameDetections) -> list[Apple]:
        j, P, xy = fd.frame, fd.P, fd.xy
        self.stats["frames"] += 1
        emitted = self._close(j)
        m = len(xy)
        claimed = np.zeros(m, bool)
        if m and self.tracks:
            pt, pd, cost, rows = self._candidates(j, P, xy)
            mature = np.array([t.mature for t in self.tracks])
            # mature tracks: one detection each, the cheapest overall (Hungarian)
            sel = mature[pt]
            if sel.any():
                ut, inv_t = np.unique(pt[sel], return_inverse=True)
                C = np.full((len(ut), m), 1e6)
                C[inv_t, pd[sel]] = cost[sel]
                r, c = linear_sum_assignment(C)
                ok = C[r, c] < 1e6
                pair = {(int(a), int(b)): n for n, (a, b) in enumerate(zip(pt, pd))}
                for ti, di in zip(ut[r[ok]], c[ok]):
                    self.tracks[ti].add(fd.detection(int(di)), P, xy[di], rows[pair[int(ti), int(di)]])
                    claimed[di] = True
                # a mature track left without a detection may share one (apples occluding each other cross)
                for row, ti in enumerate(ut):
                    t = self.tracks[ti]
                    if t.last != j and C[row].min() < 1e6:
                        di = int(np.argmin(C[row]))
                        t.add(fd.detection(di), P, xy[di])
            # young tracks: one branch per verified candidate not taken by a mature track; the track
            # itself stays as it is too, since a path may skip a frame (edges reach k frames ahead)
            new_tracks = []
            for n in np.nonzero(~sel)[0]:
                di = pd[n]
                if claimed[di]:
                    continue
                b = self.tracks[pt[n]].copy()
                b.add(fd.detection(int(di)), P, xy[di], rows[n])
                new_tracks.append(b)
            self.tracks.extend(new_tracks)
            for b in new_tracks:
                claimed[b.obs[-1].index] = True
            self._check_young(j)
        # unclaimed detections start new roots
        centre = self._frame_geometry(j, P)[1] if (~claimed).any() else None
        for di in np.nonzero(~claimed)[0]:
            t = _Track(self._next_root, centre)
            self._next_root += 1
            self.stats["roots"] += 1
            t.add(fd.detection(int(di)), P, xy[di])
            self.tracks.append(t)
        return emitted

    def _check_young(self, frame: int):
        """Promote young tracks whose nodes agree on one 3-D point; bound the branches of each root."""
        p = self.params
        by_root: dict[int, list[_Track]] = {}
        for t in self.tracks:
            if not t.mature:
                by_root.setdefault(t.root, []).append(t)
        drop = set()
        for root, ts in by_root.items():
            promoted = None
            for t in ts:  # every extension was verified, so a branch with enough views is a consistent path
                if len(t.obs) >= max(3, p.min_inliers) and t.X is not None:
                    promoted = t if promoted is None or len(t.obs) > len(promoted.obs) else promoted
            if promoted is not None:
                promoted.mature = True
                drop.update(id(t) for t in ts if t is not promoted)
                continue
            if len(ts) > p.max_branches:
                self.stats["branch_bound_hits"] += 1
                # keep the branches with the most nodes, then the smallest reprojection spread
                def score(t):
                    if t.X is None or len(t.obs) < 2:
                        return (len(t.obs), 0.0)
                    return (len(t.obs), -float(reprojection_errors(np.stack(t.Ps), np.stack(t.xs), t.X).max()))
                ts_sorted = sorted(ts, key=score, reverse=True)
                drop.update(id(t) for t in ts_sorted[p.max_branches:])
        if drop:
            self.tracks = [t for t in self.tracks if id(t) not in drop]

    def finish(self) -> list[Apple]:
        """Close every open track (end of flight)."""
        return self._close(0, final=True)

    def run(self, frames: list[FrameDetections]) -> list[Apple]:
        """All apples of a sequence (updates of a merged apple replace it, by id)."""
        apples: dict[int, Apple] = {}
        for f in frames:
            for a in self.add_frame(f):
                apples[a.id] = a
        for a in self.finish():
            apples[a.id] = a
        return [apples[i] for i in sorted(apples)]
