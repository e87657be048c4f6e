"""Procedural icy terrain for paper 2 section 4.1: heights and albedo on a north-up grid.

The geometry is a sum of features drawn from power-law size-frequency distributions (as in the lunar
simulator of Allan et al. 2019 that paper 2 builds on): rolling hills and sinuous valleys on a fractal
(fBm) background, craters, blocks, broken surfacing (chaos-like tilted plates), penitentes and
crevasses. The large-scale background is finally scaled so the total relief (max - min) equals the
paper's 31.7 m. The albedo map (section 4.2) is centred on a nominal value with "splotches" of
variability and darker linear striae that have no corresponding geometry.

Hand-written because no library generates planetary terrain; each feature is stamped into a small
window of the grid so generation stays a few seconds for 1600 x 1600 cells. Pure numpy/scipy/OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import optimize
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class TerrainOptions:
    """Feature populations. Sizes in metres; ``*_count`` are expected numbers over 400 x 400 m
    (scaled with the area); diameters follow a cumulative power law N(>D) ~ D^-slope."""

    relief_m: float = 31.7  # elevation range (paper 2 section 4.1), measured between the 0.05 and 99.95
    # percentiles so that a few metre-wide crevasses and blocks do not set the landscape's scale
    fbm_hurst: float = 1.0  # Hurst exponent of the background (power spectrum ~ k^-(2H+2)); 1 keeps
    # landscape slopes at the 5-10 m scale around 10 deg (median)
    fbm_outer_scale_m: float = 150.0  # longest wavelength kept at full power
    fbm_inner_scale_m: float = 6.0  # background rolled off below this wavelength (roughness takes over)
    roughness_m: float = 0.05  # rms of the small-scale (< 3 m) part of the background
    hill_count: int = 18
    hill_diam_m: tuple[float, float] = (20.0, 120.0)
    hill_height_frac: tuple[float, float] = (0.05, 0.15)  # height / diameter
    valley_count: int = 5
    valley_width_m: tuple[float, float] = (8.0, 30.0)
    valley_depth_frac: tuple[float, float] = (0.1, 0.25)  # depth / width
    crater_count: int = 45
    crater_diam_m: tuple[float, float] = (3.0, 40.0)
    crater_sfd_slope: float = 2.0
    block_count: int = 2500
    block_diam_m: tuple[float, float] = (0.5, 5.0)
    block_sfd_slope: float = 2.5
    broken_patch_count: int = 3
    broken_patch_radius_m: tuple[float, float] = (25.0, 60.0)
    broken_plate_m: tuple[float, float] = (4.0, 14.0)  # plate (Voronoi cell) size range
    penitente_patch_count: int = 3
    penitente_patch_radius_m: tuple[float, float] = (20.0, 45.0)
    penitente_height_m: tuple[float, float] = (1.0, 3.5)
    penitente_spacing_m: tuple[float, float] = (2.0, 4.5)
    crevasse_count: int = 8
    crevasse_length_m: tuple[float, float] = (40.0, 160.0)
    crevasse_width_m: tuple[float, float] = (0.6, 3.0)
    crevasse_depth_m: tuple[float, float] = (2.0, 8.0)


@dataclass(frozen=True)
class AlbedoOptions:
    """Albedo (reflectance in 0..1) map: nominal value, splotches and striae (paper 2 section 4.2)."""

    mean: float = 0.68  # nominal albedo; Europa's bolometric Bond albedo, as in paper 2
    splotch_rms: float = 0.08  # relative rms of the smooth splotch field
    splotch_count: int = 400  # discrete splotches (dark or bright blobs)
    splotch_radius_m: tuple[float, float] = (0.5, 15.0)
    splotch_contrast: float = 0.18  # max relative darkening / brightening of one splotch
    stria_count: int = 60
    stria_length_m: tuple[float, float] = (40.0, 400.0)
    stria_width_m: tuple[float, float] = (0.3, 2.5)
    stria_darkening: tuple[float, float] = (0.1, 0.35)  # relative darkening at the stria's centre line
    grain_rms: float = 0.03  # relative rms of cell-scale grain texture


def power_law_sizes(rng: np.random.Generator, n: int, lo: float, hi: float, slope: float) -> np.ndarray:
    """(n,) sizes in [lo, hi] with cumulative distribution N(>D) ~ D^-slope (inverse-CDF sampling)."""
    u = rng.random(n)
    a, b = lo**-slope, hi**-slope
    return (a - u * (a - b)) ** (-1.0 / slope)


def _count(rng: np.random.Generator, expected: float, area_scale: float) -> int:
    return int(rng.poisson(expected * area_scale))


def fbm_field(
    rng: np.random.Generator,
    shape: tuple[int, int],
    cell_m: float,
    hurst: float,
    outer_m: float,
    inner_m: float = 0.0,
) -> np.ndarray:
    """Unit-rms fractional Brownian surface by spectral synthesis, (rows, cols) float64.

    Amplitude spectrum ~ k^-(H+1) for k above 1/outer_m, flat below; rolled off as exp(-(k inner_m)^2)
    at wavelengths shorter than ``inner_m`` (so a landscape-scale field leaves the metre scale to others)."""
    rows, cols = shape
    kr = np.fft.fftfreq(rows, d=cell_m)[:, None]
    kc = np.fft.rfftfreq(cols, d=cell_m)[None, :]
    k = np.sqrt(kr**2 + kc**2)
    k = np.maximum(k, 1.0 / outer_m)
    amp = k ** -(hurst + 1.0) * np.exp(-((k * inner_m) ** 2))
    amp[0, 0] = 0.0
    noise = rng.standard_normal((rows, cols // 2 + 1)) + 1j * rng.standard_normal((rows, cols // 2 + 1))
    f = np.fft.irfft2(noise * amp, s=shape)
    return f / f.std()


def _window(shape: tuple[int, int], r: float, c: float, half: float) -> tuple[slice, slice] | None:
    rows, cols = shape
    r0, r1 = max(int(np.floor(r - half)), 0), min(int(np.ceil(r + half)) + 1, rows)
    c0, c1 = max(int(np.floor(c - half)), 0), min(int(np.ceil(c + half)) + 1, cols)
    if r0 >= r1 or c0 >= c1:
        return None
    return slice(r0, r1), slice(c0, c1)


def _local_xy(sl: tuple[slice, slice], r: float, c: float, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """East (x) and north (y) offsets in metres of the window's cells from fractional (r, c)."""
    rr = np.arange(sl[0].start, sl[0].stop)[:, None]
    cc = np.arange(sl[1].start, sl[1].stop)[None, :]
    return (cc - c) * cell_m, (r - rr) * cell_m


