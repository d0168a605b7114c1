"""Poses given earlier, corrected as the mapper moves the keyframes about them (ground.poses.stage.PoseStage.corrected)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ground.poses.stage import PoseStage, Pose
from ground.poses.telemetry_poses import KeyframeTelemetry
from pomar.align import IDENTITY, Similarity
from pomar.camera import Camera


def _pose(frame: int, R: np.ndarray, c, source: str = "tracked") -> Pose:
    c = np.asarray(c, float)
    return Pose(frame, R, -R @ c, source, 0.015, 0.05)


def test_frames_follow_the_keyframes_the_mapper_moved(tmp_path):
    lp = PoseStage(Camera.from_fov(1280, 720, 50.0), tmp_path)
    try:
        lp.map_frame.frozen = lp.mapper.fit = IDENTITY  # model frame = map frame = ENU
        R0 = np.eye(3)
        given = {f: _pose(f, R0, (0.1 * f, 0.0, 10.0), "telemetry" if f == 12 else "tracked") for f in range(0, 101)}
        # the mapper has since moved keyframe 10 by 2 cm and keyframe 20 by 6 cm and 0.2 degrees
        turn = Rotation.from_euler("z", 0.2, degrees=True).as_matrix()
        now = {10: _pose(10, R0, given[10].centre + [0, 0.02, 0]), 20: _pose(20, R0 @ turn, given[20].centre + [0, 0.06, 0])}
        lp.mapper.model_pose.update({k: (p.R, p.t) for k, p in now.items()})
        lp.mapper.kf_sorted[:] = sorted(now)

        out = lp.corrected(given, range(0, 101))

        assert np.allclose(out[10].centre, now[10].centre) and np.allclose(out[20].R, now[20].R)
        # between the two: the corrections interpolated, in centre and in rotation
        assert np.allclose(out[15].centre - given[15].centre, [0, 0.04, 0])
        half = np.degrees(Rotation.from_matrix(given[15].R.T @ out[15].R).magnitude())
        assert abs(half - 0.1) < 1e-6
        assert out[15].source == "tracked"
        # beyond the last keyframe: its correction; telemetry poses and frames far from any keyframe stay
        assert np.allclose(out[25].centre - given[25].centre, [0, 0.06, 0])
        assert np.allclose(out[5].centre - given[5].centre, [0, 0.02, 0])
        assert 12 not in out and 100 not in out
        # once taken, the same keyframe poses correct nothing more
        given.update(out)
        assert lp.corrected(given, range(0, 101)) == {}
    finally:
        lp.close()


def test_the_least_correction_is_in_metres_whatever_the_association_frames_unit(tmp_path):
    """A map whose map frame was fixed at a fifth of a metre a unit (a Phantom 4 Pro's first fit, from
    positions rounded to 11 m): a keyframe moved by 0.5 mm (2.5 thousandths of a unit) corrects nothing, as in a frame of metres (MIN_CORRECTION_M);
    moved by 2 cm, it does. Before, the least correction was taken in units: 0.2 mm in such a frame, and twice as many
    frames were corrected (issue 62)."""
    lp = PoseStage(Camera.from_fov(1280, 720, 50.0), tmp_path)
    try:
        unit = 0.2  # metres per association unit
        lp.map_frame.frozen = IDENTITY
        lp.mapper.fit = Similarity(unit, np.eye(3), np.zeros(3))
        assert abs(lp.metres_per_unit() - unit) < 1e-12
        R0 = np.eye(3)
        for moved_m, corrected in ((0.5e-3, False), (0.02, True)):
            given = {f: _pose(f, R0, (0.5 * f, 0.0, 50.0)) for f in range(0, 21)}
            now = {10: _pose(10, R0, given[10].centre + [0, moved_m / unit, 0])}
            lp.mapper.model_pose.clear()
            lp.mapper.model_pose.update({k: (p.R, p.t) for k, p in now.items()})
            lp.mapper.kf_sorted[:] = sorted(now)
            out = lp.corrected(given, range(0, 21))
            assert (10 in out) is corrected, (moved_m, out.keys())
    finally:
        lp.close()


def test_a_frame_given_its_pose_after_a_correction_agrees_with_the_frames_the_correction_moved(tmp_path):
    lp = PoseStage(Camera.from_fov(1280, 720, 50.0), tmp_path)
    try:
        lp.map_frame.frozen = lp.mapper.fit = IDENTITY  # model frame = map frame = ENU
        R0 = np.eye(3)
        kf = _pose(10, R0, (1.0, 0.0, 10.0), "registered")
        lp.mapper.model_pose[10] = (kf.R, kf.t)
        lp.mapper.kf_sorted[:] = [10]
        # frames 11-14 tracked from keyframe 10 as it was handed over
        for f in range(11, 15):
            p = _pose(f, R0, (0.1 * f, 0.0, 10.0))
            lp.tracking.tracked[f] = (p.R, p.t)
            lp.tracking.anchors[f] = (10, kf.R, kf.t)
        given = {f: lp.pose(f) for f in (10, 11, 12)}  # released before the mapper moved the keyframe
        assert np.allclose(given[12].centre, (1.2, 0.0, 10.0))
        # the mapper moves keyframe 10 by 30 cm and 0.5 degrees (a re-anchoring after an outage)
        turn = Rotation.from_euler("x", 0.5, degrees=True).as_matrix()
        moved = _pose(10, R0 @ turn, kf.centre + [0.0, 0.3, 0.0], "registered")
        lp.mapper.model_pose[10] = (moved.R, moved.t)
        given.update(lp.corrected(given, range(10, 13)))  # the correction round: the frames released so far
        late = lp.pose(13)  # released after it, tracked before it
        # the late frame sits where the corrected frames' motion puts it: one step on from frame 12, not 30 cm away
        assert np.linalg.norm(late.centre - given[12].centre - (given[12].centre - given[11].centre)) < 1e-6
        assert np.allclose(late.R, given[12].R)
        # its pose relative to the keyframe is the one tracking gave
        R13, t13 = lp.tracking.tracked[13]
        assert np.allclose(late.R @ moved.R.T, R13 @ kf.R.T)
        # a frame tracked from a keyframe the map has not (or no longer) got keeps its tracked pose
        lp.tracking.anchors[14] = (99, kf.R, kf.t)
        assert np.allclose(lp.pose(14).t, lp.tracking.tracked[14][1])
    finally:
        lp.close()


def test_a_tracked_frame_is_corrected_with_the_keyframe_it_was_tracked_from_and_no_other(tmp_path):
    """Frame 14 was tracked from keyframe 10; keyframe 20, mapped later, is moved by the mapper (a new keyframe's first
    placement corrected). Frame 14 keeps its pose: it was measured against keyframe 10's points. When keyframe 10 moves,
    frame 14 moves with it, its pose relative to the keyframe kept. A frame interpolated between tracked ones follows
    them."""
    lp = PoseStage(Camera.from_fov(1280, 720, 50.0), tmp_path)
    try:
        lp.map_frame.frozen = lp.mapper.fit = IDENTITY  # model frame = map frame = ENU
        R0 = np.eye(3)
        kf = {k: _pose(k, R0, (0.1 * k, 0.0, 10.0), "registered") for k in (10, 20)}
        lp.mapper.model_pose.update({k: (p.R, p.t) for k, p in kf.items()})
        lp.mapper.kf_sorted[:] = [10, 20]
        for f in (12, 14):
            p = _pose(f, R0, (0.1 * f, 0.0, 10.0))
            lp.tracking.tracked[f] = (p.R, p.t)
            lp.tracking.anchors[f] = (10, kf[10].R, kf[10].t)
        given = {f: lp.pose(f) for f in (10, 12, 13, 14, 20)}
        assert given[13].source == "interpolated" and np.allclose(given[13].centre, (1.3, 0.0, 10.0))

        moved20 = _pose(20, R0, kf[20].centre + [0.0, 0.06, 0.0], "registered")
        lp.mapper.model_pose[20] = (moved20.R, moved20.t)
        out = lp.corrected(given, range(10, 21))
        assert set(out) == {20}, sorted(out)  # the keyframe after them has no say on frames tracked from keyframe 10

        turn = Rotation.from_euler("x", 0.5, degrees=True).as_matrix()
        moved10 = _pose(10, R0 @ turn, kf[10].centre + [0.0, 0.03, 0.0], "registered")
        lp.mapper.model_pose[10] = (moved10.R, moved10.t)
        out = lp.corrected(given, range(10, 21))
        for f in (12, 14):  # carried along with keyframe 10: the pose relative to it is the one tracking measured
            R, t = lp.tracking.tracked[f]
            assert np.allclose(out[f].R @ moved10.R.T, R @ kf[10].R.T)
            assert np.allclose(out[f].R @ (moved10.centre - out[f].centre), R @ (kf[10].centre - given[f].centre))
            assert out[f].source == "tracked"
        # the interpolated frame halfway between the two tracked frames, as they are now
        assert np.allclose(out[13].centre, (out[12].centre + out[14].centre) / 2)
        assert out[13].source == "interpolated"
    finally:
        lp.close()


def test_drift_correction_applies_only_where_the_map_drifted_beyond_the_gps_wander(tmp_path):
    """The GPS's gate of MapFrame.correction: a map rigid within the GPS's stated accuracy is left as it is (what a
    correction would follow there is the GPS error's wander); a map that bent away from the GPS is taken back to it."""
    lp = PoseStage(Camera.from_fov(1280, 720, 50.0), tmp_path)
    try:
        rng = np.random.default_rng(5)
        lp.map_frame.frozen = IDENTITY
        lp.mapper.fit = IDENTITY  # model frame = ENU
        kf = np.arange(0, 3000, 2)
        truth = np.stack([0.3 * kf, np.zeros(len(kf)), np.full(len(kf), 10.0)], 1)
        for f, c in zip(kf, truth):
            lp.mapper.model_pose[int(f)] = (np.eye(3), -c)
        q = np.arange(0, 3000, 5)

        def gps(drift):
            for f, c, d in zip(kf, truth, drift):
                lp.tel[int(f)] = KeyframeTelemetry(c + d + rng.normal(0, 0.5, 3) * [1, 1, 0], np.array([1.0, 0, 0, 0]),
                                                   0.5)

        gps(np.zeros((len(kf), 3)))  # rigid map, 0.5-m GPS noise stated as 0.5 m
        assert not lp.map_frame.correction(q, 60.0)[0].any()
        assert not lp.map_frame.drift_corrected and lp.map_frame.drift_m < lp.map_frame.DRIFT_MIN_GPS_SIGMAS * 0.5, lp.map_frame.drift_m

        bend = np.stack([np.zeros(len(kf)), 15 * (1 - kf / 3000) ** 2, np.zeros(len(kf))], 1)
        gps(bend)  # the map's start lies 15 m from the GPS, its end on it
        off = lp.map_frame.correction(q, 60.0)[0]
        assert lp.map_frame.drift_corrected and lp.map_frame.drift_m > 10, lp.map_frame.drift_m
        want = np.stack([np.zeros(len(q)), 15 * (1 - q / 3000) ** 2, np.zeros(len(q))], 1)
        err = np.linalg.norm(off - want, axis=1)
        assert np.median(err) < 0.15 and err.max() < 0.5, (np.median(err), err.max())
        assert not lp.map_frame.correction(q, 0.0)[0].any()  # switched off
    finally:
        lp.close()


def test_a_map_that_turns_along_a_long_pass_is_bent_back_by_the_attitudes(tmp_path):
    """Incremental reconstruction along a long pass turns slowly, and the map bends with it. The gimbal's attitudes
    (0.5 degrees of noise each, no drift) give its tilt back: the cameras' centres are laid again along the true
    path, and their axes turned with it. A map that does not turn moves by no more than the attitudes' noise lets
    through, and a turn about the vertical is left (a compass's heading wanders as much)."""
    from scipy.spatial.transform import Rotation

    from pomar.rotations import rotation_to_quat_wxyz

    cam = Camera.from_fov(1280, 720, 50.0)
    lp = PoseStage(cam, tmp_path)
    try:
        rng = np.random.default_rng(3)
        lp.map_frame.frozen = IDENTITY
        lp.mapper.fit = IDENTITY  # model frame = ENU
        kf = np.arange(0, 900, 2)
        s = kf / kf.max() - 0.5  # along the pass, -0.5 .. 0.5
        truth_c = np.stack([np.zeros(len(kf)), 184 * s, np.full(len(kf), 12.0)], 1)
        # a camera looking east from a northward pass (world-to-camera), the same all along in truth
        R_true = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
        q = np.arange(0, 900, 3)

        def fly(turn_deg, axis=(1.0, 0, 0)):
            """The map turns about ``axis`` (east: a tilt) by turn_deg x s, and its path bends with it."""
            G = Rotation.from_rotvec(np.outer(np.radians(turn_deg) * s, axis)).as_matrix()
            steps = np.einsum("nij,nj->ni", G[1:], np.diff(truth_c, axis=0))
            c = np.vstack([truth_c[:1], truth_c[0] + np.cumsum(steps, axis=0)])
            c += truth_c.mean(0) - c.mean(0)
            lp.mapper.model_pose.clear()
            for f, Gk, ck in zip(kf, G, c):
                R = R_true @ Gk.T
                lp.mapper.model_pose[int(f)] = (R, -R @ ck)
                # the gimbal's attitude: the true camera's, through the mount, with 0.5 degrees of noise
                R_gimbal = Rotation.from_rotvec(rng.normal(0, np.radians(0.5), 3)).as_matrix() @ R_true
                lp.tel[int(f)] = KeyframeTelemetry(ck, rotation_to_quat_wxyz(camera_attitude_to_gimbal(R_gimbal, cam)),
                                                   0.5)
            return c

        bent = fly(0.8)
        off, rot = lp.map_frame.correction(q, 60.0)
        assert lp.map_frame.bend_corrected and 0.3 < lp.map_frame.bend_deg < 0.6, lp.map_frame.bend_deg  # +-0.4 at the ends
        at = np.searchsorted(kf, q)
        before = np.linalg.norm(bent[at] - truth_c[at], axis=1)
        after = np.linalg.norm(bent[at] + off - truth_c[at], axis=1)
        assert before.max() > 0.15 and after.max() < 0.2 * before.max(), (before.max(), after.max())
        for turn, axis in ((0.0, (1.0, 0, 0)), (0.8, (0, 0, 1.0))):  # none; about the vertical (a compass's heading)
            c = fly(turn, axis)
            off, rot = lp.map_frame.correction(q, 60.0)
            # the noise's share of a fitted tilt passes (a Wiener gain): centimetres, a tenth of the bent map's error
            turned = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1) / 2, -1, 1)))
            assert np.abs(off).max() < 0.1 * before.max() and turned.max() < 0.3, (np.abs(off).max(), turned.max())
            # the heading's bow stays: the correction turns the tilt only
            err, err_after = (np.linalg.norm(c[at] + o - truth_c[at], axis=1).max() for o in (0, off))
            assert err_after > 0.8 * err, (err, err_after)
    finally:
        lp.close()


