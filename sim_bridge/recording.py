"""Recordings of what goes over Zenoh, as rosbag2 bags (MCAP storage), and their replay onto Zenoh.

Topic names follow zenoh-bridge-ros2dds: the Zenoh key ``uav/camera/nadir`` is the ROS 2 topic
``/uav/camera/nadir`` (the key without the leading slash), so a bag recorded here opens in ``ros2 bag``,
Foxglove or rosbags, and a bag recorded by ROS 2 replays here.

- ``BagRecorder`` subscribes key expressions and writes every sample's payload AS RECEIVED (the CDR
  bytes, no re-encoding) with its receive time (Unix ns) as the log time. The companion's status line,
  a JSON string on Zenoh, is wrapped into a CDR ``std_msgs/msg/String``. Zenoh callbacks only enqueue;
  one writer thread owns the bag; a full queue drops and counts (nothing queues without bound).
- ``BagReplayer`` reads a rosbag2 (MCAP or sqlite3) with rosbags' Reader and publishes its image
  topics at the recorded pace (header stamps or log times, scaled by ``rate``). A message that does not
  decode as the image it claims to be is counted by reason and skipped. ``restamp`` rewrites the header
  stamp to the replay time (so a live companion's StampGate accepts it) and leaves every other byte,
  pixels included, as recorded.
- ``recover_bag`` rebuilds a readable bag from one whose recorder was killed (power cut, SIGKILL, a full
  disk): such a bag has no metadata.yaml and its MCAP no index or footer, and no reader opens it. What the
  file holds up to the first damaged record is copied into a new bag; the chunk being filled when the
  recorder died (at most ~1 MiB, a few frames) is lost. ROS 2 answers this with ``ros2 bag reindex``.
"""

from __future__ import annotations

import logging
import queue
import struct
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import zenoh
from mcap.exceptions import McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_typestore

from companion.io.frames import COMPRESSED_MSGTYPE, IMAGE_MSGTYPE, FrameError, decode_frame
from companion.io.ros_msgs import ROSBAG_VERSION
from companion.io.zenoh_io import wall_clock_us

log = logging.getLogger(__name__)

_TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
_String = _TYPESTORE.types["std_msgs/msg/String"]

STRING_MSGTYPE: Final = "std_msgs/msg/String"
"""ROS 2 type the companion's JSON status line is recorded as."""
IMAGE_MSGTYPES: Final = (IMAGE_MSGTYPE, COMPRESSED_MSGTYPE)
"""Message types the replayer publishes."""

_CDR_HEADERS: Final = (b"\x00\x00", b"\x00\x01")  # CDR big / little endian encapsulation

# Replay counter keys besides the FrameError reasons.
READ_ERROR: Final = "read_error"
"""The bag itself could not be read further (corrupt chunk, truncated file): replay stops there."""


def topic_from_key(key: str) -> str:
    """Zenoh key -> ROS 2 topic (zenoh-bridge-ros2dds mapping): ``uav/camera/nadir`` -> ``/uav/camera/nadir``."""
    return "/" + key.strip("/")


def key_from_topic(topic: str) -> str:
    """ROS 2 topic -> Zenoh key: ``/uav/camera/nadir`` -> ``uav/camera/nadir``."""
    return topic.strip("/")


# --------------------------------------------------------------------------------------------------------
# recording


@dataclass(frozen=True)
class RecordTopic:
    """One subscription: a Zenoh key expression (wildcards allowed) and the ROS 2 type of its samples."""

    key_expr: str
    msgtype: str = IMAGE_MSGTYPE
    """sensor_msgs/msg/Image, sensor_msgs/msg/CompressedImage or std_msgs/msg/String."""


@dataclass(frozen=True)
class RecorderOptions:
    """Settings of a recording."""

    storage: str = "mcap"
    """Bag storage: "mcap" (default, what Foxglove and ROS 2 Jazzy use) or "sqlite3"."""
    queue_size: int = 256
    """Samples buffered between the Zenoh threads and the writer (~60 MB of 480x480 frames); overflow drops."""


@dataclass
class TopicStats:
    """What was recorded on one topic. Times are log (receive) times in Unix ns."""

    topic: str
    msgtype: str
    messages: int = 0
    bytes: int = 0
    first_ns: int = 0
    last_ns: int = 0
    not_cdr: int = 0
    """Samples on an image topic without a CDR header (stored anyway: a recording keeps the wire as it was)."""

    def rate_hz(self) -> float:
        span = (self.last_ns - self.first_ns) * 1e-9
        return (self.messages - 1) / span if self.messages > 1 and span > 0 else 0.0


