"""End to end: the real daemon against the simulated vehicle as a separate process, on loopback.

Real Zenoh sessions, real MAVLink over UDP (and over a pty pair), no mocks. The daemon is observed the
way an operator would: through its Zenoh status topic and through what the autopilot accepted.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from netutil import wait_for
from pymavlink import mavutil

from companion.cli import apply_overrides, cmd_run
from companion.cli import main as companion_main
from companion.config import load_config
from companion.io.dem_store import save_dem_npz
from companion.io.frames import encode_image
from companion.io.zenoh_io import open_session
from sim_bridge.demo import StatusWatch, free_port
from sim_bridge.sim import SimConfig, make_trajectory
from sim_bridge.terrain import degrade_dem, make_scene

ROOT = Path(__file__).resolve().parents[1]
RATE_HZ = 5.0  # low enough for the renderer and the estimator on a loaded 2-core CI machine
# terrain_lba: share of the estimates whose error is inside their own 95 % ellipse (measured 1.0 in three runs,
# sigma 1.3-1.5 m over this start-up flight: the start and the compass are still in it)
WITHIN_95_MIN = 0.8


@pytest.fixture(scope="module")
def dem_path(tmp_path_factory) -> tuple[Path, float]:
    scene = make_scene("08", seed=0)
    dem, _ = degrade_dem(scene.dem, seed=7)
    path = tmp_path_factory.mktemp("dem") / "dem.npz"
    save_dem_npz(path, dem)
    return path, float(np.nanmean(scene.dem.height_m))


class SimProcess:
    """``python -m sim_bridge sim`` with its JSON lines read in a thread.

    wait_companion_s > 0: the vehicle takes off only once the companion's HEARTBEAT is heard (at most that
    long), then after ``start_delay_s`` (an estimator that needs seconds to start sees the whole flight)."""

    def __init__(
        self,
        out: Path,
        mavlink: str,
        zport: int,
        duration_s: float,
        rate_hz: float = RATE_HZ,
        start_delay_s: float = 4.0,
        wait_companion_s: float = 0.0,
    ) -> None:
        cmd = [
            sys.executable,
            "-m",
            "sim_bridge",
            "sim",
            "--duration",
            str(duration_s),
            "--camera-rate",
            str(rate_hz),
            "--start-delay",
            str(start_delay_s),
            "--wait-companion",
            str(wait_companion_s),
            "--zenoh-listen",
            f"tcp/127.0.0.1:{zport}",
            "--mavlink",
            mavlink,
            "--out",
            str(out),
        ]
        self.proc = subprocess.Popen(
            cmd,
            stdout=subprocess.PIPE,
            stderr=open(out / "sim.log", "w"),
            text=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        self.ready = threading.Event()
        self.done: dict | None = None
        self.progress: list[dict] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            try:
                msg = json.loads(line)
            except json.JSONDecodeError:
                continue
            if msg.get("ready"):
                self.ready.set()
            elif "progress" in msg:
                self.progress.append(msg["progress"])
            elif "done" in msg:
                self.done = msg["done"]

    def wait_done(self, timeout_s: float) -> dict:
        self.proc.wait(timeout=timeout_s)
        time.sleep(0.2)
        assert self.done is not None, "simulator did not report its summary"
        return self.done

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()


def companion_config(
    dem: Path,
    ground_m: float,
    zenoh_connect: list[str],
    mavlink: str,
    zenoh_listen: list[str],
    estimator: str = "georef",
    estimates_log: str = "",
    record_inputs: str = "",
    tlog: str = "",
):
    cfg = SimConfig(duration_s=60.0)
    s0 = make_trajectory(cfg, ground_m).state_at(0.0)
    yaw0 = float(np.degrees(np.arctan2(s0.R_world_body[1, 0], s0.R_world_body[0, 0])))
    sets = {
        "estimator.kind": estimator,
        "zenoh.connect": zenoh_connect,
        "zenoh.listen": zenoh_listen,
        "mavlink.connection": mavlink,
        "dem.path": str(dem),
        "estimator.initial_position_ned_m": [float(v) for v in s0.p_world],
        "estimator.initial_yaw_deg": yaw0,
        "daemon.log_level": "warning",
        "daemon.estimates_log": estimates_log,
        "daemon.record_inputs": record_inputs,
        "mavlink.tlog": tlog,
    }
    return apply_overrides(
        load_config(ROOT / "configs/sim_mars.toml"), [f"{k}={json.dumps(v)}" for k, v in sets.items()], "test"
    )


def estimate_errors(out: Path) -> np.ndarray:
    truth = np.loadtxt(out / "truth.tum", ndmin=2)
    est = np.loadtxt(out / "estimate.tum", ndmin=2)
    p = np.stack([np.interp(est[:, 0], truth[:, 0], truth[:, i]) for i in (1, 2, 3)], axis=1)
    return np.linalg.norm(est[:, 1:4] - p, axis=1)


def image_cdr(
    stamp_us: int, height: int, width: int, step: int, data: np.ndarray, encoding: str = "mono8"
) -> bytes:
    """A sensor_msgs/Image in CDR with whatever fields we like (consistent or not)."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Time, Header, Image = (
        ts.types[n] for n in ("builtin_interfaces/msg/Time", "std_msgs/msg/Header", "sensor_msgs/msg/Image")
    )
    header = Header(
        stamp=Time(sec=stamp_us // 1_000_000, nanosec=(stamp_us % 1_000_000) * 1000), frame_id="cam"
    )
    msg = Image(
        header=header, height=height, width=width, encoding=encoding, is_bigendian=0, step=step, data=data
    )
    return bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))


