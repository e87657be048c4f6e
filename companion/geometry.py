"""Rotations, pinhole camera model and projection. Pure numpy/scipy.

Conventions (DESIGN.md): world NED, body FRD, camera OpenCV (x right, y down, z optical axis).
Euler angles are roll, pitch, yaw in radians, intrinsic Z-Y-X (aerospace), so that
``R_world_body = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.constants import R_BODY_CAM_NADIR


def rot_from_rpy(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """3x3 R_world_body = Rz(yaw) Ry(pitch) Rx(roll) (NED/FRD, intrinsic Z-Y-X).

    Written out rather than through SciPy's Rotation: this runs for every attitude sample and frame, and
    Rotation's per-call overhead is several times the arithmetic."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def rpy_from_rot(R_world_body: np.ndarray) -> np.ndarray:
    """(3,) roll, pitch, yaw in radians from a 3x3 R_world_body (intrinsic Z-Y-X; at pitch +-90 deg, where
    roll and yaw are not separable, roll takes what arctan2 gives)."""
    R = R_world_body
    return np.array(
        [np.arctan2(R[2, 1], R[2, 2]), -np.arcsin(np.clip(R[2, 0], -1.0, 1.0)), np.arctan2(R[1, 0], R[0, 0])]
    )


def wrap_pi(angle_rad: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


def make_T(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a (3,) translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    R = T[:3, :3]
    return make_T(R.T, -R.T @ T[:3, 3])


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels; no distortion (frames are undistorted upstream)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @staticmethod
    def from_focal_sensor(width: int, height: int, focal_mm: float, sensor_mm: float) -> CameraIntrinsics:
        """Square pixels; ``sensor_mm`` spans max(width, height). 36 mm / 36 mm gives 53.13 deg FOV."""
        f_px = focal_mm / sensor_mm * max(width, height)
        return CameraIntrinsics(width, height, f_px, f_px, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def K(self) -> np.ndarray:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> CameraIntrinsics:
        """Intrinsics of the same camera resized by ``factor`` (pixel-centre convention kept)."""
        w = int(round(self.width * factor))
        h = int(round(self.height * factor))
        return CameraIntrinsics(
            w,
            h,
            self.fx * factor,
            self.fy * factor,
            (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5,
        )


def camera_pose(
    R_world_body: np.ndarray,
    p_body_in_world: np.ndarray,
    R_body_cam: np.ndarray = R_BODY_CAM_NADIR,
    p_cam_in_body: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(R_world_cam, p_cam_in_world) from the body pose and the camera extrinsics."""
    p_cb = np.zeros(3) if p_cam_in_body is None else np.asarray(p_cam_in_body, float)
    return R_world_body @ R_body_cam, p_body_in_world + R_world_body @ p_cb


def project(
    K: np.ndarray, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray, p_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project (N,3) world points. Returns (N,2) pixel coordinates and (N,) depths along z_cam.

    Points behind the camera get depth <= 0 and meaningless pixels; the caller masks them.
    """
    p_cam = (np.asarray(p_world, float) - p_cam_in_world) @ R_world_cam  # rows: R_cam_world @ (p - c)
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * p_cam[:, 0] / z + K[0, 2]
        v = K[1, 1] * p_cam[:, 1] / z + K[1, 2]
    return np.stack([u, v], axis=1), z


def pixel_rays_cam(intr: CameraIntrinsics) -> np.ndarray:
    """(H, W, 3) ray directions in the camera frame with z = 1 (not unit length)."""
    u = (np.arange(intr.width) - intr.cx) / intr.fx
    v = (np.arange(intr.height) - intr.cy) / intr.fy
    uu, vv = np.meshgrid(u, v)
    return np.stack([uu, vv, np.ones_like(uu)], axis=-1)