class BagRecorder:
    """Records Zenoh samples into a new rosbag2 directory ``out_path``. ``start()``, ``stop()``.

    clock_ns: the log-time clock (Unix ns, as ROS 2 uses); injectable for tests.
    """

    def __init__(
        self,
        session: zenoh.Session,
        out_path: str | Path,
        topics: Sequence[RecordTopic],
        options: RecorderOptions | None = None,
        clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.options = opts = options or RecorderOptions()
        if opts.storage not in ("mcap", "sqlite3"):
            raise ValueError(f"storage {opts.storage!r}: expected mcap or sqlite3")
        for t in topics:
            if t.msgtype not in (*IMAGE_MSGTYPES, STRING_MSGTYPE):
                raise ValueError(
                    f"{t.key_expr}: cannot record {t.msgtype!r} (Image, CompressedImage, String)"
                )
        if not topics:
            raise ValueError("nothing to record: no key expression given")
        self.path = Path(out_path)
        self.session = session
        self.topics = list(topics)
        self.clock_ns = clock_ns
        plugin = StoragePlugin.MCAP if opts.storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(self.path, version=ROSBAG_VERSION, storage_plugin=plugin)
        self._queue: queue.Queue[tuple[str, str, int, bytes] | None] = queue.Queue(maxsize=opts.queue_size)
        self._connections: dict[tuple[str, str], Any] = {}
        self._lock = threading.Lock()
        self.stats: dict[str, TopicStats] = {}
        """Per ROS topic, filled by the writer thread (read under ``lock`` or via ``summary()``)."""
        self.dropped = 0
        """Samples lost because the writer fell behind (queue full)."""
        self.write_errors = 0
        self._subs: list[Any] = []
        self._thread: threading.Thread | None = None
        self._closed = False

    @property
    def lock(self) -> threading.Lock:
        return self._lock

    def start(self) -> None:
        """Create the bag and start recording. Raises WriterError if ``out_path`` exists."""
        self._writer.open()
        self._thread = threading.Thread(target=self._write_loop, name="bag-writer", daemon=True)
        self._thread.start()
        for t in self.topics:
            self._subs.append(self.session.declare_subscriber(t.key_expr, self._make_handler(t.msgtype)))

    def _make_handler(self, msgtype: str) -> Callable[[zenoh.Sample], None]:
        def handler(sample: zenoh.Sample) -> None:
            # Zenoh thread: stamp and hand over, nothing else.
            item = (str(sample.key_expr), msgtype, self.clock_ns(), sample.payload.to_bytes())
            try:
                self._queue.put_nowait(item)
            except queue.Full:
                with self._lock:
                    self.dropped += 1

        return handler

    def _connection(self, topic: str, msgtype: str) -> Any:
        conn = self._connections.get((topic, msgtype))
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=_TYPESTORE)
            self._connections[(topic, msgtype)] = conn
            with self._lock:
                self.stats[topic] = TopicStats(topic, msgtype)
        return conn

    def _write_loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            key, msgtype, log_ns, payload = item
            topic = topic_from_key(key)
            not_cdr = payload[:2] not in _CDR_HEADERS
            if msgtype == STRING_MSGTYPE and not_cdr:
                # the companion's status is plain JSON text on Zenoh: wrap it so ROS tools can read it
                text = payload.decode("utf-8", errors="replace")
                payload = bytes(_TYPESTORE.serialize_cdr(_String(data=text), STRING_MSGTYPE))
                not_cdr = False
            try:
                conn = self._connection(topic, msgtype)
                self._writer.write(conn, log_ns, payload)
            except (WriterError, OSError) as exc:  # disk full, ...: count, keep the recorder alive
                with self._lock:
                    self.write_errors += 1
                log.error("recording %s: %s", topic, exc)
                continue
            with self._lock:
                s = self.stats[topic]
                s.messages += 1
                s.bytes += len(payload)
                s.first_ns = s.first_ns or log_ns
                s.last_ns = log_ns
                s.not_cdr += int(not_cdr)

    def stop(self) -> dict[str, Any]:
        """Stop subscribing, write what is queued, close the bag (metadata.yaml); returns ``summary()``."""
        if not self._closed:
            self._closed = True
            for sub in self._subs:
                sub.undeclare()
            self._subs = []
            if self._thread is not None:
                self._queue.put(None)
                self._thread.join()
                self._writer.close()
        return self.summary()

    def summary(self) -> dict[str, Any]:
        """JSON-able: bag path, per-topic counts / bytes / rates, drops and write errors."""
        with self._lock:
            return {
                "bag": str(self.path),
                "storage": self.options.storage,
                "topics": {
                    t: {
                        "type": s.msgtype,
                        "messages": s.messages,
                        "bytes": s.bytes,
                        "rate_hz": round(s.rate_hz(), 3),
                        "duration_s": round((s.last_ns - s.first_ns) * 1e-9, 3),
                        "not_cdr": s.not_cdr,
                    }
                    for t, s in sorted(self.stats.items())
                },
                "dropped": self.dropped,
                "write_errors": self.write_errors,
            }


