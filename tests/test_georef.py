"""GeoReferencer on a small synthetic world: accuracy, tilt rectification, rotation/scale, bad inputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from companion.geometry import CameraIntrinsics, camera_pose, pixel_rays_cam, rot_from_rpy
from companion.georef import georef as G
from companion.georef.dem import Dem
from companion.georef.georef import GeoReferencer, GeorefOptions
from companion.georef.shading import Sun, lambert_shading

SUN = Sun.from_degrees(10.0, 0.0, 60.0)
INTR = CameraIntrinsics.from_focal_sensor(240, 240, 36.0, 36.0)  # fx = 240 px, 53 deg field of view
AGL_M = 60.0  # GSD 0.25 m


class World:
    """A 200 m x 200 m terrain at 0.25 m (rolling hills and bumps, ~14 m relief), flat albedo, and a
    ray-casting renderer: the truth. ``dem(factor)`` is what an estimator gets."""

    cell_m = 0.25

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        n = 800
        h = np.zeros((n, n), np.float32)
        for sigma_m, amp in ((24.0, 6.0), (8.0, 1.2), (3.0, 0.25), (1.0, 0.04), (0.5, 0.012)):
            layer = cv2.GaussianBlur(
                rng.standard_normal((n, n)).astype(np.float32), (0, 0), sigma_m / self.cell_m
            )
            h += amp * layer / layer.std()
        self.truth = Dem(h, (n - 1) / 2 * self.cell_m, -(n - 1) / 2 * self.cell_m, self.cell_m)
        self.radiance = lambert_shading(h, self.cell_m, SUN) * np.float32(0.3)
        self.rays = pixel_rays_cam(INTR).reshape(-1, 3)

    def dem(self, factor: int = 1) -> Dem:
        return self.truth if factor == 1 else self.truth.resampled(self.cell_m * factor)

    def ground(self, north: float, east: float) -> float:
        return float(self.truth.height_at(north, east)[0])

    def render(self, R_world_body: np.ndarray, p_body: np.ndarray, noise: float = 1.0, seed: int = 0):
        R_wc, c = camera_pose(R_world_body, p_body)
        d = self.rays @ R_wc.T
        t = (-c[2] - float(self.truth.height_m.mean())) / d[:, 2]
        for _ in range(15):  # fixed point: slopes x ray angles < 1 here, so it converges
            x = c[None] + t[:, None] * d
            hh = self._lookup(self.truth.height_m, x)
            t = (-c[2] - hh) / d[:, 2]
        x = c[None] + t[:, None] * d
        img = self._lookup(self.radiance, x).reshape(INTR.height, INTR.width) * 70.0
        img = img + np.random.default_rng(seed).normal(0.0, noise, img.shape)
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)

    def _lookup(self, raster: np.ndarray, x: np.ndarray) -> np.ndarray:
        r, col = self.truth.rc_from_ne(x[:, 0], x[:, 1])
        shape = (INTR.height, INTR.width)
        out = cv2.remap(
            raster.astype(np.float32),
            col.astype(np.float32).reshape(shape),
            r.astype(np.float32).reshape(shape),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        return out.ravel().astype(np.float64)

    def pose(self, north: float, east: float, roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0):
        R = rot_from_rpy(*np.radians([roll_deg, pitch_deg, yaw_deg]))
        return R, np.array([north, east, -(self.ground(north, east) + AGL_M)])


@pytest.fixture(scope="module")
def world() -> World:
    return World(0)


@pytest.fixture(scope="module")
def geo_fine(world: World) -> GeoReferencer:
    # the true surface as DEM: only the method's own error is left
    return GeoReferencer(
        world.dem(1), SUN, INTR, options=GeorefOptions(reference_upsample=1, dem_smooth_cells=0.0)
    )


def _error_px(fix: G.GeoFix, p_true: np.ndarray) -> float:
    return float(np.hypot(*(fix.p_world[:2] - p_true[:2])) / (AGL_M / INTR.fx))


def test_recovers_position_from_a_wrong_prediction(world: World, geo_fine: GeoReferencer) -> None:
    rng = np.random.default_rng(10)
    errors = []
    for k in range(4):
        north, east = rng.uniform(-40, 40, 2)
        R, p = world.pose(north, east, yaw_deg=rng.uniform(-180, 180))
        img = world.render(R, p, seed=k)
        pred = p + np.r_[rng.uniform(-3, 3, 2), 0.0]  # a few metres off, like a VO prediction
        fix = geo_fine.locate(img, R, pred, alt_agl_m=AGL_M)
        assert fix.ok, fix.reason
        errors.append(_error_px(fix, p))
        # eq. 18: Z = DEM + H
        assert fix.p_world[2] == pytest.approx(p[2], abs=0.3)
        assert fix.gsd_m == pytest.approx(AGL_M / INTR.fx)
        assert 0.3 < fix.quality <= 1.0
        assert fix.cov_ne_m2.shape == (2, 2) and np.all(np.linalg.eigvalsh(fix.cov_ne_m2) > 0)
        # the reported shift is the prediction's error in frame pixels (negated)
        assert np.hypot(*fix.shift_px) == pytest.approx(np.hypot(*(pred - p)[:2]) / fix.gsd_m, abs=0.5)
    assert max(errors) < 0.25


def test_height_from_predicted_altitude_when_no_agl(world: World, geo_fine: GeoReferencer) -> None:
    R, p = world.pose(10.0, -20.0, yaw_deg=30.0)
    img = world.render(R, p)
    pred = p + np.array([2.0, -1.5, 0.0])
    fix = geo_fine.locate(img, R, pred)  # height above ground from the predicted altitude and the DEM
    assert fix.ok
    assert _error_px(fix, p) < 0.5
    assert fix.p_world[2] == pytest.approx(pred[2])


def test_tilted_frame_is_rectified(world: World, geo_fine: GeoReferencer) -> None:
    """Roll/pitch ~10 deg over ~14 m relief: as good as nadir (a plain homography would not be)."""
    rng = np.random.default_rng(11)
    for k, (roll, pitch) in enumerate(((10.0, -8.0), (-9.0, 10.0), (0.0, 12.0))):
        north, east = rng.uniform(-40, 40, 2)
        R, p = world.pose(north, east, roll, pitch, rng.uniform(-180, 180))
        img = world.render(R, p, seed=k)
        fix = geo_fine.locate(img, R, p + np.r_[rng.uniform(-3, 3, 2), 0.0], alt_agl_m=AGL_M)
        assert fix.ok, fix.reason
        assert _error_px(fix, p) < 0.3


def test_coarse_noisy_dem_still_locates(world: World) -> None:
    """The estimator's DEM 4x coarser than the surface, with noise and holes: still within 2 pixels (the
    coarse DEM's shading of sub-cell roughness costs about a pixel, measured)."""
    dem = world.dem(4)
    h = dem.height_m.copy()
    rng = np.random.default_rng(12)
    h += rng.normal(0.0, 0.1, h.shape).astype(np.float32)
    h[100:104, 60:66] = np.nan
    geo = GeoReferencer(Dem(h, dem.north0_m, dem.east0_m, dem.cell_m), SUN, INTR)
    for k in range(3):
        north, east = rng.uniform(-40, 40, 2)
        R, p = world.pose(north, east, yaw_deg=rng.uniform(-180, 180))
        fix = geo.locate(world.render(R, p, seed=k), R, p + np.r_[rng.uniform(-3, 3, 2), 0.0], AGL_M)
        assert fix.ok, fix.reason
        assert _error_px(fix, p) < 2.0


