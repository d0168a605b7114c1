"""Georeferencing: GPS alone leaves the roll about a straight flight line free; the telemetry's camera
axes fix it."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ground.poses.georeference import drift_offsets, fit_similarity, georeference_poses
from ground.evaluation.synthetic import camera_path
from pomar.align import Similarity


def rotation_error_deg(Ra, Rb):
    return np.degrees(np.linalg.norm(Rotation.from_matrix(np.einsum("nij,nkj->nik", Ra, Rb)).as_rotvec(), axis=1))


def test_axes_fix_the_roll_that_gps_leaves_free():
    rng = np.random.default_rng(0)
    R_true, t_true = camera_path(120, step_m=0.3)  # a straight line along y, ENU
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    # the model: an unknown similarity away from ENU
    S = Similarity(0.37, Rotation.from_euler("xyz", [40, -70, 120], degrees=True).as_matrix(), np.array([3.0, -1.0, 2.0]))
    c_model = (C_true - S.t) @ S.R / S.scale  # S^-1(C) = R^T (C - t) / s, as rows
    R_model = R_true @ S.R  # world(model)-to-camera
    t_model = -np.einsum("nij,nj->ni", R_model, c_model)
    gps = C_true + rng.normal(0, 1.0, C_true.shape)
    R_tel = Rotation.from_rotvec(rng.normal(0, np.radians(0.5), (120, 3))).as_matrix() @ R_true
    only_gps = fit_similarity(c_model, gps, 1.0)
    both = fit_similarity(c_model, gps, 1.0, R_model, R_tel, np.radians(0.5))
    for fit, bound in ((both, 0.3),):
        R_enu, t_enu = georeference_poses(R_model, t_model, fit.similarity)
        assert np.median(rotation_error_deg(R_enu, R_true)) < bound
        C = -np.einsum("nji,nj->ni", R_enu, t_enu)
        assert np.median(np.linalg.norm(C - C_true, axis=1)) < 0.5
        assert abs(fit.similarity.scale - S.scale) / S.scale < 0.02
    R_enu, _ = georeference_poses(R_model, t_model, only_gps.similarity)
    assert np.median(rotation_error_deg(R_enu, R_true)) > 3 * np.median(
        rotation_error_deg(georeference_poses(R_model, t_model, both.similarity)[0], R_true))


def test_a_heading_taken_from_the_track_gives_only_which_way_is_up():
    """A fixed mount on a log without attitudes: the camera's tilt is right, its heading is the track's, which a
    crabbing drone or rounded positions put off (here 10 degrees, and 30 more at random each frame). Used whole, at
    the attitude's weight, those headings turn the map; used for up alone, the map is level as with true attitudes
    and the positions turn it."""
    rng = np.random.default_rng(1)
    R_true, t_true = camera_path(120, step_m=0.3)
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    S = Similarity(0.37, Rotation.from_euler("xyz", [40, -70, 120], degrees=True).as_matrix(), np.array([3.0, -1.0, 2.0]))
    c_model = (C_true - S.t) @ S.R / S.scale
    R_model = R_true @ S.R
    t_model = -np.einsum("nij,nj->ni", R_model, c_model)
    gps = C_true + rng.normal(0, 1.0, C_true.shape)
    # world-to-camera, the camera turned about ENU's up before it looks
    R_tel = R_true @ Rotation.from_euler("z", 10.0 + rng.normal(0, 30.0, (120, 1)), degrees=True).as_matrix()
    whole = fit_similarity(c_model, gps, 1.0, R_model, R_tel, np.radians(0.5))
    up = fit_similarity(c_model, gps, 1.0, R_model, R_tel, np.radians(0.5), up_only=np.ones(120, bool))
    err = {k: np.median(rotation_error_deg(georeference_poses(R_model, t_model, f.similarity)[0], R_true))
           for k, f in (("whole", whole), ("up", up))}
    assert err["up"] < 1.0 and err["whole"] > 5.0, err
    level = up.similarity.R @ (S.R.T @ np.array([0.0, 0.0, 1.0]))  # the model's true up, taken to ENU
    assert np.degrees(np.arccos(min(level[2], 1.0))) < 0.2
    assert up.axis_rms_deg < 0.1


def test_exact_input_is_recovered_exactly():
    R_true, t_true = camera_path(30)
    C = -np.einsum("nji,nj->ni", R_true, t_true)
    C[:, 0] += np.sin(np.arange(30))  # not collinear: positions alone suffice
    fit = fit_similarity(C, C * 1.0, 1.0)
    assert abs(fit.similarity.scale - 1) < 1e-9 and np.allclose(fit.similarity.R, np.eye(3)) and fit.position_rms_m < 1e-9


def test_telemetry_poses_are_the_truth_within_telemetry_error(bundled_flight):
    import json

    from ground.poses.telemetry_poses import telemetry_poses

    R, t, flags = telemetry_poses(bundled_flight)
    R_true, t_true = bundled_flight.truth_poses()
    assert (flags == 0).all() and R.shape == R_true.shape
    C = -np.einsum("nji,nj->ni", R, t)
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    tel = json.loads((bundled_flight.path / "sim_config.json").read_text())["telemetry"]
    sigma = np.sqrt(2 * tel["gps_noise_m"] ** 2 + tel["gps_alt_noise_m"] ** 2)
    err = np.linalg.norm(C - C_true, axis=1)
    assert 0.01 < np.median(err) < 4 * sigma
    assert np.median(rotation_error_deg(R, R_true)) < 1.0


def test_drift_offsets_follow_a_bent_chain_and_average_out_the_gps_noise():
    """A map that drifts away from the GPS along the flight (a bending chain of sub-models, here 0 to 20 m over 3,000
    frames): the offsets at each frame take it back to within a few cm, while 0.5-m GPS noise averages out."""
    rng = np.random.default_rng(3)
    kf = np.arange(0, 3000, 2)
    drift = np.stack([20 * (1 - kf / 3000) ** 2, 5 * np.sin(kf / 900), np.zeros(len(kf))], 1)
    residuals = drift + rng.normal(0, 0.5, drift.shape)
    q = np.arange(300, 2700, 7)  # away from the ends, where the kernel is one-sided
    truth = np.stack([20 * (1 - q / 3000) ** 2, 5 * np.sin(q / 900), np.zeros(len(q))], 1)
    off = drift_offsets(kf, residuals, np.ones(len(kf)), q, sigma_frames=60.0)
    err = np.linalg.norm(off - truth, axis=1)
    assert np.median(err) < 0.1 and err.max() < 0.3, (np.median(err), err.max())
    # at the flight's ends too, where the keyframes lie on one side (a mean would lag the drift by ~0.6 m here)
    ends = np.array([0, 2998])
    truth_ends = np.stack([20 * (1 - ends / 3000) ** 2, 5 * np.sin(ends / 900), np.zeros(2)], 1)
    assert np.linalg.norm(drift_offsets(kf, residuals, np.ones(len(kf)), ends, 60.0) - truth_ends, axis=1).max() < 0.3
    # the GPS noise alone is not followed: 0.5 m per fix, averaged over the kernel
    flat = drift_offsets(kf, rng.normal(0, 0.5, drift.shape), np.ones(len(kf)), q, sigma_frames=300.0)
    assert np.abs(flat).max() < 0.15
    assert not drift_offsets(kf, residuals, np.ones(len(kf)), q, sigma_frames=0).any()


def test_the_floor_is_a_plane_through_the_ground_between_the_rows_not_the_canopy():
    """A map tilted 1.2 degrees (a fixed mount's stated tilt against the gimbal's real one): the floor plane follows the
    ground seen between the rows, and the canopy (rows of points a metre and more above it) does not pull it."""
    from ground.poses.georeference import floor_plane

    rng = np.random.default_rng(1)
    tilt = np.radians(1.2)
    xy = rng.uniform(-15, 15, (6000, 2))
    ground = np.c_[xy, np.tan(tilt) * xy[:, 0] + rng.normal(0, 0.02, len(xy))]
    rows = np.abs(((xy[:, 0] + 1.75) % 3.5) - 1.75) < 0.7  # rows 3.5 m apart, 1.4 m of canopy
    canopy = ground[rows] + np.c_[np.zeros((rows.sum(), 2)), rng.uniform(0.8, 3.0, rows.sum())]
    plane = floor_plane(np.concatenate([ground[~rows], canopy]))
    assert plane is not None
    assert abs(np.degrees(np.arccos(plane.normal[2])) - 1.2) < 0.1 and plane.normal[0] < 0
    assert plane.sigma_m < 0.05
    assert floor_plane(canopy[:30]) is None  # too few points to say


def test_positions_within_their_accuracy_of_one_another_do_not_scale_the_map(tmp_path):
    """A Phantom 4 Pro's first second: keyframes half a metre apart, their positions one point rounded to 4 decimals
    (11 m; stated good to 3.2 m), their heights a barometer's, a few centimetres apart. The scale they would give is noise (one such
    fit froze a map frame at 23 micrometres a unit, issue 62): without heights to scale it there is no fit yet, and the
    frames wait for one. Over 30 m, the same rounding scales the map within a tenth."""
    from ground.poses.mapper import Mapper
    from ground.poses.telemetry_poses import KeyframeTelemetry
    from pomar.camera import Camera

    cam = Camera.from_fov(1280, 720, 50.0)
    R_true, t_true = camera_path(100, step_m=0.3)
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    S = Similarity(0.37, Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.array([3.0, -1.0, 2.0]))
    c_model = (C_true - S.t) @ S.R / S.scale
    R_model = R_true @ S.R
    t_model = -np.einsum("nij,nj->ni", R_model, c_model)
    rounded = np.round(C_true / 11.0) * 11.0  # 4 decimals of latitude
    rounded[:, 2] = C_true[:, 2] + 0.01 * np.arange(len(C_true))  # a barometer (to 0.01 m) that drifts up
    m = Mapper(cam, cam, tmp_path, sigma_att_deg=180.0)  # the attitudes (a level stand-in here) weigh nothing
    try:
        for n in (4, 100):
            m.tel = {f: KeyframeTelemetry(rounded[f], np.array([1.0, 0, 0, 0]), 3.2) for f in range(n)}
            got = m._refit({f: (R_model[f], t_model[f]) for f in range(n)})
            if n == 4:
                assert got is None, got
            else:
                assert abs(got[0].scale / S.scale - 1) < 0.1, got[0].scale / S.scale
    finally:
        m.close()