# --------------------------------------------------------------------------------------------------------
# replay


@dataclass(frozen=True)
class ReplayOptions:
    """Settings of a replay."""

    rate: float = 1.0
    """Playback speed factor (2.0 = twice as fast)."""
    clock: str = "header"
    """Pace by "header" stamps (capture times) or by "log" (receive) times."""
    restamp: bool = False
    """Rewrite header stamps to the replay time (Unix us), for a live companion's StampGate."""
    topics: tuple[str, ...] = ()
    """ROS topics to replay; empty = every Image / CompressedImage topic of the bag."""
    wait_subscribers_s: float = 5.0
    """Before the first message, wait up to this long for a Zenoh subscriber of each replayed key."""
    max_gap_s: float = 2.0
    """A jump of the pacing time larger than this (either way: a driver restart, a bogus stamp) is not
    waited for: the schedule restarts at that message (counted in ``time_jumps``)."""
    lossless: bool = True
    """Publish with Zenoh's BLOCK congestion control: when the link is busy a frame waits instead of being
    dropped, so a bench replay delivers every recorded frame (late rather than never; the pacing catches
    up). False = DROP, Zenoh's default and a live camera's behaviour, for testing how a companion copes."""


@dataclass
class ReplayResult:
    """Counts of one replay."""

    published: dict[str, int] = field(default_factory=dict)
    """Messages published per topic."""
    bad: dict[str, int] = field(default_factory=dict)
    """Messages skipped, by reason (FrameError reasons, "read_error")."""
    skipped_topics: dict[str, str] = field(default_factory=dict)
    """Topics of the bag not replayed -> their type."""
    duration_s: float = 0.0
    """Wall time from the first publication to the last."""
    late_s_max: float = 0.0
    """Largest lateness of a publication behind its schedule (a slow machine shows here)."""
    time_jumps: int = 0
    """Times the pacing clock jumped by more than ``max_gap_s`` and the schedule was restarted."""

    def count_bad(self, reason: str) -> None:
        self.bad[reason] = self.bad.get(reason, 0) + 1

    def as_dict(self) -> dict[str, Any]:
        return {
            "published": dict(self.published),
            "bad": dict(self.bad),
            "skipped_topics": dict(self.skipped_topics),
            "duration_s": round(self.duration_s, 3),
            "late_s_max": round(self.late_s_max, 4),
            "time_jumps": self.time_jumps,
        }


def restamp_cdr(payload: bytes, stamp_us: int) -> bytes:
    """Return ``payload`` (CDR Image / CompressedImage) with ``header.stamp`` set to ``stamp_us``.

    Hand-written on purpose: in plain CDR (the encapsulation rosbags and ROS 2 use) both messages begin
    with ``std_msgs/Header``, whose ``stamp`` is {int32 sec, uint32 nanosec} at bytes 4..12, right after
    the 4-byte encapsulation header (byte 1 = 1 little endian, 0 big). Patching those 8 bytes keeps every
    other byte, pixels included, exactly as recorded; a decode/encode round trip would rebuild the whole
    message. The caller has already decoded the payload, so the layout is known to hold.
    """
    sec, usec = divmod(int(stamp_us), 1_000_000)
    fmt = "<iI" if payload[1:2] == b"\x01" else ">iI"
    return payload[:4] + struct.pack(fmt, sec, usec * 1000) + payload[12:]


