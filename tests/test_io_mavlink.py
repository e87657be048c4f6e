"""MAVLink link against real peers: plain pymavlink on UDP sockets, the simulated autopilot, pty serial, TCP."""

from __future__ import annotations

import os
import socket
import tempfile
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from netutil import free_port, wait_for
from pymavlink.dialects.v20 import ardupilotmega as mav2

from companion.io.mavlink import (
    REFUSE_BAD_COVARIANCE,
    REFUSE_NO_TIMESYNC,
    REFUSE_NON_FINITE,
    REFUSE_NOT_MONOTONIC,
    REFUSE_NOT_OK,
    REFUSE_TOO_OLD,
    LinkCallbacks,
    LinkState,
    MavCodec,
    MavlinkLink,
    MavlinkOptions,
    covariance_to_urt21,
    quaternion_from_rpy,
    rpy_from_quaternion,
    urt21_to_covariance,
)
from companion.io.timesync import TimeSyncOptions
from companion.io.transport import Backoff, open_transport
from companion.types import EstimateStatus, PoseEstimate
from sim_bridge.autopilot_link import SimAutopilotLink, SimAutopilotOptions, with_imu_message

KEY = bytes(range(32))
FAST_BACKOFF = Backoff(min_s=0.02, max_s=0.2)


def estimate(stamp_us: int, **kw: Any) -> PoseEstimate:
    cov = kw.pop("covariance", None)
    if cov is None:
        a = np.arange(36, dtype=float).reshape(6, 6) * 1e-3
        cov = a @ a.T + np.eye(6) * 0.01  # symmetric, every entry distinct enough to check the order
    return PoseEstimate(
        stamp_us=stamp_us,
        p_body_in_world_m=kw.pop("p", np.array([12.5, -3.25, -48.0])),
        rpy_rad=kw.pop("rpy", np.array([0.05, -0.02, 1.2])),
        covariance=cov,
        **kw,
    )


