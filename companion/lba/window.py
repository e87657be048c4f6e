"""Sliding-window local bundle adjustment with the geo-referencing term (paper 1 section 4.3, eqs. 22-24),
in GTSAM, solved by Levenberg-Marquardt, with the marginal covariances of the key-frame poses.

Cost (eq. 23), written as GTSAM factors:
- reprojection (eq. 22): ``GenericProjectionFactorCal3_S2`` per observation, isotropic pixel sigma
  (eq. 22's weight w_i = 1 / sigma_px^2) behind a robust kernel (Huber or Cauchy);
- geo-referencing (eqs. 23-24): ``GPSFactorArm`` per geo-referenced key frame: the x, y, z deviation
  between the geo-referenced point and the same point placed by the camera pose (a point fixed in the
  camera frame: the body origin, or the ground point on the optical axis, see ``lba.backend``), weighted
  by the confidence w_G: covariance = the fix's covariance / w_G (w_G = 0 drops the term), behind a robust
  kernel; optionally (``geo_bias_share`` > 0) part of each fix's horizontal variance is a bias variable per
  key frame (``biased_geo_factor``), zero-mean and a random walk from one fixed key frame to the next, so
  that fixes whose errors are correlated in time count as fewer (each window starts the chain afresh; the
  whitened residuals reported include the bias, against the fix's whole variance);
- gravity: ``AttitudeFactorPose3`` per key frame: the down direction measured by the autopilot's
  attitude (roll and pitch; yaw is left free, a compass bias must not enter);
- key frames outside the window that see the window's points ("anchors", as ORB-SLAM's fixed key
  frames) are held by a pose prior with their last marginal covariance (or pinned when none is known);
- terrain height (optional, ``terrain_sigma_m`` > 0; not in the paper): each landmark lies on the DEM.
  The surface z + h(n, e) = 0 (NED) is linearised at the landmark's initial position, so the factor is a
  ``PriorFactorPoint3`` whose information g g^T / sigma^2 (g = (dh/dn, dh/de, 1)) constrains only the
  vertical misfit, sigma^2 = sigma_v^2 + |grad h|^2 sigma_h^2 (the usual DEM error model: a horizontal
  error of the DEM is a height error on a slope): the map's heights, its tilt and, on sloping ground, its
  horizontal position are then tied to the DEM's geometry, which the shading of the geo-fixes (albedo,
  sun) does not bias.

Poses are ``T_world_cam`` (4, 4); GTSAM's Pose3 tangent is (rotation, translation) in the camera frame.
Pure math: numpy + gtsam.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, L, X

from companion.ekf.so3 import skew
from companion.geometry import rpy_from_rot

_DOWN_WORLD = np.array([0.0, 0.0, 1.0])  # NED: gravity points along +z


@dataclass(frozen=True)
class LbaOptions:
    pixel_sigma_px: float = 1.0  # reprojection noise, 1 sigma (eq. 22: w_i = 1 / sigma^2)
    reprojection_kernel: str = "huber"  # robust loss on reprojection: "huber", "cauchy" or "none"
    reprojection_kernel_k: float = 1.345  # kernel width, in sigmas
    w_geo: float = 10.0  # eq. 23 confidence w_G of the geo-referencing term; 0 = terrain-free (pure VO)
    geo_kernel: str = "huber"  # robust loss on the geo term
    geo_kernel_k: float = 1.345  # in sigmas of the weighted geo covariance
    gravity_sigma_rad: float = 0.003  # roll/pitch prior from the autopilot (1 sigma); 0 = none. The
    # simulated autopilot's attitude noise (``SimNoise.roll_pitch_rad``, a converged EKF3's ~0.2 deg); 0.005
    # before, measured looser than needed: at 100 m a tilt error of 0.1 deg moves the camera 0.17 m sideways
    # for the same ground point, so this prior sets much of the horizontal accuracy
    anchor_cov_inflation: float = 2.0  # anchors' marginal covariance x this (their information was
    # partly built from factors still in the window: counting it twice would be over-confident)
    pinned_sigma: float = 1e-4  # sigma (rad, m) of a pinned anchor whose covariance is unknown
    max_iterations: int = 15  # Levenberg-Marquardt iterations
    relative_error_tol: float = 1e-5
    outlier_chi2: float = 9.21  # after the solve, observations with whitened squared error above this
    # (2 dof, p = 0.01) are reported as outliers for the front-end to cull
    marginals: bool = True  # compute the key-frame marginal covariances
    terrain_sigma_m: float = 0.0  # landmark-on-DEM term: vertical sigma (DEM error + the feature's height
    # above the DEM surface); 0 = off
    terrain_sigma_horizontal_m: float = 0.5  # the DEM's horizontal error: on a slope s it adds s x this to
    # the vertical sigma (a steep wall's height is uncertain, and its linearisation poor)
    terrain_kernel: str = "huber"
    terrain_kernel_k: float = 1.345
    geo_bias_share: float = 0.5  # share of each fix's horizontal variance modelled as a bias correlated
    # between consecutive key frames (a random walk plus a zero-mean prior per key frame); 0 = white fixes
    geo_bias_corr_kf: float = 10.0  # its correlation length, in key frames


@dataclass(frozen=True)
class WindowProblem:
    """One local bundle adjustment.

    T_world_cam: (M, 4, 4) initial key-frame camera poses. anchor: (M,) bool, True for key frames held
        by a prior (outside the window). anchor_cov: (M, 6, 6) Pose3-tangent covariance of each anchor's
        prior, NaN where unknown (then pinned).
    p_world: (L, 3) initial landmark positions.
    obs_kf, obs_lm: (O,) indices into the poses and landmarks; obs_px: (O, 2) measured pixels.
    K: (3, 3) camera matrix.
    geo_p_world: (M, 3) geo-referenced point per key frame, NaN rows where none; geo_lever_cam: (M, 3) the
        point of the camera frame it locates (the body origin, or the ground point on the optical axis).
    geo_cov: (M, 3, 3) its covariance (m^2) before the w_G weighting.
    down_cam: (M, 3) gravity direction in the camera frame from the autopilot's attitude, NaN where none.
    lm_ground: (L, 5) per landmark the DEM at its initial position: north, east, down of the surface point
        below it and the surface slopes dh/dn, dh/de; NaN rows where none (off the DEM, in a hole). None: no
        terrain term.
    """

    T_world_cam: np.ndarray
    anchor: np.ndarray
    anchor_cov: np.ndarray
    p_world: np.ndarray
    obs_kf: np.ndarray
    obs_lm: np.ndarray
    obs_px: np.ndarray
    K: np.ndarray
    geo_p_world: np.ndarray
    geo_lever_cam: np.ndarray
    geo_cov: np.ndarray
    down_cam: np.ndarray
    lm_ground: np.ndarray | None = None


@dataclass(frozen=True)
class WindowSolution:
    """T_world_cam: (M, 4, 4); p_world: (L, 3); cov: (M, 6, 6) marginal Pose3-tangent covariances (NaN when
    not computed); obs_inlier: (O,) bool; geo_whitened: (M,) whitened geo residual norm at the solution
    (NaN without a fix); error_initial / error_final: graph cost; iterations; ok."""

    T_world_cam: np.ndarray
    p_world: np.ndarray
    cov: np.ndarray
    obs_inlier: np.ndarray
    geo_whitened: np.ndarray
    error_initial: float
    error_final: float
    iterations: int
    ok: bool
    geo_bias: np.ndarray | None = None  # (M, 3) the fixes' bias (``LbaOptions.geo_bias_share``), None = none


def robust(base: gtsam.noiseModel.Base, kernel: str, k: float) -> gtsam.noiseModel.Base:
    """``base`` behind an M-estimator: "huber", "cauchy" or "none"."""
    if kernel == "none":
        return base
    if kernel == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k), base)
    if kernel == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(k), base)
    raise ValueError(f"unknown robust kernel {kernel!r}, expected 'huber', 'cauchy' or 'none'")


def geo_factor(
    key: int, geo_p_world: np.ndarray, lever_cam: np.ndarray, noise: gtsam.noiseModel.Base
) -> gtsam.NonlinearFactor:
    """Eq. 24 as a GTSAM factor on the camera pose: error = T_world_cam * lever_cam - geo_p_world, the x, y, z
    deviation between the geo-referenced point and where the VO pose puts the same point of the camera."""
    return gtsam.GPSFactorArm(key, np.asarray(geo_p_world, float), np.asarray(lever_cam, float), noise)


def lever_point_jacobian(R: np.ndarray, lever_cam: np.ndarray) -> np.ndarray:
    """(3, 6) derivative of the world point R lever + t under the Pose3 tangent (rotation, translation),
    both in the camera frame."""
    return R @ np.hstack([-skew(lever_cam), np.eye(3)])


def geo_residual(
    problem: WindowProblem, T_world_cam: np.ndarray, geo_bias: np.ndarray | None, i: int
) -> np.ndarray:
    """(3,) key frame i's geo residual at the poses T_world_cam: where the pose puts the fix's camera-frame
    point, plus the fix's bias when modelled, minus the fix."""
    R = T_world_cam[i, :3, :3]
    r = R @ problem.geo_lever_cam[i] + T_world_cam[i, :3, 3] - problem.geo_p_world[i]
    return r if geo_bias is None else r + geo_bias[i]


