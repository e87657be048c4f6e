"""The daemon's watch on its own clock: a wall-clock step is noticed, sized and shown; slewing is not a step."""

from __future__ import annotations

import time

from companion.daemon import ClockWatch, format_status_line


def test_a_step_of_the_wall_clock_is_noticed_with_its_size() -> None:
    w = ClockWatch()
    wall, mono = 1_800_000_000_000_000, 5_000_000
    assert w.check(wall, mono) is None  # the first call only learns the offset
    for k in range(1, 6):  # a second a call, the two clocks together (a few us of jitter)
        assert w.check(wall + k * 1_000_000 + 7 * (k % 2 == 0), mono + k * 1_000_000) is None
    assert w.steps == 0
    # an NTP client steps the clock forward by an hour between two calls
    assert w.check(wall + 6_000_000 + 3_600_000_000, mono + 6_000_000) == 3_600_000_000
    assert w.steps == 1 and w.last_step_us == 3_600_000_000
    # the new offset is the reference from then on
    assert w.check(wall + 7_000_000 + 3_600_000_000, mono + 7_000_000) is None
    # and back by 2.5 s
    assert w.check(wall + 8_000_000 + 3_597_500_000, mono + 8_000_000) == -2_500_000
    assert w.steps == 2
    # below the threshold: not a step
    assert w.check(wall + 9_000_000 + 3_597_550_000, mono + 9_000_000) is None


def test_this_machines_clocks_do_not_step_between_two_calls() -> None:
    w = ClockWatch()
    for _ in range(5):
        assert w.check(time.time_ns() // 1000, time.monotonic_ns() // 1000) is None
        time.sleep(0.05)


def test_the_status_line_says_the_clock_stepped() -> None:
    st = {
        "fps_in": 15.0,
        "fps_out": 15.0,
        "latency_p50_ms": 30.0,
        "latency_p99_ms": 40.0,
        "frames_dropped_stale": 0,
        "frames": {"decode_errors": {}},
        "not_sent": {},
        "quality": 0.8,
        "estimate_status": "ok",
        "link": {"state": "up", "timesync": True},
        "clock_steps": 0,
        "clock_step_s": 0.0,
    }
    line = format_status_line(st)
    assert "CLOCK" not in line
    assert (
        format_status_line({**st, "clock_steps": 1, "clock_step_s": -2.5}) == line + "  CLOCK STEPPED -2.5 s"
    )
    assert format_status_line({**st, "clock_steps": 3, "clock_step_s": 3600.0}).endswith(
        "  CLOCK STEPPED +3600.0 s (3 steps)"
    )
