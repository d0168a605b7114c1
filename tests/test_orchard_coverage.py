"""What each tree's canopy showed the camera (pomar/coverage.py), on a made-up orchard whose answer follows
from its geometry: a camera beside two rows, looking across them, sees the near face of the near row and nothing of
the far row, which the near one hides."""

from __future__ import annotations

import numpy as np

from pomar.coverage import SURFACE_POINTS, Sight, row_coverage, tree_coverage
from pomar.camera import Camera


def _orchard(rng):
    """Rows 1 (x = 0) and 2 (x = 4) along y, 10 m long, a tree a metre from 0.5 m; 60 apples each, 1-3 m up."""
    rows = [{"row": r, "start_x": x, "start_y": 0.0, "end_x": x, "end_y": 10.0} for r, x in ((1, 0.0), (2, 4.0))]
    trees = [{"row": r["row"], "tree": k + 1, "along_m": k + 0.5, "x": r["start_x"], "y": k + 0.5}
             for r in rows for k in range(10)]
    n = 60
    row = np.repeat([1, 2], n)
    apples = {"id": np.arange(2 * n), "row": row, "x": np.where(row == 1, 0.0, 4.0) + rng.uniform(-0.6, 0.6, 2 * n),
              "y": rng.uniform(0, 10, 2 * n), "z": rng.uniform(1.0, 3.0, 2 * n), "radius_m": np.full(2 * n, 0.04)}
    return rows, trees, apples


def _cameras(ys, x=-6.0, z=2.0):
    """Cameras at (x, y, z) looking along +x (east), level: ENU-to-camera rotation rows right, down, forward."""
    from scipy.spatial.transform import Rotation

    R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    q = Rotation.from_matrix(np.repeat(R[None], len(ys), 0)).as_quat()  # xyzw
    n = len(ys)
    return {"frame": np.arange(n), "x": np.full(n, x), "y": np.asarray(ys, float), "z": np.full(n, z),
            "qw": q[:, 3], "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2]}


def test_a_camera_beside_the_rows_sees_the_near_face_of_the_near_row_only():
    rows, trees, apples = _orchard(np.random.default_rng(0))
    cam = Camera.from_fov(640, 360, 60.0)
    got = tree_coverage(trees, rows, apples, _cameras(np.linspace(0, 10, 41)), Sight(cam))
    near, far = got[:10], got[10:]
    # the near row's west face, whole for the trees the camera passed in front of; its east face faces away
    assert all(g["sides_seen"] == 1 for g in near[1:-1]) and all(abs(g["coverage"] - 0.5) < 1e-9 for g in near[1:-1])
    assert all(g["frames_seen"] > 0 and 4.5 < g["range_m"] < 8.0 for g in near)
    assert all(g["angle_deg"] < 45 for g in near[2:-2])  # looked at face on
    # the far row: its west face is behind the near row's canopy, its east face turned away
    assert all(g["coverage"] == 0 and g["sides_seen"] == 0 and g["frames_seen"] == 0 for g in far)
    row_coverage(rows, [{**t, **g} for t, g in zip(trees, got)])
    assert 0.4 < rows[0]["coverage"] <= 0.5 and rows[1]["coverage"] == 0


def test_from_above_the_far_row_shows_over_the_near_one_unless_its_apples_are_too_small_for_the_detector():
    """A camera 8 m up, 2 m west of the near row, pitched 45 degrees down: its rays to the far row's west face pass
    high over the near row's top, so that face is seen. At a detector scale that makes the apples smaller than the
    drone's detector finds (min_apple_radius_px), nothing is seen."""
    from scipy.spatial.transform import Rotation

    rows, trees, apples = _orchard(np.random.default_rng(1))
    cam = Camera.from_fov(640, 360, 60.0)
    cams = _cameras(np.linspace(0, 10, 41), x=-2.0, z=8.0)
    down = Rotation.from_euler("x", 45, degrees=True)  # the camera pitched down about its own x axis
    R = down.as_matrix() @ Rotation.from_quat(np.column_stack([cams["qx"], cams["qy"], cams["qz"], cams["qw"]])).as_matrix()
    assert R[0, 2, 2] < -0.5  # it looks down
    q = Rotation.from_matrix(R).as_quat()
    cams.update(qw=q[:, 3], qx=q[:, 0], qy=q[:, 1], qz=q[:, 2])
    got = tree_coverage(trees, rows, apples, cams, Sight(cam))
    far = got[12:18]
    assert all(abs(g["coverage"] - 0.5) < 1e-9 and g["sides_seen"] == 1 for g in far), far
    assert all(30 < g["angle_deg"] < 60 for g in far)  # seen 45 degrees down onto a vertical face
    small = tree_coverage(trees, rows, apples, cams, Sight(cam, min_px=5.0, scales={f: 0.05 for f in range(41)}))
    assert all(g["coverage"] == 0 for g in small)
    assert len(got) == 20 and SURFACE_POINTS == 9


def test_a_row_without_apples_takes_the_orchards_canopy_not_the_other_rows_apples():
    """The far row's apples all unseen (none mapped): its hedge is the near row's, where it stands, so the near row
    still hides it; before, its faces were placed by the near row's apples, metres away, and showed."""
    rows, trees, apples = _orchard(np.random.default_rng(0))
    near = apples["row"] == 1
    apples = {k: v[near] for k, v in apples.items()}
    cam = Camera.from_fov(640, 360, 60.0)
    got = tree_coverage(trees, rows, apples, _cameras(np.linspace(0, 10, 41)), Sight(cam))
    assert all(g["coverage"] == 0 for g in got[10:]) and all(g["coverage"] > 0 for g in got[1:9])
