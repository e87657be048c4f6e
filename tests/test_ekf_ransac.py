"""1-point RANSAC over the EKF's matches (companion.ekf.ransac): the pure hypothesis-and-support step on a
linear model with known outliers, and the SLAM refusing corrupted keypoints on the synthetic scene."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from test_ekf_filter import _fly
from test_ekf_scene import straight_flight

from companion.ekf.options import EkfOptions
from companion.ekf.ransac import low_innovation_inliers
from sim_bridge.trajectory import ImuNoise


def _linear_batch(seed: int, k: int, outliers: np.ndarray, outlier_px: float):
    """k matches of a 6-state linear model: H_i maps the state to pixels (translation-dominated, like a
    nadir camera), prior P, true state error drawn from P, pixel noise 0.2 px, and ``outliers`` moved."""
    rng = np.random.default_rng(seed)
    P = np.diag([4.0, 4.0, 1.0, 1e-4, 1e-4, 1e-4])
    H = np.zeros((k, 2, 6))
    H[:, 0, 0] = H[:, 1, 1] = 5.0
    H[:, :, 2] = rng.normal(0, 0.2, (k, 2))
    H[:, :, 3:] = rng.normal(0, 15.0, (k, 2, 3))
    x = rng.multivariate_normal(np.zeros(6), P)
    r = H @ x + rng.normal(0, 0.2, (k, 2))
    r[outliers] += outlier_px * np.array([0.6, -0.8])
    Hf = H.reshape(2 * k, 6)
    return Hf @ P @ Hf.T, r


def test_low_innovation_inliers_leave_out_the_outliers():
    outliers = np.array([3, 11, 17, 18])
    for seed in range(5):
        HPHt, r = _linear_batch(seed, 24, outliers, 4.0)
        inl = low_innovation_inliers(HPHt, r, 0.2, 1.0)
        assert not inl[outliers].any(), seed
        assert inl.sum() >= 24 - len(outliers) - 2, (seed, inl.sum())


def test_low_innovation_inliers_keep_a_clean_batch():
    HPHt, r = _linear_batch(7, 30, np.zeros(0, int), 0.0)
    assert low_innovation_inliers(HPHt, r, 0.2, 1.0).sum() >= 28
    assert low_innovation_inliers(HPHt, r[:0], 0.2, 1.0).shape == (0,)


def test_low_innovation_inliers_take_one_sigma_per_match():
    """Per-match sigmas (two cameras): equal ones give the single-sigma answer; a match whose camera is
    noisier carries less of the hypothesis it makes, and the set still leaves the outliers out."""
    outliers = np.array([2, 9])
    HPHt, r = _linear_batch(3, 20, outliers, 4.0)
    one = low_innovation_inliers(HPHt, r, 0.2, 1.0)
    np.testing.assert_array_equal(one, low_innovation_inliers(HPHt, r, np.full(20, 0.2), 1.0))
    two = low_innovation_inliers(HPHt, r, np.where(np.arange(20) % 2 == 0, 0.4, 0.2), 1.0)
    assert not two[outliers].any()


def test_slam_refuses_matches_the_others_disagree_with():
    """A seventh of each frame's keypoints 4 px off their points: with a loose attitude prediction (a noisy
    gyro) each passes its own gate and the plain filter takes them in; 1-point RANSAC refuses about as many
    matches as were corrupted, barely any on a clean flight, and ends closer to the truth."""
    gyro = 5e-3  # rad/s/sqrt(Hz): ~30x the default part, so the gates are several pixels wide
    base = EkfOptions(mode="visible", pixel_sigma_px=0.7, seed=0, gyro_noise_density=gyro)
    imu_noise = ImuNoise(gyro_noise_density=gyro)
    truth = straight_flight(duration_s=16.0, speed_mps=3.0).state_at(15.5).p_world  # _fly's last frame
    out = {}
    for outlier_px, ransac in ((0.0, True), (4.0, False), (4.0, True)):
        opts = replace(base, one_point_ransac=ransac)
        runs = [_fly(s, opts, 3.0, imu_noise=imu_noise, outlier_px=outlier_px) for s in range(3)]
        rejected = sum(slam.counters.ransac_rejected for _, _, slam in runs)
        tried = rejected + sum(sum(slam.counters.matches.values()) for _, _, slam in runs)
        err = float(np.mean([np.linalg.norm(est[-1] - truth) for _, est, _ in runs]))
        nees = float(np.mean([n[:, 0].mean() for n, _, _ in runs]))
        out[outlier_px, ransac] = (rejected / tried, err, nees)
    assert out[0.0, True][0] < 0.04, out
    assert out[4.0, False][0] == 0.0, out
    assert 0.07 < out[4.0, True][0] < 0.25, out  # a seventh of the keypoints is 0.14
    assert out[4.0, True][1] < out[4.0, False][1], out
    assert out[4.0, True][2] < out[4.0, False][2], out
