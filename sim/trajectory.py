"""The drone's true flight: camera centre, gimbal and vehicle attitude as smooth functions of time.

Passes fly along the rows at a set altitude, the camera tilted off nadir looking across the rows
(the vehicle's nose points across the rows and it flies sideways, as a fixed-gimbal drone does);
between passes the drone moves across to the next line. Speed, position, altitude and attitude
wobble as smooth random processes drawn from the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from sim.config import SimConfig
from sim.orchard import orchard_to_enu_matrix

RATE_HZ = 200.0  # dense sampling of the true trajectory
MARGIN_S = 3.0  # the trajectory extends this long before the video starts and after it ends


def smooth_noise(rng: np.random.Generator, n: int, corr_s: float, sigma: float, rate_hz: float = RATE_HZ,
                 by_gain: bool = False) -> np.ndarray:
    """n samples at rate_hz of a zero-mean Gaussian process of standard deviation sigma, correlation time corr_s.
    ``by_gain``: normalised by the filter's own gain (the spread its kernel leaves of unit white noise), so that the
    process has sigma whatever its length; else by the spread of the whole process drawn, which for a flight of a few
    correlation times holds few independent values and comes out larger (a 12-s flight's 20-s process: its offset
    0.16 where 0.1 was asked). The latter stays where flights rendered before must come out byte for byte (their
    trajectories, GPS errors); the barometer, whose offset over a short flight is the map's scale, takes the gain."""
    if sigma == 0 or n == 0:
        return np.zeros(n)
    white = rng.normal(size=n + int(8 * corr_s * rate_hz))
    s = corr_s * rate_hz
    x = gaussian_filter1d(white, s, mode="wrap")
    if by_gain:
        k = np.exp(-0.5 * (np.arange(-int(4 * s + 0.5), int(4 * s + 0.5) + 1) / max(s, 1e-9)) ** 2)
        return sigma * x[:n] / float(np.sqrt(((k / k.sum()) ** 2).sum()))
    return sigma * x[:n] / max(x.std(), 1e-12)  # normalised over the whole process, not the slice


@dataclass
class Trajectory:
    t: np.ndarray  # (n,) seconds since video start (true clock)
    centre: np.ndarray  # (n, 3) camera centre, ENU
    gimbal_rpy: np.ndarray  # (n, 3) gimbal roll, pitch, yaw in NED (deg), yaw in the earth frame
    vehicle_rpy: np.ndarray  # (n, 3) vehicle roll, pitch, yaw in NED (deg)
    duration: float  # seconds of video

    def sample(self, times: np.ndarray) -> dict[str, np.ndarray]:
        """Interpolate the trajectory at arbitrary times (seconds since video start)."""
        times = np.asarray(times, float)
        out = {"centre": np.stack([np.interp(times, self.t, self.centre[:, i]) for i in range(3)], 1)}
        for key in ("gimbal_rpy", "vehicle_rpy"):
            out[key] = np.stack([np.interp(times, self.t, getattr(self, key)[:, i]) for i in range(3)], 1)
        dt = 1e-2
        c2 = np.stack([np.interp(times + dt, self.t, self.centre[:, i]) for i in range(3)], 1)
        out["velocity"] = (c2 - out["centre"]) / dt
        r2 = np.stack([np.interp(times + dt, self.t, self.vehicle_rpy[:, i]) for i in range(3)], 1)
        out["vehicle_rate"] = np.radians(r2 - out["vehicle_rpy"]) / dt
        return out


def _waypoints(cfg: SimConfig):
    f = cfg.flight
    pts, yaws = [], []
    for i, p in enumerate(f.passes):
        a, b = (f.start_m, f.end_m) if i % 2 == 0 else (f.end_m, f.start_m)
        yaw = 90.0 + cfg.orchard.row_azimuth_deg + (0.0 if p.look == 1 else 180.0)
        pts += [(p.across_m, a), (p.across_m, b)]
        yaws += [yaw, yaw]
    return np.array(pts, float), np.unwrap(np.radians(yaws)) * 180 / np.pi


