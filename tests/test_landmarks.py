"""Placing a frame by the mapped apples it sees (ground.apples.landmarks), on a synthetic row."""

from __future__ import annotations

import numpy as np

from ground.apples.landmarks import place_by_apples
from ground.poses.georeference import Pose
from pomar.camera import Camera


def _pose(frame: int, x: float) -> Pose:
    """A camera at (x, 0, 0) looking along +y (world to camera), moving along the row."""
    R = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    return Pose(frame, R, -R @ np.array([x, 0.0, 0.0]), "tracked", 0.02, 0.1)


def test_a_frame_is_placed_by_the_apples_it_sees_and_left_alone_where_they_do_not_agree():
    rng = np.random.default_rng(0)
    cam = Camera.from_fov(1280, 720, 70.0)
    apples = np.column_stack([rng.uniform(-2, 3, 80), rng.uniform(3, 5, 80), rng.uniform(-1.5, 1.5, 80)])
    before, last, truth = _pose(0, 0.0), _pose(1, 0.10), _pose(2, 0.21)  # a little faster than predicted
    uv, z = cam.project(apples, truth.R, truth.t)
    seen = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 1280) & (uv[:, 1] >= 0) & (uv[:, 1] < 720)
    centres = uv[seen] + rng.normal(0, 0.5, (seen.sum(), 2))
    R, t = place_by_apples(cam, centres, apples, before, last)
    assert np.linalg.norm(-R.T @ t - truth.centre) < 0.01, -R.T @ t
    assert np.degrees(np.arccos(np.clip((np.trace(R @ truth.R.T) - 1) / 2, -1, 1))) < 0.1
    # too few apples in view, or detections that lie nowhere near where the mapped apples would be
    assert place_by_apples(cam, centres[:5], apples, before, last) is None
    assert place_by_apples(cam, centres + 60.0, apples, before, last) is None
