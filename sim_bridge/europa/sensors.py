"""Ranging altimeter over the simulated Europa (paper 2 section 3 adds one to the EKF).

The IMU comes from ``sim_bridge.trajectory.imu_samples`` (pass the trajectory built with Europa's gravity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim_bridge.europa.render import HeightfieldTracer
from sim_bridge.europa.world import EuropaWorld
from sim_bridge.trajectory import Trajectory


@dataclass(frozen=True)
class AltimeterNoise:
    """Laser/radar ranging altimeter along the body down axis.

    sigma_m + sigma_frac * range: white noise std (0.05 m + 0.2 %, a small lidar altimeter).
    bias_sigma_m: spread of a constant range bias drawn per seed (0.2 m).
    max_range_m: beyond this (or off the terrain) the sample is NaN (no return)."""

    sigma_m: float = 0.05
    sigma_frac: float = 0.002
    bias_sigma_m: float = 0.2
    max_range_m: float = 500.0


def true_ranges(
    traj: Trajectory, world: EuropaWorld, t_s: np.ndarray, tracer: HeightfieldTracer | None = None
) -> np.ndarray:
    """(N,) true distance (m) from the body origin along body +z (down) to the terrain; NaN = no hit."""
    tracer = HeightfieldTracer(world.dem) if tracer is None else tracer
    states = traj.states(np.asarray(t_s, float))
    p = np.stack([st.p_world for st in states])
    d = np.stack([st.R_world_body[:, 2] for st in states])  # body down axis in NED
    out = np.full(len(states), np.nan)
    down = d[:, 2] > 1e-3
    if down.any():
        s = tracer.march(p[down], d[down, 0] / d[down, 2], d[down, 1] / d[down, 2])
        out[down] = s / d[down, 2]  # drop -> distance along the unit axis
    return out


def altimeter_samples(
    traj: Trajectory,
    world: EuropaWorld,
    rate_hz: float = 10.0,
    noise: AltimeterNoise | None = None,
    seed: int = 0,
    tracer: HeightfieldTracer | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Altimeter readings along the trajectory: (t_us (N,) int64, range_m (N,) float64, NaN = no return).

    range = true slant range + constant bias (per seed) + white noise. tracer: reuse across calls
    (``EuropaCameras(world).tracer``) to skip the ~0.1 s set-up."""
    noise = AltimeterNoise() if noise is None else noise
    rng = np.random.default_rng([int(seed), 0xA17])
    t = np.arange(traj.t0_s, traj.t1_s, 1.0 / rate_hz)
    r = true_ranges(traj, world, t, tracer)
    bias = rng.normal(0.0, noise.bias_sigma_m)
    meas = r + bias + rng.normal(0.0, 1.0, r.shape) * (noise.sigma_m + noise.sigma_frac * np.nan_to_num(r))
    meas[~(r <= noise.max_range_m)] = np.nan
    return np.round(t * 1e6).astype(np.int64), meas
