"""The simulated vehicle: an ArduPilot-like autopilot and a nadir camera flying a trajectory over a
built-in terrain, in real time, on loopback.

Two worlds: ``mars`` (paper 1: one visible nadir camera over a built-in Mars scene) and ``europa`` (paper 2:
co-registered visible + thermal cameras publishing each pair with one capture stamp on two keys, over the
simulated Europa site, flying one of the ten paper trajectories; ``sim_bridge.europa.vehicle``).

- the autopilot side (``SimAutopilotLink``) sends telemetry from the truth with noise and bias, answers
  TIMESYNC, holds an EKF origin and checks every VISION_POSITION_ESTIMATE / ODOMETRY as ArduPilot would;
- the camera renders the frame at the true pose and publishes it on Zenoh as a ROS 2 ``sensor_msgs/Image``
  (CDR), stamped with its capture time;
- at the end, every accepted estimate is matched to the truth at its own timestamp (mapped back from the
  autopilot clock), and both trajectories are written in TUM format with a summary.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from companion.constants import GRAVITY_MPS2
from companion.geometry import CameraIntrinsics, camera_pose, rpy_from_rot
from companion.io.frames import encode_image
from companion.io.mavlink import urt21_to_covariance
from companion.metrics import covariance_consistency, error_stats
from sim_bridge.autopilot_link import SimAutopilotLink, SimAutopilotOptions, SimNoise, with_imu_message
from sim_bridge.trajectory import Trajectory, circular, forward, scanning

log = logging.getLogger("sim_bridge")


@dataclass(frozen=True)
class SimConfig:
    """One simulated flight. Distances in metres, rates in Hz, angles in degrees (as in the CLI)."""

    scene_id: str = "08"
    seed: int = 0
    trajectory: str = "circular"  # mars: circular | forward | scanning; europa: 1..10 (paper 2)
    duration_s: float = 120.0
    speed_mps: float = 4.0
    height_agl_m: float = 100.0
    radius_m: float = 120.0
    camera_rate_hz: float = 15.0
    camera_key: str = "uav/camera/nadir"
    world: str = "mars"  # mars | europa
    visible_key: str = "uav/camera/visible"  # europa: the pair's keys (configs/europa_dual_ekf.toml)
    thermal_key: str = "uav/camera/thermal"
    zenoh_listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    mavlink: str = "udpin:127.0.0.1:14550"
    origin_lat_lon_alt: tuple[float, float, float] | None = (18.4447, 77.4508, -2500.0)  # Jezero, Mars
    # (None: the autopilot has no EKF origin until a companion sets one, as without GNSS)
    out_dir: str = "runs/sim"
    progress_period_s: float = 2.0
    drop_every: int = 0  # publish only; skip every n-th frame (tests of dropped frames); 0 = none
    start_delay_s: float = 0.0  # autopilot up, camera silent: time for a companion to connect and sync
    wait_companion_s: float = 0.0  # before that, wait (at most this long) for a companion's HEARTBEAT
    autopilot_params: tuple[tuple[str, float], ...] = ()  # simulated autopilot parameters set by name
    compass_offset_deg: float = 0.0  # the simulated compass (ATTITUDE yaw) this far off, whole flight
    imu_message: str = "highres"  # the autopilot's IMU stream: highres (PX4) | raw (ArduPilot's default)
    # | scaled (sim_bridge.autopilot_link.IMU_MESSAGES)


WORLDS = ("mars", "europa")


def world_defaults(world: str) -> dict[str, Any]:
    """SimConfig fields whose default depends on the world (the CLI fills them when not given)."""
    d = SimConfig()
    if world == "mars":
        return {
            "trajectory": d.trajectory,
            "duration_s": d.duration_s,
            "camera_rate_hz": d.camera_rate_hz,
            "origin_lat_lon_alt": d.origin_lat_lon_alt,
        }
    if world == "europa":
        from sim_bridge.europa.trajectories import DURATION_S
        from sim_bridge.europa.vehicle import EUROPA_CAMERA_RATE_HZ

        # no GNSS on Europa: the companion sets the EKF origin from its config
        return {
            "trajectory": "1",
            "duration_s": DURATION_S,
            "camera_rate_hz": EUROPA_CAMERA_RATE_HZ,
            "origin_lat_lon_alt": None,
        }
    raise ValueError(f"unknown world {world!r} ({', '.join(WORLDS)})")


def make_trajectory(cfg: SimConfig, ground_m: float) -> Trajectory:
    """Paper 1's trajectories centred on the scene, at ``height_agl_m`` above the mean ground."""
    alt = ground_m + cfg.height_agl_m
    g = GRAVITY_MPS2["mars"]
    if cfg.trajectory == "circular":
        return circular((0.0, 0.0), cfg.radius_m, alt, cfg.speed_mps, cfg.duration_s, gravity_mps2=g)
    if cfg.trajectory == "forward":
        start = (-0.5 * cfg.speed_mps * cfg.duration_s, 0.0)
        return forward(start, 0.0, alt, cfg.speed_mps, cfg.duration_s, gravity_mps2=g)
    if cfg.trajectory == "scanning":
        return scanning((-100.0, -100.0), 200.0, 40.0, alt, cfg.speed_mps, cfg.duration_s, gravity_mps2=g)
    raise ValueError(f"unknown trajectory {cfg.trajectory!r} (circular, forward, scanning)")


