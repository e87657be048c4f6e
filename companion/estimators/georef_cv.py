"""The ``georef`` estimator: every nadir frame geo-referenced against the DEM, fused by a
constant-velocity Kalman filter (north, east) so that frames without a fix coast with a covariance that
grows honestly, and wild fixes are gated. Height comes from the fix (eq. 18: DEM + height above ground),
attitude from the autopilot. Pure math: no I/O.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from companion.estimators.history import SampleHistory
from companion.geometry import rot_from_rpy
from companion.georef.georef import GeoFix, GeoReferencer
from companion.types import (
    AltimeterSample,
    AttitudeSample,
    EstimateStatus,
    Frame,
    ImuSample,
    LocalPositionSample,
    PoseEstimate,
)


@dataclass(frozen=True)
class GeorefEstimatorOptions:
    accel_sigma_mps2: float = (
        2.0  # horizontal white-acceleration process noise of the constant-velocity model
    )
    vertical_accel_sigma_mps2: float = 0.5  # vertical white-acceleration process noise
    fix_sigma_floor_m: float = 0.5  # added (in quadrature) to each fix's own sigma: the matcher's covariance
    # comes from its correlation peak and cannot see the errors of the DEM itself (coarse cells, noise,
    # lighting); on the degraded DEMs of the benchmarks fixes scatter 0.3-0.6 m where the peak claims < 0.1 m
    initial_sigma_m: float = 5.0  # horizontal uncertainty of the initial position (1 sigma)
    initial_speed_sigma_mps: float = 2.0
    gate_chi2: float = 13.8  # innovation gate (chi-square, 2 dof, p = 0.001)
    reinit_after_rejections: int = 5  # consecutive gated fixes that agree before re-initialising on them
    reinit_consistency_m: float = 2.0  # gated fixes within this of each other count as agreeing
    max_coast_s: float = 2.0  # without an accepted fix for this long, the estimate is LOST
    altitude_sigma_m: float = (
        1.0  # 1-sigma of one height fix, DEM + height above ground (a 1 % rangefinder at 100 m)
    )
    attitude_sigma_rad: float = float(np.radians(2.0))  # we forward the autopilot's attitude; its 1-sigma


@dataclass
class GeorefEstimator:
    """Implements ``companion.types.Estimator`` for a single nadir camera."""

    cameras: tuple[str, ...] = ("nadir",)

    def __init__(
        self,
        options: GeorefEstimatorOptions,
        georeferencer: GeoReferencer,
        initial_p_world: np.ndarray,
    ) -> None:
        self.opt = options
        self.geo = georeferencer
        # state: north, east, down (m) and their rates (m/s)
        self._x = np.array([*np.asarray(initial_p_world, float)[:3], 0.0, 0.0, 0.0])
        self._P = np.diag(
            [options.initial_sigma_m**2] * 2
            + [options.altitude_sigma_m**2]
            + [options.initial_speed_sigma_mps**2] * 3
        )
        self._t_us: int | None = None
        self._last_fix_us: int | None = None
        self._gated_offsets: deque[np.ndarray] = deque(maxlen=2 * options.reinit_after_rejections)
        self.reset_counter = 0
        self._attitude = SampleHistory()
        self._range = SampleHistory()
        self.counters = {"fixes": 0, "no_fix": 0, "gated": 0, "reinit": 0}
        self.no_fix_reasons: dict[str, int] = {}

    # -- inputs from the autopilot ------------------------------------------------------------------
    def on_attitude(self, s: AttitudeSample) -> None:
        self._attitude.add(s.stamp_us, np.array([s.roll_rad, s.pitch_rad, s.yaw_rad]))

    def on_imu(self, s: ImuSample) -> None:
        """Not used by this estimator (the constant-velocity model needs no IMU)."""

    def on_local_position(self, s: LocalPositionSample) -> None:
        """Not used: the position comes from the terrain fixes (the configured start is the prior)."""

    def on_altimeter(self, s: AltimeterSample) -> None:
        if np.isfinite(s.range_m) and s.range_m > 0:
            self._range.add(s.stamp_us, float(s.range_m))

    def close(self) -> None:
        """Nothing to release."""

    # -- the filter --------------------------------------------------------------------------------
    def _predict(self, t_us: int) -> None:
        if self._t_us is None:
            self._t_us = t_us
            return
        dt = (t_us - self._t_us) * 1e-6
        if dt <= 0:
            return
        F = np.eye(6)
        F[0, 3] = F[1, 4] = F[2, 5] = dt
        Q = np.zeros((6, 6))
        for axis, q in (
            (0, self.opt.accel_sigma_mps2**2),
            (1, self.opt.accel_sigma_mps2**2),
            (2, self.opt.vertical_accel_sigma_mps2**2),
        ):
            idx = [axis, axis + 3]
            Q[np.ix_(idx, idx)] = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        self._x = F @ self._x
        self._P = F @ self._P @ F.T + Q
        self._t_us = t_us

    def _update(self, fix: GeoFix) -> bool:
        """Fuse one geo-fix: north/east from the match, down from DEM + height above ground (eq. 18)."""
        R_fix = fix.cov_ne_m2 + np.eye(2) * self.opt.fix_sigma_floor_m**2
        y = fix.p_world[:2] - self._x[:2]
        S = self._P[:2, :2] + R_fix
        d2 = float(y @ np.linalg.solve(S, y))
        if d2 > self.opt.gate_chi2:
            self.counters["gated"] += 1
            self._gated_offsets.append(y)
            if len(self._gated_offsets) < self.opt.reinit_after_rejections:
                return False
            # consensus: the largest group of recent rejected fixes that agree with each other
            offsets = np.array(self._gated_offsets)
            dist = np.linalg.norm(offsets[:, None, :] - offsets[None, :, :], axis=2)
            members = dist <= self.opt.reinit_consistency_m
            best = int(np.argmax(members.sum(axis=1)))
            group = offsets[members[best]]
            if len(group) < self.opt.reinit_after_rejections:
                return False
            centre = np.median(group, axis=0)
            spread = float(np.max(np.linalg.norm(group - centre, axis=1)))
            # the fixes agree with each other and not with us: we are the ones who are wrong
            self._x[:2] = self._x[:2] + centre
            self._P[:2, :] = 0.0
            self._P[:, :2] = 0.0
            self._P[:2, :2] = R_fix + np.eye(2) * (spread / 2.0) ** 2
            self.reset_counter += 1
            self.counters["reinit"] += 1
            self._gated_offsets.clear()
            self._fuse(np.array([2]), fix.p_world[2:3], np.array([[self.opt.altitude_sigma_m**2]]))
            return True
        self._fuse(np.array([0, 1]), fix.p_world[:2], R_fix)
        if np.isfinite(fix.p_world[2]):
            self._fuse(np.array([2]), fix.p_world[2:3], np.array([[self.opt.altitude_sigma_m**2]]))
        self._gated_offsets.clear()
        return True

    def _fuse(self, idx: np.ndarray, z: np.ndarray, R: np.ndarray) -> None:
        """Kalman update of the state components ``idx`` measured directly as ``z`` with covariance ``R``."""
        H = np.zeros((len(idx), 6))
        H[np.arange(len(idx)), idx] = 1.0
        S = H @ self._P @ H.T + R
        K = self._P @ H.T @ np.linalg.inv(S)
        self._x = self._x + K @ (z - H @ self._x)
        self._P = (np.eye(6) - K @ H) @ self._P
        self._P = 0.5 * (self._P + self._P.T)

    def on_frames(self, frames: dict[str, Frame]) -> PoseEstimate | None:
        frame = frames.get("nadir")
        if frame is None:
            return None
        t = frame.stamp_us
        rpy = self._attitude.nearest(t, max_gap_us=100_000)
        if rpy is None:
            # without the autopilot's attitude the frame cannot be rectified: no estimate, counted
            self.no_fix_reasons["no_attitude"] = self.no_fix_reasons.get("no_attitude", 0) + 1
            return None
        if self._last_fix_us is None:
            # the configured initial position is a prior with its own covariance: it counts as a fix
            # at the first frame, so the estimate is OK (and says how uncertain) until max_coast_s passes
            self._last_fix_us = t
        rpy = np.asarray(rpy, float)
        R = rot_from_rpy(*rpy)
        self._predict(t)
        rng = self._range.nearest(t, max_gap_us=200_000)
        p_pred = self._x[:3].copy()
        # the altimeter ranges along body down; the fix wants the height above the ground below
        agl = None if rng is None else self.geo.dem.height_above_ground(p_pred, R, float(rng))
        fix = self.geo.locate(frame.image, R, p_pred, alt_agl_m=agl)
        accepted = False
        if fix.ok:
            accepted = self._update(fix)
            if accepted:
                self._last_fix_us = t
                self.counters["fixes"] += 1
        else:
            reason = fix.reason
            self.no_fix_reasons[reason] = self.no_fix_reasons.get(reason, 0) + 1
            self.counters["no_fix"] += 1
        if (t - self._last_fix_us) * 1e-6 > self.opt.max_coast_s:
            status = EstimateStatus.LOST
        else:
            status = EstimateStatus.OK
        cov = np.zeros((6, 6))
        cov[:3, :3] = self._P[:3, :3]
        cov[3:, 3:] = np.eye(3) * self.opt.attitude_sigma_rad**2
        return PoseEstimate(
            stamp_us=t,
            p_body_in_world_m=self._x[:3].copy(),
            rpy_rad=rpy,
            covariance=cov,
            reset_counter=self.reset_counter,
            quality=float(fix.quality) if fix.ok else 0.0,
            status=status,
            info={"fix": accepted, "reason": fix.reason},
            v_world_mps=self._x[3:].copy(),
            cov_v_world=self._P[3:, 3:].copy(),
        )
