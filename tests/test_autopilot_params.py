"""The autopilot's external-vision parameters: the check itself, and reading them from the simulated
autopilot over MAVLink (UDP on loopback) through the daemon's link adapter."""

from __future__ import annotations

import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from netutil import free_port, wait_for
from pymavlink.dialects.v20 import ardupilotmega as mav2

from companion.config import MavlinkConfig
from companion.io.autopilot import AutopilotLinkAdapter
from companion.io.autopilot_params import (
    ARDUPILOT,
    ERROR,
    INFO,
    OK,
    PX4,
    WARNING,
    check_params,
    decode_param_value,
    flavour_from_heartbeat,
    params_to_read,
    worst,
)
from companion.io.mavlink import MavlinkLink, MavlinkOptions
from companion.types import EstimateStatus, PoseEstimate
from sim_bridge.autopilot_link import (
    DEFAULT_PARAMS,
    REJECT_VISO_DISABLED,
    SimAutopilotLink,
    SimAutopilotOptions,
    with_imu_message,
)

GOOD_AP = {name: value for name, (value, _kind) in DEFAULT_PARAMS.items()}
NO_OFFSET = (0.0, 0.0, 0.0)
VPE = "vision_position_estimate"


def severities(findings) -> dict[str, str]:
    return {f.param: f.severity for f in findings}


def test_ardupilot_set_up_for_external_nav_passes() -> None:
    findings = check_params(ARDUPILOT, GOOD_AP, NO_OFFSET, VPE)
    assert worst(findings) in (OK, INFO)
    checked = {p for f in findings for p in f.param.split("/")}
    assert {"VISO_TYPE", "AHRS_EKF_TYPE", "EK3_SRC1_POSXY", "VISO_POS_X", "VISO_DELAY_MS"} <= checked


@pytest.mark.parametrize(
    ("change", "param", "severity"),
    [
        ({"VISO_TYPE": 0.0}, "VISO_TYPE", ERROR),
        ({"AHRS_EKF_TYPE": 2.0}, "AHRS_EKF_TYPE", ERROR),
        ({"EK3_SRC1_POSXY": 3.0}, "EK3_SRC1_POSXY", ERROR),  # GPS, and no other set uses ExternalNav
        ({"EK3_SRC1_POSXY": 3.0, "EK3_SRC2_POSXY": 6.0}, "EK3_SRC1_POSXY", INFO),  # switchable
        ({"EK3_SRC1_VELXY": 6.0}, "EK3_SRC1_VELXY", WARNING),  # VPE has no velocity
        ({"VISO_POS_Z": 0.05}, "VISO_POS_X/VISO_POS_Y/VISO_POS_Z", WARNING),  # config says 0
    ],
)
def test_ardupilot_misconfigurations_are_named(change: dict, param: str, severity: str) -> None:
    findings = check_params(ARDUPILOT, {**GOOD_AP, **change}, NO_OFFSET, VPE)
    assert severities(findings)[param] == severity
    bad = next(f for f in findings if f.param == param)
    assert bad.message  # says what to do


def test_ardupilot_velocity_source_is_fine_with_odometry_and_missing_viso_is_an_error() -> None:
    s = severities(check_params(ARDUPILOT, {**GOOD_AP, "EK3_SRC1_VELXY": 6.0}, NO_OFFSET, "odometry"))
    assert s["EK3_SRC1_VELXY"] == OK
    no_viso = {k: v for k, v in GOOD_AP.items() if k != "VISO_TYPE"}
    assert severities(check_params(ARDUPILOT, no_viso, NO_OFFSET, VPE))["VISO_TYPE"] == ERROR
    # the offset agrees when the config says the same as the autopilot
    offset = {**GOOD_AP, "VISO_POS_X": 0.1, "VISO_POS_Z": 0.05}
    assert (
        severities(check_params(ARDUPILOT, offset, (0.1, 0.0, 0.05), VPE))["VISO_POS_X/VISO_POS_Y/VISO_POS_Z"]
        == OK
    )