@dataclass
class SimResult:
    """Truth and estimates after a flight. t_s: seconds since the flight started."""

    truth_t_s: np.ndarray
    truth_p: np.ndarray
    est_t_s: np.ndarray
    est_p: np.ndarray
    est_rpy: np.ndarray
    reset_counters: np.ndarray
    frames_published: int
    frames_skipped: int
    rejected: dict[str, int]
    duration_s: float
    """Flight time from the trajectory's start (s)."""
    est_truth_p: np.ndarray
    """(N, 3) truth at each estimate's own time (for the position errors of the summary)."""
    summary: dict[str, Any] = field(default_factory=dict)
    est_cov_ne: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    """(N, 2, 2) the horizontal covariance each accepted estimate came with (NaN: none sent)."""


def write_tum(path: Path, t_s: np.ndarray, p: np.ndarray, rpy: np.ndarray | None = None) -> None:
    """TUM trajectory: ``t x y z qx qy qz qw`` per line (here x y z = north east down)."""
    from scipy.spatial.transform import Rotation

    if rpy is None:
        q = np.tile([0.0, 0.0, 0.0, 1.0], (len(t_s), 1))
    else:
        q = Rotation.from_euler("ZYX", np.asarray(rpy)[:, ::-1]).as_quat()  # scipy quaternions are xyzw
    with open(path, "w") as f:
        for i in range(len(t_s)):
            f.write(f"{t_s[i]:.6f} " + " ".join(f"{v:.6f}" for v in (*p[i], *q[i])) + "\n")


