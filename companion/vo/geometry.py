"""Multi-view geometry of the visual odometry (paper 1 section 4.2, eqs. 12-15): triangulation, PnP with
RANSAC (EPnP, then Levenberg-Marquardt refinement) and the two-view map initialisation.

Conventions: poses are ``T_world_cam`` (4, 4), camera-to-world (x_world = R x_cam + p); pixels (N, 2);
world points (N, 3); ``K`` (3, 3) pinhole matrix of undistorted images. OpenCV does the work.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from companion.geometry import invert_T, make_T


def projection_matrix(K: np.ndarray, T_world_cam: np.ndarray) -> np.ndarray:
    """(3, 4) P = K [R_cam_world | t_cam_world] mapping homogeneous world points to pixels."""
    return K @ invert_T(T_world_cam)[:3, :]


def reproject(K: np.ndarray, T_world_cam: np.ndarray, p_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) pixels and (N,) depths of world points seen from ``T_world_cam``."""
    p_cam = (np.asarray(p_world, float) - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    z = p_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (p_cam[:, :2] / z[:, None]) * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]
    return uv, z


@dataclass(frozen=True)
class TriangulationOptions:
    min_parallax_rad: float = float(np.radians(1.0))  # below this the depth is too uncertain to keep
    max_reprojection_px: float = 2.0  # both views must reproject within this
    min_depth_m: float = 1.0  # points closer than this to either camera are rejected
    max_depth_m: float = 5000.0  # and farther than this (near-infinite points fix no translation)