def test_px4_checks_ev_ctrl_bits_and_falls_back_to_aid_mask() -> None:
    base = {"EKF2_HGT_REF": 0.0, "EKF2_EV_POS_X": 0.0, "EKF2_EV_POS_Y": 0.0, "EKF2_EV_POS_Z": 0.0}
    assert severities(check_params(PX4, {**base, "EKF2_EV_CTRL": 11.0}, NO_OFFSET, VPE))["EKF2_EV_CTRL"] == OK
    assert (
        severities(check_params(PX4, {**base, "EKF2_EV_CTRL": 14.0}, NO_OFFSET, VPE))["EKF2_EV_CTRL"] == ERROR
    )
    assert (
        severities(check_params(PX4, {**base, "EKF2_EV_CTRL": 15.0}, NO_OFFSET, VPE))["EKF2_EV_CTRL"]
        == WARNING
    )
    assert (
        severities(check_params(PX4, {**base, "EKF2_AID_MASK": 24.0}, NO_OFFSET, VPE))["EKF2_AID_MASK"] == OK
    )
    assert (
        severities(check_params(PX4, {**base, "EKF2_AID_MASK": 1.0}, NO_OFFSET, VPE))["EKF2_AID_MASK"]
        == ERROR
    )
    assert severities(check_params(PX4, base, NO_OFFSET, VPE))["EKF2_EV_CTRL"] == ERROR  # neither answered


def test_values_are_decoded_as_each_autopilot_encodes_them() -> None:
    # PX4 puts an integer's bytes in the float field; ArduPilot casts to float
    as_float = struct.unpack("<f", struct.pack("<i", 11))[0]
    assert decode_param_value(as_float, mav2.MAV_PARAM_TYPE_INT32, PX4) == 11.0
    assert decode_param_value(0.05, mav2.MAV_PARAM_TYPE_REAL32, PX4) == pytest.approx(0.05)
    assert decode_param_value(6.0, mav2.MAV_PARAM_TYPE_INT8, ARDUPILOT) == 6.0
    assert flavour_from_heartbeat(mav2.MAV_AUTOPILOT_ARDUPILOTMEGA) == ARDUPILOT
    assert flavour_from_heartbeat(mav2.MAV_AUTOPILOT_PX4) == PX4
    assert flavour_from_heartbeat(mav2.MAV_AUTOPILOT_GENERIC) is None
    with pytest.raises(ValueError, match="flavour"):
        check_params("betaflight", {}, NO_OFFSET, VPE)


def _estimate(stamp_us: int) -> PoseEstimate:
    return PoseEstimate(
        stamp_us=stamp_us,
        p_body_in_world_m=np.array([1.0, 2.0, -30.0]),
        rpy_rad=np.zeros(3),
        covariance=np.eye(6) * 0.01,
        status=EstimateStatus.OK,
        quality=1.0,
    )


def _fly(params: tuple[tuple[str, float], ...], camera_offset_m=NO_OFFSET):
    port = free_port()
    sim = SimAutopilotLink(
        f"udpin:127.0.0.1:{port}", rng=np.random.default_rng(1), options=SimAutopilotOptions(params=params)
    )
    link = MavlinkLink(MavlinkOptions(connection=f"udpout:127.0.0.1:{port}", param_retry_s=0.3))
    adapter = AutopilotLinkAdapter(
        MavlinkConfig(connection=f"udpout:127.0.0.1:{port}"), link=link, camera_offset_m=camera_offset_m
    )
    return sim, link, adapter


