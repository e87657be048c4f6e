"""Camera frame codec: ROS 2 ``sensor_msgs/msg/Image`` / ``CompressedImage`` as CDR bytes <-> ``Frame``.

Pure (bytes in, dataclasses out): no sockets, no clock. The bytes are exactly what
zenoh-bridge-ros2dds carries: CDR with its 4-byte encapsulation header. The CDR work is done by
``rosbags``' type store (a maintained implementation), never by hand.

Colour frames are converted to mono at decode (the estimators work on one channel); mono16
(thermal cameras) stays uint16.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any, Final

import cv2
import numpy as np
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from companion.types import Frame

_TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
_Image = _TYPESTORE.types["sensor_msgs/msg/Image"]
_CompressedImage = _TYPESTORE.types["sensor_msgs/msg/CompressedImage"]
_Header = _TYPESTORE.types["std_msgs/msg/Header"]
_Time = _TYPESTORE.types["builtin_interfaces/msg/Time"]

IMAGE_MSGTYPE: Final = "sensor_msgs/msg/Image"
"""ROS 2 type name of a raw image."""
COMPRESSED_MSGTYPE: Final = "sensor_msgs/msg/CompressedImage"
"""ROS 2 type name of a compressed (png/jpeg) image."""

# FrameError reasons: the label a counter is kept under.
EMPTY: Final = "empty"
"""No bytes, or an image with zero width/height/data."""
TRUNCATED: Final = "truncated"
"""The CDR stream ends before the message does."""
BAD_CDR: Final = "bad_cdr"
"""Not CDR (bad encapsulation header) or a field that cannot be decoded."""
SIZE_MISMATCH: Final = "size_mismatch"
"""len(data) != step * height, or step < width * bytes_per_pixel."""
UNKNOWN_ENCODING: Final = "unknown_encoding"
"""An encoding (or compressed format) this codec does not handle."""
BAD_IMAGE: Final = "bad_image"
"""Compressed payload that OpenCV cannot decode."""
FRAME_ERROR_REASONS: Final = (EMPTY, TRUNCATED, BAD_CDR, SIZE_MISMATCH, UNKNOWN_ENCODING, BAD_IMAGE)

# StampGate reasons.
STAMP_MISSING: Final = "stamp_missing"
"""Header stamp is zero: the driver did not stamp the frame."""
STAMP_BACKWARDS: Final = "stamp_backwards"
"""Stamp not after the last accepted one from the same camera (reordered or duplicated)."""
STAMP_FUTURE: Final = "stamp_future"
"""Stamp further in the future than the allowed clock skew."""
STAMP_STALE: Final = "stamp_stale"
"""Stamp older than the allowed age on arrival."""

# encoding -> (channels, numpy dtype, cv2 conversion to mono or None)
_RAW_ENCODINGS: Final[dict[str, tuple[int, type, int | None]]] = {
    "mono8": (1, np.uint8, None),
    "8uc1": (1, np.uint8, None),
    "mono16": (1, np.uint16, None),
    "16uc1": (1, np.uint16, None),
    "rgb8": (3, np.uint8, cv2.COLOR_RGB2GRAY),
    "bgr8": (3, np.uint8, cv2.COLOR_BGR2GRAY),
    "rgba8": (4, np.uint8, cv2.COLOR_RGBA2GRAY),
    "bgra8": (4, np.uint8, cv2.COLOR_BGRA2GRAY),
}
_CDR_HEADERS: Final = (b"\x00\x00", b"\x00\x01")  # CDR big / little endian (first 2 of the 4 bytes)
_SEQ_LEN_RE: Final = re.compile(r"(?:sequence|string) length (\d+) at offset (\d+)")


class FrameError(ValueError):
    """A frame that cannot be used. ``reason`` is one of FRAME_ERROR_REASONS (for counters)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(f"{reason}: {message}")
        self.reason = reason
        self.message = message


def _stamp_us(header: object) -> int:
    stamp = header.stamp  # type: ignore[attr-defined]
    return int(stamp.sec) * 1_000_000 + int(stamp.nanosec) // 1000


def _header(stamp_us: int, frame_id: str) -> Any:
    sec, usec = divmod(int(stamp_us), 1_000_000)
    return _Header(stamp=_Time(sec=int(sec), nanosec=int(usec) * 1000), frame_id=frame_id)


