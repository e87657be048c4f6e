"""``bench.terrain_slam.fix_errors``: the key frames' geo-fixes against the truth, on records with known
errors (the body error adds height x the key frame's tilt error to the matcher's ground-point error)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.terrain_slam import fix_errors
from companion.constants import R_BODY_CAM_NADIR
from companion.estimators.terrain_lba import GeoFixRecord


def test_ground_and_body_errors_and_bias_from_known_offsets() -> None:
    n = 30
    times = np.arange(n) / 15.0
    R_wc = np.repeat(R_BODY_CAM_NADIR[None], n, axis=0)  # level, heading north: optical axis straight down
    assert np.allclose(R_wc[0][:, 2], [0.0, 0.0, 1.0])
    p_body = np.stack([np.array([4.0 * t, 1.0, -100.0]) for t in times])
    p_cam = p_body.copy()
    rng = np.full(n, 100.0)
    ground = p_cam + rng[:, None] * R_wc[:, :, 2]
    recs = []
    for k in range(0, n, 5):
        # matcher 0.1 m north of the true ground point; the key frame tilted so the body is 0.3 m east of it
        g = ground[k] + [0.1, 0.0, 0.0]
        b = p_body[k] + [0.1, 0.3, 0.0]
        recs.append(
            GeoFixRecord.of(
                int(round(times[k] * 1e6)),
                {
                    "status": "accepted",
                    "quality": 0.5,
                    "p_fix_world": b,
                    "ground_fix_world": g,
                    "fix_sigma_m": 0.3 + 0.1 * (k % 2),
                },
            )
        )
    # a rejected fix far off is not counted
    recs.append(
        GeoFixRecord.of(
            int(round(times[3] * 1e6)),
            {"status": "rejected", "quality": 0.2, "p_fix_world": p_body[3] + 20.0},
        )
    )
    out = fix_errors(recs, times, p_body, R_wc, p_cam, rng)
    assert out["n_used"] == 6 and out["n_reported"] == 7
    assert out["ground_m"] == pytest.approx(0.1, abs=1e-9)
    assert out["bias_ne_m"] == pytest.approx([0.1, 0.0], abs=1e-9)
    assert out["body_m"] == pytest.approx(np.hypot(0.1, 0.3), abs=1e-9)
    assert out["quality_mean"] == pytest.approx(0.5)
    assert out["sigma_m_median"] == pytest.approx(0.35)  # over the fixes that reported one
    assert out["sigma_m_last"] == pytest.approx(0.4)


def test_no_used_fix_reports_counts_only() -> None:
    rec = GeoFixRecord.of(0, {"status": "pending", "quality": 0.3, "p_fix_world": [0.0, 0.0, -100.0]})
    out = fix_errors([rec], np.zeros(1), np.zeros((1, 3)), np.eye(3)[None], np.zeros((1, 3)), np.ones(1))
    assert out == {"n_used": 0, "n_reported": 1}
    assert np.isnan(rec.ground_fix_world).all()


def test_errors_along_the_heading_and_what_the_adjustment_did_not_follow() -> None:
    """Heading east: a fix 0.1 m north of the true ground point is 0.1 m to the left; the adjustment leaving
    each fix 0.2 m east of where it put the key frame is 0.2 m forward of it, unfollowed."""
    n = 20
    times = np.arange(n) / 15.0
    R_wc = np.repeat(R_BODY_CAM_NADIR[None], n, axis=0)
    p_body = np.stack([np.array([0.0, 4.0 * t, -100.0]) for t in times])
    rng = np.full(n, 100.0)
    ground = p_body + rng[:, None] * R_wc[:, :, 2]
    yaw = np.full(n, np.pi / 2)
    recs = [
        GeoFixRecord.of(
            int(round(times[k] * 1e6)),
            {
                "status": "accepted",
                "quality": 0.5,
                "p_fix_world": p_body[k],
                "ground_fix_world": ground[k] + [0.1, 0.0, 0.0],
                "post_residual_m": [0.0, 0.2, 0.05],
            },
        )
        for k in range(0, n, 4)
    ]
    recs.append(GeoFixRecord.of(int(round(times[2] * 1e6)), {"status": "accepted", "p_fix_world": p_body[2]}))
    out = fix_errors(recs, times, p_body, R_wc, p_body.copy(), rng, yaw)
    assert out["ground_fwd_right_m"] == pytest.approx([0.0, -0.1], abs=1e-9)
    # the record without a residual (its key frame was not the window's newest) is left out of these
    assert out["unfollowed_m"] == pytest.approx(0.2, abs=1e-9)
    assert out["unfollowed_ne_m"] == pytest.approx([0.0, 0.2], abs=1e-9)
    assert out["unfollowed_fwd_right_m"] == pytest.approx([0.2, 0.0], abs=1e-9)
    # without the heading, only the north / east means
    assert "unfollowed_fwd_right_m" not in fix_errors(recs, times, p_body, R_wc, p_body.copy(), rng)
