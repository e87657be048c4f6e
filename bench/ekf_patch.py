"""EKF-SLAM with and without the patch search for landmarks SIFT missed, paired on the thermal_ekf trials.

``python -m bench ekf_patch [--quick] [--json PATH] [--trials 3] [--trajectories 1,2,..] [--workers 2]``

The ``thermal_ekf`` benchmark's trials (same trajectories, seeds, sensors, renderer and options), each run
three times: SIFT tracking only (the paper's, the default), with the patch search on the visible camera
(``EkfOptions.patch_cameras = ("visible",)``) and on both cameras. The patch search: a landmark with no SIFT
match inside its gate is looked for with the image patch cut around its keypoint when it was created, warped
by the predicted motion, by normalised cross-correlation inside the same gate (MonoSLAM's active search).
Per mode (visible / thermal / dual) and variant: the mean over trials of E (%, the slope of error against
distance), of the mean position error (m), of the matches used per frame and of the position NEES, and the
paired difference to SIFT only with its standard error (the same trials: the rendering, noise and initial
error are identical; only the tracking differs). Default 10 trajectories x 3 trials (about 25 min on two
cores); --quick: trajectories 1 and 6, one trial.
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

MODES = ("visible", "thermal", "dual")
VARIANTS: dict[str, tuple[str, ...]] = {
    "sift_only": (),
    "patch_visible": ("visible",),
    "patch_both": ("visible", "thermal"),
}
KEYS = ("E_percent", "mean_error_m", "mean_matched", "nees_position")


def run_job(job: tuple[str, int, int]) -> dict[str, Any]:
    """One trial in every variant (rendered once per variant: ``thermal_ekf.run_trial`` renders and detects)."""
    name, trial, seed = job
    base = T.BENCH_OPTIONS
    T.CONFIGS = {m: (m, "kde") for m in MODES}
    out: dict[str, Any] = {"name": name, "trial": trial, "seed": seed}
    try:
        for variant, cams in VARIANTS.items():
            T.BENCH_OPTIONS = replace(base, patch_cameras=cams)
            r = T.run_trial(name, trial, seed)
            out[variant] = {
                m: {k: r[m][k] for k in KEYS} | {"filter_s_per_frame": r[m]["filter_s_per_frame"]}
                for m in MODES
            }
    finally:
        T.BENCH_OPTIONS = base
    return out


def summarise(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Per mode and variant: means over the trials and the paired differences to sift_only (mean, sem)."""
    res: dict[str, Any] = {}
    for m in MODES:
        res[m] = {}
        for v in VARIANTS:
            row: dict[str, Any] = {}
            for k in KEYS + ("filter_s_per_frame",):
                a = np.array([r[v][m][k] for r in runs])
                b = np.array([r["sift_only"][m][k] for r in runs])
                d = a - b
                row[k] = float(np.mean(a))
                if v != "sift_only":
                    row[f"{k}_diff"] = float(np.mean(d))
                    row[f"{k}_diff_sem"] = (
                        float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
                    )
            res[m][v] = row
    return res


def main(argv: list[str] | None = None) -> int:
    p = parser("ekf_patch", __doc__.splitlines()[0])
    p.add_argument("--trials", type=int, default=None, help="trials per trajectory (default 3, quick 1)")
    p.add_argument("--trajectories", type=str, default=None, help="comma-separated names (default all)")
    p.add_argument("--workers", type=int, default=2)
    a = p.parse_args(argv)
    names = T.trajectory_names(a.trajectories, a.quick)
    trials = a.trials if a.trials is not None else (1 if a.quick else 3)
    jobs = [(n, k, a.seed) for k in range(trials) for n in names]
    runs: list[dict[str, Any]] = []
    with ProcessPoolExecutor(max_workers=a.workers) as ex:
        for r in ex.map(run_job, jobs):
            runs.append(r)
            print(f"  traj {r['name']:>2} trial {r['trial']:>2}: " + "  ".join(
                f"{m} err {r['sift_only'][m]['mean_error_m']:.2f}/{r['patch_visible'][m]['mean_error_m']:.2f}/"
                f"{r['patch_both'][m]['mean_error_m']:.2f} m" for m in MODES), flush=True)  # fmt: skip
    runs.sort(key=lambda r: (int(r["name"]), r["trial"]))
    s = summarise(runs)
    rows = []
    for m in MODES:
        for v in VARIANTS:
            x = s[m][v]
            diff = v != "sift_only"

            def pm(k: str, x: dict[str, Any] = x, diff: bool = diff) -> str:
                return f"{x[k + '_diff']:+.3f} ± {x[k + '_diff_sem']:.3f}" if diff else "-"

            rows.append([m, v, x["E_percent"], pm("E_percent"), x["mean_error_m"], pm("mean_error_m"),
                         x["mean_matched"], x["nees_position"], 1000 * x["filter_s_per_frame"]])  # fmt: skip
    print()
    print(table(
        ["mode", "tracking", "E %", "ΔE (paired)", "mean err m", "Δerr (paired)", "matched", "NEES", "filter ms"],
        rows,
        title=f"SIFT only vs patch search for missed landmarks: {len(names)} trajectories x {trials} trials, seed {a.seed}",
    ))  # fmt: skip
    write_json(
        a.json,
        {
            "benchmark": "ekf_patch",
            "quick": a.quick,
            "setup": {"trajectories": names, "trials": trials, "seed": a.seed, "variants": VARIANTS},
            "modes": s,
            "runs": runs,
        },
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
