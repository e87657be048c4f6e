"""Procedural Mars terrains mirroring paper 1's nine scenes (Table 2, after the resize to ~600 x 600 m),
and the degradation that turns the true surface into the coarser, noisier DEM an estimator gets.

Every scene is deterministic from its seed (``np.random.default_rng``). The grid is north-up: row 0 is
the northernmost row, rows go south, columns go east; the scene is centred on the world origin (N = E = 0)
and its heights are shifted so that the mean ground elevation is 0 m (a ground point's NED z = -height).

Building blocks (all vectorised numpy / OpenCV / scipy.fft):
- spectral (fBm) noise: white noise shaped by a power law in the Fourier domain, band-limited between two
  wavelengths, generated on a coarse grid when only long wavelengths are wanted and upsampled bicubically;
- ridged noise (1 - |noise| per octave) for mountains;
- craters with a bowl, a raised rim and ejecta, radii from a power-law size-frequency distribution;
- dunes as asymmetric ridges (gentle stoss, steep lee) with sinuous crests;
- canyons / valleys carved along a meandering centreline through a distance transform;
- rocks as small Gaussian bumps (height) and dark spots (albedo).
Albedo combines dust (bright, in low and concave areas), bright/dark patches, mottling and rocks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft
from scipy import ndimage

from companion.georef.dem import Dem
from companion.georef.shading import Sun

SCENE_IDS: tuple[str, ...] = ("01", "02", "03", "04", "05", "06", "07", "08", "09")
"""Paper 1's nine scenes, in Table 2 order."""

SCENE_NAMES: dict[str, str] = {
    "01": "highlands",
    "02": "dunes",
    "03": "crater field",
    "04": "highlands (coarser)",
    "05": "gravel plain",
    "06": "mountain",
    "07": "canyon",
    "08": "valley",
    "09": "mountain (fine)",
}
"""Terrain type per scene (Table 2)."""

SCENE_RELIEF_M: dict[str, float] = {
    "01": 50.0,
    "02": 20.0,
    "03": 30.0,
    "04": 75.0,
    "05": 100.0,
    "06": 28.0,
    "07": 70.0,
    "08": 80.0,
    "09": 80.0,
}
"""Max - min elevation (m) after the resize to ~600 m: Table 2 coverage height / resize factor."""

SCENE_SUN_DEG: dict[str, tuple[float, float, float]] = {
    "01": (5.0, 30.0, 60.0),
    "02": (2.0, 0.0, 60.0),
    "03": (5.0, 0.0, 60.0),
    "04": (5.0, 30.0, 75.0),
    "05": (2.0, 0.0, 30.0),
    "06": (5.0, 0.0, 30.0),
    "07": (5.0, 0.0, 90.0),
    "08": (10.0, 0.0, 60.0),
    "09": (10.0, 0.0, 60.0),
}
"""Table 6 lighting: (intensity, azimuth deg clockwise from north, elevation deg)."""

DEFAULT_CELL_M = 0.25
"""True-surface cell (m): HiRISE-like, about the ground footprint of a 480 px, 53 deg camera at 110 m."""


@dataclass(frozen=True)
class Scene:
    """One simulated scene.

    dem: the TRUE surface the renderer uses (fine cell). albedo: (rows, cols) float32 in (0, 1], same grid.
    sun: Table 6 lighting. relief_m: max - min elevation of ``dem``.
    """

    scene_id: str
    name: str
    dem: Dem
    albedo: np.ndarray
    sun: Sun
    relief_m: float


# ----------------------------------------------------------------------------------------------------------
# noise building blocks


