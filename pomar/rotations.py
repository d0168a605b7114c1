"""Frame conventions shared by the simulator, the onboard node and the ground.

- World: local ENU (x east, y north, z up).
- Autopilot (MAVLink): NED earth frame, FRD body frame; attitude quaternions (w, x, y, z) rotate
  body vectors into NED (R_ned_from_body = Rz(yaw) Ry(pitch) Rx(roll)).
- Camera: COLMAP/OpenCV (x right, y down, z forward along the optical axis); a pose is
  world-to-camera, x_cam = R X_world + t.
- Gimbal: FRD, x along the optical axis. The nominal camera mount maps camera x -> gimbal y,
  camera y -> gimbal z, camera z -> gimbal x.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

R_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
R_GIMBAL_FROM_CAMERA_NOMINAL = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def quat_wxyz_to_rotation(q) -> Rotation:
    q = np.asarray(q, float)
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def rotation_to_quat_wxyz(rot: Rotation) -> np.ndarray:
    """Scalar-first quaternion(s), sign fixed so that w >= 0."""
    xyzw = rot.as_quat()
    wxyz = np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1)
    sign = np.where(wxyz[..., :1] < 0, -1.0, 1.0)
    return wxyz * sign


def ned_euler_to_rotation(roll, pitch, yaw, degrees: bool = True) -> Rotation:
    """MAVLink Euler angles (roll, pitch, yaw about NED) -> R_ned_from_body."""
    return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=-1), degrees=degrees)


def rotation_to_ned_euler(rot: Rotation, degrees: bool = True) -> np.ndarray:
    """R_ned_from_body -> (..., 3) roll, pitch, yaw."""
    ypr = rot.as_euler("ZYX", degrees=degrees)
    return ypr[..., ::-1]


def camera_from_gimbal_attitude(r_ned_from_gimbal: Rotation, r_gimbal_from_camera: np.ndarray) -> np.ndarray:
    """World(ENU)-from-camera rotation matrices (..., 3, 3) from gimbal attitudes and the camera mount."""
    return R_ENU_FROM_NED @ r_ned_from_gimbal.as_matrix() @ r_gimbal_from_camera


def camera_rotations(q_gimbal: np.ndarray, camera) -> np.ndarray:
    """World(ENU)-to-camera rotations (N, 3, 3) from gimbal attitudes (wxyz, NED; NaN = identity) and the mount of
    ``camera`` (a pomar.camera.Camera)."""
    q = np.where(np.isfinite(q_gimbal), q_gimbal, [1.0, 0.0, 0.0, 0.0])
    return np.swapaxes(camera_from_gimbal_attitude(quat_wxyz_to_rotation(q), camera.r_gimbal_from_camera), -1, -2)


def world_to_camera(r_enu_from_camera: np.ndarray, centre_enu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of x_cam = R X + t from a camera orientation and centre in ENU."""
    r = np.swapaxes(r_enu_from_camera, -1, -2)
    t = -np.einsum("...ij,...j->...i", r, centre_enu)
    return r, t
