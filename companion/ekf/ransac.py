"""1-point RANSAC for the EKF's batch of visual matches (Civera, Grasa, Davison, Montiel, "1-point RANSAC
for EKF filtering. Application to real-time structure from motion and visual odometry", JFR 2010).

Paper 2 gates each match on its own (a Mahalanobis gate); a match can pass that gate and still disagree
with the others: a keypoint that drifts a little each frame (a glint that moves with the view, an edge of
a shadow) is individually plausible while the vehicle's prediction is loose. Civera's answer, the field's
standard for inverse-depth EKF-SLAM: a hypothesis is the state corrected by ONE match; the matches it
predicts to within a few pixels are its support; the largest support is updated first ("low-innovation
inliers"), then every other match is gated again against the corrected, now tight, state and the ones
that pass are updated too ("high-innovation inliers"). Because a single match fixes a hypothesis, every
match can be tried (no random draws): the result is deterministic.

Pure arrays in and out. No library does this on an EKF's innovation covariance; written here.
"""

from __future__ import annotations

import numpy as np

from companion.ekf.filter import pixel_noise_blocks


def low_innovation_inliers(
    HPHt: np.ndarray, residual: np.ndarray, sigma_px: float | np.ndarray, threshold_px: float
) -> np.ndarray:
    """The largest set of matches that one match's correction explains.

    HPHt: (2k, 2k) H P H^T of the k matches (2 rows each, without measurement noise); residual: (k, 2)
    z - h in pixels. Hypothesis i is the EKF correction by match i alone, dx_i = P H_i^T S_i^-1 r_i with
    S_i = H_i P H_i^T + sigma_i^2 I (sigma_px: one or (k,)); it moves every predicted pixel by H dx_i = (H P H_i^T) S_i^-1 r_i
    (first order). Match j supports i when |r_j - H_j dx_i| < threshold_px. Ties go to the smaller sum of
    squared supported residuals. Returns (k,) bool.
    """
    r = np.asarray(residual, float).reshape(-1, 2)
    k = len(r)
    if k == 0:
        return np.zeros(0, bool)
    M = np.asarray(HPHt, float).reshape(k, 2, k, 2)
    S_ii = M[np.arange(k), :, np.arange(k), :] + pixel_noise_blocks(sigma_px, k)  # (k,2,2)
    a = np.linalg.solve(S_ii, r[:, :, None])[:, :, 0]  # (k,2): S_i^-1 r_i
    shift = np.einsum("jaib,ib->ija", M, a)  # (hyp i, match j, 2): H_j dx_i
    post = r[None, :, :] - shift
    d2 = np.sum(post**2, axis=2)  # (hyp, match)
    support = d2 < threshold_px**2
    count = support.sum(axis=1)
    cost = np.where(support, d2, 0.0).sum(axis=1)
    best = np.lexsort((cost, -count))[0]
    return support[best]
