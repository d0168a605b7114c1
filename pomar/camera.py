"""Pinhole camera as stored in a flight's camera.json.

camera.json holds a COLMAP camera (``model``, ``width``, ``height``, ``params``) in COLMAP's
pixel convention (top-left pixel centre at (0.5, 0.5)), plus the camera's mounting on the
gimbal. Detections and truth in this project use OpenCV's convention (top-left pixel centre
at (0, 0)); :meth:`Camera.project` returns that, and ``COLMAP_TO_OPENCV_PX`` converts.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pomar.cli import InputError
from pomar.rotations import R_GIMBAL_FROM_CAMERA_NOMINAL, quat_wxyz_to_rotation, rotation_to_quat_wxyz
from scipy.spatial.transform import Rotation

#: Subtract from a COLMAP pixel coordinate to get the OpenCV one.
COLMAP_TO_OPENCV_PX = 0.5

SUPPORTED_MODELS = {"PINHOLE": 4, "SIMPLE_PINHOLE": 3}


class CameraFileError(InputError, ValueError):
    """camera.json is missing, malformed, or describes an unsupported camera."""


@dataclass
class Camera:
    width: int
    height: int
    fx: float
    fy: float
    cx: float  # COLMAP convention
    cy: float  # COLMAP convention
    model: str = "PINHOLE"
    #: Rotation taking camera-frame vectors to the gimbal (FRD) frame.
    r_gimbal_from_camera: np.ndarray = field(default_factory=lambda: R_GIMBAL_FROM_CAMERA_NOMINAL.copy())
    #: Camera centre in the vehicle body frame (FRD, metres) relative to the GPS position.
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> "Camera":
        f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
        return cls(width, height, f, f, width / 2.0, height / 2.0)

    @property
    def K(self) -> np.ndarray:
        """Calibration matrix in COLMAP's pixel convention."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def K_opencv(self) -> np.ndarray:
        """Calibration matrix in OpenCV's pixel convention (top-left pixel centre at 0, 0)."""
        k = self.K
        k[0, 2] -= COLMAP_TO_OPENCV_PX
        k[1, 2] -= COLMAP_TO_OPENCV_PX
        return k

    def projection_matrix(self, R: np.ndarray, t: np.ndarray, opencv: bool = True) -> np.ndarray:
        """3x4 P = K [R | t] for a world-to-camera pose."""
        k = self.K_opencv if opencv else self.K
        return k @ np.hstack([R, np.reshape(t, (3, 1))])

    def project(self, X_world: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project (N, 3) world points: returns (N, 2) pixels (OpenCV convention) and (N,) depths."""
        xc = np.asarray(X_world, float) @ R.T + t
        z = xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * xc[:, 0] / z + self.cx - COLMAP_TO_OPENCV_PX
            v = self.fy * xc[:, 1] / z + self.cy - COLMAP_TO_OPENCV_PX
        return np.stack([u, v], axis=1), z

    def params(self) -> list[float]:
        if self.model == "SIMPLE_PINHOLE":
            return [self.fx, self.cx, self.cy]
        return [self.fx, self.fy, self.cx, self.cy]

    def to_dict(self) -> dict:
        return {
            "model": self.model,
            "width": self.width,
            "height": self.height,
            "params": [float(p) for p in self.params()],
            "pixel_convention": "COLMAP: top-left pixel centre at (0.5, 0.5)",
            "mount": {
                "q_gimbal_from_camera_wxyz": [
                    float(x) for x in rotation_to_quat_wxyz(Rotation.from_matrix(self.r_gimbal_from_camera))
                ],
                "lever_arm_body_frd_m": [float(x) for x in self.lever_arm_m],
                "note": "camera axes x right, y down, z optical axis; gimbal FRD (x along the optical axis)",
            },
        }

    @classmethod
    def from_dict(cls, d: dict, source: str = "camera.json") -> "Camera":
        try:
            model = d["model"]
            if model not in SUPPORTED_MODELS:
                raise CameraFileError(f"{source}: camera model {model!r} is not supported (use one of {sorted(SUPPORTED_MODELS)})")
            params = [float(p) for p in d["params"]]
            if len(params) != SUPPORTED_MODELS[model]:
                raise CameraFileError(f"{source}: model {model} needs {SUPPORTED_MODELS[model]} params, got {len(params)}")
            if model == "SIMPLE_PINHOLE":
                fx = fy = params[0]
                cx, cy = params[1:]
            else:
                fx, fy, cx, cy = params
            cam = cls(int(d["width"]), int(d["height"]), fx, fy, cx, cy, model)
            mount = d.get("mount", {})
            if "q_gimbal_from_camera_wxyz" in mount:
                cam.r_gimbal_from_camera = quat_wxyz_to_rotation(mount["q_gimbal_from_camera_wxyz"]).as_matrix()
            if "lever_arm_body_frd_m" in mount:
                cam.lever_arm_m = tuple(float(x) for x in mount["lever_arm_body_frd_m"])
        except KeyError as exc:
            raise CameraFileError(f"{source}: missing key {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            if isinstance(exc, CameraFileError):
                raise
            raise CameraFileError(f"{source}: {exc}") from None
        if cam.width <= 0 or cam.height <= 0 or cam.fx <= 0 or cam.fy <= 0:
            raise CameraFileError(f"{source}: width, height and focal length must be positive")
        return cam

    @classmethod
    def load(cls, path: str | Path) -> "Camera":
        path = Path(path)
        try:
            d = json.loads(path.read_text())
        except FileNotFoundError:
            raise CameraFileError(f"{path}: file not found") from None
        except IsADirectoryError:
            raise CameraFileError(f"{path}: is a folder, not a camera.json") from None
        except UnicodeDecodeError:
            raise CameraFileError(f"{path}: not a camera.json (binary, not JSON text)") from None
        except json.JSONDecodeError as exc:
            raise CameraFileError(f"{path}: not valid JSON ({exc})") from None
        if not isinstance(d, dict):
            raise CameraFileError(f"{path}: not a camera.json (JSON, but not an object of camera fields)")
        return cls.from_dict(d, str(path))

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")