class SimVehicle:
    """Runs one flight in real time. ``run()`` blocks until the trajectory ends or ``stop()``."""

    def __init__(self, cfg: SimConfig, progress: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.cfg = cfg
        self.progress = progress
        self._stop = threading.Event()
        self.t0_us: int | None = None
        self.frames_published = 0
        self.frames_skipped = 0
        if cfg.world == "europa":
            from sim_bridge.europa.vehicle import EUROPA_HIGHRES_IMU_HZ, EuropaFlight, europa_telemetry_noise

            self.europa = EuropaFlight(cfg.seed, cfg.trajectory)
            self.traj = self.europa.traj
            self.camera_keys: tuple[str, ...] = (cfg.visible_key, cfg.thermal_key)
            opts = SimAutopilotOptions(
                planet="europa",
                origin=cfg.origin_lat_lon_alt,
                range_max_m=250.0,
                noise=replace(europa_telemetry_noise(), yaw_offset_rad=math.radians(cfg.compass_offset_deg)),
                params=cfg.autopilot_params,
            )
            opts = with_imu_message(opts, cfg.imu_message, EUROPA_HIGHRES_IMU_HZ)
        elif cfg.world == "mars":
            from sim_bridge.render import VisibleRenderer
            from sim_bridge.terrain import make_scene

            self.scene = make_scene(cfg.scene_id, seed=cfg.seed)
            self.ground_m = float(np.nanmean(self.scene.dem.height_m))
            self.traj = make_trajectory(cfg, self.ground_m)
            self.intr = CameraIntrinsics.from_focal_sensor(480, 480, 36.0, 36.0)
            self.renderer = VisibleRenderer(self.scene.dem, self.scene.albedo, self.scene.sun, self.intr)
            self.camera_keys = (cfg.camera_key,)
            opts = SimAutopilotOptions(
                planet="mars",
                origin=cfg.origin_lat_lon_alt,
                range_max_m=max(150.0, 2 * cfg.height_agl_m),
                noise=SimNoise(yaw_offset_rad=math.radians(cfg.compass_offset_deg)),
                params=cfg.autopilot_params,
            )
            opts = with_imu_message(opts, cfg.imu_message, SimAutopilotOptions().highres_imu_hz)
        else:
            raise ValueError(f"unknown world {cfg.world!r} ({', '.join(WORLDS)})")
        # flight time: Mars trajectories are built for duration_s, Europa's (180 s) are cut at it
        self.duration_s = (
            self.traj.duration_s if cfg.world == "mars" else min(cfg.duration_s, self.traj.duration_s)
        )
        self.autopilot = SimAutopilotLink(
            cfg.mavlink, truth=self._truth, options=opts, rng=np.random.default_rng(cfg.seed + 1)
        )

    # truth for the autopilot's telemetry, in the world clock (Unix us)
    def _sim_t(self, t_us: int) -> float:
        return 0.0 if self.t0_us is None else (t_us - self.t0_us) * 1e-6

    def _truth(self, t_us: int) -> dict[str, Any]:
        s = self.traj.state_at(self._sim_t(t_us))
        R = s.R_world_body
        if self.cfg.world == "europa":
            rng_m = self.europa.range_m(s)
        else:
            rng_m = self.scene.dem.beam_range(s.p_world, R[:, 2])  # what a downward lidar reads
        return {
            "rpy_rad": rpy_from_rot(R),
            "p_ned_m": s.p_world,
            "v_ned_mps": s.v_world,
            "range_m": float(rng_m),
            "accel_body_mps2": R.T @ (s.a_world - self.traj.g_world),
            "gyro_body_rps": s.omega_body_rps,
        }

    def stop(self) -> None:
        self._stop.set()

    def run(self) -> SimResult:
        from companion.io.zenoh_io import open_session

        cfg = self.cfg
        session = open_session(
            mode="peer", connect=[], listen=list(cfg.zenoh_listen), multicast_scouting=False
        )
        publishers = [session.declare_publisher(key) for key in self.camera_keys]
        self.autopilot.start()
        # take off once a companion is heard (its heartbeat starts only when its estimator is ready)
        deadline = time.monotonic() + cfg.wait_companion_s
        while time.monotonic() < deadline and not self._stop.is_set():
            if any(compid != self.autopilot.compid for _, compid in self.autopilot.heartbeats_from):
                break
            time.sleep(0.05)
        self._stop.wait(cfg.start_delay_s)
        self.t0_us = time.time_ns() // 1000
        period_us = int(1e6 / cfg.camera_rate_hz)
        n_frames = int(self.duration_s * cfg.camera_rate_hz)
        next_progress = time.monotonic() + cfg.progress_period_s
        skipped = 0
        k = 0
        try:
            while k < n_frames and not self._stop.is_set():
                # a camera that cannot keep up skips capture slots; it never stamps a frame late
                due = (time.time_ns() // 1000 - self.t0_us + period_us - 1) // period_us
                if due > k:
                    skipped += int(min(due, n_frames) - k)
                    k = int(due)
                    if k >= n_frames:
                        break
                capture_us = self.t0_us + k * period_us
                wait_s = (capture_us - time.time_ns() // 1000) * 1e-6
                if wait_s > 0:
                    time.sleep(wait_s)
                s = self.traj.state_at(k * period_us * 1e-6)
                payloads = self._render(s, capture_us, seed=cfg.seed * 1_000_003 + k)
                k += 1
                if cfg.drop_every and k % cfg.drop_every == 0:
                    continue
                for publisher, payload in zip(publishers, payloads):
                    publisher.put(payload)
                self.frames_published += 1
                if self.progress is not None and time.monotonic() >= next_progress:
                    next_progress += cfg.progress_period_s
                    self.progress(self._progress_report(k * period_us * 1e-6))
            time.sleep(0.5)  # let the last estimates arrive
        finally:
            self.autopilot.stop()
            for publisher in publishers:
                publisher.undeclare()
            session.close()
        self.frames_skipped = skipped
        if skipped:
            log.warning(
                "camera skipped %d of %d capture slots (renderer slower than the frame rate)",
                skipped,
                n_frames,
            )
        return self._result()

    def _render(self, s: Any, capture_us: int, seed: int) -> list[bytes]:
        """The frame(s) at state ``s`` as CDR Images stamped ``capture_us``, one per ``camera_keys``."""
        if self.cfg.world == "europa":
            visible, thermal = self.europa.render(s, seed)
            # one capture stamp for the pair: the cameras are synchronised (paper 2)
            return [
                encode_image(visible, capture_us, frame_id="visible_camera", encoding="mono8"),
                encode_image(thermal, capture_us, frame_id="thermal_camera", encoding="mono16"),
            ]
        R_wc, p_c = camera_pose(s.R_world_body, s.p_world)
        image = self.renderer.render(R_wc, p_c, seed=seed)
        return [encode_image(image, capture_us, frame_id="nadir_camera", encoding="mono8")]

    def _progress_report(self, t_s: float) -> dict[str, Any]:
        recs = self.autopilot.accepted()
        err = sigma = float("nan")
        if recs:
            r = recs[-1]
            t_est = self._sim_t(self._world_us(r.usec))
            err = float(np.linalg.norm(r.p_ned_m[:2] - self.traj.state_at(t_est).p_world[:2]))
            sigma = float(np.sqrt(np.trace(_cov_ne(r.covariance))))
        return {
            "t_s": round(t_s, 1),
            "duration_s": self.duration_s,
            "frames": self.frames_published,
            "estimates": len(recs),
            "rejected": sum(self.autopilot.rejected().values()),
            "last_error_m": err,
            "last_sigma_m": sigma,  # the estimate's own horizontal 1-sigma (root of the trace)
        }

    def _world_us(self, autopilot_us: int) -> int:
        """Map an autopilot-clock time back to the world clock (the simulator knows the true offset)."""
        return int(autopilot_us - self.autopilot.true_offset_us())

    def _result(self) -> SimResult:
        recs = self.autopilot.accepted()
        t_est = np.array([self._sim_t(self._world_us(r.usec)) for r in recs])
        p_est = np.array([r.p_ned_m for r in recs]).reshape(-1, 3)
        rpy_est = np.array([r.rpy_rad for r in recs]).reshape(-1, 3)
        t_truth = np.arange(0.0, self.duration_s, 1.0 / self.cfg.camera_rate_hz)
        p_truth = np.array([s.p_world for s in self.traj.states(t_truth)])
        return SimResult(
            truth_t_s=t_truth,
            truth_p=p_truth,
            est_t_s=t_est,
            est_p=p_est,
            est_rpy=rpy_est,
            reset_counters=np.array([r.reset_counter for r in recs], int),
            frames_published=self.frames_published,
            frames_skipped=self.frames_skipped,
            rejected=self.autopilot.rejected(),
            duration_s=self.duration_s,
            est_truth_p=np.array([s.p_world for s in self.traj.states(t_est)] if len(t_est) else []).reshape(
                -1, 3
            ),
            est_cov_ne=np.array([_cov_ne(r.covariance) for r in recs]).reshape(-1, 2, 2),
        )

    def distance_m(self) -> float:
        """Path length of the flight (m)."""
        return self.traj.distance_m(self.traj.t0_s, self.traj.t0_s + self.duration_s)


def position_error_stats(res: SimResult) -> dict[str, float | int]:
    """Absolute position error (m) of the accepted estimates against the truth at their own times, no
    alignment (the estimate is in the world frame): count, mean, median, rmse, p95, max, final."""
    if not len(res.est_p):
        return {"count": 0}
    return error_stats(np.linalg.norm(res.est_p - res.est_truth_p, axis=1))


def _cov_ne(urt21: Sequence[float]) -> np.ndarray:
    """The north-east block of a MAVLink 21-element pose covariance."""
    return urt21_to_covariance(urt21)[:2, :2]


def save_result(
    res: SimResult, out_dir: Path, cfg: SimConfig, traj: Trajectory, t0_us: int | None = None
) -> dict[str, Any]:
    """Write truth.tum, estimate.tum and sim_summary.json into ``out_dir``; return the summary. With the
    flight's start on the companion's clock (``t0_us``), also truth_clock.tum: the truth at the frames'
    capture stamps (Unix s), for ``companion replay --truth-tum`` of a record of the flight."""
    out_dir.mkdir(parents=True, exist_ok=True)
    states = traj.states(res.truth_t_s)
    rpy_truth = np.array([rpy_from_rot(s.R_world_body) for s in states])
    write_tum(out_dir / "truth.tum", res.truth_t_s, res.truth_p, rpy_truth)
    if t0_us is not None:
        write_tum(out_dir / "truth_clock.tum", t0_us * 1e-6 + res.truth_t_s, res.truth_p, rpy_truth)
    write_tum(out_dir / "estimate.tum", res.est_t_s, res.est_p, res.est_rpy if len(res.est_rpy) else None)
    summary = {
        "config": asdict(cfg),
        "frames_published": res.frames_published,
        "frames_skipped": res.frames_skipped,
        "estimates_accepted": len(res.est_t_s),
        "rejected": res.rejected,
        "resets": int(res.reset_counters.max()) if len(res.reset_counters) else 0,
        "distance_m": traj.distance_m(traj.t0_s, traj.t0_s + res.duration_s),
        "position_error_m": position_error_stats(res),
        "covariance_consistency": covariance_consistency(
            res.est_p[:, :2] - res.est_truth_p[:, :2] if len(res.est_p) else np.zeros((0, 2)), res.est_cov_ne
        ),
    }
    (out_dir / "sim_summary.json").write_text(json.dumps(summary, indent=2))
    return summary
