"""MAVLink 2 link to the autopilot: our HEARTBEAT, TIMESYNC, vehicle state in, vision estimates out.

pymavlink's generated encoder/decoder (``pymavlink.dialects.v20.ardupilotmega``, a superset of
common) is used behind ``MavCodec``, a small wrapper that turns messages into bytes and bytes into
messages (no I/O, no ``mavutil``); ``MavlinkLink`` owns a transport, a codec and one I/O thread.

Conventions: positions NED metres, angles radians, the companion clock is Unix-epoch microseconds
(as ROS 2 header stamps are); the autopilot clock is its time since boot. Estimates are sent with
their capture time mapped into the autopilot clock by TIMESYNC (companion.io.timesync).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, Final

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink2
from scipy.spatial.transform import Rotation

from companion.constants import DEFAULT_COMPANION_SYSID, GRAVITY_MPS2, MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
from companion.io.autopilot_params import decode_param_value, flavour_from_heartbeat, params_to_read
from companion.io.timesync import TimeSync, TimeSyncOptions
from companion.io.tlog import TlogWriter
from companion.io.transport import Backoff, Transport, open_transport
from companion.types import AltimeterSample, AttitudeSample, EstimateStatus, ImuSample, PoseEstimate

log = logging.getLogger(__name__)

MAVLINK_SIGNING_EPOCH_S: Final = 1_420_070_400
"""MAVLink 2 signing timestamps count 10 us units since 2015-01-01T00:00:00Z."""

# Refusal reasons of the outgoing guard (counter keys).
REFUSE_NOT_OK: Final = "not_ok"
"""The estimator marked the estimate as not OK (initialising / lost)."""
REFUSE_NON_FINITE: Final = "non_finite"
"""NaN or inf in position, attitude, velocity or covariance."""
REFUSE_BAD_COVARIANCE: Final = "bad_covariance"
"""Covariance not (6, 6) or with a negative variance."""
REFUSE_NO_TIMESYNC: Final = "no_timesync"
"""No autopilot timestamp given and TIMESYNC not converged yet."""
REFUSE_NOT_MONOTONIC: Final = "not_monotonic"
"""Autopilot timestamp not after the previous one sent."""
REFUSE_RATE: Final = "rate"
"""Closer to the previous estimate than the configured maximum rate allows."""
REFUSE_TOO_OLD: Final = "too_old"
"""Captured longer ago than ``max_estimate_age_s``: the autopilot would discard it (ArduPilot's EKF3 drops
external-nav samples more than 500 ms behind its fusion time), so it is counted here instead."""
REFUSE_LINK_DOWN: Final = "link_down"
"""The transport could not write (disconnected, or no UDP peer yet)."""

SCALED_IMU_G_MPS2: Final = GRAVITY_MPS2["earth"]
"""SCALED_IMU reports milli-g of standard Earth gravity, whatever the planet."""
IMU_SOURCES: Final = ("HIGHRES_IMU", "SCALED_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3")
"""IMU messages the link reads, best first. HIGHRES_IMU is PX4's (and ArduPilot's on request), in SI units.
ArduPilot's default sensor stream (SRn_RAW_SENS) sends RAW_IMU for its first IMU, in SCALED_IMU's units
(milli-g, milli-rad/s; ArduPilot's GCS_MAVLINK::send_raw_imu), and SCALED_IMU2/3 for the others; another
autopilot's RAW_IMU is raw sensor counts and is not read. Interleaving two IMUs would hand the estimator
two sets of biases in turn, so only the best stream arriving is used (``MavlinkOptions.imu_source_hold_s``)."""


class LinkState(StrEnum):
    """Autopilot link state from its HEARTBEAT arrivals."""

    DOWN = "down"
    """No heartbeat ever, or none for ``link_timeout_s``."""
    STALE = "stale"
    """Heartbeat late (more than ``stale_after_s``) but not yet timed out."""
    UP = "up"


@dataclass(frozen=True)
class GeoOrigin:
    """The autopilot's EKF origin (GPS_GLOBAL_ORIGIN): WGS84 degrees, metres above MSL."""

    stamp_us: int
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass(frozen=True)
class LocalPositionNed:
    """The autopilot's own LOCAL_POSITION_NED: p (3,) metres and v (3,) m/s, NED."""

    stamp_us: int
    p_ned_m: np.ndarray
    v_ned_mps: np.ndarray


# --- pure helpers -----------------------------------------------------------------------------------
def covariance_to_urt21(cov_6x6: np.ndarray) -> list[float]:
    """(6, 6) -> the 21-element upper-right triangle, row-major (MAVLink's pose covariance layout)."""
    cov = np.asarray(cov_6x6, dtype=float)
    rows, cols = np.triu_indices(6)
    return [float(v) for v in cov[rows, cols]]


def urt21_to_covariance(urt: Sequence[float]) -> np.ndarray:
    """21-element upper-right triangle, row-major -> symmetric (6, 6)."""
    cov = np.zeros((6, 6))
    rows, cols = np.triu_indices(6)
    cov[rows, cols] = np.asarray(urt, dtype=float)
    cov[cols, rows] = np.asarray(urt, dtype=float)
    return cov


def quaternion_from_rpy(rpy_rad: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) intrinsic ZYX -> (4,) quaternion (w, x, y, z) rotating body into world."""
    roll, pitch, yaw = (float(a) for a in rpy_rad)
    return Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat(scalar_first=True)


def rpy_from_quaternion(q_wxyz: Sequence[float] | np.ndarray) -> np.ndarray:
    """(w, x, y, z) -> (3,) roll, pitch, yaw (intrinsic ZYX)."""
    yaw, pitch, roll = Rotation.from_quat(np.asarray(q_wxyz, dtype=float), scalar_first=True).as_euler("ZYX")
    return np.array([roll, pitch, yaw])


def signing_timestamp_now() -> int:
    """Current MAVLink 2 signing timestamp (10 us units since 2015-01-01)."""
    return max(0, int((time.time() - MAVLINK_SIGNING_EPOCH_S) * 100_000))


def wall_clock_us() -> int:
    """The companion clock: Unix epoch microseconds (same base as ROS 2 header stamps)."""
    return time.time_ns() // 1000


# --- codec --------------------------------------------------------------------------------------------
class MavCodec:
    """MAVLink 2 bytes <-> messages for one (sysid, compid), optional signing. No I/O; thread-safe encode.

    signing_key: 32-byte secret; when given, outgoing messages are signed and incoming unsigned (or
    badly signed) ones are refused unless ``accept_unsigned``.
    """

    def __init__(
        self,
        sysid: int,
        compid: int,
        signing_key: bytes | None = None,
        link_id: int = 0,
        accept_unsigned: bool = False,
    ) -> None:
        self.mav = mavlink2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True  # garbage yields MAVLink_bad_data instead of an exception
        self._lock = threading.Lock()
        self.bad_data: dict[str, int] = {}
        """Undecodable input by reason (bad CRC, bad prefix, refused signature...)."""
        self.messages_in = 0
        self.messages_out = 0
        if signing_key is not None:
            self.setup_signing(signing_key, link_id, accept_unsigned)

    def setup_signing(self, key: bytes, link_id: int = 0, accept_unsigned: bool = False) -> None:
        """Sign outgoing messages with ``key`` (32 bytes) and check incoming signatures."""
        if len(key) != 32:
            raise ValueError(f"MAVLink signing key must be 32 bytes, got {len(key)}")
        signing = self.mav.signing
        signing.secret_key = bytes(key)
        signing.link_id = int(link_id) & 0xFF
        signing.sign_outgoing = True
        signing.timestamp = max(signing.timestamp, signing_timestamp_now())
        signing.allow_unsigned_callback = lambda _mav, _msgid: accept_unsigned

    @property
    def signing_counters(self) -> dict[str, int]:
        """pymavlink's signature counters (good / bad / refused / accepted unsigned)."""
        s = self.mav.signing
        return {
            "goodsig": s.goodsig_count,
            "badsig": s.badsig_count,
            "rejected": s.reject_count,
            "unsigned_accepted": s.unsigned_count,
        }

    def encode(self, msg: Any) -> bytes:
        """Message (from ``codec.mav.<name>_encode``) -> wire bytes; advances sequence / signing clock."""
        with self._lock:
            data = msg.pack(self.mav)
            self.mav.seq = (self.mav.seq + 1) % 256
            self.messages_out += 1
        return data

    def decode(self, data: bytes) -> list[Any]:
        """Wire bytes -> complete messages (partial ones are kept for the next call). Never raises."""
        out: list[Any] = []
        try:
            msgs = self.mav.parse_buffer(data) or []
        except mavlink2.MAVError as exc:
            self._count_bad(str(exc))
            return out
        for msg in msgs:
            if msg.get_type() == "BAD_DATA":
                self._count_bad(str(getattr(msg, "reason", "bad data")))
                continue
            out.append(msg)
        self.messages_in += len(out)
        return out

    def _count_bad(self, reason: str) -> None:
        key = "signature" if "signature" in reason.lower() else reason.split(" ")[0].lower() or "bad"
        self.bad_data[key] = self.bad_data.get(key, 0) + 1


# --- the link -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MavlinkOptions:
    """Settings of the autopilot link (one per daemon)."""

    connection: str = "udpout:127.0.0.1:14550"
    """Transport string, see companion.io.transport (udpout / udpin / tcp / tcpin / serial)."""
    baudrate: int = 921_600
    """Serial baud rate when the connection string does not give one."""
    sysid: int = DEFAULT_COMPANION_SYSID
    """Our system id: the vehicle's, as ArduPilot and PX4 expect."""
    compid: int = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY
    """Our component id (197); 191 (onboard computer) is the usual alternative."""
    autopilot_sysid: int = 1
    autopilot_compid: int = 1
    """MAV_COMP_ID_AUTOPILOT1."""
    heartbeat_period_s: float = 1.0
    timesync_period_s: float = 0.2
    """TIMESYNC request period (5 Hz: the filter window of 16 then spans 3.2 s)."""
    stale_after_s: float = 1.5
    """No autopilot heartbeat for this long -> STALE."""
    link_timeout_s: float = 3.5
    """No autopilot heartbeat for this long -> DOWN; when it comes back, treated as a possible reboot."""
    reboot_backstep_ms: int = 1000
    """SYSTEM_TIME.time_boot_ms going back by more than this = autopilot reboot (smaller: reordering)."""
    reboot_coalesce_s: float = 5.0
    """Reboot signs closer than this to the previous one (a restarted boot clock shows in SYSTEM_TIME,
    TIMESYNC and the heartbeat gap, one after the other) are the same reboot: reset_counter moves once."""
    max_estimate_age_s: float = 0.5
    """Estimates whose frame was captured longer ago than this (our clock) are not sent (``REFUSE_TOO_OLD``);
    0 = off. Not applied when the caller gives the autopilot timestamp itself."""
    max_vision_rate_hz: float = 40.0
    """Cap on estimates sent (ArduPilot EKF3 drops external-nav samples closer than 20 ms; 40 Hz = 25 ms)."""
    signing_key: bytes | None = None
    """32-byte MAVLink 2 signing key; None = no signing."""
    signing_link_id: int = 0
    accept_unsigned: bool = False
    """With a signing key: whether unsigned incoming messages are still accepted."""
    timesync: TimeSyncOptions = field(default_factory=TimeSyncOptions)
    backoff: Backoff = field(default_factory=Backoff)
    read_timeout_s: float = 0.01
    """I/O thread poll period (bounds timer jitter of heartbeat / timesync sends)."""
    read_params: bool = True
    """Read the autopilot's external-vision parameters (``companion.io.autopilot_params``) once its
    HEARTBEAT says whether it is ArduPilot or PX4, and again after a reboot."""
    param_retry_s: float = 1.0
    """Unanswered PARAM_REQUEST_READs are repeated after this long ..."""
    param_attempts: int = 3
    """... this many times in all; a parameter still unanswered is reported as such."""
    imu_source_hold_s: float = 0.5
    """One IMU stream feeds the estimator (``IMU_SOURCES``, best first): a worse one is used only when no
    better one has arrived for this long."""
    request_imu_hz: float = 0.0
    """When no IMU message has arrived for ``imu_request_after_s`` since the autopilot was first heard, ask it
    for its IMU at this rate on this link (MAV_CMD_SET_MESSAGE_INTERVAL: RAW_IMU from ArduPilot, HIGHRES_IMU
    from PX4), every ``param_retry_s``, ``param_attempts`` times (again after a reboot); 0 = never ask."""
    imu_request_after_s: float = 2.0
    tlog: str = ""
    """Log every message of the link, both directions, as a MAVLink ``.tlog`` at this path (``{time}`` = the
    start time; ``companion.io.tlog``); "" = no log."""
    tlog_flush_s: float = 1.0
    """The log is flushed to disk this often (a power cut loses at most this much of it)."""


@dataclass
class LinkCallbacks:
    """Functions the daemon registers; called from the link's I/O thread (keep them short)."""

    on_attitude: Callable[[AttitudeSample], None] | None = None
    on_imu: Callable[[ImuSample], None] | None = None
    on_altimeter: Callable[[AltimeterSample], None] | None = None
    on_origin: Callable[[GeoOrigin], None] | None = None
    on_local_position: Callable[[LocalPositionNed], None] | None = None
    on_autopilot_reset: Callable[[str], None] | None = None
    """Called with the reason ("system_time", "timesync_jump", "heartbeat_gap") of a detected reboot."""


class MavlinkLink:
    """Owns transport + codec + I/O thread. ``start()``, then ``send_*`` from any thread, ``stop()``."""

    def __init__(
        self,
        options: MavlinkOptions | None = None,
        callbacks: LinkCallbacks | None = None,
        clock_us: Callable[[], int] = wall_clock_us,
        transport: Transport | None = None,
    ) -> None:
        self.options = opts = options or MavlinkOptions()
        self.callbacks = callbacks or LinkCallbacks()
        self.clock_us = clock_us
        self.codec = MavCodec(
            opts.sysid, opts.compid, opts.signing_key, opts.signing_link_id, opts.accept_unsigned
        )
        self.timesync = TimeSync(opts.timesync)
        # OSError: a wrong path fails here, at start (before the transport is opened)
        self.tlog: TlogWriter | None = TlogWriter(opts.tlog) if opts.tlog else None
        self.transport = transport or open_transport(opts.connection, opts.baudrate, opts.backoff)
        self._next_tlog_flush = 0.0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._next_heartbeat = 0.0
        self._next_timesync = 0.0
        self._seen_connects = 0
        self._last_hb_mono: float | None = None
        self._last_boot_ms: int | None = None
        self._last_vision_usec: int | None = None
        self._reset_flag = False
        self._param_names: tuple[str, ...] = ()
        self._param_tries = 0
        self._next_param_mono = 0.0
        # latest values
        self.flavour: str | None = None
        """"ardupilot" / "px4" from the autopilot's HEARTBEAT, None before it (or for another autopilot)."""
        self.params: dict[str, float] = {}
        """Autopilot parameters read so far (name -> value), see ``MavlinkOptions.read_params``."""
        self.autopilot_heartbeat: Any = None
        """Last HEARTBEAT message from the autopilot (pymavlink object), None before the first."""
        self.origin: GeoOrigin | None = None
        self.local_position: LocalPositionNed | None = None
        self.last_attitude: AttitudeSample | None = None
        self.last_imu: ImuSample | None = None
        self.last_altimeter: AltimeterSample | None = None
        # counters
        self.sent: dict[str, int] = {}
        """Messages sent by type."""
        self.received: dict[str, int] = {}
        """Messages received from the autopilot by type."""
        self.refused: dict[str, int] = {}
        """Estimates not sent, by REFUSE_* reason."""
        self.resets: dict[str, int] = {}
        """Signs of an autopilot reboot / reconnect seen, by reason (one reboot may show several)."""
        self.reboots = 0
        """Distinct reboots: signs within ``reboot_coalesce_s`` of the previous one are the same reboot."""
        self._last_reboot_mono: float | None = None
        self.last_refusal: str | None = None
        """Reason the last refused send was refused."""
        self.callback_errors = 0
        self.thread_errors = 0
        self.ignored_sources = 0
        """Messages from other systems / components (GCS, other peripherals)."""
        self.imu_source: str | None = None
        """The IMU message feeding the estimator (one of ``IMU_SOURCES``), None before the first."""
        self.imu_not_used = 0
        """IMU messages not passed on because a better IMU stream is arriving."""
        self._imu_seen_mono: dict[str, float] = {}
        self.imu_requests = 0
        """MAV_CMD_SET_MESSAGE_INTERVAL requests sent for the IMU (``MavlinkOptions.request_imu_hz``)."""
        self.imu_request_result: str | None = None
        """The autopilot's answer to the last one (MAV_RESULT name, e.g. "ACCEPTED"), None before any."""
        self._imu_req_tries = 0
        self._next_imu_req_mono = 0.0
        self.heard_mono: float | None = None
        """time.monotonic() of the autopilot's first HEARTBEAT, None before it."""

    # --- lifecycle ------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the I/O thread (idempotent)."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="mavlink-link", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Stop the I/O thread and close the transport."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None
        self.transport.close()
        if self.tlog is not None:
            self.tlog.close()

    def __enter__(self) -> MavlinkLink:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    # --- state ----------------------------------------------------------------------------------
    @property
    def state(self) -> LinkState:
        """UP / STALE / DOWN from the age of the last autopilot heartbeat."""
        last = self._last_hb_mono
        if last is None:
            return LinkState.DOWN
        age = time.monotonic() - last
        if age > self.options.link_timeout_s:
            return LinkState.DOWN
        return LinkState.STALE if age > self.options.stale_after_s else LinkState.UP

    @property
    def params_complete(self) -> bool:
        """True once every parameter asked for has answered or its last attempt has timed out."""
        if not self._param_names:
            return False
        if all(n in self.params for n in self._param_names):
            return True
        return self._param_tries >= self.options.param_attempts and time.monotonic() >= self._next_param_mono

    def params_asked(self) -> tuple[str, ...]:
        """Names of the parameters being read (empty before the autopilot is identified)."""
        return self._param_names

    def consume_reset(self) -> bool:
        """True once after an autopilot reboot / reconnect was detected (the daemon may re-init)."""
        with self._lock:
            flag, self._reset_flag = self._reset_flag, False
        return flag

    def status(self) -> dict[str, Any]:
        """JSON-able snapshot of the link for the status line."""
        ts = self.timesync
        tstats = self.transport.stats
        return {
            "state": self.state.value,
            "connection": self.transport.description,
            "timesync": {
                "synced": ts.synced,
                "offset_us": ts.offset_us,
                "last_rtt_us": ts.last_rtt_us,
                "accepted": ts.accepted,
                "rejected_rtt": ts.rejected_rtt,
                "resets": ts.resets,
            },
            "transport": {
                "connected": tstats.connected,
                "reconnects": tstats.reconnects,
                "drops": tstats.drops,
                "bytes_in": tstats.bytes_in,
                "bytes_out": tstats.bytes_out,
                "writes_dropped": tstats.writes_dropped,
            },
            "sent": dict(self.sent),
            "received": dict(self.received),
            "refused": dict(self.refused),
            "autopilot_resets": dict(self.resets),
            "autopilot_reboots": self.reboots,
            "bad_data": dict(self.codec.bad_data),
            "signing": self.codec.signing_counters if self.options.signing_key else None,
            "callback_errors": self.callback_errors,
            "thread_errors": self.thread_errors,
            "autopilot": self.flavour,
            "imu_source": self.imu_source,
            "imu_not_used": self.imu_not_used,
            "imu_requests": self.imu_requests,
            "imu_request_result": self.imu_request_result,
            "params_read": f"{sum(n in self.params for n in self._param_names)}/{len(self._param_names)}",
            "tlog": None if self.tlog is None else self.tlog.status(),
        }

    # --- sending --------------------------------------------------------------------------------
    def send_message(self, msg: Any) -> bool:
        """Encode and write one pymavlink message; True when handed to the transport."""
        data = self.codec.encode(msg)
        ok = self.transport.write(data)
        if ok:
            name = msg.get_type()
            self.sent[name] = self.sent.get(name, 0) + 1
            if self.tlog is not None:
                self.tlog.write(data)
        return ok

    def send_heartbeat(self) -> bool:
        """Our HEARTBEAT: onboard controller, no autopilot, active."""
        mav = self.codec.mav
        return self.send_message(
            mav.heartbeat_encode(
                mavlink2.MAV_TYPE_ONBOARD_CONTROLLER,
                mavlink2.MAV_AUTOPILOT_INVALID,
                0,
                0,
                mavlink2.MAV_STATE_ACTIVE,
            )
        )

    def _refuse(self, reason: str) -> bool:
        self.refused[reason] = self.refused.get(reason, 0) + 1
        self.last_refusal = reason
        return False

    def send_estimate(self, estimate: PoseEstimate, usec_autopilot: int | None = None) -> str | None:
        """VISION_POSITION_ESTIMATE; None when sent, else why not (a REFUSE_* reason or "link_down")."""
        self.last_refusal = None
        if self.send_vision_position_estimate(estimate, usec_autopilot):
            return None
        return self.last_refusal or REFUSE_LINK_DOWN

    def _check_estimate(self, estimate: PoseEstimate, usec_autopilot: int | None) -> int | None:
        """The outgoing guard: the autopilot timestamp to send, or None (refusal counted)."""
        if estimate.status is not EstimateStatus.OK:
            self._refuse(REFUSE_NOT_OK)
            return None
        cov = np.asarray(estimate.covariance, dtype=float)
        values = (estimate.p_body_in_world_m, estimate.rpy_rad, cov)
        if not all(bool(np.all(np.isfinite(np.asarray(v, dtype=float)))) for v in values):
            self._refuse(REFUSE_NON_FINITE)
            return None
        if cov.shape != (6, 6) or bool(np.any(np.diag(cov) < 0.0)):
            self._refuse(REFUSE_BAD_COVARIANCE)
            return None
        max_age = self.options.max_estimate_age_s
        # the age is measured in our clock, so only for stamps we map ourselves (a caller giving the
        # autopilot time has its own timing, e.g. a replay)
        if (
            usec_autopilot is None
            and max_age > 0
            and estimate.stamp_us < self.clock_us() - int(max_age * 1e6)
        ):
            self._refuse(REFUSE_TOO_OLD)
            return None
        usec = (
            usec_autopilot if usec_autopilot is not None else self.timesync.to_autopilot_us(estimate.stamp_us)
        )
        if usec is None or usec <= 0:
            self._refuse(REFUSE_NO_TIMESYNC)
            return None
        last = self._last_vision_usec
        if last is not None and usec <= last:
            self._refuse(REFUSE_NOT_MONOTONIC)
            return None
        if last is not None and usec - last < 1e6 / self.options.max_vision_rate_hz:
            self._refuse(REFUSE_RATE)
            return None
        return int(usec)

    def send_vision_position_estimate(
        self, estimate: PoseEstimate, usec_autopilot: int | None = None
    ) -> bool:
        """VISION_POSITION_ESTIMATE (NED position, roll/pitch/yaw, 21-element covariance, reset_counter).

        usec_autopilot: the capture time in the autopilot clock; None maps ``estimate.stamp_us``
        through TIMESYNC. Returns False (and counts why) when the guard refuses the estimate.
        """
        usec = self._check_estimate(estimate, usec_autopilot)
        if usec is None:
            return False
        p = np.asarray(estimate.p_body_in_world_m, dtype=float)
        rpy = np.asarray(estimate.rpy_rad, dtype=float)
        msg = self.codec.mav.vision_position_estimate_encode(
            usec,
            float(p[0]),
            float(p[1]),
            float(p[2]),
            float(rpy[0]),
            float(rpy[1]),
            float(rpy[2]),
            covariance_to_urt21(estimate.covariance),
            int(estimate.reset_counter) % 256,
        )
        self._last_vision_usec = usec
        return self.send_message(msg)

    def send_odometry(
        self,
        estimate: PoseEstimate,
        v_body_mps: np.ndarray,
        cov_v_body: np.ndarray,
        usec_autopilot: int | None = None,
        rates_body_rps: np.ndarray | None = None,
    ) -> bool:
        """ODOMETRY with pose in MAV_FRAME_LOCAL_FRD and velocity in MAV_FRAME_BODY_FRD.

        Frames: ArduPilot's GCS_MAVLINK::handle_odometry drops (silently) any ODOMETRY whose
        frame_id != MAV_FRAME_LOCAL_FRD or child_frame_id != MAV_FRAME_BODY_FRD, and fuses the
        velocity it carries (rotated from body to NED); PX4 maps ODOMETRY with frame_id
        MAV_FRAME_LOCAL_FRD to vehicle_visual_odometry (docs.px4.io "Using Vision or Motion Capture
        Systems", MAVLink integration table). LOCAL_FRD / BODY_FRD is therefore the pair both take.
        Our local frame is NED, i.e. an FRD frame with zero heading offset.

        v_body_mps: (3,) body FRD velocity, cov_v_body: (3, 3) its covariance (m^2/s^2). Both are
        required: ArduPilot fuses the velocity, so zeros would tell it the vehicle is still.
        rates_body_rps: (3,) body rates; None sends the last HIGHRES/SCALED_IMU gyro, and if there is
        none, zeros with a 1e4 rad^2/s^2 variance (unknown).
        """
        usec = self._check_estimate(estimate, usec_autopilot)
        if usec is None:
            return False
        v = np.asarray(v_body_mps, dtype=float).reshape(3)
        cov_v = np.asarray(cov_v_body, dtype=float)
        if not (bool(np.all(np.isfinite(v))) and bool(np.all(np.isfinite(cov_v)))):
            self._refuse(REFUSE_NON_FINITE)
            return False
        if cov_v.shape != (3, 3) or bool(np.any(np.diag(cov_v) < 0.0)):
            self._refuse(REFUSE_BAD_COVARIANCE)
            return False
        cov_twist = np.zeros((6, 6))
        cov_twist[:3, :3] = cov_v
        if rates_body_rps is not None:
            rates = np.asarray(rates_body_rps, dtype=float).reshape(3)
            cov_twist[3:, 3:] = np.eye(3) * 1e-4  # (0.01 rad/s)^2: a gyro rate of a stated source
        elif self.last_imu is not None:
            rates = np.asarray(self.last_imu.gyro_rps, dtype=float)
            cov_twist[3:, 3:] = np.eye(3) * 1e-4
        else:
            rates = np.zeros(3)
            cov_twist[3:, 3:] = np.eye(3) * 1e4
        if not bool(np.all(np.isfinite(rates))):
            self._refuse(REFUSE_NON_FINITE)
            return False
        p = np.asarray(estimate.p_body_in_world_m, dtype=float)
        q = quaternion_from_rpy(estimate.rpy_rad)
        msg = self.codec.mav.odometry_encode(
            usec,
            mavlink2.MAV_FRAME_LOCAL_FRD,
            mavlink2.MAV_FRAME_BODY_FRD,
            float(p[0]),
            float(p[1]),
            float(p[2]),
            [float(c) for c in q],
            float(v[0]),
            float(v[1]),
            float(v[2]),
            float(rates[0]),
            float(rates[1]),
            float(rates[2]),
            covariance_to_urt21(estimate.covariance),
            covariance_to_urt21(cov_twist),
            int(estimate.reset_counter) % 256,
            mavlink2.MAV_ESTIMATOR_TYPE_VISION,
            int(round(100 * min(max(estimate.quality, 0.0), 1.0))),
        )
        self._last_vision_usec = usec
        return self.send_message(msg)

    def send_set_gps_global_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> bool:
        """SET_GPS_GLOBAL_ORIGIN for the autopilot (needed by ArduPilot without GPS to fly in NED)."""
        if not all(math.isfinite(v) for v in (lat_deg, lon_deg, alt_m)):
            return self._refuse(REFUSE_NON_FINITE)
        msg = self.codec.mav.set_gps_global_origin_encode(
            self.options.autopilot_sysid,
            int(round(lat_deg * 1e7)),
            int(round(lon_deg * 1e7)),
            int(round(alt_m * 1000.0)),
            int(self.clock_us()),
        )
        return self.send_message(msg)

    # --- I/O thread -----------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._tick()
            except Exception:  # noqa: BLE001 - the I/O thread must survive anything; counted + logged
                self.thread_errors += 1
                log.exception("mavlink link: error in I/O thread")
                time.sleep(self.options.read_timeout_s)

    def _tick(self) -> None:
        data = self.transport.read(self.options.read_timeout_s)
        if data:
            for msg in self.codec.decode(data):
                if self.tlog is not None:
                    self.tlog.write(msg.get_msgbuf())
                self._handle(msg)
        mono = time.monotonic()
        if self.tlog is not None and mono >= self._next_tlog_flush:
            self._next_tlog_flush = mono + self.options.tlog_flush_s
            self.tlog.flush()
        self._maybe_request_imu(mono)
        if self.transport.stats.connects != self._seen_connects:
            # (Re)connected: introduce ourselves and re-sync at once instead of at the next period.
            self._seen_connects = self.transport.stats.connects
            self._next_heartbeat = self._next_timesync = mono
        if mono >= self._next_heartbeat:
            self._next_heartbeat = mono + self.options.heartbeat_period_s
            self.send_heartbeat()
        if mono >= self._next_timesync:
            self._next_timesync = mono + self.options.timesync_period_s
            tc1, ts1 = self.timesync.make_request(self.clock_us())
            self.send_message(self.codec.mav.timesync_encode(tc1, ts1))
        if (
            self._param_names
            and self._param_tries < self.options.param_attempts
            and mono >= self._next_param_mono
        ):
            missing = [n for n in self._param_names if n not in self.params]
            if missing:
                self._param_tries += 1
                self._next_param_mono = mono + self.options.param_retry_s
                o = self.options
                for name in missing:
                    self.send_message(
                        self.codec.mav.param_request_read_encode(
                            o.autopilot_sysid, o.autopilot_compid, name.encode("ascii"), -1
                        )
                    )

    def _maybe_request_imu(self, mono: float) -> None:
        """Ask the autopilot for its IMU stream when none has arrived (``MavlinkOptions.request_imu_hz``)."""
        o = self.options
        if o.request_imu_hz <= 0 or self.flavour is None or self.heard_mono is None:
            return
        if self._last_hb_mono is None or mono - self._last_hb_mono > o.stale_after_s:
            return  # the autopilot is not there to ask
        if self._imu_req_tries >= o.param_attempts or mono < self._next_imu_req_mono:
            return
        quiet_since = max(self._imu_seen_mono.values(), default=self.heard_mono)
        if mono - max(quiet_since, self.heard_mono) < o.imu_request_after_s:
            return
        msg_id = (
            mavlink2.MAVLINK_MSG_ID_RAW_IMU
            if self.flavour == "ardupilot"
            else mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU
        )
        self._imu_req_tries += 1
        self._next_imu_req_mono = mono + o.param_retry_s
        log.warning(
            "no IMU from the autopilot for %.1f s: asking it for %s at %.0f Hz (MAV_CMD_SET_MESSAGE_INTERVAL)",
            mono - max(quiet_since, self.heard_mono),
            mavlink2.mavlink_map[msg_id].msgname,
            o.request_imu_hz,
        )
        sent = self.send_message(
            self.codec.mav.command_long_encode(
                o.autopilot_sysid,
                o.autopilot_compid,
                mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL,
                0,
                float(msg_id),
                1e6 / o.request_imu_hz,
                0,
                0,
                0,
                0,
                0,
            )
        )
        self.imu_requests += int(sent)

    def _stamp(self, boot_us: int, arrival_us: int) -> int:
        """Companion-clock stamp of an autopilot sample: its own stamp mapped by TIMESYNC, else arrival."""
        mapped = self.timesync.to_companion_us(boot_us)
        return arrival_us if mapped is None else min(mapped, arrival_us)

    def _call(self, fn: Callable[[Any], None] | None, arg: Any) -> None:
        if fn is None:
            return
        try:
            fn(arg)
        except Exception:  # noqa: BLE001 - a daemon callback must not kill the I/O thread
            self.callback_errors += 1
            log.exception("mavlink link: callback failed")

    def _autopilot_reset(self, reason: str) -> None:
        log.warning("autopilot reset detected (%s): time sync restarts", reason)
        if reason != "timesync_jump":
            self.timesync.reset()
        self._last_boot_ms = None
        self._last_vision_usec = None
        # parameters may have changed across the reboot: read them again
        self.params = {}
        self._param_tries = 0
        self._next_param_mono = 0.0
        self._imu_req_tries = 0  # a rebooted autopilot has forgotten the stream rates it was asked for
        mono = time.monotonic()
        same = (
            self._last_reboot_mono is not None
            and mono - self._last_reboot_mono < self.options.reboot_coalesce_s
        )
        self._last_reboot_mono = mono
        if not same:
            self.reboots += 1
            with self._lock:
                self._reset_flag = True
        # counted last: whoever sees the count sees the flag already set
        self.resets[reason] = self.resets.get(reason, 0) + 1
        if not same:
            self._call(self.callbacks.on_autopilot_reset, reason)

    def _handle_imu(self, name: str, msg: Any, now_us: int) -> None:
        if name == "RAW_IMU" and self.flavour != "ardupilot":
            return  # raw sensor counts (or an autopilot not yet known): no units to read them in
        mono = time.monotonic()
        self._imu_seen_mono[name] = mono
        rank = IMU_SOURCES.index(name)
        hold = self.options.imu_source_hold_s
        if any(mono - self._imu_seen_mono.get(better, -math.inf) < hold for better in IMU_SOURCES[:rank]):
            self.imu_not_used += 1
            return
        if name != self.imu_source:
            if self.imu_source is not None:
                log.info("IMU stream %s -> %s", self.imu_source, name)
            self.imu_source = name
        if name == "HIGHRES_IMU":
            imu = ImuSample(
                stamp_us=self._stamp(int(msg.time_usec), now_us),
                accel_mps2=np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float),
                gyro_rps=np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float),
            )
        else:
            # milli-g and milli-rad/s; RAW_IMU is stamped in microseconds since boot, SCALED_IMU* in ms
            boot_us = int(msg.time_usec) if name == "RAW_IMU" else int(msg.time_boot_ms) * 1000
            imu = ImuSample(
                stamp_us=self._stamp(boot_us, now_us),
                accel_mps2=np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float) * 1e-3 * SCALED_IMU_G_MPS2,
                gyro_rps=np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float) * 1e-3,
            )
        self.last_imu = imu
        self._call(self.callbacks.on_imu, imu)

    def _handle(self, msg: Any) -> None:
        name = msg.get_type()
        now_us = self.clock_us()
        if name == "TIMESYNC":
            # Requests may come from anyone on the link; answer them all (ArduPilot sends them).
            reply = self.timesync.on_timesync(int(msg.tc1), int(msg.ts1), now_us)
            if reply is not None:
                self.send_message(self.codec.mav.timesync_encode(*reply))
            elif self.timesync.consume_reset():
                self._autopilot_reset("timesync_jump")
            return
        if msg.get_srcSystem() != self.options.autopilot_sysid or (
            msg.get_srcComponent() != self.options.autopilot_compid
        ):
            self.ignored_sources += 1
            return
        self.received[name] = self.received.get(name, 0) + 1
        if name == "HEARTBEAT":
            mono = time.monotonic()
            if self._last_hb_mono is not None and mono - self._last_hb_mono > self.options.link_timeout_s:
                self._autopilot_reset("heartbeat_gap")
            self._last_hb_mono = mono
            if self.heard_mono is None:
                self.heard_mono = mono
            self.autopilot_heartbeat = msg
            if self.flavour is None:
                self.flavour = flavour_from_heartbeat(int(msg.autopilot))
                if self.flavour is not None and self.options.read_params:
                    self._param_names = params_to_read(self.flavour)
        elif name == "PARAM_VALUE":
            if self.flavour is not None:
                pid = str(msg.param_id)
                if pid not in self._param_names:
                    return  # a GCS downloading the whole list: not ours to keep
                self.params[pid] = decode_param_value(
                    float(msg.param_value), int(msg.param_type), self.flavour
                )
        elif name == "SYSTEM_TIME":
            boot_ms = int(msg.time_boot_ms)
            last = self._last_boot_ms
            if last is not None and boot_ms + self.options.reboot_backstep_ms < last:
                self._autopilot_reset("system_time")
            self._last_boot_ms = boot_ms
        elif name == "ATTITUDE":
            sample = AttitudeSample(
                stamp_us=self._stamp(int(msg.time_boot_ms) * 1000, now_us),
                roll_rad=float(msg.roll),
                pitch_rad=float(msg.pitch),
                yaw_rad=float(msg.yaw),
            )
            self.last_attitude = sample
            self._call(self.callbacks.on_attitude, sample)
        elif name in IMU_SOURCES:
            self._handle_imu(name, msg, now_us)
        elif name == "COMMAND_ACK":
            if int(msg.command) == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL:
                result = mavlink2.enums["MAV_RESULT"].get(int(msg.result))
                self.imu_request_result = (
                    result.name.removeprefix("MAV_RESULT_") if result else str(msg.result)
                )
                if self.imu_request_result != "ACCEPTED":
                    log.warning(
                        "the autopilot answered the IMU stream request with %s", self.imu_request_result
                    )
        elif name == "DISTANCE_SENSOR":
            if int(msg.orientation) != mavlink2.MAV_SENSOR_ROTATION_PITCH_270:
                return  # not looking down
            dist_cm = int(msg.current_distance)
            if not int(msg.min_distance) <= dist_cm <= int(msg.max_distance):
                self.received["DISTANCE_SENSOR_out_of_range"] = (
                    self.received.get("DISTANCE_SENSOR_out_of_range", 0) + 1
                )
                return
            alt = AltimeterSample(
                stamp_us=self._stamp(int(msg.time_boot_ms) * 1000, now_us), range_m=dist_cm / 100.0
            )
            self.last_altimeter = alt
            self._call(self.callbacks.on_altimeter, alt)
        elif name == "GPS_GLOBAL_ORIGIN":
            self.origin = GeoOrigin(
                stamp_us=now_us,
                lat_deg=msg.latitude * 1e-7,
                lon_deg=msg.longitude * 1e-7,
                alt_m=msg.altitude * 1e-3,
            )
            self._call(self.callbacks.on_origin, self.origin)
        elif name == "LOCAL_POSITION_NED":
            self.local_position = LocalPositionNed(
                stamp_us=self._stamp(int(msg.time_boot_ms) * 1000, now_us),
                p_ned_m=np.array([msg.x, msg.y, msg.z], dtype=float),
                v_ned_mps=np.array([msg.vx, msg.vy, msg.vz], dtype=float),
            )
            self._call(self.callbacks.on_local_position, self.local_position)