def camera_attitude_to_gimbal(R_world_to_camera, cam):
    """The gimbal attitude (a Rotation, NED from gimbal) whose camera, through ``cam``'s mount, has this ENU-to-camera
    rotation: pomar.rotations.camera_from_gimbal_attitude undone."""
    from scipy.spatial.transform import Rotation

    from pomar.rotations import R_ENU_FROM_NED

    return Rotation.from_matrix(R_ENU_FROM_NED.T @ R_world_to_camera.T @ cam.r_gimbal_from_camera.T)


def test_frames_wait_for_the_models_georeference_before_the_map_frame_is_fixed(tmp_path):
    """A model the log cannot georeference yet (a Phantom 4 Pro's first second): its frames are not ready, so that the
    first frame posed does not fix the map frame on ENU and leave the flight on telemetry poses; once the model has a
    fit they are, and after as many keyframes as the first model had tries they go on without one."""
    lp = PoseStage(Camera.from_fov(1280, 720, 50.0), tmp_path)
    try:
        lp.tracking.processed = 50  # the images up to frame 50 went through tracking
        tries = lp.mapper.settings.first_model_tries
        lp.mapper.model_pose.update({k: (np.eye(3), np.zeros(3)) for k in range(4)})
        assert lp.mapper.has_model and lp.mapper.fit is None
        assert not lp.ready(10) and lp.ready(10, final=True)
        lp.mapper.fit = IDENTITY
        assert lp.ready(10) and not lp.ready(51)
        lp.mapper.fit = None
        lp.mapper.model_pose.update({k: (np.eye(3), np.zeros(3)) for k in range(tries)})
        assert lp.ready(10)
    finally:
        lp.close()
