"""Visible renderer: pinhole geometry, heightfield intersection against a brute-force ray march, shading,
cast shadows, noise and determinism."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from companion.geometry import CameraIntrinsics, camera_pose, pixel_rays_cam, project, rot_from_rpy
from companion.georef.dem import Dem
from companion.georef.shading import Sun
from sim_bridge.render import PAPER_CAMERA, SensorNoise, VisibleRenderer
from sim_bridge.terrain import make_scene

K480 = PAPER_CAMERA
K160 = CameraIntrinsics.from_focal_sensor(160, 160, 36, 36)  # same 53.13 deg field of view, fewer rays


def _flat_dem(height_m=0.0, n=401, cell=0.25):
    h = np.full((n, n), height_m, np.float32)
    half = (n - 1) / 2 * cell
    return Dem(h, half, -half, cell)


@pytest.fixture(scope="module")
def canyon():
    return make_scene("07", seed=1, cell_m=0.25, size_m=150.0)


@pytest.fixture(scope="module")
def mountain():
    return make_scene("09", seed=2, cell_m=0.25, size_m=150.0)


def test_intrinsics_match_the_paper_camera():
    assert (K480.width, K480.height) == (480, 480)
    assert K480.fx == pytest.approx(480.0)
    assert np.degrees(2 * np.arctan(240 / K480.fx)) == pytest.approx(53.13, abs=0.01)


def test_marker_appears_at_the_pixel_the_pinhole_model_predicts_and_back():
    """A bright spot on hilly ground, seen from a tilted camera: its image centroid is where ``project``
    puts the world point, and ``ground_points`` at that pixel gives the world point back."""
    cell = 0.1
    n = 1201
    half = (n - 1) / 2 * cell
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32) * cell
    h = (3.0 * np.sin(xx / 9.0) + 2.0 * np.cos(yy / 7.0)).astype(np.float32)
    dem = Dem(h, half, -half, cell)
    mark_ne = np.array([6.3, -4.1])
    nn, ee = dem.ne_from_rc(*np.mgrid[0:n, 0:n])
    albedo = np.where(np.hypot(nn - mark_ne[0], ee - mark_ne[1]) < 0.35, 1.0, 0.05).astype(np.float32)
    sun = Sun.from_degrees(1.0, 0.0, 90.0)  # overhead: flat shading, the marker is the only feature
    r = VisibleRenderer(dem, albedo, sun, K480, noise=None, ambient=1.0, exposure=200.0)
    R, p = camera_pose(rot_from_rpy(0.15, -0.2, 0.7), np.array([1.0, 2.0, -40.0]))
    img = r.render(R, p).astype(float)
    mask = img > 100
    assert 20 < mask.sum() < 2000
    vs, us = np.nonzero(mask)
    centroid = np.array([(us * img[mask]).sum(), (vs * img[mask]).sum()]) / img[mask].sum()
    world = np.array([[mark_ne[0], mark_ne[1], -float(dem.height_at(*mark_ne)[0])]])
    uv, depth = project(K480.K, R, p, world)
    assert depth[0] > 0
    np.testing.assert_allclose(centroid, uv[0], atol=0.3)
    # and back: the ground point at the predicted pixel is the marker, to within a pixel footprint
    gp = r.ground_points(R, p)
    u, v = int(round(uv[0, 0])), int(round(uv[0, 1]))
    gsd = depth[0] / K480.fx
    assert np.linalg.norm(gp[v, u] - world[0]) < 3 * gsd


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.0), (0.3, -0.25, 2.0)])
def test_ground_points_lie_on_the_surface_and_project_to_their_pixels(canyon, rpy):
    r = VisibleRenderer(canyon.dem, canyon.albedo, canyon.sun, K160, noise=None)
    R, p = camera_pose(rot_from_rpy(*rpy), np.array([5.0, -3.0, -(canyon.dem.height_m.max() + 25.0)]))
    gp = r.ground_points(R, p)
    ok = np.isfinite(gp[..., 0])
    assert ok.mean() > 0.5  # the tilted view partly looks past the 150 m raster
    q = gp[ok]
    h = canyon.dem.height_at(q[:, 0], q[:, 1])
    assert np.max(np.abs(-q[:, 2] - h)) < 0.02
    uv, z = project(K160.K, R, p, q)
    vv, uu = np.nonzero(ok)
    assert (z > 0).all()
    assert np.max(np.abs(uv - np.stack([uu, vv], 1))) < 1e-3


def test_tilted_plane_matches_analytic_ray_plane_intersection():
    cell, n = 0.5, 401
    half = (n - 1) / 2 * cell
    rr, cc = np.mgrid[0:n, 0:n]
    north, east = half - rr * cell, -half + cc * cell
    a, b, c0 = 0.2, -0.1, 3.0  # height = a * north + b * east + c0
    dem = Dem((a * north + b * east + c0).astype(np.float32), half, -half, cell)
    r = VisibleRenderer(
        dem, np.full(dem.shape, 0.3, np.float32), Sun.from_degrees(1, 0, 45), K160, noise=None
    )
    R, p = camera_pose(rot_from_rpy(0.1, 0.2, -0.4), np.array([-3.0, 4.0, -60.0]))
    gp = r.ground_points(R, p)
    d = pixel_rays_cam(K160) @ R.T  # (H, W, 3) world directions with z_cam = 1
    # plane: -z = a n + b e + c0  ->  -(pz + t dz) = a (pn + t dn) + b (pe + t de) + c0
    t = -(p[2] + a * p[0] + b * p[1] + c0) / (d[..., 2] + a * d[..., 0] + b * d[..., 1])
    truth = p + t[..., None] * d
    ok = np.isfinite(gp[..., 0])
    assert ok.all()
    assert np.max(np.linalg.norm(gp - truth, axis=-1)) < 0.05


def _brute_force_t(dem: Dem, c: np.ndarray, d: np.ndarray, t_max: float, dt: float) -> np.ndarray:
    """First ray/heightfield crossing by marching in small steps then bisecting. Independent of the
    renderer: scipy's map_coordinates for the bilinear heights. (N,) t, NaN for no hit."""
    ts = np.arange(0.0, t_max, dt)
    out = np.full(len(d), np.nan)

    def g(t, dd):
        p = c + t[..., None] * dd
        rows, cols = dem.rc_from_ne(p[..., 0], p[..., 1])
        h = ndimage.map_coordinates(dem.height_m, [rows.ravel(), cols.ravel()], order=1, mode="nearest")
        off = (rows < 0) | (cols < 0) | (rows > dem.shape[0] - 1) | (cols > dem.shape[1] - 1)
        return np.where(off, np.inf, -p[..., 2] - h.reshape(rows.shape))  # nothing beyond the raster

    for i, dd in enumerate(d):
        gi = g(ts, dd[None, :].repeat(len(ts), 0))
        below = np.nonzero(gi < 0)[0]
        if below.size == 0:
            continue
        k = below[0]
        lo, hi = ts[k - 1], ts[k]
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if g(np.array([mid]), dd[None, :])[0] > 0:
                lo = mid
            else:
                hi = mid
        out[i] = 0.5 * (lo + hi)
    return out


