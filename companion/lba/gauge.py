"""What the adjustment's marginals cannot know: where its map sits in the world before the fixes say.

Until the geo-fixes have placed the map (eq. 21), the window is held by its start-up key frames, pinned at
the configured start and the compass heading. Its marginals are then relative to those: they say how well
the key frames are known *with respect to the start*, not in the world. A compass 2 deg off turns the whole
map about the start, so 100 m further the position is 3.5 m off while the marginal says 0.4 m. The world
uncertainty of such a map is the start's (sigma_pos) plus its heading's (sigma_yaw) carried out along the
lever from the point it turns about (the pivot):

    p_world = pivot + R_down(dpsi) (p_map - pivot) + dp0   ->   dp = J dpsi + dp0,  J = (-d_E, d_N, 0)

for d = p - pivot in NED (a turn about down by dpsi moves north d_N, east d_E to north d_N - dpsi d_E, east
d_E + dpsi d_N). This module adds that, first order, to the pose covariance the estimator sends. Pure numpy.
"""

from __future__ import annotations

import numpy as np

_MAX_LINEAR_YAW_RAD = 1.0  # beyond ~1 rad the lever's first-order turn overstates a chord (<= 2 |d|)
_UNIFORM_YAW_SIGMA_RAD = float(np.pi / np.sqrt(3.0))  # sigma of a heading uniform over the whole turn


def gauge_covariance(
    p_world: np.ndarray,
    pivot_world: np.ndarray,
    sigma_pos_m: float,
    sigma_yaw_rad: float,
    heading_known: bool = False,
) -> np.ndarray:
    """(6, 6) covariance over (x, y, z, roll, pitch, yaw) NED to add to a map-relative pose covariance.

    p_world: (3,) the pose's position. pivot_world: (3,) where the map's position is known (the start, or
    the fixes that placed it). sigma_pos_m: 1-sigma horizontal error of the map at the pivot (0: placed by
    the fixes). sigma_yaw_rad: 1-sigma of the map's heading (0: known from the terrain); a compass-free
    start (sigma beyond ~1 rad) is capped at a heading uniform over the turn, and its lever at 1 rad.
    heading_known: the terrain has since turned the map to the right heading, but what was flown on the old
    one is still off by it: the lever's share stays, the heading's own (and its cross terms) go.
    """
    out = np.zeros((6, 6))
    out[0, 0] = out[1, 1] = sigma_pos_m**2
    if sigma_yaw_rad > 0:
        d = np.asarray(p_world, float)[:2] - np.asarray(pivot_world, float)[:2]
        J = np.array([-d[1], d[0]])
        s_lever = min(sigma_yaw_rad, _MAX_LINEAR_YAW_RAD)
        s_yaw = min(sigma_yaw_rad, _UNIFORM_YAW_SIGMA_RAD)
        out[:2, :2] += s_lever**2 * np.outer(J, J)
        if not heading_known:
            out[5, 5] = s_yaw**2
            out[:2, 5] = out[5, :2] = s_lever * s_yaw * J
    return out
