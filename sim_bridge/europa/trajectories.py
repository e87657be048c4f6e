"""The ten descent trajectories of paper 2 (section 3), with Gaussian actuation noise.

The paper says only: ten trajectories over the 400 m site, "two linear motions as well as an S-shape,
half-ellipse and half-circle", thirty trials each with additive Gaussian actuation noise, cameras at
1 fps, and its error plots run to ~160-180 s. No lengths, heights or speeds are given. The table below is
ours (``TRAJECTORY_TABLE``): every trajectory lasts 180 s, starts 60-140 m above the local terrain and
ends 25-60 m above it, at 0.8-1.8 m/s, and keeps the whole camera footprint on the terrain (>= 11 m from
the edge, checked for seeds 0-3). Heights are above the terrain smoothed over ~10 m (so a hill under the
path lifts the path, a block does not). Heading follows the horizontal velocity, except "7" (north).

=====  ==============================================  ======  ==============  ===========
name   shape                                            length  height (m)      mean speed
=====  ==============================================  ======  ==============  ===========
1      linear, south to north, descending              226 m   120 -> 30       1.3 m/s
2      linear, south-west to north-east, descending    282 m   110 -> 35       1.6 m/s
3      S-shape northward, +-50 m sideways              305 m   100 -> 30       1.7 m/s
4      half-ellipse, semi-axes 100 m (N) x 70 m (E)    283 m   100 -> 30       1.6 m/s
5      half-circle, radius 90 m                         293 m    90 -> 30       1.6 m/s
6      linear, east to west, constant height            222 m    60 -> 60       1.2 m/s
7      steep descent with 60 m northward drift          137 m   140 -> 25       0.8 m/s
8      descending spiral, one turn, radius 70 -> 25 m   318 m   110 -> 30       1.8 m/s
9      S-shape westward, +-40 m sideways                268 m    80 -> 40       1.5 m/s
10     dog-leg: north 100 m, rounded turn, east 100 m  244 m   100 -> 30       1.4 m/s
=====  ==============================================  ======  ==============  ===========

Actuation noise: the nominal path is sampled at knots every ``knot_s`` (5) seconds; each knot's position
gets independent N(0, actuation_sigma^2) noise per axis (0.3 m) and its heading N(0, yaw_sigma^2) (1 deg);
the C2 spline through the noisy knots is the flown (true) trajectory, so the IMU sees the perturbations.
The body tilts with the thrust (multicopter-like lander): ~3 deg on average, up to ~10 deg, in Europa's
1.315 m/s^2 gravity.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from companion.constants import GRAVITY_MPS2
from sim_bridge.europa.world import EuropaWorld
from sim_bridge.trajectory import Trajectory

DURATION_S = 180.0
"""Length of every trajectory (the paper's error plots run to about 180 s)."""

CAMERA_RATE_HZ = 1.0
"""Frame rate of the synchronised camera pair in paper 2 (1 fps)."""

# name -> (description, u -> (north_m, east_m), height above ground at start and end (m))
TRAJECTORY_TABLE: dict[
    str, tuple[str, Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], float, float]
] = {
    "1": ("linear, south to north, descending", lambda u: (-100 + 200 * u, -30 + 0 * u), 120.0, 30.0),
    "2": (
        "linear, south-west to north-east, descending",
        lambda u: (-90 + 190 * u, -90 + 190 * u),
        110.0,
        35.0,
    ),
    "3": (
        "S-shape northward, +-50 m sideways",
        lambda u: (-100 + 200 * u, 50 * np.sin(2 * np.pi * u)),
        100.0,
        30.0,
    ),
    "4": (
        "half-ellipse, semi-axes 100 m (N) x 70 m (E)",
        lambda u: (-100 * np.cos(np.pi * u), 70 * np.sin(np.pi * u) - 20),
        100.0,
        30.0,
    ),
    "5": (
        "half-circle, radius 90 m",
        lambda u: (-90 * np.cos(np.pi * u), -90 * np.sin(np.pi * u) + 30),
        90.0,
        30.0,
    ),
    "6": ("linear, east to west, constant 60 m", lambda u: (30 + 0 * u, 110 - 220 * u), 60.0, 60.0),
    "7": (
        "steep descent with 60 m northward drift",
        lambda u: (-30 + 60 * u**1.5, 20 + 0 * u),
        140.0,
        25.0,
    ),
    "8": (
        "descending spiral, one turn, radius 70 -> 25 m",
        lambda u: ((70 - 45 * u) * np.cos(2 * np.pi * u), (70 - 45 * u) * np.sin(2 * np.pi * u)),
        110.0,
        30.0,
    ),
    "9": (
        "S-shape westward, +-40 m sideways",
        lambda u: (-40 * np.sin(2 * np.pi * u) + 10, 100 - 200 * u),
        80.0,
        40.0,
    ),
    "10": (
        "dog-leg: north 100 m, rounded turn, east 100 m",
        lambda u: _dogleg(u),
        100.0,
        30.0,
    ),
}


