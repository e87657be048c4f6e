"""New-landmark sampling (paper 2 section 3.3): spatial diversity D(l) = -log f(l) (eq. 8), or uniform.

f is a kernel density estimate, in image pixels, of where the tracked landmarks are. Candidates are
drawn without replacement with probability proportional to D(l); each pick joins the tracked set
before the next draw, so the new landmarks of one frame are spread out among themselves as well.

D depends on the unit f is measured in (a change of unit adds a constant to every D, which changes
weights proportional to D), and the paper does not say which. We measure f relative to the uniform
density over the image, f * W * H, so D(l) > 0 exactly where the tracked landmarks are sparser than
uniform, and sample with weights max(D, 0): crowded places are never picked while an emptier one is
available (when every candidate is crowded, the least crowded is taken).

The KDE is a small vectorised isotropic Gaussian written here instead of ``scipy.stats.gaussian_kde``:
gaussian_kde fails with fewer than 3 points or collinear points (singular data covariance), which is
exactly the state of the map after a loss of track, and its kernel takes the shape of the tracked
set's covariance (elongated along a line of landmarks), whereas spatial diversity wants distance
in the image to count the same in every direction. The width follows Scott's rule, n^(-1/6) sigma,
with sigma the pooled per-axis standard deviation, between a floor and a cap: half the spacing of the
landmark budget spread evenly over the image (0.5 sqrt(W H / N): 48 px for 32 landmarks in 640 x 480).
Scott's rule alone, made for estimating a density, smooths over ~150 px here and hardly tells a
covered spot from an empty one; the cap makes one landmark "cover" about its share of the image (on
a uniform candidate set it raises the mean nearest-neighbour distance of 32 new landmarks from 55 to
75 px, where uniform sampling gives 55). Log densities use log-sum-exp (max-shifted) so far-away candidates get a
large finite D instead of -log 0.
"""

from __future__ import annotations

import numpy as np


def budget_bandwidth(image_area_px2: float, n_landmarks: int) -> float:
    """Half the spacing (px) of ``n_landmarks`` spread evenly over the image: the kernel-width cap."""
    return 0.5 * float(np.sqrt(image_area_px2 / max(n_landmarks, 1)))


def scott_bandwidth(points_uv: np.ndarray, min_px: float, max_px: float) -> float:
    """Isotropic kernel width (px) for (M,2) points: Scott's rule with pooled sigma, within [min_px, max_px].

    With fewer than two points the width is ``max_px``."""
    m = len(points_uv)
    if m < 2:
        return float(max_px)
    sigma = float(np.sqrt(np.mean(np.var(points_uv, axis=0, ddof=1))))
    return min(float(max_px), max(float(min_px), sigma * m ** (-1.0 / 6.0)))


def kde_log_density(query_uv: np.ndarray, points_uv: np.ndarray, bandwidth_px: float) -> np.ndarray:
    """(N,) log f at (N,2) query pixels of an isotropic Gaussian KDE over (M,2) points (M >= 1)."""
    d2 = np.sum((query_uv[:, None, :] - points_uv[None, :, :]) ** 2, axis=2)
    h2 = bandwidth_px * bandwidth_px
    # log-sum-exp over the points, written out (scipy's logsumexp costs ~10x more on these small arrays)
    x = (-0.5 / h2) * d2
    m = np.max(x, axis=1)
    lse = m + np.log(np.sum(np.exp(x - m[:, None]), axis=1))
    return lse - np.log(len(points_uv) * 2.0 * np.pi * h2)


def diversity(
    query_uv: np.ndarray, points_uv: np.ndarray, bandwidth_px: float, image_area_px2: float = 1.0
) -> np.ndarray:
    """(N,) eq. 8: D(l) = -log(f(l) * image_area_px2), f in 1/px^2. With no tracked points: 0 everywhere."""
    if len(points_uv) == 0:
        return np.zeros(len(query_uv))
    return -kde_log_density(query_uv, points_uv, bandwidth_px) - np.log(image_area_px2)


def sample_new_landmarks(
    candidates_uv: np.ndarray,
    tracked_uv: np.ndarray,
    k: int,
    method: str,
    rng: np.random.Generator,
    min_bandwidth_px: float = 16.0,
    max_bandwidth_px: float = 48.0,
    image_area_px2: float = 640.0 * 480.0,
) -> np.ndarray:
    """Indices (<= k,) into (N,2) ``candidates_uv`` of the new landmarks, given (M,2) tracked pixels.

    method "kde": weights max(D(l), 0) (eq. 8, f relative to uniform over ``image_area_px2``), recomputed
    after each pick; "uniform": equal weights.
    """
    n = len(candidates_uv)
    k = min(k, n)
    if k <= 0:
        return np.zeros(0, dtype=int)
    if method == "uniform":
        return rng.choice(n, size=k, replace=False)
    if method != "kde":
        raise ValueError(f"unknown sampling method {method!r}")
    chosen: list[int] = []
    available = np.ones(n, bool)
    tracked = np.asarray(tracked_uv, float).reshape(-1, 2)
    for _ in range(k):
        h = scott_bandwidth(tracked, min_bandwidth_px, max_bandwidth_px)
        idx = np.flatnonzero(available)
        D = diversity(candidates_uv[idx], tracked, h, image_area_px2)
        w = np.maximum(D, 0.0)
        if not np.any(w > 0):  # empty map (D = 0 everywhere) or every candidate crowded
            w = (D >= D.max()).astype(float)
        j = int(rng.choice(idx, p=w / w.sum()))
        chosen.append(j)
        available[j] = False
        tracked = np.vstack([tracked, candidates_uv[j]])
    return np.asarray(chosen, dtype=int)