@pytest.mark.parametrize(
    ("which", "intr"), [("canyon", K160), ("mountain", K160), ("canyon", K480), ("mountain", K480)]
)
def test_intersection_matches_brute_force_march_on_steep_terrain(which, intr, request):
    """Oblique views of steep terrain (occlusion by ridges and canyon walls): the fast intersection finds
    the same first hit as a fine brute-force march (at 480 px the coarse-to-fine path has three levels)."""
    sc = request.getfixturevalue(which)
    r = VisibleRenderer(sc.dem, sc.albedo, sc.sun, intr, noise=None)
    top = float(sc.dem.height_m.max())
    R, p = camera_pose(rot_from_rpy(0.1, 0.75, 0.6), np.array([-45.0, -50.0, -(top + 15.0)]))
    gp = r.ground_points(R, p)
    rng = np.random.default_rng(0)
    vv = rng.integers(0, intr.height, 150)
    uu = rng.integers(0, intr.width, 150)
    d = (R @ np.stack([(uu - intr.cx) / intr.fx, (vv - intr.cy) / intr.fy, np.ones(150)])).T
    t_ref = _brute_force_t(sc.dem, p, d, t_max=300.0, dt=0.02)
    t_fast = (gp[vv, uu] - p) @ np.array([0, 0, 1.0]) / d[:, 2]
    both = np.isfinite(t_ref) & np.isfinite(t_fast)
    assert both.mean() > 0.6  # the rest look past the far edge of the 150 m raster
    assert (np.isfinite(t_ref) == np.isfinite(t_fast)).mean() > 0.97
    err = np.abs(t_fast[both] - t_ref[both])
    # the odd disagreement is a ray grazing a crest by millimetres (a silhouette pixel)
    assert np.mean(err < 0.05) > 0.97, np.sort(err)[-10:]


def test_rays_that_miss_are_nan_and_black():
    dem = _flat_dem()
    r = VisibleRenderer(
        dem, np.full(dem.shape, 0.5, np.float32), Sun.from_degrees(1, 0, 60), K160, noise=None
    )
    # camera pitched up 60 deg from nadir... i.e. looking towards the horizon: upper rows see the sky
    R, p = camera_pose(rot_from_rpy(0.0, 0.0, 0.0) @ rot_from_rpy(0.0, 1.2, 0.0), np.array([0.0, 0.0, -20.0]))
    gp = r.ground_points(R, p)
    img = r.render(R, p)
    miss = ~np.isfinite(gp[..., 0])
    assert miss[0].all() and not miss[-1].any()
    assert (img[miss] == 0).all() and (img[~miss] > 0).all()


def test_camera_inside_the_terrain_is_refused():
    dem = _flat_dem(10.0)
    r = VisibleRenderer(
        dem, np.full(dem.shape, 0.5, np.float32), Sun.from_degrees(1, 0, 60), K160, noise=None
    )
    with pytest.raises(ValueError, match="below the lowest terrain"):
        r.render(np.eye(3), np.array([0.0, 0.0, -5.0]))


