"""A flight's picture: the estimated track over the truth, and the error against time beside the
horizontal 1-sigma the companion sent. Written by ``companion replay`` (``trajectory.png`` beside its
estimates log) and by the demo (``sim_bridge.demo``). matplotlib, imported here only (Agg: no screen).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def trajectory_plot(
    out_png: str | Path,
    t_truth_s: np.ndarray,
    p_truth: np.ndarray,
    t_est_s: np.ndarray,
    p_est: np.ndarray,
    title: str,
    sigma_h_m: np.ndarray | None = None,
) -> Path:
    """Write the picture to ``out_png`` and return its path.

    t_truth_s (T,), p_truth (T,3) and t_est_s (N,), p_est (N,3): times (s) and NED positions (m) in the
    same clock and frame; the truth is interpolated at each estimate's time (estimates outside its span are
    left out of the error); with fewer than two truth samples only the track and the sigma are drawn.
    sigma_h_m (N,): the horizontal 1-sigma sent with each estimate, drawn beside the error when given."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t_truth_s, p_truth = np.asarray(t_truth_s, float), np.asarray(p_truth, float).reshape(-1, 3)
    t_est_s, p_est = np.asarray(t_est_s, float), np.asarray(p_est, float).reshape(-1, 3)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5.5))
    if len(p_truth):
        ax1.plot(p_truth[:, 1], p_truth[:, 0], "k-", lw=1.5, label="truth")
    if len(p_est):
        ax1.plot(p_est[:, 1], p_est[:, 0], "r.", ms=2, label="companion estimate")
    ax1.set_xlabel("east (m)")
    ax1.set_ylabel("north (m)")
    ax1.set_aspect("equal", adjustable="datalim")  # a straight track keeps a readable box
    if len(p_truth) or len(p_est):
        ax1.legend()
    ax1.set_title(title)
    if len(t_truth_s) >= 2 and len(t_est_s):
        inside = (t_est_s >= t_truth_s[0]) & (t_est_s <= t_truth_s[-1])
        t = t_est_s[inside]
        truth = np.stack([np.interp(t, t_truth_s, p_truth[:, i]) for i in range(3)], axis=1)
        ax2.plot(t - t_est_s[0], np.linalg.norm(p_est[inside] - truth, axis=1), "r-", lw=0.8, label="error")
    if sigma_h_m is not None and len(t_est_s):
        ax2.plot(t_est_s - t_est_s[0], sigma_h_m, "b--", lw=0.8, label="horizontal 1-sigma sent")
    if len(t_est_s):
        ax2.legend()
    ax2.set_xlabel("time since the first estimate (s)")
    ax2.set_ylabel("position error (m)" if len(t_truth_s) >= 2 else "m (no truth to compare with)")
    ax2.grid(True, alpha=0.3)
    fig.tight_layout()
    out = Path(out_png)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
