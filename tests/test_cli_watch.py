"""``companion watch``: an operator's view of a running daemon's status over Zenoh (real sessions on loopback,
the command as its own process)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from typing import Any

from netutil import free_tcp_port

from companion.daemon import format_status_line
from companion.io.zenoh_io import StatusPublisher, open_session

STATUS = {
    "fps_in": 15.0,
    "fps_out": 14.9,
    "latency_p50_ms": 37.6,
    "latency_p99_ms": 52.1,
    "frames_dropped_stale": 2,
    "frames": {"decode_errors": {"nadir:truncated": 1}},
    "not_sent": {"no_estimate": 3, "too_old": 4},
    "quality": 0.29,
    "estimate_status": "ok",
    "sigma_h_m": 0.4243,
    "link": {
        "state": "up",
        "timesync": True,
        "params_check": {"worst": "error", "problems": {"VISO_TYPE": "error: 0"}},
    },
}


def watch(port: int, *args: str) -> subprocess.CompletedProcess:
    """``companion watch`` as its own process, connected to a companion's Zenoh endpoint on ``port``."""
    cmd = [sys.executable, "-m", "companion", "watch", "--connect", f"tcp/127.0.0.1:{port}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60)


def test_status_line_names_what_an_operator_needs() -> None:
    line = format_status_line(STATUS)
    for part in ("in  15.0 fps", "drop 2", "bad 1 (nadir:truncated 1)", "unsent 4", "est ok sigma 0.42 m"):
        assert part in line, (part, line)
    assert "link up" in line
    # no estimate yet (or one without a covariance): no sigma shown
    for none in (None, float("nan")):
        assert "sigma" not in format_status_line({**STATUS, "sigma_h_m": none})
    assert line.endswith("AUTOPILOT PARAMS ERROR: VISO_TYPE")
    blind = format_status_line({**STATUS, "estimator": {"warnings": {"imu": "NO IMU for 2.0 s"}}})
    assert blind == line + "  NO IMU for 2.0 s"
    # the link's MAVLink log: silent while it works, named when the disk refused it
    link: dict[str, Any] = dict(STATUS["link"])  # type: ignore[call-overload]
    tlog = {"path": "x.tlog", "messages": 10, "bytes": 400}
    assert format_status_line({**STATUS, "link": {**link, "tlog": {**tlog, "errors": 0}}}) == line
    failed = format_status_line({**STATUS, "link": {**link, "tlog": {**tlog, "errors": 1}}})
    assert failed == line + "  TLOG STOPPED"


def test_watch_prints_the_status_lines_of_a_publishing_companion() -> None:
    port = free_tcp_port()
    session = open_session("peer", [], [f"tcp/127.0.0.1:{port}"], False)
    pub = StatusPublisher(session)
    stop = threading.Event()

    def publish() -> None:  # the daemon's status thread: one message a short while
        while not stop.is_set():
            pub.publish(STATUS)
            session.put("companion/status", b"not json")  # a bad message is skipped, not fatal
            time.sleep(0.2)

    threading.Thread(target=publish, daemon=True).start()
    try:
        out = watch(port, "--count", "2")
    finally:
        stop.set()
        pub.close()
        session.close()
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert lines == [format_status_line(STATUS)] * 2


def test_watch_says_when_nothing_arrives() -> None:
    port = free_tcp_port()
    session = open_session("peer", [], [f"tcp/127.0.0.1:{port}"], False)  # a companion that publishes nothing
    try:
        t0 = time.monotonic()
        out = watch(port, "--timeout", "1.5")
    finally:
        session.close()
    assert out.returncode == 1 and out.stdout == ""
    assert "no status on 'companion/status' within 1.5 s" in out.stderr
    assert time.monotonic() - t0 < 30