def _dogleg(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two 100 m legs (north, then east) joined by a quarter circle of radius 20 m, by arc length."""
    leg, r = 100.0, 20.0
    arc = 0.5 * np.pi * r
    total = 2 * leg + arc
    s = np.asarray(u, float) * total
    n = np.where(s < leg, s, np.where(s < leg + arc, leg + r * np.sin((s - leg) / r), leg + r))
    e = np.where(s < leg, 0.0, np.where(s < leg + arc, r - r * np.cos((s - leg) / r), r + (s - leg - arc)))
    return n - 60.0, e - 70.0


def _smooth_ground(world: EuropaWorld, north: np.ndarray, east: np.ndarray) -> np.ndarray:
    dem = world.dem
    sigma_cells = 10.0 / dem.cell_m
    # downsample before blurring: a 10 m blur does not need the 0.25 m grid
    f = max(int(sigma_cells // 4), 1)
    small = cv2.resize(dem.height_m, None, fx=1.0 / f, fy=1.0 / f, interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma_cells / f, borderType=cv2.BORDER_REPLICATE)
    r, c = dem.rc_from_ne(north, east)
    r = (np.asarray(r) + 0.5) / f - 0.5
    c = (np.asarray(c) + 0.5) / f - 0.5
    return cv2.remap(small, c.astype(np.float32).reshape(1, -1), r.astype(np.float32).reshape(1, -1),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).ravel()  # fmt: skip


def nominal_knots(
    world: EuropaWorld, name: str, knot_s: float = 5.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t_s (K,), p_world (K, 3) NED, yaw_rad (K,)) of trajectory ``name`` without noise.

    Heading follows the horizontal velocity (tangent), except for the near-vertical descent "7" (north)."""
    _, path, h0, h1 = TRAJECTORY_TABLE[name]
    t = np.arange(0.0, DURATION_S + 1e-9, knot_s)
    u = t / DURATION_S
    n, e = (np.asarray(x, float) * np.ones_like(u) for x in path(u))
    # height above ground eases from h0 to h1 (smooth start and end of the descent rate)
    agl = h0 + (h1 - h0) * (0.5 - 0.5 * np.cos(np.pi * u))
    ground = _smooth_ground(world, n, e)
    p = np.stack([n, e, -(ground + agl)], axis=1)
    du = 1e-3
    n2, e2 = (np.asarray(x, float) * np.ones_like(u) for x in path(np.clip(u + du, 0, 1)))
    n1, e1 = (np.asarray(x, float) * np.ones_like(u) for x in path(np.clip(u - du, 0, 1)))
    yaw = np.unwrap(np.arctan2(e2 - e1, n2 - n1)) if name != "7" else np.zeros_like(u)
    return t, p, yaw


def paper_trajectories(
    world: EuropaWorld,
    seed: int,
    actuation_sigma: float = 0.3,
    yaw_sigma_rad: float = np.radians(1.0),
    knot_s: float = 5.0,
) -> dict[str, Trajectory]:
    """The ten trajectories, keys "1".."10", each with its own Gaussian actuation noise drawn from ``seed``.

    actuation_sigma: m per axis at each knot (0.3 m every 5 s: tilts ~3 deg on average, up to ~10 deg, in
    Europa's 1.315 m/s^2 gravity). Bodies tilt with thrust (multicopter-like model of the lander)."""
    out: dict[str, Trajectory] = {}
    for i, name in enumerate(TRAJECTORY_TABLE):
        t, p, yaw = nominal_knots(world, name, knot_s)
        rng = np.random.default_rng([int(seed), i])
        p = p + rng.normal(0.0, actuation_sigma, p.shape)
        yaw = yaw + rng.normal(0.0, yaw_sigma_rad, yaw.shape)
        out[name] = Trajectory(t, p, yaw, tilt=True, gravity_mps2=GRAVITY_MPS2["europa"])
    return out
