"""The streaming association the ground runs, fed one frame at a time. Each open track is a path of the paper's graph
grown frame by frame: a young track extends along the epipolar line of its last node (within tau_epipolar, branching
into every candidate, at most ``max_branches`` per root), a track with a 3-D estimate extends to the detection nearest
its reprojection (within tau_geom). Tracks not extended for k frames can no longer grow and are closed: their inliers
are re-estimated and, with at least ``min_inliers``, emitted as an apple. Time per frame and memory depend on the open
tracks only, not on the flight's length."""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from ground.apples.association import Apple, AssociationParams, Detection, FrameDetections
from ground.apples.geometry import (camera_centre, epipolar_distances, reprojection_errors, skew, triangulate,
                                    triangulate_nonlinear, triangulation_rows)
from ground.apples.merging import find_duplicate, merge_into, sample_index, sample_views
from ground.apples.ransac import polish, refine
from ground.apples.spatial_index import SpatialIndex


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
            sel = sample_index(len(self.obs), n)
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