def _polyline(rng: np.random.Generator, length_m: float, step_m: float, wander_rad: float) -> np.ndarray:
    """(n, 2) points (x east, y north) of a gently meandering path starting at the origin."""
    n = max(int(length_m / step_m), 2)
    heading = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, wander_rad, n))
    steps = np.stack([np.cos(heading), np.sin(heading)], axis=1) * step_m
    return np.concatenate([[[0.0, 0.0]], np.cumsum(steps, axis=0)])


def _add_polyline_feature(
    field: np.ndarray,
    cell_m: float,
    rc: tuple[float, float],
    pts: np.ndarray,
    half_width_m: float,
    profile,
) -> None:
    """Add ``profile(distance_m)`` within ``half_width_m`` of the polyline ``pts`` ((n, 2) east, north in
    metres relative to the grid point ``rc``). Candidate cells come from a thick raster line (OpenCV), their
    distance from the nearest point of the path resampled every cell / 4 (SciPy KD-tree)."""
    rows, cols = field.shape
    r_pts = rc[0] - pts[:, 1] / cell_m
    c_pts = rc[1] + pts[:, 0] / cell_m
    pad = half_width_m / cell_m + 2
    r0, r1 = max(int(np.floor(r_pts.min() - pad)), 0), min(int(np.ceil(r_pts.max() + pad)) + 1, rows)
    c0, c1 = max(int(np.floor(c_pts.min() - pad)), 0), min(int(np.ceil(c_pts.max() + pad)) + 1, cols)
    if r0 >= r1 or c0 >= c1:
        return
    mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
    shift = 4  # sub-pixel bits of cv2.polylines
    poly = np.round(np.stack([c_pts - c0, r_pts - r0], 1) * (1 << shift)).astype(np.int32)
    cv2.polylines(
        mask, [poly], False, 1, thickness=int(2 * np.ceil(pad)) + 1, lineType=cv2.LINE_8, shift=shift
    )
    rr, cc = np.nonzero(mask)
    if rr.size == 0:
        return
    # resample the path densely so the nearest sample is within cell / 8 of the true nearest point
    seg = np.diff(np.stack([r_pts, c_pts], 1), axis=0)
    n_sub = np.maximum(np.ceil(np.hypot(seg[:, 0], seg[:, 1]) * 4).astype(int), 1)
    dense = np.concatenate(
        [np.stack([r_pts[i] + seg[i, 0] * np.arange(k) / k, c_pts[i] + seg[i, 1] * np.arange(k) / k], 1)
         for i, k in enumerate(n_sub)] + [[[r_pts[-1], c_pts[-1]]]]
    )  # fmt: skip
    d, _ = cKDTree(dense).query(np.stack([rr + r0, cc + c0], 1), distance_upper_bound=half_width_m / cell_m)
    d_m = d * cell_m
    near = d_m < half_width_m
    field[rr[near] + r0, cc[near] + c0] += profile(d_m[near])


