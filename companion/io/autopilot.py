"""The daemon's view of the autopilot: a ``MavlinkLink`` configured from the TOML config, plus what
the daemon adds on top — the message choice (VISION_POSITION_ESTIMATE or ODOMETRY), the reset counter
bumped when the autopilot reboots (its EKF restarted, so our estimate jumps for it), setting the
EKF origin when the config gives one and the autopilot has none, and the check of the autopilot's
external-vision parameters (``companion.io.autopilot_params``), logged once they are read.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from typing import Any

from companion.config import MavlinkConfig, OriginConfig
from companion.geometry import rot_from_rpy
from companion.io.autopilot_params import ERROR, WARNING, Finding, check_params, worst
from companion.io.mavlink import LinkCallbacks, LocalPositionNed, MavlinkLink, MavlinkOptions, wall_clock_us
from companion.types import LocalPositionSample, PoseEstimate

log = logging.getLogger("companion.autopilot")


def link_options(cfg: MavlinkConfig) -> MavlinkOptions:
    """MavlinkOptions from the config section (serial connection strings carry their baud rate)."""
    return MavlinkOptions(
        connection=cfg.connection,
        sysid=cfg.sysid,
        compid=cfg.compid,
        link_timeout_s=cfg.link_timeout_s,
        max_estimate_age_s=cfg.max_estimate_age_ms / 1000.0,
        max_vision_rate_hz=max(cfg.max_rate_hz * 1.5, cfg.max_rate_hz + 5.0),
        signing_key=bytes.fromhex(cfg.signing_key_hex) if cfg.signing_key_hex else None,
        request_imu_hz=cfg.request_imu_hz,
        tlog=cfg.tlog,
    )


class AutopilotLinkAdapter:
    """Implements ``companion.daemon.AutopilotLink`` over a ``MavlinkLink``."""

    def __init__(
        self,
        cfg: MavlinkConfig,
        origin: OriginConfig | None = None,
        link: MavlinkLink | None = None,
        camera_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        clock_us: Callable[[], int] | None = None,
    ):
        """camera_offset_m: the camera's position in the body frame (FRD, m) as configured, compared with
        the autopilot's VISO_POS_* / EKF2_EV_POS_*. clock_us: the link's clock (the daemon's
        ``CompanionClock.now_us``; None: the wall clock)."""
        self.cfg = cfg
        self.origin = origin
        self.camera_offset_m = camera_offset_m
        self.findings: list[Finding] | None = None
        """The parameter check, once the parameters are read (again after an autopilot reboot)."""
        self._callbacks = LinkCallbacks(on_autopilot_reset=self._on_reset)
        if link is None:
            link = MavlinkLink(link_options(cfg), self._callbacks, clock_us=clock_us or wall_clock_us)
        else:
            link.callbacks.on_autopilot_reset = self._on_reset
        self.link = link
        self.reset_offset = 0
        self._next_origin_try = 0.0
        self.origin_sets_sent = 0

    def _on_reset(self, reason: str) -> None:
        self.reset_offset += 1
        self.findings = None  # parameters are read again after a reboot
        log.warning("autopilot reset detected (%s): reset_counter offset now %d", reason, self.reset_offset)

    def start(
        self,
        on_attitude: Callable,
        on_imu: Callable,
        on_altimeter: Callable,
        on_local_position: Callable[[LocalPositionSample], None],
    ) -> None:
        cb = self.link.callbacks
        cb.on_attitude, cb.on_imu, cb.on_altimeter = on_attitude, on_imu, on_altimeter

        def local_position(lp: LocalPositionNed) -> None:
            on_local_position(LocalPositionSample(lp.stamp_us, lp.p_ned_m, lp.v_ned_mps))

        cb.on_local_position = local_position
        self.link.start()

    def _maybe_set_origin(self) -> None:
        if self.origin is None or not self.cfg.set_origin_if_missing or self.link.origin is not None:
            return
        now = time.monotonic()
        if now < self._next_origin_try or self.link.state.value != "up":
            return
        self._next_origin_try = now + 2.0
        o = self.origin
        if self.link.send_set_gps_global_origin(o.lat_deg, o.lon_deg, o.alt_m):
            self.origin_sets_sent += 1
            log.info(
                "autopilot has no EKF origin: sent SET_GPS_GLOBAL_ORIGIN %.6f %.6f %.1f",
                o.lat_deg,
                o.lon_deg,
                o.alt_m,
            )

    def send_estimate(self, estimate: PoseEstimate) -> str | None:
        self._maybe_set_origin()
        if self.reset_offset:
            estimate = dataclasses.replace(estimate, reset_counter=estimate.reset_counter + self.reset_offset)
        if self.cfg.message == "odometry":
            if estimate.v_world_mps is None or estimate.cov_v_world is None:
                return "no_velocity"
            # ODOMETRY carries the velocity in body FRD
            R_wb = rot_from_rpy(*estimate.rpy_rad)
            v_body = R_wb.T @ estimate.v_world_mps
            cov_v_body = R_wb.T @ estimate.cov_v_world @ R_wb
            self.link.last_refusal = None
            if self.link.send_odometry(estimate, v_body, cov_v_body):
                return None
            return self.link.last_refusal or "link_down"
        return self.link.send_estimate(estimate)

    def check_autopilot(self) -> list[Finding] | None:
        """The parameter findings once every parameter has answered or timed out (logged the first time);
        None while reading, or when the autopilot is neither ArduPilot nor PX4."""
        link = self.link
        if self.findings is None and link.flavour is not None and link.params_complete:
            self.findings = check_params(
                link.flavour, dict(link.params), self.camera_offset_m, self.cfg.message
            )
            bad = [f for f in self.findings if f.severity in (WARNING, ERROR)]
            for f in bad:
                log.warning("autopilot %s %s = %s: %s", f.severity, f.param, f.value, f.message)
            if not bad:
                log.info(
                    "autopilot (%s): external vision set up (%d of %d parameters read)",
                    link.flavour,
                    len(link.params),
                    len(link.params_asked()),
                )
        return self.findings

    def status(self) -> dict[str, Any]:
        findings = self.check_autopilot()
        st = self.link.status()
        st["params_check"] = (
            None
            if findings is None
            else {
                "worst": worst(findings),
                "problems": {
                    f.param: f"{f.severity}: {f.value}" for f in findings if f.severity in (WARNING, ERROR)
                },
            }
        )
        st["timesync"] = bool(st["timesync"]["synced"])
        st["reset_offset"] = self.reset_offset
        st["origin_set"] = self.link.origin is not None
        return st

    def stop(self) -> None:
        self.link.stop()
