"""Eq. 21: the rigid transform H_Tt taking the visual-odometry trajectory onto the geo-referenced one.

Gravity is known (the autopilot's roll and pitch enter the VO and the bundle adjustment), and the scale is
fixed by the altimeter, so H is estimated with four degrees of freedom: a rotation about the vertical and a
translation. Weighted closed-form least squares (2-D Procrustes on north/east, mean offset on down),
iterated with Huber weights so that a wild geo-fix does not drag it. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.geometry import make_T


@dataclass(frozen=True)
class Alignment:
    """T_world_vo: (4, 4) world <- VO frame. yaw_rad: its rotation about down. rms_m: RMS residual of the inliers.
    inliers: (N,) bool, points within ``huber_m`` x 3 of the fit. yaw_observable: the points spread
    horizontally enough for the yaw to be estimated (otherwise yaw = 0, translation only)."""

    T_world_vo: np.ndarray
    yaw_rad: float
    rms_m: float
    inliers: np.ndarray
    yaw_observable: bool


def _fit(
    p_src: np.ndarray, p_dst: np.ndarray, w: np.ndarray, min_spread_m: float
) -> tuple[np.ndarray, float, bool]:
    ws = w / w.sum()
    cs = ws @ p_src
    cd = ws @ p_dst
    a = p_src[:, :2] - cs[:2]
    b = p_dst[:, :2] - cd[:2]
    spread = np.sqrt(ws @ np.sum(a * a, axis=1))
    yaw = 0.0
    observable = bool(spread >= min_spread_m)
    if observable:
        cross = ws @ (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])
        dot = ws @ np.sum(a * b, axis=1)
        yaw = float(np.arctan2(cross, dot))
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return make_T(R, cd - R @ cs), yaw, observable


def align_yaw_translation(
    p_vo: np.ndarray,
    p_world: np.ndarray,
    weights: np.ndarray | None = None,
    huber_m: float = 1.0,
    iterations: int = 5,
    min_spread_m: float = 5.0,
) -> Alignment:
    """H_Tt of eq. 21 from (N, 3) VO positions and their (N, 3) geo-referenced positions (N >= 1).

    weights: (N,) prior weights (e.g. the fixes' quality), default 1. huber_m: Huber threshold on the
    3-D residual. min_spread_m: RMS horizontal spread of the VO positions needed to estimate the yaw.
    """
    p_vo = np.asarray(p_vo, float)
    p_world = np.asarray(p_world, float)
    n = len(p_vo)
    if n == 0:
        raise ValueError("alignment needs at least one pair of positions")
    w0 = np.ones(n) if weights is None else np.asarray(weights, float)
    w = w0.copy()
    T, yaw, obs = _fit(p_vo, p_world, w, min_spread_m)
    for _ in range(iterations):
        r = np.linalg.norm(p_vo @ T[:3, :3].T + T[:3, 3] - p_world, axis=1)
        w = w0 * np.where(r <= huber_m, 1.0, huber_m / np.maximum(r, 1e-12))
        T, yaw, obs = _fit(p_vo, p_world, w, min_spread_m)
    r = np.linalg.norm(p_vo @ T[:3, :3].T + T[:3, 3] - p_world, axis=1)
    inl = r < 3.0 * huber_m
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else float("inf")
    return Alignment(T, yaw, rms, inl, obs)
