"""How the ``vis_thermal_ekf`` estimator starts and orders its inputs on the daemon's path: the hand-over from
the autopilot's own navigation (LOCAL_POSITION_NED, ATTITUDE) and IMU / altimeter samples that the daemon
delivers before a frame set although they were stamped after it (processing running late)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from companion.constants import GRAVITY_MPS2, R_BODY_CAM_NADIR
from companion.ekf.features import Detections
from companion.ekf.options import EkfOptions
from companion.estimators.vis_thermal_ekf import VisThermalEkfEstimator, start_attitude
from companion.geometry import CameraIntrinsics, rot_from_rpy, rpy_from_rot
from companion.types import AltimeterSample, AttitudeSample, ImuSample, LocalPositionSample

G = GRAVITY_MPS2["europa"]
NONE = Detections(np.zeros((0, 2)), np.zeros((0, 128), np.float32))


def estimator(p0: np.ndarray | None = None) -> VisThermalEkfEstimator:
    intr = CameraIntrinsics(640, 480, 554.3, 554.3, 319.5, 239.5)
    return VisThermalEkfEstimator(
        EkfOptions(mode="visible"), {"visible": intr}, {"visible": R_BODY_CAM_NADIR}, p0, gravity_mps2=G
    )


def imu(t_us: int) -> ImuSample:
    # level, unaccelerated flight: the accelerometer reads -g along body z
    return ImuSample(t_us, np.array([0.0, 0.0, -G]), np.zeros(3))


def attitude_second(est: VisThermalEkfEstimator, t_end_us: int, yaw: float = 0.0) -> None:
    """A second of the autopilot's ATTITUDE at 50 Hz, level with heading ``yaw``, up to ``t_end_us``, and its IMU
    at ``t_end_us`` (a start waits for both)."""
    for t in range(t_end_us - 1_000_000, t_end_us + 1, 20_000):
        est.on_attitude(AttitudeSample(t, 0.0, 0.0, yaw))
    est.on_imu(imu(t_end_us))


def test_starts_from_the_autopilots_position_and_velocity_once_it_has_one() -> None:
    est = estimator()
    t0 = 10_000_000
    for t in range(
        t0 - 1_020_000, t0, 20_000
    ):  # the autopilot's attitude and IMU, streaming before the frames
        est.on_attitude(AttitudeSample(t, 0.01, -0.02, 0.7))
        est.on_imu(imu(t))
    assert est.on_detections(t0, {"visible": NONE}) is None
    assert est.counters["waiting_for_position"] == 1 and not est.slam.started
    assert est.warnings["start"] == "not started: waiting for LOCAL_POSITION_NED"  # on the status line
    v = np.array([1.2, -0.4, 0.1])
    est.on_local_position(LocalPositionSample(t0 + 400_000, np.array([-100.0, -30.0, -128.0]), v))
    t1 = t0 + 500_000
    est.on_detections(t1, {"visible": NONE})
    assert est.slam.started and "start" not in est.warnings
    pose = est.slam.pose(t1)
    # the autopilot's position carried forward to the frame's stamp with its velocity (0.1 s)
    np.testing.assert_allclose(pose.p_world, [-99.88, -30.04, -127.99], atol=1e-6)
    np.testing.assert_allclose(pose.v_world, v, atol=1e-9)
    np.testing.assert_allclose(pose.rpy_rad, [0.01, -0.02, 0.7], atol=1e-9)


def test_a_configured_start_wins_and_stale_autopilot_positions_are_not_used() -> None:
    est = estimator(np.array([5.0, 6.0, -50.0]))
    t0 = 3_000_000
    attitude_second(est, t0)
    est.on_local_position(LocalPositionSample(t0 - 2_000_000, np.zeros(3), np.array([3.0, 0.0, 0.0])))
    est.on_detections(t0, {"visible": NONE})
    pose = est.slam.pose(t0)
    np.testing.assert_allclose(pose.p_world, [5.0, 6.0, -50.0])
    np.testing.assert_allclose(pose.v_world, np.zeros(3))  # 2 s old: the velocity is not used either


def test_samples_stamped_after_a_late_frame_set_wait_for_it() -> None:
    est = estimator()
    t0 = 1_000_000
    attitude_second(est, t0)
    est.on_local_position(LocalPositionSample(t0, np.array([0.0, 0.0, -60.0]), np.zeros(3)))
    est.on_detections(t0, {"visible": NONE})
    # the next frame set is processed 600 ms late: the daemon hands over the IMU (100 Hz) and altimeter
    # samples up to then first, 60 of them stamped after the frame's capture
    t1 = t0 + 500_000
    for t in range(t0 + 10_000, t1 + 600_000, 10_000):
        est.on_imu(imu(t))
        if t % 100_000 == 0:
            est.on_altimeter(AltimeterSample(t, 60.0))
    assert est.slam.t_us == t0, "samples went to the filter before the frame set older than them"
    est.on_detections(t1, {"visible": NONE})
    assert est.slam.t_us == t1 and est.counters["stale_frames"] == 0
    assert est.counters["imu_samples"] == 51 and est.counters["late_imu"] == 0  # and the one before the start
    # the rest are given with the next frame set (those up to its stamp)
    est.on_detections(t1 + 500_000, {"visible": NONE})
    assert est.counters["imu_samples"] == 101 and est.slam.t_us == t1 + 500_000


# -- the start's attitude: the autopilot's ATTITUDE samples averaged, carried to the frame by the gyro ---------
def _turning(t_s: float) -> np.ndarray:
    """R_world_body of a vehicle yawing at 0.3 rad/s while it rolls and pitches (a few degrees)."""
    return rot_from_rpy(0.1 * np.sin(2.0 * t_s), 0.05 * np.cos(1.5 * t_s), 0.4 + 0.3 * t_s)


def _body_rate(t_s: float, h: float = 1e-5) -> np.ndarray:
    """(3,) FRD body rate of ``_turning`` at ``t_s`` (central difference of R^T dR)."""
    dR = _turning(t_s - h).T @ _turning(t_s + h)
    return Rotation.from_matrix(dR).as_rotvec() / (2 * h)


def _angle(rpy: np.ndarray | None, R_true: np.ndarray) -> float:
    assert rpy is not None
    return float((Rotation.from_matrix(rot_from_rpy(*rpy)).inv() * Rotation.from_matrix(R_true)).magnitude())


def _samples(
    rng: np.random.Generator, t0_us: int, t1_us: int, sigma: tuple[float, float, float]
) -> tuple[list[AttitudeSample], list[tuple[int, np.ndarray]]]:
    """ATTITUDE at 50 Hz with white noise (roll, pitch, yaw sigma, rad) and an exact gyro at 100 Hz."""
    att = []
    for t in range(t0_us, t1_us, 20_000):
        rpy = rpy_from_rot(_turning(t * 1e-6)) + rng.normal(0.0, 1.0, 3) * np.array(sigma)
        att.append(AttitudeSample(t, *(float(a) for a in rpy)))
    gyro = [(t, _body_rate(t * 1e-6)) for t in range(t0_us - 5_000, t1_us, 10_000)]
    return att, gyro


def test_the_start_attitude_is_the_autopilots_samples_carried_to_the_frame_by_the_gyro() -> None:
    rng = np.random.default_rng(0)
    t0, t1, stamp = 2_000_000, 4_000_000, 3_310_000
    att, gyro = _samples(rng, t0, t1, (0.0, 0.0, 0.0))
    R_true = _turning(stamp * 1e-6)
    # ~100 exact samples over +-1 s of a 0.3 rad/s turn: each carried to the stamp lands on the truth
    assert _angle(start_attitude(att, gyro, stamp, 1.0), R_true) < 1e-4
    # the nearest sample is 10 ms away, 3 mrad of turn; no gyro, or no window: that sample as it is
    near = min(att, key=lambda a: abs(a.stamp_us - stamp))
    for got in (start_attitude(att, [], stamp, 1.0), start_attitude(att, gyro, stamp, 0.0)):
        assert got is not None
        np.testing.assert_allclose(got, np.array([near.roll_rad, near.pitch_rad, near.yaw_rad]))
    # samples the gyro does not reach are left out, not carried blind (up to 0.1 s past its last stamp they are
    # carried at its last rate: 1.5e-4 rad here; without the cut, samples 0.7 s past it would be ~5 mrad off)
    assert _angle(start_attitude(att, gyro[:40], 2_300_000, 1.0), _turning(2.3)) < 5e-4
    assert start_attitude([], gyro, stamp, 1.0) is None


def test_averaging_shrinks_the_autopilots_attitude_jitter() -> None:
    # a converged EKF3's sample-to-sample jitter (the simulated autopilot's: 0.17 deg roll/pitch, 0.29 deg yaw)
    rng = np.random.default_rng(1)
    nearest, averaged = [], []
    for k in range(20):
        t0 = 1_000_000 + k * 3_000_000
        att, gyro = _samples(rng, t0, t0 + 2_000_000, (0.003, 0.003, 0.005))
        stamp = t0 + 1_500_000 + 7_000  # half a second of samples after the frame: processing runs late
        R_true = _turning(stamp * 1e-6)
        nearest.append(_angle(start_attitude(att, gyro, stamp, 0.0), R_true))
        averaged.append(_angle(start_attitude(att, gyro, stamp, 1.0), R_true))
    rms_near, rms_avg = np.sqrt(np.mean(np.square(nearest))), np.sqrt(np.mean(np.square(averaged)))
    # 75 samples: sqrt(75) ~ 8.7x less expected; asserted with a wide margin
    assert rms_avg < 0.3 * rms_near, (rms_avg, rms_near)


def test_the_estimator_starts_from_the_averaged_attitude() -> None:
    est = estimator()
    rng = np.random.default_rng(2)
    t0, stamp = 5_000_000, 6_200_000
    att, gyro = _samples(rng, t0, stamp + 300_000, (0.003, 0.003, 0.005))
    for a in att:
        est.on_attitude(a)
    for t, w in gyro:
        R = _turning(t * 1e-6)
        est.on_imu(ImuSample(t, R.T @ np.array([0.0, 0.0, -G]), w))
    est.on_local_position(LocalPositionSample(stamp - 50_000, np.array([0.0, 0.0, -60.0]), np.zeros(3)))
    est.on_detections(stamp, {"visible": NONE})
    assert est.slam.started
    got = est.slam.pose(stamp).rpy_rad
    R_true = _turning(stamp * 1e-6)
    # the latest sample, what the estimator used to start from, is 280 ms of turning (~5 deg) away
    assert _angle(np.array([att[-1].roll_rad, att[-1].pitch_rad, att[-1].yaw_rad]), R_true) > 0.05
    assert _angle(got, R_true) < 0.002


def test_a_start_without_a_second_of_attitude_waits_for_it_but_not_longer() -> None:
    # a replay whose record begins with the first frames: ATTITUDE from then on, frame sets at 2 Hz
    est = estimator()
    t0 = 20_000_000
    est.on_local_position(LocalPositionSample(t0, np.array([0.0, 0.0, -60.0]), np.zeros(3)))
    est.on_attitude(AttitudeSample(t0, 0.0, 0.0, 0.3))
    est.on_imu(imu(t0))
    sent = t0  # the newest ATTITUDE stamp given
    for k in range(3):
        stamp = t0 + k * 500_000
        while sent < stamp:  # 50 Hz up to the frame set's stamp
            sent += 20_000
            est.on_attitude(AttitudeSample(sent, 0.0, 0.0, 0.3))
            est.on_imu(imu(sent))
        est.on_detections(stamp, {"visible": NONE})
        assert est.slam.started == (k == 2)
    assert est.counters["waiting_for_attitude"] == 2 and est.counters["waiting_for_position"] == 0
    # an attitude stream that stops: the start waits a window after the first frame set, then takes what it has
    est = estimator()
    est.on_local_position(LocalPositionSample(t0, np.array([0.0, 0.0, -60.0]), np.zeros(3)))
    est.on_attitude(AttitudeSample(t0, 0.0, 0.0, 0.3))
    est.on_imu(imu(t0))
    for k in range(3):
        est.on_detections(t0 + k * 500_000, {"visible": NONE})
    assert est.slam.started and est.counters["waiting_for_attitude"] == 2
    np.testing.assert_allclose(est.slam.pose(t0 + 1_000_000).rpy_rad, [0.0, 0.0, 0.3], atol=1e-9)


def test_a_camera_up_before_the_autopilot_streams_waits_for_its_heading() -> None:
    # a configured start (GPS-denied take-off) whose camera sends frames before the autopilot's first ATTITUDE:
    # starting then would take the configured heading (0) for good, the cameras cannot correct it
    est = estimator(np.array([0.0, 0.0, -60.0]))
    t0 = 5_000_000
    for k in range(2):
        est.on_detections(t0 + k * 500_000, {"visible": NONE})
        assert not est.slam.started and est.warnings["start"] == "not started: waiting for ATTITUDE"
    # the autopilot streams from 0.7 s on, heading 2 rad: the start waits a second of it, then takes it
    for t in range(t0 + 700_000, t0 + 2_000_001, 20_000):
        est.on_attitude(AttitudeSample(t, 0.0, 0.0, 2.0))
        est.on_imu(imu(t))
        if (t - t0) % 500_000 == 0:
            est.on_detections(t, {"visible": NONE})
            assert est.slam.started == (t - t0 >= 1_700_000)
    assert est.counters["waiting_for_attitude"] == 4 and "start" not in est.warnings
    assert abs(est.slam.pose(t0 + 2_000_000).rpy_rad[2] - 2.0) < 1e-6


def test_with_no_attitude_at_all_it_starts_from_gravity_and_the_configured_heading_after_the_wait(
    caplog: pytest.LogCaptureFixture,
) -> None:
    intr = CameraIntrinsics(640, 480, 554.3, 554.3, 319.5, 239.5)
    est = VisThermalEkfEstimator(
        EkfOptions(mode="visible", start_wait_s=2.0),
        {"visible": intr},
        {"visible": R_BODY_CAM_NADIR},
        np.array([0.0, 0.0, -60.0]),
        gravity_mps2=G,
        initial_yaw_rad=0.5,
    )
    roll = 0.1  # the IMU's gravity, rolled: the accelerometer reads -g along body "up" rolled by 0.1 rad
    f = -G * np.array([0.0, np.sin(roll), np.cos(roll)])
    t0 = 5_000_000
    for k in range(6):
        stamp = t0 + k * 500_000
        for t in range(stamp - 490_000, stamp + 1, 10_000):  # 100 Hz up to the frame set
            est.on_imu(ImuSample(t, f, np.zeros(3)))
        est.on_detections(stamp, {"visible": NONE})
        assert est.slam.started == (k >= 4)  # 2 s after the first frame set
    assert est.counters["waiting_for_attitude"] == 4
    np.testing.assert_allclose(est.slam.pose(t0 + 2_500_000).rpy_rad, [roll, 0.0, 0.5], atol=1e-3)
    assert "no ATTITUDE from the autopilot 2 s after the first frames" in caplog.text


def test_a_start_without_the_imu_goes_ahead_on_the_motion_model() -> None:
    # ATTITUDE streams at once, the IMU (ArduPilot's RAW_IMU) only once the companion has asked for it: the start
    # does not wait for it (bench ekf_start: as accurate), it propagates on the motion model until it comes
    est = VisThermalEkfEstimator(
        EkfOptions(mode="visible"),
        {"visible": CameraIntrinsics(640, 480, 554.3, 554.3, 319.5, 239.5)},
        {"visible": R_BODY_CAM_NADIR},
        np.array([0.0, 0.0, -60.0]),
        gravity_mps2=G,
    )
    t0 = 5_000_000
    for t in range(t0 - 3_000_000, t0 + 1, 20_000):
        est.on_attitude(AttitudeSample(t, 0.0, 0.0, 0.3))
    est.on_detections(t0, {"visible": NONE})
    assert est.slam.started and est.warnings == {"imu": "NO IMU", "altimeter": "NO ALTIMETER"}
    est.on_detections(t0 + 500_000, {"visible": NONE})
    assert est.slam.counters.steps_without_imu == est.counters["steps_without_imu"] == 1  # in the status
    for t in range(t0 + 510_000, t0 + 1_000_001, 10_000):  # the IMU comes, 100 Hz
        est.on_imu(imu(t))
    est.on_detections(t0 + 1_000_000, {"visible": NONE})
    assert "imu" not in est.warnings and est.slam.counters.imu == 50
    np.testing.assert_allclose(est.slam.pose(t0 + 1_000_000).rpy_rad, [0.0, 0.0, 0.3], atol=1e-6)
