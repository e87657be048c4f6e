"""A simulated flight written as the rosbag2 a vehicle's recorder would make (``python -m sim_bridge
flight-bag``), for ``companion replay`` and for anyone who wants a recording with a known truth.

The bag holds, all stamped in one clock (header stamp = log time):

- the camera images, ``sensor_msgs/msg/Image`` on the topics of the simulator's Zenoh keys (Europa:
  ``/uav/camera/visible`` mono8 and ``/uav/camera/thermal`` mono16 radiometric, one capture stamp per pair);
- the autopilot's IMU, ``sensor_msgs/msg/Imu`` on ``/uav/imu``: specific force and rate with the benchmark's
  IMU errors (``sim_bridge.trajectory.ImuNoise``: white noise, a bias drawn per flight and its random walk)
  and the autopilot's attitude in the orientation field (``SimNoise``: white noise and a yaw bias per flight);
- the downward range finder, ``sensor_msgs/msg/Range`` on ``/uav/range`` (``AltimeterNoise``: an offset per
  flight, noise; no return written as +inf, ROS's way);
- the vehicle's own navigation, ``nav_msgs/msg/Odometry`` on ``/uav/odometry`` (truth + ``SimNoise``'s
  local-position noise): what an estimator starts from when the vision takes over;
- the truth, ``geometry_msgs/msg/PoseStamped`` on ``/ground_truth/pose``.

Frames: ``map_ned`` / ``base_link_frd`` by default (the companion's own), or ROS's ENU / FLU with
``ned_frd=False`` (``--ros-frames enu``), converted by ``companion.io.ros_msgs``.
Deterministic for a seed: the same options write the same messages.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from companion.constants import R_BODY_CAM_NADIR
from companion.geometry import CameraIntrinsics, camera_pose, rot_from_rpy, rpy_from_rot
from companion.io import ros_msgs
from companion.io.frames import IMAGE_MSGTYPE, encode_image

START_US = 1_798_761_600_000_000
"""Stamp of the flight's first instant (2027-01-01 00:00 UTC): fixed, so a bag is the same every time."""


@dataclass(frozen=True)
class FlightBagOptions:
    """One recorded Europa flight. Rates in Hz; ``duration_s`` cuts the trajectory (180 s long)."""

    trajectory: str = "1"
    seed: int = 0
    duration_s: float = 60.0
    camera_hz: float = 2.0
    imu_hz: float = 100.0
    range_hz: float = 10.0
    odometry_hz: float = 10.0
    truth_hz: float = 20.0
    ned_frd: bool = True
    storage: str = "mcap"
    visible_topic: str = "/uav/camera/visible"
    thermal_topic: str = "/uav/camera/thermal"
    imu_topic: str = "/uav/imu"
    range_topic: str = "/uav/range"
    odometry_topic: str = "/uav/odometry"
    truth_topic: str = "/ground_truth/pose"
    distortion: tuple[float, ...] = ()
    """A lens: both cameras' images distorted with these OpenCV coefficients (k1, k2, p1, p2[, k3]) about the
    cameras' pinhole matrix, which becomes their K; () = pinhole images."""


class DistortingLens:
    """Makes a camera's raw, distorted image from a pinhole rendering: each raw pixel is undistorted with
    OpenCV's model (``cv2.undistortPoints``) and sampled in a pinhole image rendered wide enough (same focal
    length, a margin on every side) that every raw pixel sees the scene."""

    def __init__(self, K: CameraIntrinsics, distortion: tuple[float, ...]) -> None:
        d = np.asarray(distortion, float)
        Km = np.array([[K.fx, 0.0, K.cx], [0.0, K.fy, K.cy], [0.0, 0.0, 1.0]])
        u, v = np.meshgrid(np.arange(K.width, dtype=np.float64), np.arange(K.height, dtype=np.float64))
        uv = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
        x = cv2.undistortPoints(uv, Km, d).reshape(K.height, K.width, 2)  # normalised pinhole coordinates
        px, py = K.fx * x[..., 0] + K.cx, K.fy * x[..., 1] + K.cy
        m = (
            int(np.ceil(max(-px.min(), -py.min(), px.max() - (K.width - 1), py.max() - (K.height - 1), 0.0)))
            + 2
        )
        self.wide = CameraIntrinsics(K.width + 2 * m, K.height + 2 * m, K.fx, K.fy, K.cx + m, K.cy + m)
        self.map_x, self.map_y = (px + m).astype(np.float32), (py + m).astype(np.float32)

    def apply(self, wide_image: np.ndarray) -> np.ndarray:
        return cv2.remap(wide_image, self.map_x, self.map_y, cv2.INTER_LINEAR)


