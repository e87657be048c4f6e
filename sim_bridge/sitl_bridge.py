"""The camera for a real SITL autopilot (ArduPilot or PX4): read the vehicle's pose over MAVLink, render
the nadir frame at that pose over a built-in scene, publish it on Zenoh as the companion expects.

Three processes on one host: the SITL (flies the vehicle, with GPS), this bridge (the camera), and
``companion run`` (the estimator, on its own MAVLink connection to the SITL). The bridge holds a
separate MAVLink connection (``companion.io.transport`` + ``MavCodec``): it introduces itself as a
camera (MAV_COMP_ID_CAMERA), asks the autopilot for ATTITUDE and LOCAL_POSITION_NED at
``stream_rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL, honoured per link by ArduPilot and PX4) and keeps the
latest of each. With GPS the SITL's local NED is the truth the camera renders from. It also sends the
autopilot a downward DISTANCE_SENSOR measured to the scene (the SITL's own rangefinder sees its flat
ground), which the autopilot relays to the companion when RNGFND1_TYPE = 10 (MAVLink).

Frames of reference. The SITL's local NED (origin = its EKF origin, at the take-off point in practice,
z = 0 on the take-off ground) is laid onto the scene: the SITL origin goes to scene (N, E) =
``offset_ne_m`` (default the scene centre) and heights are shifted so that the SITL's take-off ground is
the scene's ground under that point: ``p_scene = p_sitl + (off_n, off_e, -h_ground)``. The degraded DEM
the bridge writes for the companion is expressed in the SITL frame (shifted back by the same offset), so
the companion's VISION_POSITION_ESTIMATE is in the autopilot's own local frame.

Clocks. A frame is stamped with its capture time in the companion clock (Unix microseconds,
``wall_clock_us``): the instant whose pose it shows. Pose samples are taken as valid when they
arrive (loopback, well under a millisecond) and extrapolated to the capture instant with the reported
velocity and body rates (at most ``max_extrapolation_s``). The autopilot's ``time_boot_ms`` counts from
its own boot: with the SITL at speedup 1 on the same host, ``wall_us ~= time_boot_ms * 1000 +
(wall time of the SITL's start)``, but the bridge needs no such mapping (both processes read the same
host clock); it uses ``time_boot_ms`` only to drop reordered samples and to notice a SITL restart.
The companion maps its estimates into the autopilot clock itself, through TIMESYNC.
"""

from __future__ import annotations

import json
import logging
import math
import shlex
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from scipy.spatial.transform import Rotation

from companion.geometry import CameraIntrinsics, camera_pose, rot_from_rpy
from companion.georef.dem import Dem
from companion.io.frames import encode_image
from companion.io.mavlink import MavCodec, wall_clock_us
from companion.io.transport import Transport, open_transport

log = logging.getLogger(__name__)

# Frame-skip reasons (counter keys).
NO_POSE: Final = "no_pose"
"""No ATTITUDE + LOCAL_POSITION_NED from the autopilot yet."""
STALE_POSE: Final = "stale_pose"
"""The latest pose is older than ``max_pose_age_s`` (link lost, SITL paused)."""
LATE: Final = "late"
"""Capture slots skipped because rendering could not keep up with the camera rate."""


