"""Smooth vehicle trajectories with their IMU: paper 1's circular, forward and scanning flights.

A trajectory is a C2 cubic spline through timed NED positions and headings. A multicopter tilts to
accelerate, so roll and pitch follow from the specific force (``tilt=True``); with ``tilt=False`` the body
stays level (a gimballed nadir camera). Pure numpy/scipy, deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

from companion.constants import GRAVITY_MPS2


@dataclass(frozen=True)
class TrajectoryState:
    """Truth at one instant. p/v/a_world: (3,) NED; R_world_body: (3,3); omega_body_rps: (3,) FRD."""

    t_s: float
    p_world: np.ndarray
    v_world: np.ndarray
    a_world: np.ndarray
    R_world_body: np.ndarray
    omega_body_rps: np.ndarray


def _R_from_thrust_and_yaw(z_body_world: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """(N,3,3) rotations whose body z axis is ``z_body_world`` (N,3 unit) and heading ``yaw_rad`` (N,)."""
    x_c = np.stack([np.cos(yaw_rad), np.sin(yaw_rad), np.zeros_like(yaw_rad)], axis=1)
    y_b = np.cross(z_body_world, x_c)
    y_b /= np.linalg.norm(y_b, axis=1, keepdims=True)
    x_b = np.cross(y_b, z_body_world)
    return np.stack([x_b, y_b, z_body_world], axis=2)


class Trajectory:
    """C2 spline trajectory through (t_s, p_world, yaw_rad) knots.

    t_s: (N,) strictly increasing seconds; p_world: (N,3) NED metres; yaw_rad: (N,) heading (unwrapped here).
    """

    def __init__(
        self,
        t_s: np.ndarray,
        p_world: np.ndarray,
        yaw_rad: np.ndarray,
        *,
        tilt: bool = True,
        gravity_mps2: float = GRAVITY_MPS2["mars"],
    ) -> None:
        t_s = np.asarray(t_s, float)
        if t_s.ndim != 1 or len(t_s) < 4 or np.any(np.diff(t_s) <= 0):
            raise ValueError("trajectory needs >= 4 strictly increasing knot times")
        self.t0_s = float(t_s[0])
        self.t1_s = float(t_s[-1])
        self.tilt = tilt
        self.g_world = np.array([0.0, 0.0, gravity_mps2])
        self._p = CubicSpline(t_s, np.asarray(p_world, float), axis=0, bc_type="natural")
        self._yaw = CubicSpline(t_s, np.unwrap(np.asarray(yaw_rad, float)), bc_type="natural")

    @property
    def duration_s(self) -> float:
        return self.t1_s - self.t0_s

    def _rotations(self, t: np.ndarray) -> np.ndarray:
        yaw = self._yaw(t)
        if self.tilt:
            f = self._p(t, 2) - self.g_world  # specific force; thrust points along -body z
            z_b = -f / np.linalg.norm(f, axis=1, keepdims=True)
        else:
            z_b = np.tile([0.0, 0.0, 1.0], (len(t), 1))
        return _R_from_thrust_and_yaw(z_b, yaw)

    def states(self, t_s: np.ndarray) -> list[TrajectoryState]:
        """Truth at each time in ``t_s`` (clipped to the trajectory span)."""
        t = np.clip(np.atleast_1d(np.asarray(t_s, float)), self.t0_s, self.t1_s)
        p, v, a = self._p(t), self._p(t, 1), self._p(t, 2)
        R = self._rotations(t)
        omega = self._angular_rate(t, R)
        return [TrajectoryState(float(t[i]), p[i], v[i], a[i], R[i], omega[i]) for i in range(len(t))]

    def state_at(self, t_s: float) -> TrajectoryState:
        return self.states(np.array([t_s]))[0]

    def _angular_rate(self, t: np.ndarray, R: np.ndarray, dt: float = 1e-3) -> np.ndarray:
        # body rate from the rotation's central difference: log(R(t-dt)^T R(t+dt)) / (2 dt)
        Rm = self._rotations(np.clip(t - dt, self.t0_s, self.t1_s))
        Rp = self._rotations(np.clip(t + dt, self.t0_s, self.t1_s))
        span = np.clip(t + dt, self.t0_s, self.t1_s) - np.clip(t - dt, self.t0_s, self.t1_s)
        rel = Rotation.from_matrix(np.einsum("nji,njk->nik", Rm, Rp))
        return rel.as_rotvec() / span[:, None]

    def distance_m(self, t0_s: float | None = None, t1_s: float | None = None, step_s: float = 0.05) -> float:
        """Path length flown between two times."""
        a = self.t0_s if t0_s is None else t0_s
        b = self.t1_s if t1_s is None else t1_s
        t = np.arange(a, b + step_s, step_s)
        p = self._p(np.clip(t, self.t0_s, self.t1_s))
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


@dataclass(frozen=True)
class ImuNoise:
    """IMU error model (continuous-time densities; defaults: a small MEMS IMU like an ICM-42688)."""

    accel_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz)
    gyro_noise_density: float = 1.7e-4  # rad/s/sqrt(Hz)
    accel_bias_sigma: float = 0.02  # m/s^2, initial bias spread
    gyro_bias_sigma: float = 1.0e-3  # rad/s, initial bias spread
    accel_bias_walk: float = 1.0e-4  # m/s^3/sqrt(Hz)
    gyro_bias_walk: float = 2.0e-6  # rad/s^2/sqrt(Hz)


@dataclass(frozen=True)
class ImuSeries:
    """Sampled IMU. t_us: (N,) int64; accel_mps2, gyro_rps: (N,3) body FRD; biases: (N,3) truth."""

    t_us: np.ndarray
    accel_mps2: np.ndarray
    gyro_rps: np.ndarray
    accel_bias: np.ndarray
    gyro_bias: np.ndarray


def imu_samples(traj: Trajectory, rate_hz: float, noise: ImuNoise | None = None, seed: int = 0) -> ImuSeries:
    """IMU readings along the trajectory: specific force R^T (a - g) and body rate, plus noise and bias."""
    noise = ImuNoise() if noise is None else noise
    rng = np.random.default_rng(seed)
    t = np.arange(traj.t0_s, traj.t1_s, 1.0 / rate_hz)
    sts = traj.states(t)
    R = np.stack([s.R_world_body for s in sts])
    a = np.stack([s.a_world for s in sts])
    f_body = np.einsum("nji,nj->ni", R, a - traj.g_world)
    w_body = np.stack([s.omega_body_rps for s in sts])
    n = len(t)
    dt = 1.0 / rate_hz
    ba = rng.normal(0, noise.accel_bias_sigma, 3) + np.cumsum(
        rng.normal(0, noise.accel_bias_walk * np.sqrt(dt), (n, 3)), axis=0
    )
    bg = rng.normal(0, noise.gyro_bias_sigma, 3) + np.cumsum(
        rng.normal(0, noise.gyro_bias_walk * np.sqrt(dt), (n, 3)), axis=0
    )
    acc = f_body + ba + rng.normal(0, noise.accel_noise_density / np.sqrt(dt), (n, 3))
    gyr = w_body + bg + rng.normal(0, noise.gyro_noise_density / np.sqrt(dt), (n, 3))
    return ImuSeries(np.round(t * 1e6).astype(np.int64), acc, gyr, ba, bg)


def _ramped_arc_length(
    speed_mps: float, duration_s: float, ramp_s: float, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Times and distance travelled for a speed profile ramping smoothly up from (and down to) rest."""
    t = np.arange(0.0, duration_s + dt / 2, dt)
    ramp = np.clip(np.minimum(t, duration_s - t) / max(ramp_s, 1e-9), 0.0, 1.0)
    v = speed_mps * (0.5 - 0.5 * np.cos(np.pi * ramp))
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    return t, s