def _times_us(t0_s: float, t1_s: float, hz: float) -> np.ndarray:
    return (
        np.round(np.arange(t0_s, t1_s + 1e-9, 1.0 / hz) * 1e6).astype(np.int64)
        if hz > 0
        else np.zeros(0, np.int64)
    )


def write_flight_bag(
    out: str | Path, opts: FlightBagOptions | None = None, progress: Callable[[int, int], None] | None = None
) -> dict[str, Any]:
    """Fly ``opts.trajectory`` over the simulated Europa site and write the bag at ``out`` (a new directory).
    Returns a summary (messages per topic, distance flown). ``progress(pairs_done, pairs)`` while rendering.
    Raises rosbags' WriterError if ``out`` exists, ValueError on bad options."""
    from sim_bridge.europa.sensors import AltimeterNoise, altimeter_samples
    from sim_bridge.europa.vehicle import EuropaFlight, europa_telemetry_noise
    from sim_bridge.trajectory import ImuNoise, imu_samples

    o = opts or FlightBagOptions()
    if o.storage not in ("mcap", "sqlite3"):
        raise ValueError(f"storage {o.storage!r}: expected mcap or sqlite3")
    if not (o.camera_hz > 0 and o.imu_hz > 0 and o.duration_s > 0):
        raise ValueError("camera and IMU rates and the duration must be > 0")
    flight = EuropaFlight(o.seed, o.trajectory)
    traj = flight.traj
    lens = wide = None
    if o.distortion:
        from sim_bridge.europa.render import EuropaCameras

        lens = DistortingLens(flight.cameras.intrinsics, o.distortion)
        wide = EuropaCameras(flight.world, lens.wide)
    t0, t1 = traj.t0_s, min(traj.t1_s, traj.t0_s + o.duration_s)
    rng = np.random.default_rng([o.seed, int(o.trajectory), 0xBA6])
    noise = europa_telemetry_noise(o.imu_hz)
    alt_noise = AltimeterNoise()

    imu = imu_samples(traj, o.imu_hz, ImuNoise(), seed=int(rng.integers(2**31)))
    keep = imu.t_us <= round(t1 * 1e6)
    alt_t, alt_r = altimeter_samples(
        traj, flight.world, o.range_hz, alt_noise, int(rng.integers(2**31)), flight.cameras.tracer
    )
    alt_keep = alt_t <= round(t1 * 1e6)
    acc, gyr, imu_t = imu.accel_mps2[keep], imu.gyro_rps[keep], imu.t_us[keep]
    alt_t, alt_r = alt_t[alt_keep], alt_r[alt_keep]
    yaw_bias = float(rng.normal(0.0, noise.yaw_bias_rad))

    events: list[tuple[int, int, int]] = []  # (stamp us from t0, order, index): sorted, then written
    cam_t = _times_us(t0, t1, o.camera_hz)
    events += [(int(t), 0, i) for i, t in enumerate(cam_t)]
    events += [(int(t), 1, i) for i, t in enumerate(imu_t)]
    events += [(int(t), 2, i) for i, t in enumerate(alt_t)]
    odo_t = _times_us(t0, t1, o.odometry_hz)
    events += [(int(t), 3, i) for i, t in enumerate(odo_t)]
    truth_t = np.union1d(_times_us(t0, t1, o.truth_hz), cam_t)
    events += [(int(t), 4, i) for i, t in enumerate(truth_t)]
    events.sort()

    plugin = StoragePlugin.MCAP if o.storage == "mcap" else StoragePlugin.SQLITE3
    writer = Writer(Path(out), version=ros_msgs.ROSBAG_VERSION, storage_plugin=plugin)
    writer.open()
    ts = ros_msgs.TYPESTORE
    conns = {
        "visible": writer.add_connection(o.visible_topic, IMAGE_MSGTYPE, typestore=ts),
        "thermal": writer.add_connection(o.thermal_topic, IMAGE_MSGTYPE, typestore=ts),
        "imu": writer.add_connection(o.imu_topic, ros_msgs.IMU_MSGTYPE, typestore=ts),
        "range": writer.add_connection(o.range_topic, ros_msgs.RANGE_MSGTYPE, typestore=ts),
        "odometry": writer.add_connection(o.odometry_topic, ros_msgs.ODOMETRY_MSGTYPE, typestore=ts),
        "truth": writer.add_connection(o.truth_topic, ros_msgs.POSE_MSGTYPE, typestore=ts),
    }
    counts = dict.fromkeys(conns, 0)
    cam_frame = "camera_frd" if o.ned_frd else "camera"

    def put(name: str, t_us: int, payload: bytes) -> None:
        writer.write(conns[name], (START_US + t_us) * 1000, payload)
        counts[name] += 1

    try:
        for t_us, kind, i in events:
            stamp = START_US + t_us
            s = traj.state_at(t_us * 1e-6)
            if kind == 0:
                if lens is None or wide is None:
                    visible, thermal = flight.render(s, seed=o.seed * 1_000_003 + i)
                else:
                    R_wc, p_c = camera_pose(s.R_world_body, s.p_world, R_BODY_CAM_NADIR)
                    visible, thermal = (
                        lens.apply(im) for im in wide.render(R_wc, p_c, seed=o.seed * 1_000_003 + i)
                    )
                put(
                    "visible",
                    t_us,
                    encode_image(visible, stamp, frame_id=f"visible_{cam_frame}", encoding="mono8"),
                )
                put(
                    "thermal",
                    t_us,
                    encode_image(thermal, stamp, frame_id=f"thermal_{cam_frame}", encoding="mono16"),
                )
                if progress is not None:
                    progress(i + 1, len(cam_t))
            elif kind == 1:
                roll, pitch, yaw = rpy_from_rot(s.R_world_body)
                att = rot_from_rpy(
                    roll + rng.normal(0.0, noise.roll_pitch_rad),
                    pitch + rng.normal(0.0, noise.roll_pitch_rad),
                    yaw + yaw_bias + rng.normal(0.0, noise.yaw_rad),
                )
                put(
                    "imu",
                    t_us,
                    ros_msgs.imu_cdr(
                        stamp,
                        acc[i],
                        gyr[i],
                        att,
                        o.ned_frd,
                        accel_var=(ImuNoise().accel_noise_density ** 2) * o.imu_hz,
                        gyro_var=(ImuNoise().gyro_noise_density ** 2) * o.imu_hz,
                        attitude_var=noise.roll_pitch_rad**2,
                    ),
                )
            elif kind == 2:
                r = float(alt_r[i])
                put("range", t_us, ros_msgs.range_cdr(stamp, r, 0.2, alt_noise.max_range_m, o.ned_frd))
            elif kind == 3:
                p = s.p_world + rng.normal(0.0, noise.position_m, 3)
                v = s.v_world + rng.normal(0.0, noise.velocity_mps, 3)
                put(
                    "odometry",
                    t_us,
                    ros_msgs.odometry_cdr(stamp, p, v, s.R_world_body, o.ned_frd, noise.position_m**2),
                )
            else:
                put("truth", t_us, ros_msgs.pose_cdr(stamp, s.p_world, s.R_world_body, o.ned_frd))
    finally:
        writer.close()
    return {
        "bag": str(out),
        "options": asdict(o),
        "messages": {getattr(o, f"{k}_topic"): n for k, n in counts.items()},
        "duration_s": round(t1 - t0, 3),
        "distance_m": round(traj.distance_m(t0, t1), 2),
        "trajectory": flight.description,
        "first_stamp_s": START_US * 1e-6,
        "altimeter_offset_sigma_m": alt_noise.bias_sigma_m,
        "yaw_bias_deg": round(math.degrees(yaw_bias), 3),
        "camera_K": asdict(flight.cameras.intrinsics),
        "distortion": list(o.distortion),
    }


