"""The README's main job: a simulated flight with the companion in the loop, all on loopback.

Starts ``python -m sim_bridge sim`` (autopilot + camera) and ``python -m companion run`` as two processes,
shows progress while they fly, then prints the error table (evo APE: mean / RMSE / max ...) and writes the
trajectories (TUM) and a trajectory-vs-truth plot (PNG) into the run directory.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.io.dem_store import save_dem_npz
from sim_bridge.sim import make_trajectory


def free_port(kind: int) -> int:
    """A port the OS says is free right now on 127.0.0.1 (TCP or UDP)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def ape_table(truth_tum: Path, est_tum: Path, max_diff_s: float = 0.02) -> dict[str, float]:
    """Absolute position error statistics (metres) of the estimate against the truth, with evo.

    No alignment: the estimate is in the world frame (geo-referenced), so any offset is an error.
    """
    from evo.core import metrics, sync
    from evo.tools import file_interface

    ref = file_interface.read_tum_trajectory_file(str(truth_tum))
    est = file_interface.read_tum_trajectory_file(str(est_tum))
    ref, est = sync.associate_trajectories(ref, est, max_diff=max_diff_s)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    stats = {k: float(v) for k, v in ape.get_all_statistics().items()}
    stats["matched"] = int(est.num_poses)
    return stats


def plot(run_dir: Path, truth_tum: Path, est_tum: Path, title: str) -> Path:
    """``trajectory.png`` of the run (``companion.report``) from its TUM files."""
    from companion.report import trajectory_plot

    tr = np.loadtxt(truth_tum, ndmin=2)
    es = np.loadtxt(est_tum, ndmin=2).reshape(-1, 8)
    return trajectory_plot(run_dir / "trajectory.png", tr[:, 0], tr[:, 1:4], es[:, 0], es[:, 1:4], title)


class StatusWatch:
    """Keeps the companion's last status message (Zenoh ``companion/status``, as an operator would see it)."""

    def __init__(self, endpoint: str, key: str = "companion/status") -> None:
        from companion.io.zenoh_io import StatusSubscriber, open_session

        self.last: dict[str, Any] | None = None
        self.session = open_session("peer", [endpoint], [], False)
        self.sub = StatusSubscriber(self.session, self._on, key)

    def _on(self, status: dict[str, Any]) -> None:
        self.last = status

    def close(self) -> None:
        self.sub.close()
        self.session.close()


def estimator_line(status: dict[str, Any] | None) -> str:
    """One line of the estimator's running totals from a status message ("" if none)."""
    if not status:
        return ""
    c = status.get("estimator", {}).get("counters", {})
    if "lba_runs" in c:  # terrain_lba: what its back-end did
        return (
            f"key frames {c['keyframes']}, LBA runs {c['lba_runs']} ({c['lba_failed']} failed), "
            f"geo-fixes accepted {c['fix_accepted']} / rejected by the gate {c['fix_rejected']} / "
            f"failed {c['fix_failed']} of {c['fix_attempts']}, alignments {c['alignments']}, "
            f"re-initialisations {c['reinit']}"
            + (f", back-end worker restarts {c['backend_restarts']}" if c.get("backend_restarts") else "")
        )
    return ", ".join(f"{k} {v}" for k, v in c.items())


def alignment_notes(log_path: Path, limit: int = 6) -> list[str]:
    """The companion's log lines that say how its map was put in the world (terrain_lba's start-up heading
    and alignments) and when the terrain stopped and started giving fixes, without the time and level."""
    key = "companion.estimators.terrain_lba: "
    try:
        lines = log_path.read_text(errors="replace").splitlines()
    except OSError:
        return []
    notes = [ln[ln.index(key) + len(key) :] for ln in lines if key in ln]
    keep = ("heading from the terrain", "map ", "no terrain fix used", "terrain fixes again")
    return [n for n in notes if n.startswith(keep)][:limit]


