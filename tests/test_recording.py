"""Recording Zenoh frames into rosbag2 (MCAP) and replaying bags onto Zenoh, over real loopback sessions."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from netutil import free_tcp_port, wait_for
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from companion.io.frames import StampGate, decode_image, encode_compressed, encode_image
from companion.io.zenoh_io import FramePublisher, FrameSubscriber, StatusPublisher, open_session
from sim_bridge import cli
from sim_bridge.recording import (
    IMAGE_MSGTYPE,
    READ_ERROR,
    STRING_MSGTYPE,
    BagRecorder,
    BagReplayer,
    RecordTopic,
    ReplayOptions,
    key_from_topic,
    restamp_cdr,
    topic_from_key,
)

KEY = "uav/camera/nadir"
TS = get_typestore(Stores.ROS2_HUMBLE)


def wait_matching(session, key: str) -> None:
    """Routes take a moment: wait until a publisher on ``key`` has a subscriber."""
    probe = session.declare_publisher(key)
    assert wait_for(lambda: probe.matching_status.matching, 5.0)
    probe.undeclare()


def pattern(k: int, size: int = 48) -> np.ndarray:
    rng = np.random.default_rng(k)
    return rng.integers(0, 256, (size, size), dtype=np.uint8)


def image_msg(stamp_us: int, height: int, width: int, encoding: str, n_bytes: int) -> bytes:
    """A well-formed CDR Image whose content may be inconsistent (for bad-input tests)."""
    sec, usec = divmod(stamp_us, 1_000_000)
    header = TS.types["std_msgs/msg/Header"](
        stamp=TS.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=usec * 1000), frame_id="cam"
    )
    msg = TS.types[IMAGE_MSGTYPE](
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width,
        data=np.zeros(n_bytes, np.uint8),
    )
    return bytes(TS.serialize_cdr(msg, IMAGE_MSGTYPE))


def now_us() -> int:
    return time.time_ns() // 1000


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_tcp_port()}"


@pytest.fixture
def sessions(endpoint):
    a = open_session("peer", listen=[endpoint], multicast_scouting=False)
    b = open_session("peer", connect=[endpoint], multicast_scouting=False)
    yield a, b
    b.close()
    a.close()


def record_frames(a, b, path: Path, n: int = 8, period_s: float = 0.1) -> tuple[list[bytes], list[int]]:
    """Publish ``n`` frames (session a) at ``period_s`` and record them (session b). Returns the payloads
    as sent and the wall times (us) just before each publication."""
    rec = BagRecorder(
        b, path, [RecordTopic(KEY), RecordTopic("companion/status", STRING_MSGTYPE)], clock_ns=time.time_ns
    )
    rec.start()
    pub = FramePublisher(a, KEY)
    status = StatusPublisher(a)
    wait_matching(a, KEY)
    wait_matching(a, "companion/status")
    payloads, sent_us = [], []
    t0 = time.monotonic()
    for k in range(n):
        time.sleep(max(0.0, t0 + k * period_s - time.monotonic()))
        stamp = now_us()
        sent_us.append(stamp)
        pub.put(pattern(k), stamp, frame_id="nadir_camera")
        payloads.append(encode_image(pattern(k), stamp, frame_id="nadir_camera"))
    status.publish({"state": "tracking", "frames": n})
    assert wait_for(lambda: rec.summary()["topics"].get("/companion/status", {}).get("messages") == 1)
    # the frames travel on another key than the status: under load the last one can land after the status
    wait_for(lambda: rec.summary()["topics"].get("/uav/camera/nadir", {}).get("messages") == n)
    summary = rec.stop()
    pub.close()
    status.close()
    assert summary["topics"]["/uav/camera/nadir"]["messages"] == n, summary
    return payloads, sent_us


def test_topic_key_mapping() -> None:
    assert topic_from_key("uav/camera/nadir") == "/uav/camera/nadir"
    assert key_from_topic("/uav/camera/nadir") == "uav/camera/nadir"
    assert key_from_topic(topic_from_key("companion/status")) == "companion/status"


def test_record_writes_mcap_with_the_cdr_bytes_as_received(sessions, tmp_path) -> None:
    a, b = sessions
    t_start = time.time_ns()
    payloads, _ = record_frames(a, b, tmp_path / "bag", n=5, period_s=0.05)
    t_end = time.time_ns()
    assert list((tmp_path / "bag").glob("*.mcap")), "MCAP storage expected"
    assert (tmp_path / "bag" / "metadata.yaml").exists()
    with Reader(tmp_path / "bag") as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        assert types == {"/uav/camera/nadir": IMAGE_MSGTYPE, "/companion/status": STRING_MSGTYPE}
        images: list[tuple[int, bytes]] = []
        status: list[tuple[int, bytes]] = []
        for conn, log_ns, raw in reader.messages():
            assert t_start <= log_ns <= t_end  # log time = receive time
            (images if conn.topic == "/uav/camera/nadir" else status).append((log_ns, bytes(raw)))
    assert [raw for _, raw in images] == payloads  # byte for byte, in order
    log_times = [t for t, _ in images]
    assert log_times == sorted(log_times)
    msg: Any = TS.deserialize_cdr(status[0][1], STRING_MSGTYPE)  # rosbags returns untyped messages
    text = msg.data
    assert json.loads(text) == {"state": "tracking", "frames": 5}


def replay_into_subscriber(
    a, b, bag: Path, options: ReplayOptions, gate: Callable[[], StampGate] | None = None
) -> tuple[Any, list[tuple[int, Any]], FrameSubscriber]:
    """Replay ``bag`` from session a into a FrameSubscriber on session b; (result, [(arrival_us, frame)])."""
    arrived: list[tuple[int, Any]] = []
    sub = FrameSubscriber(b, {"nadir": KEY}, stamp_gate=gate, sink=lambda f: arrived.append((now_us(), f)))
    res = BagReplayer(a, bag, options).run()
    n = res.published.get("/" + KEY, 0)
    wait_for(lambda: sub.counters["nadir"].received >= n, 3.0)
    sub.close()
    return res, arrived, sub


def test_replay_reproduces_the_recording_at_its_pace_and_restamps(sessions, tmp_path) -> None:
    a, b = sessions
    n, period = 8, 0.1
    payloads, sent_us = record_frames(a, b, tmp_path / "bag", n=n, period_s=period)
    sent_frames = [decode_image(p, "nadir") for p in payloads]

    # 1. as recorded (old stamps pass a gate without an age limit), at double speed
    no_age = lambda: StampGate(max_age_us=None)  # noqa: E731
    res, arrived, _ = replay_into_subscriber(a, b, tmp_path / "bag", ReplayOptions(rate=2.0), no_age)
    assert res.published == {"/uav/camera/nadir": n} and res.bad == {}
    assert res.skipped_topics == {"/companion/status": STRING_MSGTYPE}
    assert len(arrived) == n
    for (_, got), want in zip(arrived, sent_frames, strict=True):
        assert got.stamp_us == want.stamp_us
        np.testing.assert_array_equal(got.image, want.image)
    span_s = (arrived[-1][0] - arrived[0][0]) * 1e-6
    recorded_span_s = (sent_us[-1] - sent_us[0]) * 1e-6
    assert recorded_span_s / 2 * 0.7 < span_s < recorded_span_s / 2 * 1.5 + 0.05, (span_s, recorded_span_s)

    # 2. restamped at 1x into a live-style gate (2 s age limit, strictly increasing stamps)
    time.sleep(0.3)
    res, arrived, sub = replay_into_subscriber(a, b, tmp_path / "bag", ReplayOptions(rate=1.0, restamp=True))
    assert len(arrived) == n and sub.stats()["nadir"]["errors"] == {}
    for (t_arr, got), want in zip(arrived, sent_frames, strict=True):
        assert got.stamp_us > want.stamp_us + 200_000  # fresh, not the recorded stamp
        assert 0 <= t_arr - got.stamp_us < 200_000  # stamped at publication, arrived right after
        np.testing.assert_array_equal(got.image, want.image)
    gaps = np.diff([f.stamp_us for _, f in arrived]) * 1e-6
    assert np.median(gaps) == pytest.approx(period, abs=0.03)  # the recorded pace, in the new stamps


def test_restamp_changes_only_the_stamp() -> None:
    img = pattern(3, 16)
    for little in (True, False):
        msg = TS.deserialize_cdr(encode_image(img, 1_000_000_123, "cam"), IMAGE_MSGTYPE)
        payload = bytes(TS.serialize_cdr(msg, IMAGE_MSGTYPE, little_endian=little))
        out = restamp_cdr(payload, 1_700_000_000_654_321)
        assert len(out) == len(payload) and out[12:] == payload[12:] and out[:4] == payload[:4]
        frame = decode_image(out, "cam")
        assert frame.stamp_us == 1_700_000_000_654_321
        np.testing.assert_array_equal(frame.image, img)
    comp = encode_compressed(img, 5_000_000, "cam")
    cmsg: Any = TS.deserialize_cdr(restamp_cdr(comp, 7_000_001), "sensor_msgs/msg/CompressedImage")
    assert (cmsg.header.stamp.sec, cmsg.header.stamp.nanosec) == (7, 1000)


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP], ids=["sqlite3", "mcap"])
def test_bad_messages_in_a_bag_are_counted_and_skipped(sessions, tmp_path, storage) -> None:
    a, b = sessions
    t0 = now_us() - 3_600_000_000  # an hour-old flight
    good = [encode_image(pattern(k), t0 + k * 20_000) for k in range(6)]
    bad = {
        "truncated": good[0][: len(good[0]) // 2],
        "bad_cdr": b"\x07\x07not a cdr message at all",
        "empty": b"",
        "size_mismatch": image_msg(t0, 48, 48, "mono8", 100),
        "unknown_encoding": image_msg(t0, 4, 4, "yuv422_weird", 32),
    }
    path = tmp_path / "bag"
    with Writer(path, version=8, storage_plugin=storage) as w:
        conn = w.add_connection("/uav/camera/nadir", IMAGE_MSGTYPE, typestore=TS)
        other = w.add_connection("/tf_like", STRING_MSGTYPE, typestore=TS)
        thermal = w.add_connection("/uav/camera/thermal", "sensor_msgs/msg/CompressedImage", typestore=TS)
        w.write(thermal, t0 * 1000, encode_compressed(pattern(1), t0))
        w.write(thermal, t0 * 1000 + 5_000_000, encode_compressed(pattern(2), t0 + 5000, fmt="jpeg")[:-40])
        log_ns = t0 * 1000
        items = [good[0], good[1], bad["truncated"], good[2], bad["bad_cdr"], good[3], bad["empty"]]
        items += [good[4], bad["size_mismatch"], bad["unknown_encoding"], good[5]]
        for k, payload in enumerate(items):
            w.write(conn, log_ns + k * 10_000_000, payload)
        w.write(other, log_ns, bytes(TS.serialize_cdr(TS.types[STRING_MSGTYPE](data="x"), STRING_MSGTYPE)))
    res, arrived, _ = replay_into_subscriber(
        a,
        b,
        path,
        ReplayOptions(rate=4.0, restamp=True, clock="log", wait_subscribers_s=1.0),
        lambda: StampGate(),
    )
    assert res.published == {"/uav/camera/nadir": 6, "/uav/camera/thermal": 1}
    assert res.bad == {reason: 1 for reason in bad} | {"truncated": 2}
    assert res.skipped_topics == {"/tf_like": STRING_MSGTYPE}
    assert [f.image.tobytes() for _, f in arrived] == [pattern(k).tobytes() for k in range(6)]


def test_stamp_jumps_are_not_waited_for(sessions, tmp_path) -> None:
    """A bogus stamp a day ahead, then one a day behind: the replay restarts its schedule, never waits."""
    a, b = sessions
    t0 = now_us() - 60_000_000
    stamps = [t0, t0 + 50_000, t0 + 86_400_000_000, t0 + 100_000, t0 - 86_400_000_000, t0 + 150_000]
    path = tmp_path / "bag"
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/uav/camera/nadir", IMAGE_MSGTYPE, typestore=TS)
        for k, stamp in enumerate(stamps):
            w.write(conn, (t0 + k * 50_000) * 1000, encode_image(pattern(k), stamp))
    t = time.monotonic()
    res = BagReplayer(a, path, ReplayOptions(wait_subscribers_s=0.0)).run()
    assert time.monotonic() - t < 3.0
    assert res.published == {"/uav/camera/nadir": 6} and res.time_jumps == 4


def test_damaged_mcap_chunk_stops_the_replay_cleanly(sessions, tmp_path) -> None:
    """A broken record inside the bag: what comes before it is replayed, the rest is counted as lost."""
    a, b = sessions
    t0 = now_us() - 10_000_000
    path = tmp_path / "bag"
    payloads = [encode_image(pattern(k, 400), t0 + k * 10_000) for k in range(14)]  # > 1 MiB: 2+ chunks
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/uav/camera/nadir", IMAGE_MSGTYPE, typestore=TS)
        for k, payload in enumerate(payloads):
            w.write(conn, (t0 + k * 10_000) * 1000, payload)
    mcap = next(path.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    at = bytes(data).find(payloads[-1])  # the last message's record: its length field is 26 bytes before
    data[at - 26 : at - 22] = b"\xff\xff\xff\x7f"
    mcap.write_bytes(bytes(data))
    # at the recorded pace (160 kB every 10 ms); the replay is lossless (Zenoh's BLOCK congestion control),
    # so a busy machine delays frames but drops none (with DROP it once lost one at 20x, and once at 1x
    # beside three benchmarks)
    res, arrived, _ = replay_into_subscriber(
        a, b, path, ReplayOptions(rate=1.0, restamp=True), lambda: StampGate()
    )
    n = res.published.get("/uav/camera/nadir", 0)
    assert res.bad == {READ_ERROR: 1}
    assert 0 < n < len(payloads)
    assert [f.image.tobytes() for _, f in arrived] == [pattern(k, 400).tobytes() for k in range(n)]


def test_fast_replay_delivers_every_frame(sessions, tmp_path) -> None:
    """Replayed 50x faster than recorded (160 kB frames 0.2 ms apart, far beyond what the link takes at
    that pace), every frame still arrives, in order: a bench replay is lossless unless asked otherwise."""
    a, b = sessions
    t0 = now_us() - 10_000_000
    path = tmp_path / "bag"
    n = 40
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection("/uav/camera/nadir", IMAGE_MSGTYPE, typestore=TS)
        for k in range(n):
            w.write(conn, (t0 + k * 10_000) * 1000, encode_image(pattern(k, 400), t0 + k * 10_000))
    res, arrived, _ = replay_into_subscriber(
        a, b, path, ReplayOptions(rate=50.0, restamp=True), lambda: StampGate()
    )
    assert res.published == {"/uav/camera/nadir": n} and res.bad == {}
    assert [f.image.tobytes() for _, f in arrived] == [pattern(k, 400).tobytes() for k in range(n)]


def test_cli_record_then_replay(endpoint, tmp_path, capsys) -> None:
    """``python -m sim_bridge record`` and ``replay`` through the CLI entry point (in-process)."""
    pub_session = open_session("peer", listen=[endpoint], multicast_scouting=False)
    pub = FramePublisher(pub_session, KEY)
    stop = threading.Event()

    def publish() -> None:
        k = 0
        while not stop.is_set():
            pub.put(pattern(k), now_us())
            k += 1
            time.sleep(0.05)

    th = threading.Thread(target=publish, daemon=True)
    th.start()
    bag = tmp_path / "cli_bag"
    try:
        rc = cli.main(
            [
                "record",
                "--out",
                str(bag),
                "--key",
                "uav/camera/*",
                "--duration",
                "1.0",
                "--zenoh-connect",
                endpoint,
            ]
        )
    finally:
        stop.set()
        th.join()
        pub.close()
        pub_session.close()
    assert rc == 0
    out = capsys.readouterr().out
    recorded = json.loads(out.strip().splitlines()[-1])["recorded"]
    n = recorded["topics"]["/uav/camera/nadir"]["messages"]
    assert n >= 5 and recorded["topics"]["/uav/camera/nadir"]["rate_hz"] == pytest.approx(20, rel=0.5)

    sub_session = open_session("peer", connect=[endpoint], multicast_scouting=False)
    got: list[Any] = []
    sub = FrameSubscriber(sub_session, {"nadir": KEY}, sink=got.append)
    try:
        rc = cli.main(["replay", str(bag), "--restamp", "--rate", "4", "--zenoh-listen", endpoint])
        wait_for(lambda: len(got) >= n, 3.0)
    finally:
        sub.close()
        sub_session.close()
    assert rc == 0
    replayed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["replayed"]
    assert replayed["published"] == {"/uav/camera/nadir": n} and replayed["bad"] == {}
    assert len(got) == n
    assert cli.main(["replay", str(tmp_path / "missing_bag"), "--zenoh-listen", endpoint]) == 2
    assert cli.main(["record", "--out", str(bag), "--duration", "0.1", "--zenoh-connect", endpoint]) == 2


def test_a_killed_recorder_leaves_a_bag_that_recover_makes_readable(endpoint, tmp_path, capsys) -> None:
    """``record`` in its own process, SIGKILLed mid-flight (power cut): no metadata.yaml, no MCAP footer.
    ``replay`` refuses the bag and says what to do; ``recover`` copies every frame of the closed chunks,
    byte for byte and in order, into a bag that replays."""
    import signal
    import subprocess
    import sys

    pub_session = open_session("peer", listen=[endpoint], multicast_scouting=False)
    pub = FramePublisher(pub_session, KEY)
    bag = tmp_path / "flight"
    rec = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "sim_bridge",
            "record",
            "--out",
            str(bag),
            "--key",
            KEY,
            "--zenoh-connect",
            endpoint,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert rec.stdout is not None and "recording" in rec.stdout.readline()
        wait_matching(pub_session, KEY)
        n = 16  # 400 x 400 mono frames, 160 kB each: two 1 MiB chunks are closed, the third is in memory
        sent = []
        for k in range(n):
            stamp = now_us()
            pub.put(pattern(k, 400), stamp)
            sent.append(encode_image(pattern(k, 400), stamp))
            time.sleep(0.02)
        mcap = bag / f"{bag.name}.mcap"
        assert wait_for(lambda: mcap.exists() and mcap.stat().st_size > 2 * 2**20, 10.0)
        time.sleep(0.5)  # the writer thread takes the rest of the queue
    finally:
        rec.send_signal(signal.SIGKILL)
        rec.wait(10)
        pub.close()
        pub_session.close()
    assert not (bag / "metadata.yaml").exists()

    assert cli.main(["replay", str(bag), "--wait-subscribers", "0", "--zenoh-listen", endpoint]) == 2
    assert f"python -m sim_bridge recover {bag}" in capsys.readouterr().out

    assert cli.main(["recover", str(bag)]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["recovered"]
    out = Path(res["out"])
    assert out == tmp_path / "flight-recovered"
    got = res["messages"]["/uav/camera/nadir"]
    assert 7 <= got < n, res  # at least the first closed chunk; never the one in memory
    assert len(res["stopped"]) == 1 and "flight.mcap" in res["stopped"][0]
    with Reader(out) as reader:
        assert [c.msgtype for c in reader.connections] == [IMAGE_MSGTYPE]
        raw = [bytes(r) for _, _, r in reader.messages()]
    assert raw == sent[:got]
    # the recovered bag replays; recovering again into the same place is refused
    assert (
        cli.main(["replay", str(out), "--rate", "50", "--wait-subscribers", "0", "--zenoh-listen", endpoint])
        == 0
    )
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["replayed"]["published"] == {
        "/uav/camera/nadir": got
    }
    assert cli.main(["recover", str(bag)]) == 2


def test_recover_keeps_a_type_of_the_recordings_own_and_reads_sqlite(tmp_path) -> None:
    """A custom message type is rebuilt from the definition the MCAP carries; a sqlite3 bag that lost its
    metadata.yaml is copied whole; nothing to read is a clear error."""
    import subprocess
    import sys

    from rosbags.typesys import get_types_from_msg

    from sim_bridge.recording import recover_bag

    # a writer killed after one closed chunk of a custom type (os._exit: no close, no footer)
    code = f"""
