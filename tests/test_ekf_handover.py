"""How the ``vis_thermal_ekf`` estimator starts and orders its inputs on the daemon's path: the hand-over from
the autopilot's own navigation (LOCAL_POSITION_NED, ATTITUDE) and IMU / altimeter samples that the daemon
delivers before a frame set although they were stamped after it (processing running late)."""

from __future__ import annotations

import numpy as np

from companion.constants import GRAVITY_MPS2, R_BODY_CAM_NADIR
from companion.ekf.features import Detections
from companion.ekf.options import EkfOptions
from companion.estimators.vis_thermal_ekf import VisThermalEkfEstimator
from companion.geometry import CameraIntrinsics
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


def test_starts_from_the_autopilots_position_and_velocity_once_it_has_one() -> None:
    est = estimator()
    t0 = 10_000_000
    est.on_attitude(AttitudeSample(t0 - 20_000, 0.01, -0.02, 0.7))
    assert est.on_detections(t0, {"visible": NONE}) is None
    assert est.counters["waiting_for_position"] == 1 and not est.slam.started
    v = np.array([1.2, -0.4, 0.1])
    est.on_local_position(LocalPositionSample(t0 + 400_000, np.array([-100.0, -30.0, -128.0]), v))
    t1 = t0 + 500_000
    est.on_detections(t1, {"visible": NONE})
    assert est.slam.started
    pose = est.slam.pose(t1)
    # the autopilot's position carried forward to the frame's stamp with its velocity (0.1 s)
    np.testing.assert_allclose(pose.p_world, [-99.88, -30.04, -127.99], atol=1e-6)
    np.testing.assert_allclose(pose.v_world, v, atol=1e-9)
    np.testing.assert_allclose(pose.rpy_rad, [0.01, -0.02, 0.7], atol=1e-9)


def test_a_configured_start_wins_and_stale_autopilot_positions_are_not_used() -> None:
    est = estimator(np.array([5.0, 6.0, -50.0]))
    t0 = 3_000_000
    est.on_local_position(LocalPositionSample(t0 - 2_000_000, np.zeros(3), np.array([3.0, 0.0, 0.0])))
    est.on_detections(t0, {"visible": NONE})
    pose = est.slam.pose(t0)
    np.testing.assert_allclose(pose.p_world, [5.0, 6.0, -50.0])
    np.testing.assert_allclose(pose.v_world, np.zeros(3))  # 2 s old: the velocity is not used either


def test_samples_stamped_after_a_late_frame_set_wait_for_it() -> None:
    est = estimator()
    t0 = 1_000_000
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
    assert est.counters["imu_samples"] == 50 and est.counters["late_imu"] == 0
    # the rest are given with the next frame set (those up to its stamp)
    est.on_detections(t1 + 500_000, {"visible": NONE})
    assert est.counters["imu_samples"] == 100 and est.slam.t_us == t1 + 500_000
