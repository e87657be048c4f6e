"""Latest-wins frame hand-off: bounded, drops counted, pairs matched by capture time."""

from __future__ import annotations

import threading

import numpy as np

from companion.handoff import FrameHandoff
from companion.types import Frame

IMG = np.zeros((4, 4), np.uint8)


def f(cam: str, t: int) -> Frame:
    return Frame(stamp_us=t, camera=cam, image=IMG)


def test_latest_wins_and_drops_are_counted() -> None:
    h = FrameHandoff(("nadir",))
    for t in (1000, 2000, 3000):
        h.put(f("nadir", t))
    got = h.take(0.0)
    assert got is not None and got["nadir"].stamp_us == 3000
    assert h.counters.dropped_stale == 2 and h.counters.received == 3
    assert h.take(0.01) is None  # nothing waits behind the taken frame


def test_pairs_within_tolerance_and_drops_unpaired() -> None:
    h = FrameHandoff(("visible", "thermal"), pair_tolerance_us=5_000)
    h.put(f("visible", 100_000))
    assert h.take(0.0) is None
    h.put(f("thermal", 150_000))  # 50 ms apart: the older visible frame is dropped as unpaired
    assert h.take(0.0) is None and h.counters.dropped_unpaired == 1
    h.put(f("visible", 151_000))
    got = h.take(0.0)
    assert got is not None and {k: v.stamp_us for k, v in got.items()} == {
        "visible": 151_000,
        "thermal": 150_000,
    }


def test_unknown_camera_is_ignored_and_take_wakes_on_put() -> None:
    h = FrameHandoff(("nadir",))
    h.put(f("other", 1))
    assert h.counters.received == 0
    out: list = []
    t = threading.Thread(target=lambda: out.append(h.take(5.0)))
    t.start()
    h.put(f("nadir", 7))
    t.join(2.0)
    assert out and out[0]["nadir"].stamp_us == 7
