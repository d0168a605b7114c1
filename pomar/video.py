"""Small video helpers over OpenCV (needs opencv-python-headless)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pomar.cli import InputError


class VideoError(InputError, ValueError):
    """A video cannot be opened or a frame cannot be decoded."""


def _open(path):
    import cv2

    path = Path(path)
    if not path.exists():
        raise VideoError(f"{path}: file not found")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise VideoError(f"{path}: OpenCV cannot open this video")
    return cap


def video_size(path) -> tuple[int, int]:
    """(width, height) of the video's first frame; VideoError when none decodes."""
    cap = _open(path)
    try:
        ok, img = cap.read()
    finally:
        cap.release()
    if not ok or img is None:
        raise VideoError(f"{path}: OpenCV opens it, but no frame decodes")
    return img.shape[1], img.shape[0]


def video_info(path) -> tuple[float, int, int, int]:
    """(fps, frame count, width, height) as the container says; VideoError when it gives no frame rate."""
    import cv2

    cap = _open(path)
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    finally:
        cap.release()
    if not (np.isfinite(fps) and 0 < fps < 1000):
        raise VideoError(f"{path}: the container gives no frame rate ({fps})")
    if n <= 0 or w <= 0 or h <= 0:
        raise VideoError(f"{path}: the container gives no frame count or size")
    return fps, n, w, h


def count_frames(path) -> int:
    """Number of frames that actually decode (not the container's claim)."""
    cap = _open(path)
    n = 0
    try:
        while cap.grab():
            n += 1
    finally:
        cap.release()
    return n


def read_frame(path, index: int) -> np.ndarray:
    """Decode frame `index` (BGR)."""
    cap = _open(path)
    try:
        for _ in range(index):
            if not cap.grab():
                raise VideoError(f"{path}: has fewer than {index + 1} frames")
        ok, img = cap.read()
        if not ok:
            raise VideoError(f"{path}: frame {index} does not decode (video has {index} frames or is truncated)")
        return img
    finally:
        cap.release()


def iter_frames(path):
    """Yield (index, BGR frame) for every decodable frame."""
    cap = _open(path)
    i = 0
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                return
            yield i, img
            i += 1
    finally:
        cap.release()
