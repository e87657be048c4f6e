"""``bench terrain_slam`` writes its drift plot beside its JSON, so a scratch run never overwrites the
committed plot in ``bench/results/``."""

from __future__ import annotations

from pathlib import Path

from bench.terrain_slam import drift_plot_path


def test_drift_plot_goes_beside_the_json_unless_asked_elsewhere() -> None:
    assert drift_plot_path(None, Path("bench/results/terrain_slam.json")) == Path(
        "bench/results/terrain_slam_drift.png"
    )
    assert drift_plot_path(None, Path("/tmp/s7/seed2.json")) == Path("/tmp/s7/seed2_drift.png")
    assert drift_plot_path(Path("x.png"), Path("/tmp/a.json")) == Path("x.png")
    assert drift_plot_path(None, None) is None