def _soft_disc(
    shape: tuple[int, int], cell_m: float, r: float, c: float, radius_m: float, edge_m: float
) -> tuple[tuple[slice, slice], np.ndarray] | None:
    sl = _window(shape, r, c, (radius_m + edge_m) / cell_m + 1)
    if sl is None:
        return None
    x, y = _local_xy(sl, r, c, cell_m)
    d = np.hypot(x, y)
    w = np.clip((radius_m + edge_m - d) / edge_m, 0.0, 1.0)
    return sl, w * w * (3 - 2 * w)  # smoothstep


def europa_heights(
    rng: np.random.Generator, shape: tuple[int, int], cell_m: float, opts: TerrainOptions
) -> np.ndarray:
    """(rows, cols) float32 elevations (m, up positive, mean about 0) with relief ``opts.relief_m``."""
    rows, cols = shape
    area_scale = rows * cols * cell_m * cell_m / 160_000.0

    def rand_rc() -> tuple[float, float]:
        return float(rng.uniform(0, rows - 1)), float(rng.uniform(0, cols - 1))

    # --- large scale: fBm background, hills, valleys (scaled together at the end), built on a ~1 m grid
    # (they have no detail below a few metres) and interpolated to the cells ---
    f = max(int(round(1.0 / cell_m)), 1)
    shape_c = (-(-rows // f), -(-cols // f))
    cell_c = cell_m * f
    base = fbm_field(rng, shape_c, cell_c, opts.fbm_hurst, opts.fbm_outer_scale_m, opts.fbm_inner_scale_m)
    large = np.zeros(shape_c)
    for _ in range(_count(rng, opts.hill_count, area_scale)):
        d = float(rng.uniform(*opts.hill_diam_m))
        h = d * float(rng.uniform(*opts.hill_height_frac))
        r, c = float(rng.uniform(0, shape_c[0] - 1)), float(rng.uniform(0, shape_c[1] - 1))
        sl = _window(shape_c, r, c, 1.5 * d / cell_c)
        if sl is None:
            continue
        x, y = _local_xy(sl, r, c, cell_c)
        ang = rng.uniform(0, np.pi)
        ax = np.cos(ang) * x + np.sin(ang) * y
        ay = -np.sin(ang) * x + np.cos(ang) * y
        elong = float(rng.uniform(1.0, 2.0))
        q = (ax / (0.5 * d * elong)) ** 2 + (ay / (0.5 * d / elong)) ** 2
        large[sl] += h * np.exp(-2.0 * q)
    for _ in range(_count(rng, opts.valley_count, area_scale)):
        vw = float(rng.uniform(*opts.valley_width_m))
        depth = vw * float(rng.uniform(*opts.valley_depth_frac))
        pts = _polyline(rng, float(rng.uniform(150, 400)), 4.0, 0.08)
        rc = (float(rng.uniform(0, shape_c[0] - 1)), float(rng.uniform(0, shape_c[1] - 1)))
        _add_polyline_feature(
            large,
            cell_c,
            rc,
            pts,
            vw,
            lambda d, vw=vw, depth=depth: -depth * np.cos(0.5 * np.pi * d / vw) ** 2,
        )
    large_c = base + large / max(large.std(), 1e-9) * 0.6
    large_all = cv2.resize(
        large_c.astype(np.float32), (shape_c[1] * f, shape_c[0] * f), interpolation=cv2.INTER_LINEAR
    )
    large_all = large_all[:rows, :cols].astype(np.float64)

    # --- small and medium features, physical sizes, not rescaled ---
    small = opts.roughness_m * fbm_field(rng, shape, cell_m, 0.8, 6.0)
    n_craters = _count(rng, opts.crater_count, area_scale)
    for diam in power_law_sizes(rng, n_craters, *opts.crater_diam_m, opts.crater_sfd_slope):
        fresh = float(rng.uniform(0.3, 1.0))  # ice relaxes craters: shallower when older
        depth, rim = 0.2 * diam * fresh, 0.04 * diam * fresh
        r, c = rand_rc()
        sl = _window(shape, r, c, 1.5 * diam / cell_m)
        if sl is None:
            continue
        x, y = _local_xy(sl, r, c, cell_m)
        s = np.hypot(x, y) / (0.5 * diam)
        inside = rim + depth * (s * s - 1.0)
        outside = rim * np.clip(s, 1.0, None) ** -3 * np.clip((3.0 - s) / 2.0, 0.0, 1.0)
        small[sl] += np.where(s < 1.0, inside, outside)
    for _ in range(_count(rng, opts.broken_patch_count, area_scale)):
        r, c = rand_rc()
        disc = _soft_disc(shape, cell_m, r, c, float(rng.uniform(*opts.broken_patch_radius_m)), 6.0)
        if disc is None:
            continue
        sl, w = disc
        x, y = _local_xy(sl, r, c, cell_m)
        plate = float(rng.uniform(*opts.broken_plate_m))
        n_seeds = max(int(w.size * cell_m * cell_m / plate**2), 4)
        seeds = np.stack([rng.uniform(x.min(), x.max(), n_seeds), rng.uniform(y.min(), y.max(), n_seeds)], 1)
        xx, yy = np.broadcast_arrays(x, y)
        dist, idx = cKDTree(seeds).query(np.stack([xx.ravel(), yy.ravel()], 1), k=2)
        idx1 = idx[:, 0].reshape(xx.shape)
        offset = rng.normal(0.0, 0.6, n_seeds)[idx1]
        tilt = rng.normal(0.0, 0.06, (n_seeds, 2))[idx1]  # plate slopes, ~3.4 deg rms
        sx, sy = seeds[idx1, 0], seeds[idx1, 1]
        plates = offset + tilt[..., 0] * (xx - sx) + tilt[..., 1] * (yy - sy)
        gap = (dist[:, 1] - dist[:, 0]).reshape(xx.shape)  # ~ distance to the plate boundary
        crack = -0.8 * np.clip(1.0 - gap / 0.6, 0.0, 1.0)
        small[sl] += w * (plates + crack)
    for _ in range(_count(rng, opts.penitente_patch_count, area_scale)):
        r, c = rand_rc()
        disc = _soft_disc(shape, cell_m, r, c, float(rng.uniform(*opts.penitente_patch_radius_m)), 8.0)
        if disc is None:
            continue
        sl, w = disc
        x, y = _local_xy(sl, r, c, cell_m)
        h = float(rng.uniform(*opts.penitente_height_m))
        lam = float(rng.uniform(*opts.penitente_spacing_m))
        # blades run east-west (along the equatorial Sun's path), waviness from a smooth phase field
        phase = 0.25 * fbm_field(rng, w.shape, cell_m, 0.9, 15.0)
        u = y / lam + phase
        v = x / (1.7 * lam) + 0.5 * np.floor(u)  # breaks each ridge into offset blades
        tri_u = 1.0 - 2.0 * np.abs(u - np.floor(u) - 0.5)
        tri_v = 1.0 - 2.0 * np.abs(v - np.floor(v) - 0.5)
        blades = h * tri_u**1.5 * (0.35 + 0.65 * tri_v**0.7)
        small[sl] += w * (blades - 0.5 * h)
    for _ in range(_count(rng, opts.crevasse_count, area_scale)):
        width = float(rng.uniform(*opts.crevasse_width_m))
        depth = float(rng.uniform(*opts.crevasse_depth_m))
        pts = _polyline(rng, float(rng.uniform(*opts.crevasse_length_m)), 1.0, 0.05)
        hw = 0.5 * width
        # U-shaped: flat-ish floor, walls spread over at least 1.5 cells (a one-cell cliff would be drawn as
        # stairs by the bilinear surface)
        wall = max(0.4 * hw, 1.5 * cell_m)

        def crevasse(d, hw=hw, depth=depth, wall=wall):
            t = np.clip((hw - d) / wall, 0.0, 1.0)
            return -depth * t * t * (3.0 - 2.0 * t)

        _add_polyline_feature(small, cell_m, rand_rc(), pts, hw, crevasse)
    for diam in power_law_sizes(
        rng, _count(rng, opts.block_count, area_scale), *opts.block_diam_m, opts.block_sfd_slope
    ):
        r, c = rand_rc()
        sl = _window(shape, r, c, 0.75 * diam / cell_m + 1)
        if sl is None:
            continue
        x, y = _local_xy(sl, r, c, cell_m)
        ang = rng.uniform(0, np.pi)
        a, b = 0.5 * diam, 0.5 * diam * float(rng.uniform(0.5, 1.0))
        ax = (np.cos(ang) * x + np.sin(ang) * y) / a
        ay = (-np.sin(ang) * x + np.cos(ang) * y) / b
        rn = (np.abs(ax) ** 4 + np.abs(ay) ** 4) ** 0.25  # rounded-box footprint
        hb = diam * float(rng.uniform(0.3, 0.7))
        # steep sides over the outer 15 % of the block (at least 1.5 cells, so a side is never a one-cell
        # cliff that the bilinear surface would draw as stairs), slightly domed top
        edge = max(0.15, 1.5 * cell_m / b)
        t = np.clip((1.0 - rn) / edge, 0.0, 1.0)
        small[sl] += hb * t * t * (3.0 - 2.0 * t) * (1.0 - 0.1 * rn * rn)

    # scale the large-scale part so that the relief equals the target

    def relief_gap(scale: float) -> float:
        lo_h, hi_h = np.percentile(scale * large_all + small, [0.05, 99.95])
        return float(hi_h - lo_h) - opts.relief_m

    lo, hi = 0.0, 1.0
    while relief_gap(hi) < 0:
        hi *= 2.0
    scale = optimize.brentq(relief_gap, lo, hi, xtol=1e-4) if relief_gap(lo) < 0 else 0.0
    h = scale * large_all + small
    return (h - h.mean()).astype(np.float32)


def europa_albedo(
    rng: np.random.Generator, shape: tuple[int, int], cell_m: float, opts: AlbedoOptions
) -> np.ndarray:
    """(rows, cols) float32 albedo in (0, 1): nominal ``opts.mean`` with splotches and dark striae."""
    rows, cols = shape
    area_scale = rows * cols * cell_m * cell_m / 160_000.0
    rel = 1.0 + opts.splotch_rms * fbm_field(rng, shape, cell_m, 0.6, 60.0)
    for rad in power_law_sizes(rng, _count(rng, opts.splotch_count, area_scale), *opts.splotch_radius_m, 1.5):
        r, c = float(rng.uniform(0, rows - 1)), float(rng.uniform(0, cols - 1))
        sl = _window(shape, r, c, 2.5 * rad / cell_m + 1)
        if sl is None:
            continue
        x, y = _local_xy(sl, r, c, cell_m)
        # irregular outline: radius modulated with angle
        th = np.arctan2(y, x)
        k1, k2 = rng.uniform(0, 2 * np.pi, 2)
        rr = rad * (1.0 + 0.3 * np.sin(2 * th + k1) + 0.2 * np.sin(3 * th + k2))
        amp = opts.splotch_contrast * float(rng.uniform(-1.0, 0.6))  # mostly darker (non-ice material)
        rel[sl] *= 1.0 + amp * np.exp(-((np.hypot(x, y) / rr) ** 2))
    log_dark = np.zeros(shape)  # sum of log(1 - darkening): crossing striae multiply
    for _ in range(_count(rng, opts.stria_count, area_scale)):
        length = float(power_law_sizes(rng, 1, *opts.stria_length_m, 1.0)[0])
        width = float(rng.uniform(*opts.stria_width_m))
        dark = float(rng.uniform(*opts.stria_darkening))
        pts = _polyline(rng, length, 2.0, 0.01)
        _add_polyline_feature(
            log_dark,
            cell_m,
            (float(rng.uniform(0, rows - 1)), float(rng.uniform(0, cols - 1))),
            pts,
            1.5 * width,
            lambda d, width=width, dark=dark: np.log1p(-dark * np.exp(-0.5 * (d / (0.4 * width)) ** 2)),
        )
    rel *= np.exp(log_dark)
    grain = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), 0.8)
    rel *= 1.0 + opts.grain_rms * grain / max(float(grain.std()), 1e-9)
    return np.clip(opts.mean * rel, 0.02, 0.98).astype(np.float32)
