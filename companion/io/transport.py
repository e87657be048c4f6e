"""Byte transports for MAVLink: UDP (client / server), TCP (client / server), serial (pyserial).

Each transport moves bytes only and reconnects by itself: ``read`` (called from one I/O thread)
opens or re-opens the link with exponential backoff when it is down, ``write`` (any thread) sends
or drops-and-counts. Nothing raises out of ``read`` / ``write``; failures land in ``stats``.

Connection strings (ArduPilot / MAVProxy style):

- ``udpout:HOST:PORT``  send to HOST:PORT, take replies from anyone (a GCS-style client).
- ``udpin:HOST:PORT``   listen on HOST:PORT, answer the last sender (like ArduPilot's udpin).
- ``tcp:HOST:PORT``     connect to a TCP server (e.g. ArduPilot SITL on 5760).
- ``tcpin:HOST:PORT``   accept one TCP client at a time (the simulated autopilot's side).
- ``serial:DEVICE[:BAUD]``  a serial port; BAUD defaults to the ``baudrate`` argument.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import select
import socket
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import serial

log = logging.getLogger(__name__)


@dataclass
class TransportStats:
    """Counters of one transport (read by the daemon's status line)."""

    connected: bool = False
    connects: int = 0
    """Successful opens, the first one included."""
    reconnects: int = 0
    """Successful opens after a drop (connects - 1 when it ever dropped)."""
    drops: int = 0
    """Times an open link was lost (peer closed, device unplugged, I/O error)."""
    open_failures: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    writes_dropped: int = 0
    """Writes refused because the link was down or had no peer yet."""
    last_error: str = ""
    errors: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Backoff:
    """Reconnect delays: first ``min_s``, doubled per failure up to ``max_s``."""

    min_s: float = 0.05
    max_s: float = 2.0


class Transport(ABC):
    """Bytes in / out with automatic reconnection. ``read`` from one thread; ``write`` from any."""

    def __init__(self, description: str, backoff: Backoff | None = None) -> None:
        self.description = description
        self.backoff = backoff or Backoff()
        self.stats = TransportStats()
        self._lock = threading.Lock()
        self._next_attempt = 0.0
        self._delay = self.backoff.min_s
        self._ever_dropped = False
        self._closed = False

    # --- subclass hooks (called with self._lock held only for _write_raw) -------------------------
    @abstractmethod
    def _open(self) -> None:
        """Open the link; raise OSError / serial.SerialException on failure."""

    @abstractmethod
    def _close_handle(self) -> None:
        """Release the link's handle (idempotent)."""

    @abstractmethod
    def _read_raw(self, timeout_s: float) -> bytes:
        """Read what is available within timeout (b"" if nothing). Raise OSError when the link died."""

    @abstractmethod
    def _write_raw(self, data: bytes) -> bool:
        """Send data; return False when there is no peer to send to. Raise OSError when the link died."""

    @abstractmethod
    def _is_open(self) -> bool: ...

    # --- public API -----------------------------------------------------------------------------
    def read(self, timeout_s: float = 0.05) -> bytes:
        """Bytes received within ``timeout_s`` (b"" when none or while reconnecting). Never raises."""
        if self._closed:
            time.sleep(timeout_s)
            return b""
        if not self._is_open() and not self._try_open():
            time.sleep(min(timeout_s, max(0.0, self._next_attempt - time.monotonic())))
            return b""
        try:
            data = self._read_raw(timeout_s)
        except (OSError, serial.SerialException, ValueError, TypeError) as exc:
            self._drop(exc)
            return b""
        self.stats.bytes_in += len(data)
        return data

    def write(self, data: bytes) -> bool:
        """Send ``data``; False (and counted) when the link is down or has no peer. Never raises."""
        with self._lock:
            if self._closed or not self._is_open():
                self.stats.writes_dropped += 1
                return False
            try:
                ok = self._write_raw(data)
            except (OSError, serial.SerialException, ValueError, TypeError) as exc:
                self._count_error(exc)
                ok = False
                if self._fatal(exc):
                    self._drop_locked(exc)
        if ok:
            self.stats.bytes_out += len(data)
        else:
            self.stats.writes_dropped += 1
        return ok

    def close(self) -> None:
        """Close for good (no more reconnects)."""
        with self._lock:
            self._closed = True
            self._close_handle()
            self.stats.connected = False

    # --- internals ------------------------------------------------------------------------------
    def _fatal(self, exc: BaseException) -> bool:
        """Whether a write error means the link is gone (stream transports) or was transient (UDP)."""
        return True

    def _count_error(self, exc: BaseException) -> None:
        key = type(exc).__name__
        self.stats.errors[key] = self.stats.errors.get(key, 0) + 1
        self.stats.last_error = f"{key}: {exc}"

    def _try_open(self) -> bool:
        now = time.monotonic()
        if now < self._next_attempt:
            return False
        try:
            with self._lock:
                self._open()
        except (OSError, serial.SerialException, ValueError) as exc:
            self.stats.open_failures += 1
            self._count_error(exc)
            self._next_attempt = now + self._delay
            self._delay = min(self._delay * 2.0, self.backoff.max_s)
            with self._lock:
                self._close_handle()
            return False
        self._delay = self.backoff.min_s
        self.stats.connects += 1
        if self._ever_dropped:
            self.stats.reconnects += 1
            log.info("%s: reconnected (%d)", self.description, self.stats.reconnects)
        self.stats.connected = True
        return True

    def _drop(self, exc: BaseException) -> None:
        with self._lock:
            self._drop_locked(exc)

    def _drop_locked(self, exc: BaseException) -> None:
        if not self._is_open():
            return
        self._count_error(exc)
        log.warning("%s: link lost (%s)", self.description, exc)
        self._close_handle()
        self.stats.connected = False
        self.stats.drops += 1
        self._ever_dropped = True
        self._next_attempt = time.monotonic() + self._delay


class UdpTransport(Transport):
    """UDP. Client (``udpout``): sends to a fixed address. Server (``udpin``): binds, answers last sender."""

    def __init__(self, host: str, port: int, server: bool, backoff: Backoff | None = None) -> None:
        super().__init__(f"{'udpin' if server else 'udpout'}:{host}:{port}", backoff)
        self.address = (host, int(port))
        self.server = server
        self.peer: tuple[str, int] | None = None if server else self.address
        self._sock: socket.socket | None = None

    @property
    def local_address(self) -> tuple[str, int] | None:
        """The bound (host, port), e.g. to learn an ephemeral port; None while closed."""
        sock = self._sock
        return None if sock is None else sock.getsockname()

    def _open(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            if self.server:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind(self.address)
            else:
                sock.bind(("0.0.0.0", 0))
        except OSError:
            sock.close()
            raise
        self._sock = sock

    def _close_handle(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _is_open(self) -> bool:
        return self._sock is not None

    def _fatal(self, exc: BaseException) -> bool:
        # ICMP port-unreachable (peer not up yet) and friends are transient for a datagram socket.
        return False

    def _read_raw(self, timeout_s: float) -> bytes:
        sock = self._sock
        if sock is None:
            return b""
        ready, _, _ = select.select([sock], [], [], timeout_s)
        if not ready:
            return b""
        try:
            data, addr = sock.recvfrom(65535)
        except ConnectionRefusedError:
            return b""  # an earlier send hit a closed port: not a failure of ours
        if self.server:
            self.peer = addr
        return data

    def _write_raw(self, data: bytes) -> bool:
        if self._sock is None or self.peer is None:
            return False
        self._sock.sendto(data, self.peer)
        return True


class TcpClientTransport(Transport):
    """TCP client (``tcp:HOST:PORT``); reconnects when the server closes or is not there yet."""

    def __init__(self, host: str, port: int, backoff: Backoff | None = None, connect_timeout_s: float = 1.0):
        super().__init__(f"tcp:{host}:{port}", backoff)
        self.address = (host, int(port))
        self.connect_timeout_s = connect_timeout_s
        self._sock: socket.socket | None = None

    def _open(self) -> None:
        sock = socket.create_connection(self.address, timeout=self.connect_timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(None)
        self._sock = sock

    def _close_handle(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.shutdown(socket.SHUT_RDWR)
            self._sock.close()
            self._sock = None

    def _is_open(self) -> bool:
        return self._sock is not None

    def _read_raw(self, timeout_s: float) -> bytes:
        sock = self._sock
        if sock is None:
            return b""
        ready, _, _ = select.select([sock], [], [], timeout_s)
        if not ready:
            return b""
        data = sock.recv(65535)
        if not data:
            raise ConnectionResetError(errno.ECONNRESET, "peer closed the connection")
        return data

    def _write_raw(self, data: bytes) -> bool:
        if self._sock is None:
            return False
        self._sock.sendall(data)
        return True


class TcpServerTransport(Transport):
    """TCP server (``tcpin:HOST:PORT``) serving one client at a time; a new client replaces the old."""

    def __init__(self, host: str, port: int, backoff: Backoff | None = None) -> None:
        super().__init__(f"tcpin:{host}:{port}", backoff)
        self.address = (host, int(port))
        self._listener: socket.socket | None = None
        self._client: socket.socket | None = None

    @property
    def local_address(self) -> tuple[str, int] | None:
        """The listening (host, port); None while closed."""
        sock = self._listener
        return None if sock is None else sock.getsockname()

    def _open(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(self.address)
            sock.listen(1)
        except OSError:
            sock.close()
            raise
        self._listener = sock

    def _close_handle(self) -> None:
        self._close_client()
        if self._listener is not None:
            self._listener.close()
            self._listener = None

    def _close_client(self) -> None:
        if self._client is not None:
            with contextlib.suppress(OSError):
                self._client.shutdown(socket.SHUT_RDWR)
            self._client.close()
            self._client = None

    def _is_open(self) -> bool:
        return self._listener is not None

    def _try_open(self) -> bool:
        # The listener opening is not a client connection: stats count clients.
        connects, reconnects = self.stats.connects, self.stats.reconnects
        opened = super()._try_open()
        self.stats.connects, self.stats.reconnects = connects, reconnects
        self.stats.connected = self._client is not None
        return opened

    def _fatal(self, exc: BaseException) -> bool:
        self._close_client()  # the client went away; keep listening
        return False

    def _read_raw(self, timeout_s: float) -> bytes:
        listener = self._listener
        if listener is None:
            return b""
        watch = [listener] if self._client is None else [listener, self._client]
        ready, _, _ = select.select(watch, [], [], timeout_s)
        if listener in ready:
            accepted, _ = listener.accept()
            accepted.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            with self._lock:
                if self._client is not None:
                    self.stats.drops += 1
                self._close_client()
                self._client = accepted
                self.stats.connects += 1
                self.stats.reconnects = max(0, self.stats.connects - 1)
                self.stats.connected = True
            return b""
        client = self._client
        if client is None or client not in ready:
            return b""
        try:
            data = client.recv(65535)
        except OSError:
            data = b""
        if not data:
            with self._lock:
                self._close_client()
                self.stats.drops += 1
                self.stats.connected = False
        return data

    def _write_raw(self, data: bytes) -> bool:
        if self._client is None:
            return False
        self._client.sendall(data)
        return True


class SerialTransport(Transport):
    """Serial port through pyserial (``serial:DEVICE:BAUD``); re-opens the device after an unplug."""

    def __init__(self, device: str, baudrate: int, backoff: Backoff | None = None) -> None:
        super().__init__(f"serial:{device}:{baudrate}", backoff)
        self.device = device
        self.baudrate = int(baudrate)
        self._port: serial.Serial | None = None

    def _open(self) -> None:
        # exclusive=True: a second process on the same port is an error, not silent byte stealing.
        self._port = serial.Serial(self.device, self.baudrate, timeout=0, write_timeout=1.0, exclusive=True)

    def _close_handle(self) -> None:
        if self._port is not None:
            with contextlib.suppress(OSError, serial.SerialException):
                self._port.close()
            self._port = None

    def _is_open(self) -> bool:
        return self._port is not None

    def _fatal(self, exc: BaseException) -> bool:
        # A write timeout (receiver not draining, flow control) is not an unplug.
        return not isinstance(exc, serial.SerialTimeoutException)

    def _read_raw(self, timeout_s: float) -> bytes:
        port = self._port
        if port is None:
            return b""
        ready, _, _ = select.select([port.fileno()], [], [], timeout_s)
        if not ready:
            return b""
        # Read the fd directly: after an unplug (or a closed pty master) it reports EIO, or EOF.
        data = os.read(port.fileno(), 65535)
        if not data:
            raise OSError(errno.EIO, "serial device returned EOF (unplugged?)")
        return data

    def _write_raw(self, data: bytes) -> bool:
        if self._port is None:
            return False
        self._port.write(data)
        return True


def open_transport(connection: str, baudrate: int = 921_600, backoff: Backoff | None = None) -> Transport:
    """Build a transport from a connection string (see the module docstring). Raises ValueError if bad."""
    kind, _, rest = connection.partition(":")
    kind = kind.strip().lower()
    if kind in ("udpout", "udp", "udpin", "tcp", "tcpin"):
        host, sep, port_text = rest.rpartition(":")
        if not sep or not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
            raise ValueError(f"connection {connection!r}: expected {kind}:HOST:PORT")
        port = int(port_text)
        if kind == "udpin":
            return UdpTransport(host, port, server=True, backoff=backoff)
        if kind in ("udpout", "udp"):
            return UdpTransport(host, port, server=False, backoff=backoff)
        if kind == "tcp":
            return TcpClientTransport(host, port, backoff=backoff)
        return TcpServerTransport(host, port, backoff=backoff)
    if kind == "serial":
        device, sep, baud_text = rest.rpartition(":")
        if sep and baud_text.isdigit() and device:
            return SerialTransport(device, int(baud_text), backoff=backoff)
        if not rest:
            raise ValueError(f"connection {connection!r}: expected serial:DEVICE[:BAUD]")
        return SerialTransport(rest, baudrate, backoff=backoff)
    raise ValueError(
        f"connection {connection!r}: unknown kind {kind!r} (expected udpin, udpout, tcp, tcpin or serial)"
    )
