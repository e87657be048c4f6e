"""Simulated autopilot: telemetry, boot clock and reboot, TIMESYNC, origin, ArduPilot-like ext-nav checks."""

from __future__ import annotations

import os
import socket
import threading
import time
from typing import Any

import numpy as np
import pytest
from netutil import free_port, wait_for
from pymavlink.dialects.v20 import ardupilotmega as mav2

from companion.io.mavlink import covariance_to_urt21, quaternion_from_rpy
from sim_bridge.autopilot_link import (
    REJECT_BAD_FRAME,
    REJECT_FUTURE,
    REJECT_NON_FINITE,
    REJECT_NOT_MONOTONIC,
    REJECT_TOO_FAST,
    REJECT_TOO_OLD,
    SimAutopilotLink,
    SimAutopilotOptions,
    SimNoise,
    hover_truth,
)


class Gcs:
    """A plain pymavlink client on UDP (the companion's role), sending first so udpin learns it."""

    def __init__(self, port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.settimeout(0.05)
        self.dest = ("127.0.0.1", port)
        self.mav = mav2.MAVLink(None, srcSystem=1, srcComponent=197)
        self.rx = mav2.MAVLink(None)
        self.rx.robust_parsing = True
        self.msgs: list[tuple[float, Any]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65535)
            except (TimeoutError, OSError):
                continue
            now = time.monotonic()
            self.msgs.extend((now, m) for m in self.rx.parse_buffer(data) or [] if m.get_type() != "BAD_DATA")

    def send(self, msg: Any) -> None:
        self.sock.sendto(msg.pack(self.mav), self.dest)
        self.mav.seq = (self.mav.seq + 1) % 256

    def of(self, name: str) -> list[Any]:
        return [m for _, m in list(self.msgs) if m.get_type() == name]

    def hello(self) -> None:
        """Like a real GCS, repeat the heartbeat until the autopilot answers: the first datagram may arrive
        before the simulated autopilot's socket is bound (seen on a loaded machine: then nothing ever comes)."""
        for _ in range(20):
            self.send(self.mav.heartbeat_encode(18, 8, 0, 0, 4))
            if wait_for(lambda: self.msgs, 0.5):
                return

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


@pytest.fixture
def sim_and_gcs():
    port = free_port()
    sim = SimAutopilotLink(
        f"udpin:127.0.0.1:{port}", clock_offset_us=42_000_000, rng=np.random.default_rng(5)
    )
    sim.start()
    gcs = Gcs(port)
    gcs.hello()
    yield sim, gcs
    gcs.close()
    sim.stop()


def vpe(gcs: Gcs, usec: int, p=(1.0, 2.0, -30.0), rpy=(0.0, 0.0, 0.5), cov=None, reset: int = 0) -> Any:
    cov21 = covariance_to_urt21(np.eye(6) * 0.01) if cov is None else cov
    return gcs.mav.vision_position_estimate_encode(usec, *p, *rpy, cov21, reset)


def test_telemetry_rates_and_content(sim_and_gcs) -> None:
    sim, gcs = sim_and_gcs
    need = {"HEARTBEAT": 1, "SYSTEM_TIME": 2, "ATTITUDE": 60, "HIGHRES_IMU": 60, "DISTANCE_SENSOR": 25}
    # wait for the counts rather than sleeping a fixed time: a starved machine is slow, not wrong
    assert wait_for(lambda: all(len(gcs.of(n)) >= k for n, k in need.items()), timeout_s=15.0), {
        n: len(gcs.of(n)) for n in need
    }
    # rates from the autopilot's own clock: median spacing of ATTITUDE (50 Hz) and DISTANCE_SENSOR (20 Hz)
    att_ms = np.diff([m.time_boot_ms for m in gcs.of("ATTITUDE")])
    rng_ms = np.diff([m.time_boot_ms for m in gcs.of("DISTANCE_SENSOR")])
    assert 15 <= np.median(att_ms) <= 25 and 40 <= np.median(rng_ms) <= 60, (
        np.median(att_ms),
        np.median(rng_ms),
    )
    hb = gcs.of("HEARTBEAT")[0]
    assert hb.type == mav2.MAV_TYPE_QUADROTOR and hb.autopilot == mav2.MAV_AUTOPILOT_ARDUPILOTMEGA
    # No origin without GPS until one is set: no GLOBAL_POSITION_INT yet.
    assert not gcs.of("GLOBAL_POSITION_INT")
    ranges = np.array([m.current_distance for m in gcs.of("DISTANCE_SENSOR")]) / 100.0
    assert abs(ranges.mean() - 30.0) < 0.3 and 0.05 < ranges.std() < 1.5  # 30 m truth, 2 cm + 1 % noise
    att = gcs.of("ATTITUDE")
    assert abs(np.mean([m.roll for m in att])) < 0.01 and np.std([m.roll for m in att]) > 0
    boot_ms = [m.time_boot_ms for m in gcs.of("SYSTEM_TIME")]
    assert 42_000 <= boot_ms[0] < 45_000 and boot_ms == sorted(boot_ms)
    assert sim.heartbeats_from[(1, 197)] >= 1


def test_reboot_restarts_boot_clock(sim_and_gcs) -> None:
    sim, gcs = sim_and_gcs
    assert wait_for(lambda: gcs.of("SYSTEM_TIME"))
    sim.reboot()
    n = len(gcs.of("SYSTEM_TIME"))
    assert wait_for(lambda: len(gcs.of("SYSTEM_TIME")) > n)
    assert gcs.of("SYSTEM_TIME")[-1].time_boot_ms < 2_000
    assert sim.reboots == 1 and abs(sim.boot_us() - 0) < 5_000_000


def test_answers_timesync_with_its_boot_clock(sim_and_gcs) -> None:
    sim, gcs = sim_and_gcs
    gcs.send(gcs.mav.timesync_encode(0, 123_456_789))
    assert wait_for(lambda: [m for m in gcs.of("TIMESYNC") if m.ts1 == 123_456_789])
    reply = [m for m in gcs.of("TIMESYNC") if m.ts1 == 123_456_789][0]
    assert abs(reply.tc1 / 1000 - sim.boot_us()) < 500_000


def test_origin_set_and_reported(sim_and_gcs) -> None:
    sim, gcs = sim_and_gcs
    gcs.send(gcs.mav.set_gps_global_origin_encode(1, -147_000_000, 1_374_000_000, 250_000, 0))
    assert wait_for(lambda: gcs.of("GPS_GLOBAL_ORIGIN") and gcs.of("GLOBAL_POSITION_INT"))
    origin = gcs.of("GPS_GLOBAL_ORIGIN")[0]
    assert (origin.latitude, origin.longitude, origin.altitude) == (-147_000_000, 1_374_000_000, 250_000)
    assert sim.origin == pytest.approx((-14.7, 137.4, 250.0))
    gpi = gcs.of("GLOBAL_POSITION_INT")[-1]
    assert abs(gpi.relative_alt - 30_000) < 1_000 and abs(gpi.lat - origin.latitude) < 100


def test_external_nav_checks_like_ardupilot(sim_and_gcs) -> None:
    sim, gcs = sim_and_gcs
    now = sim.boot_us() - 200_000  # a capture time 200 ms ago, in the autopilot's clock
    gcs.send(vpe(gcs, now, reset=4))  # accepted
    gcs.send(vpe(gcs, now + 5_000))  # 5 ms later: faster than EKF3's 20 ms minimum interval
    gcs.send(vpe(gcs, now - 10_000))  # older than the last accepted one
    gcs.send(vpe(gcs, now + 1_200_000))  # in the future
    gcs.send(vpe(gcs, now - 2_000_000))  # older than 500 ms
    gcs.send(vpe(gcs, now + 50_000, p=(float("nan"), 0.0, 0.0)))  # not finite
    q = [float(c) for c in quaternion_from_rpy(np.array([0.1, 0.2, 0.3]))]
    cov = covariance_to_urt21(np.eye(6) * 0.02)
    for frame, child, dt in (
        (mav2.MAV_FRAME_LOCAL_NED, mav2.MAV_FRAME_BODY_FRD, 60_000),  # ArduPilot ignores this frame pair
        (mav2.MAV_FRAME_LOCAL_FRD, mav2.MAV_FRAME_BODY_FRD, 80_000),
    ):
        gcs.send(
            gcs.mav.odometry_encode(
                now + dt, frame, child, 5.0, 6.0, -20.0, q, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, cov, cov, 9, 2, 100
            )
        )
    assert wait_for(lambda: len(sim.accepted()) == 2 and sum(sim.rejected().values()) == 6)
    rejected = sim.rejected()
    for reason in (REJECT_TOO_FAST, REJECT_NOT_MONOTONIC, REJECT_FUTURE, REJECT_TOO_OLD, REJECT_NON_FINITE):
        assert rejected[reason] == 1, reason
    assert rejected[REJECT_BAD_FRAME] == 1
    first, odo = sim.accepted()
    assert first.kind == "vpe" and first.usec == now and first.reset_counter == 4
    assert first.src_compid == 197 and first.covariance[0] == pytest.approx(0.01)
    assert odo.kind == "odometry" and odo.reset_counter == 9
    np.testing.assert_allclose(odo.rpy_rad, [0.1, 0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(odo.p_ned_m, [5, 6, -20])


def test_serial_pty() -> None:
    master, slave = os.openpty()
    name = os.ttyname(slave)
    os.close(slave)
    sim = SimAutopilotLink(f"serial:{name}:115200", options=SimAutopilotOptions(attitude_hz=20))
    sim.start()
    mav = mav2.MAVLink(None, srcSystem=1, srcComponent=197)
    rx = mav2.MAVLink(None)
    rx.robust_parsing = True
    got: list[Any] = []
    try:
        # pyserial sets raw mode and flushes input when it opens: write only once it has.
        assert wait_for(lambda: sim.transport.stats.connected, 3.0)
        end = time.monotonic() + 1.5
        os.set_blocking(master, False)
        boot = sim.boot_us()
        os.write(
            master, mav.vision_position_estimate_encode(boot, 1, 2, -3, 0, 0, 0, [0.01] * 21, 1).pack(mav)
        )
        while time.monotonic() < end:
            try:
                got.extend(
                    m for m in rx.parse_buffer(os.read(master, 4096)) or [] if m.get_type() != "BAD_DATA"
                )
            except BlockingIOError:
                time.sleep(0.01)
    finally:
        sim.stop()
        os.close(master)
    names = {m.get_type() for m in got}
    assert {"HEARTBEAT", "ATTITUDE", "HIGHRES_IMU"} <= names
    assert len(sim.accepted()) == 1 and sim.accepted()[0].usec == boot


def test_compass_offset_moves_every_attitude_yaw_and_leaves_the_draws_alone() -> None:
    """``--compass-offset``: the simulated compass off by a fixed angle on top of its drawn bias."""
    off = SimAutopilotOptions(noise=SimNoise(yaw_offset_rad=0.3))
    a = SimAutopilotLink(f"udpin:127.0.0.1:{free_port()}", rng=np.random.default_rng(11))
    b = SimAutopilotLink(f"udpin:127.0.0.1:{free_port()}", rng=np.random.default_rng(11), options=off)
    try:
        assert b._yaw_bias - a._yaw_bias == pytest.approx(0.3, abs=1e-12)
        np.testing.assert_array_equal(a._accel_bias, b._accel_bias)
    finally:
        a.transport.close()
        b.transport.close()
    port = free_port()
    sim = SimAutopilotLink(f"udpin:127.0.0.1:{port}", truth=hover_truth(10.0), options=off)
    sim.start()
    gcs = Gcs(port)
    try:
        gcs.hello()
        assert wait_for(lambda: len(gcs.of("ATTITUDE")) > 20)
    finally:
        gcs.close()
        sim.stop()
    yaw = np.array([m.yaw for m in gcs.of("ATTITUDE")])
    truth_yaw = hover_truth(10.0)(0)["rpy_rad"][2]
    # the drawn bias is 0.02 rad 1-sigma and the noise 0.005 rad: the offset dominates
    assert np.mean(yaw) - truth_yaw == pytest.approx(0.3, abs=0.1)


def test_scaled_imu_units_and_seeded_biases() -> None:
    opts = SimAutopilotOptions(scaled_imu_hz=50, highres_imu_hz=0)
    a = SimAutopilotLink(f"udpin:127.0.0.1:{free_port()}", rng=np.random.default_rng(11), options=opts)
    b = SimAutopilotLink(f"udpin:127.0.0.1:{free_port()}", rng=np.random.default_rng(11), options=opts)
    try:
        np.testing.assert_array_equal(a._accel_bias, b._accel_bias)  # same seed, same biases
        port = free_port()
        sim = SimAutopilotLink(f"udpin:127.0.0.1:{port}", truth=hover_truth(10.0), options=opts)
        sim.start()
        gcs = Gcs(port)
        gcs.hello()
        assert wait_for(lambda: len(gcs.of("SCALED_IMU")) > 20)
        gcs.close()
        sim.stop()
    finally:
        a.transport.close()
        b.transport.close()
    zacc_mg = np.mean([m.zacc for m in gcs.of("SCALED_IMU")])
    assert abs(zacc_mg + 1000) < 30  # specific force at hover: -1 g in milli-g, plus bias and noise
