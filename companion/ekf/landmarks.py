"""Inverse-depth point landmarks (paper 2 eq. 5; Civera, Davison, Montiel, IEEE T-RO 24(5), 2008).

A landmark is y = (x0, y0, z0, theta, phi, rho): the world position of the camera optical centre that
first saw it, the azimuth / elevation of the ray in the world frame and the inverse of the depth along
the ray. Its Euclidean position is p = (x0, y0, z0) + m(theta, phi) / rho with Civera's unit ray

    m(theta, phi) = (cos(phi) sin(theta), -sin(phi), cos(phi) cos(theta)).

Civera writes m in an arbitrary world frame; we apply it unchanged in world NED. Its singular
direction (theta undefined) is a ray along +-east (world y), far from the nadir rays this project
sees: a straight-down ray has theta = phi = 0.

Pose perturbations follow Solà's local convention (see ``so3``): R_world_body_true = R Exp(dtheta).
All functions are vectorised over landmarks; shapes are given in each docstring.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.ekf.so3 import skew

LANDMARK_DIM = 6
"""Length of one inverse-depth landmark (x0, y0, z0, theta, phi, rho)."""


def ray_from_angles(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(N,3) unit rays m(theta, phi) in world NED from (N,) azimuths and elevations."""
    cp = np.cos(phi)
    return np.stack([cp * np.sin(theta), -np.sin(phi), cp * np.cos(theta)], axis=-1)


def angles_from_ray(h_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(theta, phi), each (N,), of (N,3) world rays (any length); inverse of ``ray_from_angles``."""
    x, y, z = h_world[..., 0], h_world[..., 1], h_world[..., 2]
    return np.arctan2(x, z), np.arctan2(-y, np.hypot(x, z))


def _dangles_dray(h_world: np.ndarray) -> np.ndarray:
    """(N,2,3) Jacobian of (theta, phi) with respect to the (unnormalised) world ray."""
    x, y, z = h_world[:, 0], h_world[:, 1], h_world[:, 2]
    s2 = x * x + z * z
    s = np.sqrt(s2)
    n2 = s2 + y * y
    J = np.zeros((len(h_world), 2, 3))
    J[:, 0, 0] = z / s2
    J[:, 0, 2] = -x / s2
    J[:, 1, 0] = x * y / (n2 * s)
    J[:, 1, 1] = -s / n2
    J[:, 1, 2] = z * y / (n2 * s)
    return J


def _dray_dangles(theta: np.ndarray, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,3) derivatives dm/dtheta and dm/dphi."""
    ct, st, cp, sp = np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi)
    dm_dt = np.stack([cp * ct, np.zeros_like(ct), -cp * st], axis=-1)
    dm_dp = np.stack([-sp * st, -cp, -sp * ct], axis=-1)
    return dm_dt, dm_dp


def to_euclidean(y: np.ndarray) -> np.ndarray:
    """(N,3) world points of (N,6) inverse-depth landmarks (rho must be > 0)."""
    return y[:, :3] + ray_from_angles(y[:, 3], y[:, 4]) / y[:, 5:6]


def to_euclidean_jacobian(y: np.ndarray) -> np.ndarray:
    """(N,3,6) Jacobian of ``to_euclidean`` with respect to (x0, y0, z0, theta, phi, rho)."""
    rho = y[:, 5]
    m = ray_from_angles(y[:, 3], y[:, 4])
    dm_dt, dm_dp = _dray_dangles(y[:, 3], y[:, 4])
    J = np.zeros((len(y), 3, 6))
    J[:, :, :3] = np.eye(3)
    J[:, :, 3] = dm_dt / rho[:, None]
    J[:, :, 4] = dm_dp / rho[:, None]
    J[:, :, 5] = -m / (rho * rho)[:, None]
    return J


def linearity_index(y: np.ndarray, sigma_rho: np.ndarray, p_cam_in_world: np.ndarray) -> np.ndarray:
    """(N,) Civera's linearity index L_d = 4 sigma_d / d^2 |m . (x0 - c)|; small means nearly Euclidean."""
    m = ray_from_angles(y[:, 3], y[:, 4])
    p = to_euclidean(y)
    d = np.linalg.norm(p - p_cam_in_world, axis=1)
    sigma_d = sigma_rho / y[:, 5] ** 2
    cos_a = np.abs(np.einsum("ni,ni->n", m, p - p_cam_in_world)) / np.maximum(d, 1e-9)
    return 4.0 * sigma_d / np.maximum(d, 1e-9) * cos_a


@dataclass(frozen=True)
class CameraModel:
    """One camera for the filter: pinhole K (3,3), image size, extrinsics R_body_cam (3,3), p_cam_in_body (3,)."""

    K: np.ndarray
    width: int
    height: int
    R_body_cam: np.ndarray
    p_cam_in_body: np.ndarray


@dataclass(frozen=True)
class Projection:
    """Predicted measurements of N landmarks in one camera.

    uv: (N,2) pixels; depth: (N,) z in the camera frame of the (rho-scaled) ray, > 0 in front;
    H_pose: (N,2,6) Jacobian w.r.t. (dr, dtheta) of the vehicle; H_lm: (N,2,6) w.r.t. the landmark.
    """

    uv: np.ndarray
    depth: np.ndarray
    H_pose: np.ndarray
    H_lm: np.ndarray


