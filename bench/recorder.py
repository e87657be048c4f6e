"""The daemon's input record (``daemon.record_inputs``): disk and CPU per camera frame, raw against PNG.

Frames as the companion gets them: the Europa camera pair of ``configs/europa_dual_ekf.toml`` (640 x 480,
visible 8-bit and thermal 16-bit, along trajectory 1) and the demo's nadir camera (480 x 480 8-bit over
scene 08, the demo's circle at 100 m). Each set is written by ``InputRecorder`` with ``frames="raw"`` and
``frames="png"`` into a new bag: megabytes per frame and per second at the camera's rate (the bag on disk,
MCAP framing included), the writer's encoding CPU per frame (``InputRecorder._encode`` timed with the
thread's CPU clock, what the writer thread spends besides the write itself), and the writer's sustained
rate (every frame queued at once, then closed: frames per wall-clock second, on a machine with other
work on it a lower bound). Every PNG frame is read back from the bag and compared with what was recorded
(lossless: the count of differing frames must be 0).

    python -m bench recorder [--quick] [--json bench/results/recorder.json]
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.common import parser, table, write_json


def europa_frames(n_pairs: int) -> tuple[list[tuple[str, np.ndarray]], float]:
    """n_pairs visible / thermal pairs along trajectory 1 (seed 0) at the sim's 2 Hz; (camera, image) list and
    the camera rate in frame sets per second."""
    from sim_bridge.europa.vehicle import EuropaFlight

    flight = EuropaFlight(0, "1")
    out: list[tuple[str, np.ndarray]] = []
    for i in range(n_pairs):
        s = flight.traj.state_at(flight.traj.t0_s + 0.5 * i)
        visible, thermal = flight.render(s, seed=i)
        out += [("visible", visible), ("thermal", thermal)]
    return out, 2.0


def demo_frames(n: int) -> tuple[list[tuple[str, np.ndarray]], float]:
    """n frames of the demo's camera: scene 08, 480 x 480, along the simulator's default trajectory (the demo's
    circle, 100 m above the ground) at its 15 Hz, as ``bench latency`` renders them."""
    from companion.geometry import CameraIntrinsics, camera_pose
    from sim_bridge.render import VisibleRenderer
    from sim_bridge.sim import SimConfig, make_trajectory
    from sim_bridge.terrain import make_scene

    scene = make_scene("08", seed=0)
    cfg = SimConfig()
    intr = CameraIntrinsics.from_focal_sensor(480, 480, 36.0, 36.0)
    renderer = VisibleRenderer(scene.dem, scene.albedo, scene.sun, intr)
    traj = make_trajectory(cfg, float(np.nanmean(scene.dem.height_m)))
    states = traj.states(5.0 + np.arange(n) / cfg.camera_rate_hz)  # from 5 s: at speed
    out = [
        ("nadir", renderer.render(*camera_pose(s.R_world_body, s.p_world), seed=k))
        for k, s in enumerate(states)
    ]
    return out, cfg.camera_rate_hz


def record(frames: list[tuple[str, np.ndarray]], fmt: str, root: Path) -> dict[str, Any]:
    """Write ``frames`` with ``InputRecorder(frames=fmt)``; read the bag back and compare."""
    from rosbags.rosbag2 import Reader

    from companion.io.frames import decode_frame
    from companion.io.input_recorder import InputRecorder
    from companion.types import Frame

    cams = sorted({c for c, _ in frames})
    items = [
        Frame(stamp_us=1_000_000 + 1000 * i, camera=c, image=img, seq=i) for i, (c, img) in enumerate(frames)
    ]
    rec = InputRecorder(str(root / fmt), {c: f"/{c}" for c in cams}, queue_size=len(items) + 8, frames=fmt)
    c0 = time.thread_time()
    for it in items:
        rec._encode(it)
    encode_ms = 1e3 * (time.thread_time() - c0) / len(items)
    t0 = time.perf_counter()
    for it in items:
        rec.put(it, it.stamp_us)
    rec.close()
    write_s = time.perf_counter() - t0
    bag_bytes = sum(f.stat().st_size for f in rec.path.iterdir())
    status = rec.status()
    differing = 0
    with Reader(rec.path) as reader:
        got = [
            decode_frame(bytes(raw), conn.topic[1:], compressed=conn.msgtype.endswith("CompressedImage"))
            for conn, _, raw in reader.messages()
            if conn.topic[1:] in cams
        ]
    if len(got) != len(items):
        raise RuntimeError(f"{fmt}: {len(got)} frames read back of {len(items)}")
    for a, b in zip(items, got, strict=True):
        differing += int(a.image.dtype != b.image.dtype or not np.array_equal(a.image, b.image))
    return {
        "frames": len(items),
        "bag_mb": bag_bytes / 1e6,
        "mb_per_frame": bag_bytes / 1e6 / len(items),
        "encode_ms_per_frame_cpu": encode_ms,
        "writer_frames_per_s": len(items) / write_s,
        "dropped": status["dropped"],
        "errors": status["errors"],
        "frames_differing_after_read_back": differing,
    }


def main(argv: list[str] | None = None) -> int:
    p = parser("recorder", __doc__.splitlines()[0])
    args = p.parse_args(argv)
    n_pairs, n_demo = (6, 30) if args.quick else (40, 300)
    sets = {
        "europa_pair": europa_frames(n_pairs),
        "demo_nadir": demo_frames(n_demo),
    }
    results: dict[str, Any] = {"bench": "recorder", "quick": bool(args.quick), "sets": {}}
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-recorder-") as tmp:
        for name, (frames, rate_hz) in sets.items():
            per_set = len({c for c, _ in frames})
            out: dict[str, Any] = {"camera_rate_hz": rate_hz, "cameras": per_set}
            for fmt in ("raw", "png"):
                r = record(frames, fmt, Path(tmp) / name)
                r["mb_per_s"] = r["mb_per_frame"] * per_set * rate_hz
                r["encode_cpu_share_of_a_core"] = r["encode_ms_per_frame_cpu"] * per_set * rate_hz / 1e3
                out[fmt] = r
                rows.append(
                    [
                        name,
                        fmt,
                        r["frames"],
                        f"{r['mb_per_frame']:.3f}",
                        f"{r['mb_per_s']:.2f}",
                        f"{r['encode_ms_per_frame_cpu']:.1f}",
                        f"{100 * r['encode_cpu_share_of_a_core']:.1f}",
                        f"{r['writer_frames_per_s']:.0f}",
                        r["frames_differing_after_read_back"],
                    ]
                )
            out["png_bytes_of_raw"] = out["png"]["bag_mb"] / out["raw"]["bag_mb"]
            results["sets"][name] = out
    print(
        table(
            [
                "frames",
                "record",
                "n",
                "MB/frame",
                "MB/s at rate",
                "encode ms CPU",
                "% of a core",
                "writer frames/s",
                "differ",
            ],
            rows,
            title="daemon.record_inputs: raw Image against lossless PNG (CompressedImage)",
        )
    )
    for name, out in results["sets"].items():
        print(f"{name}: PNG keeps {100 * out['png_bytes_of_raw']:.0f} % of the raw bag's bytes")
    write_json(args.json, results)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
