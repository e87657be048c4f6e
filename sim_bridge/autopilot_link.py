"""The MAVLink side of the simulated ArduPilot-like copter.

Sends telemetry built from a truth provider (with noise and biases), answers TIMESYNC with its own
boot clock, holds an EKF origin, and receives VISION_POSITION_ESTIMATE / ODOMETRY, checking each
the way ArduPilot would before recording it. Runs over any transport string of
companion.io.transport (``udpin`` answering the sender, ``tcpin``, ``serial`` on a pty...).

Clocks: ``clock_us`` is the simulation's world clock (the same one the simulated camera stamps
frames with, Unix-epoch microseconds by default); the truth provider is called with it. The
autopilot's boot clock (``boot_us``) starts at ``clock_offset_us`` when the object is created (as
if it had booted that long ago) and at 0 after ``reboot()``; it can drift by ``drift_ppm``.

ArduPilot behaviour reproduced (checked against GCS_Common.cpp / AP_NavEKF3 as documented):
- ODOMETRY is ignored unless frame_id == MAV_FRAME_LOCAL_FRD and child_frame_id == MAV_FRAME_BODY_FRD.
- EKF3 drops external-nav samples closer than its minimum interval (20 ms, i.e. above ~50 Hz).
- Samples must be finite; their time (autopilot clock) must increase, not lie in the future, and
  not be older than the EKF's fusion horizon (~500 ms).
- Parameters: PARAM_REQUEST_READ by name (or index) is answered with PARAM_VALUE (every type sent as a
  float, as ArduPilot does); an unknown name gets no answer. VISO_TYPE 0 drops every external-nav
  sample (counted as "viso_disabled"); EK3_SRC1_POSXY other than 6 (ExternalNav) accepts them but does
  not use them for position, which the simulation does not model beyond reporting the value.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Final

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from companion.constants import PLANET_RADIUS_M
from companion.io.mavlink import MavCodec, rpy_from_quaternion, wall_clock_us
from companion.io.transport import Backoff, Transport, open_transport

log = logging.getLogger(__name__)

TruthFn = Callable[[int], dict[str, Any]]
"""truth(t_us) -> {"rpy_rad": (3,), "p_ned_m": (3,), "v_ned_mps": (3,), "range_m": float,
"accel_body_mps2": (3,) specific force FRD, "gyro_body_rps": (3,)}; t_us in the world clock."""

# Rejection reasons (counter keys).
REJECT_NON_FINITE: Final = "non_finite"
REJECT_BAD_FRAME: Final = "bad_frame"
REJECT_FUTURE: Final = "future"
REJECT_TOO_OLD: Final = "too_old"
REJECT_NOT_MONOTONIC: Final = "not_monotonic"
REJECT_TOO_FAST: Final = "too_fast"
REJECT_VISO_DISABLED: Final = "viso_disabled"

DEFAULT_PARAMS: Final[dict[str, tuple[float, int]]] = {
    # name: (value, MAV_PARAM_TYPE) -- a copter set up for external navigation as deploy/ardupilot.parm,
    # except the camera offset: the simulated camera sits at the body origin
    "AHRS_EKF_TYPE": (3.0, mavlink2.MAV_PARAM_TYPE_INT8),
    "VISO_TYPE": (3.0, mavlink2.MAV_PARAM_TYPE_INT8),
    "EK3_SRC1_POSXY": (6.0, mavlink2.MAV_PARAM_TYPE_INT8),
    "EK3_SRC1_VELXY": (0.0, mavlink2.MAV_PARAM_TYPE_INT8),
    "EK3_SRC1_POSZ": (1.0, mavlink2.MAV_PARAM_TYPE_INT8),
    "EK3_SRC1_YAW": (1.0, mavlink2.MAV_PARAM_TYPE_INT8),
    "EK3_SRC2_POSXY": (0.0, mavlink2.MAV_PARAM_TYPE_INT8),
    "EK3_SRC3_POSXY": (0.0, mavlink2.MAV_PARAM_TYPE_INT8),
    "VISO_POS_X": (0.0, mavlink2.MAV_PARAM_TYPE_REAL32),
    "VISO_POS_Y": (0.0, mavlink2.MAV_PARAM_TYPE_REAL32),
    "VISO_POS_Z": (0.0, mavlink2.MAV_PARAM_TYPE_REAL32),
    "VISO_DELAY_MS": (20.0, mavlink2.MAV_PARAM_TYPE_INT16),
}
"""The simulated autopilot's parameters (``SimAutopilotOptions.params`` overrides values by name)."""