def biased_geo_factor(
    key: int, bias_key: int, geo_p_world: np.ndarray, lever_cam: np.ndarray, noise: gtsam.noiseModel.Base
) -> gtsam.NonlinearFactor:
    """``geo_factor`` with the fix's correlated bias b (a Point3 variable): error = T_world_cam * lever_cam + b
    - geo_p_world. Written by hand as a Python ``CustomFactor`` (one callback per fix and iteration): GTSAM
    has no factor of a pose and a point of this form."""
    g = np.asarray(geo_p_world, float)
    lever = np.asarray(lever_cam, float)

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[np.ndarray] | None) -> np.ndarray:
        T = v.atPose3(this.keys()[0])
        b = v.atPoint3(this.keys()[1])
        R = T.rotation().matrix()
        if H is not None:
            H[0] = lever_point_jacobian(R, lever)
            H[1] = np.eye(3)
        return R @ lever + T.translation() + b - g

    return gtsam.CustomFactor(noise, [key, bias_key], error)


def geo_noise(cov: np.ndarray, w_geo: float, options: LbaOptions) -> gtsam.noiseModel.Base:
    """Noise model of eq. 23's geo term: Gaussian with covariance cov / w_G behind the geo kernel."""
    base = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, float) / w_geo)
    return robust(base, options.geo_kernel, options.geo_kernel_k)


