"""Placing a restarted mapper's model in the old map's frame (ground.poses.restart)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ground.poses.restart import align_models, move_pose, move_reference
from ground.poses.tracking import Reference
from pomar.align import Similarity


def _poses(centres, rng):
    """World-to-camera poses at ``centres`` with random orientations."""
    out = {}
    for f, c in enumerate(centres):
        R = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        out[f] = (R, -R @ c)
    return out


def test_a_straight_flight_is_placed_by_orientations_and_centres():
    """Keyframes on a straight line: their centres alone leave the roll about the line free; with the orientations
    the similarity is recovered exactly, and the moved poses are the old ones."""
    rng = np.random.default_rng(0)
    old = _poses(np.c_[np.linspace(0, 3, 6), np.zeros(6), np.full(6, 10.0)], rng)
    S_true = Similarity(0.6, Rotation.from_rotvec([0.2, -1.0, 0.4]).as_matrix(), np.array([1.0, -2.0, 0.5]))
    inv_scale = 1 / S_true.scale
    # the new model's frame: x_old = S(x_new), so a pose there is the old one moved by S's inverse
    new = {}
    for f, (R, t) in old.items():
        Rn = R @ S_true.R
        new[f] = (Rn, inv_scale * (t + R @ S_true.t))
    S, info = align_models(old, new)
    assert np.isclose(S.scale, 0.6) and np.allclose(S.R, S_true.R) and np.allclose(S.t, S_true.t)
    assert info["keyframes"] == 6 and info["centre_residual_max"] < 1e-9 and info["rotation_residual_max_deg"] < 1e-4
    for f in old:
        R2, t2 = move_pose(S, *new[f])
        assert np.allclose(R2, old[f][0]) and np.allclose(t2, old[f][1])
    X_old = rng.normal(0, 1, (5, 3))
    X_new = (X_old - S_true.t) @ S_true.R / S_true.scale
    ref = Reference(frame=3, grey=np.zeros((2, 2), np.uint8), xy=np.zeros((5, 2)), X=X_new, R=new[3][0], t=new[3][1])
    moved = move_reference(S, ref)
    assert np.allclose(moved.X, X_old) and np.allclose(moved.R, old[3][0]) and np.allclose(moved.t, old[3][1])
    # each reprojects the same: the camera sees the same points either way
    assert np.allclose((moved.X @ moved.R.T + moved.t) / S.scale, X_new @ ref.R.T + ref.t)


def test_too_few_shared_keyframes_or_one_place_give_no_placement():
    rng = np.random.default_rng(1)
    old = _poses(rng.normal(0, 1, (5, 3)), rng)
    assert align_models(old, {f: old[f] for f in (0, 1)}) is None
    assert align_models(old, {f + 10: p for f, p in old.items()}) is None
    same_place = _poses(np.zeros((4, 3)), rng)
    assert align_models(same_place, same_place) is None


def test_half_a_result_left_by_a_killed_mapping_process_does_not_hold_the_ground():
    """A mapping process killed while it wrote a result leaves part of a message in the pipe. Reading the queue waits
    for the rest for ever (the ground froze for 10 minutes so, 1 run in 2); the ground reads what a thread received."""
    import os
    import queue
    import struct
    import time

    import pytest

    from ground.poses.mapper_process import MappingWorker

    w = MappingWorker()
    try:
        # a 1 MB message's header and its first kilobyte, as a process killed mid-write leaves them
        os.write(w.results._writer.fileno(), struct.pack("!i", 1_000_000) + b"x" * 1000)
        t0 = time.monotonic()
        with pytest.raises(queue.Empty):
            w.inbox.get(timeout=1.0)
        assert time.monotonic() - t0 < 3
    finally:
        w.stop()
