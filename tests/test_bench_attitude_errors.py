"""The attitude errors ``bench attitude_errors`` injects: an autopilot roll/pitch bias in every ATTITUDE
sample, and a camera mount the estimator is not told of unless calibrated (as the config would say)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.terrain_slam import FlightSpec, Simulation, gauss_markov
from companion.config import CameraConfig
from companion.constants import R_BODY_CAM_NADIR
from companion.estimators.terrain_lba import TerrainLbaOptions
from companion.geometry import rpy_from_rot


@pytest.fixture(scope="module")
def sim() -> Simulation:
    spec = FlightSpec(
        "08", "circular", 4.0, 0, tilt_bias_rad=(0.01, -0.004), mount_error_rpy_rad=(0.0, 0.02, 0.0)
    )
    return Simulation(spec)


def test_attitude_samples_carry_the_tilt_bias(sim: Simulation) -> None:
    rows = []
    for k, (_, att, _, frame) in enumerate(sim.samples()):
        true_rpy = rpy_from_rot(sim.states[k].R_world_body)
        rows.append([att.roll_rad - true_rpy[0], att.pitch_rad - true_rpy[1]])
        assert frame.image.shape == (480, 480)
    d = np.array(rows)
    # 60 samples with the simulated autopilot's 0.003 rad white noise: the mean is the bias within ~0.0004
    assert d.mean(axis=0) == pytest.approx([0.01, -0.004], abs=0.0015)


def test_true_mount_is_the_configs_composition_and_only_the_calibrated_estimator_gets_it(
    sim: Simulation,
) -> None:
    cfg = CameraConfig(key="uav/camera/nadir", extra_rpy_deg=(0.0, float(np.degrees(0.02)), 0.0))
    assert np.allclose(sim.R_body_cam_true, cfg.R_body_cam(), atol=1e-12)
    assert not np.allclose(sim.R_body_cam_true, R_BODY_CAM_NADIR, atol=1e-3)
    opts = TerrainLbaOptions()
    for known, R in ((False, R_BODY_CAM_NADIR), (True, sim.R_body_cam_true)):
        e = sim.estimator(opts, mount_known=known)
        try:
            assert np.allclose(e.R_body_cam, R, atol=1e-12)
        finally:
            e.close()


def test_compass_bias_is_on_the_initial_yaw_and_every_sample_and_leaves_the_draws_alone() -> None:
    drawn = Simulation(FlightSpec("01", "circular", 2.0, 0))
    fixed = Simulation(FlightSpec("01", "circular", 2.0, 0, yaw_bias_rad=0.09))
    true_yaw0 = rpy_from_rot(fixed.states[0].R_world_body)[2]
    assert fixed.yaw0 == pytest.approx(true_yaw0 + 0.09, abs=1e-12)
    a = [att for _, att, _, _ in drawn.samples()]
    b = [att for _, att, _, _ in fixed.samples()]
    # the same noise draws: only the yaw moves, by the difference of the biases
    assert [x.roll_rad for x in a] == [x.roll_rad for x in b]
    dyaw = np.array([y.yaw_rad - x.yaw_rad for x, y in zip(a, b)])
    assert np.allclose(dyaw, 0.09 - drawn.yaw_bias, atol=1e-12)


def test_tilt_wander_is_a_gauss_markov_error_and_leaves_the_draws_alone() -> None:
    """Known answer for the process (stationary sigma, correlation e^-1 one time constant apart), and the
    flight's own noise draws unchanged: the roll/pitch samples differ from the plain flight's by the
    wander alone."""
    x = gauss_markov(150_000, 1.0 / 15.0, 0.0035, 10.0, seed=3)
    assert x.std(axis=0) == pytest.approx([0.0035, 0.0035], rel=0.1)
    lag = 150  # 10 s at 15 Hz
    assert np.corrcoef(x[:-lag, 0], x[lag:, 0])[0, 1] == pytest.approx(np.exp(-1.0), abs=0.06)
    assert not gauss_markov(10, 0.1, 0.0, 10.0, seed=3).any()
    plain = Simulation(FlightSpec("01", "circular", 2.0, 0))
    wander = Simulation(FlightSpec("01", "circular", 2.0, 0, tilt_wander_rad=0.004, tilt_wander_tau_s=5.0))
    a = [att for _, att, _, _ in plain.samples()]
    b = [att for _, att, _, _ in wander.samples()]
    d = np.array([[y.roll_rad - x.roll_rad, y.pitch_rad - x.pitch_rad] for x, y in zip(a, b)])
    np.testing.assert_allclose(d, wander.tilt_wander[: len(d)], atol=1e-12)
    assert [x.yaw_rad for x in a] == [y.yaw_rad for y in b]
    assert np.abs(d).max() > 0.0005  # the wander is there