def add_flight_bag_parser(sub: Any) -> None:
    """The ``flight-bag`` subcommand."""
    d = FlightBagOptions()
    p = sub.add_parser(
        "flight-bag",
        help="write a simulated Europa flight as a rosbag2 (images, IMU, range, odometry, truth)",
        description="Fly one of paper 2's trajectories over the simulated Europa site and write what a "
        "vehicle's recorder would hold, for `companion replay`.",
    )
    p.add_argument("out", help="new bag directory")
    p.add_argument("--trajectory", default=d.trajectory, choices=[str(i) for i in range(1, 11)])
    p.add_argument(
        "--seed", type=int, default=d.seed, help="site, trajectory noise and sensors (%(default)s)"
    )
    p.add_argument("--duration", type=float, default=d.duration_s, help="s, at most 180 (%(default)s)")
    p.add_argument("--camera-rate", type=float, default=d.camera_hz, help="frame pairs per s (%(default)s)")
    p.add_argument("--imu-rate", type=float, default=d.imu_hz, help="Hz (%(default)s)")
    p.add_argument(
        "--ros-frames",
        default="ned",
        choices=["ned", "enu"],
        help="ned: map_ned / base_link_frd (default); enu: ROS's map / base_link (ENU, FLU)",
    )
    p.add_argument("--storage", default=d.storage, choices=["mcap", "sqlite3"])
    p.add_argument(
        "--distortion",
        default="",
        help="a lens: k1,k2,p1,p2[,k3] (OpenCV's order) applied to both cameras' images (default: pinhole)",
    )
    p.set_defaults(func=cmd_flight_bag)


