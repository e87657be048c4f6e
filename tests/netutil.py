"""Helpers the socket-level tests share: free loopback ports and polling for a condition."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable
from typing import Any


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    """A port on 127.0.0.1 the OS reports free right now (UDP by default)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    return free_port(socket.SOCK_STREAM)


def wait_for(cond: Callable[[], Any], timeout_s: float = 5.0, poll_s: float = 0.005) -> bool:
    """Poll ``cond`` until it is truthy or ``timeout_s`` passes; its last value, as a bool."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(poll_s)
    return bool(cond())
