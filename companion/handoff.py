"""Bounded, latest-wins hand-off of camera frames from the receiving threads to the estimator thread,
with pairing by capture time for two-camera estimators. Nothing here queues without bound: each camera
holds at most one waiting frame, and a frame replaced before the estimator took it is counted as dropped.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from companion.types import Frame


@dataclass
class HandoffCounters:
    received: int = 0
    dropped_stale: int = 0  # replaced by a newer frame before the estimator took it
    dropped_unpaired: int = 0  # no partner within the pairing tolerance
    taken: int = 0
    per_camera: dict[str, int] = field(default_factory=dict)


class FrameHandoff:
    """Latest frame per camera; ``take`` returns a complete, time-matched set.

    cameras: the cameras the estimator needs (one or two). pair_tolerance_us: largest difference of
    capture times within a set.
    """

    def __init__(self, cameras: tuple[str, ...], pair_tolerance_us: int = 5_000) -> None:
        if not cameras:
            raise ValueError("at least one camera is needed")
        self.cameras = tuple(cameras)
        self.tol_us = int(pair_tolerance_us)
        self._latest: dict[str, Frame] = {}
        self._cv = threading.Condition()
        self.counters = HandoffCounters()

    def put(self, frame: Frame) -> None:
        """Called from a receiving thread. Unknown cameras are ignored."""
        if frame.camera not in self.cameras:
            return
        with self._cv:
            c = self.counters
            c.received += 1
            c.per_camera[frame.camera] = c.per_camera.get(frame.camera, 0) + 1
            if frame.camera in self._latest:
                c.dropped_stale += 1
            self._latest[frame.camera] = frame
            if self._complete_locked():
                self._cv.notify()

    def _complete_locked(self) -> bool:
        if len(self._latest) < len(self.cameras):
            return False
        stamps = [f.stamp_us for f in self._latest.values()]
        if max(stamps) - min(stamps) <= self.tol_us:
            return True
        # unmatched: drop the oldest; its partner may still come for the newer one
        oldest = min(self._latest, key=lambda k: self._latest[k].stamp_us)
        del self._latest[oldest]
        self.counters.dropped_unpaired += 1
        return False

    def take(self, timeout_s: float) -> dict[str, Frame] | None:
        """Block up to ``timeout_s`` for a complete set; return it (and clear it) or None."""
        with self._cv:
            if not self._complete_locked():
                self._cv.wait(timeout_s)
                if not self._complete_locked():
                    return None
            out = dict(self._latest)
            self._latest.clear()
            self.counters.taken += 1
            return out

    def wake(self) -> None:
        """Wake a blocked ``take`` (used at shutdown)."""
        with self._cv:
            self._cv.notify_all()