class UdpPeer:
    """A plain pymavlink endpoint on its own UDP socket (no code of ours on this side)."""

    def __init__(self, sysid: int = 1, compid: int = 1, key: bytes | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.mav = mav2.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self.mav.robust_parsing = True
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.timestamp = int((time.time() - 1_420_070_400) * 100_000)
        self.msgs: list[Any] = []
        self.addr: tuple[str, int] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, self.addr = self.sock.recvfrom(65535)
            except (TimeoutError, OSError):
                continue
            for m in self.mav.parse_buffer(data) or []:
                if m.get_type() != "BAD_DATA":
                    self.msgs.append(m)

    def of(self, name: str) -> list[Any]:
        return [m for m in list(self.msgs) if m.get_type() == name]

    def send(self, msg: Any) -> None:
        assert self.addr is not None
        self.sock.sendto(msg.pack(self.mav), self.addr)
        self.mav.seq = (self.mav.seq + 1) % 256

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.sock.close()


@pytest.fixture
def peer():
    p = UdpPeer()
    yield p
    p.close()


# --- pure helpers -------------------------------------------------------------------------------------
def test_covariance_urt21_is_row_major_upper_triangle() -> None:
    cov = np.arange(36, dtype=float).reshape(6, 6)
    cov = np.triu(cov) + np.triu(cov, 1).T
    urt = covariance_to_urt21(cov)
    assert urt[:6] == [0, 1, 2, 3, 4, 5]  # first row
    assert urt[6:11] == [7, 8, 9, 10, 11]  # second row from the diagonal
    assert [urt[i] for i in (0, 6, 11, 15, 18, 20)] == [0, 7, 14, 21, 28, 35]  # the diagonal
    np.testing.assert_array_equal(urt21_to_covariance(urt), cov)


def test_quaternion_round_trip() -> None:
    rpy = np.array([0.1, -0.3, 2.5])
    q = quaternion_from_rpy(rpy)
    assert abs(np.linalg.norm(q) - 1) < 1e-12
    np.testing.assert_allclose(rpy_from_quaternion(q), rpy, atol=1e-12)
    np.testing.assert_allclose(quaternion_from_rpy(np.zeros(3)), [1, 0, 0, 0])


def test_codec_signing_without_sockets() -> None:
    signer = MavCodec(1, 197, signing_key=KEY)
    checker = MavCodec(1, 1, signing_key=KEY)
    stranger = MavCodec(1, 1, signing_key=bytes(32))
    plain = MavCodec(1, 197)
    hb = signer.encode(signer.mav.heartbeat_encode(18, 8, 0, 0, 4))
    assert [m.get_type() for m in checker.decode(hb)] == ["HEARTBEAT"]
    assert stranger.decode(hb) == [] and stranger.bad_data.get("signature") == 1
    unsigned = plain.encode(plain.mav.heartbeat_encode(18, 8, 0, 0, 4))
    assert checker.decode(unsigned) == [] and checker.signing_counters["rejected"] == 1
    assert checker.decode(b"\x01\x02garbage\xfd") == []  # garbage never raises


# --- over UDP with a plain pymavlink peer -----------------------------------------------------------
def test_heartbeat_and_vpe_content(peer: UdpPeer) -> None:
    link = MavlinkLink(MavlinkOptions(connection=f"udpout:127.0.0.1:{peer.port}"))
    with link:
        assert wait_for(lambda: len(peer.of("HEARTBEAT")) >= 1)
        t_first = time.monotonic()
        est = estimate(1_700_000_000_000_000, reset_counter=300)
        assert link.send_vision_position_estimate(est, usec_autopilot=123_456_789)
        assert wait_for(lambda: peer.of("VISION_POSITION_ESTIMATE"))
        assert wait_for(lambda: len(peer.of("HEARTBEAT")) >= 3, 4.0)
        elapsed = time.monotonic() - t_first
    hb = peer.of("HEARTBEAT")[0]
    assert hb.type == mav2.MAV_TYPE_ONBOARD_CONTROLLER and hb.autopilot == mav2.MAV_AUTOPILOT_INVALID
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 197
    assert 1.5 < elapsed < 3.5  # 1 Hz: 2 more heartbeats take about 2 s
    vpe = peer.of("VISION_POSITION_ESTIMATE")[0]
    assert vpe.usec == 123_456_789 and vpe.reset_counter == 300 % 256
    np.testing.assert_allclose([vpe.x, vpe.y, vpe.z], est.p_body_in_world_m, rtol=1e-6)
    np.testing.assert_allclose([vpe.roll, vpe.pitch, vpe.yaw], est.rpy_rad, rtol=1e-6)
    np.testing.assert_allclose(urt21_to_covariance(vpe.covariance), est.covariance, rtol=1e-6)


def test_guard_never_sends_nan_inf_or_unhealthy(peer: UdpPeer) -> None:
    link = MavlinkLink(MavlinkOptions(connection=f"udpout:127.0.0.1:{peer.port}"))
    t = time.time_ns() // 1000 - 100_000  # captured 100 ms ago
    bad_cov = np.eye(6)
    bad_cov[2, 2] = -1.0
    cases = [
        (estimate(t, p=np.array([np.nan, 0, 0])), REFUSE_NON_FINITE),
        (estimate(t, rpy=np.array([0, np.inf, 0])), REFUSE_NON_FINITE),
        (estimate(t, covariance=np.full((6, 6), np.nan)), REFUSE_NON_FINITE),
        (estimate(t, status=EstimateStatus.LOST), REFUSE_NOT_OK),
        (estimate(t, status=EstimateStatus.INITIALISING), REFUSE_NOT_OK),
        (estimate(t, covariance=bad_cov), REFUSE_BAD_COVARIANCE),
    ]
    with link:
        for est, reason in cases:
            assert link.send_estimate(est, usec_autopilot=5_000_000) == reason
        assert link.send_estimate(estimate(t - 600_000)) == REFUSE_TOO_OLD  # 0.7 s: ArduPilot would drop it
        assert link.send_estimate(estimate(t)) == REFUSE_NO_TIMESYNC  # no autopilot, no clock mapping
        assert link.send_estimate(estimate(t), usec_autopilot=5_000_000) is None
        assert link.send_estimate(estimate(t), usec_autopilot=5_000_000) == REFUSE_NOT_MONOTONIC
        v_nan = np.array([np.nan, 0.0, 0.0])
        assert not link.send_odometry(estimate(t), v_nan, np.eye(3), usec_autopilot=6_000_000)
        assert wait_for(lambda: len(peer.of("HEARTBEAT")) >= 1)
        time.sleep(0.2)
    assert len(peer.of("VISION_POSITION_ESTIMATE")) == 1 and not peer.of("ODOMETRY")
    assert link.refused[REFUSE_NON_FINITE] == 4 and link.refused[REFUSE_NOT_OK] == 2


def test_odometry_frames_and_quaternion(peer: UdpPeer) -> None:
    link = MavlinkLink(MavlinkOptions(connection=f"udpout:127.0.0.1:{peer.port}"))
    est = estimate(1_700_000_000_000_000, reset_counter=2, quality=0.8)
    with link:
        assert link.send_odometry(est, np.array([1.0, 0.5, -0.1]), np.eye(3) * 0.04, usec_autopilot=9_000_000)
        assert wait_for(lambda: peer.of("ODOMETRY"))
    odo = peer.of("ODOMETRY")[0]
    # ArduPilot ignores ODOMETRY on any other frame pair; PX4 takes LOCAL_FRD as vision.
    assert odo.frame_id == mav2.MAV_FRAME_LOCAL_FRD and odo.child_frame_id == mav2.MAV_FRAME_BODY_FRD
    np.testing.assert_allclose(rpy_from_quaternion(odo.q), est.rpy_rad, atol=1e-6)
    np.testing.assert_allclose([odo.vx, odo.vy, odo.vz], [1.0, 0.5, -0.1], rtol=1e-6)
    assert odo.velocity_covariance[0] == pytest.approx(0.04) and odo.reset_counter == 2 and odo.quality == 80


def test_parses_autopilot_messages_in_si_units(peer: UdpPeer) -> None:
    got: dict[str, list[Any]] = {"att": [], "imu": [], "alt": [], "origin": []}
    cbs = LinkCallbacks(
        on_attitude=got["att"].append,
        on_imu=got["imu"].append,
        on_altimeter=got["alt"].append,
        on_origin=got["origin"].append,
    )
    link = MavlinkLink(MavlinkOptions(connection=f"udpout:127.0.0.1:{peer.port}"), callbacks=cbs)
    m = peer.mav
    with link:
        assert wait_for(lambda: peer.addr is not None)
        peer.send(m.heartbeat_encode(2, 3, 0, 0, 3))
        peer.send(m.attitude_encode(1000, 0.1, -0.2, 0.3, 0, 0, 0))
        peer.send(m.scaled_imu_encode(1010, 0, 500, -1000, 100, -200, 300, 0, 0, 0))
        peer.send(m.highres_imu_encode(1020_000, 0.1, 0.2, -9.7, 0.01, 0.02, 0.03, 0, 0, 0, 0, 0, 0, 0, 63))
        peer.send(
            m.distance_sensor_encode(1030, 20, 4000, 1234, 0, 0, mav2.MAV_SENSOR_ROTATION_PITCH_270, 255)
        )
        peer.send(m.distance_sensor_encode(1031, 20, 4000, 777, 0, 1, mav2.MAV_SENSOR_ROTATION_NONE, 255))
        peer.send(
            m.distance_sensor_encode(1032, 20, 4000, 4001, 0, 0, mav2.MAV_SENSOR_ROTATION_PITCH_270, 255)
        )
        peer.send(m.gps_global_origin_encode(-147_000_000, 1_374_000_000, 250_500, 0))
        peer.send(m.local_position_ned_encode(1040, 1.0, 2.0, -30.0, 0.1, 0.2, 0.0))
        other = mav2.MAVLink(None, srcSystem=255, srcComponent=190)  # a GCS: not our autopilot
        assert peer.addr is not None
        peer.sock.sendto(other.attitude_encode(1050, 9, 9, 9, 0, 0, 0).pack(other), peer.addr)
        assert wait_for(lambda: link.local_position is not None)
        time.sleep(0.1)
    assert link.state is LinkState.UP or link.autopilot_heartbeat is not None
    assert len(got["att"]) == 1 and got["att"][0].roll_rad == pytest.approx(0.1)
    scaled, highres = got["imu"]
    np.testing.assert_allclose(scaled.accel_mps2, [0.0, 0.5 * 9.80665, -9.80665], rtol=1e-6)
    np.testing.assert_allclose(scaled.gyro_rps, [0.1, -0.2, 0.3], rtol=1e-6)
    np.testing.assert_allclose(highres.accel_mps2, [0.1, 0.2, -9.7], rtol=1e-6)
    assert [a.range_m for a in got["alt"]] == [12.34]  # the forward-looking and the out-of-range one dropped
    origin = got["origin"][0]
    assert origin.lat_deg == pytest.approx(-14.7) and origin.lon_deg == pytest.approx(137.4)
    assert origin.alt_m == pytest.approx(250.5)
    assert link.local_position is not None
    np.testing.assert_allclose(link.local_position.p_ned_m, [1, 2, -30])
    assert link.ignored_sources == 1
    # Stamps are in the companion clock (Unix us): arrival time while not synced.
    assert abs(got["att"][0].stamp_us - time.time_ns() // 1000) < 5_000_000


@pytest.mark.parametrize(
    ("autopilot", "first"),
    [(mav2.MAV_AUTOPILOT_ARDUPILOTMEGA, "RAW_IMU"), (mav2.MAV_AUTOPILOT_PX4, "SCALED_IMU2")],
)
def test_one_imu_stream_feeds_the_estimator(peer: UdpPeer, autopilot: int, first: str) -> None:
    """ArduPilot's default sensor stream: RAW_IMU (its first IMU, in milli-g and milli-rad/s) beside
    SCALED_IMU2 (the second IMU). Only the better stream goes on; the other takes over once the better one
    has stopped. Another autopilot's RAW_IMU is raw sensor counts and is never read."""
    got: list[Any] = []
    opts = MavlinkOptions(
        connection=f"udpout:127.0.0.1:{peer.port}", imu_source_hold_s=0.3, read_params=False
    )
    link = MavlinkLink(opts, callbacks=LinkCallbacks(on_imu=got.append))
    m = peer.mav
    with link:
        assert wait_for(lambda: peer.addr is not None)
        peer.send(m.heartbeat_encode(mav2.MAV_TYPE_QUADROTOR, autopilot, 0, 0, 3))
        assert wait_for(lambda: link.flavour is not None)
        for i in range(5):
            peer.send(m.raw_imu_encode(2_000_000 + 20_000 * i, 0, 500, -1000, 100, -200, 300, 0, 0, 0))
            peer.send(m.scaled_imu2_encode(2_000 + 20 * i, 10, 10, -990, 1, 2, 3, 0, 0, 0))
        assert wait_for(lambda: link.received.get("SCALED_IMU2", 0) == 5)
        assert wait_for(lambda: link.received.get("RAW_IMU", 0) == 5)
        time.sleep(0.05)
        assert link.imu_source == first and len(got) == 5
        assert link.imu_not_used == (5 if first == "RAW_IMU" else 0)
        if first == "RAW_IMU":
            for s in got:
                np.testing.assert_allclose(s.accel_mps2, [0.0, 0.5 * 9.80665, -9.80665], rtol=1e-6)
                np.testing.assert_allclose(s.gyro_rps, [0.1, -0.2, 0.3], rtol=1e-6)
            time.sleep(0.4)  # RAW_IMU has stopped: the second IMU takes over
            peer.send(m.scaled_imu2_encode(2_200, 10, 10, -990, 1, 2, 3, 0, 0, 0))
            assert wait_for(lambda: len(got) == 6)
            assert link.imu_source == "SCALED_IMU2" and link.status()["imu_source"] == "SCALED_IMU2"
    np.testing.assert_allclose(got[-1].accel_mps2, np.array([10, 10, -990]) * 9.80665e-3, rtol=1e-6)


def test_ardupilot_raw_imu_stream_reaches_the_estimator_in_si_units() -> None:
    """The simulated autopilot streaming only RAW_IMU, as ArduPilot's SRn_RAW_SENS does: the link reads it
    as the IMU, at hover -1 g along body down, stamped in the companion's clock once synced."""
    sim, link = make_pair(offset_us=50_000_000, sim_opts=with_imu_message(SimAutopilotOptions(), "raw"))
    got: list[Any] = []
    link.callbacks.on_imu = got.append
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.timesync.synced, 5.0)
        n0 = len(got)
        assert wait_for(lambda: len(got) > n0 + 20, 5.0)
        now = time.time_ns() // 1000
    finally:
        link.stop()
        sim.stop()
    assert link.imu_source == "RAW_IMU" and not sim.options.highres_imu_hz
    late = got[n0:]
    acc = np.array([s.accel_mps2 for s in late])
    assert abs(acc[:, 2].mean() + 9.80665) < 0.3 and np.abs(acc[:, :2].mean(axis=0)).max() < 0.3
    stamps = np.array([s.stamp_us for s in late])
    assert np.all(np.diff(stamps) > 0) and abs(int(stamps[-1]) - now) < 200_000
    assert 0.01 < np.median(np.diff(stamps)) * 1e-6 < 0.03  # 50 Hz


@pytest.mark.parametrize("hz", [0.0, 40.0])
def test_the_link_asks_a_silent_autopilot_for_its_imu(hz: float) -> None:
    """An autopilot that streams no IMU on the companion's link (ArduPilot with SRn_RAW_SENS 0): asked with
    MAV_CMD_SET_MESSAGE_INTERVAL, it starts sending RAW_IMU at the rate asked; a link told not to ask gets
    nothing."""
    silent = with_imu_message(SimAutopilotOptions(), "none")
    sim, link = make_pair(sim_opts=silent, link_opts={"request_imu_hz": hz, "imu_request_after_s": 0.5})
    got: list[Any] = []
    link.callbacks.on_imu = got.append
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.flavour == "ardupilot", 5.0)
        if hz:
            assert wait_for(lambda: len(got) > 40, 5.0)
        else:
            time.sleep(1.5)
    finally:
        link.stop()
        sim.stop()
    if hz:
        assert link.imu_requests >= 1 and link.imu_request_result == "ACCEPTED"  # a retry under load
        assert sim.rate_overrides == {"raw_imu": 40.0} and link.imu_source == "RAW_IMU"
        assert abs(np.mean([s.accel_mps2[2] for s in got]) + 9.80665) < 0.3
    else:
        assert not got and link.imu_requests == 0 and not sim.rate_overrides