def hover_truth(alt_agl_m: float = 30.0, yaw_rad: float = 0.0) -> TruthFn:
    """A truth provider for a vehicle hovering still over flat ground (for tests and demos)."""

    def truth(_t_us: int) -> dict[str, Any]:
        return {
            "rpy_rad": np.array([0.0, 0.0, yaw_rad]),
            "p_ned_m": np.array([0.0, 0.0, -alt_agl_m]),
            "v_ned_mps": np.zeros(3),
            "range_m": alt_agl_m,
            "accel_body_mps2": np.array([0.0, 0.0, -9.80665]),
            "gyro_body_rps": np.zeros(3),
        }

    return truth


@dataclass(frozen=True)
class SimNoise:
    """Noise (1-sigma, white per sample) and biases (1-sigma, drawn once per boot) of the telemetry.

    Figures: attitude like a converged EKF3 (~0.2 deg roll/pitch, ~0.3 deg yaw jitter, ~1 deg yaw
    bias from the compass); IMU like an ICM-42688 at 50 Hz output; range finder like a small lidar
    (2 cm + 1 %); local position / velocity like a GPS-less EKF holding still.
    """

    roll_pitch_rad: float = 0.003
    yaw_rad: float = 0.005
    yaw_bias_rad: float = 0.02
    yaw_offset_rad: float = 0.0  # a compass this far off on top of the drawn bias (``--compass-offset``)
    position_m: float = 0.05
    velocity_mps: float = 0.03
    accel_mps2: float = 0.05
    accel_bias_mps2: float = 0.05
    gyro_rps: float = 0.005
    gyro_bias_rps: float = 0.003
    range_m: float = 0.02
    range_frac: float = 0.01


@dataclass(frozen=True)
class SimAutopilotOptions:
    """Rates (Hz, 0 = off), ranges and the ArduPilot-like acceptance limits."""

    heartbeat_hz: float = 1.0
    system_time_hz: float = 2.0
    attitude_hz: float = 50.0
    local_position_hz: float = 10.0
    global_position_hz: float = 10.0
    distance_sensor_hz: float = 20.0
    highres_imu_hz: float = 50.0
    scaled_imu_hz: float = 0.0
    """SCALED_IMU (mG, mrad/s), as ArduPilot sends when asked; off by default."""
    raw_imu_hz: float = 0.0
    """RAW_IMU, what ArduPilot's default sensor stream (SRn_RAW_SENS) sends for its first IMU: SCALED_IMU's
    units, stamped in microseconds since boot; off by default (``--imu-message raw``)."""
    origin_hz: float = 0.2
    """GPS_GLOBAL_ORIGIN repeat rate once an origin is set (also sent right after it is set)."""
    timesync_request_hz: float = 0.2
    """ArduPilot also asks its peers for TIMESYNC; replies are counted in ``timesync_replies``."""
    range_min_m: float = 0.2
    range_max_m: float = 40.0
    planet: str = "earth"
    origin: tuple[float, float, float] | None = None
    """(lat_deg, lon_deg, alt_m) at boot; None = no origin until SET_GPS_GLOBAL_ORIGIN (as without GPS)."""
    ext_nav_min_interval_us: int = 20_000
    """EKF3 drops external-nav samples closer than this (its ~50 Hz limit)."""
    ext_nav_max_age_us: int = 500_000
    ext_nav_max_future_us: int = 20_000
    noise: SimNoise = field(default_factory=SimNoise)
    params: tuple[tuple[str, float], ...] = ()
    """(name, value) overriding ``DEFAULT_PARAMS`` (a new name is added as a float parameter)."""
    signing_key: bytes | None = None
    accept_unsigned: bool = False
    baudrate: int = 921_600
    read_timeout_s: float = 0.002
    backoff: Backoff = field(default_factory=Backoff)


