"""Altimeter update against the landmark map (paper 2 section 3: "a ranging altimeter ... to aid in
identifying range ambiguities").

The paper does not give the measurement model. A range finder measures the distance to the terrain
along the body down axis, and the filter has no terrain map, so we use the facet model of range-aided
VIO (Delaune, Bayard, Brockers, "Range-Visual-Inertial Odometry: Scale Observability Without
Excitation", IEEE RA-L 2021): the three tracked landmarks whose directions, seen from the vehicle,
enclose the range beam form a plane, and the predicted range is where the beam meets that plane.
The model error (terrain is not planar between landmarks) is part of the measurement noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import Delaunay, QhullError

from companion.ekf.so3 import skew


@dataclass(frozen=True)
class FacetRange:
    """Predicted range (m) with its Jacobians.

    H_pose: (1,6) w.r.t. (dr, dtheta); H_points: (3,3) rows d range / d p_i (world points of the facet).
    """

    range_m: float
    H_pose: np.ndarray
    H_points: np.ndarray


def select_facet(
    points_world: np.ndarray, r_world: np.ndarray, R_world_body: np.ndarray
) -> np.ndarray | None:
    """Indices (3,) of the landmarks whose Delaunay triangle (in body-frame bearing space) contains the
    body down axis, or None when the beam falls outside the landmarks' hull.

    points_world: (N,3). Only points below the vehicle (positive body-down component) are used.
    """
    if len(points_world) < 3:
        return None
    pb = (points_world - r_world) @ R_world_body  # body frame
    below = pb[:, 2] > 1e-3
    idx = np.flatnonzero(below)
    if len(idx) < 3:
        return None
    bearings = pb[idx, :2] / pb[idx, 2:3]
    try:
        tri = Delaunay(bearings)
    except QhullError:
        return None
    # point-in-triangle by edge signs, vectorised (Delaunay.find_simplex builds a ~10 ms search structure)
    a, b, c = (bearings[tri.simplices[:, k]] for k in range(3))

    def side(p: np.ndarray, q: np.ndarray) -> np.ndarray:  # sign of (q - p) x (0 - p)
        return (q[:, 0] - p[:, 0]) * (-p[:, 1]) - (q[:, 1] - p[:, 1]) * (-p[:, 0])

    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    inside = ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
    hits = np.flatnonzero(inside)
    if len(hits) == 0:
        return None
    return idx[tri.simplices[hits[0]]]


def facet_range(
    facet_world: np.ndarray, r_world: np.ndarray, R_world_body: np.ndarray, p_alt_in_body: np.ndarray
) -> FacetRange | None:
    """Range along the body down axis from the altimeter at p_alt_in_body to the plane of (3,3) points.

    With n the plane normal and d = R e3 the beam: s = n.(p1 - o) / n.d, o = r + R p_alt.
    ds/dr = -n/(n.d); ds/dtheta = (n^T R [p_alt]x + s n^T R [e3]x) / (n.d) (local perturbation);
    ds/dp_i = beta_i n^T / (n.d), beta_i the barycentric weight of the hit point.
    """
    p1, p2, p3 = facet_world
    n = np.cross(p2 - p1, p3 - p1)
    nn = np.linalg.norm(n)
    if nn < 1e-9:
        return None
    n = n / nn
    d = R_world_body[:, 2]
    nd = float(n @ d)
    if abs(nd) < 0.2:  # beam grazing the facet: the prediction would be ill-conditioned
        return None
    o = r_world + R_world_body @ p_alt_in_body
    s = float(n @ (p1 - o)) / nd
    if s <= 0:
        return None
    hit = o + s * d
    # barycentric weights of the hit point
    T = np.stack([p1 - p3, p2 - p3], axis=1)
    lam, *_ = np.linalg.lstsq(T, hit - p3, rcond=None)
    beta = np.array([lam[0], lam[1], 1.0 - lam[0] - lam[1]])
    e3 = np.array([0.0, 0.0, 1.0])
    H_pose = np.zeros((1, 6))
    H_pose[0, :3] = -n / nd
    H_pose[0, 3:] = (n @ R_world_body @ skew(p_alt_in_body) + s * (n @ R_world_body @ skew(e3))) / nd
    H_points = beta[:, None] * n[None, :] / nd
    return FacetRange(s, H_pose, H_points)
