"""Daemon latency and sustained rate: frame capture to VISION_POSITION_ESTIMATE received by the autopilot.

The real daemon runs as its own process (``python -m companion run``) against the simulated autopilot on
UDP loopback, fed by Zenoh. Frames are rendered before the clock starts, so the renderer's cost is not
counted; each is published at its capture time at the target rate. Latency = arrival time at the autopilot
(its boot clock) minus the capture time the estimate carries (mapped to that clock through TIMESYNC).
CPU per frame = the daemon process's user+system time over the run / frames it received.

    python -m bench latency [--quick] [--json bench/results/latency.json] [--rate 50] [--estimator georef]
        [--opencv-threads N] [--record-inputs raw|png]

``--record-inputs``: the daemon also records its inputs (``daemon.record_inputs``, frames as
``daemon.record_frames``), to measure what the record costs the frames' latency; the bag's size and the
frames in it are reported.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import parser, table, write_json

ROOT = Path(__file__).resolve().parents[1]


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    ticks = os.sysconf("SC_CLK_TCK")
    return (int(fields[11]) + int(fields[12])) / ticks


def run(
    rate_hz: float,
    duration_s: float,
    estimator: str,
    seed: int,
    opencv_threads: int | None = None,
    record: str = "off",
) -> dict:
    from companion.config import load_config
    from companion.geometry import CameraIntrinsics, camera_pose, rpy_from_rot
    from companion.io.dem_store import save_dem_npz
    from companion.io.frames import encode_image
    from companion.io.zenoh_io import open_session
    from sim_bridge.autopilot_link import SimAutopilotLink, SimAutopilotOptions
    from sim_bridge.demo import free_port
    from sim_bridge.render import VisibleRenderer
    from sim_bridge.sim import SimConfig, make_trajectory
    from sim_bridge.terrain import degrade_dem, make_scene

    scene = make_scene("08", seed=seed)
    dem, deg = degrade_dem(scene.dem, seed=seed + 7)
    ground = float(np.nanmean(scene.dem.height_m))
    cfg = SimConfig(duration_s=duration_s + 10.0, camera_rate_hz=rate_hz)
    traj = make_trajectory(cfg, ground)
    intr = CameraIntrinsics.from_focal_sensor(480, 480, 36.0, 36.0)
    renderer = VisibleRenderer(scene.dem, scene.albedo, scene.sun, intr)
    n = int(duration_s * rate_hz)
    t_frames = np.arange(n) / rate_hz + 5.0  # start once the vehicle is at speed
    states = traj.states(t_frames)
    print(f"rendering {n} frames of 480x480 ...", flush=True)
    images = []
    for k, s in enumerate(states):
        R_wc, p_c = camera_pose(s.R_world_body, s.p_world)
        images.append(renderer.render(R_wc, p_c, seed=seed * 7919 + k))

    tmp = Path(tempfile.mkdtemp(prefix="bench-latency-"))
    save_dem_npz(tmp / "dem.npz", dem)
    zport, mport = free_port(socket.SOCK_STREAM), free_port(socket.SOCK_DGRAM)
    t0_us = [0]

    def truth(t_us: int) -> dict:
        t = 5.0 + (t_us - t0_us[0]) * 1e-6 if t0_us[0] else 5.0
        st = traj.state_at(t)
        R = st.R_world_body
        return {
            "rpy_rad": rpy_from_rot(R),
            "p_ned_m": st.p_world,
            "v_ned_mps": st.v_world,
            "range_m": float(
                (-st.p_world[2] - scene.dem.height_at(st.p_world[0], st.p_world[1])[0]) / R[2, 2]
            ),
            "accel_body_mps2": R.T @ (st.a_world - traj.g_world),
            "gyro_body_rps": st.omega_body_rps,
        }

    # This measures the companion, so the simulated autopilot accepts samples at any spacing, as PX4 does;
    # ArduPilot's EKF3 drops samples closer than 20 ms (at exactly 50 Hz, jitter of a few microseconds in
    # the time-synced stamps drops some), so with ArduPilot keep mavlink.max_rate_hz at about 45 or below.
    ap = SimAutopilotLink(
        f"udpin:127.0.0.1:{mport}",
        truth=truth,
        options=SimAutopilotOptions(planet="mars", range_max_m=300.0, ext_nav_min_interval_us=0),
    )
    session = open_session("peer", [], [f"tcp/127.0.0.1:{zport}"], False)
    pub = session.declare_publisher("uav/camera/nadir")
    s0 = states[0]
    yaw0 = float(np.degrees(np.arctan2(s0.R_world_body[1, 0], s0.R_world_body[0, 0])))
    overrides: dict[str, object] = {
        "zenoh.connect": [f"tcp/127.0.0.1:{zport}"],
        "mavlink.connection": f"udpout:127.0.0.1:{mport}",
        "mavlink.max_rate_hz": min(rate_hz, 50.0),
        "dem.path": str(tmp / "dem.npz"),
        "estimator.kind": estimator,
        "estimator.initial_position_ned_m": [float(v) for v in s0.p_world],
        "estimator.initial_yaw_deg": yaw0,
        "daemon.log_level": "warning",
    }
    if opencv_threads is not None:
        overrides["daemon.opencv_threads"] = opencv_threads
    if record != "off":
        overrides["daemon.record_inputs"] = str(tmp / "inputs")
        overrides["daemon.record_frames"] = record
    config = ROOT / "configs/sim_mars.toml"
    daemon_cfg = load_config(config).daemon  # what the daemon runs with unless overridden
    cmd = [sys.executable, "-m", "companion", "run", "--config", str(config)]
    cmd += [arg for k, v in overrides.items() for arg in ("--set", f"{k}={json.dumps(v)}")]
    log = open(tmp / "companion.log", "w")
    ap.start()
    comp = subprocess.Popen(
        cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, OMP_NUM_THREADS="1")
    )
    try:
        time.sleep(4.0)  # Zenoh connect, TIMESYNC convergence, DEM load
        cpu0 = _cpu_s(comp.pid)
        t0_us[0] = time.time_ns() // 1000
        period_us = int(1e6 / rate_hz)
        for k, img in enumerate(images):
            capture = t0_us[0] + k * period_us
            wait = (capture - time.time_ns() // 1000) * 1e-6
            if wait > 0:
                time.sleep(wait)
            pub.put(encode_image(img, capture, frame_id="nadir", encoding="mono8"))
        time.sleep(1.0)
        cpu1 = _cpu_s(comp.pid)
    finally:
        comp.send_signal(signal.SIGINT)
        try:
            comp.wait(timeout=15)
        except subprocess.TimeoutExpired:
            comp.kill()
        ap.stop()
        pub.undeclare()
        session.close()
        log.close()
    recorded: dict[str, float] = {}
    if record != "off":
        from rosbags.rosbag2 import Reader

        with Reader(tmp / "inputs") as bag:
            frames = sum(c.msgcount for c in bag.connections if c.topic == "/uav/camera/nadir")
        size = sum(f.stat().st_size for f in (tmp / "inputs").iterdir())
        recorded = {"frames": frames, "mb": size / 1e6, "mb_per_s": size / 1e6 / (n / rate_hz)}
    recs = [r for r in ap.accepted() if r.usec >= t0_us[0] + ap.true_offset_us() - 1000]
    lat_ms = np.array([(r.recv_boot_us - r.usec) / 1000.0 for r in recs])
    span_s = n / rate_hz
    return {
        "estimator": estimator,
        "opencv_threads": opencv_threads if opencv_threads is not None else daemon_cfg.opencv_threads,
        "rate_hz": rate_hz,
        "duration_s": span_s,
        "frames_sent": n,
        "estimates_received": len(recs),
        "fps": len(recs) / span_s,
        "p50_ms": float(np.percentile(lat_ms, 50)) if len(lat_ms) else None,
        "p99_ms": float(np.percentile(lat_ms, 99)) if len(lat_ms) else None,
        "max_ms": float(lat_ms.max()) if len(lat_ms) else None,
        "cpu_ms_per_frame": 1000.0 * (cpu1 - cpu0) / n,
        "rejected_by_autopilot": ap.rejected(),
        "record_inputs": record,
        "recorded": recorded,
        "dem_degradation": deg.describe(),
        "companion_log": str(tmp / "companion.log"),
    }


def main(argv: list[str]) -> int:
    p = parser("latency", __doc__.split("\n\n")[0])
    p.add_argument("--rate", type=float, default=50.0, help="frames per second published (default 50)")
    p.add_argument("--estimator", default="georef", choices=["georef", "terrain_lba"])
    p.add_argument(
        "--opencv-threads",
        type=int,
        default=None,
        help="the daemon's daemon.opencv_threads (default: the config's, 1; 0 = OpenCV's default, one per core)",
    )
    p.add_argument(
        "--record-inputs",
        default="off",
        choices=["off", "raw", "png"],
        help="the daemon records its inputs, frames raw or in PNG (daemon.record_frames); default off",
    )
    a = p.parse_args(argv)
    duration = 8.0 if a.quick else 30.0
    r = run(a.rate, duration, a.estimator, a.seed, a.opencv_threads, a.record_inputs)
    print(
        table(
            ["estimator", "rate Hz", "sent", "received", "fps", "p50 ms", "p99 ms", "max ms", "CPU ms/frame"],
            [
                [
                    r["estimator"],
                    r["rate_hz"],
                    r["frames_sent"],
                    r["estimates_received"],
                    r["fps"],
                    r["p50_ms"],
                    r["p99_ms"],
                    r["max_ms"],
                    r["cpu_ms_per_frame"],
                ]
            ],
            title=f"frame capture -> VISION_POSITION_ESTIMATE received, 480x480, {os.cpu_count()} cores, "
            f"OpenCV threads {r['opencv_threads'] or 'default'}, record {r['record_inputs']} "
            f"(targets: >= 50 fps, p99 <= 30 ms); {r['dem_degradation']}",
        )
    )
    if r["rejected_by_autopilot"]:
        print(f"rejected by the autopilot: {r['rejected_by_autopilot']}")
    if r["recorded"]:
        rec = r["recorded"]
        print(
            f"recorded {rec['frames']} of {r['frames_sent']} frames, {rec['mb']:.1f} MB ({rec['mb_per_s']:.2f} MB/s)"
        )
    write_json(a.json, {"quick": a.quick, **r})
    return 0