def test_signed_link_refuses_unsigned_and_accepts_signed() -> None:
    unsigned_peer, signed_peer = UdpPeer(), UdpPeer(key=KEY)
    try:
        for p, expect in ((unsigned_peer, 0), (signed_peer, 1)):
            got: list[Any] = []
            opts = MavlinkOptions(connection=f"udpout:127.0.0.1:{p.port}", signing_key=KEY)
            link = MavlinkLink(opts, callbacks=LinkCallbacks(on_attitude=got.append))
            with link:
                assert wait_for(partial(p.of, "HEARTBEAT"))
                p.send(p.mav.attitude_encode(1000, 0.1, 0.2, 0.3, 0, 0, 0))
                time.sleep(0.3)
            assert len(got) == expect
            assert p.of("HEARTBEAT")[0]._signed or p.mav.signing.secret_key is None
            if expect == 0:
                assert link.codec.signing_counters["rejected"] >= 1
    finally:
        unsigned_peer.close()
        signed_peer.close()
    # The plain peer without a key cannot check, but sees the signature flag on the wire.
    raw = unsigned_peer.of("HEARTBEAT")[0].get_msgbuf()
    assert raw[2] & mav2.MAVLINK_IFLAG_SIGNED


# --- against the simulated autopilot ------------------------------------------------------------------
def make_pair(
    offset_us: int = 7_000_000, link_opts: dict | None = None, sim_opts: SimAutopilotOptions | None = None
):
    port = free_port()
    sim = SimAutopilotLink(
        f"udpin:127.0.0.1:{port}", clock_offset_us=offset_us, rng=np.random.default_rng(3), options=sim_opts
    )
    opts = MavlinkOptions(connection=f"udpout:127.0.0.1:{port}", **(link_opts or {}))
    return sim, MavlinkLink(opts)


