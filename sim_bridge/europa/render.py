"""Visible and thermal downward cameras over the simulated Europa (paper 2 sections 3 and 4).

Both cameras are co-registered and synchronised (paper 2 section 3): same pose, same 640 x 480 pinhole
intrinsics, so a ground point lands on the same pixel in both. Per frame pair:

1. Ray-heightfield intersection (shared by both cameras), coarse to fine: the rays of every 8th pixel
   are marched with conservative steps (gap / (1 + S |g|), S a local bound on the terrain slope, |g| the
   ray's horizontal run per metre of drop: such a step cannot pass through the terrain, so occlusion is
   right); the drop is interpolated to every pixel and refined by a few Newton steps on the bilinear
   heightfield; the few pixels where Newton does not settle (occlusion edges) are marched conservatively.
2. Visible: paper 2 eq. 9 per pixel, from the hit point's normal, the view vector and the fixed Sun
   (and Jupiter, when its light can reach one grey level), with the precomputed albedo and cast-shadow
   maps; fixed exposure; shot and read noise; 8-bit.
3. Thermal: the precomputed temperature map sampled at the hit points, optics blur, temporal noise (NETD)
   and a fixed pattern; 16-bit radiometric counts, centi-kelvin (the TLinear output of common
   radiometric cores: counts = 100 T[K]).

Hand-written because no library ray-casts a heightfield at this rate on a CPU (``sim_bridge.render``'s
Mars renderer does it exactly at ~0.2 s per 640x480 frame; this coarse-to-fine version is ~10x faster,
which the filter benchmark needs). OpenCV does the bilinear lookups.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.geometry import CameraIntrinsics, pixel_rays_cam
from companion.georef.dem import Dem
from sim_bridge.europa.world import EuropaWorld

COARSE_STEP_PX = 8
"""Pixel spacing of the conservatively marched rays; the rest start from their interpolation."""

SECANT_GAP_M = 0.05
"""A marching ray takes secant (not only guaranteed-safe) steps once it is this close above the terrain."""

COARSE_MAX_ITER = 40
"""Marching steps of the coarse rays; the few still short of the surface hand their last point to Newton."""

OCCLUSION_PROBE_M = 0.3
"""A Newton hit deeper than this (m) beyond the nearest surrounding coarse hit is probed for occlusion."""

OCCLUSION_PROBES = 3
"""Points probed along the ray between the nearest coarse depth and the Newton hit."""


def default_intrinsics() -> CameraIntrinsics:
    """640 x 480, 60 deg horizontal field of view (46.8 deg vertical), square pixels (fx = fy = 554.3).

    Paper 2 gives only the resolution (images resized to 640 x 480); 60 deg is a common navigation camera
    field and keeps a 150 m x 112 m footprint at 130 m above ground inside the 400 m site."""
    f = 320.0 / np.tan(np.radians(30.0))
    return CameraIntrinsics(640, 480, f, f, 319.5, 239.5)


def lookup(img: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Bilinear lookup of ``img`` (rows, cols[, ch]) float32 at fractional (row, col) of any shape, edge
    replicated. Returns row.shape (+ (ch,)) float32. cv2.remap wants 2-D maps under 32767 per side, so
    flat arrays are laid out in rows of 1024."""
    shape = np.shape(row)
    if len(shape) == 2 and max(shape) < 32767:
        return cv2.remap(img, np.asarray(col, np.float32), np.asarray(row, np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
    r_flat = np.asarray(row, np.float32).ravel()
    c_flat = np.asarray(col, np.float32).ravel()
    n, w = r_flat.size, 1024
    m = max(-(-n // w), 1)
    r2 = np.concatenate([r_flat, np.zeros(m * w - n, np.float32)]).reshape(m, w)
    c2 = np.concatenate([c_flat, np.zeros(m * w - n, np.float32)]).reshape(m, w)
    out = cv2.remap(img, c2, r2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ch = out.shape[2:] if out.ndim == 3 else ()
    return out.reshape(m * w, *ch)[:n].reshape(*shape, *ch)


class HeightfieldTracer:
    """Ray-heightfield intersection on a DEM (bilinear surface). Rays are given in NED and parametrised by
    their drop s (m below the ray origin): p(s) = origin + s * (g_n, g_e, 1), g = d_horiz / d_down."""

    BLOCK_CELLS = (4, 32)
    """Sides of the blocks of the slope-bound maps (fine: tight bound near steep features; coarse: long
    steps over gentle terrain); a conservative step never moves further than one block of its map."""

    def __init__(self, dem: Dem) -> None:
        dem = dem.filled()
        self.dem = dem
        h = np.ascontiguousarray(dem.height_m, dtype=np.float32)
        self.h_min = float(h.min())
        self.h_max = float(h.max())
        cell = dem.cell_m
        rows, cols = h.shape
        # [h, dh/d_east, dh/d_north] for Newton; the gradient of the bilinear surface is piecewise, central
        # differences are its smooth stand-in (Newton only needs a good slope, the residual is exact)
        d_col = cv2.Sobel(h, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE) / np.float32(
            2 * cell
        )
        d_row = cv2.Sobel(h, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE) / np.float32(
            2 * cell
        )
        # 4 channels (the last unused): OpenCV's 4-channel remap is twice as fast as its 3-channel one
        self.geo = np.ascontiguousarray(np.stack([h, d_col, -d_row, np.zeros_like(h)], axis=-1))
        self.h = h
        # Lipschitz bounds of the bilinear surface: per block the largest edge difference along each axis,
        # then the max over the block and its 8 neighbours (a step stays within one block)
        self.slope_blocks: list[np.ndarray] = []
        for B in self.BLOCK_CELLS:
            nbr, nbc = -(-rows // B), -(-cols // B)
            gr = np.zeros((nbr * B, nbc * B), np.float32)
            gc = np.zeros((nbr * B, nbc * B), np.float32)
            gr[: rows - 1, :cols] = np.abs(np.diff(h, axis=0))
            gc[:rows, : cols - 1] = np.abs(np.diff(h, axis=1))
            br = gr.reshape(nbr, B, nbc, B).max(axis=(1, 3))
            bc = gc.reshape(nbr, B, nbc, B).max(axis=(1, 3))
            slope = np.sqrt(br * br + bc * bc) / np.float32(cell)
            self.slope_blocks.append(
                cv2.dilate(slope, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
            )

    def _grid(self, origin_ned: np.ndarray, g_n: np.ndarray, g_e: np.ndarray):
        """Grid-space rays: row(s) = r0 + s * a_r, col(s) = c0 + s * a_c; and the origin's elevation e0.
        origin_ned: (3,) shared or (N, 3) per ray."""
        dem = self.dem
        o = np.asarray(origin_ned, float)
        r0, c0 = dem.rc_from_ne(o[..., 0], o[..., 1])
        inv = np.float32(1.0 / dem.cell_m)
        r0, c0, e0 = (np.asarray(x, np.float32) for x in (r0, c0, -o[..., 2]))
        return r0, c0, e0, (-g_n * inv).astype(np.float32), (g_e * inv).astype(np.float32)

    def march(
        self,
        origin_ned: np.ndarray,
        g_n: np.ndarray,
        g_e: np.ndarray,
        tol_m: float = 0.005,
        max_iter: int = 400,
        s_start: np.ndarray | None = None,
        last: np.ndarray | None = None,
    ) -> np.ndarray:
        """Drop s (m) of the first terrain hit of each ray. (N,) float32, NaN = miss.

        last: optional (N,) float32 output: the hit, or for rays still marching after ``max_iter`` steps
        their last point (above the terrain, short of the hit), NaN for misses.
        origin_ned: (3,) or (N, 3) NED ray origins. g_n, g_e: (N,) horizontal run per metre of drop.
        s_start: (N,) drops to start from (default: where each ray crosses the highest terrain); a ray
        whose start is already below the terrain is a miss.
        Conservative steps gap / (1 + S run) (S: slope
        bound of the block, run: horizontal metres per metre of drop) never cross the terrain; near the
        surface (``SECANT_GAP_M``) a secant step (clipped to 8 safe steps) speeds convergence; once it overshoots,
        Illinois false position between the last point above and the first below. Rays that leave the raster, start inside
        the terrain or do not converge in ``max_iter`` steps are misses."""
        r0, c0, e0, a_r, a_c = self._grid(
            origin_ned, np.asarray(g_n, np.float32), np.asarray(g_e, np.float32)
        )
        n = a_r.size
        r0, c0, e0 = (np.broadcast_to(x, (n,)).copy() for x in (r0, c0, e0))
        rows, cols = self.dem.shape
        run = np.hypot(a_r, a_c) * np.float32(self.dem.cell_m)  # metres of horizontal run per metre of drop
        with np.errstate(divide="ignore"):
            s_cap = np.where(run > 0, self.dem.cell_m / run, np.inf).astype(np.float32)  # per block cell
        s = np.maximum(e0 - np.float32(self.h_max), 0.0).astype(np.float32)
        if s_start is not None:
            s = np.maximum(s, np.asarray(s_start, np.float32))
        # s_lo/g_lo: last point known above the terrain and its gap; s_hi/g_hi: first point found below
        # it (NaN until the ray has overshot); side: which end the last bracketed step replaced (Illinois)
        s_lo = np.full(n, np.nan, np.float32)
        g_lo = np.full(n, np.nan, np.float32)
        s_hi = np.full(n, np.nan, np.float32)
        g_hi = np.full(n, np.nan, np.float32)
        side = np.zeros(n, np.int8)
        out = np.full(n, np.nan, np.float32)
        idx = np.arange(n)
        tol = np.float32(tol_m)
        for _ in range(max_iter):
            ri = r0 + s * a_r
            ci = c0 + s * a_c
            gap = e0 - s - lookup(self.h, ri, ci)
            off = (ri < 0) | (ri > rows - 1) | (ci < 0) | (ci > cols - 1)
            hit = (np.abs(gap) <= tol) & ~off
            above = gap > tol
            bracketed = np.isfinite(s_hi)
            # off the raster and moving away from it, or below the terrain with no point above: a miss
            gone = (off & (((ri < 0) & (a_r <= 0)) | ((ri > rows - 1) & (a_r >= 0))
                           | ((ci < 0) & (a_c <= 0)) | ((ci > cols - 1) & (a_c >= 0)))) | (~above & np.isnan(s_lo))  # fmt: skip
            out[idx[hit]] = s[hit]
            keep = ~(hit | gone)
            if not keep.any():
                break
            if last is not None:
                last[idx[keep]] = np.where(np.isfinite(s_hi[keep]), s_lo[keep], s[keep])
            # bracket bookkeeping (Illinois: halve the stale end's gap when the same end moves twice)
            new_hi = ~above & ~hit
            g_lo = np.where(bracketed & new_hi & (side == -1), 0.5 * g_lo, g_lo)
            g_hi = np.where(bracketed & above & (side == 1), 0.5 * g_hi, g_hi)
            side = np.where(bracketed & above, 1, np.where(new_hi, -1, side)).astype(np.int8)
            s_hi = np.where(new_hi, s, s_hi)
            g_hi = np.where(new_hi, gap, g_hi)
            g_pos = np.maximum(gap, 0.0)
            safe = np.zeros_like(gap)
            for B, blocks in zip(self.BLOCK_CELLS, self.slope_blocks):
                nbr, nbc = blocks.shape
                S = blocks[
                    np.minimum(np.maximum((ri * (1.0 / B)).astype(np.int32), 0), nbr - 1),
                    np.minimum(np.maximum((ci * (1.0 / B)).astype(np.int32), 0), nbc - 1),
                ]
                safe = np.maximum(safe, np.minimum(g_pos / (1.0 + S * run), B * s_cap))
            with np.errstate(divide="ignore", invalid="ignore"):
                # not bracketed yet: within SECANT_GAP_M of the surface, a secant step from the last point
                # above, clipped to [1, 8] safe steps (so short that no terrain can hide in its overshoot)
                sec = gap * (s - s_lo) / (g_lo - gap)
                use = (g_lo > gap) & np.isfinite(sec) & (gap < SECANT_GAP_M)
                # (np.minimum / np.maximum: np.clip's per-call overhead showed in this loop)
                sec = np.where(use, np.minimum(np.maximum(sec, safe), 8.0 * safe), safe)
                s_lo = np.where(above, s, s_lo)
                g_lo = np.where(above, gap, g_lo)
                # bracketed: false position between the two ends
                fp = s_lo - g_lo * (s_hi - s_lo) / (g_hi - g_lo)
            s = np.where(np.isfinite(s_hi), fp, s + sec).astype(np.float32)
            idx, s, s_lo, g_lo, s_hi, g_hi, side = (
                x[keep] for x in (idx, s, s_lo, g_lo, s_hi, g_hi, side)
            )  # fmt: skip
            r0, c0, e0 = r0[keep], c0[keep], e0[keep]
            a_r, a_c, run, s_cap = a_r[keep], a_c[keep], run[keep], s_cap[keep]
        if last is not None:
            last[np.isfinite(out)] = out[np.isfinite(out)]
        return out

    def gap(self, origin_ned: np.ndarray, g_n: np.ndarray, g_e: np.ndarray, s: np.ndarray) -> np.ndarray:
        """Height (m) of the ray points at drops ``s`` above the terrain (negative inside it)."""
        r0, c0, e0, a_r, a_c = self._grid(np.asarray(origin_ned, float).reshape(3), g_n, g_e)
        s = np.asarray(s, np.float32)
        return e0 - s - lookup(self.h, r0 + s * a_r, c0 + s * a_c)

    def newton(
        self,
        origin_ned: np.ndarray,
        g_n: np.ndarray,
        g_e: np.ndarray,
        s0: np.ndarray,
        tol_m: float = 0.005,
        full_iters: int = 2,
        max_iters: int = 8,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Refine drops ``s0`` by Newton steps on gap(s) = e0 - s - h(p(s)): ``full_iters`` on every ray,
        then up to ``max_iters`` in all on those whose |gap| still exceeds ``tol_m``.

        g_n, g_e, s0: same shape (any). Returns (s, converged) of that shape, float32 and bool."""
        gn = np.asarray(g_n, np.float32)
        ge = np.asarray(g_e, np.float32)
        r0, c0, e0, a_r, a_c = self._grid(np.asarray(origin_ned, float).reshape(3), gn, ge)
        s = np.array(s0, np.float32)
        conv = np.zeros(s.shape, bool)

        def step(si, gni, gei, a_ri, a_ci):
            geo = lookup(self.geo, r0 + si * a_ri, c0 + si * a_ci)
            gap = e0 - si - geo[..., 0]
            # d gap / ds = -(1 + grad h . g); kept away from 0 so a grazing ray does not jump far
            denom = np.maximum(1.0 + geo[..., 2] * gni + geo[..., 1] * gei, np.float32(0.25))
            return si + gap / denom, np.abs(gap) < tol_m

        for _ in range(full_iters):
            s, conv = step(s, gn, ge, a_r, a_c)
        idx = np.flatnonzero(~conv)
        sf, cf = s.ravel(), conv.ravel()
        gnf, gef, arf, acf = gn.ravel(), ge.ravel(), a_r.ravel(), a_c.ravel()
        for _ in range(max_iters - full_iters):
            if idx.size == 0:
                break
            si, ok = step(sf[idx], gnf[idx], gef[idx], arf[idx], acf[idx])
            sf[idx] = si
            cf[idx] = ok
            idx = idx[~ok]
        return sf.reshape(s.shape), cf.reshape(s.shape)


def _pow(x: np.ndarray, k: float) -> np.ndarray:
    """x**k; by repeated squaring when k is a small whole number (several times faster than np.power)."""
    if float(k).is_integer() and 1 <= k <= 64:
        n = int(k)
        result = np.ones_like(x)
        base = x
        while n:
            if n & 1:
                result = result * base
            n >>= 1
            if n:
                base = base * base
        return result
    return np.power(x, np.float32(k))


class PixelGrid:
    """Per-intrinsics constants of the intersection: normalised image coordinates of every pixel and of the
    coarse nodes (every ``COARSE_STEP_PX`` pixels, one node past the last row/column), and the maps that
    interpolate coarse -> full."""

    def __init__(self, intr: CameraIntrinsics) -> None:
        self.intr = intr
        H, W = intr.height, intr.width
        xy = pixel_rays_cam(intr).astype(np.float32)
        self.x, self.y = np.ascontiguousarray(xy[..., 0]), np.ascontiguousarray(xy[..., 1])
        k = COARSE_STEP_PX
        uc, vc = np.meshgrid(
            np.arange(0, W + k, k, dtype=np.float32), np.arange(0, H + k, k, dtype=np.float32)
        )
        self.xc = ((uc - intr.cx) / intr.fx).astype(np.float32)
        self.yc = ((vc - intr.cy) / intr.fy).astype(np.float32)
        mx, my = np.meshgrid(np.arange(W, dtype=np.float32) / k, np.arange(H, dtype=np.float32) / k)
        self.mx, self.my = mx, my

    @staticmethod
    def runs(R_world_cam: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(g_n, g_e): horizontal NED run per metre of drop of the rays through (x, y, 1); NaN if not downward."""
        R = np.asarray(R_world_cam, np.float32)
        dn = R[0, 0] * x + R[0, 1] * y + R[0, 2]
        de = R[1, 0] * x + R[1, 1] * y + R[1, 2]
        dd = R[2, 0] * x + R[2, 1] * y + R[2, 2]
        dd = np.where(dd > 1e-3 * np.sqrt(dn * dn + de * de + dd * dd), dd, np.nan).astype(np.float32)
        return dn / dd, de / dd


@dataclass(frozen=True)
class _Hits:
    """Per pixel (H, W) float32: drop s (m below the camera), the ray's NED run per metre of drop (g_n, g_e),
    DEM fractional row/col of the hit; valid (bool) where the ray hits the DEM."""

    s: np.ndarray
    g_n: np.ndarray
    g_e: np.ndarray
    row: np.ndarray
    col: np.ndarray
    valid: np.ndarray


def _intersect(
    tracer: HeightfieldTracer, grid: PixelGrid, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray
) -> _Hits:
    p = np.asarray(p_cam_in_world, float).reshape(3)
    H, W = grid.intr.height, grid.intr.width
    # 1. coarse rays, marched (a few slow, near-grazing ones are left short of the surface: their last
    # point is still a fine start for Newton)
    gnc, gec = grid.runs(R_world_cam, grid.xc, grid.yc)
    s_c = np.full(gnc.size, np.nan, np.float32)
    ok_c = np.isfinite(gnc.ravel())
    if ok_c.any():
        part = np.full(int(ok_c.sum()), np.nan, np.float32)
        tracer.march(p, gnc.ravel()[ok_c], gec.ravel()[ok_c], tol_m=0.02, max_iter=COARSE_MAX_ITER, last=part)
        s_c[ok_c] = part
    s_c = s_c.reshape(gnc.shape)  # type: ignore[assignment]
    gn, ge = grid.runs(R_world_cam, grid.x, grid.y)
    down = np.isfinite(gn)
    if np.isnan(s_c).all():
        nan = np.full((H, W), np.nan, np.float32)
        return _Hits(nan, gn, ge, nan, nan, np.zeros((H, W), bool))
    # 2. interpolate to every pixel (missing coarse nodes take the largest drop, so Newton starts from a
    # plausible depth), then Newton
    s_fill = np.where(np.isnan(s_c), np.nanmax(s_c), s_c).astype(np.float32)
    s0 = cv2.remap(s_fill, grid.mx, grid.my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    gn = np.where(down, gn, 0.0).astype(np.float32)
    ge = np.where(down, ge, 0.0).astype(np.float32)
    s, conv = tracer.newton(p, gn, ge, s0)
    # 3. Newton finds a surface near its start, not necessarily the first along the ray. Where its hit is
    # deeper than the nearest of the four coarse rays around the pixel, the ray is probed at a few points
    # in between; if one is inside the terrain (an occluding edge), or Newton has not settled, the pixel
    # is marched from just above that nearest depth.
    k = COARSE_STEP_PX
    near_c = np.minimum.reduce((s_fill[:-1, :-1], s_fill[1:, :-1], s_fill[:-1, 1:], s_fill[1:, 1:]))
    near = np.repeat(np.repeat(near_c, k, axis=0), k, axis=1)[:H, :W]
    deep = conv & down & (s > near + OCCLUSION_PROBE_M)
    occluded = np.zeros((H, W), bool)
    if deep.any():
        idx = np.flatnonzero(deep)
        sd, nd = s.ravel()[idx], near.ravel()[idx]
        r0, c0 = tracer.dem.rc_from_ne(p[0], p[1])
        a_r = -gn.ravel()[idx] / np.float32(tracer.dem.cell_m)
        a_c = ge.ravel()[idx] / np.float32(tracer.dem.cell_m)
        hit_in = np.zeros(idx.size, bool)
        for j in range(1, OCCLUSION_PROBES + 1):
            sj = nd + (sd - nd) * np.float32(j / (OCCLUSION_PROBES + 1))
            gap = (
                np.float32(-p[2])
                - sj
                - lookup(tracer.h, np.float32(r0) + sj * a_r, np.float32(c0) + sj * a_c)
            )
            hit_in |= gap < -0.01
        occluded.ravel()[idx[hit_in]] = True
    bad = (~conv | occluded) & down
    if bad.any():
        # rays that have not converged within the step budget (near-grazing down a steep wall) keep their
        # last point, a little short of the surface; rays that started inside the terrain go again from the top
        gb, eb = gn[bad], ge[bad]
        s_b = np.full(gb.size, np.nan, np.float32)
        tracer.march(
            p, gb, eb, s_start=np.maximum(near[bad] - OCCLUSION_PROBE_M, 0.0), max_iter=100, last=s_b
        )
        lost = np.isnan(s_b)
        if lost.any():
            s_l = np.full(int(lost.sum()), np.nan, np.float32)
            tracer.march(p, gb[lost], eb[lost], max_iter=200, last=s_l)
            s_b[lost] = s_l
        # the unconverged ones: Newton from their last point (above the surface, usually close to it)
        short = np.isfinite(s_b)
        short[short] = np.abs(tracer.gap(p, gb[short], eb[short], s_b[short])) > 0.02
        if short.any():
            s_n, ok_n = tracer.newton(p, gb[short], eb[short], s_b[short])
            s_b[np.flatnonzero(short)[ok_n & (s_n >= s_b[short])]] = s_n[ok_n & (s_n >= s_b[short])]
        s[bad] = s_b
    r0, c0 = tracer.dem.rc_from_ne(p[0], p[1])
    inv = np.float32(1.0 / tracer.dem.cell_m)
    row = np.float32(r0) - s * gn * inv
    col = np.float32(c0) + s * ge * inv
    rows, cols = tracer.dem.shape
    valid = np.isfinite(s) & down & (row >= 0) & (col >= 0) & (row <= rows - 1) & (col <= cols - 1)
    return _Hits(s, gn, ge, row, col, valid)


def ground_points(
    dem: Dem,
    intrinsics: CameraIntrinsics,
    R_world_cam: np.ndarray,
    p_cam_in_world: np.ndarray,
    tracer: HeightfieldTracer | None = None,
) -> np.ndarray:
    """(H, W, 3) float64 NED point seen at each pixel centre; NaN where the ray misses the DEM.

    tracer: reuse a ``HeightfieldTracer(dem)`` across frames (building one costs ~0.1 s)."""
    tracer = HeightfieldTracer(dem) if tracer is None else tracer
    hits = _intersect(tracer, PixelGrid(intrinsics), R_world_cam, p_cam_in_world)
    return _points(hits, p_cam_in_world)


def _points(hits: _Hits, p_cam_in_world: np.ndarray) -> np.ndarray:
    s = hits.s.astype(np.float64)
    d = np.stack([hits.g_n * s, hits.g_e * s, s], axis=-1)
    pts = np.asarray(p_cam_in_world, float).reshape(1, 1, 3) + d
    pts[~hits.valid] = np.nan
    return pts


@dataclass(frozen=True)
class VisibleNoise:
    """Visible sensor: fixed exposure, shot and read noise, 8 bits.

    flat_dn: exposure set so a level facet of the mean albedo seen at nadir reads this many DN (bright ice
    with headroom for glare). electrons_per_dn: conversion gain (40 e-/DN, ~10 ke- full well over 255 DN)
    for the photon shot noise; read_sigma_dn: read noise (2 DN)."""

    flat_dn: float = 150.0
    electrons_per_dn: float = 40.0
    read_sigma_dn: float = 2.0


@dataclass(frozen=True)
class ThermalNoise:
    """Thermal camera: optics blur, temporal noise, fixed-pattern noise, radiometric 16-bit counts.

    netd_k: temporal noise (K rms) at the 80-130 K scene. The paper gives none; 0.1 K is what a far-IR
    (17-50 um) microbolometer built for cold planetary surfaces aims at (an 8-14 um camera would see
    almost no signal from 100 K ice). fixed_pattern_k: per-pixel offset that stays with the sensor (K rms),
    drawn once from ``pattern_seed``. blur_sigma_px: optics/detector blur (thermal optics are diffraction-
    limited at ~10x the visible wavelength). counts_per_k: 100 -> counts are centi-kelvin."""

    netd_k: float = 0.1
    fixed_pattern_k: float = 0.1
    blur_sigma_px: float = 0.8
    counts_per_k: float = 100.0
    pattern_seed: int = 7


class EuropaCameras:
    """Co-registered, synchronised downward visible + thermal cameras (paper 2 section 3), zero baseline.

    intrinsics: both cameras' (default ``default_intrinsics()``: 640 x 480, 60 deg horizontal FOV).
    render(R_world_cam, p_cam_in_world, seed) -> (visible uint8 (H, W), thermal uint16 (H, W) centi-kelvin).
    Pixels whose ray misses the terrain are 0 in both images.
    """

    def __init__(
        self,
        world: EuropaWorld,
        intrinsics: CameraIntrinsics | None = None,
        visible_noise: VisibleNoise | None = VisibleNoise(),
        thermal_noise: ThermalNoise | None = ThermalNoise(),
    ) -> None:
        self.world = world
        self.intrinsics = default_intrinsics() if intrinsics is None else intrinsics
        self.visible_noise = visible_noise
        self.thermal_noise = thermal_noise
        self.tracer = HeightfieldTracer(world.dem)
        self.grid = PixelGrid(self.intrinsics)
        # per-cell maps sampled at the hit points: albedo, Sun and Jupiter visibility, temperature
        self._maps = np.ascontiguousarray(
            np.stack([world.albedo, world.sun_lit, world.jupiter_lit, world.temperature_k], -1).astype(
                np.float32
            )
        )
        illum = world.illumination
        self._sources = [(1.0, np.asarray(world.sun_dir_enu, np.float32), 1)]
        # Jupiter's visible-band light is the sunlight it reflects; kept when it can reach 0.5 DN
        rel_j = illum.jupiter_reflected_w_m2 / illum.sun_irradiance_w_m2
        refl = world.reflectance
        noise = VisibleNoise() if visible_noise is None else visible_noise
        self.exposure = noise.flat_dn / self._flat_radiance()
        if rel_j * (1.0 + refl.rho_s) * self.exposure >= 0.5:
            self._sources.append((rel_j, np.asarray(world.jupiter_dir_enu, np.float32), 2))
        H, W = self.intrinsics.height, self.intrinsics.width
        if thermal_noise is not None:
            rng = np.random.default_rng(thermal_noise.pattern_seed)
            self._pattern_k = (thermal_noise.fixed_pattern_k * rng.standard_normal((H, W))).astype(np.float32)

    def _flat_radiance(self) -> float:
        """Eq. 9 radiance (Sun units) of a level, sunlit facet of the mean albedo seen from straight above."""
        rho = float(self.world.albedo.mean())
        refl = self.world.reflectance
        L = np.asarray(self.world.sun_dir_enu, float)
        cos_g = L[2]
        alpha = 1.0 - np.arccos(np.clip(cos_g, -1, 1)) / np.pi
        rv = max(2 * L[2] * 1.0 - cos_g, 0.0)
        return rho + alpha * rho * max(L[2], 0.0) + (1 - alpha) * refl.rho_s * rv**refl.sharpness_k

    def _hits(self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray) -> _Hits:
        return _intersect(self.tracer, self.grid, R_world_cam, p_cam_in_world)

    def ground_points(self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray) -> np.ndarray:
        """(H, W, 3) float64 NED ground point at each pixel centre (same for both cameras); NaN = miss."""
        return _points(self._hits(R_world_cam, p_cam_in_world), p_cam_in_world)

    def radiance(self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free (visible radiance in Sun units per eq. 9, temperature K), each (H, W) float32, NaN = miss."""
        hits = self._hits(R_world_cam, p_cam_in_world)
        vis, temp = self._shade(hits)
        return vis, temp

    def _shade(self, hits: _Hits) -> tuple[np.ndarray, np.ndarray]:
        m = cv2.remap(self._maps, hits.col, hits.row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        geo = cv2.remap(
            self.tracer.geo, hits.col, hits.row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        albedo, temp = m[..., 0], m[..., 3]
        # ENU unit normal from the slopes, ENU unit view vector (hit -> camera) from the NED ray
        dh_de, dh_dn = geo[..., 1], geo[..., 2]
        inv = 1.0 / np.sqrt(1.0 + dh_de * dh_de + dh_dn * dh_dn)
        n_e, n_n, n_u = -dh_de * inv, -dh_dn * inv, inv
        # the NED ray is (g_n, g_e, 1) per metre of drop; the view vector points back up it
        vinv = 1.0 / np.sqrt(1.0 + hits.g_n * hits.g_n + hits.g_e * hits.g_e)
        v_e, v_n, v_u = -hits.g_e * vinv, -hits.g_n * vinv, vinv
        nv = n_e * v_e + n_n * v_n + n_u * v_u
        refl = self.world.reflectance
        rho_s = np.float32(refl.rho_s)
        vis = albedo.copy()  # ambient term rho_a (= rho_d)
        for intensity, L, ch in self._sources:
            lit = m[..., ch]
            cos_g = v_e * L[0] + v_n * L[1] + v_u * L[2]  # cos of the phase angle
            alpha = 1.0 - np.arccos(np.clip(cos_g, -1.0, 1.0)) * np.float32(1.0 / np.pi)
            nl = n_e * L[0] + n_n * L[1] + n_u * L[2]
            rv = 2.0 * nl * nv - cos_g  # R . V with R = 2 (N.L) N - L
            spec = rho_s * _pow(np.maximum(rv, 0.0), refl.sharpness_k) * (nl > 0)
            lobe = alpha * albedo * np.maximum(nl, 0.0) + (1.0 - alpha) * spec
            vis += np.float32(intensity) * lit * lobe
        if not hits.valid.all():
            vis[~hits.valid] = np.nan
            temp = temp.copy()
            temp[~hits.valid] = np.nan
        return vis, temp

    def render(
        self, R_world_cam: np.ndarray, p_cam_in_world: np.ndarray, seed: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """One synchronised frame pair: (visible uint8 (H, W), thermal uint16 (H, W), counts = 100 T[K]).

        seed: noise seed of this frame pair (same seed and pose, identical images)."""
        vis, temp = self.radiance(R_world_cam, p_cam_in_world)
        rng = np.random.default_rng([int(seed), 0xE0])
        miss = np.isnan(vis)
        dn: np.ndarray = np.nan_to_num(vis * np.float32(self.exposure), nan=0.0)
        if self.visible_noise is not None:
            vn = self.visible_noise
            var = np.float32(vn.read_sigma_dn**2) + np.maximum(dn, 0.0) / np.float32(vn.electrons_per_dn)
            dn = dn + np.sqrt(var) * rng.standard_normal(dn.shape, dtype=np.float32)
        visible = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
        visible[miss] = 0
        t = np.nan_to_num(temp, nan=0.0)
        counts_per_k = 100.0
        if self.thermal_noise is not None:
            tn = self.thermal_noise
            counts_per_k = tn.counts_per_k
            if tn.blur_sigma_px > 0:
                t = cv2.GaussianBlur(t, (0, 0), tn.blur_sigma_px, borderType=cv2.BORDER_REPLICATE)
            t = t + self._pattern_k + np.float32(tn.netd_k) * rng.standard_normal(t.shape, dtype=np.float32)
        thermal = np.clip(np.rint(t * np.float32(counts_per_k)), 0, 65535).astype(np.uint16)
        thermal[miss] = 0
        return visible, thermal