def build_graph(
    problem: WindowProblem, options: LbaOptions
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int]]:
    """The factor graph, initial values and the graph index of each geo factor (-1 where none)."""
    K = problem.K
    cal = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    M = len(problem.T_world_cam)
    for i in range(M):
        values.insert(X(i), gtsam.Pose3(problem.T_world_cam[i]))
    for j, p in enumerate(problem.p_world):
        values.insert(L(j), np.asarray(p, float))
    pix = robust(
        gtsam.noiseModel.Isotropic.Sigma(2, options.pixel_sigma_px),
        options.reprojection_kernel,
        options.reprojection_kernel_k,
    )
    for i, j, uv in zip(problem.obs_kf, problem.obs_lm, problem.obs_px):
        graph.add(gtsam.GenericProjectionFactorCal3_S2(np.asarray(uv, float), pix, X(int(i)), L(int(j)), cal))
    pinned = gtsam.noiseModel.Isotropic.Sigma(6, options.pinned_sigma)
    for ia in np.flatnonzero(problem.anchor):
        cov = problem.anchor_cov[ia]
        prior: gtsam.noiseModel.Base = pinned
        if np.all(np.isfinite(cov)):
            prior = gtsam.noiseModel.Gaussian.Covariance(cov * options.anchor_cov_inflation)
        graph.add(gtsam.PriorFactorPose3(X(int(ia)), gtsam.Pose3(problem.T_world_cam[ia]), prior))
    if options.gravity_sigma_rad > 0:
        grav = gtsam.noiseModel.Isotropic.Sigma(2, options.gravity_sigma_rad)
        n_ref = gtsam.Unit3(_DOWN_WORLD)
        for i in range(M):
            d = problem.down_cam[i]
            if problem.anchor[i] or not np.all(np.isfinite(d)):
                continue
            graph.add(gtsam.AttitudeFactorPose3(X(i), n_ref, grav, gtsam.Unit3(d)))
    geo_index = [-1] * M
    if options.w_geo > 0:
        rho = options.geo_bias_share
        prev = -1
        for i in range(M):
            g = problem.geo_p_world[i]
            if problem.anchor[i] or not np.all(np.isfinite(g)):
                continue
            geo_index[i] = graph.size()
            if rho <= 0:
                noise = geo_noise(problem.geo_cov[i], options.w_geo, options)
                graph.add(geo_factor(X(i), g, problem.geo_lever_cam[i], noise))
                continue
            noise = geo_noise(problem.geo_cov[i] * (1.0 - rho), options.w_geo, options)
            graph.add(biased_geo_factor(X(i), B(i), g, problem.geo_lever_cam[i], noise))
            cb = problem.geo_cov[i] * rho / options.w_geo
            cb = np.diag([cb[0, 0], cb[1, 1], 1e-6])  # horizontal only
            values.insert(B(i), np.zeros(3))
            graph.add(gtsam.PriorFactorPoint3(B(i), np.zeros(3), gtsam.noiseModel.Gaussian.Covariance(cb)))
            if prev >= 0:
                step = cb * (2.0 / options.geo_bias_corr_kf)
                step[2, 2] = 1e-6
                graph.add(
                    gtsam.BetweenFactorPoint3(
                        B(prev), B(i), np.zeros(3), gtsam.noiseModel.Gaussian.Covariance(step)
                    )
                )
            prev = i
    if options.terrain_sigma_m > 0 and problem.lm_ground is not None:
        for jj in np.flatnonzero(np.all(np.isfinite(problem.lm_ground), axis=1)):
            graph.add(terrain_factor(L(int(jj)), problem.lm_ground[jj], options))
    return graph, values, geo_index