IMU_MESSAGES: tuple[str, ...] = ("highres", "raw", "scaled", "none")
"""The IMU message the simulated autopilot streams: PX4's HIGHRES_IMU, ArduPilot's default RAW_IMU,
SCALED_IMU, or none (an autopilot whose sensor stream is off until a peer asks for it)."""
INTERVAL_STREAMS: Final = {
    mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU: "highres_imu",
    mavlink2.MAVLINK_MSG_ID_RAW_IMU: "raw_imu",
    mavlink2.MAVLINK_MSG_ID_SCALED_IMU: "scaled_imu",
}
"""Messages whose rate MAV_CMD_SET_MESSAGE_INTERVAL sets on the simulated autopilot (message id -> stream)."""


def with_imu_message(options: SimAutopilotOptions, message: str, hz: float = 50.0) -> SimAutopilotOptions:
    """``options`` streaming the IMU as ``message`` (one of ``IMU_MESSAGES``) only, at ``hz``."""
    if message not in IMU_MESSAGES:
        raise ValueError(f"unknown IMU message {message!r} ({', '.join(IMU_MESSAGES)})")
    return replace(
        options,
        highres_imu_hz=hz if message == "highres" else 0.0,
        raw_imu_hz=hz if message == "raw" else 0.0,
        scaled_imu_hz=hz if message == "scaled" else 0.0,
    )


@dataclass(frozen=True)
class VisionRecord:
    """An accepted external-nav sample. covariance: the 21-element upper triangle as received."""

    kind: str
    """"vpe" (VISION_POSITION_ESTIMATE) or "odometry"."""
    usec: int
    p_ned_m: np.ndarray
    rpy_rad: np.ndarray
    covariance: tuple[float, ...]
    reset_counter: int
    recv_boot_us: int
    """The autopilot boot clock when it arrived."""
    src_compid: int