def circular(
    centre_ne: tuple[float, float],
    radius_m: float,
    altitude_m: float,
    speed_mps: float,
    duration_s: float,
    *,
    ramp_s: float = 5.0,
    start_angle_rad: float = 0.0,
    heading: str = "tangent",
    tilt: bool = True,
    gravity_mps2: float = GRAVITY_MPS2["mars"],
) -> Trajectory:
    """Paper 1 trajectory (a): constant-altitude circle, counter-clockwise seen from above.

    altitude_m: height above the world origin (NED z = -altitude). heading: "tangent" or "north".
    """
    t, s = _ramped_arc_length(speed_mps, duration_s, ramp_s, 0.25)
    ang = start_angle_rad + s / radius_m
    n = centre_ne[0] + radius_m * np.cos(ang)
    e = centre_ne[1] - radius_m * np.sin(ang)  # counter-clockwise in a north-up map
    p = np.stack([n, e, np.full_like(n, -altitude_m)], axis=1)
    if heading == "tangent":
        # velocity direction of (cos a, -sin a) is (-sin a, -cos a) in (north, east)
        yaw = np.unwrap(np.arctan2(-np.cos(ang), -np.sin(ang)))
    else:
        yaw = np.zeros_like(ang)
    return Trajectory(t, p, yaw, tilt=tilt, gravity_mps2=gravity_mps2)