class BagReplayer:
    """Publishes a bag's image topics on Zenoh (key = topic without the leading slash). Call ``run()``.

    clock_us: the wall clock (Unix us) that paces the replay and gives the new stamps with ``restamp``.
    """

    def __init__(
        self,
        session: zenoh.Session,
        bag_path: str | Path,
        options: ReplayOptions | None = None,
        clock_us: Callable[[], int] = wall_clock_us,
    ) -> None:
        self.options = opts = options or ReplayOptions()
        if not opts.rate > 0:
            raise ValueError(f"rate must be > 0, got {opts.rate}")
        if opts.clock not in ("header", "log"):
            raise ValueError(f"clock {opts.clock!r}: expected header or log")
        self.session = session
        self.path = Path(bag_path)
        self.clock_us = clock_us
        self._stop = threading.Event()

    def stop(self) -> None:
        """Ask a running ``run()`` to return after the current message."""
        self._stop.set()

    def run(self, progress: Callable[[ReplayResult], None] | None = None) -> ReplayResult:
        """Replay the whole bag (or until ``stop()``). Raises ReaderError / FileNotFoundError if the bag
        cannot be opened at all; anything wrong inside it is counted and skipped."""
        opts = self.options
        res = ReplayResult()
        with Reader(self.path) as reader:
            conns = []
            for c in reader.connections:
                wanted = not opts.topics or c.topic in opts.topics
                if wanted and c.msgtype in IMAGE_MSGTYPES:
                    conns.append(c)
                else:
                    res.skipped_topics[c.topic] = c.msgtype
            missing = [t for t in opts.topics if t not in {c.topic for c in conns}]
            if missing:
                log.warning("replay: no image topic %s in %s", ", ".join(missing), self.path)
            if not conns:
                return res
            congestion = zenoh.CongestionControl.BLOCK if opts.lossless else zenoh.CongestionControl.DROP
            pubs = {
                c.topic: self.session.declare_publisher(
                    key_from_topic(c.topic), congestion_control=congestion
                )
                for c in conns
            }
            try:
                self._wait_subscribers(pubs)
                self._play(reader, conns, pubs, res, progress)
            finally:
                for pub in pubs.values():
                    pub.undeclare()
        return res

    def _wait_subscribers(self, pubs: dict[str, Any]) -> None:
        end = time.monotonic() + self.options.wait_subscribers_s
        while not self._stop.is_set():
            waiting = [t for t, p in pubs.items() if not p.matching_status.matching]
            if not waiting:
                return
            if time.monotonic() >= end:
                log.warning("replay: no subscriber yet for %s; publishing anyway", ", ".join(waiting))
                return
            time.sleep(0.01)

    def _play(
        self,
        reader: Reader,
        conns: list[Any],
        pubs: dict[str, Any],
        res: ReplayResult,
        progress: Callable[[ReplayResult], None] | None,
    ) -> None:
        opts = self.options
        t0_msg_us: int | None = None
        t0_wall_us = 0
        last_msg_us: int | None = None
        last_stamp: dict[str, int] = {}
        first_pub_us = last_pub_us = 0
        messages = reader.messages(connections=conns)
        while not self._stop.is_set():
            try:
                item = next(messages, None)
            except (ReaderError, OSError, ValueError, struct.error, KeyError) as exc:
                # the bag is damaged from here on: what was read is replayed, the rest is lost
                res.count_bad(READ_ERROR)
                log.error(
                    "replay: %s unreadable after %d messages: %s", self.path, sum(res.published.values()), exc
                )
                return
            if item is None:
                return
            conn, log_ns, raw = item
            payload = bytes(raw)
            try:
                frame = decode_frame(payload, conn.topic, compressed=conn.msgtype == COMPRESSED_MSGTYPE)
            except FrameError as exc:
                res.count_bad(exc.reason)
                log.debug("replay %s: skipped: %s", conn.topic, exc)
                continue
            t_msg_us = frame.stamp_us if opts.clock == "header" else log_ns // 1000
            if last_msg_us is not None and abs(t_msg_us - last_msg_us) > opts.max_gap_s * 1e6:
                res.time_jumps += 1
                log.warning(
                    "replay %s: time jumps %.1f s: schedule restarted",
                    conn.topic,
                    (t_msg_us - last_msg_us) * 1e-6,
                )
                t0_msg_us = last_msg_us = None
            if t0_msg_us is None:
                t0_msg_us, t0_wall_us = t_msg_us, self.clock_us()
            # out-of-order times (reordered capture stamps) go out at once, never wait backwards
            if last_msg_us is None or t_msg_us >= last_msg_us:
                due_us = t0_wall_us + int((t_msg_us - t0_msg_us) / opts.rate)
                wait_s = (due_us - self.clock_us()) * 1e-6
                if wait_s > 0 and self._stop.wait(wait_s):
                    return
                res.late_s_max = max(res.late_s_max, (self.clock_us() - due_us) * 1e-6)
                last_msg_us = t_msg_us
            now_us = self.clock_us()
            if opts.restamp:
                stamp = max(now_us, last_stamp.get(conn.topic, 0) + 1)
                last_stamp[conn.topic] = stamp
                payload = restamp_cdr(payload, stamp)
            pubs[conn.topic].put(payload)
            res.published[conn.topic] = res.published.get(conn.topic, 0) + 1
            first_pub_us = first_pub_us or now_us
            last_pub_us = now_us
            res.duration_s = (last_pub_us - first_pub_us) * 1e-6
            if progress is not None:
                progress(res)


