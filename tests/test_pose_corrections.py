"""Poses given earlier, corrected as the mapper moves the keyframes about them (ground.poses.live.LivePoses.corrected)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from ground.poses.live import LivePoses, Pose
from ground.poses.telemetry_poses import KeyframeTelemetry
from pomar.align import IDENTITY
from pomar.camera import Camera


def _pose(frame: int, R: np.ndarray, c, source: str = "tracked") -> Pose:
    c = np.asarray(c, float)
    return Pose(frame, R, -R @ c, source, 0.015, 0.05)


def test_frames_follow_the_keyframes_the_mapper_moved(tmp_path):
    lp = LivePoses(Camera.from_fov(1280, 720, 50.0), tmp_path)
    try:
        lp.assoc.frozen = IDENTITY  # model frame = association frame
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


def test_drift_correction_applies_only_where_the_map_drifted_beyond_the_gps_wander(tmp_path):
    """The gate of AssociationFrame.drift_correction: a map rigid within the GPS's stated accuracy is left as it is (what a
    correction would follow there is the GPS error's wander); a map that bent away from the GPS is taken back to it."""
    lp = LivePoses(Camera.from_fov(1280, 720, 50.0), tmp_path)
    try:
        rng = np.random.default_rng(5)
        lp.assoc.frozen = IDENTITY
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
        assert not lp.assoc.drift_correction(q, 60.0).any()
        assert not lp.assoc.drift_corrected and lp.assoc.drift_m < lp.assoc.DRIFT_MIN_GPS_SIGMAS * 0.5, lp.assoc.drift_m

        bend = np.stack([np.zeros(len(kf)), 15 * (1 - kf / 3000) ** 2, np.zeros(len(kf))], 1)
        gps(bend)  # the map's start lies 15 m from the GPS, its end on it
        off = lp.assoc.drift_correction(q, 60.0)
        assert lp.assoc.drift_corrected and lp.assoc.drift_m > 10, lp.assoc.drift_m
        want = np.stack([np.zeros(len(q)), 15 * (1 - q / 3000) ** 2, np.zeros(len(q))], 1)
        err = np.linalg.norm(off - want, axis=1)
        assert np.median(err) < 0.15 and err.max() < 0.5, (np.median(err), err.max())
        assert not lp.assoc.drift_correction(q, 0.0).any()  # switched off
    finally:
        lp.close()