class SimAutopilotLink:
    """Simulated autopilot MAVLink endpoint. ``start()`` / ``run()`` (blocking) / ``stop()``."""

    def __init__(
        self,
        transport_string: str,
        sysid: int = 1,
        compid: int = 1,
        clock_offset_us: int = 7_000_000,
        rng: np.random.Generator | None = None,
        truth: TruthFn | None = None,
        options: SimAutopilotOptions | None = None,
        clock_us: Callable[[], int] = wall_clock_us,
        drift_ppm: float = 0.0,
        transport: Transport | None = None,
    ) -> None:
        self.options = opts = options or SimAutopilotOptions()
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.truth = truth or hover_truth()
        self.clock_us = clock_us
        self.drift_ppm = float(drift_ppm)
        self.transport = transport or open_transport(transport_string, opts.baudrate, opts.backoff)
        self.codec = MavCodec(sysid, compid, opts.signing_key, 0, opts.accept_unsigned)
        self.sysid, self.compid = sysid, compid
        self._lock = threading.Lock()
        self.rate_overrides: dict[str, float] = {}
        """Stream rates (Hz) set by peers with MAV_CMD_SET_MESSAGE_INTERVAL, over ``options``' (``INTERVAL_STREAMS``)."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._boot_wall_us = clock_us()
        self._boot_offset_us = int(clock_offset_us)
        self.origin: tuple[float, float, float] | None = opts.origin
        self.records: list[VisionRecord] = []
        """Accepted external-nav samples in arrival order (read under ``lock`` or via ``accepted()``)."""
        self.rejections: dict[str, int] = {}
        self.heartbeats_from: dict[tuple[int, int], int] = {}
        """HEARTBEATs received by (sysid, compid)."""
        self.received: dict[str, int] = {}
        self.sent: dict[str, int] = {}
        self.timesync_replies = 0
        self.reboots = 0
        self._silent_until = 0.0
        self.thread_errors = 0
        self._last_ext_usec: int | None = None
        self._next_due: dict[str, float] = {}
        self.params: dict[str, tuple[float, int]] = dict(DEFAULT_PARAMS)
        for name, value in opts.params:
            kind = self.params.get(name, (0.0, mavlink2.MAV_PARAM_TYPE_REAL32))[1]
            self.params[name] = (float(value), kind)
        self._draw_biases()

    # --- clocks ---------------------------------------------------------------------------------
    def boot_us(self) -> int:
        """The autopilot's clock: microseconds since (simulated) boot."""
        elapsed = self.clock_us() - self._boot_wall_us
        return int(elapsed * (1.0 + self.drift_ppm * 1e-6)) + self._boot_offset_us

    def true_offset_us(self) -> int:
        """autopilot_clock - world clock right now (what TIMESYNC should find)."""
        now = self.clock_us()
        elapsed = now - self._boot_wall_us
        return int(elapsed * (1.0 + self.drift_ppm * 1e-6)) + self._boot_offset_us - now

    def reboot(self, boot_silence_s: float = 0.0) -> None:
        """Restart the boot clock at 0 and forget volatile state (origin, ext-nav history, biases).
        boot_silence_s: the autopilot then says nothing and hears nothing for this long (booting)."""
        self._silent_until = time.monotonic() + boot_silence_s
        with self._lock:
            self._boot_wall_us = self.clock_us()
            self._boot_offset_us = 0
            self.origin = self.options.origin
            self._last_ext_usec = None
            self.reboots += 1
            self._draw_biases()
            self._next_due.clear()

    def _draw_biases(self) -> None:
        n = self.options.noise
        self._yaw_bias = float(self.rng.normal(0.0, n.yaw_bias_rad)) + n.yaw_offset_rad
        self._accel_bias = self.rng.normal(0.0, n.accel_bias_mps2, 3)
        self._gyro_bias = self.rng.normal(0.0, n.gyro_bias_rps, 3)

    # --- results --------------------------------------------------------------------------------
    @property
    def lock(self) -> threading.Lock:
        """Guards ``records`` / counters against the I/O thread."""
        return self._lock

    def accepted(self) -> list[VisionRecord]:
        """A copy of the accepted external-nav samples."""
        with self._lock:
            return list(self.records)

    def rejected(self) -> dict[str, int]:
        """A copy of the rejection counters by reason."""
        with self._lock:
            return dict(self.rejections)

    # --- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        """Run in a background thread."""
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, name="sim-autopilot", daemon=True)
        self._thread.start()

    def run(self) -> None:
        """Serve until ``stop()``: read, answer, record, send telemetry on schedule. Never raises."""
        while not self._stop.is_set():
            try:
                self._tick()
            except Exception:  # noqa: BLE001 - the simulated autopilot must keep running; counted
                self.thread_errors += 1
                log.exception("sim autopilot: error in I/O loop")
                time.sleep(self.options.read_timeout_s)

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the loop and close the transport."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self.transport.close()

    # --- loop -----------------------------------------------------------------------------------
    def _tick(self) -> None:
        data = self.transport.read(self.options.read_timeout_s)
        if time.monotonic() < self._silent_until:
            return  # booting: deaf and mute
        if data:
            for msg in self.codec.decode(data):
                self._handle(msg)
        self._send_due()

    def _send(self, msg: Any) -> None:
        if self.transport.write(self.codec.encode(msg)):
            name = msg.get_type()
            self.sent[name] = self.sent.get(name, 0) + 1

    def _due(self, name: str, hz: float, mono: float) -> bool:
        if hz <= 0.0:
            return False
        due = self._next_due.get(name, 0.0)
        if mono < due:
            return False
        period = 1.0 / hz
        self._next_due[name] = due + period if mono - due < period else mono + period
        return True

    def _send_due(self) -> None:
        opts, mav = self.options, self.codec.mav
        mono = time.monotonic()
        with self._lock:
            overrides = dict(self.rate_overrides)
        due = {
            name: self._due(name, overrides.get(name, hz), mono)
            for name, hz in (
                ("heartbeat", opts.heartbeat_hz),
                ("system_time", opts.system_time_hz),
                ("attitude", opts.attitude_hz),
                ("local_position", opts.local_position_hz),
                ("global_position", opts.global_position_hz),
                ("distance_sensor", opts.distance_sensor_hz),
                ("highres_imu", opts.highres_imu_hz),
                ("scaled_imu", opts.scaled_imu_hz),
                ("raw_imu", opts.raw_imu_hz),
                ("origin", opts.origin_hz if self.origin is not None else 0.0),
                ("timesync", opts.timesync_request_hz),
            )
        }
        if not any(due.values()):
            return
        boot_us = self.boot_us()
        boot_ms = boot_us // 1000
        if due["heartbeat"]:
            self._send(
                mav.heartbeat_encode(
                    mavlink2.MAV_TYPE_QUADROTOR,
                    mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                    mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                    0,
                    mavlink2.MAV_STATE_STANDBY,
                )
            )
        if due["system_time"]:
            self._send(mav.system_time_encode(0, boot_ms % (1 << 32)))
        if due["timesync"]:
            self._send(mav.timesync_encode(0, boot_us * 1000))
        if due["origin"] and self.origin is not None:
            self._send_origin()
        telemetry = (
            "attitude",
            "local_position",
            "global_position",
            "distance_sensor",
            "highres_imu",
            "scaled_imu",
            "raw_imu",
        )
        if not any(due[k] for k in telemetry):
            return
        n = opts.noise
        rng = self.rng
        truth = self.truth(self.clock_us())
        if due["attitude"]:
            rpy = np.asarray(truth["rpy_rad"], dtype=float) + np.array(
                [rng.normal(0, n.roll_pitch_rad), rng.normal(0, n.roll_pitch_rad), rng.normal(0, n.yaw_rad)]
            )
            rpy[2] = math.remainder(rpy[2] + self._yaw_bias, 2 * math.pi)
            gyro = np.asarray(truth["gyro_body_rps"], dtype=float)
            self._send(mav.attitude_encode(boot_ms, *(float(a) for a in rpy), *(float(g) for g in gyro)))
        if due["local_position"] or due["global_position"]:
            p = np.asarray(truth["p_ned_m"], dtype=float) + rng.normal(0, n.position_m, 3)
            v = np.asarray(truth["v_ned_mps"], dtype=float) + rng.normal(0, n.velocity_mps, 3)
            if due["local_position"]:
                self._send(
                    mav.local_position_ned_encode(boot_ms, *(float(x) for x in p), *(float(x) for x in v))
                )
            if due["global_position"] and self.origin is not None:
                lat, lon, alt = self._geodetic(p)
                self._send(
                    mav.global_position_int_encode(
                        boot_ms,
                        int(round(lat * 1e7)),
                        int(round(lon * 1e7)),
                        int(round(alt * 1000)),
                        int(round(-p[2] * 1000)),
                        int(round(v[0] * 100)),
                        int(round(v[1] * 100)),
                        int(round(v[2] * 100)),
                        int(round(math.degrees(truth["rpy_rad"][2]) % 360.0 * 100)),
                    )
                )
        if due["distance_sensor"]:
            rng_m = float(truth["range_m"])
            rng_m += rng.normal(0, n.range_m + n.range_frac * abs(rng_m))
            min_cm, max_cm = int(opts.range_min_m * 100), int(opts.range_max_m * 100)
            dist_cm = int(round(rng_m * 100))
            dist_cm = max_cm + 1 if dist_cm > max_cm or not math.isfinite(rng_m) else max(dist_cm, 0)
            self._send(
                mav.distance_sensor_encode(
                    boot_ms % (1 << 32),
                    min_cm,
                    max_cm,
                    min(dist_cm, 65535),
                    mavlink2.MAV_DISTANCE_SENSOR_LASER,
                    0,
                    mavlink2.MAV_SENSOR_ROTATION_PITCH_270,
                    255,
                )
            )
        if due["highres_imu"] or due["scaled_imu"] or due["raw_imu"]:
            acc = (
                np.asarray(truth["accel_body_mps2"], dtype=float)
                + self._accel_bias
                + rng.normal(0, n.accel_mps2, 3)
            )
            gyr = (
                np.asarray(truth["gyro_body_rps"], dtype=float)
                + self._gyro_bias
                + rng.normal(0, n.gyro_rps, 3)
            )
            if due["highres_imu"]:
                self._send(
                    mav.highres_imu_encode(
                        boot_us,
                        *(float(a) for a in acc),
                        *(float(g) for g in gyr),
                        0,
                        0,
                        0,
                        0,
                        0,
                        0,
                        0,
                        0b111111,
                    )
                )
            if due["scaled_imu"] or due["raw_imu"]:  # both in milli-g and milli-rad/s
                acc_mg = [int(round(a / 9.80665 * 1000)) for a in acc]
                gyr_mrad = [int(round(g * 1000)) for g in gyr]
                if due["scaled_imu"]:
                    self._send(mav.scaled_imu_encode(boot_ms % (1 << 32), *acc_mg, *gyr_mrad, 0, 0, 0))
                if due["raw_imu"]:
                    self._send(mav.raw_imu_encode(boot_us, *acc_mg, *gyr_mrad, 0, 0, 0, 0, 0))

    def _geodetic(self, p_ned_m: np.ndarray) -> tuple[float, float, float]:
        """Local-tangent-plane NED -> (lat, lon, alt) around the origin (small-distance approximation)."""
        assert self.origin is not None
        lat0, lon0, alt0 = self.origin
        radius = PLANET_RADIUS_M[self.options.planet]
        lat = lat0 + math.degrees(p_ned_m[0] / radius)
        lon = lon0 + math.degrees(p_ned_m[1] / (radius * math.cos(math.radians(lat0))))
        return lat, lon, alt0 - float(p_ned_m[2])

    def _send_origin(self) -> None:
        assert self.origin is not None
        lat, lon, alt = self.origin
        self._send(
            self.codec.mav.gps_global_origin_encode(
                int(round(lat * 1e7)), int(round(lon * 1e7)), int(round(alt * 1000)), self.boot_us()
            )
        )

    # --- receiving ------------------------------------------------------------------------------
    def _reject(self, reason: str) -> None:
        with self._lock:
            self.rejections[reason] = self.rejections.get(reason, 0) + 1

    def _handle(self, msg: Any) -> None:
        name = msg.get_type()
        self.received[name] = self.received.get(name, 0) + 1
        if name == "HEARTBEAT":
            key = (msg.get_srcSystem(), msg.get_srcComponent())
            self.heartbeats_from[key] = self.heartbeats_from.get(key, 0) + 1
        elif name == "TIMESYNC":
            if msg.tc1 == 0:
                self._send(self.codec.mav.timesync_encode(self.boot_us() * 1000, msg.ts1))
            else:
                self.timesync_replies += 1
        elif name == "SET_GPS_GLOBAL_ORIGIN":
            if msg.target_system in (0, self.sysid):
                self.origin = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
                self._send_origin()
        elif name == "COMMAND_LONG":
            if msg.target_system not in (0, self.sysid):
                return
            result = mavlink2.MAV_RESULT_UNSUPPORTED
            if int(msg.command) == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
                stream = INTERVAL_STREAMS.get(int(msg.param1))
                if stream is not None:
                    # as ArduPilot: interval in us, 0 = the default rate, -1 = off
                    us = float(msg.param2)
                    with self._lock:
                        if us == 0:
                            self.rate_overrides.pop(stream, None)
                        else:
                            self.rate_overrides[stream] = 0.0 if us < 0 else 1e6 / us
                    result = mavlink2.MAV_RESULT_ACCEPTED
                else:
                    result = mavlink2.MAV_RESULT_DENIED
            self._send(self.codec.mav.command_ack_encode(int(msg.command), result))
        elif name == "PARAM_REQUEST_READ":
            if msg.target_system not in (0, self.sysid):
                return
            names = list(self.params)
            pid = str(msg.param_id)
            if int(msg.param_index) >= 0:
                pid = names[int(msg.param_index)] if int(msg.param_index) < len(names) else ""
            if pid in self.params:
                value, kind = self.params[pid]
                self._send(
                    self.codec.mav.param_value_encode(
                        pid.encode("ascii"), value, kind, len(names), names.index(pid)
                    )
                )
        elif name == "VISION_POSITION_ESTIMATE":
            p = np.array([msg.x, msg.y, msg.z], dtype=float)
            rpy = np.array([msg.roll, msg.pitch, msg.yaw], dtype=float)
            self._ext_nav("vpe", int(msg.usec), p, rpy, tuple(msg.covariance), int(msg.reset_counter), msg)
        elif name == "ODOMETRY":
            if (
                msg.frame_id != mavlink2.MAV_FRAME_LOCAL_FRD
                or msg.child_frame_id != mavlink2.MAV_FRAME_BODY_FRD
            ):
                self._reject(REJECT_BAD_FRAME)
                return
            p = np.array([msg.x, msg.y, msg.z], dtype=float)
            q = np.asarray(msg.q, dtype=float)
            twist = [msg.vx, msg.vy, msg.vz]
            if not (np.all(np.isfinite(q)) and np.all(np.isfinite(twist))):
                self._reject(REJECT_NON_FINITE)
                return
            rpy = rpy_from_quaternion([float(c) for c in q])
            self._ext_nav(
                "odometry",
                int(msg.time_usec),
                p,
                rpy,
                tuple(msg.pose_covariance),
                int(msg.reset_counter),
                msg,
            )

    def _ext_nav(
        self,
        kind: str,
        usec: int,
        p: np.ndarray,
        rpy: np.ndarray,
        cov: tuple[float, ...],
        reset_counter: int,
        msg: Any,
    ) -> None:
        """ArduPilot-like acceptance of one external-nav sample."""
        opts = self.options
        if int(self.params.get("VISO_TYPE", (1.0, 0))[0]) == 0:
            self._reject(REJECT_VISO_DISABLED)
            return
        cov_ok = math.isnan(cov[0]) or all(math.isfinite(c) for c in cov)  # NaN first = "unknown"
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(rpy)) and cov_ok):
            self._reject(REJECT_NON_FINITE)
            return
        now = self.boot_us()
        if usec > now + opts.ext_nav_max_future_us:
            self._reject(REJECT_FUTURE)
            return
        if usec < now - opts.ext_nav_max_age_us:
            self._reject(REJECT_TOO_OLD)
            return
        last = self._last_ext_usec
        if last is not None and usec <= last:
            self._reject(REJECT_NOT_MONOTONIC)
            return
        if last is not None and usec - last < opts.ext_nav_min_interval_us:
            self._reject(REJECT_TOO_FAST)
            return
        record = VisionRecord(kind, usec, p, rpy, cov, reset_counter, now, msg.get_srcComponent())
        with self._lock:
            self._last_ext_usec = usec
            self.records.append(record)
