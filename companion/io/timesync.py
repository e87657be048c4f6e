"""MAVLink TIMESYNC: estimate offset = autopilot_clock - companion_clock. Pure: no I/O, no clock.

Protocol (MAVLink common.xml, TIMESYNC #111): a request carries tc1 = 0 and ts1 = the sender's time
in ns; the answer carries tc1 = the answerer's time in ns and ts1 copied from the request. With our
request sent at t0, answered at autopilot time T and received back at t1 (companion clock):

    rtt = t1 - t0,   offset = T - (t0 + t1) / 2        (error at most rtt / 2, whatever the asymmetry)

Filter: replies with rtt above ``max_rtt_us`` are refused; of the last ``window`` accepted samples
the one with the smallest rtt (tightest bound) is the measurement; the estimate follows it with a
running mean at first (converges in a few samples) and an exponential filter afterwards. A new
sample that disagrees with the estimate by more than ``jump_threshold_us`` ``jump_confirm`` times
in a row is an autopilot reboot (its clock restarted): the filter resets to the new offset and
raises a flag the owner reads with ``consume_reset()``.

The mapping ``to_autopilot_us(stamp)`` is a function of that stamp only (stamp + offset): a dropped
or late frame can never shift the timestamps of later ones.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class TimeSyncOptions:
    """Filter settings. Times in microseconds."""

    max_rtt_us: int = 30_000
    """Replies slower than this are refused (their offset bound rtt/2 is too loose)."""
    window: int = 16
    """Accepted samples kept for the min-rtt choice (16 at 10 Hz = 1.6 s, ~80 us of 50 ppm drift)."""
    min_samples: int = 3
    """Accepted samples before ``synced`` is True."""
    smoothing: float = 0.2
    """Exponential filter gain once converged (running mean 1/n until 1/n drops below it)."""
    jump_threshold_us: int = 100_000
    """A sample this far from the estimate is a clock jump (reboot), not noise (noise <= rtt/2)."""
    jump_confirm: int = 2
    """Consecutive jumped samples needed before resetting (one corrupt reply does not reset)."""
    pending_requests: int = 64
    """Outstanding requests remembered to match replies (older ones are forgotten)."""


class TimeSync:
    """TIMESYNC request / reply bookkeeping and the offset filter (one autopilot)."""

    def __init__(self, options: TimeSyncOptions | None = None) -> None:
        self.options = options or TimeSyncOptions()
        self._pending: dict[int, int] = {}
        self._samples: deque[tuple[int, int]] = deque(maxlen=self.options.window)  # (rtt_us, offset_us)
        self._estimate_us: float | None = None
        self._count = 0
        self._jumped: list[tuple[int, int]] = []
        self._reset_flag = False
        self.last_rtt_us: int | None = None
        """Round-trip time of the last matched reply."""
        self.accepted = 0
        """Replies used by the filter."""
        self.rejected_rtt = 0
        """Replies refused for rtt above max_rtt_us (or negative rtt)."""
        self.unmatched = 0
        """Replies to requests we did not send (other components' sync) or forgot."""
        self.resets = 0
        """Clock jumps detected (autopilot reboots) plus explicit resets."""
        self.answered = 0
        """Requests from the autopilot we answered."""

    # --- protocol -------------------------------------------------------------------------------
    def make_request(self, now_us: int) -> tuple[int, int]:
        """Return (tc1, ts1) of a request to send now: tc1 = 0, ts1 = now in ns."""
        ts1 = int(now_us) * 1000
        self._pending[ts1] = int(now_us)
        while len(self._pending) > self.options.pending_requests:
            self._pending.pop(next(iter(self._pending)))
        return 0, ts1

    def on_timesync(self, tc1: int, ts1: int, now_us: int) -> tuple[int, int] | None:
        """Consume a received TIMESYNC. Returns (tc1, ts1) to send back when it was a request."""
        if tc1 == 0:
            self.answered += 1
            return int(now_us) * 1000, int(ts1)
        sent_us = self._pending.pop(int(ts1), None)
        if sent_us is None:
            self.unmatched += 1
            return None
        rtt_us = int(now_us) - sent_us
        self.last_rtt_us = rtt_us
        if rtt_us < 0 or rtt_us > self.options.max_rtt_us:
            self.rejected_rtt += 1
            return None
        offset_us = int(round(tc1 / 1000.0 - (sent_us + now_us) / 2.0))
        self.add_sample(rtt_us, offset_us)
        return None

    # --- filter ---------------------------------------------------------------------------------
    def add_sample(self, rtt_us: int, offset_us: int) -> None:
        """Feed one (rtt, offset) measurement (exposed for tests and replay)."""
        self.accepted += 1
        opts = self.options
        if self._estimate_us is not None and abs(offset_us - self._estimate_us) > opts.jump_threshold_us:
            self._jumped.append((rtt_us, offset_us))
            if len(self._jumped) < opts.jump_confirm:
                return
            jumped = self._jumped
            self.reset()
            self._reset_flag = True
            for rtt, off in jumped:
                self.add_sample(rtt, off)
            return
        self._jumped = []
        self._samples.append((rtt_us, offset_us))
        best_offset = min(self._samples)[1]
        self._count += 1
        if self._estimate_us is None:
            self._estimate_us = float(best_offset)
            return
        gain = max(1.0 / self._count, opts.smoothing)
        self._estimate_us += gain * (best_offset - self._estimate_us)

    def reset(self) -> None:
        """Forget everything learned (autopilot rebooted or link re-established)."""
        self._samples.clear()
        self._estimate_us = None
        self._count = 0
        self._jumped = []
        self._pending.clear()
        self.resets += 1

    def consume_reset(self) -> bool:
        """True once after a clock jump was detected by the filter."""
        flag, self._reset_flag = self._reset_flag, False
        return flag

    # --- results --------------------------------------------------------------------------------
    @property
    def synced(self) -> bool:
        """True once ``min_samples`` accepted samples agree."""
        return self._estimate_us is not None and self._count >= self.options.min_samples

    @property
    def offset_us(self) -> int | None:
        """autopilot_clock - companion_clock in us, or None before the first sample."""
        return None if self._estimate_us is None else int(round(self._estimate_us))

    def to_autopilot_us(self, companion_us: int) -> int | None:
        """Map a companion-clock stamp to the autopilot clock; None until synced."""
        if not self.synced:
            return None
        return int(companion_us) + int(round(self._estimate_us))  # type: ignore[arg-type]

    def to_companion_us(self, autopilot_us: int) -> int | None:
        """Map an autopilot-clock stamp (time since its boot) to the companion clock; None until synced."""
        if not self.synced:
            return None
        return int(autopilot_us) - int(round(self._estimate_us))  # type: ignore[arg-type]
