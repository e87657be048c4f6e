"""1-point RANSAC over the EKF's matches (companion.ekf.ransac): the pure hypothesis-and-support step on a
linear model with known outliers, and the SLAM refusing keypoints that drift on the synthetic scene."""

from __future__ import annotations

import numpy as np

from companion.ekf.ransac import low_innovation_inliers


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
