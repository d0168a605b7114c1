"""The flight's keyframe database (pycolmap's): the camera and its rig once, then each keyframe's SIFT features and
its verified matches, which the incremental mapper reads. In the mapping folder, or in memory; a folder whose disk
refuses a write (full, read-only) hands its database over to memory (:meth:`KeyframeDatabase.to_memory`)."""

from __future__ import annotations

import errno

import numpy as np
import pycolmap

from ground.poses.matching import unit_descriptors
from pomar.camera import Camera

#: errnos of a write the folder refuses: full, a file or quota limit, read-only (or not ours), failing.
_REFUSED = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO}
#: SQLite's words (through pycolmap) for the same.
_SQLITE_REFUSED = ("disk is full", "disk I/O error", "readonly database", "unable to open database")


def write_refused(exc: BaseException) -> bool:
    """Whether an error is the disk refusing a write (a full disk, a file size or quota limit, a folder or disk that
    is read-only, a failing disk), from the OS or from SQLite through pycolmap."""
    if isinstance(exc, OSError):
        return exc.errno in _REFUSED
    return any(w in str(exc) for w in _SQLITE_REFUSED)


class KeyframeDatabase:
    """One database for the flight at ``path`` (``":memory:"``: in memory); ``db`` is pycolmap's, for the mapper."""

    def __init__(self, camera: Camera, path: str):
        self.path = path
        self.db = pycolmap.Database.open(str(path))
        self.pcam = pycolmap.Camera(model=camera.model, width=camera.width, height=camera.height,
                                    params=list(camera.params()))
        # known, not to be estimated: COLMAP estimates the focal length of a camera without a prior when it places an
        # image in a reconstruction where no image of that camera is placed yet, whatever the options say. Live, a
        # sub-model that took one 3-12 % off the calibration put every frame tracked against it 0.3 m off along the view
        self.pcam.has_prior_focal_length = True
        self._camera_id = self.db.write_camera(self.pcam)
        self.pcam.camera_id = self._camera_id
        self._sensor = pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=self._camera_id)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(self._sensor)
        self._rig_id = self.db.write_rig(rig)

    def write_features(self, name: str, kp: np.ndarray, raw: np.ndarray) -> int:
        """A keyframe's image, frame, keypoints and descriptors (as COLMAP stores them); its image id."""
        descriptors = pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT, raw)
        image_id = self.db.write_image(pycolmap.Image(name=name, camera_id=self._camera_id))
        frame = pycolmap.Frame(rig_id=self._rig_id)
        frame.add_data_id(pycolmap.data_t(sensor_id=self._sensor, id=image_id))
        self.db.write_frame(frame)
        self.db.write_keypoints(image_id, kp)
        self.db.write_descriptors(image_id, descriptors)
        return image_id

    def read_features(self, image_id: int) -> tuple[np.ndarray, np.ndarray]:
        """A stored keyframe's keypoint xy (float64) and unit descriptors, for matching."""
        desc = unit_descriptors(self.db.read_descriptors(image_id).data)
        return self.db.read_keypoints(image_id)[:, :2].astype(np.float64), desc

    def write_pair(self, a: int, b: int, matches: np.ndarray, geometry) -> None:
        """Two keyframes' matches and their verified two-view geometry."""
        self.db.write_matches(a, b, matches)
        self.db.write_two_view_geometry(a, b, geometry)

    def to_memory(self, drop: str | None = None) -> None:
        """Move the database into memory: every keyframe but ``drop`` (whose writes failed part way), with the same
        ids."""
        src = self.db
        images = src.read_all_images()
        dst = pycolmap.Database.open(":memory:")
        for cam in src.read_all_cameras():
            dst.write_camera(cam, use_camera_id=True)
        for rig in src.read_all_rigs():
            dst.write_rig(rig, use_rig_id=True)
        # a keyframe whose writes failed part way is left out
        kept = {im.image_id for im in images if im.name != drop and src.exists_descriptors(im.image_id)}
        for fr in src.read_all_frames():  # each image's frame first: writing an image checks that it is there
            if all(d.id in kept for d in fr.data_ids):
                dst.write_frame(fr, use_frame_id=True)
        for im in images:
            if im.image_id in kept:
                dst.write_image(im, use_image_id=True)
                dst.write_keypoints(im.image_id, src.read_keypoints(im.image_id))
                dst.write_descriptors(im.image_id, src.read_descriptors(im.image_id))
        for pair_id, matches in zip(*src.read_all_matches()):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            if a in kept and b in kept:
                dst.write_matches(a, b, matches)
        for pair_id, geom in zip(*src.read_two_view_geometries()):
            a, b = pycolmap.pair_id_to_image_pair(pair_id)
            if a in kept and b in kept:
                dst.write_two_view_geometry(a, b, geom)
        src.close()
        self.db, self.path = dst, ":memory:"

    def close(self) -> None:
        self.db.close()
