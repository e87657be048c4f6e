"""Recent timestamped autopilot samples (attitude, range) looked up at a frame's capture time."""

from __future__ import annotations

from bisect import bisect_left
from collections import deque
from typing import Any


class SampleHistory:
    """The last ``maxlen`` (stamp_us, value) samples in stamp order; ``nearest`` finds the one closest to a
    time. A sample older than the newest is dropped (the history stays monotonic for the bisection)."""

    def __init__(self, maxlen: int = 400) -> None:
        self.stamps: deque[int] = deque(maxlen=maxlen)
        self.values: deque[Any] = deque(maxlen=maxlen)

    def add(self, stamp_us: int, value: Any) -> None:
        if self.stamps and stamp_us < self.stamps[-1]:
            return
        self.stamps.append(stamp_us)
        self.values.append(value)

    def nearest(self, stamp_us: int, max_gap_us: int) -> Any | None:
        """The value whose stamp is closest to ``stamp_us``, or None when none is within ``max_gap_us``."""
        if not self.stamps:
            return None
        stamps = self.stamps  # bisect indexes the deque in place (no copy of 400 stamps per lookup)
        i = bisect_left(stamps, stamp_us)
        best = min((j for j in (i - 1, i) if 0 <= j < len(stamps)), key=lambda j: abs(stamps[j] - stamp_us))
        return self.values[best] if abs(stamps[best] - stamp_us) <= max_gap_us else None
