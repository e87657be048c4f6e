"""The EKF's hand-over start when the autopilot's IMU or ATTITUDE comes after the first frames, and an IMU dropout.

``python -m bench ekf_start [--quick] [--json PATH] [--trials 1] [--trajectories 1,2,..] [--late 2.5]
[--mode dual] [--workers 2]``

The ``thermal_ekf`` benchmark's flights (same trajectories, seeds, sensors, renderer and detections), flown
through the daemon's start instead of a given initial state: the filter takes its position and velocity from
LOCAL_POSITION_NED (10 Hz) and its attitude from ATTITUDE (50 Hz), both the truth with an offset drawn per
flight from the filter's prior (``thermal_ekf.BENCH_OPTIONS``), streaming from 2 s before the first frame
pair. Variants, paired on the same flight:

- ``reference``: every autopilot stream there from the start;
- ``imu_late``: the IMU only from ``--late`` s after the first frame pair (ArduPilot sends RAW_IMU once the
  companion asks for it, ``deploy/README.md`` section 5); the filter starts at once and propagates on its
  constant-velocity motion model until the IMU comes (``EkfOptions.imu_hold_max_s``);
- ``attitude_late_*``: ATTITUDE only from ``--late`` s on, the configured heading 0 (``[estimator]
  initial_yaw_deg``'s default), the filter started at once (``at_once``: ``EkfOptions.start_wait_s`` 0, what the
  estimator did before 2026-12-07) or waiting for it (``wait``: the default, 10 s);
- ``imu_dropout_*``: the IMU silent for ``--late`` s from ``DROPOUT_AT_S`` (60 s) after the first frame pair, the
  filter propagating on the last sample held (``held``: ``EkfOptions.imu_hold_max_s`` unbounded, what it did
  before 2026-12-07) or on the constant-velocity motion model from 0.1 s after it (``motion_model``: the
  default).

Per variant: the mean position error and E (%, slope of the error against distance) over the frames from
``--late`` + 1 s on (every variant estimates those), the worst flight's mean error, the frame pairs estimated,
and the paired difference to the reference with its standard error. Default: the ten trajectories, trial 0
(about 7 min on two cores); --quick: trajectories 1 and 6.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from dataclasses import replace  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

import bench.thermal_ekf as T  # noqa: E402
from bench.common import parser, table, write_json  # noqa: E402
from companion.constants import GRAVITY_MPS2, R_BODY_CAM_NADIR  # noqa: E402
from companion.daemon import feed_sample  # noqa: E402
from companion.estimators.vis_thermal_ekf import VisThermalEkfEstimator  # noqa: E402
from companion.geometry import rpy_from_rot  # noqa: E402
from companion.types import AttitudeSample, LocalPositionSample  # noqa: E402

VARIANTS: dict[str, tuple[str | None, float, float]] = {
    "reference": (None, 10.0, 0.1),
    "imu_late": ("imu", 10.0, 0.1),
    "attitude_late_at_once": ("attitude", 0.0, 0.1),
    "attitude_late_wait": ("attitude", 10.0, 0.1),
    "imu_dropout_held": ("dropout", 10.0, float("inf")),
    "imu_dropout_motion_model": ("dropout", 10.0, 0.1),
}
"""Variant -> (the stream that comes late or drops out, EkfOptions.start_wait_s, EkfOptions.imu_hold_max_s)."""
DROPOUT_AT_S = 60.0
"""The IMU dropout begins this long after the first frame pair."""
AUTOPILOT_LEAD_S = 2.0
"""The autopilot's streams begin this long before the first frame pair (unless late)."""