def test_rotation_and_scale_recovered(world: World, geo_fine: GeoReferencer) -> None:
    """Heading off by 4 deg and height off by 4 %: recovered within 0.5 deg and 1 %, then the fix."""
    R, p = world.pose(-15.0, 25.0, yaw_deg=40.0)
    img = world.render(R, p)
    R_wrong = rot_from_rpy(0.0, 0.0, np.radians(40.0 - 4.0))
    fix = geo_fine.locate(
        img, R_wrong, p + np.array([1.5, -2.0, 0.0]), AGL_M / 1.04, solve_rotation_scale=True
    )
    assert fix.ok, fix.reason
    assert np.degrees(fix.rotation_rad) == pytest.approx(4.0, abs=0.5)
    assert fix.scale == pytest.approx(1.04, rel=0.01)
    assert fix.rotation_scale_quality > 0.05
    assert _error_px(fix, p) < 0.5


def test_heading_sweep_finds_a_heading_far_off(world: World) -> None:
    """25 deg off: out of reach of the polish from "no error" and of the log-polar proposal here; the
    coarse sweep of headings (``rs_sweep_deg``) finds it."""
    R, p = world.pose(-15.0, 25.0, yaw_deg=40.0)
    img = world.render(R, p)
    R_wrong = rot_from_rpy(0.0, 0.0, np.radians(40.0 - 25.0))
    p_pred = p + np.array([1.5, -2.0, 0.0])
    for sweep in (0.0, 30.0):
        geo = GeoReferencer(world.dem(4), SUN, INTR, options=GeorefOptions(rs_sweep_deg=sweep))
        fix = geo.locate(img, R_wrong, p_pred, AGL_M / 1.04, solve_rotation_scale=True)
        if sweep == 0.0:
            assert not fix.ok or abs(np.degrees(fix.rotation_rad) - 25.0) > 5.0
        else:
            assert fix.ok, fix.reason
            assert np.degrees(fix.rotation_rad) == pytest.approx(25.0, abs=0.5)
            assert fix.scale == pytest.approx(1.04, rel=0.02)
            assert _error_px(fix, p) < 1.0