def test_timesync_converges_and_frames_map_by_own_stamp() -> None:
    sim, link = make_pair(offset_us=123_456_789)
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.timesync.synced, 5.0)
        time.sleep(1.0)
        assert link.timesync.offset_us is not None
        assert abs(link.timesync.offset_us - sim.true_offset_us()) < 2_000
        # Frames captured every 50 ms; some dropped, one sent late: each keeps its own mapping.
        now = time.time_ns() // 1000
        stamps = [now - 300_000 + 50_000 * i for i in range(6)]
        order = [stamps[0], stamps[2], stamps[3], stamps[5]]  # 1 and 4 dropped
        for s in order:
            assert link.send_estimate(estimate(s)) is None
            time.sleep(0.06)
        assert wait_for(lambda: len(sim.accepted()) == len(order))
    finally:
        link.stop()
        sim.stop()
    true_offset = sim.true_offset_us()
    for rec, s in zip(sim.accepted(), order):
        assert abs(rec.usec - (s + true_offset)) < 2_000
    assert sim.heartbeats_from.get((1, 197), 0) >= 1


def test_signing_end_to_end_with_sim() -> None:
    signed = SimAutopilotOptions(signing_key=KEY)
    for link_key, expect_records in ((KEY, True), (None, False)):
        sim, link = make_pair(sim_opts=signed, link_opts={"signing_key": link_key})
        sim.start()
        link.start()
        try:
            if link_key is not None:
                assert wait_for(partial(getattr, link.timesync, "synced"), 5.0)
                assert link.send_estimate(estimate(time.time_ns() // 1000 - 20_000)) is None
                assert wait_for(sim.accepted, 3.0)
            else:
                time.sleep(1.0)
                link.send_estimate(estimate(time.time_ns() // 1000), usec_autopilot=sim.boot_us())
                time.sleep(0.3)
                assert not link.timesync.synced  # the sim refuses our unsigned TIMESYNC too
        finally:
            link.stop()
            sim.stop()
        assert bool(sim.accepted()) is expect_records
        if not expect_records:
            assert sim.codec.signing_counters["rejected"] >= 2


def _read_tlog(path: Path) -> list[Any]:
    """Every message of a .tlog as pymavlink's own reader gives it (``_timestamp``: the logged time, s)."""
    from pymavlink import mavutil

    mlog = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    out = []
    while (m := mlog.recv_match()) is not None:
        if m.get_type() != "BAD_DATA":
            out.append(m)
    mlog.close()
    return out


def test_the_link_logs_both_directions_as_a_tlog_pymavlink_reads(tmp_path: Path) -> None:
    sim, link = make_pair(link_opts={"tlog": str(tmp_path / "logs" / "flight-{time}")})
    assert link.tlog is not None and link.tlog.path.parent == tmp_path / "logs"
    assert link.tlog.path.name.startswith("flight-2") and link.tlog.path.suffix == ".tlog"
    t0 = time.time()
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.timesync.synced, 5.0)
        stamps = [time.time_ns() // 1000 - 300_000 + 50_000 * i for i in range(3)]
        for i, s in enumerate(stamps):
            assert link.send_estimate(estimate(s, p=np.array([1.0 + i, 2.0, -30.0]))) is None
            time.sleep(0.05)
        assert wait_for(lambda: len(sim.accepted()) == 3)
        assert wait_for(lambda: link.received.get("HEARTBEAT", 0) >= 1, 3.0)
        received_attitudes = link.received.get("ATTITUDE", 0)
    finally:
        link.stop()
        sim.stop()
    t1 = time.time()
    msgs = _read_tlog(link.tlog.path)
    assert len(msgs) == link.tlog.status()["messages"] > 0 and link.tlog.errors == 0
    ours = [m for m in msgs if (m.get_srcSystem(), m.get_srcComponent()) == (1, 197)]
    theirs = [m for m in msgs if (m.get_srcSystem(), m.get_srcComponent()) == (1, 1)]
    # what we sent, as sent
    vpe = [m for m in ours if m.get_type() == "VISION_POSITION_ESTIMATE"]
    assert [round(m.x, 3) for m in vpe] == [1.0, 2.0, 3.0]
    assert [m.usec for m in vpe] == [r.usec for r in sim.accepted()]
    assert {"HEARTBEAT", "TIMESYNC"} <= {m.get_type() for m in ours}
    # what the autopilot said, every message of it the link took in (stopping may cut the last ones off)
    assert len([m for m in theirs if m.get_type() == "ATTITUDE"]) >= received_attitudes > 10
    assert {"HEARTBEAT", "TIMESYNC", "SYSTEM_TIME"} <= {m.get_type() for m in theirs}
    # the times are the wall clock's, in order
    ts = [m._timestamp for m in msgs]
    assert t0 - 0.01 <= ts[0] and ts[-1] <= t1 + 0.01
    assert all(b >= a for a, b in zip(ts, ts[1:]))  # two threads write, stamped in turn


def test_a_tlog_the_disk_refuses_is_given_up_and_the_link_goes_on(tmp_path: Path) -> None:
    (tmp_path / "full.tlog").symlink_to("/dev/full")  # every flush fails with ENOSPC, as a full card does
    sim, link = make_pair(link_opts={"tlog": str(tmp_path / "full.tlog"), "tlog_flush_s": 0.1})
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.timesync.synced, 5.0)
        assert wait_for(lambda: link.tlog is not None and link.tlog.errors > 0, 3.0)
        assert link.send_estimate(estimate(time.time_ns() // 1000 - 20_000)) is None
        assert wait_for(lambda: len(sim.accepted()) == 1)
        assert link.status()["tlog"]["errors"] == 1  # reported once, then not written to any more
        assert link.thread_errors == 0
    finally:
        link.stop()
        sim.stop()


def test_a_tlog_path_that_cannot_be_created_fails_at_start(tmp_path: Path) -> None:
    (tmp_path / "a_file").write_text("")
    with pytest.raises(OSError):
        MavlinkLink(MavlinkOptions(connection="udpout:127.0.0.1:9", tlog=str(tmp_path / "a_file" / "x")))


def test_autopilot_reboot_is_detected_and_sync_restarts() -> None:
    sim, link = make_pair(offset_us=600_000_000)
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.timesync.synced, 5.0)
        before = link.timesync.offset_us
        assert not link.consume_reset()
        sim.reboot()
        assert wait_for(lambda: link.resets, 5.0)
        assert link.consume_reset()
        assert wait_for(
            lambda: link.timesync.synced and abs(link.timesync.offset_us - sim.true_offset_us()) < 2_000
        )
        assert before - link.timesync.offset_us > 500_000_000  # the boot clock restarted at 0
        # After the reboot the old, higher timestamps do not block new estimates.
        assert link.send_estimate(estimate(time.time_ns() // 1000 - 20_000)) is None
        assert wait_for(lambda: sim.accepted(), 3.0)
        time.sleep(1.0)  # let every sign of the reboot arrive (SYSTEM_TIME, TIMESYNC, heartbeat)
    finally:
        link.stop()
        sim.stop()
    assert set(link.resets) <= {"system_time", "timesync_jump", "heartbeat_gap"}
    assert link.reboots == 1, (link.reboots, link.resets)  # one reboot, reset_counter moved once


def test_one_reboot_moves_reset_counter_once_though_it_shows_several_signs() -> None:
    # A reboot that takes longer than the link timeout shows as a heartbeat gap AND a restarted boot clock.
    sim, link = make_pair(offset_us=600_000_000, link_opts={"link_timeout_s": 0.5, "stale_after_s": 0.3})
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.timesync.synced, 5.0)
        sim.reboot(boot_silence_s=1.2)
        assert wait_for(lambda: sum(link.resets.values()) >= 2, 6.0), link.resets
        assert wait_for(lambda: link.timesync.synced, 5.0)
        time.sleep(0.5)
    finally:
        link.stop()
        sim.stop()
    assert link.reboots == 1, (link.reboots, link.resets)


def test_link_state_goes_stale_then_down_when_autopilot_stops() -> None:
    sim, link = make_pair(link_opts={"stale_after_s": 0.4, "link_timeout_s": 0.9})
    sim.start()
    link.start()
    try:
        assert link.state is LinkState.DOWN
        assert wait_for(lambda: link.state is LinkState.UP, 3.0)
        sim.stop()
        assert wait_for(lambda: link.state is LinkState.STALE, 2.0)
        assert wait_for(lambda: link.state is LinkState.DOWN, 2.0)
    finally:
        link.stop()
        sim.stop()


# --- serial (pty) and TCP: both directions, cut and restore ---------------------------------------------
class PtyPeer:
    """The autopilot end of a pty pair: pymavlink on the master fd; the slave is reached via a symlink."""

    def __init__(self, link_path: Path) -> None:
        self.master, slave = os.openpty()
        self.slave_name = os.ttyname(slave)
        os.close(slave)  # pyserial opens it by name
        tmp = link_path.with_suffix(".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(self.slave_name)
        os.replace(tmp, link_path)  # like udev re-creating /dev/serial/by-id/... after a replug
        self.mav = mav2.MAVLink(None, srcSystem=1, srcComponent=1)
        self.mav.robust_parsing = True
        self.msgs: list[Any] = []

    def pump(self, duration_s: float) -> None:
        end = time.monotonic() + duration_s
        while time.monotonic() < end:
            try:
                os.set_blocking(self.master, False)
                data = os.read(self.master, 4096)
            except (BlockingIOError, OSError):
                time.sleep(0.01)
                continue
            self.msgs.extend(m for m in self.mav.parse_buffer(data) or [] if m.get_type() != "BAD_DATA")

    def send(self, msg: Any) -> None:
        os.write(self.master, msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256

    def close(self) -> None:
        os.close(self.master)


def test_serial_pty_both_directions_and_replug() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        dev = Path(tmp) / "ttyAUTOPILOT"
        pty = PtyPeer(dev)
        got: list[Any] = []
        opts = MavlinkOptions(connection=f"serial:{dev}:921600", backoff=FAST_BACKOFF)
        link = MavlinkLink(opts, callbacks=LinkCallbacks(on_attitude=got.append))
        with link:
            pty.pump(1.2)
            assert any(m.get_type() == "HEARTBEAT" for m in pty.msgs)  # companion -> autopilot
            pty.send(pty.mav.attitude_encode(100, 0.1, 0.2, 0.3, 0, 0, 0))
            assert wait_for(lambda: len(got) == 1, 2.0)  # autopilot -> companion
            pty.close()  # unplugged
            assert wait_for(lambda: link.transport.stats.drops == 1, 2.0)
            time.sleep(0.3)  # the device is gone for a while: reopen attempts fail and back off
            pty = PtyPeer(dev)  # plugged back (a new pty behind the same path)
            assert wait_for(lambda: link.transport.stats.reconnects == 1, 3.0)
            pty.msgs.clear()
            pty.pump(1.2)
            pty.send(pty.mav.attitude_encode(200, 0.4, 0.5, 0.6, 0, 0, 0))
            assert wait_for(lambda: len(got) == 2, 2.0)
        pty.close()
        assert any(m.get_type() == "HEARTBEAT" for m in pty.msgs)
        assert got[1].roll_rad == pytest.approx(0.4)
        assert link.transport.stats.open_failures >= 1 and link.thread_errors == 0


def test_tcp_client_reconnects_after_server_restart() -> None:
    port = free_port(socket.SOCK_STREAM)
    got: list[Any] = []
    opts = MavlinkOptions(connection=f"tcp:127.0.0.1:{port}", backoff=FAST_BACKOFF)
    link = MavlinkLink(opts, callbacks=LinkCallbacks(on_attitude=got.append))
    peer_mav = mav2.MAVLink(None, srcSystem=1, srcComponent=1)

    def serve_once(n: int) -> bytes:
        with socket.create_server(("127.0.0.1", port)) as srv:
            srv.settimeout(3.0)
            conn, _ = srv.accept()
            with conn:
                conn.settimeout(2.0)
                data = conn.recv(4096)  # the link introduces itself with a heartbeat on connecting
                conn.sendall(peer_mav.attitude_encode(n, 0.1 * n, 0, 0, 0, 0, 0).pack(peer_mav))
                assert wait_for(lambda: len(got) == n, 2.0)
        return data

    with link:
        first = serve_once(1)  # the link was retrying while no server existed
        second = serve_once(2)  # server went away and came back
    parse = mav2.MAVLink(None)
    assert any(m.get_type() == "HEARTBEAT" for m in parse.parse_buffer(first) or [])
    assert second
    assert link.transport.stats.reconnects == 1 and link.transport.stats.drops in (1, 2)


def test_udpin_answers_last_sender() -> None:
    port = free_port()
    server = open_transport(f"udpin:127.0.0.1:{port}")
    assert server.read(0.01) == b"" and not server.write(b"x")  # no peer yet: dropped, counted
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.settimeout(1.0)
    try:
        client.sendto(b"hello", ("127.0.0.1", port))
        assert wait_for(lambda: server.read(0.05) == b"hello" or server.stats.bytes_in == 5, 2.0)
        assert server.write(b"back")
        assert client.recvfrom(100)[0] == b"back"
    finally:
        client.close()
        server.close()
    assert server.stats.writes_dropped == 1


def test_bad_connection_strings() -> None:
    for bad in ("udp:nohost", "tcp:1.2.3.4:99999", "carrier-pigeon:x", "serial:"):
        with pytest.raises(ValueError):
            open_transport(bad)
    assert open_transport("serial:/dev/ttyACM0", baudrate=57600).description == "serial:/dev/ttyACM0:57600"


def test_timesync_options_are_used() -> None:
    link = MavlinkLink(MavlinkOptions(timesync=TimeSyncOptions(max_rtt_us=1234)))
    assert link.timesync.options.max_rtt_us == 1234
    link.transport.close()


def test_tcp_link_to_sim_tcp_server() -> None:
    port = free_port(socket.SOCK_STREAM)
    sim = SimAutopilotLink(f"tcpin:127.0.0.1:{port}", rng=np.random.default_rng(4))
    link = MavlinkLink(MavlinkOptions(connection=f"tcp:127.0.0.1:{port}", backoff=FAST_BACKOFF))
    sim.start()
    link.start()
    try:
        assert wait_for(lambda: link.timesync.synced and link.state is LinkState.UP, 5.0)
        assert link.send_estimate(estimate(time.time_ns() // 1000 - 20_000)) is None
        assert wait_for(lambda: sim.accepted(), 3.0)
        assert link.send_set_gps_global_origin(-14.5, 137.25, -2500.0)
        assert wait_for(lambda: link.origin is not None, 3.0)  # the sim confirms with GPS_GLOBAL_ORIGIN
    finally:
        link.stop()
        sim.stop()
    assert link.timesync.offset_us is not None
    assert abs(link.timesync.offset_us - sim.true_offset_us()) < 2_000
    assert link.origin is not None and link.origin.lat_deg == pytest.approx(-14.5)
    assert link.origin.alt_m == pytest.approx(-2500.0)
