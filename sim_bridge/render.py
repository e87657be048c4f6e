"""Visible-camera renderer over a heightfield: perspective pinhole at a full 6-DOF pose, true ray/terrain
intersection, paper 1 eq. 3 Lambertian shading x albedo with cast shadows, sensor noise.

How a frame is made (all vectorised over the H x W ray grid, bilinear lookups with ``cv2.remap``):
1. Once per (DEM, albedo, sun): the radiance map on the terrain grid,
   ``L * albedo * (ambient + (1 - ambient) * max(n . s, 0) * lit)`` (``lit`` = not in a cast shadow),
   and its image pyramid (for anti-aliasing when a pixel covers several cells); per block of cells, at
   two block sizes, the heightfield's slope bound (Lipschitz constant) and highest terrain; the height
   gradient (for Newton steps).
2. Per frame, each pixel ray p(t) = c + t d is intersected with the heightfield, coarse to fine. On a
   ray grid 4x coarser than the image, a robust march: start where the ray crosses the highest terrain,
   then take safe steps — down to the highest terrain of the surrounding block, or g / (|d_down| + S
   |d_horiz|) with g the height of the ray point above the terrain and S the block's slope bound (sphere
   tracing for heightfields) — which never pass through the terrain, so occlusion is right (a minimum
   step of half a cell, against stalling on grazing rays, may skip thinner slivers); near the surface
   secant steps, and once a point below the terrain is found, false position in the bracket.
   Each finer grid starts from the interpolated coarser depths and takes two Newton steps; pixels at
   depth discontinuities, or where Newton does not converge within the neighbours' depth range, are
   marched robustly. Checked against a brute-force march in tests/test_render.py.
3. The radiance is sampled at the hit points (trilinear between the two pyramid levels bracketing the
   frame's ground sample distance), scaled by the exposure to digital numbers (DN), and sensor noise is
   added: shot noise (Gaussian approximation of Poisson with ``electrons_per_dn``) and read noise.

Hand-written because no library ray-casts a heightfield on the CPU at this rate; OpenCV does the lookups.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.geometry import CameraIntrinsics, pixel_rays_cam
from companion.georef.dem import Dem
from companion.georef.shading import Sun, cast_shadow_mask, lambert_shading

PAPER_CAMERA = CameraIntrinsics.from_focal_sensor(480, 480, 36.0, 36.0)
"""Paper 1's camera: 480 x 480 px, focal length = sensor width = 36 mm, so fx = 480 px, 53.13 deg FOV."""


@dataclass(frozen=True)
class SensorNoise:
    """Sensor noise model, in digital numbers (DN, 0..255).

    read_sigma_dn: read noise std (2.0 DN, a typical 8-bit machine-vision sensor in daylight).
    shot: add photon shot noise, std sqrt(signal_dn / electrons_per_dn) (Gaussian approximation of Poisson).
    electrons_per_dn: conversion gain (40 e-/DN: ~10 ke- full well over 255 DN), sets the shot noise size.
    bank_frames: number of precomputed standard-normal frames drawn from; each frame picks one of them and
        a random cyclic shift, so the noise is fast and deterministic by seed (noise of frames far apart
        may repeat, which no estimator here can exploit).
    seed: seed of the noise bank and of the frame sequence when ``render`` gets no seed.
    """

    read_sigma_dn: float = 2.0
    shot: bool = True
    electrons_per_dn: float = 40.0
    bank_frames: int = 4
    seed: int = 0


@dataclass(frozen=True)
class _Hit:
    """Per-pixel intersection: ray parameter t (pixel ray with z_cam = 1, so t is the depth along the optical
    axis), fractional (row, col) on the DEM, and the valid mask. All (H, W)."""

    t: np.ndarray
    row: np.ndarray
    col: np.ndarray
    valid: np.ndarray