@dataclass(frozen=True)
class SitlCameraOptions:
    """Settings of the SITL camera bridge. Distances in metres, rates in Hz."""

    mavlink: str = "udpin:0.0.0.0:14551"
    """The bridge's own MAVLink connection to the SITL (companion.io.transport string)."""
    scene_id: str = "08"
    """Built-in scene (sim_bridge.terrain, "01".."09")."""
    seed: int = 0
    scene_size_m: float = 600.0
    scene_cell_m: float = 0.25
    offset_ne_m: tuple[float, float] = (0.0, 0.0)
    """Scene (N, E) where the SITL's local origin is placed (scene centre = (0, 0))."""
    camera_rate_hz: float = 10.0
    camera_key: str = "uav/camera/nadir"
    width: int = 480
    height: int = 480
    focal_mm: float = 36.0
    sensor_mm: float = 36.0
    """480 px, 36/36 mm: paper 1's 53.13 deg camera (the companion's configs/sim_mars.toml)."""
    noise: bool = True
    """Sensor noise in the rendered frames (sim_bridge.render.SensorNoise defaults)."""
    rangefinder_hz: float = 20.0
    """DISTANCE_SENSOR (downward, range to the SCENE along body down) sent to the autopilot; 0 = off. The
    SITL's own rangefinder sees its flat ground, not the scene: set RNGFND1_TYPE = 10 (MAVLink) so the
    autopilot uses and relays this one (deploy/SITL.md)."""
    range_min_m: float = 0.2
    range_max_m: float = 150.0
    stream_rate_hz: float = 50.0
    """ATTITUDE and LOCAL_POSITION_NED rate asked of the autopilot (0: do not ask; rely on its SRx_ / streams)."""
    request_period_s: float = 5.0
    """The interval request is repeated this often (a SITL restart forgets it)."""
    sysid: int = 1
    """Our system id: the vehicle's."""
    compid: int = mavlink2.MAV_COMP_ID_CAMERA
    autopilot_sysid: int | None = None
    """Autopilot to follow; None = the first one whose HEARTBEAT is heard."""
    max_pose_age_s: float = 0.5
    max_extrapolation_s: float = 0.1
    reboot_backstep_ms: int = 1000
    """time_boot_ms going back by more than this = the SITL restarted (smaller: a reordered datagram)."""
    read_timeout_s: float = 0.01


