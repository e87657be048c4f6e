"""Data passed between the daemon's stages and the estimators. Frozen dataclasses, no I/O.

Every sample carries ``stamp_us``: integer microseconds. Camera frames are stamped with their
capture time in the companion's clock (Unix epoch, as ROS 2 header stamps are); samples from the
autopilot are stamped on arrival in the same clock (their own boot-time stamp is kept beside it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Frame:
    """One decoded camera image.

    image: (H, W) uint8 or uint16 single channel (colour frames are converted to mono at decode).
    camera: logical camera name from the config (``nadir``, ``visible``, ``thermal``).
    """

    stamp_us: int
    camera: str
    image: np.ndarray
    seq: int = 0


@dataclass(frozen=True)
class AttitudeSample:
    """Vehicle attitude from the autopilot (ATTITUDE). Angles in radians, NED/FRD."""

    stamp_us: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


@dataclass(frozen=True)
class ImuSample:
    """Body-frame (FRD) specific force (m/s^2) and angular rate (rad/s), e.g. HIGHRES_IMU."""

    stamp_us: int
    accel_mps2: np.ndarray
    gyro_rps: np.ndarray


@dataclass(frozen=True)
class AltimeterSample:
    """Range to the ground along the body down axis (DISTANCE_SENSOR), metres."""

    stamp_us: int
    range_m: float


@dataclass(frozen=True)
class LocalPositionSample:
    """The autopilot's own position and velocity estimate (LOCAL_POSITION_NED) in the world NED frame.

    p_ned_m: (3,) metres; v_ned_mps: (3,) m/s. An estimator may start from it (the vision takes over from
    the vehicle's navigation); it is never an input afterwards (it would echo our own estimates back).
    """

    stamp_us: int
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray


class EstimateStatus(StrEnum):
    OK = "ok"
    INITIALISING = "initialising"
    LOST = "lost"


@dataclass(frozen=True)
class PoseEstimate:
    """Vehicle (body) pose in the world NED frame.

    p_body_in_world_m: (3,) NED metres. rpy_rad: (3,) roll, pitch, yaw.
    covariance: (6, 6) over (x, y, z, roll, pitch, yaw) in m^2 / rad^2, the estimator's own.
    reset_counter: bumped by the estimator whenever its estimate jumps (re-initialisation).
    quality: 0..1, the estimator's confidence (e.g. phase-correlation peak); for the status line.
    v_world_mps / cov_v_world: optional velocity; ODOMETRY is only sent for estimates that have one.
    """

    stamp_us: int
    p_body_in_world_m: np.ndarray
    rpy_rad: np.ndarray
    covariance: np.ndarray
    reset_counter: int = 0
    quality: float = 0.0
    status: EstimateStatus = EstimateStatus.OK
    info: dict = field(default_factory=dict)
    v_world_mps: np.ndarray | None = None  # (3,) NED velocity, when the estimator has one (for ODOMETRY)
    cov_v_world: np.ndarray | None = None  # (3, 3) its covariance, m^2/s^2

    def is_sendable(self) -> bool:
        """True when the estimate may go to the autopilot: status OK and all values finite."""
        return (
            self.status is EstimateStatus.OK
            and bool(np.all(np.isfinite(self.p_body_in_world_m)))
            and bool(np.all(np.isfinite(self.rpy_rad)))
            and bool(np.all(np.isfinite(self.covariance)))
        )


class Estimator(Protocol):
    """What the daemon drives. One instance per flight; called from one thread only.

    The daemon forwards autopilot samples as they arrive and hands each camera frame (or a
    synchronised pair, keyed by camera name) to ``on_frames``, which returns at once with the
    estimate for that capture time, or None when there is nothing trustworthy to send.
    """

    cameras: tuple[str, ...]

    def on_attitude(self, sample: AttitudeSample) -> None: ...

    def on_imu(self, sample: ImuSample) -> None: ...

    def on_altimeter(self, sample: AltimeterSample) -> None: ...

    def on_local_position(self, sample: LocalPositionSample) -> None: ...

    def on_frames(self, frames: dict[str, Frame]) -> PoseEstimate | None: ...

    def close(self) -> None: ...
