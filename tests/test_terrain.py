"""Procedural scenes (paper 1 Table 2 analogues) and the DEM degradation handed to estimators."""

from __future__ import annotations

import numpy as np
import pytest

from sim_bridge.terrain import (
    SCENE_IDS,
    SCENE_RELIEF_M,
    SCENE_SUN_DEG,
    DemDegradation,
    degrade_dem,
    make_scene,
)

SMALL = {"cell_m": 0.5, "size_m": 120.0}  # 240 x 240 cells: fast, every recipe still runs


@pytest.mark.parametrize("scene_id", SCENE_IDS)
def test_scene_relief_grid_albedo_and_sun(scene_id):
    sc = make_scene(scene_id, seed=3, **SMALL)
    h = sc.dem.height_m
    assert sc.scene_id == scene_id and sc.name
    assert h.shape == (240, 240) and h.dtype == np.float32 and np.isfinite(h).all()
    assert sc.dem.cell_m == pytest.approx(0.5)
    # relief as in Table 2 after the resize, mean ground at the world origin, grid centred on N = E = 0
    assert sc.relief_m == pytest.approx(SCENE_RELIEF_M[scene_id], rel=1e-3)
    assert float(h.max() - h.min()) == pytest.approx(sc.relief_m, rel=1e-4)
    assert abs(float(h.mean())) < 1e-3 * sc.relief_m
    n0, n1, e0, e1 = sc.dem.extent_ne
    assert n0 == pytest.approx(-n1) and e0 == pytest.approx(-e1)
    # albedo on the same grid, in (0, 1], with texture (not a constant)
    assert sc.albedo.shape == h.shape and sc.albedo.dtype == np.float32
    assert sc.albedo.min() > 0 and sc.albedo.max() <= 1
    assert sc.albedo.std() > 0.01
    inten, az, el = SCENE_SUN_DEG[scene_id]
    assert sc.sun.intensity == inten
    assert np.degrees(sc.sun.azimuth_rad) == pytest.approx(az)
    assert np.degrees(sc.sun.elevation_rad) == pytest.approx(el)


def test_scenes_differ_from_each_other():
    hs = [make_scene(s, seed=0, **SMALL).dem.height_m for s in ("01", "02", "07")]
    assert not np.allclose(hs[0], hs[1]) and not np.allclose(hs[1], hs[2])


@pytest.mark.parametrize("scene_id", ["03", "05", "09"])
def test_same_seed_same_scene_other_seed_other_scene(scene_id):
    a = make_scene(scene_id, seed=11, **SMALL)
    b = make_scene(scene_id, seed=11, **SMALL)
    c = make_scene(scene_id, seed=12, **SMALL)
    np.testing.assert_array_equal(a.dem.height_m, b.dem.height_m)
    np.testing.assert_array_equal(a.albedo, b.albedo)
    assert np.abs(a.dem.height_m - c.dem.height_m).mean() > 0.01 * a.relief_m
    assert not np.array_equal(a.albedo, c.albedo)


def test_gravel_plain_is_locally_gentle_but_100m_over_the_scene():
    sc = make_scene("05", seed=0, cell_m=0.5, size_m=600.0)
    gy, gx = np.gradient(sc.dem.height_m, sc.dem.cell_m)
    assert sc.relief_m == pytest.approx(100.0, rel=1e-3)
    assert np.median(np.hypot(gx, gy)) < 0.35  # about 10 deg or less


def test_unknown_scene_or_bad_grid_is_refused():
    with pytest.raises(ValueError, match="unknown scene"):
        make_scene("10")
    with pytest.raises(ValueError, match="cell_m"):
        make_scene("01", cell_m=0.0)


# ----------------------------------------------------------------------------------------------------------
# degradation


@pytest.fixture(scope="module")
def scene():
    return make_scene("08", seed=0, cell_m=0.25, size_m=100.0)


def test_degraded_dem_has_the_stated_cell_noise_and_holes(scene):
    dem = scene.dem
    deg_dem, deg = degrade_dem(dem, factor=4, noise_sigma_m=0.3, hole_fraction=0.02, seed=5)
    assert isinstance(deg, DemDegradation)
    assert deg.factor == 4 and deg.seed == 5 and deg.noise_sigma_m == 0.3
    assert deg.cell_m == pytest.approx(4 * dem.cell_m, rel=0.02)
    assert deg_dem.cell_m == deg.cell_m
    assert deg_dem.shape == (100, 100)
    # holes: the stated fraction, NaN, in blobs (most hole cells have a hole neighbour)
    holes = np.isnan(deg_dem.height_m)
    assert holes.mean() == pytest.approx(0.02, abs=0.002)
    assert deg.hole_fraction == pytest.approx(holes.mean())
    nbr = np.zeros_like(holes)
    nbr[1:] |= holes[:-1]
    nbr[:-1] |= holes[1:]
    assert (nbr[holes]).mean() > 0.5
    # noise: the residual against the noise-free coarse DEM has the stated std
    clean = dem.resampled(deg.cell_m)
    resid = (deg_dem.height_m - clean.height_m)[~holes]
    assert resid.std() == pytest.approx(0.3, rel=0.1)
    assert abs(resid.mean()) < 0.05
    # same extent as the truth (to within a coarse cell), so world coordinates agree
    assert deg_dem.north0_m == pytest.approx(clean.north0_m)
    assert deg_dem.east0_m == pytest.approx(clean.east0_m)
    line = deg.describe()
    assert "1.00 m" in line and "4x" in line and "0.30 m" in line and "2.0%" in line and "\n" not in line


def test_degradation_is_deterministic_by_seed(scene):
    a, _ = degrade_dem(scene.dem, seed=1)
    b, _ = degrade_dem(scene.dem, seed=1)
    c, _ = degrade_dem(scene.dem, seed=2)
    np.testing.assert_array_equal(a.height_m, b.height_m)
    assert not np.array_equal(np.isnan(a.height_m), np.isnan(c.height_m))


def test_degraded_dem_still_describes_the_true_surface(scene):
    deg_dem, deg = degrade_dem(scene.dem, factor=4, noise_sigma_m=0.3, hole_fraction=0.01, seed=0)
    rng = np.random.default_rng(0)
    n0, n1, e0, e1 = deg_dem.extent_ne
    n = rng.uniform(n0 + 2, n1 - 2, 2000)
    e = rng.uniform(e0 + 2, e1 - 2, 2000)
    err = deg_dem.height_at(n, e) - scene.dem.height_at(n, e)
    err = err[np.isfinite(err)]
    assert err.size > 1800
    assert np.sqrt(np.mean(err**2)) < 1.0  # noise 0.3 m plus the smoothing of a 1 m cell


def test_degrade_refuses_bad_arguments(scene):
    with pytest.raises(ValueError, match="factor"):
        degrade_dem(scene.dem, factor=0)
    with pytest.raises(ValueError, match="hole_fraction"):
        degrade_dem(scene.dem, hole_fraction=1.5)