import os
from rosbags.rosbag2 import Writer, StoragePlugin
from rosbags.typesys import Stores, get_typestore, get_types_from_msg
ts = get_typestore(Stores.ROS2_HUMBLE)
ts.register(get_types_from_msg("uint32 value", "probe_msgs/msg/Quality"))
ts.register(get_types_from_msg("std_msgs/Header header\\nfloat64 range_m\\nprobe_msgs/Quality quality", "probe_msgs/msg/Range"))
Range, Quality = ts.types["probe_msgs/msg/Range"], ts.types["probe_msgs/msg/Quality"]
H, T = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
w = Writer({str(tmp_path / "custom")!r}, version=8, storage_plugin=StoragePlugin.MCAP)
w.open()
c = w.add_connection("/probe/range", "probe_msgs/msg/Range", typestore=ts)
for i in range(60000):
    w.write(c, 10**18 + i, bytes(ts.serialize_cdr(Range(header=H(stamp=T(sec=i, nanosec=0), frame_id="alt"), range_m=i * 0.5, quality=Quality(value=i % 7)), "probe_msgs/msg/Range")))
os._exit(0)
"""
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
    res = recover_bag(tmp_path / "custom")
    n = res.messages["/probe/range"]
    assert 0 < n < 60000 and res.skipped_topics == {}
    with Reader(res.out) as reader:
        msgs = list(reader.messages())
        conn = reader.connections[0]
        assert conn.msgtype == "probe_msgs/msg/Range"
    store = get_typestore(Stores.ROS2_HUMBLE)  # a reader that knows the types from the bag alone
    found = get_types_from_msg(conn.msgdef.data, conn.msgtype)
    store.register({k: v for k, v in found.items() if k not in store.types})
    last: Any = store.deserialize_cdr(bytes(msgs[-1][2]), conn.msgtype)
    assert len(msgs) == n and msgs[-1][1] == 10**18 + n - 1
    assert (
        last.range_m == (n - 1) * 0.5 and last.quality.value == (n - 1) % 7 and last.header.stamp.sec == n - 1
    )

    # sqlite3, closed properly, then its metadata.yaml lost
    with Writer(tmp_path / "db", version=8, storage_plugin=StoragePlugin.SQLITE3) as w:
        conn = w.add_connection("/uav/camera/nadir", IMAGE_MSGTYPE, typestore=TS)
        for k in range(5):
            w.write(conn, 1000 + k, encode_image(pattern(k), 1000 + k))
    (tmp_path / "db" / "metadata.yaml").unlink()
    res = recover_bag(tmp_path / "db", tmp_path / "db-fixed")
    assert res.messages == {"/uav/camera/nadir": 5} and res.stopped == []
    with Reader(tmp_path / "db-fixed") as reader:
        assert [bytes(r) for _, _, r in reader.messages()] == [
            encode_image(pattern(k), 1000 + k) for k in range(5)
        ]

    with pytest.raises(FileNotFoundError, match="no such bag"):
        recover_bag(tmp_path / "db-fixed-not-there")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no .mcap or .db3"):
        recover_bag(tmp_path / "empty")