def triangulate(
    K: np.ndarray,
    T_world_cam1: np.ndarray,
    T_world_cam2: np.ndarray,
    px1: np.ndarray,
    px2: np.ndarray,
    options: TriangulationOptions = TriangulationOptions(),
) -> tuple[np.ndarray, np.ndarray]:
    """Linear (DLT) triangulation of (N, 2) matches between two posed views.

    Returns ((N, 3) world points, (N,) bool mask of points passing the depth, parallax and
    reprojection checks). Rejected points still hold their (meaningless) DLT value.
    """
    n = len(px1)
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, bool)
    P1 = projection_matrix(K, T_world_cam1)
    P2 = projection_matrix(K, T_world_cam2)
    X_h = cv2.triangulatePoints(P1, P2, np.asarray(px1, float).T, np.asarray(px2, float).T)
    w = X_h[3]
    ok = np.abs(w) > 1e-12
    p_world = np.full((n, 3), np.nan)
    p_world[ok] = (X_h[:3, ok] / w[ok]).T
    uv1, z1 = reproject(K, T_world_cam1, p_world)
    uv2, z2 = reproject(K, T_world_cam2, p_world)
    e1 = np.linalg.norm(uv1 - px1, axis=1)
    e2 = np.linalg.norm(uv2 - px2, axis=1)
    ray1 = p_world - T_world_cam1[:3, 3]
    ray2 = p_world - T_world_cam2[:3, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_par = np.sum(ray1 * ray2, axis=1) / (np.linalg.norm(ray1, axis=1) * np.linalg.norm(ray2, axis=1))
    parallax = np.arccos(np.clip(cos_par, -1.0, 1.0))
    with np.errstate(invalid="ignore"):
        ok &= (z1 > options.min_depth_m) & (z2 > options.min_depth_m)
        ok &= (z1 < options.max_depth_m) & (z2 < options.max_depth_m)
        ok &= (e1 < options.max_reprojection_px) & (e2 < options.max_reprojection_px)
        ok &= parallax > options.min_parallax_rad
    return p_world, ok


@dataclass(frozen=True)
class PnpOptions:
    ransac_threshold_px: float = 2.0  # inlier threshold of the EPnP RANSAC
    ransac_confidence: float = 0.999
    ransac_iterations: int = 100  # upper bound; OpenCV stops early once the confidence is reached
    min_inliers: int = 12  # fewer inliers than this: tracking is lost
    refine: bool = True  # Levenberg-Marquardt on the inliers after RANSAC


@dataclass(frozen=True)
class PnpResult:
    """ok: a pose was found with enough inliers. inliers: (N,) bool over the input points."""

    ok: bool
    T_world_cam: np.ndarray
    inliers: np.ndarray
    rms_px: float


def solve_pnp(
    K: np.ndarray, p_world: np.ndarray, px: np.ndarray, options: PnpOptions = PnpOptions()
) -> PnpResult:
    """Camera pose from (N, 3) world points and their (N, 2) pixels: EPnP in RANSAC, then LM on inliers."""
    n = len(px)
    fail = PnpResult(False, np.eye(4), np.zeros(n, bool), float("inf"))
    if n < max(options.min_inliers, 6):
        return fail
    obj = np.ascontiguousarray(p_world, dtype=np.float64)
    img = np.ascontiguousarray(px, dtype=np.float64)
    # Centre the object points: EPnP's conditioning and the LM step are better near the origin
    # (world coordinates may be kilometres from it).
    centre = obj.mean(axis=0)
    obj_c = obj - centre
    ok, rvec, tvec, idx = cv2.solvePnPRansac(
        obj_c,
        img,
        K,
        None,
        iterationsCount=options.ransac_iterations,
        reprojectionError=options.ransac_threshold_px,
        confidence=options.ransac_confidence,
        flags=cv2.SOLVEPNP_EPNP,
    )
    if not ok or idx is None or len(idx) < options.min_inliers:
        return fail
    inl = np.zeros(n, bool)
    inl[idx.ravel()] = True
    if options.refine:
        rvec, tvec = cv2.solvePnPRefineLM(obj_c[inl], img[inl], K, None, rvec, tvec)
    R_cam_world, _ = cv2.Rodrigues(rvec)
    T_cam_world = make_T(R_cam_world, tvec.ravel() - R_cam_world @ centre)
    T_world_cam = invert_T(T_cam_world)
    uv, z = reproject(K, T_world_cam, obj)
    err = np.linalg.norm(uv - img, axis=1)
    with np.errstate(invalid="ignore"):
        inl = (err < options.ransac_threshold_px) & (z > 0)
    if inl.sum() < options.min_inliers:
        return fail
    return PnpResult(True, T_world_cam, inl, float(np.sqrt(np.mean(err[inl] ** 2))))


@dataclass(frozen=True)
class TwoViewOptions:
    ransac_threshold_rad: float = 2.0e-3  # angular epipolar residual for inliers (about 1 px at f = 480)
    ransac_iterations: int = 200
    min_inliers: int = 30
    seed: int = 0
    # the second view's rotation refined from the matches, the attitude's as its prior with this 1 sigma
    # (rad, the relative rotation of two attitude samples); 0 = the attitude's rotation taken as exact
    rotation_prior_sigma_rad: float = 0.0
    epipolar_sigma_rad: float = 1.0e-3  # 1 sigma of a match's epipolar residual (about 0.5 px at f = 480)
    refine_rounds: int = 2  # inliers re-selected, rotation and direction re-fitted


def translation_known_rotation(
    K: np.ndarray,
    R_world_cam0: np.ndarray,
    R_world_cam1: np.ndarray,
    px0: np.ndarray,
    px1: np.ndarray,
    options: TwoViewOptions = TwoViewOptions(),
) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction of the camera's displacement (world frame) between two views of known attitude.

    Hand-written instead of cv2.findEssentialMat + recoverPose: nadir views of gently rolling terrain
    are nearly planar, where the five-point essential matrix has two valid decompositions; with the
    rotation known from the autopilot's attitude the epipolar constraint is linear in the displacement,
    (b0 x b1) . d = 0 for the world-frame bearings b0, b1, so two matches give d (RANSAC over pairs,
    then least squares on the inliers). Returns ((3,) unit d in world, (N,) bool inliers).
    """
    Kinv = np.linalg.inv(K)
    h0 = np.c_[px0, np.ones(len(px0))] @ Kinv.T
    h1 = np.c_[px1, np.ones(len(px1))] @ Kinv.T
    b0 = h0 @ R_world_cam0.T
    b1 = h1 @ R_world_cam1.T
    b0 /= np.linalg.norm(b0, axis=1, keepdims=True)
    b1 /= np.linalg.norm(b1, axis=1, keepdims=True)
    A = np.cross(b0, b1)  # rows: normals of the epipolar planes, each orthogonal to d
    n = len(A)
    if n < options.min_inliers:
        return np.zeros(3), np.zeros(n, bool)
    rng = np.random.default_rng(options.seed)
    best = np.zeros(n, bool)
    for _ in range(options.ransac_iterations):
        i, j = rng.choice(n, 2, replace=False)
        d = np.cross(A[i], A[j])
        nd = np.linalg.norm(d)
        if nd < 1e-12:
            continue
        inl = np.abs(A @ (d / nd)) < options.ransac_threshold_rad
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < options.min_inliers:
        return np.zeros(3), best
    _, _, Vt = np.linalg.svd(A[best])
    d = Vt[-1]
    # sign: with c1 = c0 + s d (s > 0) and X = c0 + l0 b0 = c1 + l1 b1 (l0, l1 > 0), crossing with b0
    # gives b0 x d = -(l1 / s) (b0 x b1): the two cross products point in opposite directions.
    if np.sum(np.einsum("ij,ij->i", np.cross(b0[best], d), A[best])) > 0:
        d = -d
    inl = best & (np.abs(A @ d) < options.ransac_threshold_rad)
    return d, inl


def _epipolar_residuals(b0: np.ndarray, b1: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(N,) (b0 x b1) . d for unit world bearings and a unit displacement: zero on the epipolar plane."""
    return np.cross(b0, b1) @ d


def relative_pose_rotation_prior(
    K: np.ndarray,
    R_world_cam0: np.ndarray,
    R_world_cam1: np.ndarray,
    px0: np.ndarray,
    px1: np.ndarray,
    options: TwoViewOptions = TwoViewOptions(),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The second view's rotation and the unit displacement between two views, the rotation from the
    autopilot's attitude as a prior (``options.rotation_prior_sigma_rad``).

    At a map's initialisation the parallax is small (25 px), so an attitude sample's noise (a few mrad, about
    2 px at f = 500) turns the displacement by several degrees and mis-scales the map by 10-20 % (measured on
    the Table 7 flights of ``bench terrain_slam``), while the matches pin the relative rotation far better.
    Minimises the epipolar residuals (Huber) of the inliers plus the rotation's prior, over a small turn of
    the second view (world frame) and the displacement, with ``scipy.optimize.least_squares``; by hand
    because OpenCV's two-view solvers take no prior and the five-point essential matrix is ambiguous on
    nearly planar terrain (see ``translation_known_rotation``). Inliers come from ``translation_known_rotation``
    with the threshold widened to what the prior's sigma can explain, then at the normal threshold with the
    refined rotation. Returns ((3, 3) refined R_world_cam1, (3,) unit d in world, (N,) bool inliers); with a
    zero sigma, the attitude's rotation and ``translation_known_rotation``'s answer.
    """
    if options.rotation_prior_sigma_rad <= 0:
        d, inl = translation_known_rotation(K, R_world_cam0, R_world_cam1, px0, px1, options)
        return R_world_cam1, d, inl
    Kinv = np.linalg.inv(K)
    b0 = np.c_[px0, np.ones(len(px0))] @ Kinv.T @ R_world_cam0.T
    b0 /= np.linalg.norm(b0, axis=1, keepdims=True)
    h1 = np.c_[px1, np.ones(len(px1))] @ Kinv.T
    h1 /= np.linalg.norm(h1, axis=1, keepdims=True)
    wide = replace(
        options,
        ransac_threshold_rad=options.ransac_threshold_rad + 2.0 * options.rotation_prior_sigma_rad,
    )
    d, inl = translation_known_rotation(K, R_world_cam0, R_world_cam1, px0, px1, wide)
    if inl.sum() < options.min_inliers:
        return R_world_cam1, d, inl
    R1 = R_world_cam1
    for _ in range(max(options.refine_rounds, 1)):
        b0i, h1i = b0[inl], h1[inl]

        def residuals(x: np.ndarray, b0i: np.ndarray = b0i, h1i: np.ndarray = h1i) -> np.ndarray:
            R = Rotation.from_rotvec(x[:3]).as_matrix() @ R_world_cam1
            dd = x[3:] / np.linalg.norm(x[3:])
            r = _epipolar_residuals(b0i, h1i @ R.T, dd) / options.epipolar_sigma_rad
            return np.concatenate(
                [r, x[:3] / options.rotation_prior_sigma_rad, [np.linalg.norm(x[3:]) - 1.0]]
            )

        x0 = np.concatenate([Rotation.from_matrix(R1 @ R_world_cam1.T).as_rotvec(), d])
        sol = least_squares(residuals, x0, loss="huber", f_scale=2.0, x_scale="jac")
        R1 = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R_world_cam1
        d = sol.x[3:] / np.linalg.norm(sol.x[3:])
        b1 = h1 @ R1.T
        if np.sum(np.einsum("ij,ij->i", np.cross(b0, d), np.cross(b0, b1))) > 0:
            d = -d  # the sign as in translation_known_rotation
        inl = np.abs(_epipolar_residuals(b0, b1, d)) < options.ransac_threshold_rad
        if inl.sum() < options.min_inliers:
            break
    return R1, d, inl
