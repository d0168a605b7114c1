"""Incremental registration of keyframes with pycolmap, one keyframe at a time, at a bounded cost.

For each keyframe: SIFT features, matching against the previous ``match_window`` keyframes, then the
incremental mapper registers it into the current sub-model (2D-3D pose), triangulates its new points
and refines locally; a global refinement runs every ``global_ba_every`` keyframes. A sub-model holds
at most ``submodel_size`` keyframes: then a new one is bootstrapped from the last ``overlap`` keyframes
and chained to the previous one by a similarity over the cameras they share. The database cache is
built over the current sub-model only, so the cost per keyframe does not grow with the flight.
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

from ground.matching import match_descriptors, unit_descriptors
from pomar.align import Similarity
from pomar.camera import Camera

log = logging.getLogger(__name__)
# COLMAP's own INFO lines (several per keyframe) would drown the node's progress; warnings still show.
pycolmap.logging.minloglevel = 1


@dataclass
class RegistrationSettings:
    match_window: int = 5
    submodel_size: int = 60
    overlap: int = 10
    global_ba_every: int = 10
    init_frames: int = 6
    first_octave: int = 0
    max_num_features: int = 4096
    # "colmap" (pycolmap's SIFT) or "opencv": OpenCV's takes half the time (0.17 against 0.33 s per
    # 1280x720 keyframe) and the final batch poses are as good, but in the live ground node, where each
    # frame's pose is decided soon after its keyframe registers, it let the model's scale drift (4.5 px
    # median reprojection error of the true apples against 1 px with pycolmap's, on the bundled flight)
    sift: str = "colmap"
    init_min_tri_angle: float = 2.0
    local_refinements: int = 1
    global_refinements: int = 1
    # SIFT without orientation (COLMAP's upright option): consecutive keyframes of a gimbal-stabilised
    # camera barely rotate in the image plane, and skipping orientation saves a quarter of extraction; on
    # the bundled flight it cost some accuracy (true apples 0.99 against 0.83 px after a similarity)
    upright: bool = False
    # Ceres solves a bundle adjustment on one thread below this many residuals. On more threads its sums come in
    # another order each run and a flight's keyframes drift apart between runs; on one, a lock-step replay repeats
    # bit for bit, and the ground is no slower (benchmarks/live_ground.py)
    ba_threads_min_residuals: int = 10**9
    # finished sub-models kept in memory (the newest is chained to the one before it); older ones are written to
    # the work directory and read back only for the final model files
    keep_submodels: int = 2

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


class IncrementalRegistrar:
    def __init__(self, camera: Camera, workdir: str | Path, settings: RegistrationSettings | None = None):
        self.cam, self.s = camera, settings or RegistrationSettings()
        self.work = Path(workdir)
        if self.work.exists():
            shutil.rmtree(self.work)
        (self.work / "images").mkdir(parents=True)
        self.db_path = self.work / "database.db"
        self.names: list[str] = []  # every keyframe, in order
        self.frame_of: dict[str, int] = {}
        self.submodels: list[Submodel] = []
        self.failed: list[int] = []
        self.seconds: list[float] = []
        self.stage_seconds: list[tuple[float, float, float]] = []  # features, matching, mapping
        self._mopts = pycolmap.IncrementalPipelineOptions()
        self._mopts.ba_refine_focal_length = False
        self._mopts.ba_refine_principal_point = False
        self._mopts.ba_refine_extra_params = False
        self._mopts.mapper.init_min_tri_angle = self.s.init_min_tri_angle
        self._mopts.mapper.init_min_num_inliers = 50
        self._mopts.ba_min_num_residuals_for_cpu_multi_threading = self.s.ba_threads_min_residuals
        self._mopts.random_seed = 0  # RANSAC's samples the same each run
        self._open_database()

    # -- features and matches
    def _open_database(self):
        """One database for the flight: the camera and its rig once, then an image and a frame per keyframe."""
        self._db = pycolmap.Database.open(self.db_path)
        self._pcam = pycolmap.Camera(model=self.cam.model, width=self.cam.width, height=self.cam.height,
                                     params=list(self.cam.params()))
        self._camera_id = self._db.write_camera(self._pcam)
        self._pcam.camera_id = self._camera_id
        self._sensor = pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=self._camera_id)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(self._sensor)
        self._rig_id = self._db.write_rig(rig)
        ext = pycolmap.FeatureExtractionOptions()
        ext.sift.first_octave = self.s.first_octave
        ext.sift.max_num_features = self.s.max_num_features
        ext.sift.upright = self.s.upright
        # kept alive for the whole flight: pycolmap's extract_features would rebuild it and re-read the image.
        # The mapper only reads keypoints and verified matches, so either SIFT serves (see RegistrationSettings)
        colmap = self.s.sift == "colmap"
        self._extractor = pycolmap.FeatureExtractor.create(ext, pycolmap.Device.cpu) if colmap else None
        self._cv_sift = None if colmap else cv2.SIFT_create(nfeatures=self.s.max_num_features)
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="two-view")
        self._two_view = pycolmap.TwoViewGeometryOptions()
        self._two_view.ransac.random_seed = 0
        self._recent = deque(maxlen=max(self.s.match_window, 1))  # (image id, keypoint xy, unit descriptors)

    def _extract(self, name: str, image_bgr: np.ndarray):
        gray = np.ascontiguousarray(image_bgr if image_bgr.ndim == 2 else cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY))
        if self._cv_sift is not None:
            kps, raw = self._cv_sift.detectAndCompute(gray, None)
            # OpenCV puts the top-left pixel centre at (0, 0), COLMAP at (0.5, 0.5)
            kp = np.array([k.pt for k in kps], np.float32).reshape(-1, 2) + 0.5
            raw = np.zeros((0, 128), np.float32) if raw is None else raw
            root = np.sqrt(raw / np.maximum(raw.sum(1, keepdims=True), 1e-12))  # RootSIFT, as COLMAP stores it
            descriptors = pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                                      np.clip(np.round(root * 512), 0, 255).astype(np.uint8))
            desc = root.astype(np.float32)
        else:
            keypoints, descriptors = self._extractor.extract_from_uint8_array(gray)
            kp = pycolmap.keypoints_to_matrix(keypoints)
            desc = unit_descriptors(descriptors.data)
        image_id = self._db.write_image(pycolmap.Image(name=name, camera_id=self._camera_id))
        frame = pycolmap.Frame(rig_id=self._rig_id)
        frame.add_data_id(pycolmap.data_t(sensor_id=self._sensor, id=image_id))
        self._db.write_frame(frame)
        self._db.write_keypoints(image_id, kp)
        self._db.write_descriptors(image_id, descriptors)
        return image_id, kp[:, :2].astype(np.float64), desc

    def _match(self, new) -> None:
        """Match the new keyframe against the previous ``match_window`` ones and verify each pair's geometry
        (RANSAC in pycolmap releases the GIL: the pairs are verified on two threads)."""
        image_id, xy, desc = new
        pairs = [(prev_id, prev_xy, match_descriptors(prev_desc, desc)) for prev_id, prev_xy, prev_desc in self._recent]
        pairs = [p for p in pairs if len(p[2])]
        geoms = self._pool.map(lambda p: pycolmap.estimate_calibrated_two_view_geometry(
            self._pcam, p[1], self._pcam, xy, p[2], self._two_view), pairs)
        for (prev_id, _, matches), geom in zip(pairs, geoms):
            self._db.write_matches(prev_id, image_id, matches)
            self._db.write_two_view_geometry(prev_id, image_id, geom)
        self._recent.append(new)

    def close(self) -> None:
        self._pool.shutdown(wait=True)
        self._db.close()

    # -- mapping
    def _mapper(self, names: list[str]):
        copts = pycolmap.DatabaseCacheOptions()
        copts.min_num_matches = 15
        copts.image_names = set(names)
        cache = pycolmap.DatabaseCache.create(self._db, copts)
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
                mapper.iterative_global_refinement(self.s.global_refinements, 0.0005, mo, self._mopts.get_global_bundle_adjustment(), tri, False)
        mapper.end_reconstruction(False)
        if ok:
            sm.names.append(name)
        return ok

    def _chain(self, new: Submodel, old: Submodel) -> None:
        shared = [n for n in new.names if n in old.names]
        if len(shared) < 3:
            raise RuntimeError(f"sub-models share only {len(shared)} cameras")
        from ground.georeference import fit_similarity

        m_new = np.array([new.rec.find_image_with_name(n).cam_from_world().matrix() for n in shared])
        m_old = np.array([old.rec.find_image_with_name(n).cam_from_world().matrix() for n in shared])
        c_new = -np.einsum("nji,nj->ni", m_new[:, :, :3], m_new[:, :, 3])
        c_old = -np.einsum("nji,nj->ni", m_old[:, :, :3], m_old[:, :, 3])
        # the shared cameras lie on a short, nearly straight stretch: their centres leave the roll about
        # it free, so their orientations take part in the fit (the same fit as georeferencing)
        spread = max(float(np.linalg.norm(c_old - c_old.mean(0), axis=1).mean()), 1e-9)
        to_old = fit_similarity(c_new, c_old, 0.01 * spread, m_new[:, :, :3], m_old[:, :, :3], np.radians(0.05)).similarity
        first = old.to_first or Similarity(1.0, np.eye(3), np.zeros(3))
        new.to_first = Similarity(first.scale * to_old.scale, first.R @ to_old.R, first.scale * first.R @ to_old.t + first.t)

    def add_keyframe(self, frame: int, image_bgr: np.ndarray) -> bool:
        """Register one keyframe; returns whether it has a pose now."""
        t0 = time.perf_counter()
        name = f"{frame:06d}.jpg"
        cv2.imwrite(str(self.work / "images" / name), image_bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
        features = self._extract(name, image_bgr)
        t1 = time.perf_counter()
        self.names.append(name)
        self.frame_of[name] = frame
        self._match(features)
        t2 = time.perf_counter()
        ok = False
        sm = self.submodels[-1] if self.submodels else None
        if sm is None:
            if len(self.names) >= self.s.init_frames:
                sm = self._bootstrap(self.names[-self.s.init_frames * 2:])
                if sm is not None:
                    sm.to_first = Similarity(1.0, np.eye(3), np.zeros(3))
                    self.submodels.append(sm)
                    ok = name in sm.names
        else:
            if len(sm.names) >= self.s.submodel_size:
                new = self._bootstrap(sm.names[-self.s.overlap:] + [name])
                if new is not None:
                    self._chain(new, sm)
                    self.submodels.append(new)
                    ok = name in new.names
                    for k, old in enumerate(self.submodels[:-self.s.keep_submodels]):
                        if old.rec is not None:
                            old.offload(self.work / "submodels" / str(k))
                else:
                    ok = self._register_into(sm, name, False)
            else:
                n = len(sm.names)
                ok = self._register_into(sm, name, refine_global=(n % self.s.global_ba_every == 0))
        if not ok:
            self.failed.append(frame)
        t3 = time.perf_counter()
        self.seconds.append(t3 - t0)
        self.stage_seconds.append((t1 - t0, t2 - t1, t3 - t2))
        return ok

    def poses(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """World-to-camera (R, t) of every registered keyframe, in the first sub-model's frame (the latest
        sub-model wins where they overlap)."""
        from ground.georeference import georeference_poses

        out = {}
        for sm in self.submodels:
            m = sm.cam_from_world()
            R, t = georeference_poses(m[:, :, :3], m[:, :, 3], sm.to_first)
            for name, Ri, ti in zip(sm.names, R, t):
                out[self.frame_of[name]] = (Ri, ti)
        return out