# --------------------------------------------------------------------------------------------------------
# recovery of a bag whose recorder died


@dataclass
class RecoveryResult:
    """What ``recover_bag`` copied."""

    out: str
    """The new bag directory."""
    messages: dict[str, int] = field(default_factory=dict)
    """Messages copied per topic."""
    skipped_topics: dict[str, str] = field(default_factory=dict)
    """Topics not copied -> why (a type whose definition is unknown)."""
    stopped: list[str] = field(default_factory=list)
    """Per source file that could not be read to its end: where and why (the rest of it is lost)."""
    first_ns: int = 0
    last_ns: int = 0
    """Log times (Unix ns) of the first and last message copied."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "out": self.out,
            "messages": dict(self.messages),
            "skipped_topics": dict(self.skipped_topics),
            "stopped": list(self.stopped),
            "duration_s": round((self.last_ns - self.first_ns) * 1e-9, 3) if self.messages else 0.0,
        }


# (topic, msgtype, message definition text or "", offered QoS profiles (YAML) or "", log time ns, payload)
_RawMessage = tuple[str, str, str, str, int, bytes]


def _mcap_messages(path: Path, res: RecoveryResult) -> Iterator[_RawMessage]:
    """Messages of an MCAP file in file order, read record by record (mcap's StreamReader, which needs no
    index or footer), up to the first truncated or corrupt record."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    count = 0
    with path.open("rb") as f:
        try:
            for rec in StreamReader(f, validate_crcs=True).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    ch = channels[rec.channel_id]
                    sc = schemas.get(ch.schema_id)
                    msgtype = sc.name if sc is not None else ""
                    msgdef = sc.data.decode("utf-8", errors="replace") if sc is not None else ""
                    qos = ch.metadata.get("offered_qos_profiles", "")
                    count += 1
                    yield ch.topic, msgtype, msgdef, qos, rec.log_time, rec.data
        except (McapError, ValueError, struct.error, OSError) as exc:  # EndOfFile, bad CRC, bad opcode, ...
            res.stopped.append(f"{path.name}: after {count} messages: {type(exc).__name__} {exc}".strip())


def _sqlite_messages(path: Path, res: RecoveryResult) -> Iterator[_RawMessage]:
    """Messages of a rosbag2 sqlite3 file in insertion order: what was committed. A killed writer leaves a hot
    journal that sqlite rolls back on opening, so the file is read from a copy and the source is never
    modified. (rosbags' sqlite3 writer, ``record --storage sqlite3``, commits only when closed: a killed one
    leaves nothing; ROS 2's recorder commits as it goes.)"""
    import shutil
    import sqlite3
    import tempfile

    count = 0
    tmp = Path(tempfile.mkdtemp(prefix="recover-"))
    try:
        for part in path.parent.glob(path.name + "*"):  # the file and its -journal / -wal
            shutil.copy2(part, tmp / part.name)
        con = sqlite3.connect(tmp / path.name)
        try:
            cols = {row[1] for row in con.execute("PRAGMA table_info(topics)")}
            qos_col = "offered_qos_profiles" if "offered_qos_profiles" in cols else "''"
            topics = {
                tid: (name, msgtype, qos or "")
                for tid, name, msgtype, qos in con.execute(f"SELECT id, name, type, {qos_col} FROM topics")
            }
            for tid, stamp, data in con.execute("SELECT topic_id, timestamp, data FROM messages ORDER BY id"):
                if tid in topics:
                    name, msgtype, qos = topics[tid]
                    count += 1
                    yield name, msgtype, "", qos, int(stamp), bytes(data)
        finally:
            con.close()
    except (sqlite3.Error, OSError) as exc:
        res.stopped.append(f"{path.name}: after {count} messages: {type(exc).__name__} {exc}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _recovery_sources(src: Path) -> list[Path]:
    if src.is_file():
        return [src]
    if not src.is_dir():
        raise FileNotFoundError(f"{src}: no such bag directory or file")
    import re

    def split_number(p: Path) -> list[Any]:  # ROS 2 splits as bag_0, bag_1, ..., bag_10: numeric order
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]

    files = sorted(src.glob("*.mcap"), key=split_number) + sorted(src.glob("*.db3"), key=split_number)
    if not files:
        raise FileNotFoundError(f"{src}: no .mcap or .db3 file in it")
    return files