def terrain_factor(key: int, ground: np.ndarray, options: LbaOptions) -> gtsam.NonlinearFactor:
    """A landmark on the DEM, linearised at (north, east) = ground[:2]: error g . (p - ground[:3]) with
    g = (dh/dn, dh/de, 1), i.e. the landmark's down minus the surface's down there, to first order; its
    variance sigma_v^2 + |grad h|^2 sigma_h^2 (``LbaOptions.terrain_sigma_m``, ``terrain_sigma_horizontal_m``).

    Written as a Point3 prior whose information matrix has rank one (plus a negligible ridge that keeps it
    positive definite for the Cholesky of the noise model): GTSAM's own factor in C++, no Python callback
    per landmark and iteration."""
    g = np.array([ground[3], ground[4], 1.0])
    var = (
        options.terrain_sigma_m**2 + (ground[3] ** 2 + ground[4] ** 2) * options.terrain_sigma_horizontal_m**2
    )
    info = np.outer(g, g) / var + np.eye(3) * 1e-8
    base = gtsam.noiseModel.Gaussian.Information(info)
    noise = robust(base, options.terrain_kernel, options.terrain_kernel_k)
    return gtsam.PriorFactorPoint3(key, np.asarray(ground[:3], float), noise)


def solve_window(problem: WindowProblem, options: LbaOptions = LbaOptions()) -> WindowSolution:
    """Levenberg-Marquardt over the window; marginals of every key-frame pose."""
    M = len(problem.T_world_cam)
    Lm = len(problem.p_world)
    O = len(problem.obs_kf)
    graph, values, geo_index = build_graph(problem, options)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(options.max_iterations)
    params.setRelativeErrorTol(options.relative_error_tol)
    err0 = graph.error(values)
    try:
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        iters = opt.iterations()
    except RuntimeError:
        # indeterminate system (a degenerate window): keep the input, say so
        return WindowSolution(
            problem.T_world_cam.copy(),
            problem.p_world.copy(),
            np.full((M, 6, 6), np.nan),
            np.ones(O, bool),
            np.full(M, np.nan),
            float(err0),
            float(err0),
            0,
            False,
        )
    T = np.stack([result.atPose3(X(i)).matrix() for i in range(M)])
    P = np.stack([result.atPoint3(L(j)) for j in range(Lm)]) if Lm else np.zeros((0, 3))
    # observation inliers from the plain (non-robust) whitened reprojection error
    inl = np.ones(O, bool)
    if O:
        R = T[problem.obs_kf, :3, :3]
        p_cam = np.einsum("nji,nj->ni", R, P[problem.obs_lm] - T[problem.obs_kf, :3, 3])
        z = p_cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv_hat = (
                p_cam[:, :2] / z[:, None] * np.array([problem.K[0, 0], problem.K[1, 1]]) + problem.K[:2, 2]
            )
            e2 = np.sum((uv_hat - problem.obs_px) ** 2, axis=1) / options.pixel_sigma_px**2
            inl = (z > 0) & (e2 < options.outlier_chi2)
    geo_w = np.full(M, np.nan)
    bias = None
    if options.geo_bias_share > 0:
        bias = np.zeros((M, 3))
        for i, gi in enumerate(geo_index):
            if gi >= 0:
                bias[i] = result.atPoint3(B(i))
    for i, gi in enumerate(geo_index):
        if gi >= 0:
            r = geo_residual(problem, T, bias, i)
            geo_w[i] = float(np.sqrt(r @ np.linalg.solve(problem.geo_cov[i] / options.w_geo, r)))
    cov = np.full((M, 6, 6), np.nan)
    if options.marginals:
        # an indeterminate system leaves them NaN: the caller keeps its previous covariance and says so
        with contextlib.suppress(RuntimeError):
            marg = gtsam.Marginals(graph, result)
            for i in range(M):
                cov[i] = marg.marginalCovariance(X(i))
    return WindowSolution(
        T, P, cov, inl, geo_w, float(err0), float(graph.error(result)), int(iters), True, bias
    )


