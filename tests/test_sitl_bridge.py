"""The SITL camera bridge against the simulated autopilot standing in for an ArduPilot SITL: MAVLink pose in
(TCP on loopback), rendered frames out on Zenoh (real sessions, multicast scouting off)."""

from __future__ import annotations

import json
import math
import shlex
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from netutil import free_port, wait_for

from companion.cli import apply_overrides
from companion.config import load_config
from companion.geometry import camera_pose, rot_from_rpy
from companion.io.dem_store import load_dem
from companion.io.zenoh_io import FrameSubscriber, open_session
from sim_bridge import cli
from sim_bridge.autopilot_link import SimAutopilotLink, SimAutopilotOptions, SimNoise
from sim_bridge.render import VisibleRenderer
from sim_bridge.sitl_bridge import SitlCameraBridge, SitlCameraOptions, companion_command, format_command
from sim_bridge.terrain import make_scene

REPO = Path(__file__).resolve().parents[1]
ORIGIN = (47.397742, 8.545594, 488.0)  # PX4's default SITL home (Zurich)
OFFSET_NE = (10.0, -5.0)
ALT_M = 60.0
V_NE = np.array([3.0, 1.0])
YAW0, YAW_RATE, PITCH = 0.4, 0.1, 0.05


@pytest.fixture(scope="module")
def scene():
    return make_scene("08", seed=0, size_m=200.0, cell_m=0.5)


class Flight:
    """A vehicle in the SITL's local NED: straight level line at 60 m, pitched 0.05 rad, turning slowly."""

    def __init__(self) -> None:
        self.t0_us = time.time_ns() // 1000

    def pose(self, t_us: int) -> tuple[np.ndarray, np.ndarray]:
        t = (t_us - self.t0_us) * 1e-6
        p = np.array([V_NE[0] * t - 20.0, V_NE[1] * t + 5.0, -ALT_M])
        return rot_from_rpy(0.0, PITCH, YAW0 + YAW_RATE * t), p

    def truth(self, t_us: int) -> dict[str, Any]:
        R, p = self.pose(t_us)
        t = (t_us - self.t0_us) * 1e-6
        return {
            "rpy_rad": np.array([0.0, PITCH, YAW0 + YAW_RATE * t]),
            "p_ned_m": p,
            "v_ned_mps": np.array([V_NE[0], V_NE[1], 0.0]),
            "range_m": ALT_M,
            "accel_body_mps2": R.T @ np.array([0.0, 0.0, -9.80665]),
            # body rates of a pure yaw rate at pitch theta, roll 0 (ZYX kinematics)
            "gyro_body_rps": np.array([-math.sin(PITCH) * YAW_RATE, 0.0, math.cos(PITCH) * YAW_RATE]),
        }


def sitl_stand_in(port: int, flight: Flight) -> SimAutopilotLink:
    opts = SimAutopilotOptions(
        attitude_hz=50.0,
        local_position_hz=50.0,
        global_position_hz=0.0,
        distance_sensor_hz=0.0,
        highres_imu_hz=0.0,
        origin_hz=2.0,
        origin=ORIGIN,
        planet="earth",
        noise=SimNoise(*(0.0,) * 11),
    )
    return SimAutopilotLink(f"tcpin:127.0.0.1:{port}", truth=flight.truth, options=opts)