def _deserialize(data: bytes, msgtype: str) -> object:
    """CDR bytes -> rosbags message, mapping every failure to a FrameError."""
    if len(data) == 0:
        raise FrameError(EMPTY, "zero-length payload")
    if len(data) < 4:
        raise FrameError(TRUNCATED, f"{len(data)} bytes, shorter than the CDR encapsulation header")
    if bytes(data[:2]) not in _CDR_HEADERS:
        raise FrameError(BAD_CDR, f"no CDR encapsulation header (first bytes {bytes(data[:4]).hex()})")
    try:
        return _TYPESTORE.deserialize_cdr(data, msgtype)
    except SerdeError as exc:
        text = str(exc)
        match = _SEQ_LEN_RE.search(text)
        runs_out = "requires a buffer" in text or "out of range" in text
        if match is not None:
            length, offset = int(match.group(1)), int(match.group(2))
            # A plausible sequence / string that just does not fit: the message was cut short. The
            # offset rosbags reports is that of the 4-byte length field, counted from the end of the
            # 4-byte encapsulation header.
            runs_out = length < (1 << 28) and 4 + offset + 4 + length > len(data)
        reason = TRUNCATED if runs_out else BAD_CDR
        raise FrameError(reason, f"{msgtype} ({len(data)} bytes): {text}") from exc
    except (ValueError, IndexError, UnicodeDecodeError, OverflowError, MemoryError) as exc:
        raise FrameError(BAD_CDR, f"{msgtype} ({len(data)} bytes): {exc}") from exc


