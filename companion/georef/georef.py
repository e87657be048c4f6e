"""Geo-referencing a camera frame against the DEM (paper 1 sections 3 and 4.3, eqs. 16-18).

Pipeline of ``GeoReferencer.locate``:

1. Sanity checks on the inputs (bad shapes, blank or saturated frames, sun below the horizon, no height
   above ground): each gives ``GeoFix(ok=False, reason=...)``, never an exception.
2. The frame is reduced to the working resolution and divided by its local mean (the reflectance is
   multiplicative: large albedo patches would otherwise dominate the low frequencies).
3. Rectification to nadir: an ``OrthoGrid`` at the frame's ground sample distance / ``work_scale``, aligned
   with the frame's heading and centred where the optical axis meets the ground. Each grid cell takes its
   DEM height; that 3-D point is projected into the camera with the predicted pose and the frame is
   ``cv2.remap``-ed onto the grid: tilt and relief parallax removed in one warp.
4. Reference: the presumed-sun shading of the DEM (eq. 3) warped onto the same grid (``ReferenceMap``).
5. Phase correlation (eqs. 1-2, 16): Tukey window, a band weight limited to what the coarse, noisy DEM
   represents, sub-pixel peak by an upsampled DFT. Eq. 18: the grid shift is the horizontal error of the
   prediction, turned into world north/east through the grid's heading (X = X_R + GSD dX, rotated into NED;
   Z = DEM + H).
6. A second pass at the corrected position (relief parallax of the first pass gone) correlates against a
   reference fitted to the frame (``companion.georef.illumination``: sun-agnostic shading terms and a
   local-relief term for topography-correlated reflectance, coherence weights). The quality is the peak value
   of the presumed-sun correlation of that pass (the fitted one adapts to the frame, so it is no quality).

Optionally (``solve_rotation_scale=True``) heading and height errors are recovered first: Fourier-Mellin on
the rectified pair proposes them, a pattern search on the translation peak value polishes them, and the pair
is rectified again with the corrected heading and height.

Pure math: numpy/OpenCV, no I/O; ``time.perf_counter`` only to fill ``GeoFix.ms``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from companion.constants import R_BODY_CAM_NADIR
from companion.geometry import CameraIntrinsics, rot_from_rpy, wrap_pi
from companion.georef import illumination, phase
from companion.georef.dem import Dem
from companion.georef.reference import OrthoGrid, ReferenceMap
from companion.georef.shading import Sun

REASON_BLANK = "blank"
"""Frame has (almost) no contrast: sky, fog, lens cap, a dark night frame."""
REASON_SATURATED = "saturated"
"""Too many pixels at the ends of the range (0 or full scale)."""
REASON_OFF_DEM = "off_dem"
"""Predicted footprint lies (mostly) off the DEM or in its holes."""
REASON_SUN_BELOW_HORIZON = "sun_below_horizon"
"""Presumed sun elevation <= 0: the DEM gives no shading to match."""
REASON_LOW_QUALITY = "low_quality"
"""Phase-correlation peak (or, when asked, the rotation/scale peak) below the calibrated minimum."""
REASON_NO_HEIGHT = "no_height"
"""No usable height above ground (none given and the predicted altitude is not above the DEM)."""
REASON_LOW_OVERLAP = "low_overlap"
"""Too little of the rectification grid is seen by the camera (extreme tilt, camera not looking down)."""
REASON_BAD_INPUT = "bad_input"
"""Malformed input: wrong image shape or type, non-finite pose, not a rotation matrix."""


@dataclass(frozen=True)
class GeorefOptions:
    """Geo-referencing settings; defaults measured with ``python -m bench georef``."""

    # correlate at this fraction of the frame resolution (grid GSD = frame GSD / work_scale): the DEM carries
    # nothing finer than ~4 cells, and 1/3 was measured as accurate as 1/2 at 60 % of the time
    work_scale: float = 1.0 / 3.0
    grid_fraction: float = 1.0  # side of the ortho grid / side of the nadir footprint
    window_alpha: float = 0.5  # Tukey window taper fraction (1 = Hann)
    band_lo_cycles: float = 2.4  # lowest frequency kept: cycles across the grid (drops albedo gradients)
    band_hi_cycles_per_cell: float = 0.24  # highest frequency kept, cycles per DEM cell (DEM noise above)
    band_hi_max_cpp: float = 0.25  # and at most this, cycles per grid cell
    upsample: int = 16  # sub-pixel peak: upsampled-DFT factor (then a parabola on the fine grid)
    iterations: int = 2  # rectify + correlate passes (later ones at the corrected position)
    refine: bool = True  # later passes correlate against the fitted reference (``illumination``)
    fit_iters: int = 2  # fit + correlate rounds per refining pass
    # then move the shift to where the fitted reference explains the frame best (``illumination.joint_shift``).
    # It removes most of the along-sun bias of a coarsened DEM (``bench georef_budget --joint-shift``, DEM only
    # coarsened, uniform albedo: scene 08 -0.92 -> -0.25 px, 05 -0.56 -> -0.17 px) but adds noise where the
    # alternating fit was right (true DEM, real albedo, scene 05: 100 % -> 5 % under 1 px), and costs ~12 ms a
    # frame (Nelder-Mead over the shift). Off for a single fix (as benchmarked, 20 frames a scene: success
    # summed over the nine scenes 4.35 -> 4.15); on in terrain_lba, whose adjustment averages fixes
    joint_shift: bool = False
    n_rings: int = 4  # fitted reference: independent coefficients per log-spaced frequency ring
    n_sectors: int = 8  # coherence weights: orientation sectors per ring
    coherence_floor: float = 0.05  # coherence weight rho^2 / (1 - rho^2 + floor)
    # local-relief bases, h - Gaussian blur of h with each of these stds (m): reflectance tied to the relief
    # (dust in hollows) at that scale; one scale alone leaves a term at another scale that pulls the shift
    relief_scales_m: tuple[float, ...] = (20.0,)
    rock_filter_px: int = 1  # spot filter size (work pixels; 1 = off: measured no better on the scenes)
    rock_filter: str = "median"  # "median" (symmetric) or "close" (grey closing: dark spots only)
    contrast_sigma_px: float = 8.0  # frame divided by its local mean (Gaussian std, work px): albedo patches
    reference_upsample: int = 2  # shading raster upsampling over the DEM cell
    dem_smooth_cells: float = 0.7  # Gaussian std (DEM cells) on the DEM before shading (noise -> fake slopes)
    # below: "low_quality"; on the full benchmark no fix more than 2 m wrong scored above 0.243
    min_quality: float = 0.25
    blank_std: float = 1.0  # frame std below this (8-bit grey levels): "blank"
    max_saturated_fraction: float = 0.4  # pixels at 0 or full scale above this fraction: "saturated"
    max_invalid_fraction: float = 0.3  # grid cells off the DEM / in holes above this: "off_dem"
    min_overlap_fraction: float = 0.5  # grid cells seen by the camera below this: "low_overlap"
    max_tilt_rad: float = float(np.radians(45.0))  # optical axis further than this from nadir: "low_overlap"
    fm_n_angle: int = 360  # Fourier-Mellin: log-polar rows over a half turn
    fm_n_radius: int = 256  # Fourier-Mellin: log-polar columns
    # rotation/scale polish: pattern-search steps (degrees, scale fraction), coarse to fine
    rs_search_steps: tuple[tuple[float, float], ...] = ((2.0, 0.02), (0.6, 0.006))
    # and a coarse sweep of headings within +-rs_sweep_deg (steps of rs_sweep_step_deg) as starts besides
    # "no error" and Fourier-Mellin's proposal (0 = none): the translation peak is only found within ~2 deg
    # of the true heading, and the log-polar proposal is often wrong
    rs_sweep_deg: float = 0.0
    rs_sweep_step_deg: float = 2.0
    # covariance model, sigma_px = sigma_floor + sigma_k * (1/q - 1)^2 per axis (frame pixels), fitted to
    # the error against quality on the benchmark scenes
    sigma_floor_px: float = 0.5
    sigma_k_px: float = 0.33


@dataclass(frozen=True)
class GeoFix:
    """One geo-referencing result.

    ok/reason: reason is "" when ok, else one of the REASON_* constants.
    p_world: (3,) NED of the camera/vehicle from eq. 18 (NaN when not ok).
    shift_px: (2,) grid shift (right, down) in frame pixels at ``gsd_m`` (the prediction's error, negated).
    quality: phase-correlation peak value 0..1. gsd_m: frame ground sample distance at nadir (m/pixel).
    cov_ne_m2: (2, 2) horizontal covariance of p_world: (gsd_m * sigma_px)^2 I with
        sigma_px = sigma_floor_px + sigma_k_px * (1 / quality - 1)^2 (options; fitted to the per-axis RMS
        error against quality on the benchmark scenes, where the error is mostly scene bias, not noise).
    rotation_rad: recovered heading error (true yaw = given yaw + rotation_rad), when asked.
    scale: recovered height ratio (true height above ground = given height * scale), when asked.
    rotation_scale_quality: translation peak value 0..1 at the recovered rotation and scale (0 when not
        asked); below ``min_quality`` the fix is refused as "low_quality".
    ms: compute time of ``locate`` in milliseconds.
    """

    ok: bool
    reason: str
    p_world: np.ndarray
    shift_px: np.ndarray
    quality: float
    gsd_m: float
    cov_ne_m2: np.ndarray
    rotation_rad: float = 0.0
    scale: float = 1.0
    rotation_scale_quality: float = 0.0
    ms: float = 0.0


@dataclass(frozen=True)
class RectifiedPair:
    """A frame rectified onto an ortho grid and the reference shading on the same grid.

    frame, reference, weight, valid: (n, n) float32; valid is 0 where the camera or the DEM has no data (soft
    edges), weight = window x valid. grid: the OrthoGrid. gsd_m: frame GSD at nadir (m/pixel). alt_cam_m:
    camera elevation used. seen_fraction / dem_invalid_fraction: coverage diagnostics.
    """

    frame: np.ndarray
    reference: np.ndarray
    weight: np.ndarray
    grid: OrthoGrid
    gsd_m: float
    alt_cam_m: float
    seen_fraction: float
    dem_invalid_fraction: float
    valid: np.ndarray


def _fail(reason: str, t0: float, gsd_m: float = float("nan")) -> GeoFix:
    return GeoFix(
        ok=False,
        reason=reason,
        p_world=np.full(3, np.nan),
        shift_px=np.full(2, np.nan),
        quality=0.0,
        gsd_m=gsd_m,
        cov_ne_m2=np.full((2, 2), np.nan),
        ms=(time.perf_counter() - t0) * 1e3,
    )


class GeoReferencer:
    """Locates frames of one camera on one DEM under one presumed sun.

    dem: the estimator's DEM (world NED frame, holes NaN). sun: presumed lighting. intrinsics: the frame's
    pinhole model (undistorted). R_body_cam: camera-to-body rotation (nadir camera by default).
    Construction precomputes the shading and basis rasters (``ReferenceMap``): do it once per DEM and sun.
    """

    def __init__(
        self,
        dem: Dem,
        sun: Sun,
        intrinsics: CameraIntrinsics,
        R_body_cam: np.ndarray = R_BODY_CAM_NADIR,
        options: GeorefOptions = GeorefOptions(),
    ) -> None:
        self.dem = dem
        self.sun = sun
        self.intr = intrinsics
        self.R_body_cam = np.asarray(R_body_cam, float)
        self.opt = options
        self.ref = ReferenceMap(
            dem,
            sun,
            options.reference_upsample,
            options.dem_smooth_cells,
            with_bases=options.refine,
            relief_scales_m=tuple(options.relief_scales_m),
        )
        self.intr_work = intrinsics.scaled(options.work_scale)
        side = options.grid_fraction * max(self.intr_work.width, self.intr_work.height)
        self.grid_size = int(cv2.getOptimalDFTSize(max(int(round(side)), 16)))
        n = self.grid_size
        self._window = phase.tukey_window(n, n, options.window_alpha)
        # grid cell index vectors for the projection (float64: world coordinates can be large)
        self._jj = np.arange(n, dtype=np.float64)[None, :]
        self._ii = np.arange(n, dtype=np.float64)[:, None]
        k = max(int(options.rock_filter_px), 1)
        self._rock_kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)) if k > 1 else None

    # ------------------------------------------------------------------------------------------------------
    # pieces, public so that benchmarks can run other matchers on the very same pair

    def band(self, grid_gsd_m: float) -> tuple[float, float]:
        """(f_lo, f_hi) in cycles per grid cell (see ``GeorefOptions``)."""
        f_lo = self.opt.band_lo_cycles / self.grid_size
        f_hi = self.opt.band_hi_cycles_per_cell * grid_gsd_m / self.dem.cell_m
        return float(f_lo), float(min(max(f_hi, 2.0 * f_lo), self.opt.band_hi_max_cpp))

    def work_image(self, image: np.ndarray) -> np.ndarray:
        """Frame resized to the working resolution, float32 in 8-bit grey levels."""
        img = image.astype(np.float32)
        if image.dtype == np.uint16:
            img *= np.float32(255.0 / 65535.0)
        w, h = self.intr_work.width, self.intr_work.height
        if (w, h) != (image.shape[1], image.shape[0]):
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        return img

    def preprocess(self, img_work: np.ndarray) -> np.ndarray:
        """What the DEM cannot explain, removed from a working-resolution frame: small dark spots (rocks,
        grey closing) and slow reflectance changes (division by the local mean). float32."""
        out = img_work
        if self._rock_kernel is not None:
            if self.opt.rock_filter == "close":
                out = cv2.morphologyEx(out, cv2.MORPH_CLOSE, self._rock_kernel)
            else:
                out = cv2.medianBlur(out, min(int(self.opt.rock_filter_px) | 1, 5))
        if self.opt.contrast_sigma_px > 0:
            mean = cv2.GaussianBlur(out, (0, 0), self.opt.contrast_sigma_px)
            out = out / np.maximum(mean, np.float32(1e-3 + 1e-3 * float(mean.max())))
        return out.astype(np.float32, copy=False)

    def ground_height(self, north_m: float, east_m: float) -> float:
        """Elevation of the (filled, smoothed) DEM at a world point; NaN off the DEM."""
        r, c = self.dem.rc_from_ne(north_m, east_m)
        rows, cols = self.dem.shape
        if not (0 <= r <= rows - 1 and 0 <= c <= cols - 1):
            return float("nan")
        out = cv2.getRectSubPix(self.ref.height_m, (1, 1), (float(c), float(r)))
        return float(out[0, 0])

    def rectify(
        self,
        image_work: np.ndarray,
        R_world_body: np.ndarray,
        ne_cam: np.ndarray,
        alt_cam_m: float,
        agl_m: float,
    ) -> RectifiedPair | str:
        """Rectify a working-resolution frame onto the ortho grid; the reference on the same grid.

        ne_cam: (2,) camera north/east; alt_cam_m: camera elevation (up); agl_m: height above the ground
        below the camera (sets the GSD). Returns the pair or a REASON_* string."""
        R_world_cam = R_world_body @ self.R_body_cam
        axis = R_world_cam[:, 2]
        if axis[2] < np.cos(self.opt.max_tilt_rad):
            return REASON_LOW_OVERLAP
        gsd = agl_m / self.intr.fx
        gsd_w = gsd / self.opt.work_scale
        # grid centre: where the optical axis meets the ground (flat at the height below the camera)
        t = agl_m / axis[2]
        centre = ne_cam + t * axis[:2]
        up = -R_world_cam[:2, 1]  # image top direction on the ground (camera -y, horizontal part)
        heading = float(np.arctan2(up[1], up[0]))
        grid = OrthoGrid.make(centre, heading, gsd_w, self.grid_size)
        s = self.ref.sample(grid)
        dem_invalid = float(s.invalid.mean())
        if dem_invalid > self.opt.max_invalid_fraction:
            return REASON_OFF_DEM
        # project every grid cell's 3-D point (north, east, down = -height) into the camera
        A = grid.ne_affine()
        Rt = R_world_cam.T
        dn = A[0, 0] * self._jj + A[0, 1] * self._ii + (A[0, 2] - ne_cam[0])
        de = A[1, 0] * self._jj + A[1, 1] * self._ii + (A[1, 2] - ne_cam[1])
        dd = alt_cam_m - s.height_m.astype(np.float64)  # down from camera to ground point
        x = Rt[0, 0] * dn + Rt[0, 1] * de + Rt[0, 2] * dd
        y = Rt[1, 0] * dn + Rt[1, 1] * de + Rt[1, 2] * dd
        z = Rt[2, 0] * dn + Rt[2, 1] * de + Rt[2, 2] * dd
        iw = self.intr_work
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (iw.fx * x / z + iw.cx).astype(np.float32)
            v = (iw.fy * y / z + iw.cy).astype(np.float32)
        seen = (z > 0) & (u >= 0) & (v >= 0) & (u <= iw.width - 1) & (v <= iw.height - 1)
        seen_fraction = float(seen.mean())
        if seen_fraction < self.opt.min_overlap_fraction:
            return REASON_LOW_OVERLAP
        u[~seen] = -1.0
        v[~seen] = -1.0
        frame = cv2.remap(image_work, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        valid = seen.astype(np.float32) * (1.0 - s.invalid)
        if valid.min() < 1.0:
            # soften the mask edges so they do not ring in the spectrum
            valid = cv2.GaussianBlur(valid, (0, 0), 2.0) * valid
        weight = self._window * valid
        return RectifiedPair(
            frame, s.shading, weight, grid, gsd, alt_cam_m, seen_fraction, dem_invalid, valid
        )

    def correlate(self, pair: RectifiedPair, refine: bool) -> tuple[phase.Correlation, phase.Correlation]:
        """(final, presumed) correlations of a rectified pair; shifts in grid cells, frame(x) ~ ref(x - shift).

        presumed: band-weighted phase correlation against the presumed-sun shading (eq. 16); its peak value is
        the match quality. final: with ``refine``, ``fit_iters`` rounds of: fit the reference to the frame at
        the current shift, coherence weights, phase correlation against the fitted reference
        (``companion.georef.illumination``); without, the presumed one. The final peak is not a quality: the
        fit and the weights adapt to the frame, so a wrong match can score high too (measured)."""
        n = pair.grid.size
        shape = (n, n)
        f_lo, f_hi = self.band(pair.grid.gsd_m)
        w_band = phase.band_weight(n, n, f_lo, f_hi)
        f_img = phase.spectrum(pair.frame, pair.weight)
        if not refine:
            f_ref = phase.spectrum(pair.reference, pair.weight)
            corr = phase.correlate_spectra(f_img, f_ref, shape, w_band, self.opt.upsample)
            return corr, corr
        f_bases = [phase.spectrum(b, pair.weight) for b in self.ref.sample_bases(pair.grid, pair.reference)]
        presumed = phase.correlate_spectra(f_img, f_bases[0], shape, w_band, self.opt.upsample)
        corr = presumed
        bins = illumination.bins(shape, f_lo, f_hi, self.opt.n_rings, self.opt.n_sectors)
        for _ in range(self.opt.fit_iters):
            ref_bins = illumination.fit_reference(f_img, f_bases, bins, corr.shift_px)
            w_bins = illumination.coherence_weight(
                f_img, ref_bins, bins, corr.shift_px, self.opt.coherence_floor
            )
            if not w_bins.any():
                break
            f_ref = illumination.scatter(ref_bins, bins, shape)
            w = illumination.scatter(w_bins, bins, shape, np.float32)
            corr = phase.correlate_spectra(f_img, f_ref, shape, w, self.opt.upsample)
        if self.opt.joint_shift:
            shift = illumination.joint_shift(f_img, f_bases, bins, corr.shift_px)
            corr = phase.Correlation(shift, corr.peak, corr.psr)
        return corr, presumed

    def covariance(self, quality: float, gsd_m: float) -> np.ndarray:
        """(2, 2) horizontal covariance (m^2) of a fix of this quality: the model in ``GeoFix``'s docstring."""
        q = max(quality, 1e-3)
        sigma_px = self.opt.sigma_floor_px + self.opt.sigma_k_px * (1.0 / q - 1.0) ** 2
        return np.eye(2) * (sigma_px * gsd_m) ** 2

    # ------------------------------------------------------------------------------------------------------

    def _check_image(self, image: np.ndarray) -> str:
        if not isinstance(image, np.ndarray) or image.ndim != 2:
            return REASON_BAD_INPUT
        if image.shape != (self.intr.height, self.intr.width):
            return REASON_BAD_INPUT
        if image.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
            return REASON_BAD_INPUT
        if image.dtype.kind == "f":
            if not np.isfinite(image).all():
                return REASON_BAD_INPUT
            full = 255.0
        else:
            full = float(np.iinfo(image.dtype).max)
        n_hi = n_lo = 0
        if image.dtype.kind != "f":
            n_hi = int(np.count_nonzero(image == full))
            n_lo = int(np.count_nonzero(image == 0))
        limit = self.opt.max_saturated_fraction * image.size
        if n_hi > limit:  # over-exposed (a white frame is saturated, not blank)
            return REASON_SATURATED
        _, std = cv2.meanStdDev(image.astype(np.float32) if image.dtype == np.float64 else image)
        if float(std[0, 0]) * 255.0 / full < self.opt.blank_std:  # no contrast (a black frame is blank)
            return REASON_BLANK
        if n_hi + n_lo > limit:  # contrast, but clipped at both ends
            return REASON_SATURATED
        return ""

    def locate(
        self,
        image: np.ndarray,
        R_world_body: np.ndarray,
        p_pred_world: np.ndarray,
        alt_agl_m: float | None = None,
        solve_rotation_scale: bool = False,
    ) -> GeoFix:
        """Geo-reference one frame. Never raises on bad data: returns ``GeoFix(ok=False, reason=...)``.

        image: (H, W) uint8/uint16 (or float in 8-bit grey levels) matching the intrinsics.
        R_world_body: 3x3 attitude (the yaw may be uncertain when ``solve_rotation_scale``).
        p_pred_world: (3,) predicted body position NED (the camera is taken at the body origin).
        alt_agl_m: height above the ground below the vehicle; None = -p_pred_world[2] - DEM height there.
        solve_rotation_scale: also recover heading and height errors (Fourier-Mellin).
        """
        t0 = time.perf_counter()
        try:
            R = np.asarray(R_world_body, float)
            p = np.asarray(p_pred_world, float)
            if R.shape != (3, 3) or p.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(p).all()):
                return _fail(REASON_BAD_INPUT, t0)
            if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R.T @ R, np.eye(3), atol=1e-3):
                return _fail(REASON_BAD_INPUT, t0)
            if alt_agl_m is not None:
                alt_agl_m = float(alt_agl_m)
        except (TypeError, ValueError):
            return _fail(REASON_BAD_INPUT, t0)
        if alt_agl_m is not None and not np.isfinite(alt_agl_m):
            return _fail(REASON_NO_HEIGHT, t0)
        if not self.ref.sun_up:
            return _fail(REASON_SUN_BELOW_HORIZON, t0)
        bad = self._check_image(image)
        if bad:
            return _fail(bad, t0)
        ne = p[:2].copy()
        h0 = self.ground_height(ne[0], ne[1])
        if not np.isfinite(h0):
            return _fail(REASON_OFF_DEM, t0)
        agl = alt_agl_m if alt_agl_m is not None else float(-p[2] - h0)
        if not agl > 0.0:
            return _fail(REASON_NO_HEIGHT, t0)
        gsd0 = agl / self.intr.fx
        # A measured height above ground makes the camera elevation follow the ground below the current
        # estimate; with only the predicted altitude, that altitude is kept (eq. 18: Z = DEM(X_R) + H).
        follow_ground = alt_agl_m is not None
        alt_cam = h0 + agl
        img_w = self.preprocess(self.work_image(image))

        rotation, scale, rs_quality = 0.0, 1.0, 0.0
        if solve_rotation_scale:
            res = self._solve_rotation_scale(img_w, R, ne, alt_cam, agl)
            if isinstance(res, str):
                return _fail(res, t0, gsd0)
            rotation, scale, rs_quality = res
            if rs_quality < self.opt.min_quality:
                return _fail(REASON_LOW_QUALITY, t0, gsd0)
            R = rot_from_rpy(0.0, 0.0, rotation) @ R  # about world down: a yaw increase
            # what the search pins down is the camera elevation (ground below the prediction + height);
            # from here on it is kept, and the reported scale is re-expressed at the final position
            alt_cam = h0 + agl * scale
            agl *= scale
            follow_ground = False

        total = np.zeros(2)
        corr: phase.Correlation | None = None
        presumed: phase.Correlation | None = None
        pair: RectifiedPair | None = None
        for it in range(max(self.opt.iterations, 1)):
            res_pair = self.rectify(img_w, R, ne, alt_cam, agl)
            if isinstance(res_pair, str):
                return _fail(res_pair, t0, agl / self.intr.fx)
            pair = res_pair
            corr, presumed = self.correlate(pair, refine=self.opt.refine and it > 0)
            # eq. 18 in NED: the frame content sits at the prediction's error, negated, on the grid
            ne = ne - pair.grid.ne_of_grid_shift(corr.shift_px)
            total += corr.shift_px
            if follow_ground:
                h = self.ground_height(ne[0], ne[1])
                if not np.isfinite(h):
                    return _fail(REASON_OFF_DEM, t0, agl / self.intr.fx)
                alt_cam = h + agl
        assert corr is not None and presumed is not None and pair is not None
        if solve_rotation_scale:
            h_final = self.ground_height(ne[0], ne[1])
            if np.isfinite(h_final):
                scale = (alt_cam - h_final) / (agl / scale)
        gsd = pair.gsd_m
        shift_px = total * pair.grid.gsd_m / gsd
        quality = presumed.peak
        ok = quality >= self.opt.min_quality
        return GeoFix(
            ok=ok,
            reason="" if ok else REASON_LOW_QUALITY,
            p_world=np.array([ne[0], ne[1], -alt_cam]) if ok else np.full(3, np.nan),
            shift_px=shift_px,
            quality=quality,
            gsd_m=gsd,
            cov_ne_m2=self.covariance(quality, gsd) if ok else np.full((2, 2), np.nan),
            rotation_rad=rotation,
            scale=scale,
            rotation_scale_quality=rs_quality,
            ms=(time.perf_counter() - t0) * 1e3,
        )

    def _solve_rotation_scale(
        self, img_w: np.ndarray, R: np.ndarray, ne: np.ndarray, alt_cam: float, agl: float
    ) -> tuple[float, float, float] | str:
        """(rotation_rad, scale, quality) of the heading and height errors.

        Fourier-Mellin on the pair rectified with the given attitude and height proposes rotation (modulo pi)
        and scale. Measured on the simulated scenes, the log-polar peak of the albedo-dominated frame against
        the shading is only good to a few degrees and per cent, so the proposal (and "no error") are then
        polished by a pattern search that maximises the translation peak value (the match quality) over
        rotation and scale, finishing with a parabola through the last three samples of each.
        quality: the translation peak value at the solution (the Fourier-Mellin peak only proposes a start).
        Signs: true yaw = yaw + rotation, true height above ground = height * scale.
        """
        pair = self.rectify(img_w, R, ne, alt_cam, agl)
        if isinstance(pair, str):
            return pair
        f_lo, f_hi = self.band(pair.grid.gsd_m)
        # the square Tukey window would imprint a non-rotating cross on both spectra: validity only (the
        # Fourier-Mellin function adds a rotationally symmetric window)
        rs = phase.rotation_scale(
            pair.frame,
            pair.reference,
            pair.valid,
            f_lo=f_lo,
            f_hi=f_hi,
            n_angle=self.opt.fm_n_angle,
            n_radius=self.opt.fm_n_radius,
        )
        ground = alt_cam - agl
        cache: dict[tuple[float, float], float] = {}

        def peak_at(rotation: float, scale: float) -> float:
            key = (round(rotation, 9), round(scale, 9))
            if key not in cache:
                agl_c = agl * scale
                pc = self.rectify(img_w, rot_from_rpy(0.0, 0.0, rotation) @ R, ne, ground + agl_c, agl_c)
                cache[key] = -1.0 if isinstance(pc, str) else self.correlate(pc, refine=False)[1].peak
            return cache[key]

        # content turned clockwise on screen by a = camera turned anticlockwise seen from above: yaw - a;
        # content magnified by s = camera lower than assumed: true height = height / s
        starts = [(0.0, 1.0)]
        if 0.5 < rs.scale < 2.0:
            starts += [(float(wrap_pi(-rs.angle_rad + k * np.pi)), 1.0 / rs.scale) for k in (0, 1)]
        if self.opt.rs_sweep_deg > 0 and self.opt.rs_sweep_step_deg > 0:
            n = int(self.opt.rs_sweep_deg / self.opt.rs_sweep_step_deg)
            starts += [
                (float(np.radians(k * self.opt.rs_sweep_step_deg)), 1.0) for k in range(-n, n + 1) if k
            ]
        rotation, scale = max(starts, key=lambda x: peak_at(*x))
        if peak_at(rotation, scale) < 0:
            return REASON_LOW_OVERLAP
        for da, ds in self.opt.rs_search_steps:
            rotation = _line_search(lambda a, s=scale: peak_at(a, s), rotation, float(np.radians(da)))
            scale = _line_search(lambda x, a=rotation: peak_at(a, x), scale, ds)
        return float(wrap_pi(rotation)), float(scale), peak_at(rotation, scale)


def _line_search(f, x: float, step: float, max_moves: int = 4) -> float:
    """Maximise f near x: walk in ``step``s while a neighbour is better (at most ``max_moves``), then the
    vertex of the parabola through the last three samples (clipped to +-step)."""
    fm, f0, fp = f(x - step), f(x), f(x + step)
    for _ in range(max_moves):
        if fp > f0 and fp >= fm:
            x, fm, f0, fp = x + step, f0, fp, f(x + 2 * step)
        elif fm > f0:
            x, fm, f0, fp = x - step, f(x - 2 * step), fm, f0
        else:
            break
    return x + step * _vertex(fm, f0, fp)


def _vertex(m: float, c: float, p: float) -> float:
    """Offset (in steps, clipped to +-1) of the vertex of the parabola through (-1, m), (0, c), (1, p)."""
    den = m - 2.0 * c + p
    if den >= 0:
        return float(np.clip((p - m) * 1e9, -1.0, 1.0)) if p != m else 0.0
    return float(np.clip(0.5 * (m - p) / den, -1.0, 1.0))
