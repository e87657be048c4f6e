"""Visible-camera renderer over a heightfield: perspective pinhole at a full 6-DOF pose, true ray/terrain
intersection, paper 1 eq. 3 Lambertian shading x albedo with cast shadows, sensor noise.

How a frame is made (all vectorised over the H x W ray grid, bilinear lookups with ``cv2.remap``):
1. Once per (DEM, albedo, sun): the radiance map on the terrain grid,
   ``L * albedo * (ambient + (1 - ambient) * max(n . s, 0) * lit)`` (``lit`` = not in a cast shadow),
   and its image pyramid (for anti-aliasing when a pixel covers several cells); a coarse map of the
   local maximum terrain slope (Lipschitz bound of the heightfield).
2. Per frame, each pixel ray p(t) = c + t d is intersected with the heightfield: start where the ray
   crosses the highest terrain, then take conservative steps t += g / (|d_down| + S |d_horiz|), where g
   is the height of the ray point above the terrain and S the local slope bound — such a step can never
   pass through the terrain (sphere tracing for heightfields), so occlusion is right. A few secant steps
   finish; rays that have not converged keep stepping (on the shrinking subset) until they do.
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


class VisibleRenderer:
    """Render 8-bit grey frames of a terrain seen by a pinhole camera.

    dem: the true surface (holes are filled). albedo: (rows, cols) reflectance on the DEM grid.
    sun: lighting (azimuth clockwise from north). intrinsics: pinhole camera (no distortion).
    noise: sensor noise, None for a noise-free image. ambient: fraction of the direct light that still
    reaches surfaces in shadow or facing away (sky light; 0.08). exposure: DN per unit radiance; None =
    automatic, so that the 99.5th percentile of the scene radiance maps to 200 DN (then the image does not
    change with ``sun.intensity``; pass a number to study intensity, as in paper 1 section 5.3.1).
    """

    BLOCK_CELLS = 32
    """Cells per side of a block of the slope-bound map; a safe step never moves further than one block."""

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
        self._pyramid = [rad]
        while min(self._pyramid[-1].shape) > 64 and len(self._pyramid) < 8:
            self._pyramid.append(cv2.pyrDown(self._pyramid[-1]))

        # per block of BLOCK_CELLS x BLOCK_CELLS cells, over the block and its 8 neighbours (a step never
        # leaves the neighbourhood): channel 0 = Lipschitz bound of the bilinear heightfield (largest edge
        # difference along each axis / cell), channel 1 = highest terrain
        rows, cols = h.shape
        B = self.BLOCK_CELLS
        nbr, nbc = -(-rows // B), -(-cols // B)
        pad_r, pad_c = nbr * B - rows, nbc * B - cols
        hp = np.pad(h, ((0, pad_r), (0, pad_c)), mode="edge")
        d_r = np.zeros_like(hp)
        d_c = np.zeros_like(hp)
        d_r[:-1] = np.abs(np.diff(hp, axis=0))
        d_c[:, :-1] = np.abs(np.diff(hp, axis=1))
        br = d_r.reshape(nbr, B, nbc, B).max(axis=(1, 3))
        bc = d_c.reshape(nbr, B, nbc, B).max(axis=(1, 3))
        bh = hp.reshape(nbr, B, nbc, B).max(axis=(1, 3))
        k3 = np.ones((3, 3), np.uint8)
        slope = cv2.dilate(
            np.sqrt(br * br + bc * bc) / np.float32(dem.cell_m), k3, borderType=cv2.BORDER_REPLICATE
        )
        hmax = cv2.dilate(bh, k3, borderType=cv2.BORDER_REPLICATE)
        self._block_bounds = np.ascontiguousarray(np.stack([slope, hmax], axis=-1).astype(np.float32))

        # rays in the camera frame (z_cam = 1) and the noise bank
        self._rays_cam = pixel_rays_cam(intrinsics).astype(np.float32)
        self._ray_x = np.ascontiguousarray(self._rays_cam[..., 0].ravel())
        self._ray_y = np.ascontiguousarray(self._rays_cam[..., 1].ravel())
        H, W = intrinsics.height, intrinsics.width
        if noise is not None:
            bank_rng = np.random.default_rng(noise.seed)
            self._bank = bank_rng.standard_normal((max(noise.bank_frames, 1), H, W), dtype=np.float32)
            self._frame_rng = np.random.default_rng([noise.seed, 1])

    # ------------------------------------------------------------------------------------------------------

    def _intersect(self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray, max_iter: int = 400) -> _Hit:
        """Intersect every pixel ray with the heightfield (see the module docstring)."""
        dem = self.dem
        f32 = np.float32
        cell = f32(dem.cell_m)
        rows, cols = dem.shape
        R = np.asarray(R_world_cam, np.float64)
        c = np.asarray(p_cam_in_world, np.float64).reshape(3)
        r0f, c0f = dem.rc_from_ne(c[0], c[1])
        r0, c0, u0 = f32(r0f), f32(c0f), f32(-c[2])
        if u0 < self._hmin:
            raise ValueError(f"camera at height {u0:.1f} m is below the lowest terrain ({self._hmin:.1f} m)")
        B = self.BLOCK_CELLS
        tol = f32(max(0.02 * dem.cell_m, 1e-3))
        # world NED ray directions d = R (x, y, 1); grid-space ray: row(t) = r0 + t * a_row,
        # col(t) = c0 + t * a_col, up(t) = u0 - t * a_down
        x, y = self._ray_x, self._ray_y
        d_n = f32(R[0, 0]) * x + f32(R[0, 1]) * y + f32(R[0, 2])
        d_e = f32(R[1, 0]) * x + f32(R[1, 1]) * y + f32(R[1, 2])
        a_down = f32(R[2, 0]) * x + f32(R[2, 1]) * y + f32(R[2, 2])
        a_row = d_n * (-1.0 / cell)
        a_col = d_e * (1.0 / cell)
        a_horiz = np.sqrt(d_n * d_n + d_e * d_e)
        n = x.size
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            # largest t step that keeps the horizontal move within one block of the bound maps
            a_tblock = (B * cell) / a_horiz
            inv_down = np.where(a_down > 1e-6, 1.0 / a_down, np.inf).astype(f32)
            # start where the ray crosses the highest terrain (or at the camera if it is below that)
            a_t = np.maximum((u0 - f32(self._hmax)) * inv_down, 0.0)
            a_t = np.where(np.isfinite(a_t), a_t, 0.0).astype(f32)
            # parameter where the ray leaves the raster rectangle for good (slab test; -inf if never in)
            tr = (np.float32(-0.5) - r0) / a_row, (f32(rows - 0.5) - r0) / a_row
            tc = (np.float32(-0.5) - c0) / a_col, (f32(cols - 0.5) - c0) / a_col
            t_exit = np.minimum(np.fmax(tr[0], tr[1]), np.fmax(tc[0], tc[1]))
            t_exit = np.where(np.isnan(t_exit), np.inf, t_exit).astype(f32)
        idx = np.arange(n)
        a_tprev = np.full(n, np.nan, f32)
        a_gprev = np.full(n, np.nan, f32)
        t_out = np.full(n, np.nan, f32)
        r_out = np.full(n, np.nan, f32)
        c_out = np.full(n, np.nan, f32)
        hit_out = np.zeros(n, bool)
        bounds = self._block_bounds
        inv_b = f32(1.0 / B)
        first = True
        for _ in range(max_iter):
            ri = r0 + a_t * a_row
            ci = c0 + a_t * a_col
            hi = _remap_flat(self._h, ci, ri)
            up = u0 - a_t * a_down
            g = up - hi  # height of the ray point above the terrain (m)
            conv = np.abs(g) <= tol
            fin = conv | (a_t > t_exit)
            if first:
                # below the terrain at the start: the camera is inside the terrain
                fin |= g < -tol
                first = False
            if fin.any():
                f_idx = idx[fin]
                t_out[f_idx] = a_t[fin]
                r_out[f_idx] = ri[fin]
                c_out[f_idx] = ci[fin]
                hit_out[f_idx] = conv[fin]
                keep = ~fin
                if not keep.any():
                    break
                idx, a_t, a_tprev, a_gprev = idx[keep], a_t[keep], a_tprev[keep], a_gprev[keep]
                a_row, a_col, a_down, inv_down = a_row[keep], a_col[keep], a_down[keep], inv_down[keep]
                a_horiz, a_tblock, t_exit = a_horiz[keep], a_tblock[keep], t_exit[keep]
                ri, ci, g, up = ri[keep], ci[keep], g[keep], up[keep]
            # conservative steps (never through the terrain), the larger of:
            # (a) Lipschitz: |dg/dt| <= |d_down| + S |d_horiz| with S the slope bound of this block and its
            #     neighbours; (b) down to the highest terrain of this block and its neighbours.
            # Both hold only while the ray stays within one block, hence the cap ``a_tblock``.
            sb = _remap_flat(bounds, ci * inv_b - 0.5, ri * inv_b - 0.5, nearest=True)
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                step = np.maximum(
                    g / (np.abs(a_down) + sb[:, 0] * a_horiz + f32(1e-6)), (up - sb[:, 1]) * inv_down
                )
                step = np.minimum(step, a_tblock)
                # secant from the previous point (above the terrain), accepted only near the surface where
                # the linear model holds: larger than the safe step but at most 8 of them
                sec = g * (a_t - a_tprev) / (a_gprev - g)
                use_sec = (sec > step) & (sec < 8.0 * step + 4.0 * tol)
                new_t = a_t + np.where(use_sec, sec, step)
                below = g < -tol
                if below.any():
                    # secant overshoot below the terrain: false position between the last point above and
                    # this one; the last point above stays the reference
                    fp = a_tprev + a_gprev * (a_t - a_tprev) / (a_gprev - g)
                    new_t = np.where(below, fp, new_t)
                    a_tprev = np.where(below, a_tprev, a_t)
                    a_gprev = np.where(below, a_gprev, g)
                else:
                    a_tprev, a_gprev = a_t, g
            a_t = new_t.astype(f32, copy=False)
        valid = (
            hit_out & (t_out > 0) & (r_out >= 0) & (c_out >= 0) & (r_out <= rows - 1) & (c_out <= cols - 1)
        )
        H, W = self.intrinsics.height, self.intrinsics.width
        return _Hit(t_out.reshape(H, W), r_out.reshape(H, W), c_out.reshape(H, W), valid.reshape(H, W))

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
        ts = hit.t[hit.valid]
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
            rng = self._frame_rng if seed is None else np.random.default_rng([nz.seed, 2, int(seed)])
            k = int(rng.integers(0, self._bank.shape[0]))
            shift = (int(rng.integers(0, img.shape[0])), int(rng.integers(0, img.shape[1])))
            z = np.roll(self._bank[k], shift, axis=(0, 1))
            var = np.float32(nz.read_sigma_dn**2)
            if nz.shot:
                var = var + np.maximum(img, 0.0) / np.float32(nz.electrons_per_dn)
            img = img + np.sqrt(var) * z
        return np.clip(np.rint(img), 0, 255).astype(np.uint8)