def recover_bag(src: str | Path, out: str | Path | None = None) -> RecoveryResult:
    """Copy every readable message of the bag ``src`` (a directory of .mcap / .db3 files, or one file) into a
    new MCAP bag ``out`` (default: ``src`` + "-recovered"), which any rosbag2 reader and ``replay`` open.

    Payloads and log times are copied as they are. A message whose type is neither in the ROS 2 Humble
    type store nor described by a definition the file carries is left out, its topic listed in
    ``skipped_topics``. Raises FileNotFoundError when there is nothing to read and WriterError when ``out``
    exists."""
    from rosbags.typesys import get_types_from_msg

    src = Path(src)
    files = _recovery_sources(src)
    base = src if src.is_dir() else src.parent / src.stem
    out_path = Path(out) if out is not None else base.with_name(base.name + "-recovered")
    res = RecoveryResult(str(out_path))
    typestore = get_typestore(Stores.ROS2_HUMBLE)
    writer = Writer(out_path, version=ROSBAG_VERSION, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conns: dict[tuple[str, str], Any] = {}
    try:
        for path in files:
            reader = _mcap_messages(path, res) if path.suffix == ".mcap" else _sqlite_messages(path, res)
            for topic, msgtype, msgdef, qos, log_ns, data in reader:
                conn = conns.get((topic, msgtype))
                if conn is None:
                    if topic in res.skipped_topics:
                        continue
                    if msgtype not in typestore.types:
                        try:  # a type of the recording's own: register it from the definition in the file
                            # (rosbags parses the "ros2msg" layout with its "MSG:" dependencies itself)
                            found = get_types_from_msg(msgdef, msgtype)
                            typestore.register({k: v for k, v in found.items() if k not in typestore.types})
                        except Exception as exc:  # noqa: BLE001 - any parse failure means "unknown type"
                            res.skipped_topics[topic] = f"{msgtype or 'no type'}: definition unknown ({exc})"
                            continue
                    try:
                        profiles = parse_qos(qos) if qos else []
                    except Exception:  # noqa: BLE001 - QoS is advisory: a bad one is dropped, not fatal
                        profiles = []
                    conn = writer.add_connection(
                        topic, msgtype, typestore=typestore, offered_qos_profiles=profiles
                    )
                    conns[(topic, msgtype)] = conn
                writer.write(conn, log_ns, data)
                res.messages[topic] = res.messages.get(topic, 0) + 1
                res.first_ns = min(res.first_ns or log_ns, log_ns)
                res.last_ns = max(res.last_ns, log_ns)
    finally:
        writer.close()
    return res


# --------------------------------------------------------------------------------------------------------
# command line (``python -m sim_bridge record`` / ``replay``; sim_bridge.cli registers these)


def add_zenoh_args(p: Any, listen: Sequence[str] = (), connect: Sequence[str] = ()) -> None:
    """--zenoh-mode / --zenoh-listen / --zenoh-connect (repeatable) with the given defaults."""
    p.add_argument("--zenoh-mode", default="peer", choices=["peer", "client"])
    p.add_argument(
        "--zenoh-listen",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to listen on, repeatable (default {' '.join(listen) or 'none'})",
    )
    p.add_argument(
        "--zenoh-connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to connect to, repeatable (default {' '.join(connect) or 'none'})",
    )
    p.set_defaults(_zenoh_listen_default=list(listen), _zenoh_connect_default=list(connect))


def open_zenoh_from_args(a: Any) -> zenoh.Session:
    """Open the session described by ``add_zenoh_args``' options (multicast scouting off)."""
    from companion.io.zenoh_io import open_session

    listen = a.zenoh_listen if a.zenoh_listen is not None else a._zenoh_listen_default
    connect = a.zenoh_connect if a.zenoh_connect is not None else a._zenoh_connect_default
    return open_session(a.zenoh_mode, connect=connect, listen=listen, multicast_scouting=False)


def add_record_parser(sub: Any) -> None:
    """The ``record`` subcommand."""
    p = sub.add_parser(
        "record",
        help="record Zenoh camera keys (and the companion status) into a rosbag2 (MCAP)",
        description="Record Zenoh samples into a rosbag2 bag; topic = key with a leading slash; payloads "
        "stored as received, log time = receive time. Stops on Ctrl-C / SIGTERM or after --duration.",
    )
    p.add_argument("--out", default=None, help="bag directory to create (default runs/rec-<time>)")
    p.add_argument(
        "--key",
        action="append",
        default=None,
        help="Zenoh key (expression) carrying sensor_msgs/Image, repeatable (default uav/camera/nadir)",
    )
    p.add_argument(
        "--compressed-key", action="append", default=[], help="key carrying sensor_msgs/CompressedImage"
    )
    p.add_argument("--status", action="store_true", help="also record the companion status (std_msgs/String)")
    p.add_argument("--status-key", default="companion/status")
    p.add_argument("--duration", type=float, default=0.0, help="seconds; 0 = until Ctrl-C (default)")
    p.add_argument(
        "--storage",
        default="mcap",
        choices=["mcap", "sqlite3"],
        help="mcap (default) keeps all but the last ~1 MiB if the recorder is killed; sqlite3 keeps nothing then",
    )
    add_zenoh_args(p, connect=["tcp/127.0.0.1:7447"])
    p.set_defaults(func=cmd_record)


def add_replay_parser(sub: Any) -> None:
    """The ``replay`` subcommand."""
    p = sub.add_parser(
        "replay",
        help="publish a rosbag2's image topics on Zenoh at the recorded pace",
        description="Replay a rosbag2 (MCAP or sqlite3) onto Zenoh (key = topic without the leading "
        "slash). Bad messages are counted and skipped.",
    )
    p.add_argument("bag", help="bag directory, or a .mcap / .db3 file")
    p.add_argument("--rate", type=float, default=1.0, help="speed factor (default %(default)s)")
    p.add_argument("--clock", default="header", choices=["header", "log"], help="pace by (default header)")
    p.add_argument("--restamp", action="store_true", help="rewrite header stamps to now (live companion)")
    p.add_argument("--topic", action="append", default=[], help="replay only this topic, repeatable")
    p.add_argument(
        "--wait-subscribers", type=float, default=5.0, help="s to wait for a subscriber (default 5)"
    )
    p.add_argument(
        "--lossy",
        action="store_true",
        help="let Zenoh drop frames when the link is busy, as a live camera does (default: wait, lose none)",
    )
    add_zenoh_args(p, listen=["tcp/127.0.0.1:7447"])
    p.set_defaults(func=cmd_replay)


def add_recover_parser(sub: Any) -> None:
    """The ``recover`` subcommand."""
    p = sub.add_parser(
        "recover",
        help="rebuild a readable bag from one whose recorder was killed (no metadata.yaml / MCAP footer)",
        description="Copy every readable message of a damaged rosbag2 (MCAP or sqlite3) into a new MCAP bag, "
        "up to the first truncated or corrupt record; payloads and log times unchanged.",
    )
    p.add_argument("bag", help="the damaged bag directory, or its .mcap / .db3 file")
    p.add_argument("--out", default=None, help="new bag directory (default: BAG-recovered)")
    p.set_defaults(func=cmd_recover)


def cmd_recover(a: Any) -> int:
    """``python -m sim_bridge recover``: 0 when a bag was written (even if part of the source was lost), 2 when
    there was nothing to read or the output exists."""
    import json

    try:
        res = recover_bag(a.bag, a.out)
    except (FileNotFoundError, WriterError) as exc:
        print(f"recover: {exc}")
        return 2
    print(f"recovered into {res.out}")
    for topic, n in res.messages.items():
        print(f"  {topic:28s} {n:6d} messages")
    if not res.messages:
        print("  no message could be read")
    for topic, why in res.skipped_topics.items():
        print(f"  {topic:28s} not copied: {why}")
    for where in res.stopped:
        print(f"  read stopped in {where} (the rest of that file is lost)")
    print(json.dumps({"recovered": res.as_dict()}), flush=True)
    return 0


def _print_record_summary(summary: dict[str, Any]) -> None:
    print(f"bag: {summary['bag']} ({summary['storage']})")
    if not summary["topics"]:
        print("  nothing was received")
    for topic, t in summary["topics"].items():
        extra = f", {t['not_cdr']} without CDR header" if t["not_cdr"] else ""
        print(
            f"  {topic:28s} {t['type']:34s} {t['messages']:6d} msgs {t['bytes'] / 1e6:9.2f} MB "
            f"{t['duration_s']:8.1f} s {t['rate_hz']:7.2f} Hz{extra}"
        )
    if summary["dropped"] or summary["write_errors"]:
        print(f"  dropped (writer behind): {summary['dropped']}, write errors: {summary['write_errors']}")


def cmd_record(a: Any) -> int:
    """``python -m sim_bridge record``: 0 on a clean stop, 2 if the bag cannot be created."""
    import json
    import signal

    keys = a.key if a.key else ([] if a.compressed_key else ["uav/camera/nadir"])
    topics = [RecordTopic(k, IMAGE_MSGTYPE) for k in keys]
    topics += [RecordTopic(k, COMPRESSED_MSGTYPE) for k in a.compressed_key]
    if a.status:
        topics.append(RecordTopic(a.status_key, STRING_MSGTYPE))
    out = a.out or f"runs/rec-{time.strftime('%Y%m%d-%H%M%S')}"
    session = open_zenoh_from_args(a)
    stop = threading.Event()
    try:
        rec = BagRecorder(session, out, topics, RecorderOptions(storage=a.storage))
        rec.start()
    except (WriterError, ValueError) as exc:
        print(f"record: {exc}")
        session.close()
        return 2
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    print(
        f"recording {', '.join(f'{t.key_expr} ({t.msgtype})' for t in topics)} into {out}"
        + (f" for {a.duration:g} s" if a.duration > 0 else " until Ctrl-C"),
        flush=True,
    )
    end = time.monotonic() + a.duration if a.duration > 0 else None
    while not stop.is_set() and (end is None or time.monotonic() < end):
        stop.wait(0.2 if end is None else min(0.2, max(0.0, end - time.monotonic())))
    summary = rec.stop()
    session.close()
    for sig, handler in previous.items():
        signal.signal(sig, handler)
    _print_record_summary(summary)
    print(json.dumps({"recorded": summary}), flush=True)
    return 0


def cmd_replay(a: Any) -> int:
    """``python -m sim_bridge replay``: 0 when the bag was played (bad messages counted), 2 if unreadable."""
    import json
    import signal

    opts = ReplayOptions(
        rate=a.rate,
        clock=a.clock,
        restamp=a.restamp,
        topics=tuple(a.topic),
        wait_subscribers_s=a.wait_subscribers,
        lossless=not a.lossy,
    )
    session = open_zenoh_from_args(a)
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        replayer = BagReplayer(session, a.bag, opts)
        for sig in previous:
            signal.signal(sig, lambda *_: replayer.stop())
        print(f"replaying {a.bag} at x{a.rate:g} (pace: {a.clock} times, restamp {a.restamp})", flush=True)
        res = replayer.run()
    except (ReaderError, FileNotFoundError, ValueError) as exc:
        print(f"replay: cannot read {a.bag}: {exc}")
        bag = Path(a.bag)
        if bag.is_dir() and not (bag / "metadata.yaml").exists() and any(bag.glob("*.mcap")):
            print(f"  its recorder did not close it (killed?): python -m sim_bridge recover {a.bag}")
        return 2
    finally:
        session.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    for topic, n in res.published.items():
        print(f"  {topic:28s} {n:6d} published")
    for topic, msgtype in res.skipped_topics.items():
        print(f"  {topic:28s} not replayed ({msgtype})")
    if res.bad:
        print(f"  skipped bad messages: {', '.join(f'{k} {v}' for k, v in sorted(res.bad.items()))}")
    jumps = f", {res.time_jumps} time jumps not waited for" if res.time_jumps else ""
    print(f"  {res.duration_s:.2f} s, at most {res.late_s_max * 1000:.1f} ms behind schedule{jumps}")
    print(json.dumps({"replayed": res.as_dict()}), flush=True)
    return 0
