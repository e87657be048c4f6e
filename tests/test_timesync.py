"""TIMESYNC filter: convergence with asymmetric delays, RTT rejection, reboot jumps, per-stamp mapping."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.io.timesync import TimeSync, TimeSyncOptions

OFFSET_US = 4_321_000 - 1_700_000_000_000_000  # autopilot boot clock - Unix-epoch companion clock


def offset(sync: TimeSync) -> int:
    """The synced offset (autopilot minus companion, us); fails the test when there is none."""
    assert sync.offset_us is not None, "not synced"
    return sync.offset_us


def exchange(sync: TimeSync, t0_us: int, up_us: int, down_us: int, offset_us: int = OFFSET_US) -> None:
    """One request/reply round trip with the given one-way delays (companion clock)."""
    tc1, ts1 = sync.make_request(t0_us)
    assert tc1 == 0 and ts1 == t0_us * 1000
    autopilot_ns = (t0_us + up_us + offset_us) * 1000
    assert sync.on_timesync(autopilot_ns, ts1, t0_us + up_us + down_us) is None


def test_converges_within_rtt_bound_despite_asymmetric_delays() -> None:
    rng = np.random.default_rng(1)
    sync = TimeSync()
    t = 1_700_000_000_000_000
    errors = []
    for _ in range(60):
        up, down = (int(v) for v in rng.exponential(3_000, 2) + 200)  # 0.2 ms floor, heavy tail
        exchange(sync, t, up, down)
        t += 200_000
        if sync.synced:
            errors.append(abs(offset(sync) - OFFSET_US))
    assert sync.synced
    assert max(errors[-40:]) < 1_000  # min-RTT choice: bound is rtt_min / 2, well under 2 ms
    assert sync.to_autopilot_us(t) == t + offset(sync)


def test_converges_fast_at_start() -> None:
    sync = TimeSync(TimeSyncOptions(min_samples=3))
    t = 10_000_000
    for i in range(3):
        assert not sync.synced
        exchange(sync, t + i * 100_000, 400, 600)
    assert sync.synced and abs(offset(sync) - OFFSET_US) <= 100


def test_slow_replies_are_rejected_and_do_not_move_the_estimate() -> None:
    sync = TimeSync(TimeSyncOptions(max_rtt_us=10_000))
    t = 5_000_000
    for i in range(5):
        exchange(sync, t + i * 100_000, 500, 500)
    before = sync.offset_us
    exchange(sync, t + 600_000, 30_000, 100)  # 30 ms up, would bias the offset by ~15 ms
    assert sync.rejected_rtt == 1 and sync.offset_us == before


def test_unmatched_replies_are_ignored_and_requests_answered() -> None:
    sync = TimeSync()
    assert sync.on_timesync(123_000_000, 999, 5_000_000) is None
    assert sync.unmatched == 1 and sync.offset_us is None
    # The autopilot asks us: tc1 = 0, we answer with our time in ns and its ts1.
    assert sync.on_timesync(0, 777_000, 5_000_000) == (5_000_000_000, 777_000)
    assert sync.answered == 1


def test_reboot_jump_resets_and_flags_but_one_outlier_does_not() -> None:
    sync = TimeSync(TimeSyncOptions(jump_confirm=2))
    t = 50_000_000
    for i in range(10):
        exchange(sync, t + i * 100_000, 300, 300)
    t += 1_000_000
    exchange(sync, t, 300, 300, offset_us=OFFSET_US + 9_000_000)  # one corrupt reply
    exchange(sync, t + 100_000, 300, 300)
    assert not sync.consume_reset() and abs(offset(sync) - OFFSET_US) < 100
    resets_before = sync.resets
    new_offset = OFFSET_US - 45_000_000  # rebooted: its clock restarted near zero
    for i in range(2, 6):
        exchange(sync, t + i * 100_000, 300, 300, offset_us=new_offset)
    assert sync.consume_reset() and not sync.consume_reset()
    assert sync.resets == resets_before + 1
    assert abs(offset(sync) - new_offset) < 100


def test_not_synced_maps_to_none() -> None:
    sync = TimeSync()
    assert sync.to_autopilot_us(1) is None and sync.to_companion_us(1) is None


@settings(max_examples=50, deadline=None)
@given(
    stamps=st.lists(
        st.integers(1_600_000_000_000_000, 1_800_000_000_000_000), min_size=2, max_size=30, unique=True
    ),
    keep=st.lists(st.booleans(), min_size=30, max_size=30),
)
def test_mapping_depends_on_each_stamp_only(stamps: list[int], keep: list[bool]) -> None:
    """A dropped or late frame never shifts later timestamps: mapping is per stamp, in any order."""
    sync = TimeSync()
    for i in range(5):
        exchange(sync, 1_000_000 + i * 100_000, 250, 350)
    all_mapped = {s: sync.to_autopilot_us(s) for s in stamps}
    kept = [s for s, k in zip(stamps, keep) if k]
    for s in reversed(kept):  # late / out of order / with gaps
        assert sync.to_autopilot_us(s) == all_mapped[s] == s + offset(sync)
        mapped = all_mapped[s]
        assert mapped is not None and sync.to_companion_us(mapped) == s