def test_frames_show_the_reported_pose_at_the_camera_rate(scene, tmp_path) -> None:
    port = free_port(socket.SOCK_STREAM)
    flight = Flight()
    autopilot = sitl_stand_in(port, flight)
    autopilot.start()
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    pub_session = open_session("peer", listen=[endpoint])
    sub_session = open_session("peer", connect=[endpoint])
    arrived: list[tuple[int, Any]] = []
    sub = FrameSubscriber(
        sub_session, {"nadir": "uav/camera/nadir"}, sink=lambda f: arrived.append((time.time_ns() // 1000, f))
    )
    rate_hz = 5.0
    opts = SitlCameraOptions(
        mavlink=f"tcp:127.0.0.1:{port}", offset_ne_m=OFFSET_NE, camera_rate_hz=rate_hz, noise=False
    )
    bridge = SitlCameraBridge(pub_session, opts, scene=scene)
    try:
        bridge.start()
        assert bridge.wait_pose(5.0) is not None
        probe = pub_session.declare_publisher("uav/camera/nadir")
        # zenoh's stub types matching_status as bool; it is a MatchingStatus with .matching
        assert wait_for(lambda: probe.matching_status.matching)  # type: ignore[attr-defined]
        probe.undeclare()
        t_run = time.monotonic()
        status = bridge.run(duration_s=2.4)
        run_s = time.monotonic() - t_run
        wait_for(lambda: len(arrived) >= status["frames"], 2.0)
        assert wait_for(lambda: bridge.origin_lla is not None, 2.0)
        argv = companion_command(
            bridge,
            bridge.write_dem(tmp_path / "dem.npz"),
            "tcp:127.0.0.1:5763",
            ["tcp/127.0.0.1:7447"],
            config=str(REPO / "configs" / "sim_mars.toml"),
            pose=bridge.pose(),
        )
        text = format_command(argv)
        # the SITL goes away: no frame from a frozen pose, the slots are counted as stale
        autopilot.stop()
        time.sleep(opts.max_pose_age_s + 0.1)
        after = bridge.run(duration_s=0.5)
    finally:
        sub.close()
        bridge.close()
        autopilot.stop()
        sub_session.close()
        pub_session.close()

    # the autopilot was followed, asked for its streams, and saw our camera heartbeat
    assert status["autopilot"] == "ArduPilot"
    assert (1, 100) in autopilot.heartbeats_from
    assert autopilot.received.get("COMMAND_LONG", 0) >= 2  # SET_MESSAGE_INTERVAL x2 (+ REQUEST_MESSAGE)
    assert autopilot.received.get("DISTANCE_SENSOR", 0) >= 0.7 * 20 * run_s  # the rangefinder, 20 Hz

    # about the camera rate: every slot is a frame or a counted skip; frames land on the slot grid
    frames = [f for _, f in arrived]
    assert len(frames) == status["frames"] >= 0.6 * run_s * rate_hz, status
    slots = np.diff([f.stamp_us for f in frames]) / (1e6 / rate_hz)
    assert np.allclose(slots, np.round(slots), atol=1e-3) and np.all(slots >= 1)
    assert status["frames"] + sum(status["skipped"].values()) >= run_s * rate_hz - 1

    assert after["frames"] == status["frames"] and after["skipped"].get("stale_pose", 0) >= 2, after

    # each frame is the view at the pose the autopilot reported for its stamp (mapped onto the scene)
    ref = VisibleRenderer(scene.dem, scene.albedo, scene.sun, bridge.intrinsics, noise=None)
    ground = float(scene.dem.height_at(*OFFSET_NE)[0])
    offset = np.array([OFFSET_NE[0], OFFSET_NE[1], -ground])
    diffs, shifted = [], []
    for frame in frames[:: max(1, len(frames) // 5)]:
        R, p = flight.pose(frame.stamp_us)
        img = frame.image.astype(float)
        diffs.append(np.abs(img - ref.render(*camera_pose(R, p + offset))).mean())
        wrong = p + offset + np.array([1.0, 0.0, 0.0])  # the same view 1 m further north
        shifted.append(np.abs(img - ref.render(*camera_pose(R, wrong))).mean())
    assert max(diffs) < 1.0, diffs
    assert min(shifted) > 3 * max(diffs) and min(shifted) > 3.0, (diffs, shifted)

    # the rangefinder measures to the scene: the ground point the renderer sees on the optical axis
    c = (bridge.intrinsics.height // 2, bridge.intrinsics.width // 2)
    for t_us in (frames[0].stamp_us, frames[-1].stamp_us):
        R, p = flight.pose(t_us)
        R_wc, p_c = camera_pose(R, p + offset)
        hit = ref.ground_points(R_wc, p_c)[c[0] - 1 : c[0] + 1, c[1] - 1 : c[1] + 1].reshape(-1, 3).mean(0)
        rng = bridge.range_to_scene(R, p)
        assert rng is not None and rng == pytest.approx(float(np.linalg.norm(hit - p_c)), abs=0.3)

    # the DEM for the companion is in the SITL frame: its take-off ground is at height 0
    dem = load_dem(tmp_path / "dem.npz")
    assert abs(float(dem.filled().height_at(0.0, 0.0)[0])) < 1.5
    truth_ne = (30.0, -20.0)
    want = float(scene.dem.height_at(truth_ne[0] + OFFSET_NE[0], truth_ne[1] + OFFSET_NE[1])[0]) - ground
    assert abs(float(dem.filled().height_at(*truth_ne)[0]) - want) < 1.5

    # the printed command is valid for `companion run` and carries the current pose
    sets = [argv[i + 1] for i in range(len(argv)) if argv[i] == "--set"]
    cfg = apply_overrides(load_config(argv[argv.index("--config") + 1]), sets, "test")
    assert cfg.dem is not None and Path(cfg.dem.path) == (tmp_path / "dem.npz").resolve()
    assert cfg.mavlink.connection == "tcp:127.0.0.1:5763" and cfg.zenoh.connect == ["tcp/127.0.0.1:7447"]
    assert cfg.origin is not None and cfg.origin.planet == "earth"
    assert cfg.origin.lat_deg == pytest.approx(ORIGIN[0], abs=1e-6)
    assert cfg.estimator.initial_position_ned_m is not None
    assert cfg.estimator.initial_position_ned_m[2] == pytest.approx(-ALT_M, abs=0.1)
    assert shlex.split(text.replace("\\\n", " ")) == argv  # the text pastes into a shell as this argv


def test_cli_sitl_camera(tmp_path, capsys) -> None:
    """``python -m sim_bridge sitl-camera`` in-process: DEM written, command printed, frames published."""
    port = free_port(socket.SOCK_STREAM)
    autopilot = sitl_stand_in(port, Flight())
    autopilot.start()
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    try:
        rc = cli.main(
            [
                "sitl-camera",
                "--mavlink", f"tcp:127.0.0.1:{port}",
                "--scene-size", "150",
                "--camera-rate", "4",
                "--duration", "1.5",
                "--wait-pose", "5",
                "--out", str(tmp_path),
                "--zenoh-listen", endpoint,
            ]
        )  # fmt: skip
    finally:
        autopilot.stop()
    assert rc == 0
    out = capsys.readouterr().out
    assert (tmp_path / "dem.npz").exists()
    assert "-m companion run --config configs/sim_mars.toml" in out
    assert f"--set 'zenoh.connect=[\"{endpoint}\"]'" in out
    assert "--set 'estimator.initial_position_ned_m=[" in out
    status = json.loads(out.strip().splitlines()[-1])["sitl_camera"]
    assert status["frames"] >= 3 and status["autopilot"] == "ArduPilot"
    assert status["agl_m"] is not None and status["p_ned_m"][2] == pytest.approx(-ALT_M, abs=0.1)
    assert (
        cli.main(["sitl-camera", "--mavlink", "bogus:1", "--scene-size", "50", "--out", str(tmp_path)]) == 2
    )


def test_bad_and_reordered_telemetry_and_a_sitl_restart() -> None:
    """Crafted MAVLink on the wire: NaN samples are ignored, older samples dropped, a clock reset clears."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2

    from companion.io.mavlink import MavCodec
    from companion.io.transport import open_transport

    port = free_port(socket.SOCK_STREAM)
    server = open_transport(f"tcpin:127.0.0.1:{port}")
    codec = MavCodec(1, 1)
    mav = codec.mav
    session = open_session("peer", listen=[f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"])
    bridge = SitlCameraBridge(
        session,
        SitlCameraOptions(mavlink=f"tcp:127.0.0.1:{port}", rangefinder_hz=0.0),
        scene=make_scene("08", seed=1, size_m=60.0, cell_m=0.5),
    )

    def send(*msgs: Any) -> None:
        for m in msgs:
            server.write(codec.encode(m))
        time.sleep(0.1)

    try:
        bridge.start()
        assert wait_for(lambda: server.read(0.01) is not None and server.stats.connected, 5.0)
        hb = mav.heartbeat_encode(
            mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4, 0, 0, mavlink2.MAV_STATE_ACTIVE
        )
        send(
            hb,
            mav.attitude_encode(5000, 0.0, 0.0, 1.0, 0, 0, 0),
            mav.local_position_ned_encode(5000, 1, 2, -30, 0, 0, 0),
        )
        assert wait_for(lambda: bridge.pose() is not None, 2.0) and bridge.autopilot_type == "PX4"
        nan = float("nan")
        send(
            mav.attitude_encode(5100, nan, 0.0, 1.0, 0, 0, 0),  # NaN: ignored
            mav.local_position_ned_encode(5100, 1, 2, float("inf"), 0, 0, 0),  # inf: ignored
            mav.attitude_encode(4900, 0.0, 0.0, 2.0, 0, 0, 0),  # older than the last: dropped
        )
        pose = bridge.pose()
        assert (
            pose is not None
            and pose.rpy_rad[2] == pytest.approx(1.0)
            and pose.p_ned_m[2] == pytest.approx(-30)
        )
        assert bridge.counters.non_finite == 2 and bridge.counters.reordered == 1
        send(mav.attitude_encode(10, 0.0, 0.0, 3.0, 0, 0, 0))  # the clock restarted: old pose forgotten
        assert bridge.counters.sitl_restarts == 1
        assert bridge.pose() is None  # no position since the restart yet
        send(mav.local_position_ned_encode(20, 0, 0, -5, 0, 0, 0))
        pose = bridge.pose()
        assert (
            pose is not None
            and pose.rpy_rad[2] == pytest.approx(3.0)
            and pose.p_ned_m[2] == pytest.approx(-5)
        )
    finally:
        bridge.close()
        server.close()
        session.close()
