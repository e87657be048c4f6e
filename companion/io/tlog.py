"""The autopilot link's traffic as a MAVLink telemetry log (``.tlog``), both directions.

A ``.tlog`` is the format ground stations and MAVProxy write and pymavlink's tools read
(``mavlogdump.py``, ``mavgraph.py``, MAVExplorer, Mission Planner): each message's wire bytes, signature
included, preceded by its arrival (or sending) time as a big-endian unsigned 64-bit count of microseconds
since the Unix epoch. pymavlink reads such files (``mavutil.mavlink_connection("x.tlog")``) but writes only
the raw bytes (its writers leave the timestamp to the caller, as MAVProxy does), so the 8-byte header is
written here.

The file is buffered and flushed by the link about once a second: a power cut loses at most the last second.
A write that fails (disk full, card pulled) is counted and logged once; the link goes on without the log.
"""

from __future__ import annotations

import contextlib
import logging
import struct
import threading
import time
from pathlib import Path
from typing import Any, BinaryIO

log = logging.getLogger(__name__)

_HEADER = struct.Struct(">Q")


def tlog_path(template: str, start_time_s: float | None = None) -> Path:
    """The log's path: ``{time}`` in ``template`` becomes the local start time (YYYYmmdd-HHMMSS), and
    ``.tlog`` is appended unless the name ends with it (pymavlink picks its reader by that suffix)."""
    stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(start_time_s))
    p = Path(template.replace("{time}", stamp))
    return p if p.suffix == ".tlog" else p.with_name(p.name + ".tlog")


class TlogWriter:
    """Appends timestamped messages to ``tlog_path(template)``; thread-safe (the link's I/O thread writes
    what it receives, any thread what it sends). Raises OSError at construction when the file cannot be
    created: a wrong path fails at start, not in flight."""

    def __init__(self, template: str) -> None:
        self.path = tlog_path(template)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: BinaryIO | None = open(self.path, "ab")  # noqa: SIM115 - open for the link's life
        self._lock = threading.Lock()
        self.messages = 0
        """Messages written (both directions)."""
        self.bytes = 0
        self.errors = 0
        """Writes or flushes that failed; after the first the log is closed and nothing more is written."""

    def write(self, msgbuf: bytes) -> None:
        """One message's wire bytes, stamped with the wall clock now (the format's readers expect Unix time),
        read under the writer's lock so that the log is in time order whichever thread writes."""
        with self._lock:
            if self._f is None:
                return
            try:
                self._f.write(_HEADER.pack(time.time_ns() // 1000) + msgbuf)
            except OSError as exc:
                self._fail(exc)
                return
            self.messages += 1
            self.bytes += _HEADER.size + len(msgbuf)

    def flush(self) -> None:
        with self._lock:
            if self._f is None:
                return
            try:
                self._f.flush()
            except OSError as exc:
                self._fail(exc)

    def close(self) -> None:
        self.flush()
        with self._lock:
            if self._f is not None:
                try:
                    self._f.close()
                except OSError as exc:  # the buffer's last bytes could not be written
                    self._fail(exc)
                self._f = None

    def _fail(self, exc: OSError) -> None:
        # called with the lock held
        self.errors += 1
        if self.errors == 1:
            log.error("MAVLink log %s: %s; no more of the link's traffic is logged", self.path, exc)
        f, self._f = self._f, None
        if f is not None:
            with contextlib.suppress(OSError):  # already failed and reported; its buffer is lost either way
                f.close()

    def status(self) -> dict[str, Any]:
        return {"path": str(self.path), "messages": self.messages, "bytes": self.bytes, "errors": self.errors}
