import numpy as np
import pycolmap

from ground.poses.matching import match_descriptors, unit_descriptors


def planted(seed=0, n=300, extra=200, noise=0.05):
    rng = np.random.default_rng(seed)
    b = unit_descriptors(np.abs(rng.normal(size=(n + extra, 128))))
    pick = rng.permutation(n + extra)[:n]
    a = unit_descriptors(b[pick] + noise * np.abs(rng.normal(size=(n, 128))))
    a = np.vstack([a, unit_descriptors(np.abs(rng.normal(size=(extra, 128))))])  # unmatched distractors
    return a, b, pick


def test_planted_correspondences_found_and_distractors_left():
    a, b, pick = planted()
    m = match_descriptors(a, b)
    truth = {(i, int(j)) for i, j in enumerate(pick)}
    found = set(map(tuple, m.tolist()))
    assert len(found & truth) >= 0.95 * len(truth)
    assert all(i < len(pick) for i, _ in found)  # no distractor row matched
    assert len(set(m[:, 1].tolist())) == len(m)  # cross-checked: one-to-one


def test_ratio_test_rejects_ambiguous():
    a, b, _ = planted(n=50, extra=0)
    b2 = np.vstack([b, b])  # every descriptor twice: best and second are equal
    assert len(match_descriptors(a, b2)) == 0
    assert len(match_descriptors(a, b2, max_ratio=1.01, cross_check=False)) > 0


def test_agrees_with_colmap_matcher():
    a, b, _ = planted(seed=3, n=200, extra=100, noise=0.08)
    to_u8 = lambda d: pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                                  np.clip(np.round(d * 512), 0, 255).astype(np.uint8))
    da, db = to_u8(a), to_u8(b)
    ours = set(map(tuple, match_descriptors(unit_descriptors(da.data), unit_descriptors(db.data)).tolist()))
    theirs = set(map(tuple, pycolmap.FeatureMatcher.create(pycolmap.FeatureMatchingOptions(), pycolmap.Device.cpu)
                     .match(None, da, None, db).tolist()))
    assert len(theirs) > 100
    assert len(ours & theirs) >= 0.97 * max(len(ours), len(theirs))


def test_empty_inputs():
    assert match_descriptors(np.zeros((0, 128), np.float32), np.ones((5, 128), np.float32)).shape == (0, 2)
    assert match_descriptors(np.ones((5, 128), np.float32), np.ones((1, 128), np.float32)).shape == (0, 2)
