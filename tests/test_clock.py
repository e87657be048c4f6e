"""The companion's clock: the wall clock without its steps (``companion.clock``), and what it spares the link and
the frames when an NTP client sets the wall clock in flight, against the real simulated autopilot and real Zenoh."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from netutil import free_port, wait_for

from companion.clock import CompanionClock
from companion.daemon import format_status_line
from companion.io.frames import StampGate, encode_image
from companion.io.mavlink import MavlinkLink, MavlinkOptions
from companion.io.zenoh_io import FrameSubscriber, open_session
from companion.types import PoseEstimate
from sim_bridge.autopilot_link import SimAutopilotLink


class SteppedWall:
    """The machine's wall clock, set forward or back by ``step`` (an NTP client's settimeofday) at will."""

    def __init__(self) -> None:
        self.step_ns = 0

    def __call__(self) -> int:
        return time.time_ns() + self.step_ns

    def us(self) -> int:
        return self() // 1000


def test_steps_are_taken_out_and_slewing_is_not() -> None:
    wall = [1_800_000_000_000_000_000]
    mono = [5_000_000_000]
    clock = CompanionClock(lambda: wall[0], lambda: mono[0])

    def tick(seconds: float, wall_extra_ns: int = 0) -> None:
        mono[0] += int(seconds * 1e9)
        wall[0] += int(seconds * 1e9) + wall_extra_ns

    assert clock.now_us() == wall[0] // 1000 and clock.from_wall(123) == 123  # no step: the wall clock itself
    for _ in range(5):
        tick(1.0, wall_extra_ns=7_000)  # a few us of read jitter between the clocks
        assert clock.now_us() == wall[0] // 1000
    assert clock.steps == 0
    before = clock.now_us()
    tick(1.0, wall_extra_ns=3_600 * 10**9)  # set an hour forward
    stamp_wall = wall[0] // 1000 - 20_000  # a frame exposed 20 ms ago, stamped with the stepped clock
    assert (
        abs(clock.from_wall(stamp_wall) - (stamp_wall - 3_600_000_000)) < 100
    )  # the jitter's 35 us go with it
    assert clock.steps == 1 and abs(clock.last_step_us - 3_600_000_000) < 100
    assert abs(clock.now_us() - before - 1_000_000) < 100  # a second later, not an hour and a second
    tick(1.0, wall_extra_ns=-2_500_000_000)  # then 2.5 s back
    assert abs(clock.now_us() - before - 2_000_000) < 100
    assert clock.steps == 2 and abs(clock.correction_us - 3_597_500_000) < 100
    tick(1.0, wall_extra_ns=50_000_000)  # 50 ms: below the threshold, passed on as the wall clock moved
    assert clock.steps == 2 and abs(clock.now_us() - before - 3_050_000) < 100


def test_the_status_line_says_the_clock_was_stepped() -> None:
    st: dict[str, Any] = {
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
    assert "clock" not in line
    assert (
        format_status_line({**st, "clock_steps": 1, "clock_step_s": -2.5}) == line + "  clock stepped -2.5 s"
    )
    assert format_status_line({**st, "clock_steps": 3, "clock_step_s": 3600.0}).endswith(
        "  clock stepped +3600.0 s (3 steps)"
    )


def estimate(stamp_us: int) -> PoseEstimate:
    return PoseEstimate(
        stamp_us=stamp_us,
        p_body_in_world_m=np.array([1.0, 2.0, -30.0]),
        rpy_rad=np.zeros(3),
        covariance=np.eye(6) * 0.01,
    )


@pytest.mark.parametrize("companion_clock", [True, False], ids=["companion_clock", "wall_clock"])
def test_a_wall_clock_step_is_not_an_autopilot_reboot_to_the_link(companion_clock: bool) -> None:
    wall = SteppedWall()
    clock = CompanionClock(wall)
    port = free_port()
    sim = SimAutopilotLink(
        f"udpin:127.0.0.1:{port}", clock_offset_us=40_000_000, rng=np.random.default_rng(3)
    )
    link = MavlinkLink(
        MavlinkOptions(connection=f"udpout:127.0.0.1:{port}", read_params=False),
        clock_us=clock.now_us if companion_clock else wall.us,
    )
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.timesync.synced, 5.0)
        time.sleep(0.5)
        wall.step_ns = 5 * 10**9  # an NTP client sets the companion's clock 5 s forward
        time.sleep(1.5)  # several TIMESYNC rounds (5 Hz)
        stamp = clock.from_wall(wall.us() - 20_000) if companion_clock else wall.us() - 20_000
        assert wait_for(lambda: link.timesync.synced, 5.0)
        sent = link.send_estimate(estimate(stamp))
        assert sent is None, sent
        assert wait_for(lambda: len(sim.accepted()) == 1)
        true_usec = time.time_ns() // 1000 - 20_000 + sim.true_offset_us()
    finally:
        link.stop()
        sim.stop()
    if companion_clock:
        # the step never reached the link: no reboot, and the estimate is put at its true autopilot time
        assert link.reboots == 0 and link.resets == {}, link.resets
        assert abs(sim.accepted()[0].usec - true_usec) < 100_000
    else:
        # the old way: the link takes the step for an autopilot reboot (and reset_counter moves for nothing)
        assert link.reboots == 1 and "timesync_jump" in link.resets, link.resets


def _frames_through_a_step(
    stamp_from_wall: Callable[[int], int] | None, clock_us: Callable[[], int], wall: SteppedWall
):
    """Frames stamped with the companion's wall clock at 20 Hz over Zenoh on loopback; the clock set 3 s back
    midway. Returns the stamps the subscriber let through and its counters."""
    port = free_port(socket.SOCK_STREAM)
    a = open_session("peer", [], [f"tcp/127.0.0.1:{port}"], False)
    b = open_session("peer", [f"tcp/127.0.0.1:{port}"], [], False)
    got: list[int] = []
    lock = threading.Lock()

    def sink(frame: Any) -> None:
        with lock:
            got.append(frame.stamp_us)

    sub = FrameSubscriber(
        b,
        {"nadir": "uav/camera/nadir"},
        stamp_gate=lambda: StampGate(max_future_us=200_000, max_age_us=500_000),
        clock_us=clock_us,
        sink=sink,
        stamp_from_wall=stamp_from_wall,
    )
    pub = a.declare_publisher("uav/camera/nadir")
    img = np.zeros((48, 64), np.uint8)
    try:
        time.sleep(0.5)  # discovery
        for k in range(40):
            if k == 20:
                wall.step_ns = -3 * 10**9
            pub.put(encode_image(img, wall.us(), encoding="mono8"))
            time.sleep(0.05)
        time.sleep(0.3)
        stats = sub.stats()["nadir"]
    finally:
        pub.undeclare()
        sub.close()
        a.close()
        b.close()
    return got, stats


def test_frames_keep_coming_through_a_step_back_of_the_wall_clock() -> None:
    wall = SteppedWall()
    clock = CompanionClock(wall)
    got, stats = _frames_through_a_step(clock.from_wall, clock.now_us, wall)
    assert stats["received"] == 40 and len(got) >= 38, stats  # none lost to the step (Zenoh may drop one)
    assert np.all(np.diff(got) > 0) and np.max(np.diff(got)) < 200_000  # in order, and no 3 s gap
    # the old way: every frame after the step is refused as running backwards
    wall = SteppedWall()
    got, stats = _frames_through_a_step(None, wall.us, wall)
    assert stats["errors"].get("stamp_backwards", 0) >= 15 and len(got) <= 22, stats