def bad_payloads(now_us: int) -> list[tuple[str, bytes]]:
    img = np.full((480, 480), 100, np.uint8)
    good = encode_image(img, now_us, encoding="mono8")
    rng = np.random.default_rng(3)
    return [
        ("truncated", good[: len(good) // 3]),
        ("random", rng.integers(0, 256, 3000, dtype=np.uint8).tobytes()),
        (
            "unknown_encoding",
            encode_image(np.zeros((8, 8, 3), np.uint8), now_us, encoding="rgb8").replace(b"rgb8", b"yuv9"),
        ),
        ("size_mismatch", image_cdr(now_us, height=480, width=480, step=480, data=np.zeros(1000, np.uint8))),
        ("future", encode_image(img, now_us + 3_600_000_000, encoding="mono8")),
        ("backwards", encode_image(img, now_us - 10_000_000, encoding="mono8")),
    ]


@dataclass(frozen=True)
class FlightCase:
    """One estimator's flight. init_s: flight time before its first estimate (frames before it are not
    sent: the VO initialises once the vehicle has moved). Error bounds (m) from measured runs, wide margins."""

    estimator: str
    rate_hz: float
    duration_s: float
    init_s: float
    median_max_m: float
    p95_max_m: float


FLIGHTS = [
    # georef: median 0.65 / 0.67 / 0.67 m, 95th percentile 1.07 / 1.19 / 1.27 m measured (three runs)
    FlightCase("georef", RATE_HZ, 20.0, 0.0, 2.0, 6.0),
    # terrain_lba at 10 Hz (a key frame every 20 frames); the VO initialises ~4 s into the flight, once the
    # take-off ramp has moved the camera; median 0.62 m, 95th percentile 1.23 m measured on a loaded machine
    # (1.31-1.51 / 1.89-1.95 m before the simulated range finder read along its beam)
    FlightCase("terrain_lba", 10.0, 24.0, 6.0, 2.0, 3.0),
]


@pytest.mark.parametrize("case", FLIGHTS, ids=[c.estimator for c in FLIGHTS])
def test_flight_estimates_reach_the_autopilot_and_bad_frames_are_counted(
    tmp_path: Path, dem_path, case: FlightCase, caplog
) -> None:
    caplog.set_level("INFO", logger="companion.estimators.terrain_lba")
    dem, ground = dem_path
    zsim, zbad, zcomp = (free_port(socket.SOCK_STREAM) for _ in range(3))
    mport = free_port(socket.SOCK_DGRAM)
    # the vehicle takes off once the companion's heartbeat is heard (terrain_lba starts its back-end first)
    sim = SimProcess(
        tmp_path, f"udpin:127.0.0.1:{mport}", zsim, case.duration_s, case.rate_hz, 3.0, wait_companion_s=60.0
    )
    bad_session = open_session("peer", [], [f"tcp/127.0.0.1:{zbad}"], False)
    bad_pub = bad_session.declare_publisher("uav/camera/nadir")
    endpoints = [f"tcp/127.0.0.1:{zsim}", f"tcp/127.0.0.1:{zbad}"]
    stop = threading.Event()
    cfg = companion_config(
        dem,
        ground,
        endpoints,
        f"udpout:127.0.0.1:{mport}",
        [f"tcp/127.0.0.1:{zcomp}"],
        case.estimator,
        estimates_log=str(tmp_path / "companion" / "estimates-{time}"),
        record_inputs=str(tmp_path / "inputs") if case.estimator == "terrain_lba" else "",
        tlog=str(tmp_path / "companion" / "mavlink-{time}"),
    )
    daemon = threading.Thread(target=cmd_run, args=(cfg, stop), daemon=True)
    status: StatusWatch | None = None
    try:
        assert sim.ready.wait(60)
        daemon.start()
        status = StatusWatch(f"tcp/127.0.0.1:{zcomp}")  # an operator's laptop connects to the companion
        assert wait_for(lambda: status is not None and status.last is not None, 60.0, 0.1), "no status"
        time.sleep(6.0)  # mid-flight: throw every kind of bad frame at the daemon
        for _, payload in bad_payloads(time.time_ns() // 1000):
            bad_pub.put(payload)
            time.sleep(0.05)
        summary = sim.wait_done(120)
        time.sleep(1.5)  # one more status message
    finally:
        stop.set()
        daemon.join(15)
        sim.kill()
        bad_pub.undeclare()
        bad_session.close()
        st = status.last if status is not None else None
        if status is not None:
            status.close()
    assert not daemon.is_alive(), "daemon did not stop on request"
    published, accepted = summary["frames_published"], summary["estimates_accepted"]
    # the flight happened (the simulator renders in real time and publishes fewer frames when the machine is
    # loaded: 0.8 failed once under a parallel benchmark; what the daemon did with them is checked below)
    assert published >= 0.5 * case.duration_s * case.rate_hz, summary
    assert accepted >= 0.95 * (published - case.init_s * case.rate_hz), summary
    assert not summary["rejected"], f"the autopilot rejected estimates: {summary['rejected']}"
    err = estimate_errors(tmp_path)
    assert np.median(err) < case.median_max_m and np.percentile(err, 95) < case.p95_max_m, (
        f"median {np.median(err):.2f} m, 95th percentile {np.percentile(err, 95):.2f} m"
    )
    # the operator sees every bad frame, by reason, and the daemon kept estimating after them
    assert st is not None
    reasons = " ".join(st["frames"]["decode_errors"])
    for word in ("truncated", "encoding", "size", "future"):
        assert word in reasons, f"{word!r} not among the counted reasons: {st['frames']['decode_errors']}"
    assert sum(st["frames"]["decode_errors"].values()) >= 6
    assert st["estimator_errors"] == 0
    # the daemon read the simulated ArduPilot's external-vision parameters and found it set up for us
    assert st["link"]["autopilot"] == "ardupilot" and st["link"]["params_check"] is not None, st["link"]
    assert st["link"]["params_check"]["problems"] == {}, st["link"]["params_check"]
    # the companion's own log: every estimate with its outcome (CSV), the sent ones as TUM; everything the
    # autopilot received is in it, to float32 precision (MAVLink's)
    (csv_path,) = (tmp_path / "companion").glob("estimates-*.csv")
    rows = csv_path.read_text().splitlines()
    assert rows[0].startswith("stamp_s,x_m,y_m,z_m,roll_rad") and len(rows) > 1
    outcomes = [r.split(",")[15] for r in rows[1:]]
    ours = np.loadtxt(csv_path.with_suffix(".tum"), ndmin=2)
    assert len(ours) == outcomes.count("sent") and st["estimates_log"]["errors"] == 0
    received = np.loadtxt(tmp_path / "estimate.tum", ndmin=2)
    assert 0 < len(received) <= len(ours)
    gap = np.min(np.linalg.norm(received[:, None, 1:4] - ours[None, :, 1:4], axis=2), axis=1)
    assert np.max(gap) < 1e-3, f"{np.sum(gap >= 1e-3)} estimates the autopilot got are not in the log"
    # and the link's MAVLink log, as pymavlink reads it: every estimate sent, and what the autopilot said
    (tlog,) = (tmp_path / "companion").glob("mavlink-*.tlog")
    mlog = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    logged: dict[tuple[int, str], list[Any]] = {}
    while (m := mlog.recv_match()) is not None:
        logged.setdefault((m.get_srcComponent(), m.get_type()), []).append(m)
    mlog.close()
    vpe = logged.get((197, "VISION_POSITION_ESTIMATE"), [])
    assert len(vpe) == outcomes.count("sent") and st["link"]["tlog"]["errors"] == 0
    assert np.max(np.abs(np.array([[m.x, m.y, m.z] for m in vpe]) - ours[:, 1:4])) < 1e-3
    assert len(logged.get((1, "ATTITUDE"), [])) > 10 * case.duration_s  # the autopilot streams it at 50 Hz
    if case.estimator == "terrain_lba":
        # key frames went through the back-end: geo-fixes against the DEM, the adjustment, results applied
        c = st["estimator"]["counters"]
        assert c["keyframes"] >= 5 and c["lba_runs"] >= 4 and c["backend_applied"] >= 4, c
        assert c["fix_accepted"] >= 3 and c["alignments"] >= 1, c
        # and the log says when the map was put in the world (what the demo prints after a flight)
        assert "map aligned to the geo-fixes" in caplog.text
        assert c["fix_accepted"] + c["fix_rejected"] + c["fix_failed"] <= c["fix_attempts"], c
        assert c["backend_errors"] == 0 and c["lost"] == 0 and c["lba_failed"] == 0, c
        assert isinstance(st["estimator"]["no_fix_reasons"], dict)
        # every estimate the autopilot took came with a covariance, and it owned up to the error
        cons = summary["covariance_consistency"]
        assert cons["count"] == accepted and cons["within_95"] >= WITHIN_95_MIN, cons
        assert st["sigma_h_m"] is not None and 0.0 < st["sigma_h_m"] < 10.0, st["sigma_h_m"]
        # the daemon recorded its inputs; replayed at full speed (the adjustment used a fixed number of frames
        # after its key frame) the flight gives the same estimates every time, as many as in flight
        assert st["inputs_record"]["dropped"] == 0 and st["inputs_record"]["errors"] == 0, st["inputs_record"]
        runs = []
        for k in range(2):
            out = tmp_path / f"replay{k}"
            truth = ["--truth-tum", str(tmp_path / "truth_clock.tum")]  # the simulator's truth on our clock
            assert companion_main(["replay", str(tmp_path / "inputs"), "--out", str(out), *truth]) == 0
            runs.append(np.loadtxt(out / "estimates.csv", delimiter=",", skiprows=1, usecols=range(7)))
            summary_k = json.loads((out / "replay_summary.json").read_text())
            assert summary_k["estimator_errors"] == 0 and summary_k["bad"] == {}, summary_k
            e = summary_k["error_m"]
            assert e["count"] == summary_k["would_send"] and e["median"] < case.median_max_m, e
        np.testing.assert_array_equal(runs[0], runs[1])
        assert len(runs[0]) == len(rows) - 1, (len(runs[0]), len(rows) - 1)


class PtyBridge:
    """Serial cable emulation: a pty pair whose master end is pumped to and from a UDP peer.

    The daemon opens the pty's slave as a serial port; ``cut()`` stops the pump (the cable is pulled).
    """

    def __init__(self, udp_port: int) -> None:
        self.master, slave = os.openpty()
        self.dev = os.ttyname(slave)
        self._slave = slave
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(("127.0.0.1", udp_port))
        self.connected = threading.Event()
        self.connected.set()
        self._stop = threading.Event()
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        while not self._stop.is_set():
            fds: list[Any] = [self.master, self.sock]  # a pty fd and a socket
            r, _, _ = select.select(fds, [], [], 0.05)
            for fd in r:
                try:
                    data = os.read(self.master, 4096) if fd == self.master else self.sock.recv(4096)
                except OSError:
                    continue
                if not self.connected.is_set():
                    continue  # cable pulled: bytes are lost both ways
                with contextlib.suppress(OSError):  # the peer went away: the byte is lost, as on a cable
                    if fd == self.master:
                        self.sock.send(data)
                    else:
                        os.write(self.master, data)

    def close(self) -> None:
        self._stop.set()
        time.sleep(0.1)
        self.sock.close()
        os.close(self.master)
        os.close(self._slave)


def test_serial_link_cut_restored_and_autopilot_reboot(tmp_path: Path, dem_path) -> None:
    dem, ground = dem_path
    zsim, zcomp, mport = (
        free_port(socket.SOCK_STREAM),
        free_port(socket.SOCK_STREAM),
        free_port(socket.SOCK_DGRAM),
    )
    sim = SimProcess(tmp_path, f"udpin:127.0.0.1:{mport}", zsim, duration_s=36.0)
    assert sim.ready.wait(60)
    bridge = PtyBridge(mport)
    stop = threading.Event()
    cfg = companion_config(
        dem, ground, [f"tcp/127.0.0.1:{zsim}"], f"serial:{bridge.dev}:115200", [f"tcp/127.0.0.1:{zcomp}"]
    )
    daemon = threading.Thread(target=cmd_run, args=(cfg, stop), daemon=True)
    states: list[str] = []
    status: StatusWatch | None = None
    try:
        daemon.start()
        time.sleep(2.0)
        status = StatusWatch(f"tcp/127.0.0.1:{zcomp}")
        time.sleep(12.0)
        bridge.connected.clear()  # pull the cable for 5 s
        time.sleep(5.0)
        states.append(status.last["link"]["state"] if status.last else "?")
        bridge.connected.set()
        time.sleep(6.0)
        sim.proc.send_signal(signal.SIGUSR1)  # the autopilot reboots: its clock restarts at 0
        summary = sim.wait_done(120)
    finally:
        stop.set()
        daemon.join(15)
        sim.kill()
        bridge.close()
        st = status.last if status is not None else None
        if status is not None:
            status.close()
    assert states == ["down"], f"link state while the cable was out: {states}"
    recs_t = np.loadtxt(tmp_path / "estimate.tum", ndmin=2)[:, 0]
    t_cut = 14.0 - 4.0  # flight time when the cable was pulled (after the 4 s start delay), roughly
    after_restore = recs_t[recs_t > t_cut + 7.0]
    assert len(after_restore) >= 10, "no estimates after the link came back"
    assert summary is not None, "the simulated autopilot did not finish"
    assert summary["resets"] >= 1, "reset_counter was not bumped after the autopilot rebooted"
    assert st is not None, "no status from the daemon"
    assert st["link"]["autopilot_resets"], st["link"]
    # estimates kept flowing after the reboot, stamped in the new boot clock
    assert recs_t.max() > 30.0 - 4.0, f"last estimate at {recs_t.max():.1f} s"
