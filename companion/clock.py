"""The companion's clock: the wall clock (Unix microseconds, the clock ROS 2 header stamps use) without its steps.

Frame stamps, the autopilot's time sync, the estimators' time and the records are all in this clock. The wall
clock itself can be stepped in flight (an NTP client setting the time when a server appears, a ground station
setting it): unchecked, a step back would make every frame look as if it ran backwards until the clock caught
up, a step forward would show the estimators a gap as long as the step and the time sync a jump it takes for
an autopilot reboot. So the companion keeps the wall clock's time at start and moves with it, slews included,
but takes each step out: ``now_us`` = wall clock - the steps so far. A step is what moves the wall clock against
the monotonic one: on Linux an NTP client's frequency corrections (slewing) move both, so their difference
moves only when the wall clock is set.

The cameras' stamps are wall-clock times taken on the companion (or on a camera synchronised to it), so they
step with it: ``from_wall`` takes the steps out of them too. A frame stamped before a step and converted after
it is off by the step and refused by the stamp gate; that is one or two frames. Thread-safe: every thread
reads it. Written by hand: no library keeps a step-free wall time (``time.monotonic`` has no epoch)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

STEP_THRESHOLD_US = 100_000
"""A change of the wall clock against the monotonic one larger than this is a step (0.1 s; the two clocks'
difference moves by microseconds between reads otherwise)."""


class CompanionClock:
    """``now_us()``: the wall clock without its steps; ``from_wall(stamp)``: a wall-clock stamp in that clock.

    wall_ns / mono_ns: the clocks read (time.time_ns / time.monotonic_ns; a test gives others)."""

    def __init__(
        self,
        wall_ns: Callable[[], int] = time.time_ns,
        mono_ns: Callable[[], int] = time.monotonic_ns,
        threshold_us: int = STEP_THRESHOLD_US,
    ) -> None:
        self._wall_ns = wall_ns
        self._mono_ns = mono_ns
        self.threshold_us = threshold_us
        self._lock = threading.Lock()
        self._offset_us = wall_ns() // 1000 - mono_ns() // 1000  # wall - monotonic, at the last step
        self.correction_us = 0
        """The steps so far (us): the wall clock is this far ahead of the companion's."""
        self.steps = 0
        self.last_step_us = 0
        """The last step's size (us; negative: the wall clock was set back)."""

    def _wall_us(self) -> int:
        """The wall clock now (us), after taking in a step if it has just been set; call with the lock held."""
        wall = self._wall_ns() // 1000
        offset = wall - self._mono_ns() // 1000
        step = offset - self._offset_us
        if abs(step) > self.threshold_us:
            self._offset_us = offset
            self.correction_us += step
            self.steps += 1
            self.last_step_us = step
        return wall

    def now_us(self) -> int:
        """The companion's time (Unix us, the wall clock's at start, without the steps since)."""
        with self._lock:
            return self._wall_us() - self.correction_us

    def from_wall(self, stamp_us: int) -> int:
        """A wall-clock stamp taken now or a moment ago (a frame's capture time) in the companion's time."""
        with self._lock:
            self._wall_us()
            return int(stamp_us) - self.correction_us
