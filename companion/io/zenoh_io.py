"""Zenoh side of the companion: open a session, subscribe camera frames, publish status.

Frames arrive as CDR ``sensor_msgs/msg/Image`` / ``CompressedImage`` (what zenoh-bridge-ros2dds
carries: ROS topic ``/uav/camera/nadir`` <-> key ``uav/camera/nadir``). They are decoded in
Zenoh's callback thread (decode is pure and fast) and handed to a ``LatestSlot``: latest wins, a
frame overwritten before the daemon took it counts as dropped; nothing queues without bound.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import numpy as np
import zenoh

from companion.io.frames import FrameError, StampGate, decode_frame, encode_compressed, encode_image
from companion.types import Frame

log = logging.getLogger(__name__)

T = TypeVar("T")


def wall_clock_us() -> int:
    """The companion clock: Unix epoch microseconds (the base of ROS 2 header stamps)."""
    return time.time_ns() // 1000


def open_session(
    mode: str = "peer",
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    multicast_scouting: bool = False,
) -> zenoh.Session:
    """Open a Zenoh session. mode: "peer" or "client"; endpoints like ``tcp/127.0.0.1:7447``."""
    if mode not in ("peer", "client", "router"):
        raise ValueError(f"zenoh mode {mode!r}: expected peer, client or router")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect or [])))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen or [])))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(multicast_scouting)))
    return zenoh.open(conf)


class LatestSlot(Generic[T]):
    """Thread-safe latest-wins hand-off, one slot per key (camera). Bounded by the number of keys.

    ``put`` never blocks; ``take`` returns every fresh item (and empties the slots), waiting up to
    ``timeout_s`` for at least one. An item replaced before it was taken counts as dropped.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._items: dict[str, T] = {}
        self.put_count: dict[str, int] = {}
        self.taken: dict[str, int] = {}
        self.dropped: dict[str, int] = {}

    def put(self, key: str, item: T) -> bool:
        """Store ``item`` for ``key``; True when it replaced an untaken one (a drop)."""
        with self._cond:
            replaced = key in self._items
            if replaced:
                self.dropped[key] = self.dropped.get(key, 0) + 1
            self._items[key] = item
            self.put_count[key] = self.put_count.get(key, 0) + 1
            self._cond.notify_all()
        return replaced

    def take(self, timeout_s: float | None = 0.0) -> dict[str, T]:
        """All fresh items by key (maybe empty after the timeout); None timeout waits forever."""
        with self._cond:
            if not self._items and timeout_s != 0.0:
                self._cond.wait_for(lambda: bool(self._items), timeout=timeout_s)
            items, self._items = self._items, {}
            for key in items:
                self.taken[key] = self.taken.get(key, 0) + 1
        return items

    def peek_keys(self) -> list[str]:
        """Keys holding a fresh item right now."""
        with self._cond:
            return list(self._items)


@dataclass(frozen=True)
class CameraTopic:
    """One camera subscription: Zenoh key expression and message type."""

    key_expr: str
    compressed: bool = False


@dataclass
class CameraCounters:
    """Per-camera subscriber counters."""

    received: int = 0
    decoded: int = 0
    errors: dict[str, int] | None = None
    """Decode and timestamp refusals by reason (FrameError / StampGate reasons)."""

    def count_error(self, reason: str) -> None:
        if self.errors is None:
            self.errors = {}
        self.errors[reason] = self.errors.get(reason, 0) + 1