def decode_image(data: bytes, camera: str, seq: int = 0) -> Frame:
    """CDR ``sensor_msgs/msg/Image`` -> Frame (mono uint8 or uint16, stamp from header.stamp).

    Raises FrameError on any bad input (never another exception type).
    """
    msg = _deserialize(data, IMAGE_MSGTYPE)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)  # type: ignore[attr-defined]
    encoding = str(msg.encoding).lower()  # type: ignore[attr-defined]
    raw = np.asarray(msg.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if height == 0 or width == 0 or raw.size == 0:
        raise FrameError(EMPTY, f"image {width}x{height} with {raw.size} data bytes")
    if encoding not in _RAW_ENCODINGS:
        raise FrameError(UNKNOWN_ENCODING, f"encoding {msg.encoding!r}")  # type: ignore[attr-defined]
    channels, dtype, conversion = _RAW_ENCODINGS[encoding]
    bytes_pp = channels * np.dtype(dtype).itemsize
    if step < width * bytes_pp:
        raise FrameError(SIZE_MISMATCH, f"step {step} < width {width} * {bytes_pp} bytes/pixel")
    if raw.size != step * height:
        raise FrameError(SIZE_MISMATCH, f"data {raw.size} bytes != step {step} * height {height}")
    rows = raw.reshape(height, step)[:, : width * bytes_pp]
    if dtype is np.uint16:
        big = bool(msg.is_bigendian)  # type: ignore[attr-defined]
        pixels = np.ascontiguousarray(rows).view(">u2" if big else "<u2").astype(np.uint16)
    else:
        pixels = np.ascontiguousarray(rows)
    image: np.ndarray = (
        pixels.reshape(height, width, channels) if channels > 1 else pixels.reshape(height, width)
    )
    if conversion is not None:
        image = cv2.cvtColor(image, conversion)
    return Frame(stamp_us=_stamp_us(msg.header), camera=camera, image=image, seq=seq)  # type: ignore[attr-defined]


def decode_compressed(data: bytes, camera: str, seq: int = 0) -> Frame:
    """CDR ``sensor_msgs/msg/CompressedImage`` (png / jpeg) -> Frame (mono, uint8 or uint16)."""
    msg = _deserialize(data, COMPRESSED_MSGTYPE)
    fmt = str(msg.format).lower()  # type: ignore[attr-defined]
    if "png" not in fmt and "jpeg" not in fmt and "jpg" not in fmt:
        raise FrameError(UNKNOWN_ENCODING, f"compressed format {msg.format!r}")  # type: ignore[attr-defined]
    raw = np.asarray(msg.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if raw.size == 0:
        raise FrameError(EMPTY, "compressed image with no data")
    image = cv2.imdecode(raw, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_GRAYSCALE)
    if image is None or image.size == 0:
        raise FrameError(BAD_IMAGE, f"OpenCV could not decode {raw.size} bytes as {fmt}")
    return Frame(stamp_us=_stamp_us(msg.header), camera=camera, image=image, seq=seq)  # type: ignore[attr-defined]


def decode_frame(data: bytes, camera: str, compressed: bool = False, seq: int = 0) -> Frame:
    """Decode either message type; ``compressed`` selects CompressedImage."""
    if compressed:
        return decode_compressed(data, camera, seq)
    return decode_image(data, camera, seq)


def encode_image(image: np.ndarray, stamp_us: int, frame_id: str = "camera", encoding: str = "") -> bytes:
    """Image -> CDR ``sensor_msgs/msg/Image`` bytes (little endian, tight rows).

    image: (H, W) uint8 / uint16 or (H, W, 3|4) uint8. ``encoding`` defaults from the array:
    mono8, mono16, bgr8, bgra8. Used by the simulator, the replayer and the tests.
    """
    image = np.ascontiguousarray(image)
    if not encoding:
        if image.ndim == 2:
            encoding = "mono16" if image.dtype == np.uint16 else "mono8"
        else:
            encoding = "bgra8" if image.shape[2] == 4 else "bgr8"
    key = encoding.lower()
    if key not in _RAW_ENCODINGS:
        raise FrameError(UNKNOWN_ENCODING, f"cannot encode {encoding!r}")
    channels, dtype, _ = _RAW_ENCODINGS[key]
    if image.dtype != dtype or (image.shape[2] if image.ndim == 3 else 1) != channels:
        raise FrameError(SIZE_MISMATCH, f"{encoding} needs {channels} x {np.dtype(dtype)}, got {image.shape}")
    height, width = image.shape[:2]
    data = image.astype(np.dtype(dtype).newbyteorder("<"), copy=False).view(np.uint8).reshape(-1)
    msg = _Image(
        header=_header(stamp_us, frame_id),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * channels * np.dtype(dtype).itemsize,
        data=data,
    )
    return bytes(_TYPESTORE.serialize_cdr(msg, IMAGE_MSGTYPE))


def encode_compressed(
    image: np.ndarray,
    stamp_us: int,
    frame_id: str = "camera",
    fmt: str = "png",
    jpeg_quality: int = 90,
    png_level: int = 3,
) -> bytes:
    """Image -> CDR ``sensor_msgs/msg/CompressedImage`` bytes; fmt ``png`` (lossless, 8/16 bit; zlib level
    ``png_level`` 0-9, OpenCV's default 3) or ``jpeg``."""
    ext = {"png": ".png", "jpeg": ".jpg", "jpg": ".jpg"}.get(fmt.lower())
    if ext is None:
        raise FrameError(UNKNOWN_ENCODING, f"cannot compress as {fmt!r}")
    if ext == ".jpg":
        params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)]
    else:
        params = [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)]
    ok, buf = cv2.imencode(ext, image, params)
    if not ok:
        raise FrameError(BAD_IMAGE, f"OpenCV could not encode {image.shape} {image.dtype} as {fmt}")
    msg = _CompressedImage(header=_header(stamp_us, frame_id), format=fmt.lower(), data=buf.reshape(-1))
    return bytes(_TYPESTORE.serialize_cdr(msg, COMPRESSED_MSGTYPE))


@dataclass
class StampGate:
    """Per-camera timestamp sanity check. Pure: the caller passes ``now_us`` (companion clock).

    max_future_us: a stamp later than now + this is refused (clock skew allowance).
    max_age_us: a stamp older than now - this is refused; None disables the check.
    A stamp not strictly after the last accepted one is refused (reordered / duplicate).
    """

    max_future_us: int = 50_000
    max_age_us: int | None = 2_000_000
    last_stamp_us: int | None = None

    def check(self, stamp_us: int, now_us: int) -> str | None:
        """Return a STAMP_* reason to refuse the frame, or None (and remember the stamp)."""
        if stamp_us <= 0:
            return STAMP_MISSING
        if stamp_us > now_us + self.max_future_us:
            return STAMP_FUTURE
        if self.max_age_us is not None and stamp_us < now_us - self.max_age_us:
            return STAMP_STALE
        if self.last_stamp_us is not None and stamp_us <= self.last_stamp_us:
            return STAMP_BACKWARDS
        self.last_stamp_us = stamp_us
        return None

    def reset(self) -> None:
        """Forget the last stamp (e.g. after the camera driver restarted)."""
        self.last_stamp_us = None
