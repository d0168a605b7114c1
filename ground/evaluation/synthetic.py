"""Synthetic association inputs with a known answer: a camera flying along a row of apples.

No rendering: apples are points, detections their exact projections (plus jitter, misses, false
positives as asked). For tests and benchmarks of the association (long sequences, many detections).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ground.apples.association import FrameDetections
from pomar.camera import Camera
from pomar.rotations import R_GIMBAL_FROM_CAMERA_NOMINAL, camera_from_gimbal_attitude, ned_euler_to_rotation, world_to_camera


@dataclass
class SyntheticSequence:
    frames: list[FrameDetections]
    apples: np.ndarray  # (A, 3) true positions
    sources: list[np.ndarray]  # per frame, the apple index of each detection (-1 = false positive)
    camera: Camera


def camera_path(n_frames: int, step_m: float = 0.2, altitude_m: float = 12.0, tilt_deg: float = 30.0):
    """World-to-camera poses of a drone flying north along y, camera looking east, tilted off nadir."""
    y = np.arange(n_frames) * step_m
    centres = np.stack([np.zeros(n_frames), y, np.full(n_frames, altitude_m)], 1)
    rot = ned_euler_to_rotation(np.zeros(n_frames), np.full(n_frames, -(90.0 - tilt_deg)), np.full(n_frames, 90.0))
    return world_to_camera(camera_from_gimbal_attitude(rot, R_GIMBAL_FROM_CAMERA_NOMINAL), centres)


def apples_along(length_m: float, n: int, rng: np.random.Generator, across=(5.0, 11.0), height=(0.8, 3.0)):
    return np.stack([rng.uniform(*across, n), rng.uniform(-5.0, length_m + 5.0, n), rng.uniform(*height, n)], 1)


def make_sequence(n_frames: int = 50, apples: np.ndarray | None = None, n_apples: int = 20, noise_px: float = 0.0,
                  miss: float = 0.0, fp_per_frame: float = 0.0, step_m: float = 0.2, width: int = 1280, height: int = 720,
                  hfov_deg: float = 50.0, seed: int = 0, max_per_frame: int | None = None) -> SyntheticSequence:
    rng = np.random.default_rng(seed)
    cam = Camera.from_fov(width, height, hfov_deg)
    R, t = camera_path(n_frames, step_m)
    if apples is None:
        apples = apples_along(n_frames * step_m, n_apples, rng)
    frames, sources = [], []
    for i in range(n_frames):
        uv, z = cam.project(apples, R[i], t[i])
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= height - 1)
        idx = np.nonzero(inside & (rng.random(len(apples)) >= miss))[0]
        if max_per_frame is not None:
            idx = idx[:max_per_frame]
        xy = uv[idx] + rng.normal(0, noise_px, (len(idx), 2)) if noise_px else uv[idx]
        nfp = rng.poisson(fp_per_frame) if fp_per_frame else 0
        xy = np.concatenate([xy, rng.uniform([0, 0], [width - 1, height - 1], (nfp, 2))])
        frames.append(FrameDetections(i, cam.projection_matrix(R[i], t[i]), xy))
        sources.append(np.concatenate([idx, np.full(nfp, -1)]))
    return SyntheticSequence(frames, apples, sources, cam)
