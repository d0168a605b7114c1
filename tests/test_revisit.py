"""Places seen again (ground/poses/revisit.py): the keyframe index and the robust similarity, on numbers whose answer is
known."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ground.poses.revisit import Places, robust_similarity
from pomar.align import Similarity


def test_near_finds_earlier_keyframes_of_the_same_place_only(tmp_path):
    p = Places(tmp_path, radius=0.2, max_angle_deg=40, min_gap=5)
    down = np.array([0.0, 0.5, -1.0]) / np.linalg.norm([0.0, 0.5, -1.0])
    back = down * [1, -1, 1]  # the other side of the row
    for k in range(20):
        p.add(f"a{k}", k, np.array([0.0, k * 1.0, 0.0]), down)  # one pass along y
    p.add("b0", 20, np.array([0.0, 3.0, 0.0]), back)
    # a keyframe of a later pass looking at y = 3.2 from the same side, 14 m away: within 0.2 * 14 = 2.8 m
    near = p.near(np.array([0.5, 3.2, 0.0]), down, 14.0, order=30)
    assert near[0] == "a3" and len(near) == 2 and set(near) <= {"a2", "a3", "a4", "a5"}
    assert "b0" not in p.near(np.array([0.0, 3.0, 0.0]), down, 14.0, order=30)  # looks the other way
    assert p.near(np.array([0.0, 50.0, 0.0]), down, 14.0, order=30) == []  # nowhere near
    # the 5 keyframes before it are the chain's, already matched: the nearest earlier one is a16, not a18
    assert p.near(np.array([0.0, 18.0, 0.0]), down, 14.0, order=21) == ["a16"]


def test_anchors_come_back_from_disk(tmp_path):
    p = Places(tmp_path)
    X = np.random.default_rng(0).normal(size=(7, 3))
    p.keep_anchors(3, {"k1": (np.arange(7) * 2, X), "k2": (np.zeros(0, int), np.zeros((0, 3)))})
    k, idx, Xb = p.anchors("k1")
    assert k == 3 and idx.tolist() == list(range(0, 14, 2)) and np.allclose(Xb, X, atol=1e-6)
    assert len(p.anchors("k2")[1]) == 0 and p.anchors("nope") is None
    assert (tmp_path / "3.npz").exists()


def test_robust_similarity_recovers_the_transform_through_outliers():
    rng = np.random.default_rng(1)
    true = Similarity(1.3, Rotation.from_euler("xyz", [3, -2, 40], degrees=True).as_matrix(), np.array([2.0, -1.0, 0.5]))
    src = rng.uniform(-5, 5, size=(200, 3))
    dst = true.apply(src) + rng.normal(scale=0.005, size=(200, 3))
    bad = rng.choice(200, 60, replace=False)
    dst[bad] += rng.uniform(-3, 3, size=(60, 3))  # 30 % false matches
    S, inl = robust_similarity(src, dst, tol=0.05)
    assert abs(S.scale - 1.3) < 1e-3 and np.allclose(S.R, true.R, atol=1e-3) and np.allclose(S.t, true.t, atol=0.01)
    assert not inl[bad].any() and inl.sum() >= 135
    assert robust_similarity(src[:2], dst[:2], tol=0.05) is None