def project(y: np.ndarray, r_world: np.ndarray, R_world_body: np.ndarray, cam: CameraModel) -> Projection:
    """Civera's measurement model for (N,6) landmarks seen from body pose (r_world (3,), R_world_body).

    h_cam = R_cam_world (rho (x0 - p_cam) + m): the ray scaled by rho, which stays finite as rho -> 0.
    """
    R_wb = R_world_body
    R_bc = cam.R_body_cam
    R_cw = R_bc.T @ R_wb.T
    rho = y[:, 5]
    m = ray_from_angles(y[:, 3], y[:, 4])
    # w: rho-scaled landmark direction from the body origin, in body axes
    d_world = rho[:, None] * (y[:, :3] - r_world) + m
    w_body = d_world @ R_wb
    h = (w_body - rho[:, None] * cam.p_cam_in_body) @ R_bc
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    z = h[:, 2]
    zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
    uv = np.stack([fx * h[:, 0] / zs + cx, fy * h[:, 1] / zs + cy], axis=1)
    n = len(y)
    J_proj = np.zeros((n, 2, 3))
    J_proj[:, 0, 0] = fx / zs
    J_proj[:, 0, 2] = -fx * h[:, 0] / zs**2
    J_proj[:, 1, 1] = fy / zs
    J_proj[:, 1, 2] = -fy * h[:, 1] / zs**2
    # dh/d(dr) = -rho R_cw ; dh/d(dtheta) = R_bc^T [w_body]x
    dh_dr = -rho[:, None, None] * R_cw[None]
    wx = np.zeros((n, 3, 3))
    wx[:, 0, 1], wx[:, 0, 2] = -w_body[:, 2], w_body[:, 1]
    wx[:, 1, 0], wx[:, 1, 2] = w_body[:, 2], -w_body[:, 0]
    wx[:, 2, 0], wx[:, 2, 1] = -w_body[:, 1], w_body[:, 0]
    dh_dth = np.einsum("ij,njk->nik", R_bc.T, wx)
    dm_dt, dm_dp = _dray_dangles(y[:, 3], y[:, 4])
    p_cam = r_world + R_wb @ cam.p_cam_in_body
    dh_dy = np.empty((n, 3, 6))
    dh_dy[:, :, :3] = rho[:, None, None] * R_cw[None]
    dh_dy[:, :, 3] = dm_dt @ R_cw.T
    dh_dy[:, :, 4] = dm_dp @ R_cw.T
    dh_dy[:, :, 5] = (y[:, :3] - p_cam) @ R_cw.T
    H_pose = np.concatenate([J_proj @ dh_dr, J_proj @ dh_dth], axis=2)
    H_lm = J_proj @ dh_dy
    return Projection(uv, z, H_pose, H_lm)


def initialise(
    uv: np.ndarray,
    rho0: np.ndarray,
    r_world: np.ndarray,
    R_world_body: np.ndarray,
    cam: CameraModel,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """New landmarks from (N,2) pixels with prior inverse depths rho0 (N,) (Civera's initialisation).

    Returns y (N,6), J_pose (N,6,6) = dy/d(dr, dtheta) and J_uv (N,6,2) = dy/d(u, v); dy/drho = e6.
    """
    R_wc = R_world_body @ cam.R_body_cam
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    n = len(uv)
    h_cam = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fy, np.ones(n)], axis=1)
    h_world = h_cam @ R_wc.T
    theta, phi = angles_from_ray(h_world)
    p_cam = r_world + R_world_body @ cam.p_cam_in_body
    y = np.concatenate([np.tile(p_cam, (n, 1)), theta[:, None], phi[:, None], rho0[:, None]], axis=1)
    dA = _dangles_dray(h_world)  # (n,2,3)
    J_pose = np.zeros((n, 6, 6))
    J_pose[:, :3, :3] = np.eye(3)
    J_pose[:, :3, 3:] = -R_world_body @ skew(cam.p_cam_in_body)
    # h_world = R_wb Exp(dtheta) R_bc h_cam -> d h_world / d dtheta = -R_wb [R_bc h_cam]x
    hb = h_cam @ cam.R_body_cam.T
    hbx = np.zeros((n, 3, 3))
    hbx[:, 0, 1], hbx[:, 0, 2] = -hb[:, 2], hb[:, 1]
    hbx[:, 1, 0], hbx[:, 1, 2] = hb[:, 2], -hb[:, 0]
    hbx[:, 2, 0], hbx[:, 2, 1] = -hb[:, 1], hb[:, 0]
    J_pose[:, 3:5, 3:] = dA @ (-R_world_body @ hbx)
    J_uv = np.zeros((n, 6, 2))
    dhw_duv = np.stack([R_wc[:, 0] / fx, R_wc[:, 1] / fy], axis=1)  # (3,2)
    J_uv[:, 3:5, :] = dA @ dhw_duv
    return y, J_pose, J_uv
