"""SIFT features of a keyframe, as the registration's settings ask (pycolmap's, or OpenCV's)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np
import pycolmap

from ground.poses.matching import unit_descriptors

if TYPE_CHECKING:
    from ground.poses.registration import RegistrationSettings


class SiftExtractor:
    """SIFT as the registration's settings ask (pycolmap's, or OpenCV's), kept alive for the whole flight (pycolmap's
    extract_features would rebuild it and re-read the image). Called with an image: (keypoints (n, >= 2) float32 in
    COLMAP pixels, descriptors (n, 128) uint8 as COLMAP stores them, unit float32 descriptors for matching). The
    mapper only reads keypoints and verified matches, so either SIFT serves (see RegistrationSettings)."""

    def __init__(self, settings: RegistrationSettings):
        ext = pycolmap.FeatureExtractionOptions()
        ext.sift.first_octave = settings.first_octave
        ext.sift.max_num_features = settings.max_num_features
        ext.sift.upright = settings.upright
        colmap = settings.sift == "colmap"
        self._extractor = pycolmap.FeatureExtractor.create(ext, pycolmap.Device.cpu) if colmap else None
        self._cv_sift = None if colmap else cv2.SIFT_create(nfeatures=settings.max_num_features)
        self.width = settings.sift_width

    def __call__(self, image_bgr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        gray = np.ascontiguousarray(image_bgr if image_bgr.ndim == 2 else cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY))
        h, w = gray.shape
        if not self.width or w <= self.width:
            return self._extract(gray)
        small = cv2.resize(gray, (self.width, max(1, round(h * self.width / w))), interpolation=cv2.INTER_AREA)
        kp, raw, unit = self._extract(small)
        # COLMAP's pixels start at the image's corner, so a resize scales the coordinates (and SIFT's scale) alike
        kp = kp.copy()
        kp[:, :2] *= np.array([w / small.shape[1], h / small.shape[0]], np.float32)
        kp[:, 2:3] *= w / small.shape[1]  # pycolmap's (x, y, scale, orientation); OpenCV's are (x, y)
        return kp, raw, unit

    def _extract(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self._cv_sift is not None:
            kps, raw = self._cv_sift.detectAndCompute(gray, None)
            # OpenCV puts the top-left pixel centre at (0, 0), COLMAP at (0.5, 0.5)
            kp = np.array([k.pt for k in kps], np.float32).reshape(-1, 2) + 0.5
            raw = np.zeros((0, 128), np.float32) if raw is None else raw
            root = np.sqrt(raw / np.maximum(raw.sum(1, keepdims=True), 1e-12))  # RootSIFT, as COLMAP stores it
            return kp, np.clip(np.round(root * 512), 0, 255).astype(np.uint8), root.astype(np.float32)
        keypoints, descriptors = self._extractor.extract_from_uint8_array(gray)
        raw = np.asarray(descriptors.data)
        return pycolmap.keypoints_to_matrix(keypoints), raw, unit_descriptors(raw)
