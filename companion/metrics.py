"""Accuracy of estimates against a known truth: the figures a simulated flight, a replay and the benchmarks
report. Pure functions of arrays."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

CHI2_2DOF_95 = float(chi2.ppf(0.95, 2))  # an error inside the 95 % ellipse of its 2-D covariance


def error_stats(err_m: np.ndarray) -> dict[str, float | int]:
    """Absolute position errors (m, one per estimate, in time order): count, mean, median, rmse, p95, max,
    final. ``{"count": 0}`` when there are none."""
    err = np.asarray(err_m, float).ravel()
    if not len(err):
        return {"count": 0}
    return {
        "count": int(len(err)),
        "mean": float(np.mean(err)),
        "median": float(np.median(err)),
        "rmse": float(np.sqrt(np.mean(err**2))),
        "p95": float(np.percentile(err, 95)),
        "max": float(np.max(err)),
        "final": float(err[-1]),
    }


def covariance_consistency(err_ne: np.ndarray, cov_ne: np.ndarray) -> dict[str, float | int]:
    """Does the estimator know how wrong it is? err_ne: (N, 2) horizontal errors against the truth (m);
    cov_ne: (N, 2, 2) the covariance each estimate came with. Returns, over the estimates with a usable
    covariance: count, the mean reported 1-sigma (root of the trace, m), the mean and median normalised
    error squared (NEES, 2 dof: 2 on average when the covariance is right) and the fraction of errors inside
    the estimate's own 95 % ellipse (0.95 when right; lower = over-confident)."""
    err_ne = np.asarray(err_ne, float).reshape(-1, 2)
    cov_ne = np.asarray(cov_ne, float).reshape(-1, 2, 2)
    ok = np.all(np.isfinite(cov_ne), axis=(1, 2)) & (np.linalg.det(np.nan_to_num(cov_ne)) > 0)
    if not ok.any():
        return {"count": 0}
    e, c = err_ne[ok], cov_ne[ok]
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(c), e)
    return {
        "count": int(ok.sum()),
        "sigma_mean_m": float(np.mean(np.sqrt(c[:, 0, 0] + c[:, 1, 1]))),
        "nees_mean": float(np.mean(nees)),
        "nees_median": float(np.median(nees)),
        "within_95": float(np.mean(nees <= CHI2_2DOF_95)),
    }