@dataclass(frozen=True)
class VehiclePose:
    """The autopilot's latest state in its local NED frame; stamps in the companion clock (arrival)."""

    att_stamp_us: int
    rpy_rad: np.ndarray
    omega_body_rps: np.ndarray
    pos_stamp_us: int
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray

    def at(self, t_us: int, max_extrapolation_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(R_world_body, p_body_in_world) extrapolated to ``t_us`` (constant velocity / body rates)."""
        dt_att = float(np.clip((t_us - self.att_stamp_us) * 1e-6, 0.0, max_extrapolation_s))
        dt_pos = float(np.clip((t_us - self.pos_stamp_us) * 1e-6, 0.0, max_extrapolation_s))
        R = rot_from_rpy(*self.rpy_rad) @ Rotation.from_rotvec(self.omega_body_rps * dt_att).as_matrix()
        return R, self.p_ned_m + self.v_ned_mps * dt_pos


@dataclass(frozen=True)
class SceneMapping:
    """SITL local NED -> scene NED: ``p_scene = p_sitl + offset_ned_m`` (no rotation: both are NED)."""

    offset_ned_m: np.ndarray

    @staticmethod
    def for_scene(dem: Dem, offset_ne_m: tuple[float, float] = (0.0, 0.0)) -> SceneMapping:
        """SITL origin at scene (N, E) = offset, its take-off ground (z = 0) on the scene's ground there."""
        n, e = float(offset_ne_m[0]), float(offset_ne_m[1])
        ground = float(dem.filled().height_at(n, e)[0])
        if not math.isfinite(ground):
            raise ValueError(f"scene offset ({n:.1f}, {e:.1f}) m is outside the scene")
        return SceneMapping(np.array([n, e, -ground]))

    def to_scene(self, p_sitl_ned: np.ndarray) -> np.ndarray:
        return np.asarray(p_sitl_ned, dtype=float) + self.offset_ned_m

    def dem_in_sitl_frame(self, dem: Dem) -> Dem:
        """The same terrain with its placement and heights expressed in the SITL's local frame."""
        n, e, d = self.offset_ned_m
        return Dem(
            (dem.height_m + np.float32(d)).astype(np.float32), dem.north0_m - n, dem.east0_m - e, dem.cell_m
        )


@dataclass
class BridgeCounters:
    """What the bridge did (read by ``status()``)."""

    frames: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    off_scene: int = 0
    """Frames whose nadir point was outside the scene (rendered anyway: partly black)."""
    received: dict[str, int] = field(default_factory=dict)
    """MAVLink messages received from the followed autopilot, by type."""
    reordered: int = 0
    non_finite: int = 0
    """ATTITUDE / LOCAL_POSITION_NED with NaN or inf (ignored)."""
    sitl_restarts: int = 0
    interval_requests: int = 0
    ranges_sent: int = 0
    render_s_total: float = 0.0

    def skip(self, reason: str, n: int = 1) -> None:
        self.skipped[reason] = self.skipped.get(reason, 0) + n


class SitlCameraBridge:
    """MAVLink pose in, rendered frames out. ``start()`` the MAVLink side, ``run()`` the camera, ``stop()``.

    session: an open Zenoh session to publish on. scene: a sim_bridge.terrain.Scene (None: make
    ``options.scene_id``). clock_us: the companion clock (Unix us).
    """

    def __init__(
        self,
        session: Any,
        options: SitlCameraOptions | None = None,
        scene: Any = None,
        clock_us: Callable[[], int] = wall_clock_us,
        transport: Transport | None = None,
    ) -> None:
        from sim_bridge.render import SensorNoise, VisibleRenderer
        from sim_bridge.terrain import make_scene

        self.options = opts = options or SitlCameraOptions()
        if not opts.camera_rate_hz > 0:
            raise ValueError(f"camera rate must be > 0, got {opts.camera_rate_hz}")
        self.scene = scene or make_scene(
            opts.scene_id, seed=opts.seed, cell_m=opts.scene_cell_m, size_m=opts.scene_size_m
        )
        self.mapping = SceneMapping.for_scene(self.scene.dem, opts.offset_ne_m)
        self.intrinsics = CameraIntrinsics.from_focal_sensor(
            opts.width, opts.height, opts.focal_mm, opts.sensor_mm
        )
        self.renderer = VisibleRenderer(
            self.scene.dem,
            self.scene.albedo,
            self.scene.sun,
            self.intrinsics,
            noise=SensorNoise(seed=opts.seed) if opts.noise else None,
        )
        self.clock_us = clock_us
        self.transport = transport or open_transport(opts.mavlink)
        self.codec = MavCodec(opts.sysid, opts.compid)
        self.counters = BridgeCounters()
        self._publisher = session.declare_publisher(opts.camera_key)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.autopilot: tuple[int, int] | None = (
            None if opts.autopilot_sysid is None else (opts.autopilot_sysid, mavlink2.MAV_COMP_ID_AUTOPILOT1)
        )
        self.autopilot_type: str = ""
        self.origin_lla: tuple[float, float, float] | None = None
        """The autopilot's GPS_GLOBAL_ORIGIN (deg, deg, m) once heard."""
        self._att: tuple[int, int, np.ndarray, np.ndarray] | None = None  # (boot_ms, stamp_us, rpy, omega)
        self._pos: tuple[int, int, np.ndarray, np.ndarray] | None = None  # (boot_ms, stamp_us, p, v)
        self._last_boot_ms: int | None = None
        self._next_heartbeat = 0.0
        self._next_request = 0.0
        self._next_range = 0.0
        self._t0_mono = time.monotonic()

    # --- pose ---------------------------------------------------------------------------------------
    def pose(self) -> VehiclePose | None:
        """The latest attitude and position (None until both have arrived)."""
        with self._lock:
            att, pos = self._att, self._pos
        if att is None or pos is None:
            return None
        return VehiclePose(att[1], att[2], att[3], pos[1], pos[2], pos[3])

    def camera_pose_at(self, pose: VehiclePose, t_us: int) -> tuple[np.ndarray, np.ndarray]:
        """(R_world_cam, p_cam_in_world) in the SCENE frame for the vehicle pose extrapolated to ``t_us``."""
        R_wb, p_sitl = pose.at(t_us, self.options.max_extrapolation_s)
        return camera_pose(R_wb, self.mapping.to_scene(p_sitl))

    # --- MAVLink side ---------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the MAVLink I/O thread (idempotent)."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._mavlink_loop, name="sitl-mavlink", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the camera loop and the MAVLink thread; close the MAVLink transport."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        self.transport.close()

    @property
    def stopped(self) -> bool:
        """Whether ``stop()`` was called."""
        return self._stop.is_set()

    def close(self) -> None:
        """``stop()`` and undeclare the Zenoh publisher."""
        self.stop()
        self._publisher.undeclare()

    def _send(self, msg: Any) -> None:
        self.transport.write(self.codec.encode(msg))

    def _mavlink_loop(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.transport.read(self.options.read_timeout_s)
                if data:
                    for msg in self.codec.decode(data):
                        self._handle(msg)
                self._periodic()
            except Exception:  # noqa: BLE001 - the camera's link must survive anything; logged
                log.exception("sitl bridge: MAVLink loop error")
                time.sleep(self.options.read_timeout_s)

    def range_to_scene(self, R_world_body: np.ndarray, p_sitl_ned: np.ndarray) -> float | None:
        """Distance (m) along body down from the vehicle to the scene's true surface; None beyond range_max_m.

        Samples the ray every 0.25 m (one vectorised DEM lookup) and interpolates the crossing linearly.
        """
        opts = self.options
        origin = self.mapping.to_scene(p_sitl_ned)
        t = np.arange(0.0, opts.range_max_m + 0.25, 0.25)
        pts = origin[None, :] + t[:, None] * R_world_body[:, 2][None, :]
        above = -pts[:, 2] - self.scene.dem.height_at(pts[:, 0], pts[:, 1])  # NaN off the scene
        below = np.flatnonzero(~(above > 0.0))  # first sample at / under the ground (or off the scene)
        if below.size == 0 or not np.isfinite(above[below[0]]):
            return None
        i = int(below[0])
        if i == 0:
            return 0.0
        a0, a1 = float(above[i - 1]), float(above[i])
        return float(t[i - 1] + (t[i] - t[i - 1]) * a0 / (a0 - a1))

    def _send_range(self) -> None:
        opts = self.options
        pose = self.pose()
        if pose is None:
            return
        R, p = pose.at(self.clock_us(), opts.max_extrapolation_s)
        rng = self.range_to_scene(R, p)
        min_cm, max_cm = int(opts.range_min_m * 100), int(opts.range_max_m * 100)
        dist_cm = max_cm + 1 if rng is None else max(0, int(round(rng * 100)))  # > max: out of range
        self._send(
            self.codec.mav.distance_sensor_encode(
                int((time.monotonic() - self._t0_mono) * 1000) % (1 << 32),
                min_cm,
                max_cm,
                min(dist_cm, 65535),
                mavlink2.MAV_DISTANCE_SENSOR_LASER,
                0,
                mavlink2.MAV_SENSOR_ROTATION_PITCH_270,
                255,
            )
        )
        self.counters.ranges_sent += 1

    def _periodic(self) -> None:
        opts, mav = self.options, self.codec.mav
        mono = time.monotonic()
        if opts.rangefinder_hz > 0 and mono >= self._next_range:
            period = 1.0 / opts.rangefinder_hz
            self._next_range = (
                self._next_range + period if mono - self._next_range < period else mono + period
            )
            self._send_range()
        if mono >= self._next_heartbeat:
            self._next_heartbeat = mono + 1.0
            self._send(
                mav.heartbeat_encode(
                    mavlink2.MAV_TYPE_CAMERA, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0, mavlink2.MAV_STATE_ACTIVE
                )
            )
        if self.autopilot is not None and opts.stream_rate_hz > 0 and mono >= self._next_request:
            self._next_request = mono + opts.request_period_s
            interval_us = 1e6 / opts.stream_rate_hz
            for msg_id in (mavlink2.MAVLINK_MSG_ID_ATTITUDE, mavlink2.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
                self._send(
                    mav.command_long_encode(
                        self.autopilot[0],
                        self.autopilot[1],
                        mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
                        0,
                        float(msg_id),
                        float(interval_us),
                        0,
                        0,
                        0,
                        0,
                        0,
                    )
                )
            if self.origin_lla is None:  # the EKF origin, for the companion's command line
                self._send(
                    mav.command_long_encode(
                        self.autopilot[0],
                        self.autopilot[1],
                        mavlink2.MAV_CMD_REQUEST_MESSAGE,
                        0,
                        float(mavlink2.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN),
                        0,
                        0,
                        0,
                        0,
                        0,
                        0,
                    )
                )
            self.counters.interval_requests += 1

    def _handle(self, msg: Any) -> None:
        name = msg.get_type()
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if name == "HEARTBEAT" and msg.autopilot != mavlink2.MAV_AUTOPILOT_INVALID:
            if self.autopilot is None:
                self.autopilot = src
                self._next_request = 0.0
            if src == self.autopilot and not self.autopilot_type:
                names = {mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA: "ArduPilot", mavlink2.MAV_AUTOPILOT_PX4: "PX4"}
                self.autopilot_type = names.get(msg.autopilot, f"autopilot type {msg.autopilot}")
                log.info("following %s, system %d component %d", self.autopilot_type, *src)
        if src != self.autopilot:
            return
        self.counters.received[name] = self.counters.received.get(name, 0) + 1
        now_us = self.clock_us()
        if name == "ATTITUDE":
            boot_ms = int(msg.time_boot_ms)
            rpy = np.array([msg.roll, msg.pitch, msg.yaw], float)
            omega = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], float)
            if not (np.all(np.isfinite(rpy)) and np.all(np.isfinite(omega))):
                self.counters.non_finite += 1
            elif self._fresh(boot_ms, 0):
                with self._lock:
                    self._att = (boot_ms, now_us, rpy, omega)
        elif name == "LOCAL_POSITION_NED":
            boot_ms = int(msg.time_boot_ms)
            p = np.array([msg.x, msg.y, msg.z], float)
            v = np.array([msg.vx, msg.vy, msg.vz], float)
            if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v))):
                self.counters.non_finite += 1
            elif self._fresh(boot_ms, 1):
                with self._lock:
                    self._pos = (boot_ms, now_us, p, v)
        elif name == "GPS_GLOBAL_ORIGIN":
            self.origin_lla = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)

    def _fresh(self, boot_ms: int, which: int) -> bool:
        """Whether a sample is newer than the last of its kind; resets the pose on a SITL restart."""
        with self._lock:
            last = (self._att, self._pos)[which]
        if self._last_boot_ms is not None and boot_ms + self.options.reboot_backstep_ms < self._last_boot_ms:
            log.warning("autopilot clock went back %d ms: SITL restarted", self._last_boot_ms - boot_ms)
            self.counters.sitl_restarts += 1
            with self._lock:
                self._att = self._pos = None
            self._last_boot_ms = boot_ms
            self._next_request = 0.0  # ask for the streams again
            return True
        if last is not None and boot_ms < last[0]:
            self.counters.reordered += 1
            return False
        self._last_boot_ms = max(boot_ms, self._last_boot_ms or 0)
        return True

    # --- camera side ----------------------------------------------------------------------------------
    def wait_pose(self, timeout_s: float) -> VehiclePose | None:
        """Block until the first pose arrived (or timeout); returns it or None."""
        end = time.monotonic() + timeout_s
        while not self._stop.is_set():
            pose = self.pose()
            if pose is not None or time.monotonic() >= end:
                return pose
            time.sleep(0.01)
        return None

    def run(
        self,
        duration_s: float = 0.0,
        progress: Callable[[dict[str, Any]], None] | None = None,
        progress_period_s: float = 2.0,
    ) -> dict[str, Any]:
        """Render and publish frames at the camera rate until ``stop()`` (or ``duration_s`` > 0 elapsed).

        Capture slots are ``t0 + k / camera_rate``; a slot that has passed before its frame could be
        started is skipped and counted (a frame is never stamped late). Returns ``status()``.
        """
        opts = self.options
        period_us = int(round(1e6 / opts.camera_rate_hz))
        t0 = self.clock_us()
        end_us = t0 + int(duration_s * 1e6) if duration_s > 0 else None
        next_progress = time.monotonic() + progress_period_s
        k = 0
        while not self._stop.is_set():
            # first slot not yet passed (a quarter period of grace: the loop's own overhead is not a miss)
            due = -(-(self.clock_us() - t0 - period_us // 4) // period_us)
            if due > k:
                self.counters.skip(LATE, int(due - k))
                k = int(due)
            capture_us = t0 + k * period_us
            k += 1
            if end_us is not None and capture_us > end_us:
                break
            wait_s = (capture_us - self.clock_us()) * 1e-6
            if wait_s > 0 and self._stop.wait(wait_s):
                break
            self._capture(capture_us, k)
            if progress is not None and time.monotonic() >= next_progress:
                next_progress += progress_period_s
                progress(self.status())
        return self.status()

    def _capture(self, capture_us: int, k: int) -> None:
        pose = self.pose()
        if pose is None:
            self.counters.skip(NO_POSE)
            return
        age_s = (capture_us - min(pose.att_stamp_us, pose.pos_stamp_us)) * 1e-6
        if age_s > self.options.max_pose_age_s:
            self.counters.skip(STALE_POSE)
            return
        R_wc, p_c = self.camera_pose_at(pose, capture_us)
        if not self.scene.dem.contains(p_c[0], p_c[1]):
            self.counters.off_scene += 1
        t = time.perf_counter()
        image = self.renderer.render(R_wc, p_c, seed=k)
        self.counters.render_s_total += time.perf_counter() - t
        self._publisher.put(encode_image(image, capture_us, frame_id="nadir_camera", encoding="mono8"))
        self.counters.frames += 1

    def status(self) -> dict[str, Any]:
        """JSON-able counters and the latest pose (SITL frame) with its height above the scene ground."""
        c = self.counters
        pose = self.pose()
        out: dict[str, Any] = {
            "autopilot": self.autopilot_type or None,
            "frames": c.frames,
            "skipped": dict(c.skipped),
            "off_scene": c.off_scene,
            "received": dict(c.received),
            "reordered": c.reordered,
            "non_finite": c.non_finite,
            "sitl_restarts": c.sitl_restarts,
            "ranges_sent": c.ranges_sent,
            "render_ms_mean": round(1000 * c.render_s_total / c.frames, 1) if c.frames else None,
            "link": {"connected": self.transport.stats.connected, "bytes_in": self.transport.stats.bytes_in},
        }
        if pose is not None:
            p_scene = self.mapping.to_scene(pose.p_ned_m)
            ground = float(self.scene.dem.height_at(p_scene[0], p_scene[1])[0])
            out["p_ned_m"] = [round(float(v), 2) for v in pose.p_ned_m]
            out["yaw_deg"] = round(math.degrees(float(pose.rpy_rad[2])), 1)
            out["speed_mps"] = round(float(np.linalg.norm(pose.v_ned_mps)), 2)
            out["agl_m"] = round(float(-p_scene[2] - ground), 1) if math.isfinite(ground) else None
        return out

    # --- files and the companion command line --------------------------------------------------------
    def write_dem(
        self, path: str | Path, factor: int = 4, noise_sigma_m: float = 0.3, hole_fraction: float = 0.01
    ) -> Path:
        """Write the companion's DEM: the scene degraded (sim_bridge.terrain.degrade_dem), in the SITL frame."""
        from companion.io.dem_store import save_dem_npz
        from sim_bridge.terrain import degrade_dem

        dem, _ = degrade_dem(
            self.scene.dem,
            factor=factor,
            noise_sigma_m=noise_sigma_m,
            hole_fraction=hole_fraction,
            seed=self.options.seed + 7,
        )
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        save_dem_npz(out, self.mapping.dem_in_sitl_frame(dem))
        return out


def companion_command(
    bridge: SitlCameraBridge,
    dem_path: str | Path,
    companion_mavlink: str,
    zenoh_connect: list[str],
    config: str = "configs/sim_mars.toml",
    planet: str = "earth",
    pose: VehiclePose | None = None,
    python: str = "python",
) -> list[str]:
    """The ``companion run`` argv matching this bridge: its DEM, camera key, Zenoh endpoint, scene sun, the
    companion's own MAVLink connection and (given a pose) the vehicle's current position and yaw."""
    from sim_bridge.terrain import SCENE_SUN_DEG

    sun = SCENE_SUN_DEG[bridge.scene.scene_id] if bridge.scene.scene_id in SCENE_SUN_DEG else None
    sets: dict[str, Any] = {
        "zenoh.connect": list(zenoh_connect),
        "zenoh.listen": [],
        "mavlink.connection": companion_mavlink,
        "dem.path": str(Path(dem_path).resolve()),
        "cameras.nadir.key": bridge.options.camera_key,
        "cameras.nadir.width": bridge.options.width,
        "cameras.nadir.height": bridge.options.height,
        "cameras.nadir.focal_mm": bridge.options.focal_mm,
        "cameras.nadir.sensor_mm": bridge.options.sensor_mm,
        "origin.planet": planet,
    }
    if bridge.origin_lla is not None:
        lat, lon, alt = bridge.origin_lla
        sets.update(
            {"origin.lat_deg": round(lat, 7), "origin.lon_deg": round(lon, 7), "origin.alt_m": round(alt, 3)}
        )
    if sun is not None:
        sets.update({"sun.intensity": sun[0], "sun.azimuth_deg": sun[1], "sun.elevation_deg": sun[2]})
    if pose is not None:
        sets["estimator.initial_position_ned_m"] = [round(float(v), 2) for v in pose.p_ned_m]
        sets["estimator.initial_yaw_deg"] = round(math.degrees(float(pose.rpy_rad[2])), 2)
    argv = [python, "-m", "companion", "run", "--config", config]
    for key, value in sets.items():
        argv += ["--set", f"{key}={json.dumps(value)}"]
    return argv


def format_command(argv: list[str]) -> str:
    """Shell-quoted, one ``--set`` per line (backslash continuations): paste into bash as it is."""
    parts = [shlex.join(argv[:6])]
    parts += [f"{argv[i]} {shlex.quote(argv[i + 1])}" for i in range(6, len(argv), 2)]
    return " \\\n    ".join(parts)


# --------------------------------------------------------------------------------------------------------
# command line (``python -m sim_bridge sitl-camera``; sim_bridge.cli registers it)


def add_sitl_camera_parser(sub: Any) -> None:
    """The ``sitl-camera`` subcommand."""
    from sim_bridge.recording import add_zenoh_args
    from sim_bridge.terrain import SCENE_IDS

    d = SitlCameraOptions()
    p = sub.add_parser(
        "sitl-camera",
        help="nadir camera for an ArduPilot / PX4 SITL: its pose over MAVLink -> rendered frames on Zenoh",
        description="Render the nadir camera at the pose a SITL autopilot reports (LOCAL_POSITION_NED + "
        "ATTITUDE) over a built-in scene and publish it on Zenoh; write the scene's degraded DEM and print "
        "the companion command line to run next. See deploy/SITL.md.",
    )
    p.add_argument(
        "--mavlink",
        default=d.mavlink,
        help="the bridge's own connection to the SITL, e.g. udpin:0.0.0.0:14551 (MAVProxy --out), "
        "tcp:127.0.0.1:5762 (ArduPilot SERIAL1), udpin:0.0.0.0:14550 (PX4 GCS link) (default %(default)s)",
    )
    p.add_argument("--scene", default=d.scene_id, choices=list(SCENE_IDS), help="built-in scene")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--scene-size", type=float, default=d.scene_size_m, help="m (default %(default)s)")
    p.add_argument("--offset-north", type=float, default=0.0, help="scene N (m) of the SITL origin")
    p.add_argument("--offset-east", type=float, default=0.0, help="scene E (m) of the SITL origin")
    p.add_argument("--camera-rate", type=float, default=d.camera_rate_hz, help="Hz (default %(default)s)")
    p.add_argument("--camera-key", default=d.camera_key)
    p.add_argument("--stream-rate", type=float, default=d.stream_rate_hz, help="pose rate asked of the SITL")
    p.add_argument(
        "--rangefinder-rate",
        type=float,
        default=d.rangefinder_hz,
        help="DISTANCE_SENSOR to the scene sent to the SITL, Hz; 0 = off (default %(default)s)",
    )
    p.add_argument("--no-noise", action="store_true", help="render without sensor noise")
    p.add_argument("--duration", type=float, default=0.0, help="seconds; 0 = until Ctrl-C (default)")
    p.add_argument("--wait-pose", type=float, default=30.0, help="s to wait for the first pose")
    p.add_argument("--out", default="runs/sitl", help="directory for dem.npz (default %(default)s)")
    p.add_argument("--companion-config", default="configs/sim_mars.toml", help="config the command uses")
    p.add_argument(
        "--companion-mavlink",
        default="tcp:127.0.0.1:5763",
        help="the companion's own connection to the SITL, put in the printed command "
        "(default %(default)s: ArduPilot SITL SERIAL2; PX4 SITL: udpin:0.0.0.0:14540)",
    )
    p.add_argument("--planet", default="earth", choices=["earth", "mars", "moon", "europa"])
    p.add_argument(
        "--hover-agl",
        type=float,
        default=10.0,
        help="re-print the command once the vehicle hovers (< 0.5 m/s) above this height (default %(default)s m)",
    )
    add_zenoh_args(p, listen=["tcp/127.0.0.1:7447"])
    p.set_defaults(func=cmd_sitl_camera)


def cmd_sitl_camera(a: Any) -> int:
    """``python -m sim_bridge sitl-camera``: 0 on a clean stop, 2 on a bad argument."""
    import signal
    import sys

    from sim_bridge.recording import open_zenoh_from_args

    opts = SitlCameraOptions(
        mavlink=a.mavlink,
        scene_id=a.scene,
        seed=a.seed,
        scene_size_m=a.scene_size,
        offset_ne_m=(a.offset_north, a.offset_east),
        camera_rate_hz=a.camera_rate,
        camera_key=a.camera_key,
        noise=not a.no_noise,
        stream_rate_hz=a.stream_rate,
        rangefinder_hz=a.rangefinder_rate,
    )
    print(f"scene {a.scene}: generating terrain ({a.scene_size:g} m) ...", flush=True)
    session = open_zenoh_from_args(a)
    try:
        bridge = SitlCameraBridge(session, opts)
    except ValueError as exc:
        print(f"sitl-camera: {exc}")
        session.close()
        return 2
    listen = a.zenoh_listen if a.zenoh_listen is not None else a._zenoh_listen_default
    connect = [ep.replace("0.0.0.0", "127.0.0.1") for ep in listen] or list(a.zenoh_connect or [])
    dem_path = bridge.write_dem(Path(a.out) / "dem.npz")
    previous = {sig: signal.signal(sig, lambda *_: bridge.stop()) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        bridge.start()
        print(f"DEM for the companion (SITL frame): {dem_path}", flush=True)
        print(f"waiting for ATTITUDE + LOCAL_POSITION_NED on {a.mavlink} ...", flush=True)
        pose = bridge.wait_pose(a.wait_pose)
        if pose is None and not bridge.stopped:
            print(
                f"no pose from the SITL after {a.wait_pose:g} s; still waiting (see deploy/SITL.md)",
                flush=True,
            )

        def command(p: VehiclePose | None) -> str:
            argv = companion_command(
                bridge,
                dem_path,
                a.companion_mavlink,
                connect,
                a.companion_config,
                a.planet,
                p,
                python=sys.executable,
            )
            return format_command(argv)

        printed = pose is not None
        if printed:
            print(f"following {bridge.autopilot_type}; run the companion with:\n{command(pose)}", flush=True)
        printed_hover = False

        def progress(st: dict[str, Any]) -> None:
            nonlocal printed, printed_hover
            agl = st.get("agl_m")
            if not printed and bridge.pose() is not None:
                printed = True
                print(f"following {bridge.autopilot_type}; run the companion with:\n{command(bridge.pose())}")
            print(
                f"  frames {st['frames']:6d}  skipped {sum(st['skipped'].values()):4d}  "
                f"NED {st.get('p_ned_m')}  yaw {st.get('yaw_deg')} deg  AGL {agl} m  "
                f"render {st['render_ms_mean']} ms",
                flush=True,
            )
            hovering = st.get("speed_mps") is not None and st["speed_mps"] < 0.5
            if not printed_hover and agl is not None and agl > a.hover_agl and hovering:
                printed_hover = True
                print(
                    f"hovering at {agl} m: a companion started now takes:\n{command(bridge.pose())}",
                    flush=True,
                )

        status = bridge.run(a.duration, progress)
    finally:
        bridge.close()
        session.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print(json.dumps({"sitl_camera": status}), flush=True)
    return 0
