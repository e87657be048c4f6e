"""Per-frame fitted reference: the frame's spectrum explained as a combination of DEM-derived basis images,
and coherence weights for the phase correlation. Pure numpy.

Why: paper 1 renders the reference with eq. 3 under a *presumed* sun. Measured on the simulated scenes, two
things move the phase-correlation peak away from the truth along the sun azimuth by 0.5-3 frame pixels:
the real sun differs from the presumed one (Table 6), and the surface reflectance is correlated with the
topography (dust in hollows, dark valley floors), which adds an even (height-like) component to the frame
that sits in quadrature with the odd (slope-like) shading. Linearising eq. 3,
``I ~ L r (sin s - cos s (p_e sin t + p_n cos t)) / sqrt(1 + |grad h|^2)``, any sun is a linear combination
of three images of the DEM: p_e / n, p_n / n and 1 / n (n = sqrt(1 + |grad h|^2)); a topography-correlated
reflectance adds a local-relief image. After a first alignment, the coefficients of these bases are fitted
to the frame by least squares in the Fourier domain, per frequency ring (the reflectance coupling depends
on scale), and the phase correlation is repeated against the fitted reference.

Coherence weights: per (ring, orientation sector) the real coherence rho between the aligned frame and the
fitted reference; weight rho^2 / (1 - rho^2) (Hannan-Thomson / maximum-likelihood weighting of generalised
cross-correlation), zero where rho <= 0. Bins dominated by albedo texture or DEM noise then stop diluting
the peak.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np
from scipy.optimize import minimize

from companion.georef.phase import hermitian_multiplicity, rfreq


@dataclass(frozen=True)
class Bins:
    """Frequency bins of a half-plane spectrum: ring (n_rings log-spaced between f_lo and f_hi) and sector
    (n_sectors orientations over a half turn) of every bin in the band, flat indices into the spectrum."""

    index: np.ndarray  # (B,) flat indices of the band bins
    ring: np.ndarray  # (B,) ring of each bin
    sector: np.ndarray  # (B,) sector of each bin
    fx: np.ndarray  # (B,) cycles/pixel
    fy: np.ndarray
    mult: np.ndarray  # (B,) Hermitian multiplicity (1 or 2)
    n_rings: int
    n_sectors: int

    @staticmethod
    def make(shape: tuple[int, int], f_lo: float, f_hi: float, n_rings: int, n_sectors: int) -> Bins:
        rows, cols = shape
        fx, fy, f = rfreq(rows, cols)
        fxx = np.broadcast_to(fx, f.shape)
        fyy = np.broadcast_to(fy, f.shape)
        band = (f >= f_lo) & (f <= f_hi)
        idx = np.flatnonzero(band.ravel())
        fb = f.ravel()[idx]
        edges = np.geomspace(f_lo, f_hi, n_rings + 1)
        ring = np.clip(np.searchsorted(edges, fb, side="right") - 1, 0, n_rings - 1)
        ang = np.arctan2(fyy.ravel()[idx], fxx.ravel()[idx]) % np.pi
        sector = np.minimum((ang / np.pi * n_sectors).astype(np.int64), n_sectors - 1)
        mult = np.broadcast_to(hermitian_multiplicity(rows, cols), f.shape).ravel()[idx]
        return Bins(idx, ring, sector, fxx.ravel()[idx], fyy.ravel()[idx], mult, n_rings, n_sectors)

    def ramp(self, shift_px: np.ndarray) -> np.ndarray:
        """(B,) exp(+2 pi i f . shift): multiplying a frame spectrum by it undoes a content shift."""
        return np.exp(2j * np.pi * (self.fx * shift_px[0] + self.fy * shift_px[1]))


@lru_cache(maxsize=16)
def bins(shape: tuple[int, int], f_lo: float, f_hi: float, n_rings: int, n_sectors: int) -> Bins:
    """Cached ``Bins.make`` (the same grid size and band come back every frame)."""
    return Bins.make(shape, f_lo, f_hi, n_rings, n_sectors)


def _ring_systems(X: np.ndarray, bins: Bins) -> Iterator[tuple[np.ndarray, Any, Any, Any]]:
    """Per ring: (mask, X^H W (K, Bm), Re(X^H W X) (K, K), column scales 1 / sqrt(diag)) of the per-ring least
    squares, W the Hermitian multiplicity; (mask, None, None, None) for a ring with too few bins to fit."""
    for r in range(bins.n_rings):
        m = bins.ring == r
        if m.sum() < 2 * X.shape[1]:
            yield m, None, None, None
            continue
        XwH = np.conj(X[m]).T * bins.mult[m]
        G = (XwH @ X[m]).real
        yield m, XwH, G, 1.0 / np.sqrt(np.maximum(np.diag(G), 1e-30))


def fit_reference(
    f_frame: np.ndarray, f_bases: list[np.ndarray], bins: Bins, shift_px: np.ndarray
) -> np.ndarray:
    """Least-squares combination of the basis spectra that best explains the frame spectrum after undoing
    ``shift_px``, with separate real coefficients per ring. Returns (B,) complex reference on the band bins."""
    a = f_frame.ravel()[bins.index] * bins.ramp(shift_px)
    X = np.stack([b.ravel()[bins.index] for b in f_bases], axis=1)
    out = np.zeros(a.shape, np.complex128)
    for m, XwH, G, scale in _ring_systems(X, bins):
        if XwH is None:
            out[m] = X[m, 0]
            continue
        # real coefficients c minimising sum_bins w |a - X c|^2: normal equations (K x K, K = 5), each
        # column scaled to unit norm so that the heights (m) and the shadings (0..L) condition alike
        rhs = XwH @ a[m]
        Gs = G * np.outer(scale, scale)
        coef = scale * np.linalg.solve(Gs + 1e-9 * np.eye(len(scale)), rhs.real * scale)
        out[m] = X[m] @ coef
    return out


def joint_shift(
    f_frame: np.ndarray,
    f_bases: list[np.ndarray],
    bins: Bins,
    shift0_px: np.ndarray,
    step_px: float = 0.3,
    max_move_px: float = 3.0,
) -> np.ndarray:
    """The shift that, with its own best basis coefficients (``fit_reference``'s model: real coefficients per
    ring), leaves the least of the frame unexplained; searched from ``shift0_px`` (Nelder-Mead, initial steps
    ``step_px``). Returns ``shift0_px`` if the search moves further than ``max_move_px``.

    Why: the frame holds even, height-like terms (reflectance tied to the relief: dark rocks, dust in hollows;
    and the darkening 1/sqrt(1 + |grad h|^2) of slopes finer than the DEM, which a smoothed DEM under-draws).
    Correlated against the odd shading, they move the correlation peak along the sun; alternating "fit the
    coefficients at the peak, correlate against the fit" settles where the two explain each other, not at
    the truth, because a shift of the shading along the sun looks partly like such a term. Minimising the
    fitted residual over the shift itself (the profile likelihood of the shift) does not: with the DEM only
    coarsened and a uniform albedo (``python -m bench georef_budget --joint-shift``) the bias along the sun
    went from -0.92 to -0.25 px on scene 08 and from -0.56 to -0.17 px on scene 05. It costs noise where the
    alternating fit was right (see ``GeorefOptions.joint_shift``).

    The residual at given shift needs no new fit: with G = Re(X^H W X) per ring (independent of the shift,
    the ramp has unit modulus) and r = Re(X^H W a e^{2 pi i f.s}), it is sum W|a|^2 - r^T G^-1 r."""
    a0 = f_frame.ravel()[bins.index].astype(np.complex128)
    X = np.stack([b.ravel()[bins.index] for b in f_bases], axis=1).astype(np.complex128)
    rings = []
    for m, XwH, G, scale in _ring_systems(X, bins):
        if XwH is None:
            continue
        Ginv = np.linalg.inv(G * np.outer(scale, scale) + 1e-9 * np.eye(len(scale)))
        rings.append((m, XwH * scale[:, None], Ginv))
    if not rings:
        return np.asarray(shift0_px, float)

    def explained(shift: np.ndarray) -> float:
        a = a0 * bins.ramp(shift)
        total = 0.0
        for m, XwH, Ginv in rings:
            r = (XwH @ a[m]).real
            total += float(r @ Ginv @ r)
        return -total

    s0 = np.asarray(shift0_px, float)
    simplex = s0 + np.array([[0.0, 0.0], [step_px, 0.0], [0.0, step_px]])
    res = minimize(
        explained, s0, method="Nelder-Mead", options=dict(initial_simplex=simplex, xatol=0.005, fatol=0.0)
    )
    s = np.asarray(res.x, float)
    return s if np.all(np.isfinite(s)) and np.hypot(*(s - s0)) <= max_move_px else s0


def coherence_weight(
    f_frame: np.ndarray, ref_bins: np.ndarray, bins: Bins, shift_px: np.ndarray, floor: float = 0.05
) -> np.ndarray:
    """(B,) weights rho^2 / (1 - rho^2 + floor) per (ring, sector), rho = real coherence of the aligned frame
    and the reference in that cell (0 where rho <= 0 or the cell is empty)."""
    a = f_frame.ravel()[bins.index] * bins.ramp(shift_px)
    cross = (a * np.conj(ref_bins)).real * bins.mult
    pa = (np.abs(a) ** 2) * bins.mult
    pr = (np.abs(ref_bins) ** 2) * bins.mult
    cell = bins.ring * bins.n_sectors + bins.sector
    n_cells = bins.n_rings * bins.n_sectors
    s_cross = np.bincount(cell, cross, n_cells)
    s_a = np.bincount(cell, pa, n_cells)
    s_r = np.bincount(cell, pr, n_cells)
    rho = s_cross / np.sqrt(s_a * s_r + 1e-30)
    rho = np.clip(rho, 0.0, 0.999)
    w_cell = rho * rho / (1.0 - rho * rho + floor)
    return w_cell[cell]


def scatter(values: np.ndarray, bins: Bins, shape: tuple[int, int], dtype=np.complex64) -> np.ndarray:
    """Put (B,) band-bin values into a zero half-plane spectrum of an image of ``shape``."""
    rows, cols = shape
    out = np.zeros(rows * (cols // 2 + 1), dtype)
    out[bins.index] = values
    return out.reshape(rows, cols // 2 + 1)
