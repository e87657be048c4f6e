"""bench.recorder's measurement on synthetic frames: both records read back exactly, PNG in fewer bytes."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def test_recorder_bench_reads_back_every_frame_and_png_is_smaller(tmp_path: Path) -> None:
    from bench.recorder import record

    rng = np.random.default_rng(0)
    ramp = np.add.outer(np.arange(120), np.arange(160)).astype(float)
    frames: list[tuple[str, np.ndarray]] = [
        ("visible", (ramp + rng.normal(0, 3, ramp.shape)).clip(0, 255).astype(np.uint8)),
        ("thermal", (ramp * 40 + 9000 + rng.normal(0, 20, ramp.shape)).astype(np.uint16)),
    ] * 3
    raw = record(frames, "raw", tmp_path)
    png = record(frames, "png", tmp_path)
    for r in (raw, png):
        assert r["frames"] == 6 and r["frames_differing_after_read_back"] == 0
        assert r["dropped"] == 0 and r["errors"] == 0
    assert png["bag_mb"] < 0.8 * raw["bag_mb"], (png["bag_mb"], raw["bag_mb"])
