"""Reference terrain-shading images (paper 1 eq. 3, section 4.3 R_k) on a heading-aligned ortho grid.

Everything that depends only on (DEM, presumed sun) is computed once in ``ReferenceMap``: the hole-filled
and lightly smoothed DEM, upsampled, and its Lambertian shading. The reference for one frame is then a
single ``cv2.warpAffine`` of that raster onto the frame's ``OrthoGrid`` (frame GSD, rotated to the frame's
heading), which costs well under a millisecond.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.georef.dem import Dem
from companion.georef.shading import Sun, lambert_shading, slopes


@dataclass(frozen=True)
class OrthoGrid:
    """A square nadir grid in the world, aligned with the frame's heading.

    Cell (row i, col j) of an ``size`` x ``size`` grid has world (north, east)
    ``centre_ne + (j - c) * gsd_m * right_ne - (i - c) * gsd_m * up_ne`` with c = (size - 1) / 2: columns go
    to the image's right, rows go down the image (away from ``up_ne``, the image-top direction on the ground).
    centre_ne, up_ne, right_ne: (2,) world (north, east); up/right are unit vectors. gsd_m: cell size (m).
    """

    centre_ne: np.ndarray
    up_ne: np.ndarray
    right_ne: np.ndarray
    gsd_m: float
    size: int

    @staticmethod
    def make(centre_ne: np.ndarray, heading_rad: float, gsd_m: float, size: int) -> OrthoGrid:
        """Grid whose image-top direction points along ``heading_rad`` (clockwise from north)."""
        up = np.array([np.cos(heading_rad), np.sin(heading_rad)])
        right = np.array([-np.sin(heading_rad), np.cos(heading_rad)])  # 90 deg clockwise of up
        return OrthoGrid(np.asarray(centre_ne, float), up, right, float(gsd_m), int(size))

    def ne_affine(self) -> np.ndarray:
        """2x3 A with (north, east) = A @ (col, row, 1)."""
        c = (self.size - 1) / 2.0
        g = self.gsd_m
        a_col = g * self.right_ne
        a_row = -g * self.up_ne
        t = self.centre_ne - c * (a_col + a_row)
        return np.stack([a_col, a_row, t], axis=1)

    def ne_of_grid_shift(self, shift_cells: np.ndarray) -> np.ndarray:
        """(2,) world (north, east) displacement of a (d_col, d_row) displacement on the grid."""
        return self.gsd_m * (shift_cells[0] * self.right_ne - shift_cells[1] * self.up_ne)


@dataclass(frozen=True)
class GridSample:
    """Reference data on an ``OrthoGrid``: (size, size) float32 each.

    shading: eq. 3 under the presumed sun. height_m: elevation of the hole-filled DEM. invalid: 1 where the
    cell lies off the DEM or in a hole of the original DEM, 0 elsewhere (fractional at the edges)."""

    shading: np.ndarray
    height_m: np.ndarray
    invalid: np.ndarray


class ReferenceMap:
    """Precomputed shading and heights of one DEM under one presumed sun.

    dem: the estimator's DEM (coarse, noisy, holes as NaN). sun: presumed lighting.
    upsample: the shading raster is computed on the DEM upsampled (bicubic) by this factor, so the
        reference keeps smooth, sub-cell slope changes instead of piecewise-linear facets.
    smooth_cells: Gaussian std (DEM cells) applied to the heights before shading: the DEM's per-cell noise
        turns into large, spurious slopes otherwise.
    with_bases: also precompute the basis rasters of ``companion.georef.illumination`` (sun-agnostic shading
        terms p_e/n, p_n/n, 1/n and the local relief h - blur(h, s) for every s in ``relief_scales_m``), in
        ``basis_names`` order after the presumed-sun shading.
    """

    SHADING_BASIS_NAMES = ("shading", "slope_east", "slope_north", "flat")

    def __init__(
        self,
        dem: Dem,
        sun: Sun,
        upsample: int = 2,
        smooth_cells: float = 0.7,
        with_bases: bool = True,
        relief_scales_m: tuple[float, ...] = (20.0,),
    ) -> None:
        if np.isnan(dem.height_m).all():
            raise ValueError("DEM has no valid cell")
        self.dem = dem
        self.sun = sun
        self.upsample = int(max(upsample, 1))
        filled = dem.filled()
        h = filled.height_m.astype(np.float32)
        if smooth_cells > 0:
            h = cv2.GaussianBlur(h, (0, 0), smooth_cells, borderType=cv2.BORDER_REPLICATE)
        self.height_m = h
        self.holes = np.isnan(dem.height_m).astype(np.float32)
        rows, cols = h.shape
        u = self.upsample
        if u > 1:
            # pixel-centre convention: fine cell k covers coarse position (k + 0.5) / u - 0.5
            fine = cv2.resize(h, (cols * u, rows * u), interpolation=cv2.INTER_CUBIC)
        else:
            fine = h
        self.sun_up = sun.elevation_rad > 0.0
        self.shading = lambert_shading(fine, dem.cell_m / u, sun) if self.sun_up else np.zeros_like(fine)
        # channels warped together (one cv2.warpAffine per frame each): shading + height, and the bases
        self._shading_height = np.ascontiguousarray(np.dstack([self.shading, fine]).astype(np.float32))
        self._bases: np.ndarray | None = None
        if with_bases:
            cell = dem.cell_m / u
            de, dn = slopes(fine, cell)
            inv_n = 1.0 / np.sqrt(1.0 + de * de + dn * dn)
            relief = [
                fine - cv2.GaussianBlur(fine, (0, 0), s / cell, borderType=cv2.BORDER_REPLICATE)
                for s in relief_scales_m
            ]
            self._bases = np.ascontiguousarray(
                np.dstack([de * inv_n, dn * inv_n, inv_n, *relief]).astype(np.float32)
            )
        self.basis_names = self.SHADING_BASIS_NAMES + tuple(f"relief_{s:g}m" for s in relief_scales_m)

    def _raster_affine(self, grid: OrthoGrid, cell_scale: float) -> np.ndarray:
        """2x3 M with raster (col, row) = M @ (grid col, grid row, 1); raster cells ``cell_scale`` per DEM cell,
        with the pixel-centre convention of cv2.resize for cell_scale > 1."""
        A = grid.ne_affine()
        d = self.dem
        # DEM (col, row) = ((east - east0) / cell, (north0 - north) / cell)
        col = np.array([A[1, 0], A[1, 1], A[1, 2] - d.east0_m]) / d.cell_m
        row = np.array([-A[0, 0], -A[0, 1], d.north0_m - A[0, 2]]) / d.cell_m
        M = np.stack([col, row]) * cell_scale
        M[:, 2] += 0.5 * cell_scale - 0.5
        return M

    def sample(self, grid: OrthoGrid) -> GridSample:
        """Reference shading, heights and invalid mask on ``grid``: two ``cv2.warpAffine`` calls."""
        n = grid.size
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        Mu = self._raster_affine(grid, float(self.upsample))
        sh = cv2.warpAffine(self._shading_height, Mu, (n, n), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        invalid = cv2.warpAffine(
            self.holes,
            self._raster_affine(grid, 1.0),
            (n, n),
            flags=flags,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=1.0,
        )
        return GridSample(np.ascontiguousarray(sh[..., 0]), np.ascontiguousarray(sh[..., 1]), invalid)

    def sample_bases(self, grid: OrthoGrid, shading: np.ndarray | None = None) -> list[np.ndarray]:
        """The basis images (``basis_names`` order) on ``grid``, (size, size) float32 each; ``shading`` is the
        already sampled first one (else sampled again). Needs ``with_bases``."""
        if self._bases is None:
            raise ValueError("ReferenceMap was built without bases")
        n = grid.size
        Mu = self._raster_affine(grid, float(self.upsample))
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        b = cv2.warpAffine(self._bases, Mu, (n, n), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        if shading is None:
            shading = self.sample(grid).shading
        return [shading] + [np.ascontiguousarray(b[..., k]) for k in range(b.shape[2])]