def test_deterministic(world: World, geo_fine: GeoReferencer) -> None:
    R, p = world.pose(5.0, 5.0, yaw_deg=-60.0)
    img = world.render(R, p)
    a = geo_fine.locate(img, R, p + np.array([1.0, 1.0, 0.0]), AGL_M)
    b = geo_fine.locate(img, R, p + np.array([1.0, 1.0, 0.0]), AGL_M)
    assert np.array_equal(a.p_world, b.p_world) and a.quality == b.quality


# ---------------------------------------------------------------------------------------------------------
# bad inputs: each gives its reason, never an exception, never a fix


def _assert_no_fix(fix: G.GeoFix, reason: str) -> None:
    assert not fix.ok
    assert fix.reason == reason
    assert np.all(np.isnan(fix.p_world))


def test_blank_frame(world: World, geo_fine: GeoReferencer) -> None:
    R, p = world.pose(0.0, 0.0)
    _assert_no_fix(geo_fine.locate(np.full((240, 240), 87, np.uint8), R, p, AGL_M), G.REASON_BLANK)
    dark = np.random.default_rng(0).integers(0, 2, (240, 240)).astype(np.uint8)  # night: noise only
    _assert_no_fix(geo_fine.locate(dark, R, p, AGL_M), G.REASON_BLANK)


def test_saturated_frame(world: World, geo_fine: GeoReferencer) -> None:
    R, p = world.pose(0.0, 0.0)
    img = world.render(R, p).astype(np.int32) * 8
    _assert_no_fix(geo_fine.locate(np.clip(img, 0, 255).astype(np.uint8), R, p, AGL_M), G.REASON_SATURATED)


def test_off_dem(world: World, geo_fine: GeoReferencer) -> None:
    R, p = world.pose(0.0, 0.0)
    img = world.render(R, p)
    _assert_no_fix(geo_fine.locate(img, R, np.array([500.0, 0.0, -70.0]), AGL_M), G.REASON_OFF_DEM)
    # inside the DEM but the footprint mostly outside
    _assert_no_fix(geo_fine.locate(img, R, np.array([95.0, 95.0, -70.0]), AGL_M), G.REASON_OFF_DEM)
    holes = world.dem(4).height_m.copy()
    holes[10:-10, 10:-10] = np.nan
    d4 = world.dem(4)
    geo = GeoReferencer(Dem(holes, d4.north0_m, d4.east0_m, d4.cell_m), SUN, INTR)
    _assert_no_fix(geo.locate(img, R, p, AGL_M), G.REASON_OFF_DEM)


def test_sun_below_horizon(world: World) -> None:
    geo = GeoReferencer(world.dem(4), Sun.from_degrees(10.0, 0.0, -5.0), INTR)
    R, p = world.pose(0.0, 0.0)
    _assert_no_fix(geo.locate(world.render(R, p), R, p, AGL_M), G.REASON_SUN_BELOW_HORIZON)


