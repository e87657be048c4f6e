"""Frame codec: CDR Image / CompressedImage round trips, every kind of bad input, timestamp gate."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from companion.io import frames
from companion.io.frames import (
    FrameError,
    StampGate,
    decode_compressed,
    decode_frame,
    decode_image,
    encode_compressed,
    encode_image,
)

TS = get_typestore(Stores.ROS2_HUMBLE)
STAMP_US = 1_700_000_123_456_789


def raw_image_cdr(
    height: int,
    width: int,
    encoding: str,
    step: int,
    data: np.ndarray,
    big: int = 0,
    stamp_us: int = STAMP_US,
) -> bytes:
    """Build an Image straight with rosbags (independent of our encoder)."""
    img_t = TS.types["sensor_msgs/msg/Image"]
    header = TS.types["std_msgs/msg/Header"](
        stamp=TS.types["builtin_interfaces/msg/Time"](
            sec=stamp_us // 1_000_000, nanosec=stamp_us % 1_000_000 * 1000
        ),
        frame_id="cam",
    )
    msg = img_t(
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=big,
        step=step,
        data=np.asarray(data, dtype=np.uint8).reshape(-1),
    )
    return bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/Image"))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


def test_mono8_round_trip_keeps_pixels_and_stamp(rng: np.random.Generator) -> None:
    img = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    data = encode_image(img, STAMP_US, "nadir_optical")
    assert data[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation, as the ROS 2 bridge carries
    frame = decode_image(data, "nadir", seq=5)
    assert frame.stamp_us == STAMP_US and frame.camera == "nadir" and frame.seq == 5
    assert frame.image.dtype == np.uint8 and frame.image.shape == (48, 64)
    np.testing.assert_array_equal(frame.image, img)


def test_mono16_round_trip_and_big_endian(rng: np.random.Generator) -> None:
    img = rng.integers(0, 65536, (20, 30), dtype=np.uint16)
    frame = decode_image(encode_image(img, STAMP_US), "thermal")
    assert frame.image.dtype == np.uint16
    np.testing.assert_array_equal(frame.image, img)
    big = raw_image_cdr(20, 30, "mono16", 60, img.astype(">u2").view(np.uint8), big=1)
    np.testing.assert_array_equal(decode_image(big, "thermal").image, img)


@pytest.mark.parametrize(
    ("encoding", "channels", "code"),
    [
        ("rgb8", 3, cv2.COLOR_RGB2GRAY),
        ("bgr8", 3, cv2.COLOR_BGR2GRAY),
        ("rgba8", 4, cv2.COLOR_RGBA2GRAY),
        ("bgra8", 4, cv2.COLOR_BGRA2GRAY),
    ],
)
def test_colour_is_converted_to_mono(
    rng: np.random.Generator, encoding: str, channels: int, code: int
) -> None:
    img = rng.integers(0, 256, (16, 24, channels), dtype=np.uint8)
    frame = decode_image(encode_image(img, STAMP_US, encoding=encoding), "visible")
    assert frame.image.shape == (16, 24) and frame.image.dtype == np.uint8
    np.testing.assert_array_equal(frame.image, cv2.cvtColor(img, code))


def test_padded_rows_are_cropped(rng: np.random.Generator) -> None:
    img = rng.integers(0, 256, (10, 13), dtype=np.uint8)
    padded = np.zeros((10, 16), dtype=np.uint8)
    padded[:, :13] = img
    padded[:, 13:] = 255  # padding bytes must not leak into the image
    frame = decode_image(raw_image_cdr(10, 13, "mono8", 16, padded), "nadir")
    np.testing.assert_array_equal(frame.image, img)


def test_compressed_png_is_lossless_for_8_and_16_bit(rng: np.random.Generator) -> None:
    img8 = rng.integers(0, 256, (32, 40), dtype=np.uint8)
    img16 = rng.integers(0, 65536, (32, 40), dtype=np.uint16)
    np.testing.assert_array_equal(decode_compressed(encode_compressed(img8, STAMP_US), "a").image, img8)
    f16 = decode_frame(encode_compressed(img16, STAMP_US), "t", compressed=True)
    assert f16.image.dtype == np.uint16 and f16.stamp_us == STAMP_US
    np.testing.assert_array_equal(f16.image, img16)


def test_compressed_jpeg_colour_decodes_to_close_mono() -> None:
    yy, xx = np.mgrid[0:64, 0:64]
    bgr = np.dstack([xx * 4, yy * 4, (xx + yy) * 2]).astype(np.uint8)
    frame = decode_compressed(encode_compressed(bgr, STAMP_US, fmt="jpeg", jpeg_quality=95), "v")
    expected = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(int)
    assert frame.image.shape == (64, 64)
    assert np.abs(frame.image.astype(int) - expected).mean() < 3.0


def test_every_truncation_is_refused_as_truncated(rng: np.random.Generator) -> None:
    data = encode_image(rng.integers(0, 256, (8, 8), dtype=np.uint8), STAMP_US, "cam")
    for cut in range(0, len(data)):
        with pytest.raises(FrameError) as info:
            decode_image(data[:cut], "nadir")
        assert info.value.reason == (frames.EMPTY if cut == 0 else frames.TRUNCATED), cut


@pytest.mark.parametrize(
    ("height", "width", "encoding", "step", "nbytes"),
    [
        (10, 10, "mono8", 10, 99),  # data shorter than step * height
        (10, 10, "mono8", 10, 101),  # longer
        (10, 10, "mono8", 8, 80),  # step < width * 1
        (10, 10, "mono16", 10, 100),  # step < width * 2
        (10, 10, "rgb8", 20, 200),  # step < width * 3
    ],
)
def test_size_mismatch(height: int, width: int, encoding: str, step: int, nbytes: int) -> None:
    data = raw_image_cdr(height, width, encoding, step, np.zeros(nbytes, dtype=np.uint8))
    with pytest.raises(FrameError) as info:
        decode_image(data, "nadir")
    assert info.value.reason == frames.SIZE_MISMATCH


@pytest.mark.parametrize("encoding", ["yuv422", "bayer_rggb8", "32FC1", ""])
def test_unknown_encoding(encoding: str) -> None:
    data = raw_image_cdr(4, 4, encoding, 4, np.zeros(16, dtype=np.uint8))
    with pytest.raises(FrameError) as info:
        decode_image(data, "nadir")
    assert info.value.reason == frames.UNKNOWN_ENCODING


def test_zero_size_and_empty_payload() -> None:
    for data in (b"", raw_image_cdr(0, 0, "mono8", 0, np.zeros(0, dtype=np.uint8))):
        with pytest.raises(FrameError) as info:
            decode_image(data, "nadir")
        assert info.value.reason == frames.EMPTY


def test_not_cdr_and_bad_compressed() -> None:
    with pytest.raises(FrameError) as info:
        decode_image(b"\x89PNG\r\n\x1a\n" + bytes(100), "nadir")
    assert info.value.reason == frames.BAD_CDR
    msg = TS.types["sensor_msgs/msg/CompressedImage"](
        header=TS.types["std_msgs/msg/Header"](
            stamp=TS.types["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id=""
        ),
        format="png",
        data=np.frombuffer(b"definitely not a png", dtype=np.uint8),
    )
    with pytest.raises(FrameError) as info:
        decode_compressed(bytes(TS.serialize_cdr(msg, "sensor_msgs/msg/CompressedImage")), "nadir")
    assert info.value.reason == frames.BAD_IMAGE


@settings(max_examples=300, deadline=None)
@given(payload=st.binary(max_size=400), cdr_prefix=st.booleans(), compressed=st.booleans())
def test_random_bytes_only_ever_raise_frame_error(payload: bytes, cdr_prefix: bool, compressed: bool) -> None:
    data = (b"\x00\x01\x00\x00" + payload) if cdr_prefix else payload
    try:
        frame = decode_frame(data, "nadir", compressed=compressed)
    except FrameError as exc:
        assert exc.reason in frames.FRAME_ERROR_REASONS
    else:  # rare but legal: the bytes happened to form a valid small image
        assert frame.image.ndim == 2 and frame.image.size > 0


def test_stamp_gate_reasons_and_recovery() -> None:
    gate = StampGate(max_future_us=50_000, max_age_us=1_000_000)
    now = STAMP_US
    assert gate.check(now - 10_000, now) is None
    assert gate.check(now - 10_000, now) == frames.STAMP_BACKWARDS  # duplicate
    assert gate.check(now - 20_000, now) == frames.STAMP_BACKWARDS  # reordered
    assert gate.check(now + 60_000, now) == frames.STAMP_FUTURE
    assert gate.check(now - 2_000_000, now) == frames.STAMP_STALE
    assert gate.check(0, now) == frames.STAMP_MISSING
    assert gate.check(now + 40_000, now) is None  # small skew is allowed
    assert gate.check(now + 80_000, now + 50_000) is None  # refusals did not poison the gate
    gate.reset()
    assert gate.check(now, now) is None
