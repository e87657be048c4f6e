"""Zenoh I/O over real sessions on loopback (peer mode, multicast scouting off)."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import numpy as np
import pytest
from netutil import free_tcp_port, wait_for

from companion.io import frames
from companion.io.frames import StampGate, encode_image
from companion.io.zenoh_io import (
    CameraTopic,
    FramePublisher,
    FrameSubscriber,
    LatestSlot,
    StatusPublisher,
    open_session,
)


@pytest.fixture
def sessions():
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    a = open_session("peer", listen=[endpoint], multicast_scouting=False)
    b = open_session("peer", connect=[endpoint], multicast_scouting=False)
    yield a, b
    b.close()
    a.close()


def publish_until_seen(pub: FramePublisher, sub: FrameSubscriber, camera: str) -> None:
    """Routes take a moment to establish: publish warm-up frames until one arrives."""
    img = np.zeros((8, 8), dtype=np.uint8)

    def seen() -> bool:
        pub.put(img, time.time_ns() // 1000)
        return sub.counters[camera].decoded > 0

    assert wait_for(seen, 5.0)
    time.sleep(0.2)  # let warm-up frames still in flight land, then empty the slot
    sub.slot.take(0.0)


def test_latest_slot_latest_wins_and_counts_drops() -> None:
    slot: LatestSlot[int] = LatestSlot()
    assert slot.take(0.0) == {}
    assert not slot.put("nadir", 1)
    assert slot.put("nadir", 2)  # 1 was never taken: dropped
    slot.put("thermal", 7)
    assert slot.take(0.0) == {"nadir": 2, "thermal": 7}
    assert slot.dropped == {"nadir": 1} and slot.taken == {"nadir": 1, "thermal": 1}
    threading.Timer(0.05, slot.put, args=("nadir", 3)).start()
    assert slot.take(2.0) == {"nadir": 3}  # a waiting taker wakes up
    assert slot.take(0.05) == {}


def test_frames_flow_and_bad_frames_are_counted(sessions) -> None:
    a, b = sessions
    sub = FrameSubscriber(
        a, {"nadir": "uav/camera/nadir", "thermal": CameraTopic("uav/camera/thermal", True)}
    )
    pub = FramePublisher(b, "uav/camera/nadir")
    pub_t = FramePublisher(b, "uav/camera/thermal", compressed=True)
    status_seen: list[str] = []
    status_sub = a.declare_subscriber(
        "companion/status", lambda s: status_seen.append(s.payload.to_bytes().decode())
    )
    try:
        publish_until_seen(pub, sub, "nadir")
        rng = np.random.default_rng(2)
        img = rng.integers(0, 256, (60, 80), dtype=np.uint8)
        stamp = time.time_ns() // 1000
        pub.put(img, stamp)
        assert wait_for(lambda: "nadir" in sub.slot.peek_keys())
        frame = sub.slot.take(1.0)["nadir"]
        assert frame.stamp_us == stamp and frame.camera == "nadir"
        np.testing.assert_array_equal(frame.image, img)
        thermal = rng.integers(0, 65536, (30, 40), dtype=np.uint16)
        pub_t.put(thermal, stamp + 1)
        assert wait_for(lambda: "thermal" in sub.slot.peek_keys())
        np.testing.assert_array_equal(sub.slot.take(0.0)["thermal"].image, thermal)
        good = encode_image(img, stamp + 10)
        pub.put_bytes(good[: len(good) // 2])  # truncated
        pub.put_bytes(b"\x07" * 100)  # not CDR
        pub.put_bytes(encode_image(img, stamp - 1_000))  # backwards in time
        pub.put_bytes(encode_image(img, stamp + 10_000_000))  # from the future
        errors = lambda: sub.stats()["nadir"]["errors"]  # noqa: E731
        assert wait_for(lambda: sum(errors().values()) == 4)
        assert errors() == {
            frames.TRUNCATED: 1,
            frames.BAD_CDR: 1,
            frames.STAMP_BACKWARDS: 1,
            frames.STAMP_FUTURE: 1,
        }
        status = StatusPublisher(b, "companion/status")
        text = status.publish({"fps": np.float64(49.5), "link": {"state": "up"}, "counts": np.arange(2)})
        assert json.loads(text) == {"fps": 49.5, "link": {"state": "up"}, "counts": [0, 1]}
        assert wait_for(lambda: status_seen)
        assert json.loads(status_seen[0])["link"]["state"] == "up"
    finally:
        status_sub.undeclare()
        sub.close()
        pub.close()
        pub_t.close()


def test_slow_consumer_drops_stale_frames_never_queues(sessions) -> None:
    a, b = sessions
    sub = FrameSubscriber(a, {"nadir": "uav/camera/nadir"}, stamp_gate=lambda: StampGate(max_age_us=None))
    pub = FramePublisher(b, "uav/camera/nadir")
    try:
        publish_until_seen(pub, sub, "nadir")
        before = dict(sub.slot.dropped)
        base = time.time_ns() // 1000
        img = np.zeros((16, 16), dtype=np.uint8)
        for i in range(20):  # nobody takes while these arrive
            pub.put(img, base + 1_000 * (i + 1))
        assert wait_for(lambda: sub.counters["nadir"].decoded >= 21)
        time.sleep(0.1)
        taken = sub.slot.take(0.0)
        assert taken["nadir"].stamp_us == base + 20_000  # the latest one wins
        assert sub.slot.dropped["nadir"] - before.get("nadir", 0) == 19
    finally:
        sub.close()
        pub.close()


def test_sink_receives_frames_instead_of_slot(sessions) -> None:
    a, b = sessions
    got: list[Any] = []
    sub = FrameSubscriber(a, {"nadir": "uav/camera/nadir"}, sink=got.append)
    pub = FramePublisher(b, "uav/camera/nadir")
    try:
        img = np.zeros((8, 8), dtype=np.uint8)
        assert wait_for(lambda: pub.put(img, time.time_ns() // 1000) and bool(got))
        assert got[0].camera == "nadir" and sub.slot.take(0.0) == {}
    finally:
        sub.close()
        pub.close()


def test_bad_mode_is_refused() -> None:
    with pytest.raises(ValueError):
        open_session("satellite")