def test_shading_follows_eq3_and_exposure():
    """Flat ground, uniform albedo: DN = exposure * L * albedo * (ambient + (1 - ambient) sin(elevation))."""
    dem = _flat_dem()
    alb = np.full(dem.shape, 0.4, np.float32)
    R, p = camera_pose(np.eye(3), np.array([0.0, 0.0, -30.0]))
    for inten, el in ((2.0, 30.0), (4.0, 30.0), (4.0, 70.0)):
        r = VisibleRenderer(
            dem, alb, Sun.from_degrees(inten, 45, el), K160, noise=None, ambient=0.1, exposure=50
        )
        img = r.render(R, p).astype(float)
        want = 50 * inten * 0.4 * (0.1 + 0.9 * np.sin(np.radians(el)))
        assert np.abs(img - want).max() <= 0.51


def test_cast_shadow_behind_a_wall_is_at_ambient_level():
    n, cell = 401, 0.25
    half = (n - 1) / 2 * cell
    h = np.zeros((n, n), np.float32)
    h[190:200, :] = 8.0  # an east-west wall 2.5 m thick, 8 m high, just north of the centre
    dem = Dem(h, half, -half, cell)
    alb = np.full(dem.shape, 0.5, np.float32)
    sun = Sun.from_degrees(1.0, 0.0, 30.0)  # from the north, low: the shadow falls south of the wall
    r = VisibleRenderer(dem, alb, sun, K160, noise=None, ambient=0.1, exposure=200)
    R, p = camera_pose(np.eye(3), np.array([-5.0, 0.0, -40.0]))
    gp = r.ground_points(R, p)
    img = r.render(R, p).astype(float)
    north = gp[..., 0]
    shadow = (north < -2.0) & (north > 2.5 - 8.0 / np.tan(np.radians(30)) + 1.0)  # ~ -11.4 .. -2 m
    lit = north < -16.0
    assert shadow.sum() > 100 and lit.sum() > 100
    assert np.median(img[shadow]) == pytest.approx(200 * 0.5 * 0.1, abs=1.0)
    assert np.median(img[lit]) == pytest.approx(200 * 0.5 * (0.1 + 0.9 * 0.5), abs=1.0)


def test_noise_statistics_and_determinism_by_seed(canyon):
    noise = SensorNoise(read_sigma_dn=3.0, shot=True, electrons_per_dn=20.0, seed=4)
    r = VisibleRenderer(canyon.dem, canyon.albedo, canyon.sun, K160, noise=noise)
    clean = VisibleRenderer(canyon.dem, canyon.albedo, canyon.sun, K160, noise=None)
    R, p = camera_pose(rot_from_rpy(0.05, 0.0, 0.3), np.array([0.0, 0.0, -(canyon.dem.height_m.max() + 50)]))
    a = r.render(R, p, seed=7)
    b = r.render(R, p, seed=7)
    c = r.render(R, p, seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    # any integer seed works (timestamps, negative numbers)
    np.testing.assert_array_equal(r.render(R, p, seed=-3), r.render(R, p, seed=-3))
    assert not np.array_equal(r.render(R, p, seed=2**40), a)
    ref = clean.radiance_at_pixels(R, p)
    resid = a.astype(float) - ref
    ok = (ref > 20) & (ref < 230)
    want = np.sqrt(3.0**2 + ref[ok] / 20.0 + 1 / 12)  # + uniform quantisation
    assert np.std(resid[ok] / want) == pytest.approx(1.0, abs=0.1)
    assert abs(np.mean(resid[ok])) < 0.3
    # the renderer's own sequence (seed=None) is reproducible from SensorNoise.seed
    r2 = VisibleRenderer(canyon.dem, canyon.albedo, canyon.sun, K160, noise=noise)
    r3 = VisibleRenderer(canyon.dem, canyon.albedo, canyon.sun, K160, noise=noise)
    seq2 = [r2.render(R, p) for _ in range(2)]
    seq3 = [r3.render(R, p) for _ in range(2)]
    np.testing.assert_array_equal(seq2[0], seq3[0])
    np.testing.assert_array_equal(seq2[1], seq3[1])
    assert not np.array_equal(seq2[0], seq2[1])


def test_same_scene_seed_gives_identical_frames():
    a = make_scene("03", seed=5, cell_m=0.5, size_m=120.0)
    b = make_scene("03", seed=5, cell_m=0.5, size_m=120.0)
    c = make_scene("03", seed=6, cell_m=0.5, size_m=120.0)
    R, p = camera_pose(np.eye(3), np.array([0.0, 0.0, -60.0]))
    frames = [VisibleRenderer(s.dem, s.albedo, s.sun, K160).render(R, p, seed=1) for s in (a, b, c)]
    np.testing.assert_array_equal(frames[0], frames[1])
    assert np.abs(frames[0].astype(int) - frames[2]).mean() > 5


def test_albedo_on_another_grid_is_refused():
    dem = _flat_dem()
    with pytest.raises(ValueError, match="albedo shape"):
        VisibleRenderer(dem, np.ones((3, 3), np.float32), Sun.from_degrees(1, 0, 60), K160)
