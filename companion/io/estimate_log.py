"""The daemon's own record of its estimates, for analysis after a flight or a bench replay.

Two files, written as the estimates come (one line each, line-buffered: a power cut loses at most the line
being written):

- ``<stem>.csv``: every estimate the estimator produced, sent or not: capture time (Unix s, the frame's
  own stamp), position NED (m), roll / pitch / yaw (rad), the 1-sigma of the covariance sent, quality,
  status, what became of it (``sent`` or the reason it was not: ``rate_cap``, ``too_old``,
  ``status_lost``, ...) and the reset counter;
- ``<stem>.tum``: the estimates that went to the autopilot, as a TUM trajectory (``t x y z qx qy qz qw``,
  x y z = north east down), which evo reads as it is (``evo_ape tum truth.tum <stem>.tum``).

A write that fails (disk full, card pulled) is counted and logged once; the daemon goes on.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from scipy.spatial.transform import Rotation

from companion.types import PoseEstimate

log = logging.getLogger(__name__)

CSV_HEADER = (
    "stamp_s,x_m,y_m,z_m,roll_rad,pitch_rad,yaw_rad,sigma_x_m,sigma_y_m,sigma_z_m,"
    "sigma_roll_rad,sigma_pitch_rad,sigma_yaw_rad,quality,status,outcome,reset_counter"
)


def log_paths(template: str, start_time_s: float | None = None) -> tuple[Path, Path]:
    """(csv, tum) paths of ``template``: ``{time}`` in it becomes the local start time (YYYYmmdd-HHMMSS), a
    ``.csv`` / ``.tum`` suffix is dropped, then each file gets its own."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(start_time_s))
    p = Path(template.replace("{time}", stamp))
    if p.suffix in (".csv", ".tum"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".csv"), p.with_name(p.name + ".tum")


class EstimateLog:
    """Appends estimates to the CSV and TUM files of ``template`` (``log_paths``). Raises OSError at
    construction when they cannot be created (a wrong path fails at start, not in flight).

    tum_outcomes: the outcomes whose estimates go into the TUM file (the daemon's: those sent; an offline
    replay, which sends nothing, writes ``would_send``)."""

    def __init__(self, template: str, tum_outcomes: tuple[str, ...] = ("sent",)) -> None:
        self.csv_path, self.tum_path = log_paths(template)
        self.tum_outcomes = tuple(tum_outcomes)
        self.csv_path.parent.mkdir(parents=True, exist_ok=True)
        new = not self.csv_path.exists() or self.csv_path.stat().st_size == 0
        self._csv: TextIO = open(self.csv_path, "a", buffering=1)  # noqa: SIM115 - open for the daemon's life
        self._tum: TextIO = open(self.tum_path, "a", buffering=1)  # noqa: SIM115
        if new:
            self._csv.write(CSV_HEADER + "\n")
        self.lines = 0
        self.errors = 0

    def write(self, est: PoseEstimate, outcome: str) -> None:
        """One estimate and what became of it (``sent`` or the reason it was not). Never raises."""
        try:
            p = np.asarray(est.p_body_in_world_m, float)
            rpy = np.asarray(est.rpy_rad, float)
            sig = np.sqrt(np.clip(np.diag(np.asarray(est.covariance, float)), 0.0, None))
            t = est.stamp_us * 1e-6
            values = ",".join(f"{v:.6g}" for v in (*p, *rpy, *sig))
            self._csv.write(
                f"{t:.6f},{values},{est.quality:.4g},{est.status.value},{outcome},{est.reset_counter}\n"
            )
            if outcome in self.tum_outcomes:
                q = Rotation.from_euler("ZYX", rpy[::-1]).as_quat()  # R_world_body; scipy order x y z w
                self._tum.write(f"{t:.6f} " + " ".join(f"{v:.6f}" for v in (*p, *q)) + "\n")
            self.lines += 1
        except (OSError, ValueError) as exc:
            self.errors += 1
            if self.errors == 1:
                log.error(
                    "estimates log %s: %s (counting further failures, not logging them)", self.csv_path, exc
                )

    def status(self) -> dict[str, Any]:
        return {"path": str(self.csv_path), "lines": self.lines, "errors": self.errors}

    def close(self) -> None:
        for f in (self._csv, self._tum):
            try:
                f.close()
            except OSError as exc:  # the last buffered line could not be written: nothing else to do
                log.error("estimates log %s: %s", f.name, exc)