def test_no_height(world: World, geo_fine: GeoReferencer) -> None:
    R, p = world.pose(0.0, 0.0)
    img = world.render(R, p)
    below_ground = np.array([p[0], p[1], -world.ground(p[0], p[1]) + 5.0])
    _assert_no_fix(geo_fine.locate(img, R, below_ground), G.REASON_NO_HEIGHT)
    _assert_no_fix(geo_fine.locate(img, R, p, float("nan")), G.REASON_NO_HEIGHT)
    _assert_no_fix(geo_fine.locate(img, R, p, -3.0), G.REASON_NO_HEIGHT)


def test_low_quality_for_unrelated_texture(world: World, geo_fine: GeoReferencer) -> None:
    R, p = world.pose(0.0, 0.0)
    rng = np.random.default_rng(1)
    clouds = cv2.GaussianBlur(rng.standard_normal((240, 240)).astype(np.float32), (0, 0), 4.0)
    img = np.clip(120 + 40 * clouds / clouds.std(), 0, 255).astype(np.uint8)
    fix = geo_fine.locate(img, R, p, AGL_M)
    _assert_no_fix(fix, G.REASON_LOW_QUALITY)
    assert fix.quality < geo_fine.opt.min_quality


def test_low_overlap_when_looking_at_the_horizon(world: World, geo_fine: GeoReferencer) -> None:
    R, p = world.pose(0.0, 0.0, pitch_deg=70.0)
    _assert_no_fix(geo_fine.locate(world.render(*world.pose(0.0, 0.0)), R, p, AGL_M), G.REASON_LOW_OVERLAP)


@pytest.mark.parametrize(
    ("image", "R", "p"),
    [
        (np.zeros((240, 241), np.uint8), np.eye(3), np.zeros(3)),  # wrong size
        (np.zeros((240, 240, 3), np.uint8), np.eye(3), np.zeros(3)),  # colour
        (np.zeros((240, 240), np.int64), np.eye(3), np.zeros(3)),  # odd type
        (np.full((240, 240), np.nan, np.float32), np.eye(3), np.zeros(3)),  # NaN pixels
        (np.zeros((240, 240), np.uint8), np.full((3, 3), np.nan), np.zeros(3)),  # NaN attitude
        (np.zeros((240, 240), np.uint8), 2 * np.eye(3), np.zeros(3)),  # not a rotation
        (np.zeros((240, 240), np.uint8), np.eye(3), np.array([0.0, np.inf, -70.0])),  # inf position
        (np.zeros((240, 240), np.uint8), np.eye(3), np.zeros(2)),  # wrong position shape
    ],
)
def test_bad_input(geo_fine: GeoReferencer, image, R, p) -> None:
    _assert_no_fix(geo_fine.locate(image, R, p, AGL_M), G.REASON_BAD_INPUT)