def forward(
    start_ne: tuple[float, float],
    heading_rad: float,
    altitude_m: float,
    speed_mps: float,
    duration_s: float,
    *,
    ramp_s: float = 5.0,
    tilt: bool = True,
    gravity_mps2: float = GRAVITY_MPS2["mars"],
) -> Trajectory:
    """Paper 1 trajectory (b): straight line at constant altitude and heading."""
    t, s = _ramped_arc_length(speed_mps, duration_s, ramp_s, 0.25)
    n = start_ne[0] + s * np.cos(heading_rad)
    e = start_ne[1] + s * np.sin(heading_rad)
    p = np.stack([n, e, np.full_like(n, -altitude_m)], axis=1)
    return Trajectory(t, p, np.full_like(t, heading_rad), tilt=tilt, gravity_mps2=gravity_mps2)


def scanning(
    start_ne: tuple[float, float],
    leg_m: float,
    spacing_m: float,
    altitude_m: float,
    speed_mps: float,
    duration_s: float,
    *,
    ramp_s: float = 5.0,
    tilt: bool = True,
    gravity_mps2: float = GRAVITY_MPS2["mars"],
) -> Trajectory:
    """Paper 1 trajectory (c): lawn-mower legs along north, joined by half-circle turns stepping east."""
    r = spacing_m / 2.0
    # one period: leg north, half turn east, leg south, half turn east
    period = 2 * leg_m + 2 * np.pi * r
    t, s = _ramped_arc_length(speed_mps, duration_s, ramp_s, 0.25)
    k, u = np.divmod(s, period)
    n = np.empty_like(s)
    e = np.empty_like(s)
    yaw = np.empty_like(s)
    e0 = start_ne[1] + k * 2 * spacing_m
    a1, a2, a3 = leg_m, leg_m + np.pi * r, 2 * leg_m + np.pi * r
    m = u < a1  # northbound leg
    n[m], e[m], yaw[m] = start_ne[0] + u[m], e0[m], 0.0
    m = (u >= a1) & (u < a2)  # turn at the north end, centre (leg, e0 + r)
    th = (u[m] - a1) / r
    n[m], e[m], yaw[m] = start_ne[0] + leg_m + r * np.sin(th), e0[m] + r - r * np.cos(th), th
    m = (u >= a2) & (u < a3)  # southbound leg
    n[m], e[m], yaw[m] = start_ne[0] + leg_m - (u[m] - a2), e0[m] + spacing_m, np.pi
    m = u >= a3  # turn at the south end, centre (0, e0 + 3r)
    th = (u[m] - a3) / r
    n[m], e[m], yaw[m] = start_ne[0] - r * np.sin(th), e0[m] + spacing_m + r - r * np.cos(th), np.pi - th
    p = np.stack([n, e, np.full_like(n, -altitude_m)], axis=1)
    return Trajectory(t, p, np.unwrap(yaw), tilt=tilt, gravity_mps2=gravity_mps2)
