"""The daemon's record of its inputs (``daemon.record_inputs``): every frame set the estimator took and every
autopilot sample that reached its inbox, in one rosbag2 (MCAP) that ``companion replay`` runs the estimator
over again on a bench, giving the estimates the daemon made.

A vehicle that runs the companion without ROS has no other record of what its estimator saw: the frames
come over Zenoh and the IMU, attitude, range and local position over MAVLink. Here they are written as ROS
messages, all in the companion's clock. Header stamps are what the estimator was given (the frames' capture
times, the samples' stamps mapped from the autopilot's clock); log times are when: a sample's arrival in the
inbox, a frame's hand-over to the estimator (after the inbox was drained for it). Replayed in log-time order,
each frame set meets the samples the daemon had fed before it. Frames the daemon skipped (the estimator
busy) are not in the record:

- each camera's frames on its topic (the configured key with a leading ``/``), as decoded (mono8 / mono16):
  ``sensor_msgs/msg/CompressedImage`` in lossless PNG (``frames="png"``, the default) or
  ``sensor_msgs/msg/Image`` (``frames="raw"``). A camera's sensor noise leaves little to compress: PNG
  keeps 64 % of the bytes of the Europa pair and 68 % of the demo's camera, for 11 ms (640 x 480, the pair's
  mean) and 6 ms (480 x 480, 8-bit) of the writer thread's CPU per frame: 4 % of a core for the pair at 2 Hz,
  9 % for the demo's camera at 15 Hz (``python -m bench recorder``, bench/results/recorder.json); a camera
  that sent JPEG is stored lossless, larger;
- ``/companion/imu``: ``sensor_msgs/msg/Imu``, FRD (``base_link_frd``), no orientation (covariance -1);
- ``/companion/attitude``: ``geometry_msgs/msg/QuaternionStamped``, the FRD body in NED (``map_ned``);
- ``/companion/range``: ``sensor_msgs/msg/Range`` (NaN, no return, as +inf);
- ``/companion/local_position``: ``nav_msgs/msg/Odometry`` with the twist in the world frame
  (``child_frame_id`` = ``map_ned``; the autopilot's LOCAL_POSITION_NED has no attitude);
- ``/companion/config``: ``std_msgs/msg/String``, once at the start: the daemon's whole configuration as
  JSON (overrides included), which ``companion replay`` uses when given no ``--config``.

The daemon's threads only enqueue (a bounded queue: when the disk falls behind, samples are dropped and
counted, never waited for); one writer thread encodes and writes. A write that fails is counted and logged
once. Close it to write the bag's metadata; a bag whose daemon was killed is rebuilt with
``python -m sim_bridge recover``.
"""

from __future__ import annotations

import logging
import os
import queue
import shutil
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.errors import WriterError

from companion.geometry import rot_from_rpy
from companion.io import ros_msgs
from companion.io.frames import COMPRESSED_MSGTYPE, IMAGE_MSGTYPE, encode_compressed, encode_image
from companion.types import AltimeterSample, AttitudeSample, Frame, ImuSample, LocalPositionSample

log = logging.getLogger(__name__)

IMU_TOPIC = "/companion/imu"
ATTITUDE_TOPIC = "/companion/attitude"
RANGE_TOPIC = "/companion/range"
LOCAL_POSITION_TOPIC = "/companion/local_position"
CONFIG_TOPIC = "/companion/config"

Item = Frame | ImuSample | AttitudeSample | AltimeterSample | LocalPositionSample

FRAME_FORMATS = ("png", "raw")
PNG_LEVEL = 1
"""zlib level of the recorded PNGs: level 3 (OpenCV's default) or 6 saves 1-4 % more bytes of a noisy frame
for 1.3-4.3x the time (measured on the Europa pair)."""
WRITER_NICE = 10
"""Niceness added to the writer thread (Linux: a thread is a task with its own nice value): its encoding
takes the CPU the estimator and the links leave. Measured with it (``python -m bench latency
--record-inputs``): recording adds 1-2 ms to the median capture-to-send latency, PNG up to 2.5 ms more."""