def geo_redundancy(
    problem: WindowProblem, sol: WindowSolution, w_geo: float, q_cap: float = np.inf
) -> tuple[float, float]:
    """The horizontal geo-fixes' share of the window's a-posteriori variance factor (Helmert's variance
    component estimate): (sum of the fixes' whitened squared horizontal residuals, sum of their redundancy
    numbers). A fix's redundancy is 2 - tr(S^-1 P): S its horizontal covariance in the adjustment (geo_cov /
    w_G), P the posterior covariance of the point it locates (the key frame's marginal through the lever
    arm); a fix the adjustment simply follows has redundancy ~0, one the rest of the window overrules ~2.
    The ratio of the two sums estimates by how much S should be scaled for the fixes to scatter as their
    covariance says. Each whitened squared residual is capped at ``q_cap`` (a gross outlier the robust
    kernel already discounts must not inflate the estimate). Key frames without a fix or a finite marginal
    are skipped; (0, 0) when none."""
    q_sum, red_sum = 0.0, 0.0
    for i in np.flatnonzero(np.isfinite(sol.geo_whitened)):
        C = sol.cov[i]
        if not np.all(np.isfinite(C)):
            continue
        r = geo_residual(problem, sol.T_world_cam, sol.geo_bias, int(i))[:2]
        J = lever_point_jacobian(sol.T_world_cam[i, :3, :3], problem.geo_lever_cam[i])
        P = (J @ C @ J.T)[:2, :2]
        S_inv = np.linalg.inv(problem.geo_cov[i][:2, :2] / w_geo)
        q_sum += min(float(r @ S_inv @ r), q_cap)
        red_sum += 2.0 - float(np.trace(S_inv @ P))
    return q_sum, red_sum


def body_covariance(
    T_world_cam: np.ndarray, cov_tangent: np.ndarray, R_body_cam: np.ndarray, p_body_in_cam: np.ndarray
) -> np.ndarray:
    """(6, 6) covariance over the body's (x, y, z, roll, pitch, yaw) (NED m, rad) from a camera pose's
    (6, 6) Pose3-tangent covariance (rotation, translation in the camera frame), by a numerical Jacobian
    of body position and Euler angles with respect to the tangent (exact enough, and no sign to get wrong)."""

    def body(T: np.ndarray) -> np.ndarray:
        R_wb = T[:3, :3] @ R_body_cam.T
        p = T[:3, :3] @ p_body_in_cam + T[:3, 3]
        return np.concatenate([p, rpy_from_rot(R_wb)])

    pose = gtsam.Pose3(T_world_cam)
    J = np.zeros((6, 6))
    h = 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = h
        fp = body(pose.retract(xi).matrix())
        fm = body(pose.retract(-xi).matrix())
        d = fp - fm
        d[3:] = (d[3:] + np.pi) % (2 * np.pi) - np.pi
        J[:, k] = d / (2 * h)
    C = J @ cov_tangent @ J.T
    return 0.5 * (C + C.T)