class FrameSubscriber:
    """Subscribes one key expression per camera; decoded frames go to ``slot`` keyed by camera name.

    cameras: camera name -> CameraTopic (or a bare key expression string for raw Image).
    sink: where decoded frames go instead of the slot (e.g. the daemon's ``FrameHandoff.put``);
    None keeps them in ``self.slot``.
    stamp_gate: factory for one StampGate per camera (None: default gate).
    clock_us: the gate's clock; stamp_from_wall: how a frame's wall-clock stamp becomes a stamp in that clock
    (the daemon's ``CompanionClock.from_wall``, which takes out the wall clock's steps; None: as it is).
    """

    def __init__(
        self,
        session: zenoh.Session,
        cameras: Mapping[str, CameraTopic | str],
        slot: LatestSlot[Frame] | None = None,
        stamp_gate: Callable[[], StampGate] | None = None,
        clock_us: Callable[[], int] = wall_clock_us,
        sink: Callable[[Frame], object] | None = None,
        stamp_from_wall: Callable[[int], int] | None = None,
    ) -> None:
        self.slot: LatestSlot[Frame] = slot if slot is not None else LatestSlot()
        self._sink = sink
        self.clock_us = clock_us
        self.stamp_from_wall = stamp_from_wall
        self.topics = {
            name: topic if isinstance(topic, CameraTopic) else CameraTopic(topic)
            for name, topic in cameras.items()
        }
        self.counters = {name: CameraCounters() for name in self.topics}
        self._gates = {name: (stamp_gate or StampGate)() for name in self.topics}
        self._lock = threading.Lock()
        self._subs = [
            session.declare_subscriber(topic.key_expr, self._make_handler(name, topic))
            for name, topic in self.topics.items()
        ]

    def _make_handler(self, camera: str, topic: CameraTopic) -> Callable[[zenoh.Sample], None]:
        def handler(sample: zenoh.Sample) -> None:
            # Runs in a Zenoh thread: never let an exception escape (counted instead).
            counters = self.counters[camera]
            with self._lock:
                counters.received += 1
                seq = counters.received
            try:
                frame = decode_frame(sample.payload.to_bytes(), camera, topic.compressed, seq)
            except FrameError as exc:
                with self._lock:
                    counters.count_error(exc.reason)
                log.debug("camera %s: %s", camera, exc)
                return
            except Exception as exc:  # noqa: BLE001 - defensive: a codec bug must not kill the subscriber
                with self._lock:
                    counters.count_error("internal")
                log.exception("camera %s: unexpected decode failure: %s", camera, exc)
                return
            if self.stamp_from_wall is not None:
                frame = dataclasses.replace(frame, stamp_us=self.stamp_from_wall(frame.stamp_us))
            with self._lock:
                reason = self._gates[camera].check(frame.stamp_us, self.clock_us())
                if reason is not None:
                    counters.count_error(reason)
                    return
                counters.decoded += 1
            if self._sink is not None:
                self._sink(frame)
            else:
                self.slot.put(camera, frame)

        return handler

    def stats(self) -> dict[str, Any]:
        """JSON-able counters per camera (received / decoded / errors / dropped by the slot)."""
        with self._lock:
            return {
                name: {
                    "received": c.received,
                    "decoded": c.decoded,
                    "errors": dict(c.errors or {}),
                    "dropped": self.slot.dropped.get(name, 0),
                }
                for name, c in self.counters.items()
            }

    def close(self) -> None:
        """Undeclare the subscribers."""
        for sub in self._subs:
            sub.undeclare()
        self._subs = []


class FramePublisher:
    """Publishes camera frames as CDR Image / CompressedImage (for the simulator and the tests)."""

    def __init__(self, session: zenoh.Session, key_expr: str, compressed: bool = False, fmt: str = "png"):
        self.key_expr = key_expr
        self.compressed = compressed
        self.fmt = fmt
        self._pub = session.declare_publisher(key_expr)

    def put(self, image: np.ndarray, stamp_us: int, frame_id: str = "camera", encoding: str = "") -> int:
        """Encode and publish one image; returns the payload size in bytes."""
        if self.compressed:
            payload = encode_compressed(image, stamp_us, frame_id, self.fmt)
        else:
            payload = encode_image(image, stamp_us, frame_id, encoding)
        self._pub.put(payload)
        return len(payload)

    def put_bytes(self, payload: bytes) -> None:
        """Publish raw bytes as they are (e.g. a recording or a deliberately bad frame)."""
        self._pub.put(payload)

    def close(self) -> None:
        self._pub.undeclare()


class StatusPublisher:
    """Puts a JSON status string on a key (the daemon's health line)."""

    def __init__(self, session: zenoh.Session, key_expr: str = "companion/status") -> None:
        self.key_expr = key_expr
        self._pub = session.declare_publisher(key_expr)
        self.published = 0

    def publish(self, status: Mapping[str, Any]) -> str:
        """Serialise ``status`` (non-JSON values through str) and put it; returns the JSON text."""
        text = json.dumps(status, default=_json_default, sort_keys=True)
        self._pub.put(text)
        self.published += 1
        return text

    def close(self) -> None:
        self._pub.undeclare()


class StatusSubscriber:
    """Receives the daemon's JSON status messages (for ``companion watch`` on an operator's laptop).

    sink(dict) is called from Zenoh's thread for each message that parses as a JSON object; others are
    skipped (a publisher of another kind on the key must not stop the watch)."""

    def __init__(
        self,
        session: zenoh.Session,
        sink: Callable[[dict[str, Any]], None],
        key_expr: str = "companion/status",
    ) -> None:
        self.key_expr = key_expr
        self.sink = sink
        self._sub = session.declare_subscriber(key_expr, self._on)

    def _on(self, sample: Any) -> None:
        try:
            status = json.loads(sample.payload.to_bytes())
        except (ValueError, UnicodeDecodeError):
            return
        if isinstance(status, dict):
            self.sink(status)

    def close(self) -> None:
        self._sub.undeclare()


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