def run_demo(a: argparse.Namespace) -> int:
    from sim_bridge.cli import sim_config_from_args
    from sim_bridge.terrain import degrade_dem, make_scene

    run_dir = Path(a.out or f"runs/demo-{time.strftime('%Y%m%d-%H%M%S')}").resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    zport, mport = free_port(socket.SOCK_STREAM), free_port(socket.SOCK_DGRAM)
    zstatus = free_port(socket.SOCK_STREAM)  # the companion listens here; the demo reads its status
    print(f"run directory: {run_dir}", flush=True)
    print(f"scene {a.scene}: generating terrain and the degraded DEM the companion gets ...", flush=True)
    scene = make_scene(a.scene, seed=a.seed)
    dem, degradation = degrade_dem(scene.dem, seed=a.seed + 7)
    save_dem_npz(run_dir / "dem.npz", dem)
    cfg = sim_config_from_args(a)
    start = make_trajectory(cfg, float(np.nanmean(scene.dem.height_m))).state_at(0.0)
    yaw0 = float(np.degrees(np.arctan2(start.R_world_body[1, 0], start.R_world_body[0, 0])))
    p0 = [round(float(v), 3) for v in start.p_world]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    sim_cmd = [
        sys.executable,
        "-m",
        "sim_bridge",
        "sim",
        "--scene",
        a.scene,
        "--seed",
        str(a.seed),
        "--trajectory",
        a.trajectory,
        "--duration",
        str(a.duration),
        "--speed",
        str(a.speed),
        "--height",
        str(a.height),
        "--camera-rate",
        str(a.camera_rate),
        "--wait-companion",
        "60",
        "--start-delay",
        str(2.0 if a.start_delay is None else a.start_delay),
        "--compass-offset",
        str(a.compass_offset),
        "--imu-message",
        a.imu_message,
        "--zenoh-listen",
        f"tcp/127.0.0.1:{zport}",
        "--mavlink",
        f"udpin:127.0.0.1:{mport}",
        "--out",
        str(run_dir),
    ]
    overrides = {
        "zenoh.connect": [f"tcp/127.0.0.1:{zport}"],
        "zenoh.listen": [f"tcp/127.0.0.1:{zstatus}"],
        "mavlink.connection": f"udpout:127.0.0.1:{mport}",
        "dem.path": str(run_dir / "dem.npz"),
        "estimator.kind": a.estimator,
        "estimator.initial_position_ned_m": p0,
        "estimator.initial_yaw_deg": round(yaw0 + a.compass_offset, 3),
        "cameras.nadir.key": cfg.camera_key,
    }
    if a.record_inputs:
        overrides["daemon.record_inputs"] = str(run_dir / "inputs")
    if abs(a.compass_offset) > 30.0:  # beyond the default search: the vehicle's owner would set it
        overrides["estimator.terrain_lba.heading_search_deg"] = 180.0
        overrides["estimator.terrain_lba.compass_sigma_deg"] = 180.0
        print(
            "compass more than 30 deg off: the companion searches all headings and trusts none until the"
            " terrain gives one (heading_search_deg 180, compass_sigma_deg 180)"
        )
    comp_cmd = [sys.executable, "-m", "companion", "run", "--config", a.config]
    for k, v in overrides.items():
        comp_cmd += ["--set", f"{k}={json.dumps(v)}"]
    sim_log = open(run_dir / "sim.log", "w")
    comp_log = open(run_dir / "companion.log", "w")
    sim = subprocess.Popen(sim_cmd, stdout=subprocess.PIPE, stderr=sim_log, text=True, env=env)
    comp: subprocess.Popen | None = None
    watch: StatusWatch | None = None
    summary: dict[str, Any] | None = None
    try:
        assert sim.stdout is not None
        for line in sim.stdout:
            try:
                msg = json.loads(line)
            except json.JSONDecodeError:
                continue
            if msg.get("ready"):
                comp = subprocess.Popen(
                    comp_cmd, stdout=comp_log, stderr=subprocess.STDOUT, text=True, env=env
                )
                watch = StatusWatch(f"tcp/127.0.0.1:{zstatus}")
                print(
                    f"flying: {a.trajectory} over scene {a.scene} ({scene.name}), {a.duration:.0f} s at "
                    f"{a.speed} m/s, {a.height:.0f} m above ground, camera {a.camera_rate:g} Hz; "
                    f"companion estimator: {a.estimator}",
                    flush=True,
                )
                print(
                    f"  (its status line, from another terminal: companion watch --connect tcp/127.0.0.1:{zstatus})",
                    flush=True,
                )
            elif "progress" in msg:
                p = msg["progress"]
                err, sig = p["last_error_m"], p.get("last_sigma_m", float("nan"))
                err_s = f"{err:6.2f} m" if err == err else "   -   "
                sig_s = f" (its sigma {sig:5.2f} m)" if sig == sig else ""
                print(
                    f"  t {p['t_s']:6.1f}/{p['duration_s']:.0f} s   frames {p['frames']:5d}   "
                    f"estimates accepted {p['estimates']:5d}   rejected {p['rejected']:3d}   "
                    f"last error {err_s}{sig_s}",
                    flush=True,
                )
                if comp is not None and comp.poll() is not None:
                    print(
                        f"companion exited early with code {comp.returncode}; see {run_dir / 'companion.log'}"
                    )
                    sim.send_signal(signal.SIGINT)
            elif "done" in msg:
                summary = msg["done"]
        sim.wait(timeout=30)
        time.sleep(1.2)  # the companion's next status message, with the flight's last estimates
    finally:
        status = watch.last if watch is not None else None
        if watch is not None:
            watch.close()
        if comp is not None and comp.poll() is None:
            comp.send_signal(signal.SIGINT)
            try:
                comp.wait(timeout=15)
            except subprocess.TimeoutExpired:
                comp.kill()
        if sim.poll() is None:
            sim.kill()
        sim_log.close()
        comp_log.close()
    if summary is None:
        print(f"the simulator did not finish; see {run_dir / 'sim.log'}")
        return 1
    truth, est = run_dir / "truth.tum", run_dir / "estimate.tum"
    published = summary["frames_published"]
    accepted = summary["estimates_accepted"]
    print()
    print(f"DEM given to the companion: {degradation.describe()}")
    print(
        f"frames published {published}, estimates accepted by the autopilot {accepted} "
        f"({100.0 * accepted / max(published, 1):.1f} %), rejected {summary['rejected']}, "
        f"distance flown {summary['distance_m']:.0f} m"
    )
    line = estimator_line(status)
    if line:
        print(f"companion estimator {a.estimator}: {line}")
    for note in alignment_notes(run_dir / "companion.log"):
        print(f"  {note}")
    if accepted == 0:
        print("no estimate reached the autopilot: see companion.log")
        return 1
    stats = ape_table(truth, est)
    (run_dir / "ape.json").write_text(
        json.dumps({"ape_m": stats, **summary, "companion_status": status}, indent=2, default=float)
    )
    png = plot(run_dir, truth, est, f"scene {a.scene} {a.trajectory}, {a.estimator}")
    print()
    print("absolute position error (evo APE, translation, no alignment), metres")
    print(f"{'estimates':>10} {'mean':>8} {'median':>8} {'rmse':>8} {'max':>8} {'std':>8}")
    print(
        f"{stats['matched']:>10d} {stats['mean']:>8.3f} {stats['median']:>8.3f} {stats['rmse']:>8.3f} "
        f"{stats['max']:>8.3f} {stats['std']:>8.3f}"
    )
    cons = summary.get("covariance_consistency", {})
    if cons.get("count"):
        print(
            f"the companion's own horizontal sigma: mean {cons['sigma_mean_m']:.2f} m; errors inside its 95 % "
            f"ellipse: {100.0 * cons['within_95']:.0f} % of the estimates (95 % when it knows how wrong it is)"
        )
    print(f"wrote {truth.name}, {est.name} (TUM), {png.name}, ape.json in {run_dir}")
    if a.record_inputs:
        print(
            f"the companion's inputs are in {run_dir / 'inputs'}; replay them (as fast as it goes; --rate 1 at "
            f"the flight's pace):\n  .venv/bin/companion replay {run_dir / 'inputs'} --out {run_dir / 'replay'} "
            f"--truth-tum {run_dir / 'truth_clock.tum'}"
        )
    return 0
