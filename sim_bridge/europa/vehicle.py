"""The simulated vehicle's Europa world (``python -m sim_bridge sim --world europa``): the site, the
co-registered visible + thermal camera pair, one of paper 2's ten trajectories, and the truth the simulated
autopilot turns into telemetry (the range along body down for DISTANCE_SENSOR).

The sensor noise of the autopilot's telemetry over Europa (``EUROPA_TELEMETRY_NOISE``) matches the sensors
of the offline benchmark (``bench/thermal_ekf.py``): the IMU of ``sim_bridge.trajectory.ImuNoise`` and the
altimeter of ``sim_bridge.europa.sensors.AltimeterNoise``, so the daemon's EKF sees what it is tuned for.
"""

from __future__ import annotations

import math

import numpy as np

from companion.constants import R_BODY_CAM_NADIR
from companion.geometry import camera_pose
from sim_bridge.autopilot_link import SimNoise
from sim_bridge.europa.render import EuropaCameras
from sim_bridge.europa.sensors import AltimeterNoise
from sim_bridge.europa.trajectories import TRAJECTORY_TABLE, paper_trajectories
from sim_bridge.europa.world import EuropaWorld, make_europa
from sim_bridge.trajectory import ImuNoise, Trajectory, TrajectoryState

EUROPA_CAMERA_RATE_HZ = 2.0
"""Default frame-pair rate of the simulated cameras (paper 2 flies at 1 Hz). Measured on this 2-core
machine with the daemon beside the simulator and other work loading it (load 6-8): a pair renders in
42-61 ms alone (render_ms_per_pair in the committed bench/results/thermal_ekf*.json; 86 in an older
run), but the daemon's SIFT on both
images takes most of the rest. At 4 Hz the camera skipped 20 % of its slots and 36 % of the estimates
reached the autopilot later than its 500 ms fusion horizon; at 2 Hz it skipped 2 of 120 and 81 % of
the pairs became accepted estimates. ``--camera-rate 4`` (ArduPilot's minimum external-nav rate) suits
an unloaded machine."""

EUROPA_HIGHRES_IMU_HZ = 50.0
"""HIGHRES_IMU rate of the simulated autopilot (its default)."""


def europa_telemetry_noise(imu_hz: float = EUROPA_HIGHRES_IMU_HZ) -> SimNoise:
    """Autopilot telemetry noise over Europa: per-sample IMU sigmas from ImuNoise's densities at ``imu_hz``
    (sigma = density * sqrt(rate)), ImuNoise's bias spreads, the benchmark altimeter's white noise
    (AltimeterNoise: 5 cm + 0.2 %); attitude and local position keep SimNoise's figures."""
    imu, alt = ImuNoise(), AltimeterNoise()
    root = math.sqrt(imu_hz)
    return SimNoise(
        accel_mps2=imu.accel_noise_density * root,
        accel_bias_mps2=imu.accel_bias_sigma,
        gyro_rps=imu.gyro_noise_density * root,
        gyro_bias_rps=imu.gyro_bias_sigma,
        range_m=alt.sigma_m,
        range_frac=alt.sigma_frac,
    )


class EuropaFlight:
    """Site, cameras and trajectory of one simulated flight over Europa.

    seed: the site (``make_europa``) and the trajectory's actuation noise (``paper_trajectories``).
    trajectory: "1".."10" (``TRAJECTORY_TABLE``). Building the site takes ~5 s.
    """

    def __init__(self, seed: int = 0, trajectory: str = "1") -> None:
        if trajectory not in TRAJECTORY_TABLE:
            raise ValueError(f"unknown Europa trajectory {trajectory!r} (1..10)")
        self.world: EuropaWorld = make_europa(seed)
        self.cameras = EuropaCameras(self.world)
        self.traj: Trajectory = paper_trajectories(self.world, seed)[trajectory]
        self.description = TRAJECTORY_TABLE[trajectory][0]

    def range_m(self, s: TrajectoryState) -> float:
        """True distance (m) from the body origin along body down (+z) to the terrain; NaN = no return."""
        d = s.R_world_body[:, 2]  # body down axis in NED
        if d[2] <= 1e-3:
            return float("nan")
        drop = self.cameras.tracer.march(s.p_world, np.array([d[0] / d[2]]), np.array([d[1] / d[2]]))[0]
        return float(drop / d[2])  # drop -> distance along the unit axis

    def render(self, s: TrajectoryState, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """The synchronised pair at ``s``: (visible uint8 (480, 640), thermal uint16 centi-kelvin)."""
        R_wc, p_c = camera_pose(s.R_world_body, s.p_world, R_BODY_CAM_NADIR)
        return self.cameras.render(R_wc, p_c, seed=seed)