class _PeriodicTerrain:
    """A periodic random terrain (1 m cells, ``n`` x ``n``, 15 m std) under a sun in the north, with the
    matcher's basis images computed with wrapped derivatives, and frames moved by an exact sub-pixel shift."""

    def __init__(self, n: int, corner_cycles_per_m: float, seed: int) -> None:
        from companion.georef.shading import slopes

        self.n = n
        rng = np.random.default_rng(seed)
        self.fy = np.fft.fftfreq(n)[:, None]
        self.fx = np.fft.fftfreq(n)[None, :]
        f = np.hypot(self.fx, self.fy)
        spec = np.fft.fft2(rng.standard_normal((n, n))) * np.exp(-((f / corner_cycles_per_m) ** 2))
        h = np.fft.ifft2(spec).real
        self.h = (15.0 * h / h.std()).astype(np.float32)
        sun = Sun.from_degrees(10.0, 0.0, 45.0)
        self.shading = self.periodic(lambda x: lambert_shading(x, 1.0, sun))
        de = self.periodic(lambda x: slopes(x, 1.0)[0])
        dn = self.periodic(lambda x: slopes(x, 1.0)[1])
        inv_n = 1.0 / np.sqrt(1.0 + de * de + dn * dn)
        self.shading_bases = [self.shading, de * inv_n, dn * inv_n, inv_n]

    def periodic(self, fn):  # evaluate on a 3x3 tiling so that filters wrap, keep the middle
        n = self.n
        return fn(np.tile(self.h, (3, 3)))[n : 2 * n, n : 2 * n]

    def relief(self, scale_m: float) -> np.ndarray:
        """The matcher's local-relief basis: h - Gaussian blur of h (std ``scale_m``)."""
        return self.periodic(lambda x: x - cv2.GaussianBlur(x, (0, 0), scale_m))

    def shifted(self, img: np.ndarray, shift_px: np.ndarray) -> np.ndarray:
        """``img``'s content moved by (right, down) ``shift_px`` (exact, periodic)."""
        ramp = np.exp(-2j * np.pi * (self.fx * shift_px[0] + self.fy * shift_px[1]))
        return np.fft.ifft2(np.fft.fft2(img) * ramp).real.astype(np.float32)

    def joint_shift(self, frame: np.ndarray, bases: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(the presumed-sun correlation's shift, ``illumination.joint_shift`` from it) with these bases."""
        from companion.georef import illumination, phase

        n = self.n
        ones = np.ones((n, n), np.float32)
        f_img = phase.spectrum(frame, ones)
        f_bases = [phase.spectrum(b.astype(np.float32), ones) for b in bases]
        f_lo, f_hi = 3.0 / n, 0.2
        w = phase.band_weight(n, n, f_lo, f_hi)
        corr = phase.correlate_spectra(f_img, f_bases[0], (n, n), w, 16)
        b = illumination.bins((n, n), f_lo, f_hi, 4, 8)
        return corr.shift_px, illumination.joint_shift(f_img, f_bases, b, corr.shift_px)


def test_joint_shift_is_not_pulled_by_a_height_like_term() -> None:
    # The frame is the shading plus a reflectance tied to the relief (darker high ground), shifted by a known
    # sub-pixel amount. Correlating against the shading alone puts the peak off along the sun; minimising the
    # fitted residual over the shift (the even term is one of the bases) finds the shift.
    t = _PeriodicTerrain(128, 0.04, 5)
    relief = t.h - t.h.mean()
    truth = np.array([0.37, -0.21])  # (right, down) pixels
    # as strong as the shading at the longest wavelengths
    presumed, est = t.joint_shift(t.shifted(t.shading - 1.0 * relief, truth), t.shading_bases + [relief])
    pull = presumed - truth
    assert abs(pull[1]) > 0.05 and abs(pull[1]) > 5 * abs(pull[0])  # pulled off, along the sun (north)
    np.testing.assert_allclose(est, truth, atol=0.005)


def test_joint_shift_needs_the_relief_at_the_reflectance_scale() -> None:
    # Reflectance tied to the relief at a small scale (h - blur(h, 5 m): dust in small hollows) is not a
    # per-ring multiple of the 20 m relief image where the two filters differ, inside the lowest frequency
    # ring: with the 20 m basis alone the rest pulls the joint shift along the sun; with a 5 m basis beside
    # it (``GeorefOptions.relief_scales_m`` = (20, 5), terrain SLAM's) the shift is found.
    t = _PeriodicTerrain(128, 0.06, 5)
    r20, r5 = t.relief(20.0), t.relief(5.0)
    truth = np.array([0.37, -0.21])
    frame = t.shifted(t.shading - r5 * float(t.shading.std() / r5.std()), truth)
    _, one = t.joint_shift(frame, t.shading_bases + [r20])
    _, two = t.joint_shift(frame, t.shading_bases + [r20, r5])
    assert abs(one[1] - truth[1]) > 0.05 and abs(one[1] - truth[1]) > 3 * abs(one[0] - truth[0])
    np.testing.assert_allclose(two, truth, atol=0.005)


def test_reference_map_has_one_relief_basis_per_scale() -> None:
    from companion.georef.reference import OrthoGrid, ReferenceMap

    h = np.random.default_rng(0).normal(0.0, 2.0, (80, 80)).astype(np.float32)
    dem = Dem(h, 40.0, -40.0, 1.0)
    ref = ReferenceMap(dem, Sun.from_degrees(10.0, 0.0, 45.0), relief_scales_m=(20.0, 5.0))
    assert ref.basis_names == ("shading", "slope_east", "slope_north", "flat", "relief_20m", "relief_5m")
    bases = ref.sample_bases(OrthoGrid.make(np.zeros(2), 0.0, 0.5, 64))
    assert len(bases) == 6 and all(b.shape == (64, 64) for b in bases)
    # the smaller scale keeps less of the long wavelengths: less variance than the 20 m relief
    assert 0.0 < float(bases[5].std()) < float(bases[4].std())