def cmd_flight_bag(a: Any) -> int:
    """``python -m sim_bridge flight-bag``: 0 when written, 2 when the bag cannot be created."""
    import json

    from rosbags.rosbag2.errors import WriterError

    opts = FlightBagOptions(
        trajectory=a.trajectory,
        seed=a.seed,
        duration_s=a.duration,
        camera_hz=a.camera_rate,
        imu_hz=a.imu_rate,
        ned_frd=a.ros_frames == "ned",
        storage=a.storage,
        distortion=tuple(float(x) for x in a.distortion.split(",")) if a.distortion else (),
    )

    def progress(done: int, total: int) -> None:
        if done % 20 == 0 or done == total:
            print(f"  rendered {done}/{total} frame pairs", flush=True)

    print(
        f"flying Europa trajectory {a.trajectory} (seed {a.seed}) for {a.duration:g} s into {a.out}",
        flush=True,
    )
    try:
        s = write_flight_bag(a.out, opts, progress)
    except (WriterError, ValueError) as exc:
        print(f"flight-bag: {exc}")
        return 2
    for topic, n in s["messages"].items():
        print(f"  {topic:24s} {n:6d} messages")
    print(f"  {s['trajectory']}: {s['distance_m']:.1f} m in {s['duration_s']:.1f} s")
    if opts.distortion:
        k = s["camera_K"]
        print(
            f"  the cameras' calibration, for [cameras.visible] and [cameras.thermal]: fx_px = {k['fx']:.3f}, "
            f"fy_px = {k['fy']:.3f}, cx_px = {k['cx']:.2f}, cy_px = {k['cy']:.2f}, distortion = {list(opts.distortion)}"
        )
    print(f"  replay it: companion replay {a.out} --config configs/europa_dual_ekf.toml")
    print(json.dumps({"flight_bag": s}), flush=True)
    return 0
