"""The bundled replay flight's files agree with each other and with the truth (real files, real decoders)."""

from __future__ import annotations

import numpy as np
import pytest

from pomar.rotations import camera_from_gimbal_attitude, quat_wxyz_to_rotation
from pomar.video import count_frames, iter_frames


def read_tlog(path):
    from pomar.mavlink import dialect  # noqa: F401  (MAVLink 2 before pymavlink loads)
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    msgs = {}
    while (m := conn.recv_match()) is not None:
        if m.get_type() == "BAD_DATA":
            raise AssertionError(f"bad data in {path}: {m}")
        msgs.setdefault(m.get_type(), []).append(m)
    conn.close()
    return msgs


@pytest.fixture(scope="module")
def tlog(bundled_flight):
    return read_tlog(bundled_flight.tlog)


def boot_to_unix(tlog):
    """Autopilot boot time (unix s) from SYSTEM_TIME; every sample must agree."""
    st = tlog["SYSTEM_TIME"]
    offsets = np.array([m.time_unix_usec / 1e6 - m.time_boot_ms / 1e3 for m in st])
    assert np.ptp(offsets) < 2e-3
    return float(np.median(offsets))


def test_video_decodes_to_frame_count(bundled_flight):
    meta = bundled_flight.meta()
    assert count_frames(bundled_flight.video) == meta.frame_count
    assert meta.frame_count == len(bundled_flight.truth_frames()["frame"])


def test_tlog_has_what_autopilots_send(tlog, bundled_flight):
    for kind in ("HEARTBEAT", "SYSTEM_TIME", "GLOBAL_POSITION_INT", "GPS_RAW_INT", "ATTITUDE",
                 "GIMBAL_DEVICE_ATTITUDE_STATUS", "CAMERA_FEEDBACK"):
        assert kind in tlog, kind
    meta = bundled_flight.meta()
    fb = tlog["CAMERA_FEEDBACK"]
    assert [m.img_idx for m in fb] == list(range(meta.frame_count))
    assert all(m.get_header().srcComponent == 154 for m in tlog["GIMBAL_DEVICE_ATTITUDE_STATUS"])
    # the GPS updates slower than the video
    gps_t = np.array([m.time_usec for m in tlog["GPS_RAW_INT"]]) / 1e6
    assert 1.0 / np.median(np.diff(gps_t)) < meta.fps


def gps_sigma(flight):
    """The GPS noise the flight was simulated with (horizontal, vertical), from sim_config.json."""
    import json

    tel = json.loads((flight.path / "sim_config.json").read_text())["telemetry"]
    return tel["gps_noise_m"], tel["gps_alt_noise_m"]


def test_tlog_positions_match_truth_at_frame_times(tlog, bundled_flight):
    sig_h, sig_v = gps_sigma(bundled_flight)
    fr = bundled_flight.truth_frames()
    origin = bundled_flight.origin()
    true_enu = origin.to_enu(fr["lat"], fr["lon"], fr["alt"])
    boot = boot_to_unix(tlog)
    # CAMERA_FEEDBACK: one per frame, timed on the autopilot clock = the true capture time
    fb = tlog["CAMERA_FEEDBACK"]
    t_fb = np.array([m.time_usec for m in fb]) / 1e6
    np.testing.assert_allclose(t_fb, fr["t_unix"], atol=1e-5)
    fb_enu = origin.to_enu([m.lat / 1e7 for m in fb], [m.lng / 1e7 for m in fb], [m.alt_msl for m in fb])
    err = np.linalg.norm(fb_enu[:, :2] - true_enu[:, :2], axis=1)
    assert np.median(err) < 4 * sig_h and err.max() < 6 * sig_h, (np.median(err), err.max())
    assert np.median(err) > 0.01  # the telemetry is noisy, not the truth copied
    assert np.median(np.abs(fb_enu[:, 2] - true_enu[:, 2])) < 4 * sig_v
    # GLOBAL_POSITION_INT interpolated at the frame times
    gp = tlog["GLOBAL_POSITION_INT"]
    t_gp = boot + np.array([m.time_boot_ms for m in gp]) / 1e3
    gp_enu = origin.to_enu([m.lat / 1e7 for m in gp], [m.lon / 1e7 for m in gp], [m.alt / 1e3 for m in gp])
    interp = np.stack([np.interp(fr["t_unix"], t_gp, gp_enu[:, i]) for i in range(3)], 1)
    err_h = np.linalg.norm(interp[:, :2] - true_enu[:, :2], axis=1)
    err_v = np.abs(interp[:, 2] - true_enu[:, 2])
    assert np.median(err_h) < 4 * sig_h and err_h.max() < 6 * sig_h, (np.median(err_h), err_h.max())
    assert np.median(err_v) < 4 * sig_v and err_v.max() < 6 * sig_v, (np.median(err_v), err_v.max())


