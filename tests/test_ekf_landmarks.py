"""Inverse-depth landmarks (Civera et al.): initialisation, conversion, projection and Jacobians, and the
altimeter facet model, each checked against numerical derivatives."""

from __future__ import annotations

import numpy as np
import pytest

from companion.constants import R_BODY_CAM_NADIR
from companion.ekf import landmarks as L
from companion.ekf.altimeter import facet_range, select_facet
from companion.ekf.so3 import quat_exp, quat_from_rot, quat_mul, rot_exp, rot_from_quat, rot_log
from companion.geometry import CameraIntrinsics, project, rot_from_rpy

INTR = CameraIntrinsics(640, 480, 554.0, 554.0, 319.5, 239.5)


def _cam(p_cam_in_body=(0.0, 0.0, 0.0)) -> L.CameraModel:
    return L.CameraModel(INTR.K, 640, 480, R_BODY_CAM_NADIR.copy(), np.asarray(p_cam_in_body, float))


def _num_jac(f, x0: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    y0 = np.asarray(f(x0))
    J = np.zeros((y0.size, x0.size))
    for i in range(x0.size):
        d = np.zeros_like(x0)
        d[i] = eps
        J[:, i] = (np.asarray(f(x0 + d)).ravel() - np.asarray(f(x0 - d)).ravel()) / (2 * eps)
    return J


def test_ray_angles_round_trip_and_nadir_is_regular():
    rng = np.random.default_rng(0)
    h = rng.normal(size=(50, 3))
    h[:, 2] = np.abs(h[:, 2]) + 0.1
    th, ph = L.angles_from_ray(h)
    m = L.ray_from_angles(th, ph)
    np.testing.assert_allclose(m, h / np.linalg.norm(h, axis=1, keepdims=True), atol=1e-12)
    th0, ph0 = L.angles_from_ray(np.array([[0.0, 0.0, 1.0]]))
    assert abs(th0[0]) < 1e-12 and abs(ph0[0]) < 1e-12  # straight down: far from the singular east axis


def test_initialise_then_convert_gives_the_point_on_the_pixel_ray():
    rng = np.random.default_rng(1)
    R_wb = rot_from_rpy(0.05, -0.03, 0.7)
    r = np.array([10.0, -4.0, -80.0])
    cam = _cam((0.1, -0.05, 0.2))
    uv = rng.uniform([0, 0], [639, 479], (20, 2))
    depth = rng.uniform(40, 120, 20)
    y, _, _ = L.initialise(uv, 1.0 / depth, r, R_wb, cam)
    p = L.to_euclidean(y)
    R_wc = R_wb @ cam.R_body_cam
    c = r + R_wb @ cam.p_cam_in_body
    np.testing.assert_allclose(y[:, :3], np.tile(c, (20, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(p - c, axis=1), depth, rtol=1e-10)  # rho = 1 / ray depth
    uv2, z = project(INTR.K, R_wc, c, p)
    assert np.all(z > 0)
    np.testing.assert_allclose(uv2, uv, atol=1e-8)
    pr = L.project(y, r, R_wb, cam)  # Civera's model agrees with the plain pinhole
    np.testing.assert_allclose(pr.uv, uv, atol=1e-8)


def test_to_euclidean_jacobian_matches_numerical():
    y = np.array([[1.0, 2.0, -50.0, 0.2, -0.1, 0.02]])
    J = L.to_euclidean_jacobian(y)[0]
    np.testing.assert_allclose(J, _num_jac(lambda v: L.to_euclidean(v[None])[0], y[0]), atol=1e-5)


@pytest.mark.parametrize("lever", [(0.0, 0.0, 0.0), (0.3, -0.2, 0.5)])
def test_projection_jacobians_match_numerical(lever):
    rng = np.random.default_rng(2)
    cam = _cam(lever)
    q = quat_from_rot(rot_from_rpy(0.1, -0.05, 1.2))
    r = np.array([5.0, 3.0, -60.0])
    y, _, _ = L.initialise(
        rng.uniform([50, 50], [590, 430], (5, 2)), rng.uniform(0.01, 0.03, 5), r, rot_from_quat(q), cam
    )
    # move the vehicle so the anchor differs from the current camera
    r2 = r + np.array([4.0, -2.0, 1.0])
    q2 = quat_mul(q, quat_exp(np.array([0.02, -0.01, 0.05])))
    pr = L.project(y, r2, rot_from_quat(q2), cam)
    for i in range(len(y)):

        def h_pose(x, i=i):
            return L.project(y[i : i + 1], r2 + x[:3], rot_from_quat(quat_mul(q2, quat_exp(x[3:]))), cam).uv[
                0
            ]

        def h_lm(v):
            return L.project(v[None], r2, rot_from_quat(q2), cam).uv[0]

        np.testing.assert_allclose(pr.H_pose[i], _num_jac(h_pose, np.zeros(6)), rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(pr.H_lm[i], _num_jac(h_lm, y[i].copy(), 1e-7), rtol=1e-4, atol=1e-3)


def test_initialisation_jacobians_match_numerical():
    cam = _cam((0.2, 0.1, -0.3))
    q = quat_from_rot(rot_from_rpy(-0.08, 0.04, 2.5))
    r = np.array([-3.0, 7.0, -45.0])
    uv = np.array([[100.0, 400.0], [500.0, 60.0]])
    rho = np.array([0.02, 0.03])
    _, Jp, Ju = L.initialise(uv, rho, r, rot_from_quat(q), cam)
    for i in range(2):

        def f_pose(x, i=i):
            return L.initialise(
                uv[i : i + 1], rho[i : i + 1], r + x[:3], rot_from_quat(quat_mul(q, quat_exp(x[3:]))), cam
            )[0][0]

        def f_uv(z, i=i):
            return L.initialise(z[None], rho[i : i + 1], r, rot_from_quat(q), cam)[0][0]

        np.testing.assert_allclose(Jp[i], _num_jac(f_pose, np.zeros(6)), atol=1e-6)
        np.testing.assert_allclose(Ju[i], _num_jac(f_uv, uv[i].copy(), 1e-4), atol=1e-7)


def test_linearity_index_small_for_a_well_observed_point():
    y = np.array([[0.0, 0.0, -100.0, 0.0, 0.0, 0.01]])
    assert L.linearity_index(y, np.array([1e-4]), np.array([5.0, 0.0, -100.0]))[0] < 0.1
    assert L.linearity_index(y, np.array([5e-3]), np.array([5.0, 0.0, -100.0]))[0] > 0.1


def test_facet_range_on_a_plane_and_its_jacobians():
    # a level plane 50 m below a tilted vehicle: range = 50 / cos(tilt)
    R_wb = rot_from_rpy(0.1, -0.05, 0.3)
    r = np.array([0.0, 0.0, -50.0])
    tri = np.array([[30.0, 0.0, 0.0], [-20.0, 25.0, 0.0], [-20.0, -25.0, 0.0]])
    fr = facet_range(tri, r, R_wb, np.zeros(3))
    assert fr is not None
    assert fr.range_m == pytest.approx(50.0 / R_wb[2, 2], rel=1e-9)
    lever = np.array([0.1, 0.2, 0.3])
    fr = facet_range(tri, r, R_wb, lever)
    q = quat_from_rot(R_wb)

    def f_pose(x):
        return facet_range(tri, r + x[:3], rot_from_quat(quat_mul(q, quat_exp(x[3:]))), lever).range_m

    np.testing.assert_allclose(fr.H_pose[0], _num_jac(f_pose, np.zeros(6))[0], atol=1e-6)

    def f_pts(x):
        return facet_range(x.reshape(3, 3), r, R_wb, lever).range_m

    np.testing.assert_allclose(fr.H_points.ravel(), _num_jac(f_pts, tri.ravel())[0], atol=1e-6)


def test_select_facet_encloses_the_beam():
    rng = np.random.default_rng(5)
    R_wb = rot_from_rpy(0.05, 0.02, 0.0)
    r = np.array([0.0, 0.0, -60.0])
    pts = np.column_stack([rng.uniform(-40, 40, (30, 2)), rng.normal(0, 1, 30)])
    idx = select_facet(pts, r, R_wb)
    assert idx is not None and len(set(idx.tolist())) == 3
    fr = facet_range(pts[idx], r, R_wb, np.zeros(3))
    assert fr is not None and 55.0 < fr.range_m < 66.0
    # all points on one side of the beam: no facet
    assert select_facet(pts[pts[:, 0] > 5.0], r, R_wb) is None


def test_so3_helpers_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        w = rng.normal(size=3)
        R = rot_exp(w)
        np.testing.assert_allclose(rot_from_quat(quat_exp(w)), R, atol=1e-12)
        if np.linalg.norm(w) < np.pi:
            np.testing.assert_allclose(rot_log(R), w, atol=1e-9)
        np.testing.assert_allclose(rot_exp(rot_log(R)), R, atol=1e-9)  # any angle, wrapped or not
        np.testing.assert_allclose(rot_from_quat(quat_from_rot(R)), R, atol=1e-12)
