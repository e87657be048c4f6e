"""Dispatch ``python -m bench <name> ...`` to ``bench.<name>.main(argv)``."""

from __future__ import annotations

import importlib
import sys

BENCHES = {
    "georef": "Table 3 and sections 5.3.1-5.3.3 analogues: geo-referencing accuracy and speed",
    "georef_budget": "geo-referencing error budget: DEM, albedo, lighting and noise switched off in turn",
    "latency": "daemon frame-capture to VISION_POSITION_ESTIMATE latency and sustained rate",
    "terrain_slam": "Tables 4, 5, 7 analogues: VO only vs terrain LBA",
    "thermal_ekf": "paper 2 Tables 1-2 analogues: visible / thermal / dual EKF-SLAM drift",
    "renderer": "renderer frame rate",
    "attitude_errors": "terrain SLAM with an autopilot tilt bias or a misaligned camera mount it is not told of",
    "ekf_patch": "EKF-SLAM with and without the patch search for landmarks SIFT missed (paired trials)",
    "ekf_start": "the EKF's start with the autopilot's IMU or ATTITUDE late, and an IMU dropout in flight",
    "recorder": "the daemon's input record: MB and CPU per camera frame, raw against lossless PNG",
    "replay": "recorded Europa flights replayed through the daemon's path (companion replay): accuracy, speed, a lens",
}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in BENCHES:
        print("usage: python -m bench <name> [--quick] [--json PATH]\n")
        for name, what in BENCHES.items():
            print(f"  {name:<14} {what}")
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    module = importlib.import_module(f"bench.{argv[0]}")
    return int(module.main(argv[1:]) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