def inputs_path(template: str, start_time_s: float | None = None) -> Path:
    """The bag directory of ``template``: ``{time}`` becomes the local start time (YYYYmmdd-HHMMSS)."""
    return Path(template.replace("{time}", time.strftime("%Y%m%d-%H%M%S", time.localtime(start_time_s))))


class InputRecorder:
    """Records frames and samples into a new bag at ``inputs_path(template)``. Raises OSError at construction
    when it cannot be created (an existing path, a read-only disk): at start, not in flight.

    camera_topics: camera name -> ROS topic of its frames. config_json: the daemon's configuration, written
    once on ``CONFIG_TOPIC`` ("" = not written). frames: "png" (lossless CompressedImage) or "raw" (Image).
    min_free_mb: when the disk has less free space than this, the
    record is closed (readable, metadata written) and the rest of the flight is not recorded: a full card
    must not take the companion's own files or the bag with it (``stopped`` says why).
    """

    def __init__(
        self,
        template: str,
        camera_topics: dict[str, str],
        queue_size: int = 2048,
        config_json: str = "",
        min_free_mb: float = 500.0,
        frames: str = "png",
    ) -> None:
        if frames not in FRAME_FORMATS:
            raise ValueError(f"inputs record: frames {frames!r}, expected one of {FRAME_FORMATS}")
        self.frames = frames
        self.path = inputs_path(template)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._writer = Writer(
                self.path, version=ros_msgs.ROSBAG_VERSION, storage_plugin=StoragePlugin.MCAP
            )
            self._writer.open()
        except WriterError as exc:  # the path exists: refuse to mix two flights
            raise OSError(f"inputs record {self.path}: {exc}") from exc
        ts = ros_msgs.TYPESTORE
        self._conns: dict[str, Any] = {
            cam: self._writer.add_connection(
                topic, COMPRESSED_MSGTYPE if frames == "png" else IMAGE_MSGTYPE, typestore=ts
            )
            for cam, topic in camera_topics.items()
        }
        for key, topic, msgtype in (
            ("imu", IMU_TOPIC, ros_msgs.IMU_MSGTYPE),
            ("attitude", ATTITUDE_TOPIC, ros_msgs.QUATERNION_MSGTYPE),
            ("range", RANGE_TOPIC, ros_msgs.RANGE_MSGTYPE),
            ("local_position", LOCAL_POSITION_TOPIC, ros_msgs.ODOMETRY_MSGTYPE),
        ):
            self._conns[key] = self._writer.add_connection(topic, msgtype, typestore=ts)
        if config_json:
            conn = self._writer.add_connection(CONFIG_TOPIC, ros_msgs.STRING_MSGTYPE, typestore=ts)
            self._writer.write(conn, time.time_ns(), ros_msgs.string_cdr(config_json))
        self._queue: queue.Queue[tuple[Item, int] | None] = queue.Queue(maxsize=queue_size)
        self._lock = threading.Lock()
        self.messages: dict[str, int] = {}
        self.bytes = 0
        self.dropped = 0
        self.errors = 0
        self.stopped = ""
        self.min_free_bytes = int(min_free_mb * 1e6)
        self._next_space_check = 0
        self._closed = False
        self._writer_closed = False
        self._thread = threading.Thread(target=self._write_loop, name="input-recorder", daemon=True)
        self._thread.start()

    # -- any thread ---------------------------------------------------------------------------------------
    def put(self, item: Item, log_us: int) -> None:
        """Enqueue a frame or a sample with its log time (us, companion clock); never blocks (a full queue
        drops it and counts it)."""
        if (isinstance(item, Frame) and item.camera not in self._conns) or self.stopped:
            return
        try:
            self._queue.put_nowait((item, int(log_us)))
        except queue.Full:
            with self._lock:
                self.dropped += 1

    def status(self) -> dict[str, Any]:
        with self._lock:
            return {
                "path": str(self.path),
                "messages": dict(self.messages),
                "mbytes": round(self.bytes / 1e6, 1),
                "dropped": self.dropped,
                "errors": self.errors,
                "stopped": self.stopped,
            }

    def close(self) -> None:
        """Write what is queued, then the bag's metadata. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:  # a writer stuck on a stalled disk: give it 30 s, then close what was written
            self._queue.put(None, timeout=30.0)
        except queue.Full:
            log.error("inputs record %s: the writer did not drain its queue in 30 s", self.path)
        self._thread.join(timeout=30.0)
        self._close_writer()

    def _close_writer(self) -> None:
        with self._lock:
            if self._writer_closed:
                return
            self._writer_closed = True
        try:
            self._writer.close()
        except (WriterError, OSError) as exc:
            log.error("inputs record %s: cannot close: %s", self.path, exc)

    def _disk_low(self) -> bool:
        """Every ~16 MB written: is the disk below ``min_free_bytes``?"""
        if self.bytes < self._next_space_check:
            return False
        self._next_space_check = self.bytes + 16_000_000
        try:
            free = shutil.disk_usage(self.path).free
        except OSError:
            return False
        return free < self.min_free_bytes

    # -- the writer thread -------------------------------------------------------------------------------
    def _encode(self, item: Item) -> tuple[str, bytes]:
        if isinstance(item, Frame):
            frame_id = f"{item.camera}_camera"
            if self.frames == "png":
                return item.camera, encode_compressed(
                    item.image, item.stamp_us, frame_id, png_level=PNG_LEVEL
                )
            return item.camera, encode_image(item.image, item.stamp_us, frame_id=frame_id)
        if isinstance(item, ImuSample):
            return "imu", ros_msgs.imu_cdr(item.stamp_us, item.accel_mps2, item.gyro_rps, None, True)
        if isinstance(item, AttitudeSample):
            R = rot_from_rpy(item.roll_rad, item.pitch_rad, item.yaw_rad)
            return "attitude", ros_msgs.quaternion_cdr(item.stamp_us, R)
        if isinstance(item, AltimeterSample):
            return "range", ros_msgs.range_cdr(item.stamp_us, item.range_m, 0.0, 0.0, True)
        return "local_position", ros_msgs.odometry_world_twist_cdr(
            item.stamp_us, np.asarray(item.p_ned_m, float), np.asarray(item.v_ned_mps, float)
        )

    def _write_loop(self) -> None:
        try:  # this thread only; best effort (other systems, a sandbox without setpriority)
            os.setpriority(
                os.PRIO_PROCESS, threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0) + WRITER_NICE
            )
        except (AttributeError, OSError) as exc:
            log.debug("inputs record: writer thread left at the daemon's priority (%s)", exc)
        while True:
            got = self._queue.get()
            if got is None:
                return
            item, log_us = got
            if self.stopped:
                continue
            if self._disk_low():
                # closed first, then said: whoever sees ``stopped`` finds the bag readable
                self._close_writer()
                why = f"disk below {self.min_free_bytes / 1e6:.0f} MB free"
                with self._lock:
                    self.stopped = why
                log.error(
                    "inputs record %s: %s: record closed, the flight goes on unrecorded", self.path, why
                )
                continue
            try:
                key, payload = self._encode(item)
                self._writer.write(self._conns[key], log_us * 1000, payload)
            except (WriterError, OSError, ValueError) as exc:  # disk full, a sample that cannot be encoded
                with self._lock:
                    self.errors += 1
                    first = self.errors == 1
                if first:
                    log.error("inputs record %s: %s (counting further failures)", self.path, exc)
                continue
            with self._lock:
                self.messages[key] = self.messages.get(key, 0) + 1
                self.bytes += len(payload)
