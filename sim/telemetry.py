"""The autopilot's view of a simulated flight, written as a MAVLink 2 .tlog.

Messages as ArduPilot (or PX4) sends them: HEARTBEAT and SYSTEM_TIME at 1 Hz, GPS_RAW_INT and
GLOBAL_POSITION_INT at the GPS rate with GPS-like error (a slowly wandering bias plus white
noise), ATTITUDE with noise, GIMBAL_DEVICE_ATTITUDE_STATUS from the gimbal component (quaternion in
the earth frame, NED, yaw in the earth frame), and one capture record per video frame
(CAMERA_FEEDBACK, ArduPilot, with img_idx = frame index; or CAMERA_TRIGGER, PX4, with seq =
frame index), timed by the autopilot's clock.
"""

from __future__ import annotations

import logging

import numpy as np

from pomar.geo import Origin
from pomar.mavlink import TlogWriter, dialect
from pomar.rotations import ned_euler_to_rotation, rotation_to_quat_wxyz
from pomar.telemetry.base import height_source_param
from sim.config import SimConfig
from sim.trajectory import MARGIN_S, Trajectory, smooth_noise

#: A barometer's height above take-off wanders this much over a flight (m): the EKF's with ``height_source = "baro"``,
#: and a DJI SRT's (sim.logs; pomar.telemetry.srt assumes the same).
BARO_DRIFT_M = 0.1

log = logging.getLogger(__name__)

AUTOPILOT_COMPONENT = 1
GIMBAL_COMPONENT = 154  # MAV_COMP_ID_GIMBAL


def _times(rate_hz: float, t0: float, t1: float, phase: float) -> np.ndarray:
    return np.arange(t0 + phase / rate_hz, t1, 1.0 / rate_hz)


