"""Offline replay of a recorded flight (``companion replay``) and the simulator's flight bags.

The flight bags are real rosbag2 (MCAP) files written by ``sim_bridge.flight_bag`` from rendered Europa frames
and the simulated sensors; the replay runs the configured dual-camera EKF over them."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from companion.cli import main as companion_main
from companion.config import load_config
from companion.factory import build_estimator
from companion.geometry import rot_from_rpy, rpy_from_rot
from companion.io import ros_msgs
from companion.replay import ReplayError, choose_topics, replay_bag
from sim_bridge.flight_bag import FlightBagOptions, write_flight_bag

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "europa_dual_ekf.toml"


# -- ROS conventions (pure) --------------------------------------------------------------------------------


@pytest.mark.parametrize("ned_frd", [True, False], ids=["ned_frd", "enu_flu"])
def test_ros_messages_round_trip_in_either_convention(ned_frd: bool) -> None:
    rng = np.random.default_rng(3)
    R = rot_from_rpy(0.1, -0.2, 2.5)
    acc, gyr = np.array([0.3, -0.2, -1.31]), np.array([0.01, -0.02, 0.03])
    ts = ros_msgs.TYPESTORE
    m: Any = ts.deserialize_cdr(ros_msgs.imu_cdr(1_000_123, acc, gyr, R, ned_frd), ros_msgs.IMU_MSGTYPE)
    r = ros_msgs.imu_reading(m)
    assert r.imu.stamp_us == 1_000_123
    np.testing.assert_allclose(r.imu.accel_mps2, acc, atol=1e-12)
    np.testing.assert_allclose(r.imu.gyro_rps, gyr, atol=1e-12)
    assert r.attitude is not None
    np.testing.assert_allclose(
        [r.attitude.roll_rad, r.attitude.pitch_rad, r.attitude.yaw_rad], [0.1, -0.2, 2.5]
    )
    # the FLU message really is FLU: the body's down axis is its -z
    if not ned_frd:
        assert m.linear_acceleration.z == pytest.approx(1.31)
    p, v = rng.normal(0, 50, 3), rng.normal(0, 3, 3)
    od: Any = ts.deserialize_cdr(ros_msgs.odometry_cdr(5, p, v, R, ned_frd), ros_msgs.ODOMETRY_MSGTYPE)
    lp = ros_msgs.local_position_sample(od)
    np.testing.assert_allclose(lp.p_ned_m, p, atol=1e-9)
    np.testing.assert_allclose(lp.v_ned_mps, v, atol=1e-9)
    if not ned_frd:  # ENU: north is y, down is -z
        assert od.pose.pose.position.y == pytest.approx(p[0]) and od.pose.pose.position.z == pytest.approx(
            -p[2]
        )
    t, pp, RR = ros_msgs.pose_ned(
        ts.deserialize_cdr(ros_msgs.pose_cdr(7, p, R, ned_frd), ros_msgs.POSE_MSGTYPE)
    )
    np.testing.assert_allclose(pp, p, atol=1e-9)
    np.testing.assert_allclose(RR, R, atol=1e-9)


def test_imu_without_orientation_and_range_without_return() -> None:
    ts = ros_msgs.TYPESTORE
    m = ts.deserialize_cdr(ros_msgs.imu_cdr(1, np.zeros(3), np.zeros(3), None, True), ros_msgs.IMU_MSGTYPE)
    assert ros_msgs.imu_reading(m).attitude is None  # orientation_covariance[0] = -1: ROS's "none"
    for r in (float("nan"), float("inf"), 0.1, 600.0):  # no return, too close, too far
        msg = ts.deserialize_cdr(ros_msgs.range_cdr(1, r, 0.2, 500.0, True), ros_msgs.RANGE_MSGTYPE)
        assert np.isnan(ros_msgs.altimeter_sample(msg).range_m)
    msg = ts.deserialize_cdr(ros_msgs.range_cdr(1, 72.5, 0.2, 500.0, True), ros_msgs.RANGE_MSGTYPE)
    assert ros_msgs.altimeter_sample(msg).range_m == pytest.approx(72.5)
    assert rpy_from_rot(ros_msgs.rot_ned_frd(np.array([0.0, 0.0, 0.0, 1.0]), False))[2] == pytest.approx(
        np.pi / 2
    )


# -- a simulated flight bag, replayed ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("bags") / "europa"
    write_flight_bag(out, FlightBagOptions(trajectory="1", duration_s=12.0))
    return out


def test_flight_bag_holds_every_sensor_in_one_clock(flight: Path) -> None:
    with Reader(flight) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        counts = {c.topic: c.msgcount for c in r.connections}
        stamps: dict[str, list[int]] = {}
        for conn, log_ns, raw in r.messages():
            msg: Any = ros_msgs.TYPESTORE.deserialize_cdr(bytes(raw), conn.msgtype)
            stamps.setdefault(conn.topic, []).append(ros_msgs.stamp_us(msg.header))
            assert log_ns == ros_msgs.stamp_us(msg.header) * 1000
    assert types["/uav/imu"] == ros_msgs.IMU_MSGTYPE and types["/uav/range"] == ros_msgs.RANGE_MSGTYPE
    assert counts["/uav/camera/visible"] == counts["/uav/camera/thermal"] == 25  # 12 s at 2 Hz, both ends
    assert counts["/uav/imu"] == 1201
    assert stamps["/uav/camera/visible"] == stamps["/uav/camera/thermal"]  # one capture stamp per pair
    assert stamps["/uav/imu"][0] == stamps["/uav/camera/visible"][0]


def test_replay_runs_the_dual_ekf_over_the_bag_and_measures_it(flight: Path, tmp_path: Path) -> None:
    cfg = load_config(CONFIG)
    s = replay_bag(flight, cfg, build_estimator(cfg), tmp_path)
    assert s.messages["visible"] == s.messages["thermal"] == s.frame_sets == 25
    assert s.messages["imu"] == 1201 and s.bad == {} and s.estimator_errors == 0
    assert s.estimator["counters"]["imu_samples"] == 1201
    assert s.estimator["counters"]["altimeter_updates"] >= 100
    assert s.estimator["counters"]["frames_without_imu"] == 0
    # the record begins with the frames: the start waits for a second of ATTITUDE (two frame sets at 2 Hz)
    assert s.estimator["counters"]["waiting_for_attitude"] == 2
    assert s.would_send == 22 and s.not_sent == {"no_estimate": 2, "status_initialising": 1}
    assert s.error_m is not None and s.error_m["count"] == 22
    # measured 0.24 m mean on the 20 s version of this flight; a filter without IMU or altimeter drifts metres
    assert s.error_m["mean"] < 1.0 and s.error_m["max"] < 2.0
    tum = np.loadtxt(tmp_path / "estimates.tum")
    assert tum.shape == (22, 8)
    truth = np.loadtxt(tmp_path / "truth.tum")
    assert len(truth) == 241 and np.allclose(np.linalg.norm(truth[:, 4:], axis=1), 1.0)


def test_a_flight_without_truth_still_gets_its_picture(flight: Path, tmp_path: Path) -> None:
    """A real flight has no truth: the replay draws the track and the 1-sigma sent, and claims no error."""
    cfg = load_config(CONFIG)
    s = replay_bag(flight, cfg, build_estimator(cfg), tmp_path, overrides={"truth": ""})
    assert s.topics["truth"] is None and s.error_m is None and s.would_send == 22
    assert s.plot == str(tmp_path / "trajectory.png") and not (tmp_path / "truth.tum").exists()
    assert (tmp_path / "trajectory.png").read_bytes()[:4] == b"\x89PNG"


def test_a_bag_in_ros_enu_flu_frames_replays_to_the_same_estimates(flight: Path, tmp_path: Path) -> None:
    enu = tmp_path / "enu"
    write_flight_bag(enu, FlightBagOptions(trajectory="1", duration_s=12.0, ned_frd=False))
    cfg = load_config(CONFIG)
    replay_bag(flight, cfg, build_estimator(cfg), tmp_path / "a")
    replay_bag(enu, cfg, build_estimator(cfg), tmp_path / "b")
    a, b = np.loadtxt(tmp_path / "a" / "estimates.tum"), np.loadtxt(tmp_path / "b" / "estimates.tum")
    np.testing.assert_allclose(a, b, atol=2e-6)


def _copy_with_damage(src: Path, dst: Path) -> dict[str, int]:
    """Copy ``src`` into a new bag, truncating every 5th IMU message and the 3rd visible image and adding an
    Imu that is not CDR at all."""
    damaged = {"imu": 0, "visible": 0}
    with Reader(src) as r:
        w = Writer(dst, version=8, storage_plugin=StoragePlugin.MCAP)
        w.open()
        conns = {
            c.topic: w.add_connection(c.topic, c.msgtype, typestore=ros_msgs.TYPESTORE) for c in r.connections
        }
        n = {"/uav/imu": 0, "/uav/camera/visible": 0}
        for conn, log_ns, raw in r.messages():
            data = bytes(raw)
            if conn.topic in n:
                n[conn.topic] += 1
                if conn.topic == "/uav/imu" and n[conn.topic] % 5 == 0:
                    data, damaged["imu"] = data[:30], damaged["imu"] + 1
                if conn.topic == "/uav/camera/visible" and n[conn.topic] == 3:
                    data, damaged["visible"] = data[:1000], damaged["visible"] + 1
            w.write(conns[conn.topic], log_ns, data)
            if conn.topic == "/uav/imu" and n[conn.topic] == 7:
                w.write(conns[conn.topic], log_ns + 1, b"not a message")
                damaged["imu"] += 1
        w.close()
    return damaged


def test_bad_messages_are_counted_and_the_replay_goes_on(flight: Path, tmp_path: Path) -> None:
    bag = tmp_path / "damaged"
    damaged = _copy_with_damage(flight, bag)
    cfg = load_config(CONFIG)
    s = replay_bag(bag, cfg, build_estimator(cfg), tmp_path / "out")
    assert s.bad == {"imu:bad_message": damaged["imu"], "visible:truncated": 1}
    assert s.messages["imu"] == 1201 - (damaged["imu"] - 1)
    # the lone thermal frame of the broken pair has no partner: 24 sets, each estimated
    assert s.frame_sets == 24 and s.frames_unpaired == 1 and s.estimator_errors == 0
    assert s.error_m is not None and s.error_m["mean"] < 1.0


def test_missing_or_ambiguous_topics_say_what_to_pass(flight: Path, tmp_path: Path) -> None:
    cfg = load_config(CONFIG)
    types = {
        "/uav/camera/visible": "sensor_msgs/msg/Image",
        "/uav/camera/thermal": "sensor_msgs/msg/Image",
        "/a/imu": ros_msgs.IMU_MSGTYPE,
        "/b/imu": ros_msgs.IMU_MSGTYPE,
    }
    with pytest.raises(ReplayError, match="--imu-topic"):
        choose_topics(types, cfg, ("visible", "thermal"))
    t = choose_topics(types, cfg, ("visible", "thermal"), {"imu": "/b/imu"})
    assert t.imu == "/b/imu" and t.range is None and t.truth is None
    with pytest.raises(ReplayError, match="--camera-topic thermal=/topic"):
        choose_topics({"/uav/camera/visible": "sensor_msgs/msg/Image"}, cfg, ("visible", "thermal"))
    # the command line: exit 2 with the reason, nothing replayed
    rc = companion_main(
        [
            "replay",
            str(flight),
            "--config",
            str(CONFIG),
            "--out",
            str(tmp_path / "x"),
            "--camera-topic",
            "thermal=/no/such/topic",
        ]
    )
    assert rc == 2
    assert not (tmp_path / "x" / "estimates.csv").exists()


def test_replay_command_prints_the_error_and_writes_its_summary(
    flight: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "cli"
    rc = companion_main(
        ["replay", str(flight), "--config", str(CONFIG), "--out", str(out), "--range-topic", ""]
    )
    assert rc == 0
    text = capsys.readouterr().out
    assert "error against the truth over 22 estimates" in text and "not in the bag: range" in text
    summary = json.loads((out / "replay_summary.json").read_text())
    assert summary["topics"]["range"] is None and summary["estimator"]["counters"]["altimeter_updates"] == 0
    assert summary["estimator"]["counters"]["frames_without_altimeter"] > 0
    # the picture of the flight beside its log, named in the output
    assert summary["plot"] == str(out / "trajectory.png") and f"plot: {out / 'trajectory.png'}" in text
    assert (out / "trajectory.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a second replay into the same directory would append to its estimates log: refused, exit 2
    assert companion_main(["replay", str(flight), "--config", str(CONFIG), "--out", str(out)]) == 2
    assert "holds a replay already" in capsys.readouterr().err


# -- the daemon's record of its inputs ----------------------------------------------------------------------


@pytest.mark.parametrize("frames", ["png", "raw"])
def test_input_recorder_writes_what_the_replay_reads_back(tmp_path: Path, frames: str) -> None:
    from companion.io.frames import decode_frame
    from companion.io.input_recorder import InputRecorder
    from companion.replay import _decode_sample
    from companion.types import AltimeterSample, AttitudeSample, Frame, ImuSample, LocalPositionSample

    rec = InputRecorder(str(tmp_path / "rec-{time}"), {"visible": "/uav/camera/visible"}, frames=frames)
    img = (np.arange(480 * 640) % 251).astype(np.uint8).reshape(480, 640)
    items: list[tuple[Any, int]] = [
        (ImuSample(1_000, np.array([0.1, -0.2, -1.3]), np.array([0.01, 0.02, -0.03])), 1_500),
        (AttitudeSample(2_000, 0.05, -0.04, 2.9), 2_100),
        (AltimeterSample(3_000, 71.25), 3_050),
        (AltimeterSample(3_100, float("nan")), 3_150),
        (LocalPositionSample(4_000, np.array([10.0, -20.0, -70.0]), np.array([1.0, 0.5, -0.2])), 4_010),
        (Frame(5_000, "visible", img), 6_000),
        (Frame(5_000, "thermal", img), 6_000),  # not a recorded camera: ignored
    ]
    for item, log_us in items:
        rec.put(item, log_us)
    rec.close()
    assert rec.status()["messages"] == {
        "imu": 1,
        "attitude": 1,
        "range": 2,
        "local_position": 1,
        "visible": 1,
    }
    (bag,) = tmp_path.glob("rec-*")
    got: list[tuple[int, Any]] = []
    with Reader(bag) as r:
        for conn, log_ns, raw in r.messages():
            if conn.topic == "/uav/camera/visible":
                png = conn.msgtype == "sensor_msgs/msg/CompressedImage"
                assert png == (frames == "png"), conn.msgtype
                f = decode_frame(bytes(raw), "visible", compressed=png)
                assert f.stamp_us == 5_000 and log_ns == 6_000_000 and np.array_equal(f.image, img)
                continue
            got += [(log_ns, s) for s in _decode_sample(conn.msgtype, bytes(raw), True)]
    got.sort(key=lambda x: x[0])
    assert [g[0] for g in got] == [1_500_000, 2_100_000, 3_050_000, 3_150_000, 4_010_000]
    imu, att, alt, no_return, lp = (g[1] for g in got)
    np.testing.assert_array_equal(imu.accel_mps2, [0.1, -0.2, -1.3])
    np.testing.assert_array_equal(imu.gyro_rps, [0.01, 0.02, -0.03])
    assert (att.roll_rad, att.pitch_rad, att.yaw_rad) == pytest.approx((0.05, -0.04, 2.9), abs=1e-12)
    assert alt.range_m == 71.25 and np.isnan(no_return.range_m)
    np.testing.assert_array_equal(lp.p_ned_m, [10.0, -20.0, -70.0])
    np.testing.assert_array_equal(lp.v_ned_mps, [1.0, 0.5, -0.2])
    with pytest.raises(OSError, match="exists"):
        InputRecorder(str(bag), {"visible": "/uav/camera/visible"})


def test_input_recorder_keeps_16_bit_frames_exactly_in_less_space(tmp_path: Path) -> None:
    """A thermal camera's 16-bit radiometric frame (noise in its low bits) comes back bit for bit from the
    PNG record, which is smaller than the raw one; an unknown frame format is refused at start."""
    from companion.io.frames import decode_frame
    from companion.io.input_recorder import InputRecorder
    from companion.types import Frame

    rng = np.random.default_rng(3)
    ramp = np.add.outer(np.arange(480), np.arange(640)) * 20 + 20_000
    img = (ramp + rng.normal(0, 30, ramp.shape)).clip(0, 65535).astype(np.uint16)
    sizes = {}
    for frames in ("png", "raw"):
        rec = InputRecorder(str(tmp_path / frames), {"thermal": "/t"}, frames=frames)
        rec.put(Frame(7_000, "thermal", img), 7_000)
        rec.close()
        sizes[frames] = sum(f.stat().st_size for f in (tmp_path / frames).iterdir())
        with Reader(tmp_path / frames) as r:
            ((conn, _, raw),) = [m for m in r.messages() if m[0].topic == "/t"]
            f = decode_frame(bytes(raw), "thermal", compressed=frames == "png")
        assert f.image.dtype == np.uint16 and np.array_equal(f.image, img)
    assert sizes["png"] < 0.8 * sizes["raw"], sizes
    with pytest.raises(ValueError, match="jpeg"):
        InputRecorder(str(tmp_path / "j"), {"thermal": "/t"}, frames="jpeg")


def test_input_recorder_drops_and_counts_when_the_disk_falls_behind(tmp_path: Path) -> None:
    import threading

    from companion.io.input_recorder import InputRecorder
    from companion.types import AltimeterSample

    rec = InputRecorder(str(tmp_path / "rec"), {}, queue_size=4)
    # a disk that stalls: the bag's own write waits until released, so the queue fills
    disk = threading.Event()
    write = rec._writer.write

    def stalled(*args: Any) -> None:
        disk.wait(10.0)
        write(*args)

    rec._writer.write = stalled  # type: ignore[method-assign,assignment]
    for i in range(50):
        rec.put(AltimeterSample(i, 10.0), i)  # never blocks the caller
    dropped = rec.status()["dropped"]
    disk.set()
    rec.close()
    st = rec.status()
    assert 40 <= dropped <= 46 and st["dropped"] == dropped
    assert st["messages"]["range"] + dropped == 50 and st["errors"] == 0


def test_input_recorder_closes_its_record_when_the_disk_runs_low(tmp_path: Path) -> None:
    from companion.daemon import format_status_line
    from companion.io.input_recorder import InputRecorder
    from companion.types import AltimeterSample

    # a threshold above any disk's free space: the first write finds the disk "full"
    rec = InputRecorder(str(tmp_path / "rec"), {}, min_free_mb=1e12)
    for i in range(20):
        rec.put(AltimeterSample(i, 10.0), i)
    for _ in range(200):
        if rec.status()["stopped"]:
            break
        time.sleep(0.01)
    st = rec.status()
    assert st["stopped"].startswith("disk below") and st["messages"] == {} and st["errors"] == 0
    # the record was closed properly: a reader opens it (its metadata written), nothing lost but what was not written
    assert (tmp_path / "rec" / "metadata.yaml").exists()
    with Reader(tmp_path / "rec") as r:
        assert sum(c.msgcount for c in r.connections) == 0
    rec.put(AltimeterSample(99, 10.0), 99)  # ignored from now on, never an error
    rec.close()
    status = {
        "fps_in": 1.0, "fps_out": 1.0, "latency_p50_ms": 1.0, "latency_p99_ms": 1.0, "frames_dropped_stale": 0,
        "frames": {}, "not_sent": {}, "quality": 1.0, "estimate_status": "ok", "link": {"state": "up"},
        "inputs_record": rec.status(),
    }  # fmt: skip
    assert "REC STOPPED (disk below" in format_status_line(status)
    status["inputs_record"] = {"mbytes": 107.4, "dropped": 0, "errors": 0, "stopped": ""}
    assert format_status_line(status).endswith("  rec 107 MB")


def test_a_record_whose_daemon_was_killed_is_named_with_the_way_to_recover_it(
    flight: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import shutil

    killed = tmp_path / "inputs"
    killed.mkdir()
    for f in flight.glob("*.mcap"):  # the data without the metadata a clean stop writes
        shutil.copy(f, killed / f.name)
    rc = companion_main(["replay", str(killed), "--config", str(CONFIG), "--out", str(tmp_path / "out")])
    assert rc == 2
    assert f"python -m sim_bridge recover {killed}" in capsys.readouterr().err
