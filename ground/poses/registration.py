"""Incremental registration of keyframes with pycolmap, one keyframe at a time, at a bounded cost.

For each keyframe: SIFT features, matching against the previous ``match_window`` keyframes and against the earlier
keyframes that look at the same place (another pass of a whole-plot flight: :mod:`ground.poses.revisit`), then the
incremental mapper registers it into the current sub-model (2D-3D pose), triangulates its new points
and refines locally; a global refinement runs every ``global_ba_every`` keyframes. Once a sub-model holds
``submodel_size`` keyframes, and its last ``overlap`` ones are not in a turn (or it holds half as many again), a
new one is bootstrapped from those keyframes and chained to the previous one by a similarity over the cameras
they share. The database cache is
built over the current sub-model only, so the cost per keyframe does not grow with the flight.

Across passes: an earlier keyframe of the same place in the current sub-model takes part in the new one's
registration (their matches are in the database); one in a finished sub-model re-anchors the current sub-model
onto its 3-D points (a similarity over the points they share), so that a pass lands where the earlier passes put
the same trees. When the chain breaks (``break_after`` keyframes in a row fail, e.g. a turn over bare ground), a
new sub-model is made from them and placed by their GPS and attitude against the model's, then re-anchored as
soon as it sees a place seen before: the flight stays one map.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from ground.poses.keyframe_db import KeyframeDatabase, write_refused
from ground.poses.matching import match_descriptors, unit_descriptors
from ground.poses.passes import AcrossPasses
from ground.poses.revisit import Places
from ground.poses.sift import SiftExtractor
from pomar.align import IDENTITY, Similarity, compose
from pomar.camera import Camera

log = logging.getLogger(__name__)
# COLMAP's own INFO lines (several per keyframe) would drown the node's progress; warnings still show.
pycolmap.logging.minloglevel = 1


@dataclass
class RegistrationSettings:
    #: Each keyframe is matched against this many previous ones: the wider the baselines, the better the map's scale
    #: holds along a long pass (each sub-model drifts less).
    match_window: int = 10
    #: Keyframes in one sub-model (a local pycolmap reconstruction) before the next one takes over.
    submodel_size: int = 60
    #: Keyframes two consecutive sub-models share, on which the next is chained to the one before.
    overlap: int = 10
    #: A full sub-model hands over to the next only where its last ``overlap`` keyframes look within this of the
    #: newest one's way (degrees), or at 1.5 x its size: the next one is chained on the cameras they share, which in a
    #: turn (few views, changing fast) place it poorly.
    chain_max_turn_deg: float = 15.0
    #: A bundle adjustment of the whole sub-model every this many keyframes (local ones in between).
    global_ba_every: int = 10
    #: Keyframes the first model is made from (live, frames wait for it).
    init_frames: int = 6
    #: SIFT's first octave (-1 also looks at the image doubled: more, smaller features, slower).
    first_octave: int = 0
    #: SIFT runs on keyframes shrunk to at most this width (0: their own size); keypoints are scaled back, so the
    #: mapper sees keyframe pixels. Extraction and matching cost about the pixel count and the feature count.
    sift_width: int = 0
    #: SIFT features per keyframe, at most.
    max_num_features: int = field(default=4096, metadata={"flag": "--max-features"})
    #: SIFT implementation, "colmap" (pycolmap's) or "opencv". OpenCV's takes half the time (0.17 against 0.33 s per
    #: 1280x720 keyframe) and the final batch poses are as good, but in the live ground node, where each frame's pose
    #: is decided soon after its keyframe registers, it let the model's scale drift (4.5 px median reprojection error
    #: of the true apples against 1 px with pycolmap's, on the bundled flight).
    sift: str = field(default="colmap", metadata={"choices": ["opencv", "colmap"]})
    #: The least triangulation angle (degrees) of the first model's points.
    init_min_tri_angle: float = 2.0
    #: Rounds of retriangulation and bundle adjustment after each local refinement.
    local_refinements: int = 1
    #: ... and after each global one.
    global_refinements: int = 1
    #: SIFT without orientation (COLMAP's upright option). Consecutive keyframes of a gimbal-stabilised camera barely
    #: rotate in the image plane, and skipping orientation saves a quarter of extraction; on the bundled flight it
    #: cost some accuracy (true apples 0.99 against 0.83 px after a similarity).
    upright: bool = False
    #: Ceres solves a bundle adjustment on one thread below this many residuals. On more threads its sums come in
    #: another order each run and a flight's keyframes drift apart between runs; on one, a lock-step replay repeats
    #: bit for bit, and the ground is no slower (benchmarks/live_ground.py).
    ba_threads_min_residuals: int = 10**9
    #: Finished sub-models kept in memory (the newest is chained to the one before it); older ones are written to
    #: the work directory and read back only for the final model files.
    keep_submodels: int = 2
    #: Keyframes are also matched against earlier keyframes of the same place (other passes), and a sub-model is
    #: re-anchored on the points they share (--no-revisit: only the previous ones, a baseline for whole-plot flights).
    revisit: bool = True
    #: Earlier keyframes count as the same place where their look points lie within this share of the viewing depth.
    revisit_radius: float = 0.4
    #: A sub-model is re-anchored on an earlier pass once this many 3-D points are shared ...
    revisit_min_points: int = 150
    #: ... from at least this many keyframe pairs (one pair sees too small a patch).
    revisit_min_pairs: int = 3
    #: Keyframes back before one may count as another pass's (nearer ones the matching window links already); while
    #: keyframes fail to register, any beyond the matching window counts.
    revisit_min_gap: int = 8
    #: Keyframes in a row that fail to register before a new sub-model is made from them (placed by telemetry).
    break_after: int = 3

    @property
    def first_model_tries(self) -> int:
        """Keyframes the first model is tried on before the frames go on without one."""
        return 3 * self.init_frames

    def __post_init__(self):
        if self.sift not in ("colmap", "opencv"):
            raise ValueError(f"RegistrationSettings.sift must be 'colmap' or 'opencv', got {self.sift!r}")
        if self.upright and self.sift != "colmap":
            raise ValueError("RegistrationSettings.upright applies to pycolmap's SIFT only (sift='colmap')")


@dataclass
class Submodel:
    rec: pycolmap.Reconstruction | None  # None once the sub-model was written to ``path`` and left memory
    names: list[str] = field(default_factory=list)
    to_first: Similarity | None = None  # maps this sub-model's coordinates into the first sub-model's
    path: Path | None = None
    _frozen: np.ndarray | None = None  # (n, 3, 4) cam_from_world of ``names``, kept when ``rec`` left memory
    # 3-D points shared with finished sub-models (this sub-model's frame, the first's): what re-anchors it
    revisit_src: list = field(default_factory=list, repr=False)
    revisit_dst: list = field(default_factory=list, repr=False)
    anchored_on: int = 0  # shared points at its last re-anchoring
    placed_by_telemetry: bool = False  # re-joined after the chain broke: metres off until re-anchored

    def reconstruction(self) -> pycolmap.Reconstruction:
        """The sub-model, read back from disk if it left memory."""
        return self.rec if self.rec is not None else pycolmap.Reconstruction(str(self.path))

    def cam_from_world(self) -> np.ndarray:
        """(n, 3, 4) world-to-camera matrices of the registered keyframes, in ``names`` order."""
        if self.rec is None:
            return self._frozen
        return np.array([self.rec.find_image_with_name(n).cam_from_world().matrix() for n in self.names])

    def offload(self, path: Path) -> None:
        """Write the sub-model to ``path`` (COLMAP binary) and drop it from memory, keeping its poses: a finished
        sub-model holds every keyframe's features and 3-D points, and the flight's memory would grow with them."""
        path.mkdir(parents=True, exist_ok=True)
        self._frozen = self.cam_from_world()
        self.rec.write_binary(str(path))
        self.path, self.rec = path, None


class IncrementalRegistrar(AcrossPasses):
    def __init__(self, camera: Camera, workdir: str | Path | None, settings: RegistrationSettings | None = None,
                 sigma_att_deg: float = 0.5):
        """sigma_att_deg: the telemetry's attitude error, which weighs the axes in placing a re-joined sub-model (the
        same as in georeferencing)."""
        self.cam, self.s = camera, settings or RegistrationSettings()
        self.sigma_att = np.radians(sigma_att_deg)
        # workdir None: everything in memory, the database included; no keyframe images are kept and finished
        # sub-models stay in memory. A folder whose disk refuses a write (full) is left for memory the same way
        # (_to_memory), at the keyframe where that happened
        self.work = Path(workdir) if workdir is not None else None
        self.in_memory_from: int | None = None  # the keyframe at which the folder refused a write
        self.places = Places(self.work / "places" if self.work is not None else None, radius=self.s.revisit_radius,
                             min_gap=self.s.revisit_min_gap)
        if self.work is not None:
            try:
                if self.work.exists():
                    shutil.rmtree(self.work)
                (self.work / "images").mkdir(parents=True)
            except OSError as exc:
                if not write_refused(exc):
                    raise
                self._leave_folder(exc, 0)
        self.db_path = self.work / "database.db" if self.work is not None else ":memory:"
        self.names: list[str] = []  # every keyframe, in order
        self.frame_of: dict[str, int] = {}
        self.submodels: list[Submodel] = []
        self.failed: list[int] = []
        self.seconds: list[float] = []
        self.stage_seconds: list[tuple[float, float, float]] = []  # features, matching, mapping
        self.priors: dict[str, tuple[np.ndarray, np.ndarray, float]] = {}  # keyframe -> (ENU centre, R, sigma m)
        self._image_ids: dict[str, int] = {}
        self._revisit_matches: dict[str, list[tuple[str, np.ndarray]]] = {}  # new keyframe -> (earlier one, matches)
        self._last_place: tuple[np.ndarray, np.ndarray, float] | None = None  # look point, axis, depth
        self._failing: list[str] = []  # keyframes in a row that failed to register
        self.revisits = 0  # keyframes matched to an earlier keyframe of the same place
        self.reanchored = 0  # times a sub-model was re-anchored onto earlier passes' points
        self.rejoined = 0  # new sub-models placed by telemetry after the chain broke
        self.global_adjustments = 0  # global bundle adjustments so far (each moves all of its sub-model's keyframes)
        self._mopts = pycolmap.IncrementalPipelineOptions()
        # the camera is calibrated (camera.json): bundle adjustment keeps its intrinsics (so does a new image's pose:
        # the mapper's options follow these), and the database's camera says its focal length is known
        self._mopts.ba_refine_focal_length = False
        self._mopts.ba_refine_principal_point = False
        self._mopts.ba_refine_extra_params = False
        self._mopts.mapper.init_min_tri_angle = self.s.init_min_tri_angle
        self._mopts.mapper.init_min_num_inliers = 50
        self._mopts.ba_min_num_residuals_for_cpu_multi_threading = self.s.ba_threads_min_residuals
        self._mopts.random_seed = 0  # RANSAC's samples the same each run
        try:
            self.db = KeyframeDatabase(self.cam, str(self.db_path))
        except Exception as exc:  # a new database in a folder just made: what fails is the folder (a full disk)
            if self.work is None:
                raise
            self._leave_folder(exc, 0)
            self.db = KeyframeDatabase(self.cam, str(self.db_path))
        self._start_workers()

    # -- features and matches
    def _start_workers(self):
        self._sift = SiftExtractor(self.s)
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="two-view")
        self._two_view = pycolmap.TwoViewGeometryOptions()
        self._two_view.ransac.random_seed = 0
        self._recent = deque(maxlen=max(self.s.match_window, 1))  # (image id, keypoint xy, unit descriptors)
        self._order: dict[str, int] = {}  # keyframe -> its place in the flight's keyframes

    def _store(self, name: str, frame: int, kp: np.ndarray, raw: np.ndarray, desc: np.ndarray, prior) -> None:
        """The keyframe into the database: its features, then its matches."""
        new = self._write_features(name, kp, raw, desc)
        self._order[name] = len(self.names)
        self.names.append(name)
        self.frame_of[name] = frame
        if prior is not None and all(np.isfinite(np.asarray(p, float)).all() for p in prior):
            self.priors[name] = prior
        self._match(name, new)

    def _forget(self, name: str) -> None:
        """Undo what _store did for a keyframe whose writes failed part way."""
        for d in (self._image_ids, self._order, self.frame_of, self.priors, self._revisit_matches):
            d.pop(name, None)
        if self.names and self.names[-1] == name:
            self.names.pop()

    def _write_features(self, name: str, kp: np.ndarray, raw: np.ndarray, desc: np.ndarray):
        """Store the keyframe's features in the database; (image id, keypoint xy, unit descriptors)."""
        image_id = self.db.write_features(name, kp, raw)
        self._image_ids[name] = image_id
        return image_id, kp[:, :2].astype(np.float64), desc

    def _match(self, name: str, new) -> None:
        """Match the new keyframe against the previous ``match_window`` ones and the earlier keyframes of the place
        it is expected to look at, and verify each pair's geometry (RANSAC in pycolmap releases the GIL: the pairs
        are verified on two threads)."""
        image_id, xy, desc = new
        pairs = [(prev_id, prev_xy, match_descriptors(prev_desc, desc)) for prev_id, prev_xy, prev_desc in self._recent]
        # a keyframe of the matching window is matched once (a pair written twice breaks the database's constraint)
        recent = {prev_id for prev_id, _, _ in self._recent}
        revisit = [o for o in self._revisit_candidates(name) if self._image_ids[o] not in recent]
        for old in revisit:
            old_id = self._image_ids[old]
            old_xy, old_desc = self.db.read_features(old_id)
            pairs.append((old_id, old_xy, match_descriptors(old_desc, desc)))
        pairs = [p for p in pairs if len(p[2])]
        geoms = self._pool.map(lambda p: pycolmap.estimate_calibrated_two_view_geometry(
            self.db.pcam, p[1], self.db.pcam, xy, p[2], self._two_view), pairs)
        old_of = {self._image_ids[o]: o for o in revisit}
        for (prev_id, _, matches), geom in zip(pairs, geoms):
            self.db.write_pair(prev_id, image_id, matches, geom)
            inl = np.asarray(geom.inlier_matches).reshape(-1, 2)
            if prev_id in old_of and len(inl) >= 30:
                self._revisit_matches.setdefault(name, []).append((old_of[prev_id], inl))
        if name in self._revisit_matches:
            self.revisits += 1
        self._recent.append(new)

    def _revisit_candidates(self, name: str) -> list[str]:
        """Earlier keyframes of other passes that look where the new keyframe should: about where the last registered
        one looked (a keyframe moves a fraction of the view). Once keyframes fail to register (the chain is lost),
        any earlier keyframe beyond the matching window may be the way back."""
        if not self.s.revisit or self._last_place is None:
            return []
        look, axis, depth = self._last_place
        return self.places.near(look, axis, depth, self._order[name],
                                min_gap=self.s.match_window + 1 if self._failing else None)

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        self.db.close()

    # -- mapping
    def _mapper(self, names: list[str]):
        copts = pycolmap.DatabaseCacheOptions()
        copts.min_num_matches = 15
        copts.image_names = set(names)
        cache = pycolmap.DatabaseCache.create(self.db.db, copts)
        return cache, pycolmap.IncrementalMapper(cache)

    def _image_id(self, cache, name):
        for iid, im in cache.images.items():
            if im.name == name:
                return iid
        return None

    def _bootstrap(self, names: list[str]) -> Submodel | None:
        cache, mapper = self._mapper(names)
        rec = pycolmap.Reconstruction()
        mapper.begin_reconstruction(rec)
        mo = self._mopts.get_mapper()
        found = None
        # pycolmap 4.2 finds no pair when both ids are left free (-1, -1); fixing the first works
        for name in names:
            iid = self._image_id(cache, name)
            if iid is not None:
                found = mapper.find_initial_image_pair(mo, iid, -1)
                if found is not None:
                    break
        if found is None:
            mapper.end_reconstruction(True)
            return None
        (i1, i2), cam2_from_cam1 = found
        mapper.register_initial_image_pair(mo, i1, i2, cam2_from_cam1)
        tri = self._mopts.get_triangulation()
        mapper.triangulate_image(tri, i1)
        mapper.triangulate_image(tri, i2)
        mapper.adjust_global_bundle(mo, self._mopts.get_global_bundle_adjustment())
        for name in names:
            iid = self._image_id(cache, name)
            if iid is None or iid in (i1, i2):
                continue
            if mapper.register_next_image(mo, iid):
                mapper.triangulate_image(tri, iid)
        mapper.iterative_global_refinement(3, 0.0005, mo, self._mopts.get_global_bundle_adjustment(), tri, False)
        mapper.end_reconstruction(False)
        sm = Submodel(rec, [n for n in names if self._registered(rec, n)])
        return sm if len(sm.names) >= 3 else None

    @staticmethod
    def _registered(rec, name):
        im = rec.find_image_with_name(name)
        return im is not None and im.has_pose

    def _register_into(self, sm: Submodel, name: str, refine_global: bool) -> bool:
        cache, mapper = self._mapper(sm.names + [name])
        mapper.begin_reconstruction(sm.rec)
        mo, tri = self._mopts.get_mapper(), self._mopts.get_triangulation()
        iid = self._image_id(cache, name)
        ok = iid is not None and mapper.register_next_image(mo, iid)
        if ok:
            mapper.triangulate_image(tri, iid)
            mapper.iterative_local_refinement(self.s.local_refinements, 0.001, mo, self._mopts.get_local_bundle_adjustment(), tri, iid)
            if refine_global:
                self.global_adjustments += 1
                mapper.iterative_global_refinement(self.s.global_refinements, 0.0005, mo, self._mopts.get_global_bundle_adjustment(), tri, False)
        mapper.end_reconstruction(False)
        if ok:
            sm.names.append(name)
        return ok

    def _straight(self, sm: Submodel) -> bool:
        """Whether the sub-model's last ``overlap`` keyframes look within chain_max_turn_deg of the newest one's way."""
        axes = np.array([sm.rec.find_image_with_name(n).cam_from_world().rotation.matrix()[2]
                         for n in sm.names[-self.s.overlap:]])
        return bool((axes @ axes[-1]).min() >= np.cos(np.radians(self.s.chain_max_turn_deg)))

    def _chain(self, new: Submodel, old: Submodel) -> None:
        shared = [n for n in new.names if n in old.names]
        if len(shared) < 3:
            raise RuntimeError(f"sub-models share only {len(shared)} cameras")
        from ground.poses.georeference import fit_similarity

        m_new = np.array([new.rec.find_image_with_name(n).cam_from_world().matrix() for n in shared])
        m_old = np.array([old.rec.find_image_with_name(n).cam_from_world().matrix() for n in shared])
        c_new = -np.einsum("nji,nj->ni", m_new[:, :, :3], m_new[:, :, 3])
        c_old = -np.einsum("nji,nj->ni", m_old[:, :, :3], m_old[:, :, 3])
        # the shared cameras lie on a short, nearly straight stretch: their centres leave the roll about
        # it free, so their orientations take part in the fit (the same fit as georeferencing)
        spread = max(float(np.linalg.norm(c_old - c_old.mean(0), axis=1).mean()), 1e-9)
        to_old = fit_similarity(c_new, c_old, 0.01 * spread, m_new[:, :, :3], m_old[:, :, :3], np.radians(0.05)).similarity
        new.to_first = compose(old.to_first or IDENTITY, to_old)

    def add_keyframe(self, frame: int, image_bgr: np.ndarray,
                     prior: tuple[np.ndarray, np.ndarray, float] | None = None,
                     features: tuple[np.ndarray, np.ndarray] | None = None) -> bool:
        """Register one keyframe; returns whether it has a pose now. ``prior``: where the telemetry puts the camera
        (ENU centre, world(ENU)-to-camera rotation, position sigma in m), which places a new sub-model when the
        chain breaks. ``features``: its SIFT features if they were extracted elsewhere (:class:`SiftExtractor`)."""
        t0 = time.perf_counter()
        name = f"{frame:06d}.jpg"
        if self.work is not None:
            cv2.imwrite(str(self.work / "images" / name), image_bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
        kp, raw, desc = self._sift(image_bgr) if features is None else (*features, unit_descriptors(features[1]))
        t1 = time.perf_counter()
        try:
            self._store(name, frame, kp, raw, desc, prior)
        except Exception as exc:
            if self.work is None or not write_refused(exc):
                raise
            self._forget(name)
            self._to_memory(exc, frame, drop=name)
            self._store(name, frame, kp, raw, desc, prior)
        t2 = time.perf_counter()
        ok = False
        sm = self.submodels[-1] if self.submodels else None
        if sm is None:
            if len(self.names) >= self.s.init_frames:
                sm = self._bootstrap(self.names[-self.s.init_frames * 2:])
                if sm is not None:
                    sm.to_first = IDENTITY
                    self._start(sm)
                    ok = name in sm.names
        else:
            if len(sm.names) >= self.s.submodel_size and (self._straight(sm)
                                                          or len(sm.names) >= 3 * self.s.submodel_size // 2):
                new = self._bootstrap(sm.names[-self.s.overlap:] + [name])
                if new is not None:
                    self._chain(new, sm)
                    self._start(new)
                    ok = name in new.names
                else:
                    ok = self._register_into(sm, name, False)
            else:
                n = len(sm.names)
                ok = self._register_into(sm, name, refine_global=(n % self.s.global_ba_every == 0))
            if ok and name in self.submodels[-1].names:
                self._registered_one(self.submodels[-1], name)
            elif not ok:
                ok = self._rejoin(name)
        self._failing = [] if ok else self._failing + [name]
        self._revisit_matches.pop(name, None)
        if not ok:
            self.failed.append(frame)
        t3 = time.perf_counter()
        self.seconds.append(t3 - t0)
        self.stage_seconds.append((t1 - t0, t2 - t1, t3 - t2))
        return ok

    # -- across passes
    def _start(self, sm: Submodel) -> None:
        """A new sub-model: the one before it is finished (its keyframes' 3-D points kept as anchors for later passes),
        and the oldest leave memory."""
        if self.submodels:
            self._refusable(True, self._keep_anchors, len(self.submodels) - 1, self.submodels[-1])
        self.submodels.append(sm)
        for k in range(len(self.submodels) - self.s.keep_submodels):
            self.offload(k)
        for n in sm.names:
            if n not in self.places:
                self._add_place(sm, n)

    def offload(self, k: int) -> None:
        """Sub-model ``k`` to the folder, out of memory (:meth:`Submodel.offload`); it stays in memory where there
        is no folder, or its disk refuses it."""
        sm = self.submodels[k]
        if sm.rec is not None and self.work is not None:
            self._refusable(False, sm.offload, self.work / "submodels" / str(k))

    def _refusable(self, again: bool, write, *args) -> None:
        """A write to the folder; where its disk refuses it, mapping goes on in memory, and the write is done ``again``
        there (not a sub-model's offload: it stays in memory)."""
        try:
            write(*args)
        except Exception as exc:
            if self.work is None or not write_refused(exc):
                raise
            self._to_memory(exc, self.frame_of.get(self.names[-1], 0) if self.names else 0)
            if again:
                write(*args)

    def _leave_folder(self, exc: BaseException, frame: int) -> None:
        """Nothing more goes to the folder: said once, with the keyframe it happened at."""
        log.error("the mapping folder %s refused a write (%s): mapping goes on in memory from keyframe %d; the "
                  "keyframes' images, the database and the sub-models left to write are not kept there", self.work,
                  exc, frame)
        self.work, self.db_path, self.in_memory_from = None, ":memory:", frame
        self.places.folder = None

    def _to_memory(self, exc: BaseException, frame: int, drop: str | None = None) -> None:
        """The folder's disk refused a write: the database moves into memory (every keyframe but ``drop``, whose
        writes failed part way, with the same ids) and nothing more is written to the folder. Sub-models and anchors
        already written there stay and are read as before."""
        self._leave_folder(exc, frame)
        self.db.to_memory(drop)

    def poses(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """World-to-camera (R, t) of every registered keyframe, in the first sub-model's frame (the latest
        sub-model wins where they overlap)."""
        from ground.poses.georeference import georeference_poses

        out = {}
        for sm in self.submodels:
            m = sm.cam_from_world()
            R, t = georeference_poses(m[:, :, :3], m[:, :, 3], sm.to_first)
            for name, Ri, ti in zip(sm.names, R, t):
                out[self.frame_of[name]] = (Ri, ti)
        return out