def build_trajectory(cfg: SimConfig) -> Trajectory:
    f = cfg.flight
    rng = np.random.default_rng([cfg.seed, 1])
    pts, yaws = _waypoints(cfg)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s_way = np.concatenate([[0.0], np.cumsum(seg)])
    length = s_way[-1]
    # arc length over time with speed wobble; long enough for the whole path plus margins
    n = int((length / (f.speed_mps * 0.5) + 4 * MARGIN_S) * RATE_HZ)
    speed = f.speed_mps * np.clip(1.0 + smooth_noise(rng, n, 2.0, f.speed_wobble), 0.3, 2.0)
    t = np.arange(n) / RATE_HZ - MARGIN_S
    s = np.cumsum(speed) / RATE_HZ
    s -= np.interp(0.0, t, s)  # s = 0 at video start
    duration = float(np.interp(length, s, t))
    keep = t <= duration + MARGIN_S
    t, s = t[keep], s[keep]
    n = len(t)
    # position along the polyline, extrapolated along the first/last segment
    d0 = (pts[1] - pts[0]) / seg[0]
    d1 = (pts[-1] - pts[-2]) / seg[-1]
    xy = np.stack([np.interp(s, s_way, pts[:, 0]), np.interp(s, s_way, pts[:, 1])], 1)
    xy[s < 0] = pts[0] + s[s < 0, None] * d0
    xy[s > length] = pts[-1] + (s[s > length, None] - length) * d1
    yaw_nom = np.interp(s, s_way, yaws)
    if f.turn_s > 0:  # round the corners: the path and the heading low-passed over about turn_s
        sigma = 0.5 * f.turn_s * RATE_HZ
        xy = gaussian_filter1d(xy, sigma, axis=0, mode="nearest")
        yaw_nom = gaussian_filter1d(yaw_nom, sigma, mode="nearest")
    # lateral wobble (across the direction of travel, approximated by the across-row axis on passes)
    xy[:, 0] += smooth_noise(rng, n, 3.0, f.lateral_wobble_m)
    xy[:, 1] += smooth_noise(rng, n, 4.0, f.lateral_wobble_m * 0.3)
    z = f.altitude_m + smooth_noise(rng, n, 3.0, f.altitude_wobble_m)
    to_enu = orchard_to_enu_matrix(cfg.orchard.row_azimuth_deg)
    centre = np.column_stack([xy @ to_enu.T, z])
    aw = f.attitude_wobble_deg
    gimbal = np.column_stack([
        smooth_noise(rng, n, 0.7, aw * 0.6),
        -(90.0 - f.tilt_deg) + smooth_noise(rng, n, 0.8, aw),
        yaw_nom + smooth_noise(rng, n, 1.2, aw),
    ])
    # vehicle: banked to fly sideways, plus gusts; yaw close to the gimbal's
    vw = f.vehicle_tilt_wobble_deg
    vel = np.gradient(centre, axis=0) * RATE_HZ
    heading = np.radians(yaw_nom)
    right = np.stack([np.cos(heading), -np.sin(heading)], 1)  # body right axis in (east, north)
    v_right = np.sum(vel[:, :2] * right, axis=1)
    v_fwd = np.sum(vel[:, :2] * np.stack([np.sin(heading), np.cos(heading)], 1), axis=1)
    vehicle = np.column_stack([
        1.5 * v_right + smooth_noise(rng, n, 0.6, vw),
        -1.5 * v_fwd + smooth_noise(rng, n, 0.6, vw),
        gimbal[:, 2] + smooth_noise(rng, n, 2.0, 0.5),
    ])
    return Trajectory(t=t, centre=centre, gimbal_rpy=gimbal, vehicle_rpy=vehicle, duration=duration)


def camera_poses(traj_sample: dict, r_gimbal_from_camera: np.ndarray, mount_error: Rotation | None = None):
    """World-to-camera (R, t) arrays from sampled gimbal attitudes and camera centres."""
    from pomar.rotations import camera_from_gimbal_attitude, ned_euler_to_rotation, world_to_camera

    g = traj_sample["gimbal_rpy"]
    mount = r_gimbal_from_camera if mount_error is None else r_gimbal_from_camera @ mount_error.as_matrix()
    r_wc = camera_from_gimbal_attitude(ned_euler_to_rotation(g[:, 0], g[:, 1], g[:, 2]), mount)
    return world_to_camera(r_wc, traj_sample["centre"])
