"""The ``vis_thermal_ekf`` estimator (paper 2): inverse-depth EKF-SLAM on the visible camera, the
thermal camera, or both in one map, propagated with the IMU and aided by the altimeter.

The daemon drives ``VisThermalEkfEstimator`` (``companion.types.Estimator``); the benchmark and tests
drive the same object through ``run_sequence``. The math lives in ``companion.ekf``.

Numerical note: the filter's matrices are a few hundred wide, where multi-threaded OpenBLAS is
slower than one thread and collapses on a loaded 2-core machine (measured: 8 ms single-threaded vs
130 ms with two contended threads for the dual-mode update). Every call into the filter therefore
runs under ``threadpoolctl`` with BLAS limited to one thread (scoped to the call; the rest of the
process keeps its setting).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import ThreadpoolController

from companion.constants import GRAVITY_MPS2
from companion.ekf.features import Detections, SiftDetector
from companion.ekf.landmarks import CameraModel
from companion.ekf.options import EkfOptions, cameras_for_mode
from companion.ekf.slam import SlamPose, VisThermalSlam
from companion.ekf.so3 import quat_from_rot
from companion.geometry import CameraIntrinsics, rot_from_rpy, rpy_from_rot
from companion.lba.gauge import gauge_covariance
from companion.types import (
    AltimeterSample,
    AttitudeSample,
    EstimateStatus,
    Frame,
    ImuSample,
    LocalPositionSample,
    PoseEstimate,
)

__all__ = ["EkfOptions", "SequenceResult", "VisThermalEkfEstimator", "run_sequence", "start_attitude"]

_BLAS = ThreadpoolController()
log = logging.getLogger(__name__)


def _attitude_from_gravity(accel_mps2: np.ndarray, yaw_rad: float) -> np.ndarray:
    """(3,) roll, pitch, yaw of a vehicle at rest whose accelerometer reads ``accel_mps2`` (FRD)."""
    f = -np.asarray(accel_mps2, float)  # at rest the specific force is -g: f points up, -f down
    roll = float(np.arctan2(f[1], f[2]))
    pitch = float(np.arctan2(-f[0], np.hypot(f[1], f[2])))
    return np.array([roll, pitch, yaw_rad])


def start_attitude(
    attitudes: Sequence[AttitudeSample],
    gyro: Sequence[tuple[int, np.ndarray]],
    stamp_us: int,
    window_s: float,
    max_extrapolation_s: float = 0.1,
) -> np.ndarray | None:
    """(3,) roll, pitch, yaw (rad) at ``stamp_us``: the mean of the ATTITUDE samples within ``window_s`` of it,
    each carried to ``stamp_us`` by the body rates ``gyro`` ((stamp_us, (3,) rad/s FRD) samples) integrated
    between the two stamps. None without any sample.

    An autopilot's attitude jitters from sample to sample (a converged EKF3: ~0.2 deg roll/pitch, ~0.3 deg yaw);
    the filter starts from one attitude and keeps its error as a tilt of the map, so averaging the ~50 samples
    of a second shrinks the white part by ~7x (a slow error, e.g. the compass's yaw bias, stays). Samples the gyro
    does not cover (beyond ``max_extrapolation_s`` of its first / last stamp) are left out; with none left, or
    ``window_s`` <= 0, the sample nearest in time to ``stamp_us`` is returned as it is."""
    if not attitudes:
        return None
    t_att = np.array([a.stamp_us for a in attitudes], dtype=np.int64)
    near = attitudes[int(np.argmin(np.abs(t_att - stamp_us)))]
    nearest = np.array([near.roll_rad, near.pitch_rad, near.yaw_rad])
    if window_s <= 0 or len(gyro) < 2:
        return nearest
    order = np.argsort([g[0] for g in gyro], kind="stable")
    gt = np.array([gyro[i][0] for i in order], dtype=np.int64)
    gw = np.array([np.asarray(gyro[i][1], float) for i in order])
    # body rotation since the first gyro stamp, R(t0)^T R(t_k) (trapezoidal rate over each step); a hand loop
    # because scipy's Rotation has no cumulative product, and a start runs it once over ~100 samples
    dt = np.diff(gt) * 1e-6
    steps = Rotation.from_rotvec(0.5 * (gw[:-1] + gw[1:]) * dt[:, None])
    cum = [Rotation.identity()]
    for k in range(len(steps)):
        cum.append(cum[-1] * steps[k])
    ext_us = max_extrapolation_s * 1e6

    def since_first(t_us: int) -> Rotation | None:
        if t_us < gt[0] - ext_us or t_us > gt[-1] + ext_us:
            return None
        k = int(np.clip(np.searchsorted(gt, t_us, side="right") - 1, 0, len(gt) - 1))
        return cum[k] * Rotation.from_rotvec(gw[k] * ((t_us - gt[k]) * 1e-6))

    at_stamp = since_first(stamp_us)
    if at_stamp is None:
        return nearest
    carried = []
    for a, t in zip(attitudes, t_att):
        if abs(int(t) - stamp_us) > window_s * 1e6:
            continue
        at_sample = since_first(int(t))
        if at_sample is None:
            continue
        R_wb = Rotation.from_matrix(rot_from_rpy(a.roll_rad, a.pitch_rad, a.yaw_rad))
        carried.append(R_wb * at_sample.inv() * at_stamp)
    if not carried:
        return nearest
    mean = Rotation.concatenate(carried).mean()
    return np.asarray(rpy_from_rot(mean.as_matrix()), float)


class VisThermalEkfEstimator:
    """Implements ``companion.types.Estimator`` for paper 2's EKF-SLAM.

    intrinsics / R_body_cam / p_cam_in_body: per camera name ("visible", "thermal"); the cameras of
    ``options.mode`` must be present. The two cameras may share the pose (paper 2: co-registered) or
    have their own extrinsics. The filter starts at the first frame set's stamp, from:
    - position: ``initial_p_world``, or if None the autopilot's LOCAL_POSITION_NED (``on_local_position``,
      extrapolated to the frame's stamp with its velocity): the vision takes over from the vehicle's own
      navigation, and until the autopilot has sent one the frames are counted in ``waiting_for_position``;
    - velocity: ``initial_v_world``, or if None the autopilot's LOCAL_POSITION_NED velocity, else zero;
    - attitude: ``initial_rpy``, or if None the autopilot's ATTITUDE samples of the last
      ``options.initial_attitude_window_s`` averaged, each carried to the frame's stamp by the IMU's gyro
      (``start_attitude``; with less than that window of samples yet, the start waits for them, at most that
      long after the first frame set or the first sample, whichever came later, counted in
      ``waiting_for_attitude``); with no sample at all (the camera up before the autopilot streams) the start
      waits up to ``options.start_wait_s`` after the first frame set, then takes gravity from the IMU with yaw
      ``initial_yaw_rad``. ``warnings`` says what a start waits for. It does not wait for the IMU: without one
      the filter propagates on a constant-velocity motion model (``EkfOptions.imu_hold_max_s``).
    A LOCAL_POSITION_NED sample older than ``max_local_position_age_s`` at the frame is not used.
    """

    max_local_position_age_s = 1.0
    hold_s = 1.0
    """Longest time (s) IMU / altimeter samples wait for a frame set older than them (``_hold``)."""
    imu_gap_s = 0.5
    """A frame set with no IMU sample this close before it is counted in ``frames_without_imu`` and the
    status says so (``warnings``): without an IMU the filter propagates a constant velocity with the motion
    model's noise (``EkfOptions.imu_hold_max_s``)."""
    altimeter_gap_s = 2.0
    """Likewise for the altimeter (``frames_without_altimeter``): without it the scale rests on the landmarks'
    first depths only (out of its range, or DISTANCE_SENSOR not streamed)."""

    def __init__(
        self,
        options: EkfOptions,
        intrinsics: Mapping[str, CameraIntrinsics],
        R_body_cam: Mapping[str, np.ndarray],
        initial_p_world: np.ndarray | None,
        initial_v_world: np.ndarray | None = None,
        initial_rpy: np.ndarray | None = None,
        gravity_mps2: float = GRAVITY_MPS2["europa"],
        p_cam_in_body: Mapping[str, np.ndarray] | None = None,
        initial_yaw_rad: float = 0.0,
    ) -> None:
        self.options = options
        self.cameras: tuple[str, ...] = cameras_for_mode(options.mode)
        models = {}
        for c in self.cameras:
            if c not in intrinsics or c not in R_body_cam:
                raise ValueError(f"mode {options.mode!r} needs intrinsics and R_body_cam for camera {c!r}")
            intr = intrinsics[c]
            p = np.zeros(3) if p_cam_in_body is None or c not in p_cam_in_body else p_cam_in_body[c]
            models[c] = CameraModel(
                intr.K, intr.width, intr.height, np.asarray(R_body_cam[c], float), np.asarray(p, float)
            )
        self._models = models
        self.slam = VisThermalSlam(options, models, gravity_mps2)
        self._detectors = {c: SiftDetector(options, c) for c in self.cameras}
        self._pool = ThreadPoolExecutor(max_workers=len(self.cameras)) if len(self.cameras) > 1 else None
        self._p0 = None if initial_p_world is None else np.asarray(initial_p_world, float).copy()
        self._v0 = None if initial_v_world is None else np.asarray(initial_v_world, float).copy()
        self._rpy0 = None if initial_rpy is None else np.asarray(initial_rpy, float).copy()
        self._yaw0 = float(initial_yaw_rad)
        # the start's buffers (stamp_us, sample), for ``start_attitude``
        self._attitudes: deque[tuple[int, AttitudeSample]] = deque()
        self._gyro: deque[tuple[int, np.ndarray]] = deque()
        self._local: LocalPositionSample | None = None
        self._first_frame_us: int | None = None
        self._estimates = 0  # estimates made (the first is INITIALISING)
        self._pending: list[ImuSample | AltimeterSample] = []
        self._last_good: SlamPose | None = None
        # the start's yaw uncertainty beyond the filter's own share (EkfOptions.filter_yaw_sigma_rad): the map
        # is turned about the start by it, which the covariance sent carries (lba.gauge) and the filter does not
        self._gauge_yaw_sigma = math.sqrt(
            max(options.initial_yaw_sigma_rad**2 - options.filter_yaw_sigma_rad**2, 0.0)
        )
        self._gauge_pivot: np.ndarray | None = None
        self.reset_counter = 0
        self.counters = {
            "frames": 0,
            "bad_frames": 0,
            "reinit": 0,
            "missing_camera": 0,
            "waiting_for_position": 0,
            "waiting_for_attitude": 0,  # frame sets before the ATTITUDE samples to start from (see the class doc)
            # from the filter's counters, refreshed at each frame set
            "imu_samples": 0,
            "late_imu": 0,
            "steps_without_imu": 0,  # propagation steps on the motion model: no IMU sample close enough
            "stale_frames": 0,
            "altimeter_updates": 0,
            "matches_refused": 0,  # gated matches the 1-point RANSAC refused
            "patch_matches": 0,  # landmarks SIFT missed that their first patch found (patch_cameras)
            "frames_without_imu": 0,  # frame sets with no IMU sample in the imu_gap_s before them
            "frames_without_altimeter": 0,  # ... no altimeter range in the altimeter_gap_s before them
        }
        self.warnings: dict[str, str] = {}
        """What the status line should show now (key -> text), e.g. no IMU arriving."""
        self._last_imu_us: int | None = None
        self._last_alt_us: int | None = None

    # -- autopilot inputs ----------------------------------------------------------------------------
    def on_attitude(self, s: AttitudeSample) -> None:
        """Used for the initial attitude only (the filter estimates its own afterwards): the samples of the last
        few seconds are kept for ``start_attitude`` until the filter has a good pose (a restart starts from that)."""
        if self._last_good is None:
            self._keep(self._attitudes, s.stamp_us, s)

    def on_imu(self, s: ImuSample) -> None:
        """Hold an IMU sample for the filter (``_hold``); propagation (eqs. 1-4) happens as it needs it. Its
        gyro is also kept a few seconds, until the filter has a good pose, to carry ATTITUDE samples to the
        start (``start_attitude``)."""
        self._last_imu_us = s.stamp_us if self._last_imu_us is None else max(self._last_imu_us, s.stamp_us)
        if self._last_good is None:
            self._keep(self._gyro, s.stamp_us, np.asarray(s.gyro_rps, float))
        self._hold(s)

    def _keep(self, buf: deque[tuple[int, Any]], stamp_us: int, item: Any) -> None:
        """Append to a start buffer, dropping what is older than a start could use (its window, the frames'
        hold_s and a second's margin)."""
        buf.append((stamp_us, item))
        horizon_us = (self.options.initial_attitude_window_s + self.hold_s + 1.0) * 1e6
        while buf and buf[0][0] < stamp_us - horizon_us:
            buf.popleft()

    def on_local_position(self, s: LocalPositionSample) -> None:
        """The autopilot's position and velocity: used for the initial state only (see the class doc)."""
        self._local = s

    def on_altimeter(self, s: AltimeterSample) -> None:
        """Hold an altimeter sample for the filter (``_hold``): it updates the filter at its own stamp."""
        if np.isfinite(s.range_m) and s.range_m > 0:
            self._last_alt_us = (
                s.stamp_us if self._last_alt_us is None else max(self._last_alt_us, s.stamp_us)
            )
        self._hold(s)

    def _hold(self, s: ImuSample | AltimeterSample) -> None:
        """Keep a sample until a frame set at or after its stamp, then give it to the filter in stamp order.

        The daemon hands over every sample that arrived before a frame set is processed, so when the
        processing runs late (SIFT on a loaded machine: a few hundred ms) those include samples stamped
        after the frames' capture; given at once they would carry the filter past the capture time and
        the frames would be fused at the wrong time (``stale_frames``). Samples older than
        ``hold_s`` behind the newest go to the filter anyway (no frames: the filter keeps up)."""
        self._pending.append(s)
        if s.stamp_us - self._pending[0].stamp_us > self.hold_s * 1e6:
            self._feed(s.stamp_us - int(self.hold_s * 1e6))

    def _feed(self, until_us: int) -> None:
        """Give the filter the held samples stamped at or before ``until_us``, in stamp order."""
        due = sorted((x for x in self._pending if x.stamp_us <= until_us), key=lambda x: x.stamp_us)
        if not due:
            return
        self._pending = [x for x in self._pending if x.stamp_us > until_us]
        with _BLAS.limit(limits=1, user_api="blas"):
            for x in due:
                if isinstance(x, ImuSample):
                    self.slam.add_imu(x.stamp_us, x.accel_mps2, x.gyro_rps)
                else:
                    self.slam.add_altimeter(x.stamp_us, x.range_m)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    # -- frames -----------------------------------------------------------------------------------------
    def detect(self, frames: Mapping[str, Frame]) -> dict[str, Detections]:
        """SIFT on each usable frame of this estimator's cameras (in parallel threads for two cameras)."""
        todo: dict[str, np.ndarray] = {}
        for c in self.cameras:
            f = frames.get(c)
            if f is None:
                self.counters["missing_camera"] += 1
                continue
            m = self._models[c]
            img = f.image
            if img.ndim != 2 or img.shape != (m.height, m.width) or img.dtype not in (np.uint8, np.uint16):
                self.counters["bad_frames"] += 1
                continue
            todo[c] = img
        if self._pool is not None and len(todo) > 1:
            futs = {c: self._pool.submit(self._detectors[c].detect, img) for c, img in todo.items()}
            return {c: fu.result() for c, fu in futs.items()}
        return {c: self._detectors[c].detect(img) for c, img in todo.items()}

    def on_frames(self, frames: dict[str, Frame]) -> PoseEstimate | None:
        """Detect, then ``on_detections`` at the mean capture stamp of the set."""
        usable = {c: f for c, f in frames.items() if c in self.cameras}
        if not usable:
            return None
        stamp = int(round(np.mean([f.stamp_us for f in usable.values()])))
        return self.on_detections(stamp, self.detect(usable))

    def on_detections(self, stamp_us: int, detections: Mapping[str, Detections]) -> PoseEstimate | None:
        """One filter step from precomputed detections (the benchmark shares SIFT across modes)."""
        self.counters["frames"] += 1
        self._check_inputs(stamp_us)
        self._feed(stamp_us)
        with _BLAS.limit(limits=1, user_api="blas"):
            if not self.slam.started and (waiting := self._start(stamp_us)) is not None:
                self.counters[waiting] += 1
                return None
            pose = self.slam.process_frame(stamp_us, dict(detections))
            c = self.slam.counters
            self.counters.update(
                imu_samples=c.imu,
                late_imu=c.late_imu,
                steps_without_imu=c.steps_without_imu,
                stale_frames=c.stale_frames,
                altimeter_updates=c.altimeter_updates,
                matches_refused=c.ransac_rejected,
                patch_matches=c.patch_matches,
            )
            ekf = self.slam.ekf
            if ekf is None or not ekf.is_finite() or not np.all(np.isfinite(pose.p_world)):
                self._reinit(stamp_us)
                return None
        return self._to_estimate(pose)

    def _check_inputs(self, stamp_us: int) -> None:
        """Count and report frame sets that arrive with no recent IMU sample or altimeter range (an autopilot
        not streaming HIGHRES_IMU / RAW_IMU / SCALED_IMU or DISTANCE_SENSOR: ``deploy/README.md``)."""
        for key, last, gap_s, label, effect in (
            (
                "imu",
                self._last_imu_us,
                self.imu_gap_s,
                "IMU",
                "the filter carries on at constant velocity, its uncertainty growing",
            ),
            ("altimeter", self._last_alt_us, self.altimeter_gap_s, "ALTIMETER", "no range to hold the scale"),
        ):
            if last is not None and stamp_us - last <= gap_s * 1e6:
                if self.warnings.pop(key, None) is not None:
                    log.info("%s samples arriving again", label)
                continue
            self.counters[f"frames_without_{key}"] += 1
            text = f"NO {label}" if last is None else f"NO {label} for {(stamp_us - last) * 1e-6:.1f} s"
            if key not in self.warnings:
                log.warning("%s: %s (deploy/README.md, section 5)", text, effect)
            self.warnings[key] = text

    def _start(self, stamp_us: int) -> str | None:
        """Start the filter at ``stamp_us``; None if started, else the counter saying why not: the initial
        position unknown (``waiting_for_position``), or less than ``initial_attitude_window_s`` of ATTITUDE
        samples to average yet (``waiting_for_attitude``: a replay whose record begins with the first frames,
        at most that long after the first frame set or sample; none at all, at most ``start_wait_s``)."""
        if self._first_frame_us is None:
            self._first_frame_us = stamp_us
        lp = self._local
        dt_s = float("inf") if lp is None else (stamp_us - lp.stamp_us) * 1e-6
        if abs(dt_s) > self.max_local_position_age_s:
            lp = None
        if self._p0 is not None:
            p0 = self._p0
        elif lp is not None:
            p0 = np.asarray(lp.p_ned_m, float) + np.asarray(lp.v_ned_mps, float) * dt_s
        else:
            self.warnings["start"] = "not started: waiting for LOCAL_POSITION_NED"
            return "waiting_for_position"
        # the camera up before the autopilot streams: a start now would take the configured heading, which the
        # cameras cannot correct. (No wait for the IMU: started without it, on the motion model until it comes,
        # the filter did as well as with it, ``python -m bench ekf_start``.)
        if self._rpy0 is None and not self._attitudes:
            if stamp_us - self._first_frame_us < self.options.start_wait_s * 1e6:
                self.warnings["start"] = "not started: waiting for ATTITUDE"
                return "waiting_for_attitude"
            log.warning(
                "no ATTITUDE from the autopilot %.0f s after the first frames: starting from the IMU's gravity and "
                "the configured heading, %.1f deg, which the cameras cannot correct",
                self.options.start_wait_s,
                math.degrees(self._yaw0),
            )
        window_us = self.options.initial_attitude_window_s * 1e6
        if (
            self._rpy0 is None
            and self._attitudes
            and self._attitudes[-1][0] - self._attitudes[0][0] < window_us
            and stamp_us - max(self._first_frame_us, self._attitudes[0][0]) < window_us
        ):
            self.warnings["start"] = f"not started: waiting for {window_us * 1e-6:g} s of ATTITUDE"
            return "waiting_for_attitude"
        self.warnings.pop("start", None)
        if self._v0 is not None:
            v0 = self._v0
        else:
            v0 = np.zeros(3) if lp is None else np.asarray(lp.v_ned_mps, float)
        rpy = self._rpy0
        if rpy is None:
            rpy = start_attitude(
                [a for _, a in self._attitudes], self._gyro, stamp_us, self.options.initial_attitude_window_s
            )
        if rpy is None:
            imu = self.slam.latest_imu()
            rpy = (
                _attitude_from_gravity(imu[0], self._yaw0)
                if imu is not None
                else np.array([0, 0, self._yaw0])
            )
        q = quat_from_rot(rot_from_rpy(*rpy))
        self.slam.start(stamp_us, p0, v0, q)
        if self._gauge_pivot is None:  # a restart keeps the first start's turn: the yaw error since stays
            self._gauge_pivot = np.asarray(p0, float).copy()
        return None

    def _reinit(self, stamp_us: int) -> None:
        """Restart the filter at the last good pose (landmarks dropped) and bump reset_counter."""
        self.counters["reinit"] += 1
        self.reset_counter += 1
        good = self._last_good
        self.slam = self.slam.restarted()
        if good is None:
            self._start(stamp_us)
        else:
            self.slam.start(stamp_us, good.p_world, good.v_world, quat_from_rot(rot_from_rpy(*good.rpy_rad)))

    def _to_estimate(self, pose: SlamPose) -> PoseEstimate:
        o = self.options
        matched = sum(pose.matched.values())
        tracked = sum(pose.n_landmarks.values())
        if self._estimates == 0:  # the filter's first frame set (after any waiting for the start's inputs)
            status = EstimateStatus.INITIALISING
        elif (
            pose.frames_since_match >= o.lost_after_frames
            or pose.position_sigma_max_m > o.lost_position_sigma_m
        ):
            status = EstimateStatus.LOST
        else:
            status = EstimateStatus.OK
        if status is EstimateStatus.OK:
            self._last_good = pose
        c = self.slam.counters
        cov = pose.covariance
        self._estimates += 1
        if self._gauge_yaw_sigma > 0 and self._gauge_pivot is not None:
            cov = cov + gauge_covariance(pose.p_world, self._gauge_pivot, 0.0, self._gauge_yaw_sigma)
        return PoseEstimate(
            stamp_us=pose.stamp_us,
            p_body_in_world_m=pose.p_world,
            rpy_rad=pose.rpy_rad,
            covariance=cov,
            reset_counter=self.reset_counter,
            quality=float(matched / max(tracked, 1)),
            status=status,
            info={
                "matched": pose.matched,
                "landmarks": pose.n_landmarks,
                "position_sigma_m": pose.position_sigma_max_m,
                "altimeter_updates": c.altimeter_updates,
                "stale_frames": c.stale_frames,
                "late_imu": c.late_imu,
            },
        )


@dataclass(frozen=True)
class SequenceResult:
    """Estimates of an offline run, one row per frame set.

    stamp_us: (F,) int64; p_world: (F,3); rpy_rad: (F,3); covariance: (F,6,6); status: list of str;
    matched: (F,) visual matches used; seconds: wall time spent in the estimator (frames only).
    """

    stamp_us: np.ndarray
    p_world: np.ndarray
    rpy_rad: np.ndarray
    covariance: np.ndarray
    status: list[str]
    matched: np.ndarray
    seconds: float
    counters: dict


def run_sequence(
    estimator: VisThermalEkfEstimator,
    imu: Iterable[ImuSample],
    altimeter: Iterable[AltimeterSample],
    frames: Iterable[tuple[int, Mapping[str, Frame | Detections]]],
) -> SequenceResult:
    """Feed a recorded flight to ``estimator`` in time order and collect its estimates.

    frames: (stamp_us, {camera: Frame or Detections}) in increasing stamp order. Samples stamped at or
    before a frame reach the estimator before it (the daemon sees the same when the IMU is on time).
    """
    events: list[tuple[int, int, object]] = []
    events += [(s.stamp_us, 0, s) for s in imu]
    events += [(s.stamp_us, 1, s) for s in altimeter]
    events += [(int(t), 2, fs) for t, fs in frames]
    events.sort(key=lambda e: (e[0], e[1]))
    rows: list[PoseEstimate] = []
    spent = 0.0
    for stamp, kind, obj in events:
        if kind == 0:
            estimator.on_imu(obj)  # type: ignore[arg-type]
        elif kind == 1:
            estimator.on_altimeter(obj)  # type: ignore[arg-type]
        else:
            fs = dict(obj)  # type: ignore[call-overload]
            t0 = time.perf_counter()
            if fs and all(isinstance(v, Detections) for v in fs.values()):
                est = estimator.on_detections(stamp, fs)
            else:
                est = estimator.on_frames(fs)
            spent += time.perf_counter() - t0
            if est is not None:
                rows.append(est)
    n = len(rows)
    return SequenceResult(
        stamp_us=np.array([r.stamp_us for r in rows], dtype=np.int64),
        p_world=np.array([r.p_body_in_world_m for r in rows]).reshape(n, 3),
        rpy_rad=np.array([r.rpy_rad for r in rows]).reshape(n, 3),
        covariance=np.array([r.covariance for r in rows]).reshape(n, 6, 6),
        status=[r.status.value for r in rows],
        matched=np.array([sum(r.info["matched"].values()) for r in rows], dtype=int),
        seconds=spent,
        counters={"estimator": dict(estimator.counters), "slam": vars(estimator.slam.counters).copy()},
    )