def _remap_flat(img: np.ndarray, x: np.ndarray, y: np.ndarray, nearest: bool = False) -> np.ndarray:
    """Bilinear (or nearest) lookup of ``img`` at flat float32 arrays (x = col, y = row), edge replicated.
    (N,) or (N, channels) float32.

    cv2.remap wants 2-D maps shorter than 32767 per side, so the flat arrays are padded to rows of 1024."""
    n = x.size
    w = 1024
    m = -(-n // w)
    if m * w != n:
        x = np.concatenate([x, np.zeros(m * w - n, np.float32)])
        y = np.concatenate([y, np.zeros(m * w - n, np.float32)])
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    out = cv2.remap(img, x.reshape(m, w), y.reshape(m, w), interp, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(m * w, -1)[:n] if out.ndim == 3 else out.ravel()[:n]


def _block_bounds(h: np.ndarray, cell_m: float, B: int) -> np.ndarray:
    """(ceil(rows/B), ceil(cols/B), 2) float32 bounds of the bilinear heightfield per block of B x B cells,
    each taken over the block and its 8 neighbours (so they hold for any point within one block of it):
    channel 0 = Lipschitz bound (largest edge difference along each axis / cell, combined), channel 1 =
    highest terrain."""
    rows, cols = h.shape
    nbr, nbc = -(-rows // B), -(-cols // B)
    hp = np.pad(h, ((0, nbr * B - rows), (0, nbc * B - cols)), mode="edge")
    d_r = np.zeros_like(hp)
    d_c = np.zeros_like(hp)
    d_r[:-1] = np.abs(np.diff(hp, axis=0))
    d_c[:, :-1] = np.abs(np.diff(hp, axis=1))
    br = d_r.reshape(nbr, B, nbc, B).max(axis=(1, 3))
    bc = d_c.reshape(nbr, B, nbc, B).max(axis=(1, 3))
    bh = hp.reshape(nbr, B, nbc, B).max(axis=(1, 3))
    k3 = np.ones((3, 3), np.uint8)
    slope = cv2.dilate(np.sqrt(br * br + bc * bc) / np.float32(cell_m), k3, borderType=cv2.BORDER_REPLICATE)
    hmax = cv2.dilate(bh, k3, borderType=cv2.BORDER_REPLICATE)
    return np.ascontiguousarray(np.stack([slope, hmax], axis=-1).astype(np.float32))


class VisibleRenderer:
    """Render 8-bit grey frames of a terrain seen by a pinhole camera.

    dem: the true surface (holes are filled). albedo: (rows, cols) reflectance on the DEM grid.
    sun: lighting (azimuth clockwise from north). intrinsics: pinhole camera (no distortion).
    noise: sensor noise, None for a noise-free image. ambient: fraction of the direct light that still
    reaches surfaces in shadow or facing away (sky light; 0.08). exposure: DN per unit radiance; None =
    automatic, so that the 99.5th percentile of the scene radiance maps to 200 DN (then the image does not
    change with ``sun.intensity``; pass a number to study intensity, as in paper 1 section 5.3.1).
    """

    COARSE_LEVELS = 2
    """Ray grids coarser than the image (each half the previous) used to start the finer ones."""

    MIN_COARSE_PX = 48
    """Smallest side of a coarse ray grid."""

    BLOCK_CELLS = (8, 32)
    """Cells per side of the blocks of the two heightfield-bound maps; a safe step based on one map never
    moves further than one of its blocks."""

    def __init__(
        self,
        dem: Dem,
        albedo: np.ndarray,
        sun: Sun,
        intrinsics: CameraIntrinsics,
        noise: SensorNoise | None = SensorNoise(),
        ambient: float = 0.08,
        exposure: float | None = None,
    ) -> None:
        if albedo.shape != dem.shape:
            raise ValueError(f"albedo shape {albedo.shape} differs from the DEM's {dem.shape}")
        dem = dem.filled()
        self.dem = dem
        self.sun = sun
        self.intrinsics = intrinsics
        self.noise = noise
        self.ambient = float(ambient)
        h = np.ascontiguousarray(dem.height_m, dtype=np.float32)
        self._h = h
        self._hmax = float(h.max())
        self._hmin = float(h.min())

        # 1. radiance map and its pyramid
        direct = lambert_shading(h, dem.cell_m, sun) / np.float32(max(sun.intensity, 1e-12))
        if sun.elevation_rad > 0:
            direct = direct * ~cast_shadow_mask(h, dem.cell_m, sun)
        else:
            direct = np.zeros_like(direct)
        rad = sun.intensity * albedo.astype(np.float32) * (self.ambient + (1.0 - self.ambient) * direct)
        rad = rad.astype(np.float32)
        self.radiance = rad
        if exposure is None:
            p = float(np.percentile(rad[::4, ::4], 99.5))
            exposure = 200.0 / p if p > 0 else 1.0
        self.exposure = float(exposure)
        self._pyramid: list[np.ndarray] = [rad]
        while min(self._pyramid[-1].shape) > 64 and len(self._pyramid) < 8:
            self._pyramid.append(cv2.pyrDown(self._pyramid[-1]))

        # heightfield bounds per block, at two block sizes (fine for steps near the surface, coarse for
        # long steps through the air): see _block_bounds
        self._bounds = [(b, _block_bounds(h, dem.cell_m, b)) for b in self.BLOCK_CELLS]

        # height and its gradient (per cell, along rows and columns) for Newton refinement
        g_row = cv2.Sobel(h, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE) * np.float32(0.5)
        g_col = cv2.Sobel(h, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE) * np.float32(0.5)
        self._hg = np.ascontiguousarray(np.stack([h, g_row, g_col], axis=-1))

        # rays in the camera frame (z_cam = 1) on the image grid and on coarser grids (each half the
        # previous, same pixel-centre convention as CameraIntrinsics.scaled / cv2.resize)
        self._rays_cam = pixel_rays_cam(intrinsics).astype(np.float32)
        self._ray_levels: list[tuple[np.ndarray, np.ndarray, int, int]] = []
        intr = intrinsics
        while True:
            rays = pixel_rays_cam(intr).astype(np.float32)
            xs = np.ascontiguousarray(rays[..., 0].ravel())
            ys = np.ascontiguousarray(rays[..., 1].ravel())
            self._ray_levels.append((xs, ys, intr.height, intr.width))
            if (
                len(self._ray_levels) > self.COARSE_LEVELS
                or min(intr.width, intr.height) < 2 * self.MIN_COARSE_PX
            ):
                break
            intr = CameraIntrinsics(
                intr.width // 2,
                intr.height // 2,
                intr.fx / 2,
                intr.fy / 2,
                (intr.cx + 0.5) / 2 - 0.5,
                (intr.cy + 0.5) / 2 - 0.5,
            )
        H, W = intrinsics.height, intrinsics.width
        if noise is not None:
            bank_rng = np.random.default_rng(noise.seed % 2**63)
            self._bank = bank_rng.standard_normal((max(noise.bank_frames, 1), H, W), dtype=np.float32)
            self._frame_rng = np.random.default_rng([noise.seed % 2**63, 1])

    # ------------------------------------------------------------------------------------------------------

    def _intersect(self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray) -> _Hit:
        """Intersect every pixel ray with the heightfield, coarse to fine.

        The coarsest ray grid is marched robustly (``_march``). Each finer grid starts from the coarser
        depths, bilinearly interpolated, and refines them by Newton's method (``_newton``) where the coarse
        neighbourhood saw one smooth surface; rays at depth discontinuities (occlusion edges, the raster
        edge), rays where Newton does not converge or leaves the neighbours' depth range, are marched
        robustly. Thin occluders seen by none of the coarse rays around a pixel (a few pixels wide) can be
        missed by the refinement; the test against a brute-force march bounds how often.
        """
        dem = self.dem
        R = np.asarray(R_world_cam, np.float64)
        c = np.asarray(p_cam_in_world, np.float64).reshape(3)
        r0f, c0f = dem.rc_from_ne(c[0], c[1])
        u0 = float(-c[2])
        if u0 < self._hmin:
            raise ValueError(f"camera at height {u0:.1f} m is below the lowest terrain ({self._hmin:.1f} m)")
        origin = (np.float32(r0f), np.float32(c0f), np.float32(u0))
        levels = self._ray_levels
        x, y, H, W = levels[-1]
        t, r, cc, hit = self._march(R, origin, x, y)
        for x, y, Hf, Wf in reversed(levels[:-1]):
            tc = np.where(hit, t, np.float32(-1.0)).reshape(H, W)
            k3 = np.ones((3, 3), np.uint8)
            tmin = cv2.erode(tc, k3, borderType=cv2.BORDER_REPLICATE)
            tmax = cv2.dilate(tc, k3, borderType=cv2.BORDER_REPLICATE)
            t0 = cv2.resize(tc, (Wf, Hf), interpolation=cv2.INTER_LINEAR).ravel()
            tmin = cv2.resize(tmin, (Wf, Hf), interpolation=cv2.INTER_NEAREST).ravel()
            tmax = cv2.resize(tmax, (Wf, Hf), interpolation=cv2.INTER_NEAREST).ravel()
            margin = np.float32(0.02) * tmax + np.float32(4.0 * dem.cell_m)
            # one smooth surface around: every coarse neighbour hit, depths within a few percent
            smooth = (tmin > 0) & (tmax - tmin <= margin)
            H, W = Hf, Wf
            # Newton on every ray (cheaper than selecting), kept where the surface was smooth
            t, r, cc, hit = self._newton(R, origin, x, y, t0)
            hit &= smooth & (t >= tmin - margin) & (t <= tmax + margin)
            rest = np.flatnonzero(~hit)
            if rest.size:
                tr, rr, cr, hr = self._march(R, origin, x[rest], y[rest])
                t[rest], r[rest], cc[rest], hit[rest] = tr, rr, cr, hr
        rows, cols = dem.shape
        valid = hit & (t > 0) & (r >= 0) & (cc >= 0) & (r <= rows - 1) & (cc <= cols - 1)
        return _Hit(t.reshape(H, W), r.reshape(H, W), cc.reshape(H, W), valid.reshape(H, W))

    def _ray_setup(self, R: np.ndarray, x: np.ndarray, y: np.ndarray):
        """Grid-space directions of the rays d = R (x, y, 1): (a_row, a_col, a_down, a_horiz), each (N,)
        float32, so that row(t) = r0 + t a_row, col(t) = c0 + t a_col, up(t) = u0 - t a_down."""
        f32 = np.float32
        inv_cell = f32(1.0 / self.dem.cell_m)
        d_n = f32(R[0, 0]) * x + f32(R[0, 1]) * y + f32(R[0, 2])
        d_e = f32(R[1, 0]) * x + f32(R[1, 1]) * y + f32(R[1, 2])
        a_down = f32(R[2, 0]) * x + f32(R[2, 1]) * y + f32(R[2, 2])
        return -d_n * inv_cell, d_e * inv_cell, a_down, np.sqrt(d_n * d_n + d_e * d_e)

    def _newton(self, R, origin, x, y, t):
        """Two Newton steps on g(t) = up(t) - h(t) from ``t`` for rays (x, y) (no compaction: boolean
        indexing costs more than computing the few converged rays again). Returns (t, row, col, ok)."""
        f32 = np.float32
        r0, c0, u0 = origin
        tol = f32(max(0.02 * self.dem.cell_m, 1e-3))
        a_row, a_col, a_down, _ = self._ray_setup(R, x, y)
        t = t.astype(f32)
        for _ in range(2):
            ri = r0 + t * a_row
            ci = c0 + t * a_col
            hg = _remap_flat(self._hg, ci, ri)
            g = (u0 - t * a_down) - hg[:, 0]
            # dg/dt = -d_down - (dh/drow d_row + dh/dcol d_col); a ray rising relative to the surface has no
            # root nearby: the clamp sends it far off and the range check rejects it
            dg = -a_down - (hg[:, 1] * a_row + hg[:, 2] * a_col)
            t = t - g / np.minimum(dg, f32(-1e-3))
        ri = r0 + t * a_row
        ci = c0 + t * a_col
        g = (u0 - t * a_down) - _remap_flat(self._h, ci, ri)
        return t, ri, ci, np.abs(g) <= tol

    def _march(self, R: np.ndarray, origin, x: np.ndarray, y: np.ndarray, max_iter: int = 400):
        """Robust intersection of rays (x, y) (camera-frame, z = 1): returns flat (t, row, col, hit).

        Per ray: t_lo, the furthest point known to be above the terrain (every step to it was safe), and
        once a point below the terrain is found, t_hi; then the first crossing lies in [t_lo, t_hi] and is
        found by false position clamped to shrink the bracket. Before that, steps are the largest safe
        step from the bound maps, at least half a cell (a sliver of terrain thinner than that can be
        missed, the price of not stalling on grazing rays), and, near the surface (g < 2 cells), a secant
        step through the last two points above the terrain.
        """
        dem = self.dem
        f32 = np.float32
        cell = f32(dem.cell_m)
        rows, cols = dem.shape
        r0, c0, u0 = origin
        tol = f32(max(0.02 * dem.cell_m, 1e-3))  # |height above terrain| accepted as a hit (m)
        g_sec = f32(2.0 * dem.cell_m)
        a_row, a_col, a_down, a_horiz = self._ray_setup(R, x, y)
        n = x.size
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            inv_h = f32(1.0) / a_horiz
            inv_down = np.where(a_down > 1e-6, 1.0 / a_down, np.inf).astype(f32)
            a_min = (0.5 * cell) / np.sqrt(a_horiz * a_horiz + a_down * a_down)
            # start where the ray crosses the highest terrain (or at the camera if it is below that)
            a_t = np.maximum((u0 - f32(self._hmax)) * inv_down, 0.0)
            a_t = np.where(np.isfinite(a_t), a_t, 0.0).astype(f32)
            # parameter where the ray leaves the raster rectangle for good (slab test; -inf if never in)
            tr = (f32(0.0) - r0) / a_row, (f32(rows - 1) - r0) / a_row
            tc = (f32(0.0) - c0) / a_col, (f32(cols - 1) - c0) / a_col
            t_exit = np.minimum(np.fmax(tr[0], tr[1]), np.fmax(tc[0], tc[1]))
            t_exit = np.where(np.isnan(t_exit), np.inf, t_exit).astype(f32)
        idx = np.arange(n)
        nanv = np.full(n, np.nan, f32)
        a_tlo, a_glo, a_tlo2, a_glo2 = nanv.copy(), nanv.copy(), nanv.copy(), nanv.copy()
        a_thi, a_ghi = np.full(n, np.inf, f32), nanv.copy()
        t_out = nanv.copy()
        r_out = nanv.copy()
        c_out = nanv.copy()
        hit_out = np.zeros(n, bool)
        a_done = np.zeros(n, bool)
        first = True
        for _ in range(max_iter):
            ri = r0 + a_t * a_row
            ci = c0 + a_t * a_col
            hi = _remap_flat(self._h, ci, ri)
            up = u0 - a_t * a_down
            g = up - hi  # height of the ray point above the terrain (m)
            conv = np.abs(g) <= tol
            fin = conv | ((a_t > t_exit) & (g > 0))
            if first:
                fin |= g < -tol  # below the terrain at the start: the camera is inside the terrain
                first = False
            fin &= ~a_done
            if fin.any():
                f_idx = idx[fin]
                t_out[f_idx] = a_t[fin]
                r_out[f_idx] = ri[fin]
                c_out[f_idx] = ci[fin]
                hit_out[f_idx] = conv[fin]
                a_done |= fin
                n_done = int(a_done.sum())
                if n_done == a_done.size:
                    break
                # finished rays are frozen in place; the active set is compacted only once half of it is
                # done (boolean indexing costs as much as a few dozen arithmetic passes)
                if n_done > a_done.size // 2:
                    keep = ~a_done
                    idx, a_t, a_tlo, a_glo = idx[keep], a_t[keep], a_tlo[keep], a_glo[keep]
                    a_tlo2, a_glo2, a_thi, a_ghi = a_tlo2[keep], a_glo2[keep], a_thi[keep], a_ghi[keep]
                    a_row, a_col, a_down, inv_down = a_row[keep], a_col[keep], a_down[keep], inv_down[keep]
                    a_horiz, inv_h, a_min, t_exit = a_horiz[keep], inv_h[keep], a_min[keep], t_exit[keep]
                    ri, ci, g, up, a_done = ri[keep], ci[keep], g[keep], up[keep], a_done[keep]
            above = g > 0
            a_tlo2 = np.where(above, a_tlo, a_tlo2)
            a_glo2 = np.where(above, a_glo, a_glo2)
            a_tlo = np.where(above, a_t, a_tlo)
            a_glo = np.where(above, g, a_glo)
            a_thi = np.where(above, a_thi, a_t)
            a_ghi = np.where(above, a_ghi, g)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                # safe steps from each bound map (never through the terrain while within one block):
                # (a) Lipschitz |dg/dt| <= |d_down| + S |d_horiz|, (b) down to the block's highest terrain
                step = a_min
                for B, bounds in self._bounds:
                    inv_b = f32(1.0 / B)
                    sb = _remap_flat(bounds, ci * inv_b - 0.5, ri * inv_b - 0.5, nearest=True)
                    s_lip = g / (np.abs(a_down) + sb[:, 0] * a_horiz + f32(1e-6))
                    s_top = (up - sb[:, 1]) * inv_down
                    step = np.maximum(step, np.minimum(np.maximum(s_lip, s_top), (B * cell) * inv_h))
                # near the surface: secant through the last two points above the terrain
                sec = g * (a_tlo - a_tlo2) / (a_glo2 - g)
                step = np.where((g < g_sec) & (sec > step), np.minimum(sec, 16.0 * step), step)
                t_next = a_t + step
                # bracketed rays: false position, kept 10 % inside the bracket so it always shrinks
                fp = a_tlo + a_glo * (a_thi - a_tlo) / (a_glo - a_ghi)
                w = a_thi - a_tlo
                fp = np.clip(fp, a_tlo + 0.1 * w, a_thi - 0.1 * w)
                t_next = np.where(np.isfinite(a_thi), fp, t_next)
            a_t = np.where(a_done, a_t, t_next).astype(f32, copy=False)
        return t_out, r_out, c_out, hit_out

    # ------------------------------------------------------------------------------------------------------

    def ground_points(self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray) -> np.ndarray:
        """(H, W, 3) float64 NED world point seen at each pixel centre; NaN where the ray misses the DEM."""
        hit = self._intersect(R_world_cam, p_cam_in_world)
        d = self._rays_cam.astype(np.float64) @ np.asarray(R_world_cam, np.float64).T
        p = np.asarray(p_cam_in_world, np.float64).reshape(1, 1, 3) + hit.t[..., None].astype(np.float64) * d
        p[~hit.valid] = np.nan
        return p

    def radiance_at_pixels(self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray) -> np.ndarray:
        """(H, W) float32 noise-free image in DN (before clipping and quantisation); NaN where rays miss."""
        hit = self._intersect(R_world_cam, p_cam_in_world)
        return self._shade(hit)

    def _shade(self, hit: _Hit) -> np.ndarray:
        # ground sample distance at the frame's median depth, in cells -> pyramid level (fractional)
        ts = hit.t[::4, ::4][hit.valid[::4, ::4]]
        if ts.size:
            gsd_cells = float(np.median(ts)) / self.intrinsics.fx / self.dem.cell_m
        else:
            gsd_cells = 1.0
        lev = float(np.clip(np.log2(max(gsd_cells, 1e-6)), 0.0, len(self._pyramid) - 1))
        l0 = int(np.floor(lev))
        l1 = min(l0 + 1, len(self._pyramid) - 1)
        w1 = np.float32(lev - l0)
        img = self._sample_level(l0, hit)
        if w1 > 0 and l1 != l0:
            img = img * (1 - w1) + self._sample_level(l1, hit) * w1
        img = img * np.float32(self.exposure)
        img[~hit.valid] = np.nan
        return img

    def _sample_level(self, level: int, hit: _Hit) -> np.ndarray:
        s = np.float32(2.0**level)
        # pyrDown pixel-centre convention: x_l = (x_0 + 0.5) / 2^l - 0.5
        x = (hit.col + 0.5) / s - 0.5
        y = (hit.row + 0.5) / s - 0.5
        return cv2.remap(self._pyramid[level], x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def render(
        self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray, seed: int | None = None
    ) -> np.ndarray:
        """(H, W) uint8 frame. Pixels whose ray misses the DEM are 0 (black sky / void).

        seed: noise seed of this frame (same seed, same noise); None draws the next noise from the
        renderer's own generator (a deterministic sequence from ``noise.seed``).
        """
        img = self.radiance_at_pixels(R_world_cam, p_cam_in_world)
        img = np.nan_to_num(img, nan=0.0)
        if self.noise is not None:
            nz = self.noise
            rng = (
                self._frame_rng
                if seed is None
                else np.random.default_rng([nz.seed % 2**63, 2, int(seed) % 2**63])
            )
            k = int(rng.integers(0, self._bank.shape[0]))
            shift = (int(rng.integers(0, img.shape[0])), int(rng.integers(0, img.shape[1])))
            z = np.roll(self._bank[k], shift, axis=(0, 1))
            var = np.float32(nz.read_sigma_dn**2)
            if nz.shot:
                var = var + np.maximum(img, 0.0) / np.float32(nz.electrons_per_dn)
            img = img + np.sqrt(var) * z
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
