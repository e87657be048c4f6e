"""Altimeter update against the landmark map (paper 2 section 3: "a ranging altimeter ... to aid in
identifying range ambiguities").

The paper does not give the measurement model. A range finder measures the distance to the terrain
along the body down axis, and the filter has no terrain map, so we use the facet model of range-aided
VIO (Delaune, Bayard, Brockers, "Range-Visual-Inertial Odometry: Scale Observability Without
Excitation", IEEE RA-L 2021): the three tracked landmarks whose directions, seen from the vehicle,
enclose the range beam form a plane, and the predicted range is where the beam meets that plane.
The model error (terrain is not planar between landmarks) stays nearly the same from sample to sample while
a facet lasts; ``slam`` carries it as a state of the filter, new for each facet (``EkfOptions.facet_error_state``),
or else as white measurement noise.
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


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b of two (3,) vectors (np.cross costs ~10x more on single vectors; this runs at the altimeter rate)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _contains_origin(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(T,) bool: triangles with (T,2) vertices a, b, c that contain the origin (edges included)."""

    def side(p: np.ndarray, q: np.ndarray) -> np.ndarray:  # sign of (q - p) x (0 - p)
        return (q[:, 0] - p[:, 0]) * (-p[:, 1]) - (q[:, 1] - p[:, 1]) * (-p[:, 0])

    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    return ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))


def facet_encloses_beam(facet_world: np.ndarray, r_world: np.ndarray, R_world_body: np.ndarray) -> bool:
    """True when the (3,3) points are below the vehicle and their bearing triangle contains the body down
    axis: a facet chosen by ``select_facet`` stays usable while this holds (between the camera frames the
    map only moves a little, so the triangulation need not be rebuilt at the altimeter rate)."""
    pb = (np.asarray(facet_world, float) - r_world) @ R_world_body
    if np.any(pb[:, 2] <= 1e-3):
        return False
    bearings = pb[:, :2] / pb[:, 2:3]
    return bool(_contains_origin(bearings[0:1], bearings[1:2], bearings[2:3])[0])


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
    hits = np.flatnonzero(_contains_origin(a, b, c))
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
    n = _cross(p2 - p1, p3 - p1)
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
    # barycentric weights of the hit point (in the facet's plane: sub-triangle areas along the normal)
    area = nn  # = n . ((p2 - p1) x (p3 - p1)) with the unit n
    b1 = float(n @ _cross(p2 - hit, p3 - hit)) / area
    b2 = float(n @ _cross(p3 - hit, p1 - hit)) / area
    beta = np.array([b1, b2, 1.0 - b1 - b2])
    e3 = np.array([0.0, 0.0, 1.0])
    H_pose = np.zeros((1, 6))
    H_pose[0, :3] = -n / nd
    H_pose[0, 3:] = (n @ R_world_body @ skew(p_alt_in_body) + s * (n @ R_world_body @ skew(e3))) / nd
    H_points = beta[:, None] * n[None, :] / nd
    return FacetRange(s, H_pose, H_points)
