"""Renderer frame rate and scene generation time, per scene of paper 1's Table 2.

For each scene: generate it (true surface, default cell), build the renderer (radiance map, shadows,
bounds), then render 480 x 480 frames along a short circle at ~100 m above the ground with gentle roll and
pitch (the poses a nadir-camera drone has), noise on. Frames/s is measured by the wall clock and by the
process CPU time (the latter is what the machine could do if the renderer had it to itself; the wall
figure depends on whatever else runs). Also reported: the share of pixels whose rays hit the DEM.

    python -m bench renderer [--quick] [--json bench/results/renderer.json] [--seed 0]
"""

from __future__ import annotations

import time

import numpy as np

from bench.common import parser, table, write_json


def _poses(n: int, ground_up_m: float, alt_agl_m: float, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    from companion.geometry import camera_pose, rot_from_rpy

    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        a = 2 * np.pi * k / max(n, 1)
        roll, pitch = rng.normal(0.0, np.radians(5.0), 2)
        R_wb = rot_from_rpy(roll, pitch, a + np.pi / 2)
        p = np.array([60.0 * np.cos(a), 60.0 * np.sin(a), -(ground_up_m + alt_agl_m)])
        out.append(camera_pose(R_wb, p))
    return out


def run_scene(scene_id: str, frames: int, seed: int, alt_agl_m: float = 100.0) -> dict:
    from companion.geometry import CameraIntrinsics
    from sim_bridge.render import VisibleRenderer
    from sim_bridge.terrain import make_scene

    t0 = time.perf_counter()
    c0 = time.process_time()
    scene = make_scene(scene_id, seed=seed)
    gen_s, gen_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    intr = CameraIntrinsics.from_focal_sensor(480, 480, 36.0, 36.0)
    t0 = time.perf_counter()
    renderer = VisibleRenderer(scene.dem, scene.albedo, scene.sun, intr)
    init_s = time.perf_counter() - t0
    ground = float(np.mean(scene.dem.height_m))
    poses = _poses(frames, ground, alt_agl_m, seed)
    renderer.render(*poses[0], seed=0)  # warm-up
    hit = []
    t0 = time.perf_counter()
    c0 = time.process_time()
    for k, (R, p) in enumerate(poses):
        img = renderer.render(R, p, seed=k)
        hit.append(float((img > 0).mean()))
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    return {
        "scene": scene_id,
        "name": scene.name,
        "grid": list(scene.dem.shape),
        "cell_m": scene.dem.cell_m,
        "relief_m": scene.relief_m,
        "generate_s": gen_s,
        "generate_cpu_s": gen_cpu_s,
        "renderer_init_s": init_s,
        "frames": frames,
        "fps_wall": frames / wall,
        "fps_cpu": frames / cpu if cpu > 0 else float("nan"),
        "ms_per_frame_cpu": 1e3 * cpu / frames,
        "hit_fraction": float(np.mean(hit)),
    }


def main(argv: list[str] | None = None) -> int:
    p = parser("renderer", __doc__.splitlines()[0])
    args = p.parse_args(argv)
    from sim_bridge.terrain import SCENE_IDS

    frames = 10 if args.quick else 60
    rows, results = [], []
    for sid in SCENE_IDS:
        r = run_scene(sid, frames, args.seed)
        results.append(r)
        rows.append(
            [
                r["scene"],
                r["name"],
                f"{r['grid'][0]}x{r['grid'][1]}",
                r["generate_s"],
                r["renderer_init_s"],
                r["fps_wall"],
                r["fps_cpu"],
                r["ms_per_frame_cpu"],
            ]
        )
        print(
            f"  {sid} {r['name']}: {r['fps_wall']:.1f} frames/s wall, {r['fps_cpu']:.1f} by CPU time",
            flush=True,
        )
    print()
    print(
        table(
            ["scene", "name", "grid", "gen s", "init s", "fps wall", "fps cpu", "ms/frame cpu"],
            rows,
            title=f"480x480 frames, 53.13 deg FOV, ~100 m above ground, {frames} frames per scene, noise on",
        )
    )
    fps_wall = [r["fps_wall"] for r in results]
    fps_cpu = [r["fps_cpu"] for r in results]
    print(
        f"\nmin frames/s: {min(fps_wall):.1f} wall, {min(fps_cpu):.1f} by CPU time "
        f"(target >= 20 at 480x480; wall figures depend on other load on the machine)"
    )
    write_json(args.json, {"bench": "renderer", "quick": args.quick, "frames": frames, "scenes": results})
    return 0
