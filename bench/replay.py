"""Recorded flights replayed through the daemon's path (``companion replay``): accuracy and speed.

Each of paper 2's ten Europa trajectories is flown by the simulator and written as a rosbag2
(``sim_bridge.flight_bag``: the camera pair at 2 Hz, the autopilot's IMU at 100 Hz with its attitude, the range
finder, the odometry the filter starts from, the truth), then replayed with ``configs/europa_dual_ekf.toml`` in
each mode. Unlike ``bench thermal_ekf`` (the filter on cached detections, started from the truth with 0.01°)
this is the path a bench replay of a vehicle's recording takes: CDR decoding, pairing, the start from the
autopilot's odometry and attitude (its yaw off by the drawn heading bias of the simulated autopilot, 1.1°
at 1 sigma: "start yaw err" in the table, the same for every mode of a flight), SIFT on every frame. A second table
flies trajectories through a wide-angle lens and replays them with and without its model.

Printed per trajectory and mode: estimates, mean / max error against the truth (m), the final error over the
distance flown (%), NEES (2 when the covariance is right), and the replay's speed (times real time).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import parser, table, write_json
from companion.config import CompanionConfig, load_config, parse_config
from companion.factory import build_estimator
from companion.replay import replay_bag
from sim_bridge.flight_bag import FlightBagOptions, write_flight_bag

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "europa_dual_ekf.toml"
MODES = ("visible", "thermal", "dual")
LENS = (-0.12, 0.05, 0.001, -0.0005, -0.01)


def _config(mode: str, calibration: dict[str, Any] | None = None) -> CompanionConfig:
    data = load_config(CONFIG).model_dump()
    data["estimator"]["ekf"]["mode"] = mode
    for cam in ("visible", "thermal"):
        data["cameras"][cam].update(calibration or {})
    return parse_config(data)


def _run(bag: Path, cfg: CompanionConfig, out: Path, flight_s: float) -> dict[str, Any]:
    s = replay_bag(bag, cfg, build_estimator(cfg), out)
    e, c = s.error_m or {}, s.covariance_consistency or {}
    return {
        "estimates": s.would_send,
        "mean_m": e.get("mean"),
        "max_m": e.get("max"),
        "final_m": e.get("final"),
        "final_over_distance_pct": None
        if not e.get("count")
        else 100.0 * e["final"] / (s.distance_m or np.nan),
        "nees": c.get("nees_mean"),
        "wall_s": s.wall_s,
        "x_real_time": flight_s / s.wall_s,
        "ms_per_pair": s.ms_per_frame_set,
        "estimator_errors": s.estimator_errors,
    }


def main(argv: list[str] | None = None) -> int:
    p = parser("replay", __doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=60.0, help="seconds of each flight (default 60)")
    a = p.parse_args(argv)
    trajs = ["1", "3"] if a.quick else [str(i) for i in range(1, 11)]
    lens_trajs = ["1"] if a.quick else ["1", "4", "7"]
    duration = 20.0 if a.quick else a.duration
    res: dict[str, Any] = {"settings": {"duration_s": duration, "seed": a.seed, "config": str(CONFIG.name),
                                        "camera_hz": FlightBagOptions().camera_hz, "lens": list(LENS)},
                           "flights": {}, "lens": {}}  # fmt: skip
    rows, lens_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for t in trajs:
            bag = Path(tmp) / f"t{t}"
            w0 = time.perf_counter()
            made = write_flight_bag(bag, FlightBagOptions(trajectory=t, seed=a.seed, duration_s=duration))
            write_s = time.perf_counter() - w0
            res["flights"][t] = {
                "distance_m": made["distance_m"],
                "write_s": write_s,
                "start_yaw_error_deg": made["yaw_bias_deg"],
                "modes": {},
            }
            for mode in MODES:
                r = _run(bag, _config(mode), Path(tmp) / f"out{t}{mode}", made["duration_s"])
                res["flights"][t]["modes"][mode] = r
                rows.append([t, made["yaw_bias_deg"], mode, r["estimates"], r["mean_m"], r["max_m"],
                             r["final_over_distance_pct"], r["nees"], r["x_real_time"], r["ms_per_pair"]])  # fmt: skip
                print(
                    f"  trajectory {t} {mode}: mean {r['mean_m']:.3f} m, x{r['x_real_time']:.1f}", flush=True
                )
            for mode_dir in Path(tmp).glob(f"out{t}*"):
                for f in mode_dir.iterdir():
                    f.unlink()
            for f in bag.iterdir():
                f.unlink()
        for t in lens_trajs:
            bag = Path(tmp) / f"lens{t}"
            made = write_flight_bag(
                bag, FlightBagOptions(trajectory=t, seed=a.seed, duration_s=duration, distortion=LENS)
            )
            K = made["camera_K"]
            cal = {
                "fx_px": K["fx"],
                "fy_px": K["fy"],
                "cx_px": K["cx"],
                "cy_px": K["cy"],
                "distortion": list(LENS),
            }
            with_lens = _run(bag, _config("dual", cal), Path(tmp) / f"lo{t}", made["duration_s"])
            without = _run(bag, _config("dual"), Path(tmp) / f"lx{t}", made["duration_s"])
            res["lens"][t] = {"with_model": with_lens, "without_model": without}
            for name, r in (("lens model", with_lens), ("pinhole assumed", without)):
                lens_rows.append(
                    [t, name, r["estimates"], r["mean_m"], r["max_m"], r["nees"], r["ms_per_pair"]]
                )
    print()
    print(table(["traj", "start yaw err deg", "mode", "estimates", "mean m", "max m", "final/dist %", "NEES",
                 "x real time", "ms/pair"],
                rows, f"Europa flights replayed ({duration:g} s each, camera pair at 2 Hz, seed {a.seed})"))  # fmt: skip
    for mode in MODES:
        m = [res["flights"][t]["modes"][mode]["mean_m"] for t in trajs]
        x = [res["flights"][t]["modes"][mode]["x_real_time"] for t in trajs]
        res.setdefault("average", {})[mode] = {"mean_m": float(np.mean(m)), "x_real_time": float(np.mean(x))}
        print(
            f"  {mode:8s} average over the trajectories: mean error {np.mean(m):.3f} m, x{np.mean(x):.1f} real time"
        )
    print()
    print(table(["traj", "cameras", "estimates", "mean m", "max m", "NEES", "ms/pair"], lens_rows,
                f"dual through a wide-angle lens (OpenCV k1..k3 {list(LENS)})"))  # fmt: skip
    write_json(a.json, {"bench": "replay", "quick": a.quick, **res})
    return 0
