"""Digital elevation model in the local NED world frame. Pure numpy/scipy/OpenCV, no file I/O
(GeoTIFF loading is in ``companion.io.dem_file``)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage


@dataclass(frozen=True)
class Dem:
    """Elevation raster.

    height_m: (rows, cols) float32 elevations above the world origin, up positive (so a ground
        point's NED z is ``-height``). NaN marks holes (nodata).
    Row 0 is the northernmost row; rows go south, columns go east (GeoTIFF order, north-up map).
    north0_m, east0_m: world north and east of the centre of cell (0, 0). cell_m: cell size (m).
    """

    height_m: np.ndarray
    north0_m: float
    east0_m: float
    cell_m: float

    def __post_init__(self) -> None:
        if self.height_m.ndim != 2:
            raise ValueError(f"DEM heights must be 2-D, got shape {self.height_m.shape}")
        if not self.cell_m > 0:
            raise ValueError(f"DEM cell size must be > 0, got {self.cell_m}")

    @property
    def shape(self) -> tuple[int, int]:
        return self.height_m.shape  # type: ignore[return-value]

    def rc_from_ne(
        self, north_m: np.ndarray | float, east_m: np.ndarray | float
    ) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, col) of world (north, east)."""
        r = (self.north0_m - np.asarray(north_m, float)) / self.cell_m
        c = (np.asarray(east_m, float) - self.east0_m) / self.cell_m
        return r, c

    def ne_from_rc(self, row: np.ndarray | float, col: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """World (north, east) of fractional (row, col)."""
        n = self.north0_m - np.asarray(row, float) * self.cell_m
        e = self.east0_m + np.asarray(col, float) * self.cell_m
        return n, e

    @property
    def extent_ne(self) -> tuple[float, float, float, float]:
        """(north_min, north_max, east_min, east_max) of the cell centres."""
        rows, cols = self.shape
        return (
            self.north0_m - (rows - 1) * self.cell_m,
            self.north0_m,
            self.east0_m,
            self.east0_m + (cols - 1) * self.cell_m,
        )

    def contains(self, north_m: float, east_m: float, margin_m: float = 0.0) -> bool:
        n0, n1, e0, e1 = self.extent_ne
        return (n0 + margin_m <= north_m <= n1 - margin_m) and (e0 + margin_m <= east_m <= e1 - margin_m)

    def height_at(self, north_m: np.ndarray | float, east_m: np.ndarray | float) -> np.ndarray:
        """Bilinear elevation at world (north, east); NaN off the raster or next to a hole."""
        r, c = self.rc_from_ne(north_m, east_m)
        r = np.atleast_1d(r).astype(np.float32)
        c = np.atleast_1d(c).astype(np.float32)
        shape = r.shape
        # cv2.remap takes maps of at most 32767 columns: lay the points out in rows of 1024
        n = r.size
        width = 1024
        rows_needed = max(-(-n // width), 1)
        pad = rows_needed * width - n
        rm = np.concatenate([r.ravel(), np.zeros(pad, np.float32)]).reshape(rows_needed, width)
        cm = np.concatenate([c.ravel(), np.zeros(pad, np.float32)]).reshape(rows_needed, width)
        out = (
            cv2.remap(
                self.height_m.astype(np.float32, copy=False),
                cm,
                rm,
                interpolation=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=float("nan"),
            )
            .ravel()[:n]
            .reshape(shape)
        )
        rows, cols = self.shape
        outside = (r < 0) | (c < 0) | (r > rows - 1) | (c > cols - 1)
        out[outside] = np.nan
        return out

    def hole_fraction(self) -> float:
        return float(np.isnan(self.height_m).mean())

    def filled(self) -> Dem:
        """Copy with holes filled from the nearest valid cell, then smoothed inside the holes."""
        h = self.height_m
        holes = np.isnan(h)
        if not holes.any():
            return self
        if holes.all():
            raise ValueError("DEM has no valid cell")
        idx = ndimage.distance_transform_edt(holes, return_distances=False, return_indices=True)
        f = h[tuple(idx)].astype(np.float32)
        blurred = cv2.GaussianBlur(f, (0, 0), 2.0)
        f[holes] = blurred[holes]
        return Dem(f, self.north0_m, self.east0_m, self.cell_m)

    def height_above_ground(self, p_world: np.ndarray, R_world_body: np.ndarray, range_m: float) -> float:
        """Vertical height of ``p_world`` (NED) above the ground straight below it, from a range measured
        along body down (a downward altimeter).

        When the body tilts the beam hits the ground beside the point below (3.5 m aside at 2 deg and
        100 m), whose elevation differs on a slope: range * cos(tilt) is the height above the hit point,
        plus the DEM step from the hit point to the point below. Without a DEM step (holes, off the
        raster) the cosine term alone."""
        down = np.asarray(R_world_body, float)[:, 2]
        p = np.asarray(p_world, float)
        return float(self.heights_above_ground(p[None], down[None], np.array([float(range_m)]))[0])

    def heights_above_ground(self, p_world: np.ndarray, down: np.ndarray, range_m: np.ndarray) -> np.ndarray:
        """``height_above_ground`` for many samples at once: p_world (N, 3) NED, down (N, 3) the body's down
        axis in the world (R_world_body[:, 2]), range_m (N,); returns (N,) metres."""
        p = np.asarray(p_world, float).reshape(-1, 3)
        d = np.asarray(down, float).reshape(-1, 3)
        r = np.asarray(range_m, float).reshape(-1)
        h_vert = r * d[:, 2]
        hit = p + r[:, None] * d
        step = self.height_at(hit[:, 0], hit[:, 1]) - self.height_at(p[:, 0], p[:, 1])
        return h_vert + np.where(np.isfinite(step), step, 0.0)

    def beam_range(self, p_world: np.ndarray, direction: np.ndarray, max_range_m: float = 1000.0) -> float:
        """Distance from ``p_world`` (NED) along the unit ``direction`` (NED) to the first surface hit, as a
        range finder reads it; NaN when the beam leaves the raster or meets nothing within ``max_range_m``.
        Marches in steps of half a cell, then bisects the crossing to a millimetre."""
        p = np.asarray(p_world, float)
        d = np.asarray(direction, float)
        ts = np.arange(0.0, max_range_m + self.cell_m, 0.5 * self.cell_m)
        pts = p[None, :] + ts[:, None] * d[None, :]
        h = self.height_at(pts[:, 0], pts[:, 1])
        below = pts[:, 2] > -h  # NED: under the surface when z > -elevation (NaN compares False)
        i = int(np.argmax(below))
        if not below[i] or np.isnan(h[: i + 1]).any():
            return float("nan")
        lo, hi = float(ts[max(i - 1, 0)]), float(ts[i])
        while hi - lo > 1e-3:
            mid = 0.5 * (lo + hi)
            q = p + mid * d
            if q[2] > -float(self.height_at(q[0], q[1])[0]):
                hi = mid
            else:
                lo = mid
        return 0.5 * (lo + hi)

    def crop(self, north_m: float, east_m: float, half_size_m: float) -> Dem:
        """Sub-raster of cells within ``half_size_m`` of (north, east), clipped to the raster."""
        r, c = self.rc_from_ne(north_m, east_m)
        k = int(np.ceil(half_size_m / self.cell_m))
        rows, cols = self.shape
        r0, r1 = max(int(np.floor(r)) - k, 0), min(int(np.ceil(r)) + k + 1, rows)
        c0, c1 = max(int(np.floor(c)) - k, 0), min(int(np.ceil(c)) + k + 1, cols)
        if r0 >= r1 or c0 >= c1:
            raise ValueError(f"crop at N={north_m:.1f} E={east_m:.1f} lies off the DEM")
        n0, e0 = self.ne_from_rc(r0, c0)
        return Dem(self.height_m[r0:r1, c0:c1], float(n0), float(e0), self.cell_m)

    def resampled(self, cell_m: float) -> Dem:
        """Area-averaged (coarser) or bilinear (finer) resampling to about ``cell_m``, same extent.

        The returned cell size is the exact one used (the extent is divided into whole cells)."""
        rows, cols = self.shape
        new_rows = max(int(round(rows * self.cell_m / cell_m)), 2)
        new_cols = max(int(round(cols * self.cell_m / cell_m)), 2)
        interp = cv2.INTER_AREA if cell_m > self.cell_m else cv2.INTER_LINEAR
        h = cv2.resize(self.height_m.astype(np.float32), (new_cols, new_rows), interpolation=interp)
        sx, sy = cols / new_cols, rows / new_rows
        # cv2.resize maps destination pixel x to source x * s + 0.5 * s - 0.5 (pixel-centre convention)
        n0, e0 = self.ne_from_rc(0.5 * sy - 0.5, 0.5 * sx - 0.5)
        return Dem(h, float(n0), float(e0), self.cell_m * sx)