def fly(job: tuple[str, int, int, float, str]) -> dict[str, Any]:
    """One flight, every variant on the same rendered frames and detections."""
    name, trial, seed, late_s, mode = job
    fl = T.render_flight(name, trial, seed)
    base, rng = fl.base, fl.rng
    dp = rng.normal(0, base.initial_position_sigma_m, 3)
    dv = rng.normal(0, base.initial_velocity_sigma_mps, 3)
    sig = [base.initial_tilt_sigma_rad, base.initial_tilt_sigma_rad, base.initial_yaw_sigma_rad]
    drpy = rng.normal(0, 1, 3) * np.array(sig)
    traj = fl.traj
    t_ap = np.arange(traj.t0_s - AUTOPILOT_LEAD_S, traj.t1_s, 0.02)
    st_ap = traj.states(np.clip(t_ap, traj.t0_s, traj.t1_s))  # before take-off: at the first state
    us = np.round(t_ap * 1e6).astype(np.int64)
    attitude = [AttitudeSample(int(t), *(rpy_from_rot(s.R_world_body) + drpy)) for t, s in zip(us, st_ap)]
    local = [LocalPositionSample(int(t), s.p_world + dp, s.v_world + dv) for t, s in zip(us[::5], st_ap[::5])]
    stamps = np.array([t for t, _ in fl.frames])
    t_late = int(stamps[0] + late_s * 1e6)
    gap = (int(stamps[0] + DROPOUT_AT_S * 1e6), int(stamps[0] + (DROPOUT_AT_S + late_s) * 1e6))
    scored = stamps >= stamps[0] + (late_s + 1.0) * 1e6
    out: dict[str, Any] = {"name": name, "trial": trial, "seed": seed}
    for variant, (late, wait_s, hold_s) in VARIANTS.items():
        opts = replace(
            base,
            seed=seed * 100_003 + trial,
            mode=mode,
            sampling="kde",
            start_wait_s=wait_s,
            imu_hold_max_s=hold_s,
        )
        est = VisThermalEkfEstimator(
            opts,
            {"visible": fl.intrinsics, "thermal": fl.intrinsics},
            {"visible": R_BODY_CAM_NADIR, "thermal": R_BODY_CAM_NADIR},
            None,
            gravity_mps2=GRAVITY_MPS2["europa"],
        )
        samples: list[Any] = [*local, *fl.altimeter]
        samples += [a for a in attitude if late != "attitude" or a.stamp_us >= t_late]
        samples += [
            s
            for s in fl.imu
            if not (
                late == "imu" and s.stamp_us < t_late or late == "dropout" and gap[0] <= s.stamp_us < gap[1]
            )
        ]
        # the daemon's order: every sample stamped at or before a frame pair reaches the estimator before it
        events = sorted(
            [(s.stamp_us, 0, s) for s in samples] + [(t, 1, d) for t, d in fl.frames], key=lambda e: e[:2]
        )
        est_at: dict[int, np.ndarray] = {}
        for t, kind, obj in events:
            if kind == 0:
                feed_sample(est, obj)
            elif (e := est.on_detections(t, obj)) is not None:
                est_at[t] = e.p_body_in_world_m
        est.close()
        keep = np.array([t in est_at for t in stamps]) & scored
        err = np.array([np.linalg.norm(est_at[t] - p) for t, p in zip(stamps[keep], fl.truth[keep])])
        out[variant] = {
            "mean_error_m": float(np.mean(err)),
            "E_percent": T.slope_percent(fl.distance_m[keep], err),
            "estimates": len(est_at),
            "steps_without_imu": est.slam.counters.steps_without_imu,
            "scored_frames": int(keep.sum()),
            "waiting": {k: v for k, v in est.counters.items() if k.startswith("waiting_for")},
        }
    out["frames"] = len(stamps)
    return out


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    res: dict[str, Any] = {}
    for v in VARIANTS:
        m = np.array([r[v]["mean_error_m"] for r in runs])
        d = m - np.array([r["reference"]["mean_error_m"] for r in runs])
        res[v] = {
            "mean_error_m": float(np.mean(m)),
            "median_of_mean_error_m": float(np.median(m)),
            "worst_mean_error_m": float(np.max(m)),
            "E_percent": float(np.mean([r[v]["E_percent"] for r in runs])),
            "estimates": float(np.mean([r[v]["estimates"] for r in runs])),
            "diff_m": float(np.mean(d)),
            "diff_sem_m": float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan"),
        }
    return res


def main(argv: list[str] | None = None) -> int:
    p = parser("ekf_start", __doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=1, help="trials per trajectory (default 1)")
    p.add_argument("--trajectories", type=str, default=None, help="comma-separated names (default all)")
    p.add_argument(
        "--late", type=float, default=2.5, help="s a stream comes late, and the IMU dropout's length"
    )
    p.add_argument("--mode", choices=("visible", "thermal", "dual"), default="dual")
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args(argv)
    names = T.trajectory_names(a.trajectories, a.quick)
    jobs = [(n, k, a.seed, a.late, a.mode) for k in range(a.trials) for n in names]
    runs: list[dict[str, Any]] = []
    with ProcessPoolExecutor(max_workers=a.workers) as ex:
        for r in ex.map(fly, jobs):
            runs.append(r)
            print(f"  traj {r['name']:>2} trial {r['trial']}: mean error m " + "  ".join(
                f"{v} {r[v]['mean_error_m']:.2f}" for v in VARIANTS), flush=True)  # fmt: skip
    s = summarise(runs)
    rows = [
        [v, x["mean_error_m"], x["median_of_mean_error_m"], x["worst_mean_error_m"],
         "-" if v == "reference" else f"{x['diff_m']:+.3f} ± {x['diff_sem_m']:.3f}", x["E_percent"], x["estimates"]]
        for v, x in s.items()
    ]  # fmt: skip
    print()
    print(table(
        ["variant", "mean err m", "median m", "worst m", "vs reference (paired)", "E %", "estimates"],
        rows,
        title=f"EKF, {a.mode}: a stream {a.late:g} s late at the start, or the IMU {a.late:g} s silent from "
              f"{DROPOUT_AT_S:g} s; {len(runs)} flights, seed {a.seed}, errors from {a.late + 1:g} s on",
    ))  # fmt: skip
    write_json(
        a.json,
        {
            "benchmark": "ekf_start",
            "quick": a.quick,
            "setup": {"trajectories": names, "trials": a.trials, "seed": a.seed, "late_s": a.late,
                      "mode": a.mode, "variants": VARIANTS, "autopilot_lead_s": AUTOPILOT_LEAD_S,
                      "dropout_at_s": DROPOUT_AT_S},
            "variants": s,
            "runs": runs,
        },
    )  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