def test_tlog_gimbal_attitude_matches_truth_at_frame_times(tlog, bundled_flight):
    from scipy.spatial.transform import Slerp

    fr = bundled_flight.truth_frames()
    cam = bundled_flight.camera()
    boot = boot_to_unix(tlog)
    g = tlog["GIMBAL_DEVICE_ATTITUDE_STATUS"]
    t_g = boot + np.array([m.time_boot_ms for m in g]) / 1e3
    rots = quat_wxyz_to_rotation(np.array([m.q for m in g]))
    inside = (fr["t_unix"] >= t_g[0]) & (fr["t_unix"] <= t_g[-1])
    assert inside.all()
    r_ned_gimbal = Slerp(t_g, rots)(fr["t_unix"])
    r_enu_cam = camera_from_gimbal_attitude(r_ned_gimbal, cam.r_gimbal_from_camera)
    q = np.stack([fr[k] for k in ("qw", "qx", "qy", "qz")], 1)
    r_true = quat_wxyz_to_rotation(q).as_matrix()  # world-to-camera
    rel = np.einsum("nij,njk->nik", r_true, r_enu_cam)  # identity if they agree
    ang = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert np.median(ang) < 1.0 and ang.max() < 2.5, (np.median(ang), ang.max())
    # vehicle ATTITUDE yaw is close to the camera's heading (the drone faces across the rows)
    yaw = np.degrees([m.yaw for m in tlog["ATTITUDE"]]) % 360
    heading = np.degrees(np.arctan2(r_enu_cam[:, 0, 2], r_enu_cam[:, 1, 2])) % 360
    assert abs(((np.median(yaw) - np.median(heading)) + 180) % 360 - 180) < 5


def test_truth_projection_gives_detections(bundled_flight):
    cam = bundled_flight.camera()
    R, t = bundled_flight.truth_poses()
    a = bundled_flight.truth_apples()
    d = bundled_flight.truth_detections()
    xyz = np.stack([a["x"], a["y"], a["z"]], 1)
    idx = np.searchsorted(a["apple_id"], d["apple_id"])
    assert np.array_equal(a["apple_id"][idx], d["apple_id"])
    for f in np.unique(d["frame"]):
        sel = d["frame"] == f
        uv, z = cam.project(xyz[idx[sel]], R[f], t[f])
        assert (z > 0).all()
        np.testing.assert_allclose(uv[:, 0], d["u"][sel], atol=2e-3)
        np.testing.assert_allclose(uv[:, 1], d["v"][sel], atol=2e-3)
        np.testing.assert_allclose(cam.fx * a["radius_m"][idx[sel]] / z, d["r_px"][sel], rtol=1e-3, atol=2e-3)
    assert ((d["visible_fraction"] > 0) & (d["visible_fraction"] <= 1)).all()
    # truth centres lat/lon agree with the ENU poses
    fr = bundled_flight.truth_frames()
    centres = -np.einsum("nji,nj->ni", R, t)
    enu = bundled_flight.origin().to_enu(fr["lat"], fr["lon"], fr["alt"])
    np.testing.assert_allclose(centres, enu, atol=1e-3)


def test_truth_detections_land_on_apple_coloured_pixels(bundled_flight):
    d = bundled_flight.truth_detections()
    a = bundled_flight.truth_apples()
    variety = dict(zip(a["apple_id"].tolist(), a["variety"].tolist()))
    sel = (d["visible_fraction"] >= 0.9) & (d["r_px"] >= 2.5)
    frames = set(np.unique(d["frame"][sel])[::8].tolist())
    rng = np.random.default_rng(0)
    apple_rg, other_rg, gala_red = [], [], []
    for f, img in iter_frames(bundled_flight.video):
        if f not in frames:
            continue
        rgb = img[..., ::-1].astype(float)
        h, w = rgb.shape[:2]
        s = sel & (d["frame"] == f)
        for u, v, aid in zip(d["u"][s], d["v"][s], d["apple_id"][s]):
            x, y = int(round(u)), int(round(v))
            if 1 <= x < w - 1 and 1 <= y < h - 1:
                patch = rgb[y - 1 : y + 2, x - 1 : x + 2].reshape(-1, 3).mean(0)
                apple_rg.append(patch[0] - patch[1])
                if variety[int(aid)] == "Gala":
                    gala_red.append(patch[0] > patch[1] + 20)
        ys, xs = rng.integers(0, h, 200), rng.integers(0, w, 200)
        other_rg.extend((rgb[ys, xs, 0] - rgb[ys, xs, 1]).tolist())
    assert len(apple_rg) > 50
    # apples are redder than the scene around them, and Gala apples are red
    assert np.median(apple_rg) > np.median(other_rg) + 30, (np.median(apple_rg), np.median(other_rg))
    assert np.mean(gala_red) > 0.85