def test_daemon_link_reads_the_simulated_autopilots_parameters() -> None:
    sim, link, adapter = _fly(())
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: adapter.check_autopilot() is not None, 5.0)
        assert link.flavour == ARDUPILOT
        assert set(link.params) == set(params_to_read(ARDUPILOT))  # every name answered
        assert link.params["EK3_SRC1_POSXY"] == 6.0
        st = adapter.status()
        assert st["params_check"]["problems"] == {}
        assert st["params_read"] == f"{len(params_to_read(ARDUPILOT))}/{len(params_to_read(ARDUPILOT))}"
        assert wait_for(lambda: link.timesync.synced, 5.0)
        assert adapter.send_estimate(_estimate(time.time_ns() // 1000)) is None
        assert wait_for(lambda: len(sim.accepted()) == 1)
    finally:
        link.stop()
        sim.stop()


def test_misconfigured_autopilot_is_reported_and_really_drops_estimates() -> None:
    # VISO_TYPE 0 (the autopilot ignores us) and a camera offset that disagrees with the config
    sim, link, adapter = _fly((("VISO_TYPE", 0.0), ("VISO_POS_X", 0.12)), camera_offset_m=(0.0, 0.0, 0.0))
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: adapter.check_autopilot() is not None, 5.0)
        problems = adapter.status()["params_check"]["problems"]
        assert problems["VISO_TYPE"].startswith(ERROR)
        assert problems["VISO_POS_X/VISO_POS_Y/VISO_POS_Z"].startswith(WARNING)
        assert adapter.status()["params_check"]["worst"] == ERROR
        assert wait_for(lambda: link.timesync.synced, 5.0)
        adapter.send_estimate(_estimate(time.time_ns() // 1000))
        assert wait_for(lambda: sim.rejected().get(REJECT_VISO_DISABLED, 0) == 1)
        assert sim.accepted() == []
    finally:
        link.stop()
        sim.stop()


def test_unanswered_parameters_end_the_reading_after_the_retries() -> None:
    # a firmware without the parameter: no answer, three tries, then reported as unanswered
    sim, link, adapter = _fly(())
    del sim.params["VISO_TYPE"]
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: adapter.check_autopilot() is not None, 5.0)
        assert "VISO_TYPE" not in link.params
        assert sim.received.get("PARAM_REQUEST_READ", 0) >= len(params_to_read(ARDUPILOT)) + 2
        assert adapter.status()["params_check"]["problems"]["VISO_TYPE"] == f"{ERROR}: unanswered"
    finally:
        link.stop()
        sim.stop()


@pytest.mark.parametrize("request_imu_hz", [50, 0])
def test_check_autopilot_reports_the_sensor_streams_the_estimator_needs(request_imu_hz: int) -> None:
    """``companion check-autopilot`` (its own process) against the simulated autopilot streaming no IMU, as
    an ArduPilot with SRn_RAW_SENS 0: the EKF's configuration asks for it and reports it streaming; told not
    to ask, it reports the missing IMU as an error and exits 1."""
    port = free_port()
    opts = with_imu_message(SimAutopilotOptions(), "none")
    sim = SimAutopilotLink(f"udpin:127.0.0.1:{port}", rng=np.random.default_rng(2), options=opts)
    sim.start()
    try:
        cmd = [
            sys.executable, "-m", "companion", "check-autopilot", "--config", "configs/europa_dual_ekf.toml",
            "--set", f'mavlink.connection="udpout:127.0.0.1:{port}"',
            "--set", f"mavlink.request_imu_hz={request_imu_hz}", "--timeout", "10",
        ]  # fmt: skip
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    finally:
        sim.stop()
    lines = {ln.split()[1]: ln for ln in out.stdout.splitlines() if ln.startswith("  ")}
    assert lines["ATTITUDE"].split()[0] == "OK" and lines["DISTANCE_SENSOR"].split()[0] == "OK", out.stdout
    if request_imu_hz:
        assert out.returncode == 0, out.stdout + out.stderr
        assert lines["IMU"].split()[0] == "OK" and "RAW_IMU" in lines["IMU"], out.stdout
        assert sim.rate_overrides == {"raw_imu": 50.0}
    else:
        assert out.returncode == 1, out.stdout + out.stderr
        assert lines["IMU"].split()[:4] == ["ERROR", "IMU", "=", "none"] and "not asked" in lines["IMU"]
        assert not sim.rate_overrides