def write_tlog(cfg: SimConfig, traj: Trajectory, origin: Origin, start_unix: float, n_frames: int, path) -> dict:
    """Write the .tlog; returns a summary (message counts)."""
    m = dialect()
    tel = cfg.telemetry
    rng = np.random.default_rng([cfg.seed, 2])
    t0, t1 = -MARGIN_S + 0.5, traj.duration + MARGIN_S - 0.5
    boot = start_unix - cfg.flight.boot_s_before_start  # autopilot boot time (unix)
    events: list[tuple[float, int, int, object]] = []  # (t_sim, tiebreak, component, msg)

    def boot_ms(ts):
        return int(round((start_unix + ts - boot) * 1000))

    px4 = tel.capture_message == "CAMERA_TRIGGER"
    ap = m.MAV_AUTOPILOT_PX4 if px4 else m.MAV_AUTOPILOT_ARDUPILOTMEGA
    w = TlogWriter(path, system_id=tel.system_id)
    enc = w.sender(AUTOPILOT_COMPONENT)
    genc = w.sender(GIMBAL_COMPONENT)

    for ts in _times(1.0, t0, t1, 0.1):
        base = m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | m.MAV_MODE_FLAG_SAFETY_ARMED | m.MAV_MODE_FLAG_GUIDED_ENABLED
        events.append((ts, 0, AUTOPILOT_COMPONENT, enc.heartbeat_encode(m.MAV_TYPE_QUADROTOR, ap, base, 3, m.MAV_STATE_ACTIVE)))
        events.append((ts + 0.001, 1, AUTOPILOT_COMPONENT, enc.system_time_encode(int(round((start_unix + ts) * 1e6)), boot_ms(ts))))

    # the EKF's height source, as a ground station downloads the parameters on connecting (PARAM_VALUE)
    name, value = height_source_param(tel.height_source, "px4" if px4 else "ardupilot")
    events.append((t0, -1, AUTOPILOT_COMPONENT, enc.param_value_encode(
        name.encode(), float(value), m.MAV_PARAM_TYPE_INT32 if px4 else m.MAV_PARAM_TYPE_INT8, 1, 0)))

    # GPS error: a bias wandering over ~20 s plus white noise; shared by GPS_RAW_INT and the EKF output
    sigma = np.array([tel.gps_noise_m, tel.gps_noise_m, tel.gps_alt_noise_m])
    n_dense = len(traj.t)
    bias = np.column_stack([smooth_noise(rng, n_dense, 20.0, 0.8 * sg) for sg in sigma])

    def gps_error(ts, white_frac):
        e = np.column_stack([np.interp(ts, traj.t, bias[:, i]) for i in range(3)])
        return e + rng.normal(0, 1, (len(ts), 3)) * sigma * white_frac

    ts = _times(tel.gps_rate_hz, t0, t1, 0.3)
    s = traj.sample(ts)
    geo = origin.to_geodetic(s["centre"] + gps_error(ts, 0.6))
    vel = s["velocity"]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    cog = (np.degrees(np.arctan2(vel[:, 0], vel[:, 1])) % 360) * 100
    for i, tt in enumerate(ts):
        events.append((tt, 2, AUTOPILOT_COMPONENT, enc.gps_raw_int_encode(
            boot_ms(tt) * 1000, 3, int(round(geo[i, 0] * 1e7)), int(round(geo[i, 1] * 1e7)), int(round(geo[i, 2] * 1000)),
            90, 140, int(round(speed[i] * 100)), int(round(cog[i])), 14,
            alt_ellipsoid=int(round(geo[i, 2] * 1000)), h_acc=int(tel.gps_noise_m * 1000), v_acc=int(tel.gps_alt_noise_m * 1000),
            vel_acc=200, hdg_acc=0)))

    ts_pos = _times(tel.position_rate_hz, t0, t1, 0.5)
    sp = traj.sample(ts_pos)
    err_p = gps_error(ts_pos, 0.15)
    if tel.height_source == "baro":  # the EKF's height from the barometer; its own stream, the others' unchanged
        err_p[:, 2] = smooth_noise(np.random.default_rng([cfg.seed, 38]), len(ts_pos), 20.0, BARO_DRIFT_M,
                                   rate_hz=tel.position_rate_hz, by_gain=True)
    geo_p = origin.to_geodetic(sp["centre"] + err_p)
    vned = np.column_stack([sp["velocity"][:, 1], sp["velocity"][:, 0], -sp["velocity"][:, 2]])
    for i, tt in enumerate(ts_pos):
        hdg = int(round((sp["vehicle_rpy"][i, 2] % 360) * 100))
        events.append((tt, 3, AUTOPILOT_COMPONENT, enc.global_position_int_encode(
            boot_ms(tt), int(round(geo_p[i, 0] * 1e7)), int(round(geo_p[i, 1] * 1e7)), int(round(geo_p[i, 2] * 1000)),
            int(round((geo_p[i, 2] - origin.alt) * 1000)), *[int(round(x * 100)) for x in vned[i]], hdg)))

    ta = _times(tel.attitude_rate_hz, t0, t1, 0.7)
    sa = traj.sample(ta)
    rpy = sa["vehicle_rpy"] + rng.normal(0, tel.attitude_noise_deg, sa["vehicle_rpy"].shape)
    rates = sa["vehicle_rate"]
    for i, tt in enumerate(ta):
        r, p, y = np.radians(rpy[i])
        y = (y + np.pi) % (2 * np.pi) - np.pi
        events.append((tt, 4, AUTOPILOT_COMPONENT, enc.attitude_encode(boot_ms(tt), r, p, y, *rates[i])))

    tg = _times(tel.gimbal_rate_hz, t0, t1, 0.9)
    sg = traj.sample(tg)
    grpy = sg["gimbal_rpy"] + rng.normal(0, tel.gimbal_noise_deg, sg["gimbal_rpy"].shape)
    q = rotation_to_quat_wxyz(ned_euler_to_rotation(grpy[:, 0], grpy[:, 1], grpy[:, 2]))
    flags = m.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME | m.GIMBAL_DEVICE_FLAGS_YAW_LOCK
    for i, tt in enumerate(tg):
        events.append((tt, 5, GIMBAL_COMPONENT, genc.gimbal_device_attitude_status_encode(
            tel.system_id, AUTOPILOT_COMPONENT, boot_ms(tt), flags, [float(x) for x in q[i]], 0.0, 0.0, 0.0, 0,
            delta_yaw=float(np.radians(grpy[i, 2] - sg["vehicle_rpy"][i, 2])), gimbal_device_id=1)))

    # one capture record per frame, at the frame's true capture time
    tf = np.arange(n_frames) / cfg.flight.fps
    sf = traj.sample(tf)
    geo_f = origin.to_geodetic(sf["centre"] + gps_error(tf, 0.15))
    vr = sf["vehicle_rpy"] + rng.normal(0, tel.attitude_noise_deg, sf["vehicle_rpy"].shape)
    focal_mm = 8.8  # nominal, informational
    for i, tt in enumerate(tf):
        usec = int(round((start_unix + tt) * 1e6))
        if px4:
            msg = enc.camera_trigger_encode(usec, i)
        else:
            msg = enc.camera_feedback_encode(
                usec, tel.system_id, 0, i % 65536, int(round(geo_f[i, 0] * 1e7)), int(round(geo_f[i, 1] * 1e7)),
                float(geo_f[i, 2]), float(geo_f[i, 2] - origin.alt), float(vr[i, 0]), float(vr[i, 1]),
                float(vr[i, 2] % 360), focal_mm, m.CAMERA_FEEDBACK_PHOTO, completed_captures=(i + 1) % 65536)
        events.append((tt, 6, AUTOPILOT_COMPONENT, msg))

    events.sort(key=lambda e: (e[0], e[1]))
    counts: dict[str, int] = {}
    with w:
        for tt, _, comp, msg in events:
            w.write(start_unix + tt + tel.link_latency_s, comp, msg)
            counts[msg.get_type()] = counts.get(msg.get_type(), 0) + 1
    log.info("wrote %s: %s", path, counts)
    return counts
