"""The Dem type: placement, bilinear lookup (any number of points), holes, resampling."""

from __future__ import annotations

import numpy as np

from companion.georef.dem import Dem


def plane_dem() -> Dem:
    rows, cols = 200, 300
    r, c = np.mgrid[0:rows, 0:cols].astype(np.float32)
    n0, e0, cell = 100.0, -50.0, 0.5
    north, east = n0 - r * cell, e0 + c * cell
    return Dem((0.2 * north - 0.1 * east + 7.0).astype(np.float32), n0, e0, cell)


def test_height_at_is_exact_on_a_plane_for_many_points() -> None:
    dem = plane_dem()
    rng = np.random.default_rng(0)
    n0, n1, e0, e1 = dem.extent_ne
    north = rng.uniform(n0, n1, 100_000)  # more than OpenCV's 32767-column limit for one remap row
    east = rng.uniform(e0, e1, 100_000)
    np.testing.assert_allclose(dem.height_at(north, east), 0.2 * north - 0.1 * east + 7.0, atol=2e-3)


def test_outside_and_holes_are_nan_and_filled_removes_holes() -> None:
    dem = plane_dem()
    assert np.isnan(dem.height_at(1e4, 0.0)[0])
    h = dem.height_m.copy()
    h[50:60, 70:80] = np.nan
    holed = Dem(h, dem.north0_m, dem.east0_m, dem.cell_m)
    n, e = holed.ne_from_rc(55.0, 75.0)
    assert np.isnan(holed.height_at(n, e)[0])
    filled = holed.filled()
    assert not np.isnan(filled.height_m).any()
    assert abs(filled.height_at(n, e)[0] - dem.height_at(n, e)[0]) < 1.5


def test_resampled_keeps_the_placement() -> None:
    dem = plane_dem()
    coarse = dem.resampled(2.0)
    assert coarse.cell_m == 2.0
    rng = np.random.default_rng(1)
    n0, n1, e0, e1 = coarse.extent_ne
    north, east = rng.uniform(n0, n1, 500), rng.uniform(e0, e1, 500)
    # area averaging a plane is still the same plane, so the placement must match to the millimetre
    np.testing.assert_allclose(coarse.height_at(north, east), dem.height_at(north, east), atol=5e-3)


def test_height_above_ground_from_a_tilted_range_on_a_slope() -> None:
    # ground rises 0.3 m per metre east; the vehicle is 100 m above the point below it and rolls 5 deg, so
    # its downward beam hits the slope east of that point, closer than 100 m / cos(5 deg)
    from companion.geometry import rot_from_rpy

    n = 401
    east = (np.arange(n) - 200) * 1.0
    dem = Dem(np.tile(0.3 * east, (n, 1)).astype(np.float32), 200.0, -200.0, 1.0)
    R = rot_from_rpy(np.radians(5.0), 0.0, 0.0)
    d = R[:, 2]
    p = np.array([0.0, 0.0, -100.0])
    t = 100.0 / (d[2] + 0.3 * d[1])  # where -100 + t d_z = -0.3 (t d_e)
    assert abs(dem.beam_range(p, d) - t) < 1e-3
    assert abs(dem.height_above_ground(p, R, t) - 100.0) < 1e-3
    # the cosine alone is off by the DEM step (several metres here)
    assert abs(t * d[2] - 100.0) > 2.0
    # off the raster: the cosine term only
    far = np.array([0.0, 5000.0, -100.0])
    assert dem.height_above_ground(far, R, 50.0) == 50.0 * d[2]
