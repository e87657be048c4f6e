"""The demo's summary quotes the companion's log lines on how its map was put in the world and when the
terrain stopped giving fixes."""

from __future__ import annotations

from pathlib import Path

from sim_bridge.demo import alignment_notes


def test_alignment_notes_quote_the_heading_and_alignment_lines_only(tmp_path: Path) -> None:
    log = tmp_path / "companion.log"
    prefix = "2026-11-23 06:03:32,026 INFO    companion.estimators.terrain_lba: "
    log.write_text(
        "2026-11-23 06:03:30,000 INFO    companion: in 15.0 fps\n"
        + prefix
        + "heading from the terrain: map turned by -21.0 deg (coarse)\n"
        + prefix
        + "map aligned to the geo-fixes\n"
        + prefix.replace("INFO   ", "WARNING")
        + "no terrain fix used in the last 10 key frames (low_quality 10): position from the visual odometry\n"
        + "2026-11-23 06:03:40,000 WARNING companion.estimators.terrain_lba: terrain_lba back-end worker hung\n"
    )
    assert alignment_notes(log) == [
        "heading from the terrain: map turned by -21.0 deg (coarse)",
        "map aligned to the geo-fixes",
        "no terrain fix used in the last 10 key frames (low_quality 10): position from the visual odometry",
    ]
    assert alignment_notes(tmp_path / "missing.log") == []
