"""The registrar across passes (its second job beside registering keyframes in order): each registered keyframe
indexed by the place it looks at (:class:`ground.poses.revisit.Places`), a finished sub-model's points kept as
anchors, the current sub-model re-anchored onto an earlier pass's points when a keyframe sees a place seen before,
and a new sub-model placed by the telemetry when the chain breaks.

:class:`AcrossPasses` is :class:`ground.poses.registration.IncrementalRegistrar`'s base: it reads the registrar's
sub-models, keyframe order, telemetry priors, revisit matches and settings, and calls back its ``_bootstrap`` and
``_start``.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from ground.poses.revisit import robust_similarity
from pomar.align import IDENTITY, Similarity, compose, inverse

if TYPE_CHECKING:
    from ground.poses.registration import Submodel

log = logging.getLogger("ground.poses.registration")  # its messages are the registrar's


class AcrossPasses:
    def _keep_anchors(self, k: int, sm: Submodel) -> None:
        if sm.rec is None:
            return
        anchors = {}
        for n in sm.names:
            im = sm.rec.find_image_with_name(n)
            idx, X = [], []
            for i, p in zip(im.get_observation_point2D_idxs(), im.get_observation_points2D()):
                q = sm.rec.points3D[p.point3D_id]
                if q.track.length() >= 3 and q.error <= 1.5:
                    idx.append(i)
                    X.append(q.xyz)
            anchors[n] = (np.array(idx, np.int32), np.array(X, float).reshape(-1, 3))
        self.places.keep_anchors(k, anchors)

    def _add_place(self, sm: Submodel, name: str) -> None:
        """Index a registered keyframe by the point it looks at (the median of its 3-D points) and its axis."""
        im = sm.rec.find_image_with_name(name)
        X = np.array([sm.rec.points3D[p.point3D_id].xyz for p in im.get_observation_points2D()], float).reshape(-1, 3)
        if len(X) < 10:
            return
        X = sm.to_first.apply(X)
        m = im.cam_from_world().matrix()
        R = sm.to_first.R @ m[:, :3].T  # camera axes in the first frame (columns)
        c = sm.to_first.apply(-m[:, :3].T @ m[:, 3])
        look = np.median(X, 0)
        self.places.add(name, self._order[name], look, R[:, 2])
        self._last_place = (look, R[:, 2], float(np.median(np.linalg.norm(X - c, axis=1))))

    def _registered_one(self, sm: Submodel, name: str) -> None:
        """A keyframe registered into the current sub-model: index its place, and re-anchor the sub-model on the 3-D
        points it shares with the earlier keyframes of that place in finished sub-models."""
        if name not in self.places:
            self._add_place(sm, name)
        im = sm.rec.find_image_with_name(name)
        for old, inl in self._revisit_matches.get(name, []):
            if old in sm.names:
                continue  # the mapper used these matches: the old keyframe is in this sub-model
            a = self.places.anchors(old)
            if a is None:
                continue
            k, idx, X_old = a
            row = {int(i): r for r, i in enumerate(idx)}
            src, dst = [], []
            for i_old, i_new in inl:
                r = row.get(int(i_old))
                p = im.points2D[int(i_new)]
                if r is None or not p.has_point3D():
                    continue
                q = sm.rec.points3D[p.point3D_id]
                if q.track.length() >= 3:
                    src.append(q.xyz)
                    dst.append(X_old[r])
            if src:
                sm.revisit_src.append(np.array(src))
                sm.revisit_dst.append(self.submodels[k].to_first.apply(np.array(dst)))
        self._reanchor(sm)

    def _reanchor(self, sm: Submodel) -> None:
        """Fit the sub-model onto the earlier passes' points it shares, once it shares revisit_min_points, then again
        each time they grew by half (a few fits per sub-model: the cost stays flat, and the poses do not jitter)."""
        n = sum(len(s) for s in sm.revisit_src)
        if (n < max(self.s.revisit_min_points, 1.5 * sm.anchored_on) or len(sm.revisit_src) < self.s.revisit_min_pairs
                or self._last_place is None):
            return
        src, dst = np.concatenate(sm.revisit_src), np.concatenate(sm.revisit_dst)
        look, _, depth = self._last_place
        sm.anchored_on = n
        fit = robust_similarity(src, dst, tol=0.01 * depth)
        if fit is None:
            return
        S, inl = fit
        if inl.sum() < self.s.revisit_min_points or inl.mean() < 0.5:
            return
        # a re-anchoring moves a chained sub-model by the chain's drift (cm, a tenth of a degree), one placed by
        # telemetry by the GPS error: more than that is a false match between two look-alike places
        here = inverse(sm.to_first).apply(look[None])[0]
        shift = float(np.linalg.norm(S.apply(here[None])[0] - look))
        turn = np.degrees(np.arccos(np.clip((np.trace(S.R @ sm.to_first.R.T) - 1) / 2, -1, 1)))
        max_shift, max_turn = (0.1, 3.0) if sm.placed_by_telemetry else (0.03, 0.5)
        if shift > max_shift * depth or turn > max_turn:
            log.warning("re-anchoring refused: it would move the sub-model %.2f (%.0f%% of the depth) and turn it "
                        "%.1f deg", shift, 100 * shift / depth, turn)
            return
        sm.to_first = S
        sm.placed_by_telemetry = False
        self.reanchored += 1
        log.info("sub-model %d re-anchored on %d points shared with earlier passes: moved %.3f, turned %.3f deg",
                 len(self.submodels) - 1, int(inl.sum()), shift, turn)

    def _rejoin(self, name: str) -> bool:
        """The chain broke: after ``break_after`` keyframes in a row failed, a new sub-model from them, placed where
        their telemetry puts them against the model's registered keyframes' telemetry."""
        failing = self._failing + [name]
        if len(failing) < self.s.break_after or not all(n in self.priors for n in failing):
            return False
        new = self._bootstrap(failing[-2 * self.s.init_frames:])
        if new is None:
            return False
        to_first = self._place_by_priors(new)
        if to_first is None:
            return False
        new.to_first, new.placed_by_telemetry = to_first, True
        self._start(new)
        self.rejoined += 1
        log.info("registration re-joined after %d keyframes that did not register: a new sub-model of %d placed by "
                 "telemetry", len(failing), len(new.names))
        return name in new.names

    def _place_by_priors(self, new: Submodel) -> Similarity | None:
        """new -> first frame, through ENU: each side fitted to its keyframes' telemetry (positions and axes)."""
        from ground.poses.georeference import fit_similarity, georeference_poses

        def to_enu(sms: list[Submodel]) -> Similarity | None:
            names, R, t = [], [], []
            for sm in sms:
                m = sm.cam_from_world()
                Ri, ti = georeference_poses(m[:, :, :3], m[:, :, 3], sm.to_first or IDENTITY)
                keep = [k for k, n in enumerate(sm.names) if n in self.priors]
                names += [sm.names[k] for k in keep]
                R.append(Ri[keep])
                t.append(ti[keep])
            names, R, t = names[-200:], np.concatenate(R)[-200:], np.concatenate(t)[-200:]
            if len(names) < 3:
                return None
            pr = [self.priors[n] for n in names]
            c = -np.einsum("nji,nj->ni", R, t)
            return fit_similarity(c, np.array([p[0] for p in pr]), np.array([p[2] for p in pr]), R,
                                  np.array([p[1] for p in pr]), self.sigma_att).similarity

        # the placed sub-models' last keyframes (to_enu keeps 200), whether or not they are still in memory: how many
        # stay in memory must not move the map
        first_to_enu = to_enu([sm for sm in self.submodels if sm.to_first is not None])
        new_to_enu = to_enu([new])  # not yet placed: its own frame
        if first_to_enu is None or new_to_enu is None:
            return None
        return compose(inverse(first_to_enu), new_to_enu)