def _spectral_noise(
    rng: np.random.Generator,
    shape: tuple[int, int],
    cell_m: float,
    beta: float,
    lmin_m: float,
    lmax_m: float,
) -> np.ndarray:
    """(rows, cols) float32, zero mean, unit std: power spectrum ~ k^-beta between wavelengths lmin..lmax.

    Generated on a grid 2^k times coarser than ``cell_m`` (at least 4 coarse cells per shortest wavelength)
    and brought to ``cell_m`` with ``cv2.pyrUp`` (a smooth B-spline-like interpolator: bicubic upsampling
    would leave slope kinks on the coarse grid that the shading makes visible as stripes). The field is
    periodic over the generated tile, which is padded by 25 % to hide the wrap.
    """
    rows, cols = shape
    k = int(np.floor(np.log2(max(lmin_m / (4.0 * cell_m), 1.0))))
    gen_cell = cell_m * 2**k
    out_rows = -(-rows // 2**k) + 2
    out_cols = -(-cols // 2**k) + 2
    gr = int(np.ceil(out_rows * 1.25))
    gc = int(np.ceil(out_cols * 1.25))
    ky = scipy.fft.fftfreq(gr, d=gen_cell).astype(np.float32)[:, None]
    kx = scipy.fft.rfftfreq(gc, d=gen_cell).astype(np.float32)[None, :]
    k2 = kx * kx + ky * ky
    band = (k2 >= np.float32(lmax_m**-2)) & (k2 <= np.float32(lmin_m**-2))
    amp = np.zeros(k2.shape, np.float32)
    amp[band] = k2[band] ** np.float32(-beta / 4.0)  # |k|^(-beta/2)
    spec = np.empty(k2.shape, np.complex64)
    spec.real = rng.standard_normal(k2.shape, dtype=np.float32) * amp
    spec.imag = rng.standard_normal(k2.shape, dtype=np.float32) * amp
    field = scipy.fft.irfft2(spec, s=(gr, gc))[:out_rows, :out_cols].astype(np.float32)
    for _ in range(k):
        field = cv2.pyrUp(field)
    field = np.ascontiguousarray(field[:rows, :cols])
    field -= field.mean()
    std = float(field.std())
    return field / np.float32(std) if std > 0 else field


def _ridged(
    rng: np.random.Generator,
    shape: tuple[int, int],
    cell_m: float,
    lmax_m: float,
    lmin_m: float,
    gain: float = 0.5,
) -> np.ndarray:
    """Ridged multifractal noise in [0, ~1]: sharp crests, rounded valleys. (rows, cols) float32.

    Octaves from lmax down to lmin, each ``gain`` x the amplitude of the previous one, weighted by the
    previous octave so that detail concentrates on the crests."""
    out = np.zeros(shape, np.float32)
    weight = np.ones(shape, np.float32)
    lam, amp, total = lmax_m, 1.0, 0.0
    while lam >= lmin_m:
        n = _spectral_noise(rng, shape, cell_m, 2.0, lam / 2.0, lam)
        r = (1.0 - np.abs(n) / 2.5).clip(0.0, 1.0) ** 2
        out += amp * r * weight
        weight = (r * 1.2).clip(0.0, 1.0)
        total += amp
        lam /= 2.0
        amp *= gain
    return out / total


def _smooth(img: np.ndarray, sigma_cells: float) -> np.ndarray:
    """Gaussian blur of std ``sigma_cells``; wide blurs are done on a downsampled copy (same result to a few
    per cent of the blurred signal, tens of times faster than a 6-sigma kernel at full resolution)."""
    f = 1
    while sigma_cells / (2 * f) >= 4.0:
        f *= 2
    if f == 1:
        return cv2.GaussianBlur(img, (0, 0), sigma_cells, borderType=cv2.BORDER_REFLECT)
    rows, cols = img.shape
    small = cv2.resize(img, (-(-cols // f), -(-rows // f)), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), np.sqrt(max(sigma_cells**2 / f**2 - 0.25, 0.25)))
    return cv2.resize(small, (cols, rows), interpolation=cv2.INTER_LINEAR)


def _rescale(h: np.ndarray, relief_m: float) -> np.ndarray:
    """Scale to max - min = relief_m and shift to zero mean."""
    span = float(h.max() - h.min())
    h = h * (relief_m / span) if span > 0 else h
    return (h - h.mean()).astype(np.float32)


def _grid_ne(shape: tuple[int, int], cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """World (north, east) of every cell of a scene grid centred on the origin, (rows, 1) and (1, cols)."""
    rows, cols = shape
    n = ((rows - 1) / 2.0 - np.arange(rows, dtype=np.float32))[:, None] * cell_m
    e = (np.arange(cols, dtype=np.float32) - (cols - 1) / 2.0)[None, :] * cell_m
    return n, e


def _blobs(
    rng: np.random.Generator, shape: tuple[int, int], cell_m: float, density_per_m2: float, sigma_m: float
) -> np.ndarray:
    """Sum of unit-peak Gaussian blobs of std ``sigma_m`` at Poisson-random cells. (rows, cols) float32."""
    rows, cols = shape
    count = rng.poisson(density_per_m2 * rows * cols * cell_m * cell_m)
    img = np.zeros(shape, np.float32)
    r = rng.integers(0, rows, count)
    c = rng.integers(0, cols, count)
    amp = rng.uniform(0.4, 1.0, count).astype(np.float32)
    np.add.at(img, (r, c), amp)
    s = max(sigma_m / cell_m, 0.5)
    blurred = cv2.GaussianBlur(img, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    return blurred * np.float32(2.0 * np.pi * s * s)


def _rocks(
    rng: np.random.Generator, shape: tuple[int, int], cell_m: float, density_per_m2: float
) -> np.ndarray:
    """Rock field: blobs in three size classes (0.15, 0.3, 0.6 m std), peak ~ rock size. float32 (m)."""
    out = np.zeros(shape, np.float32)
    for sigma_m, frac in ((0.15, 0.7), (0.3, 0.25), (0.6, 0.05)):
        out += _blobs(rng, shape, cell_m, density_per_m2 * frac, sigma_m) * np.float32(1.2 * sigma_m)
    return out


def _craters(
    rng: np.random.Generator,
    h: np.ndarray,
    cell_m: float,
    count: int,
    r_min_m: float,
    r_max_m: float,
    slope: float = 2.0,
) -> np.ndarray:
    """Add ``count`` craters in place-free fashion (returns a new array).

    Radii from a power-law size-frequency distribution N(>R) ~ R^-slope between r_min and r_max. Profile
    (simple crater): parabolic bowl of depth 0.2 D below the pre-impact surface, rim 0.04 D high, ejecta
    falling off as (r/R)^-3 out to 3 R. Hand-written (no library stamps craters); each crater touches only
    its own window.
    """
    rows, cols = h.shape
    out = h.copy()
    u = rng.uniform(0.0, 1.0, count)
    a, b = r_min_m ** (-slope), r_max_m ** (-slope)
    radii = (a - u * (a - b)) ** (-1.0 / slope)
    cr = rng.uniform(0, rows, count)
    cc = rng.uniform(0, cols, count)
    fresh = rng.uniform(0.4, 1.0, count)  # degradation state: older craters are shallower
    for R, r0, c0, f in sorted(zip(radii, cr, cc, fresh), key=lambda x: -x[0]):
        k = int(np.ceil(3.0 * R / cell_m))
        ra, rb = max(int(r0) - k, 0), min(int(r0) + k + 1, rows)
        ca, cb = max(int(c0) - k, 0), min(int(c0) + k + 1, cols)
        if ra >= rb or ca >= cb:
            continue
        yy = (np.arange(ra, rb, dtype=np.float32)[:, None] - r0) * cell_m
        xx = (np.arange(ca, cb, dtype=np.float32)[None, :] - c0) * cell_m
        x = np.sqrt(xx * xx + yy * yy) / R  # radius in crater radii
        D = 2.0 * R
        depth, rim = 0.2 * D * f, 0.04 * D * f
        inside = rim + (depth + rim) * (x * x - 1.0)
        outside = rim * np.clip(x, 1.0, None) ** -3.0
        prof = np.where(x < 1.0, inside, outside)
        prof = np.where(x < 3.0, prof - rim / 27.0 * (x >= 1.0), 0.0)  # ejecta reaches 0 at 3 R
        sigma_cells = 0.06 * R / cell_m
        if sigma_cells >= 1.0:  # round the rim crest (the profile's slope jumps there)
            prof = _smooth(prof.astype(np.float32), sigma_cells)
        win = out[ra:rb, ca:cb]
        # fill the bowl relative to the local mean so craters on slopes keep their shape
        base = float(win[x < 1.0].mean()) if (x < 1.0).any() else float(win.mean())
        blend = np.clip((1.2 - x) / 0.4, 0.0, 1.0)  # inner floor follows the flat base, rim follows terrain
        out[ra:rb, ca:cb] = win * (1.0 - blend) + base * blend + prof.astype(np.float32)
    return out


def _meander(
    rng: np.random.Generator, shape: tuple[int, int], cell_m: float, amplitude_m: float, wavelength_m: float
) -> np.ndarray:
    """Distance (m) from every cell to a meandering north-south centreline. (rows, cols) float32."""
    rows, cols = shape
    n_pts = rows
    s = np.arange(n_pts, dtype=np.float64) * cell_m
    phase = rng.uniform(0, 2 * np.pi, 3)
    offs = (
        amplitude_m * np.sin(2 * np.pi * s / wavelength_m + phase[0])
        + 0.4 * amplitude_m * np.sin(2 * np.pi * s / (0.43 * wavelength_m) + phase[1])
        + 0.2 * amplitude_m * np.sin(2 * np.pi * s / (0.17 * wavelength_m) + phase[2])
    )
    centre_col = (cols - 1) / 2.0 + rng.uniform(-0.1, 0.1) * cols + offs / cell_m
    line = np.ones(shape, np.uint8)
    cc = np.clip(np.round(centre_col).astype(int), 0, cols - 1)
    line[np.arange(rows), cc] = 0
    # connect consecutive centreline cells so the line has no gaps
    for r in range(1, rows):
        a, b = sorted((cc[r - 1], cc[r]))
        line[r, a : b + 1] = 0
    dist = cv2.distanceTransform(line, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return dist * np.float32(cell_m)


# ----------------------------------------------------------------------------------------------------------
# scene recipes: each returns (height before rescale, albedo hint in [-1, 1] or None)


def _fine(rng, shape, cell_m, sigma_m: float) -> np.ndarray:
    """Small-scale roughness (0.5-4 m wavelengths) of std ``sigma_m`` (m)."""
    return sigma_m * _spectral_noise(rng, shape, cell_m, 2.0, max(0.5, 2 * cell_m), 4.0)


def _scene_highlands(rng, shape, cell_m, coarse: bool):
    if coarse:
        # GoogleMap-derived (8.6 m DEM resized x20, so nothing finer than ~1 m): smoother spectrum, no
        # small craters or roughness
        h = _spectral_noise(rng, shape, cell_m, 4.4, 1.5, 600.0)
        h = h + 0.15 * np.abs(_spectral_noise(rng, shape, cell_m, 3.8, 6.0, 100.0))
        return _rescale(h, 75.0), None
    h = _spectral_noise(rng, shape, cell_m, 4.0, 2.0, 600.0)
    h = h + 0.4 * np.abs(_spectral_noise(rng, shape, cell_m, 3.5, 10.0, 150.0))  # eroded knobs
    h = _rescale(h, 50.0)  # metres, so crater sizes below are in metres too
    h = _craters(rng, h, cell_m, 40, 2.0, 25.0)
    return h + _fine(rng, shape, cell_m, 0.03), None


def _scene_dunes(rng, shape, cell_m):
    n, e = _grid_ne(shape, cell_m)
    theta = rng.uniform(0, np.pi)  # crest orientation
    wavelength = 35.0
    warp = _spectral_noise(rng, shape, cell_m, 4.0, 40.0, 400.0)
    coord = (n * np.cos(theta) + e * np.sin(theta)) / wavelength + 0.5 * warp
    frac = coord - np.floor(coord)
    # asymmetric profile: gentle stoss (70 % of the wavelength) then steep lee (~30 deg for 6 m dunes)
    prof = np.where(frac < 0.7, frac / 0.7, (1.0 - frac) / 0.3)
    prof = np.sin(0.5 * np.pi * prof) ** 1.5
    amp = 0.7 + 0.3 * np.tanh(_spectral_noise(rng, shape, cell_m, 4.0, 60.0, 600.0))
    base = _rescale(_spectral_noise(rng, shape, cell_m, 4.0, 60.0, 600.0), 14.0)
    ripples = 0.02 * _spectral_noise(rng, shape, cell_m, 1.5, 0.5, 3.0)
    h = 6.0 * prof * amp + base + ripples
    return h.astype(np.float32), -prof  # dark sand on the crests


def _scene_craters(rng, shape, cell_m):
    h = _rescale(_spectral_noise(rng, shape, cell_m, 4.0, 5.0, 600.0), 8.0)  # metres
    h = _craters(rng, h, cell_m, 600, 1.5, 90.0, slope=1.8)
    return h + _fine(rng, shape, cell_m, 0.02), None


def _scene_gravel(rng, shape, cell_m):
    n, e = _grid_ne(shape, cell_m)
    theta = rng.uniform(0, 2 * np.pi)
    ramp = (n * np.cos(theta) + e * np.sin(theta)) * np.float32(0.13)  # ~7 deg regional slope
    h = ramp + 5.0 * _spectral_noise(rng, shape, cell_m, 4.0, 20.0, 600.0)
    # gravel: pebbles of a few cm everywhere (rocks are added by make_scene)
    h = h + 0.04 * _spectral_noise(rng, shape, cell_m, 1.0, 2 * cell_m, 2.0)
    return h.astype(np.float32), None


def _scene_mountain(rng, shape, cell_m, fine: bool):
    if fine:
        h = _ridged(rng, shape, cell_m, 300.0, 2.0, gain=0.4)
    else:
        h = _ridged(rng, shape, cell_m, 300.0, 8.0, gain=0.4)
    h = h + 0.3 * _spectral_noise(rng, shape, cell_m, 4.0, 50.0, 600.0)
    h = _rescale(h, 80.0 if fine else 28.0)
    return h + _fine(rng, shape, cell_m, 0.03 if fine else 0.01), None


def _scene_canyon(rng, shape, cell_m):
    dist = _meander(rng, shape, cell_m, 60.0, 400.0)
    half_width = 60.0 + 15.0 * _spectral_noise(rng, shape, cell_m, 4.0, 50.0, 400.0)
    x = dist / half_width
    # flat floor, steep walls with a terrace at mid height, flat plateau
    wall = np.clip((x - 0.45) / 0.35, 0, 1)
    terrace = np.clip((x - 0.85) / 0.25, 0, 1)
    prof = 0.55 * (wall * wall * (3 - 2 * wall)) + 0.45 * (terrace * terrace * (3 - 2 * terrace))
    h = 70.0 * prof + 4.0 * _spectral_noise(rng, shape, cell_m, 4.0, 4.0, 300.0)
    h = h + _fine(rng, shape, cell_m, 0.03)
    return h.astype(np.float32), -np.clip(1.0 - x, 0, 1)  # darker floor deposits


def _scene_valley(rng, shape, cell_m):
    dist = _meander(rng, shape, cell_m, 40.0, 500.0)
    x = dist / 250.0
    prof = 60.0 * np.clip(x, 0, 1.5) ** 1.3  # broad V/U valley
    hills = 25.0 * _spectral_noise(rng, shape, cell_m, 4.0, 10.0, 400.0) * np.clip(x, 0.2, 1.0)
    trib = 6.0 * np.abs(_spectral_noise(rng, shape, cell_m, 4.0, 20.0, 150.0))  # tributary gullies
    h = prof + hills - trib + _fine(rng, shape, cell_m, 0.02)
    return h.astype(np.float32), -np.clip(1.0 - 4.0 * x, 0, 1)  # dark valley-floor deposits


def _albedo(
    rng: np.random.Generator, h: np.ndarray, cell_m: float, rocks: np.ndarray, hint: np.ndarray | None
) -> np.ndarray:
    """Albedo in (0, 1]: base Mars ~0.25, bright dust in low/concave areas and on gentle slopes, large
    bright/dark patches, fine mottling, dark rocks. float32 (rows, cols)."""
    shape = h.shape
    local = h - _smooth(h, 10.0 / cell_m)
    lstd = float(local.std()) or 1.0
    dust = np.clip(-local / (2.0 * lstd), 0.0, 1.0)  # hollows collect dust
    gy, gx = np.gradient(h, cell_m)
    slope = np.sqrt(gx * gx + gy * gy)
    dust = dust * np.exp(-slope / 0.5)
    patches = _spectral_noise(rng, shape, cell_m, 3.0, 8.0, 300.0)
    mottle = _spectral_noise(rng, shape, cell_m, 1.0, 0.5, 6.0)
    a = 0.25 * (1.0 + 0.25 * np.tanh(patches)) * (1.0 + 0.08 * mottle) + 0.12 * dust
    if hint is not None:
        a = a * (1.0 + 0.25 * hint)
    a = a * (1.0 - 0.5 * np.clip(rocks / 0.3, 0.0, 1.0))  # rocks darker than dust
    return np.clip(a, 0.02, 1.0).astype(np.float32)


_RECIPES: dict[str, Callable] = {
    "01": lambda rng, shape, cell: _scene_highlands(rng, shape, cell, coarse=False),
    "02": _scene_dunes,
    "03": _scene_craters,
    "04": lambda rng, shape, cell: _scene_highlands(rng, shape, cell, coarse=True),
    "05": _scene_gravel,
    "06": lambda rng, shape, cell: _scene_mountain(rng, shape, cell, fine=False),
    "07": _scene_canyon,
    "08": _scene_valley,
    "09": lambda rng, shape, cell: _scene_mountain(rng, shape, cell, fine=True),
}

_ROCK_DENSITY_PER_M2: dict[str, float] = {
    "01": 0.02,
    "02": 0.002,
    "03": 0.03,
    "04": 0.0,
    "05": 0.15,
    "06": 0.01,
    "07": 0.03,
    "08": 0.02,
    "09": 0.01,
}
"""Rocks per square metre (gravel plain densest; the coarse GoogleMap-like scene has none resolved)."""


def make_scene(scene_id: str, seed: int = 0, cell_m: float = DEFAULT_CELL_M, size_m: float = 600.0) -> Scene:
    """Generate scene ``scene_id`` ("01".."09") of ``size_m`` x ``size_m`` at ``cell_m``, from ``seed``.

    The same (scene_id, seed, cell_m, size_m) always gives the identical scene.
    """
    if scene_id not in SCENE_IDS:
        raise ValueError(f"unknown scene id {scene_id!r}, expected one of {SCENE_IDS}")
    if not (cell_m > 0 and size_m > 4 * cell_m):
        raise ValueError(f"need cell_m > 0 and size_m > 4 cells, got cell_m={cell_m} size_m={size_m}")
    n = int(round(size_m / cell_m))
    shape = (n, n)
    rng = np.random.default_rng([int(seed), int(scene_id)])
    h, hint = _RECIPES[scene_id](rng, shape, cell_m)
    relief = SCENE_RELIEF_M[scene_id]
    h = _rescale(h.astype(np.float32), relief)
    rocks = _rocks(rng, shape, cell_m, _ROCK_DENSITY_PER_M2[scene_id])
    h = _rescale(h + rocks, relief)
    albedo = _albedo(rng, h, cell_m, rocks, hint)
    north0 = (n - 1) / 2.0 * cell_m
    east0 = -(n - 1) / 2.0 * cell_m
    dem = Dem(h, float(north0), float(east0), float(cell_m))
    sun = Sun.from_degrees(*SCENE_SUN_DEG[scene_id])
    return Scene(scene_id, SCENE_NAMES[scene_id], dem, albedo, sun, float(h.max() - h.min()))


# ----------------------------------------------------------------------------------------------------------
# DEM degradation


@dataclass(frozen=True)
class DemDegradation:
    """How the estimator's DEM differs from the true surface.

    factor: cell-size multiplier (area averaging). cell_m: resulting cell (m). noise_sigma_m: std of the
    white elevation noise added per cell (m). hole_fraction: fraction of cells set to NaN (in blobs, like
    stereo-matching failures). seed: RNG seed of noise and holes.
    """

    factor: int
    cell_m: float
    noise_sigma_m: float
    hole_fraction: float
    seed: int

    def describe(self) -> str:
        """One line for benchmark tables."""
        return (
            f"DEM degraded: {self.cell_m:.2f} m cell ({self.factor}x coarser than truth), "
            f"noise sigma {self.noise_sigma_m:.2f} m, {100 * self.hole_fraction:.1f}% holes, seed {self.seed}"
        )


def degrade_dem(
    dem: Dem,
    factor: int = 4,
    noise_sigma_m: float = 0.3,
    hole_fraction: float = 0.01,
    seed: int = 0,
) -> tuple[Dem, DemDegradation]:
    """The DEM an estimator gets: ``factor`` x coarser (area average), white noise of ``noise_sigma_m``,
    and ``hole_fraction`` of cells as NaN blobs. Returns (degraded Dem, its description)."""
    if factor < 1:
        raise ValueError(f"degradation factor must be >= 1, got {factor}")
    if not 0.0 <= hole_fraction < 1.0:
        raise ValueError(f"hole_fraction must be in [0, 1), got {hole_fraction}")
    rng = np.random.default_rng(seed)
    coarse = dem.filled().resampled(dem.cell_m * factor) if factor > 1 else dem.filled()
    h = coarse.height_m.astype(np.float32).copy()
    if noise_sigma_m > 0:
        h += rng.normal(0.0, noise_sigma_m, h.shape).astype(np.float32)
    if hole_fraction > 0:
        # blobs a few cells wide: smooth white noise, keep the top ``hole_fraction`` quantile
        blob = ndimage.gaussian_filter(rng.standard_normal(h.shape).astype(np.float32), 2.0)
        k = int(round(hole_fraction * h.size))
        if k > 0:
            idx = np.argpartition(blob.ravel(), h.size - k)[h.size - k :]
            h.ravel()[idx] = np.nan
    out = Dem(h, coarse.north0_m, coarse.east0_m, coarse.cell_m)
    deg = DemDegradation(
        int(factor), float(coarse.cell_m), float(noise_sigma_m), out.hole_fraction(), int(seed)
    )
    return out, deg
