"""Local bundle adjustment with the geo-referencing term (companion.lba): factor Jacobian, recovery of a
synthetic window, w_G = 0 is pure VO, robust loss and gating against a bad geo-fix, eq. 21 alignment,
marginal covariances (and the first window's, expected to be indeterminate), the gravity prior against the
tilt/shift ambiguity, the landmark-on-DEM term and the DEM lookup it uses (``ground_below``), and the start-up
heading from the matcher's rotation recovery."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import B, X
from gtsam.utils.numerical_derivative import numericalDerivative11

from companion.constants import R_BODY_CAM_NADIR
from companion.geometry import CameraIntrinsics, make_T, rot_from_rpy, wrap_pi
from companion.georef.dem import Dem
from companion.lba.align import align_yaw_translation
from companion.lba.backend import Backend, BackendJob, BackendOptions, ground_below, quality_var_scale
from companion.lba.gauge import gauge_covariance
from companion.lba.window import (
    LbaOptions,
    WindowProblem,
    biased_geo_factor,
    body_covariance,
    geo_factor,
    geo_redundancy,
    solve_window,
)
from companion.vo.geometry import reproject
from companion.vo.odometry import WindowSnapshot

K = CameraIntrinsics.from_focal_sensor(480, 480, 36, 36).K


def _scene(seed: int = 0, n_kf: int = 12, n_pts: int = 600):
    """A nadir camera flying east at 100 m over rolling ground; key frames every 6 m."""
    rng = np.random.default_rng(seed)
    poses = []
    for i in range(n_kf):
        R = (
            rot_from_rpy(0.02 * rng.standard_normal(), 0.02 * rng.standard_normal(), 0.5 * np.pi)
            @ R_BODY_CAM_NADIR
        )
        poses.append(make_T(R, np.array([0.0, 6.0 * i, -100.0])))
    T = np.stack(poses)
    P = np.c_[
        rng.uniform(-50, 50, n_pts), rng.uniform(-50, 6.0 * n_kf + 50, n_pts), rng.uniform(-8, 8, n_pts)
    ]
    kf_list: list[int] = []
    lm_list: list[int] = []
    px_list: list[np.ndarray] = []
    for i in range(n_kf):
        uv, z = reproject(K, T[i], P)
        vis = np.flatnonzero((z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < 480) & (uv[:, 1] > 0) & (uv[:, 1] < 480))
        kf_list += [i] * len(vis)
        lm_list += [int(j) for j in vis]
        px_list += list(uv[vis] + 0.3 * rng.standard_normal((len(vis), 2)))
    obs_kf, obs_lm, obs_px = np.array(kf_list), np.array(lm_list), np.array(px_list)
    seen = np.bincount(obs_lm, minlength=n_pts) >= 2
    remap = -np.ones(n_pts, int)
    remap[seen] = np.arange(seen.sum())
    keep = seen[obs_lm]
    return T, P[seen], obs_kf[keep], remap[obs_lm[keep]], obs_px[keep], rng


def _problem(T_true, P_true, obs_kf, obs_lm, obs_px, rng, geo_sigma=0.3, n_anchor=2, perturb=True):
    M = len(T_true)
    T0 = T_true.copy()
    P0 = P_true.copy()
    if perturb:
        T0[n_anchor:, :3, 3] += rng.normal(0, 0.5, (M - n_anchor, 3))
        P0 = P0 + rng.normal(0, 0.5, P0.shape)
    anchor = np.zeros(M, bool)
    anchor[:n_anchor] = True
    geo = T_true[:, :3, 3] + rng.normal(0, geo_sigma, (M, 3))
    down = np.stack([T[:3, :3].T @ np.array([0.0, 0.0, 1.0]) for T in T_true])
    return WindowProblem(
        T_world_cam=T0,
        anchor=anchor,
        anchor_cov=np.full((M, 6, 6), np.nan),
        p_world=P0,
        obs_kf=obs_kf,
        obs_lm=obs_lm,
        obs_px=obs_px,
        K=K,
        geo_p_world=geo,
        geo_lever_cam=np.zeros((M, 3)),
        geo_cov=np.tile(np.eye(3), (M, 1, 1)),
        down_cam=down,
    )


def test_geo_factor_jacobian_matches_numerical_derivative():
    lever = np.array([0.05, -0.1, 0.2])
    g = np.array([3.0, -2.0, -98.0])
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    f = geo_factor(X(0), g, lever, noise)
    rng = np.random.default_rng(3)
    for _ in range(5):
        pose = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.5, 3)), rng.normal(0, 5, 3))
        v = gtsam.Values()
        v.insert(X(0), pose)
        # eq. 24 by hand: body position from the camera pose and lever arm, minus the fix
        e_hand = pose.rotation().matrix() @ lever + pose.translation() - g
        np.testing.assert_allclose(f.unwhitenedError(v), e_hand, atol=1e-9)
        A, _ = f.linearize(v).jacobian()

        def err(p: gtsam.Pose3) -> np.ndarray:
            return p.rotation().matrix() @ lever + p.translation() - g

        J_num = numericalDerivative11(err, pose)
        np.testing.assert_allclose(A, J_num, atol=1e-6)


def test_window_recovers_perturbed_poses_and_points():
    T, P, ok, ol, opx, rng = _scene(0)
    prob = _problem(T, P, ok, ol, opx, rng)
    sol = solve_window(prob, LbaOptions(w_geo=10.0))
    assert sol.ok
    err0 = np.abs(prob.T_world_cam[:, :3, 3] - T[:, :3, 3]).max()
    err = np.abs(sol.T_world_cam[:, :3, 3] - T[:, :3, 3]).max()
    assert err0 > 0.5
    assert err < 0.25
    assert np.median(np.linalg.norm(sol.p_world - P, axis=1)) < 0.3
    assert sol.obs_inlier.mean() > 0.97
    assert sol.error_final < sol.error_initial


def test_w_geo_zero_equals_pure_vo():
    T, P, ok, ol, opx, rng = _scene(1)
    prob = _problem(T, P, ok, ol, opx, rng)
    no_geo = replace(prob, geo_p_world=np.full_like(prob.geo_p_world, np.nan))
    a = solve_window(prob, LbaOptions(w_geo=0.0))
    b = solve_window(no_geo, LbaOptions(w_geo=10.0))
    np.testing.assert_allclose(a.T_world_cam, b.T_world_cam, atol=1e-9)
    np.testing.assert_allclose(a.p_world, b.p_world, atol=1e-9)
    c = solve_window(prob, LbaOptions(w_geo=10.0))
    assert np.abs(c.T_world_cam[:, :3, 3] - a.T_world_cam[:, :3, 3]).max() > 1e-4  # the fixes do act


def test_geo_term_pulls_a_shifted_window_and_weight_orders_it():
    T, P, ok, ol, opx, rng = _scene(2)
    # the VO map is shifted by 2 m east (a drifted window) and only weakly anchored
    shift = np.array([0.0, 2.0, 0.0])
    prob = _problem(T, P, ok, ol, opx, rng, geo_sigma=0.05, perturb=False)
    Ts = prob.T_world_cam.copy()
    Ts[:, :3, 3] += shift
    cov = np.diag([1e-4] * 3 + [4.0] * 3)
    prob = replace(
        prob, T_world_cam=Ts, p_world=prob.p_world + shift, anchor_cov=np.tile(cov, (len(Ts), 1, 1))
    )
    errs = []
    for w in (1.0, 100.0):
        sol = solve_window(prob, LbaOptions(w_geo=w))
        errs.append(np.abs(sol.T_world_cam[:, 1, 3] - T[:, 1, 3]).mean())
    assert errs[1] < 0.2
    assert errs[1] < errs[0]


def test_bad_geo_fix_is_bounded_by_the_robust_loss():
    T, P, ok, ol, opx, rng = _scene(4)
    prob = _problem(T, P, ok, ol, opx, rng, geo_sigma=0.1, perturb=False)
    bad = prob.geo_p_world.copy()
    bad[-1] += np.array([20.0, 0.0, 0.0])  # a 20 m wrong fix on the newest key frame
    good = solve_window(prob, LbaOptions(w_geo=10.0))
    hit = solve_window(replace(prob, geo_p_world=bad), LbaOptions(w_geo=10.0))
    plain = solve_window(replace(prob, geo_p_world=bad), LbaOptions(w_geo=10.0, geo_kernel="none"))
    pull_robust = np.linalg.norm(hit.T_world_cam[-1, :3, 3] - good.T_world_cam[-1, :3, 3])
    pull_plain = np.linalg.norm(plain.T_world_cam[-1, :3, 3] - good.T_world_cam[-1, :3, 3])
    assert pull_robust < 0.5
    assert pull_plain > 2 * pull_robust
    assert hit.geo_whitened[-1] > 10.0


def _snapshot(T, P, ok, ol, opx):
    M = len(T)
    anchor = np.zeros(M, bool)
    anchor[:2] = True
    down = np.stack([t[:3, :3].T @ np.array([0.0, 0.0, 1.0]) for t in T])
    return WindowSnapshot(np.arange(M), T.copy(), anchor, down, np.arange(len(P)), P.copy(), ok, ol, opx)


class _Fix:
    def __init__(self, p):
        self.ok, self.reason, self.p_world, self.quality = True, "", np.asarray(p, float), 0.5
        self.rotation_rad, self.rotation_scale_quality = 0.0, 0.5


def _first_kfs_job(snap_all: WindowSnapshot, T: np.ndarray, k: int, held: bool = True) -> BackendJob:
    """The back-end's job for key frame k of a flight whose map holds key frames 0..k (points seen twice
    or more among them, as ``VisualOdometry.snapshot`` gives). held: keep the snapshot's anchors; False:
    none, as at a real start (the back-end then holds the oldest itself)."""
    sel = np.arange(k + 1)
    m = np.isin(snap_all.obs_kf, sel)
    seen = np.bincount(snap_all.obs_lm[m], minlength=len(snap_all.p_world)) >= 2
    m &= seen[snap_all.obs_lm]
    remap = np.cumsum(seen) - 1
    snap = replace(
        snap_all,
        kf_ids=sel,
        T_world_cam=T[sel],
        anchor=snap_all.anchor[sel] if held else np.zeros(len(sel), bool),
        down_cam=snap_all.down_cam[sel],
        lm_ids=snap_all.lm_ids[seen],
        p_world=snap_all.p_world[seen],
        obs_kf=snap_all.obs_kf[m],
        obs_lm=remap[snap_all.obs_lm[m]],
        obs_px=snap_all.obs_px[m],
    )
    R_wb = T[k, :3, :3] @ R_BODY_CAM_NADIR.T
    return BackendJob(
        snap, k, np.zeros((4, 4), np.uint8), R_wb, T[k, :3, 3], 100.0, None, 6.0, np.zeros(3), K
    )


def test_first_window_is_held_whole_and_its_marginal_is_not_a_failure():
    """Key frames 0 and 1 (the VO's initial pair): with the newest free the monocular scale would be free
    and the adjustment would slide it along the baseline, so both are held (the points alone move) and the
    newest has no marginal, by construction; from three key frames on (two held) it is determined. Only a
    failure after that start is a failure."""
    T, P, ok, ol, opx, _ = _scene(5)
    T_init = T.copy()
    T_init[1, :3, 3] += 0.2 * (T[1, :3, 3] - T[0, :3, 3])  # the initial pair's scale 20 % off
    snap_all = _snapshot(T_init, P, ok, ol, opx)
    be = Backend(BackendOptions(lba=LbaOptions(w_geo=0.0)), None)
    first = be.process(_first_kfs_job(snap_all, T_init, 1, held=False))
    np.testing.assert_allclose(first.T_world_cam[1][:3, 3], T_init[1][:3, 3], atol=1e-3)
    assert not np.all(np.isfinite(first.cov_newest))
    assert first.counters["marginals_failed"] == 0
    second = be.process(_first_kfs_job(snap_all, T, 2, held=False))
    assert np.all(np.isfinite(second.cov_newest))
    assert second.counters["marginals_failed"] == 0


def test_backend_gates_a_bad_fix_and_counts_it():
    T, P, ok, ol, opx, rng = _scene(5)
    truth = {i: T[i, :3, 3] for i in range(len(T))}
    fixes = {i: truth[i] + rng.normal(0, 0.2, 3) for i in range(len(T))}
    fixes[len(T) - 1] = truth[len(T) - 1] + np.array([0.0, 20.0, 0.0])  # scene-07-like failure
    current = {"k": 0}

    def locate(image, R, p, alt, solve_rotation_scale):
        return _Fix(fixes[current["k"]])

    be = Backend(BackendOptions(lba=LbaOptions(w_geo=10.0)), locate)
    snap_all = _snapshot(T, P, ok, ol, opx)
    results = {}
    for k in range(2, len(T)):
        current["k"] = k
        res = results[k] = be.process(_first_kfs_job(snap_all, T, k))
    assert res.geo["status"] == "rejected"
    # not placed until eq. 21 on the first fixes; then the result says so, about the centre of those fixes
    k_al = next(k for k, r in results.items() if r.geo["status"] == "aligned")
    assert not any(results[k].located for k in range(2, k_al))
    assert np.all(np.isnan(results[2].pivot_world))
    np.testing.assert_allclose(results[k_al].pivot_world, np.mean([fixes[k] for k in range(2, k_al + 1)], 0))
    assert res.located and np.array_equal(res.pivot_world, results[k_al].pivot_world)
    # the outcome carries what the fix said (a replay checks it against truth)
    assert np.allclose(res.geo["p_fix_world"], fixes[len(T) - 1])
    assert res.counters["fix_rejected"] == 1
    assert res.counters["fix_accepted"] >= len(T) - 4
    # the newest pose is not pulled towards the bad fix beyond the gate
    gate_m = np.sqrt(be.opt.geo_gate_chi2) * be.opt.geo_sigma_m
    assert np.linalg.norm(res.T_world_cam[-1, :3, 3] - T[-1, :3, 3]) < min(gate_m, 0.5)


def _fly_with_heading_error(
    heading: bool,
    yaw_err_deg: float,
    rot_noise_deg: float,
    seed: int = 5,
    plain_off_deg: float = 90.0,
    plain_off: str = "fails",
    **options,
):
    """A start-up over ``_scene``: the map turned by -yaw_err_deg (a compass that far off), good fixes, and a
    matcher whose heading estimate (true yaw - given yaw) has ``rot_noise_deg`` of noise. The key frames span
    about 20 m RMS, short of ``align_min_spread_m``: only the matcher's heading can align the yaw. A plain fix
    (no heading search) asked at a heading more than ``plain_off_deg`` wrong ``plain_off``: "fails", is
    "wrong" by metres in a random direction, as the phase correlation does, or is "biased" east by 1.2 m per
    degree. Returns the back-end and the
    map's remaining yaw error (deg) after the corrections it sent."""
    T, P, ok, ol, opx, rng = _scene(seed)
    d = np.radians(-yaw_err_deg)
    turn = make_T(rot_from_rpy(0.0, 0.0, d), T[0, :3, 3] - rot_from_rpy(0.0, 0.0, d) @ T[0, :3, 3])
    T_map = np.einsum("ij,njk->nik", turn, T)
    P_map = P @ turn[:3, :3].T + turn[:3, 3]
    fixes = {i: T[i, :3, 3] + rng.normal(0, 0.2, 3) for i in range(len(T))}
    current = {"k": 0}

    def locate(image, R, p, alt, solve_rotation_scale):
        f = _Fix(fixes[current["k"]])
        R_true = T[current["k"], :3, :3] @ R_BODY_CAM_NADIR.T
        off = float(wrap_pi(np.arctan2(R_true[1, 0], R_true[0, 0]) - np.arctan2(R[1, 0], R[0, 0])))
        if solve_rotation_scale:
            f.rotation_rad = off + np.radians(rot_noise_deg) * rng.normal()
        elif abs(off) > np.radians(plain_off_deg):
            if plain_off == "fails":
                f.ok, f.reason, f.p_world = False, "low_quality", np.full(3, np.nan)
            elif plain_off == "biased":
                # the correlation peak follows the part of the footprint that matches best: metres per
                # degree, the same way over consecutive key frames (the Table 7 flights: 0.2-1.2 m/deg)
                f.p_world = f.p_world + np.array([0.0, 1.2 * np.degrees(off), 0.0])
            else:
                f.p_world = f.p_world + rng.normal(0.0, 4.0, 3)
        return f

    be = Backend(BackendOptions(lba=LbaOptions(w_geo=10.0), heading_from_matcher=heading, **options), locate)
    for k in range(2, len(T)):
        current["k"] = k
        snap_all = _snapshot(T_map, P_map, ok, ol, opx)
        res = be.process(_first_kfs_job(snap_all, T_map, k))
        # the front-end moves its whole map by the alignment (``VisualOdometry.apply_correction``)
        T_map = np.einsum("ij,njk->nik", res.T_align, T_map)
        P_map = P_map @ res.T_align[:3, :3].T + res.T_align[:3, 3]
    R_rel = T_map[-1, :3, :3] @ T[-1, :3, :3].T
    return be, float(np.degrees(np.arctan2(R_rel[1, 0], R_rel[0, 0])))


def test_matcher_heading_turns_the_start_up_map_before_the_fixes_spread():
    be, left_deg = _fly_with_heading_error(True, 2.5, 0.2)
    assert be.yaw_aligned and len(be.heading_samples) >= be.opt.heading_min_samples
    assert abs(left_deg) < 0.25 and be.counters["heading_coarse_turns"] == 0
    # without it the yaw waits for the fixes to spread 25 m, which this flight does not reach
    be0, left0_deg = _fly_with_heading_error(False, 2.5, 0.2)
    assert not be0.yaw_aligned and abs(left0_deg) > 2.0
    # estimates that disagree (a matcher finding wrong peaks) do not turn the map
    be1, left1_deg = _fly_with_heading_error(True, 2.5, 8.0)
    assert not be1.yaw_aligned and abs(left1_deg) > 2.0


def test_matcher_heading_rescues_a_start_up_whose_compass_is_too_far_off_for_the_plain_match():
    # every plain fix at the compass heading fails: the search's heading finds the terrain. The plain fix is
    # asked at the heading the estimates so far give (``heading_for_fixes``), or without that, asked again
    # at the search's heading when it failed at the compass's ("rescued")
    for at_estimate in (True, False):
        be, left_deg = _fly_with_heading_error(
            True, 10.0, 0.2, plain_off_deg=5.0, plain_off="fails", heading_for_fixes=at_estimate
        )
        assert be.aligned and be.yaw_aligned and abs(left_deg) < 0.25
        assert be.counters["fix_accepted"] >= 3
        assert (be.counters["fix_heading_rescued"] >= 1) is not at_estimate
        # two agreeing estimates far off turned the map at once, the fine turn followed
        assert be.counters["heading_coarse_turns"] == 1
    # the plain fixes are wrong by metres: they never agree on an alignment until the map is turned
    be, left_deg = _fly_with_heading_error(True, 10.0, 0.2, plain_off_deg=5.0, plain_off="wrong")
    assert be.aligned and be.yaw_aligned and abs(left_deg) < 0.25
    assert be.counters["fix_heading_rescued"] == 0
    # no compass at all: the heading is half a turn off, the estimates fall either side of +-180 deg; with
    # the coarse turn, and with the fine one alone (its median is taken about the estimates' circular mean)
    for coarse_deg in (5.0, 360.0):
        be, left_deg = _fly_with_heading_error(
            True, 180.0, 0.3, plain_off_deg=5.0, plain_off="fails", heading_coarse_deg=coarse_deg
        )
        assert be.aligned and be.yaw_aligned and abs(left_deg) < 0.25
        assert be.counters["heading_coarse_turns"] == (1 if coarse_deg < 180 else 0)
    # without the matcher's heading neither aligns
    for mode in ("fails", "wrong"):
        be0, left0_deg = _fly_with_heading_error(False, 10.0, 0.2, plain_off_deg=5.0, plain_off=mode)
        assert not be0.aligned and abs(left0_deg) > 9.0


def test_start_up_fixes_are_matched_at_the_heading_the_estimates_give_not_the_compass():
    # a compass 1.5 deg off biases the plain fixes by 1.8 m, all the same way: the first alignment would
    # place the map by that much; matched at the estimates' heading (0.3 deg noise each) they are not
    T = _scene(5)[0]
    err = {}
    for at_estimate in (True, False):
        be, _ = _fly_with_heading_error(
            True, 1.5, 0.3, plain_off_deg=0.0, plain_off="biased", heading_for_fixes=at_estimate
        )
        first = sorted(be.fixes)[:3]
        assert len(first) == 3
        err[at_estimate] = float(np.mean([abs(be.fixes[k][1] - T[k, 1, 3]) for k in first]))
    assert err[True] < 0.7 and err[False] > 1.4


def test_fix_heading_is_the_estimates_median_shrunk_towards_the_compass():
    be = Backend(BackendOptions(heading_prior_sigma_rad=np.radians(2.0)), None)
    assert be.fix_heading() == 0.0
    be.heading_samples.append(np.radians(3.0))
    # one estimate of 1 deg spread against a 2 deg compass: 4 / (4 + 1.2533^2) of it
    assert np.degrees(be.fix_heading()) == pytest.approx(3.0 * 4.0 / (4.0 + 1.2533**2), rel=1e-6)
    # three that agree to 0.1 deg: nearly their median, a wild one does not move it
    be.heading_samples[:] = list(np.radians([1.9, 2.0, 2.1, 40.0]))
    assert np.degrees(be.fix_heading()) == pytest.approx(2.05, abs=0.1)
    # across +-180 deg (no compass: a huge prior)
    be = Backend(BackendOptions(heading_prior_sigma_rad=np.pi), None)
    be.heading_samples[:] = list(np.radians([179.0, -179.0, 179.5]))
    assert abs(np.degrees(wrap_pi(be.fix_heading() - np.pi))) < 1.0
    # switched off: the compass's
    be = Backend(BackendOptions(heading_for_fixes=False), None)
    be.heading_samples.append(0.05)
    assert be.fix_heading() == 0.0


def test_alignment_recovers_yaw_and_translation_despite_an_outlier():
    rng = np.random.default_rng(6)
    p_vo = np.c_[rng.uniform(-60, 60, 20), rng.uniform(-60, 60, 20), rng.uniform(-105, -95, 20)]
    yaw = np.radians(2.0)
    T_true = make_T(rot_from_rpy(0.0, 0.0, yaw), np.array([3.0, -1.0, 0.5]))
    p_w = p_vo @ T_true[:3, :3].T + T_true[:3, 3] + rng.normal(0, 0.1, p_vo.shape)
    p_w[3] += np.array([30.0, 0.0, 0.0])
    a = align_yaw_translation(p_vo, p_w)
    assert a.yaw_observable
    assert abs(a.yaw_rad - yaw) < np.radians(0.1)
    np.testing.assert_allclose(a.T_world_vo[:3, 3], T_true[:3, 3], atol=0.1)
    assert not a.inliers[3] and a.inliers.sum() == 19
    # a short base does not estimate the yaw
    b = align_yaw_translation(p_vo[:3] * 0.01, p_w[:3] * 0.0 + p_vo[:3] * 0.01 + 1.0)
    assert not b.yaw_observable and b.yaw_rad == 0.0


def test_marginal_covariance_shrinks_with_geo_and_maps_to_body_axes():
    T, P, ok, ol, opx, rng = _scene(7)
    prob = _problem(T, P, ok, ol, opx, rng, perturb=False)
    cov_init = np.diag([1e-4] * 3 + [1.0] * 3)
    prob = replace(prob, anchor_cov=np.tile(cov_init, (len(T), 1, 1)))
    vo = solve_window(prob, LbaOptions(w_geo=0.0))
    geo = solve_window(prob, LbaOptions(w_geo=100.0))
    assert np.all(np.isfinite(vo.cov[-1])) and np.all(np.isfinite(geo.cov[-1]))
    assert np.trace(geo.cov[-1][3:, 3:]) < 0.5 * np.trace(vo.cov[-1][3:, 3:])
    C = body_covariance(T[-1], geo.cov[-1], R_BODY_CAM_NADIR, np.zeros(3))
    assert C.shape == (6, 6)
    np.testing.assert_allclose(C, C.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(C) > 0)
    # position block: the camera-frame translation covariance rotated into the world
    R = T[-1, :3, :3]
    np.testing.assert_allclose(C[:3, :3], R @ geo.cov[-1][3:, 3:] @ R.T, rtol=1e-3, atol=1e-8)


@pytest.mark.parametrize("kernel", ["huber", "cauchy", "none"])
def test_kernels_accepted(kernel):
    T, P, ok, ol, opx, rng = _scene(8, n_kf=5, n_pts=200)
    sol = solve_window(
        _problem(T, P, ok, ol, opx, rng), LbaOptions(reprojection_kernel=kernel, geo_kernel=kernel)
    )
    assert sol.ok


def _wavy_dem() -> Dem:
    """Analytic ground h = 6 sin(2 pi e / 40) cos(2 pi n / 55) + 0.05 n on a 1 m grid around the window."""
    n = 80.0 - np.arange(0.0, 200.0)
    e = np.arange(-80.0, 200.0)
    h = (
        6.0 * np.sin(2 * np.pi * e[None, :] / 40.0) * np.cos(2 * np.pi * n[:, None] / 55.0)
        + 0.05 * n[:, None]
    )
    return Dem(h.astype(np.float32), 80.0, -80.0, 1.0)


def test_ground_below_gives_heights_slopes_and_nan_in_holes():
    dem = _wavy_dem()
    p = np.array([[10.3, 20.7, -50.0], [-30.2, 55.1, 0.0], [0.0, 500.0, 0.0]])
    g = ground_below(dem, p)
    n, e = p[:2, 0], p[:2, 1]
    h = 6.0 * np.sin(2 * np.pi * e / 40.0) * np.cos(2 * np.pi * n / 55.0) + 0.05 * n
    dh_dn = -6.0 * np.sin(2 * np.pi * e / 40.0) * np.sin(2 * np.pi * n / 55.0) * 2 * np.pi / 55.0 + 0.05
    dh_de = 6.0 * np.cos(2 * np.pi * e / 40.0) * np.cos(2 * np.pi * n / 55.0) * 2 * np.pi / 40.0
    np.testing.assert_allclose(g[:2, 2], -h, atol=0.05)  # bilinear on a 1 m grid
    np.testing.assert_allclose(g[:2, 3], dh_dn, atol=0.03)
    np.testing.assert_allclose(g[:2, 4], dh_de, atol=0.03)
    assert np.all(np.isnan(g[2, 2:]))  # off the DEM
    holed = dem.height_m.copy()
    r, c = (int(round(x)) for x in dem.rc_from_ne(10.3, 20.7))
    holed[r - 1 : r + 2, c - 1 : c + 2] = np.nan
    g = ground_below(Dem(holed, dem.north0_m, dem.east0_m, dem.cell_m), p[:2])
    assert np.all(np.isnan(g[0, 2:])) and np.all(np.isfinite(g[1]))  # in a hole / beside none


def test_terrain_term_pulls_a_shifted_window_back_onto_the_dem():
    """A window drifted 1.5 m east and 1 m down over sloping ground, no geo-fixes: with landmarks tied to
    the DEM, the heights and the slopes bring it back; without, it stays where the VO put it."""
    dem = _wavy_dem()
    T, P, ok, ol, opx, rng = _scene(5)
    P = P.copy()
    P[:, 2] = -dem.height_at(P[:, 0], P[:, 1])  # the landmarks on the ground
    # re-measure the pixels of the landmarks at their new heights
    opx = np.stack([reproject(K, T[i], P[j : j + 1])[0][0] for i, j in zip(ok, ol)])
    opx += 0.3 * rng.standard_normal(opx.shape)
    prob = _problem(T, P, ok, ol, opx, rng, perturb=False)
    shift = np.array([0.0, 1.5, 1.0])
    Ts = prob.T_world_cam.copy()
    Ts[:, :3, 3] += shift
    cov = np.diag([1e-4] * 3 + [9.0] * 3)  # anchors: rotation known, position loose
    prob = replace(
        prob,
        T_world_cam=Ts,
        p_world=prob.p_world + shift,
        anchor_cov=np.tile(cov, (len(Ts), 1, 1)),
        geo_p_world=np.full_like(prob.geo_p_world, np.nan),
    )
    prob = replace(prob, lm_ground=ground_below(dem, prob.p_world))
    off = solve_window(prob, LbaOptions(w_geo=10.0))
    on = solve_window(prob, LbaOptions(w_geo=10.0, terrain_sigma_m=0.3))
    err_off = np.linalg.norm(off.T_world_cam[:, :3, 3] - T[:, :3, 3], axis=1).mean()
    err_on = np.linalg.norm(on.T_world_cam[:, :3, 3] - T[:, :3, 3], axis=1).mean()
    assert err_off > 1.4
    assert err_on < 0.3
    # no term without ground rows, nor from NaN rows (landmarks off the DEM or over a hole)
    none = solve_window(replace(prob, lm_ground=None), LbaOptions(w_geo=10.0, terrain_sigma_m=0.3))
    np.testing.assert_allclose(none.T_world_cam, off.T_world_cam, atol=1e-9)
    nan_rows = np.full_like(prob.lm_ground, np.nan)
    nan = solve_window(replace(prob, lm_ground=nan_rows), LbaOptions(w_geo=10.0, terrain_sigma_m=0.3))
    np.testing.assert_allclose(nan.T_world_cam, off.T_world_cam, atol=1e-9)


def test_gravity_prior_sets_the_body_position_when_fixes_pin_the_ground():
    """A nadir camera's tilt and a sideways shift look alike: a map turned about the ground line under the
    flight satisfies the images and fixes that locate the ground point on the optical axis just as well, with
    every camera moved sideways by height x angle. Only the autopilot's roll/pitch (the gravity factor)
    tells them apart, and the tighter its sigma, the closer the body comes back."""
    T, P, ok, ol, opx, rng = _scene(5)
    M = len(T)
    lever = np.array([0.0, 0.0, 100.0])  # the ground point on the optical axis (geo_on_ground)
    ground = np.stack([Ti[:3, :3] @ lever + Ti[:3, 3] for Ti in T])
    angle = np.radians(0.3)  # about the east axis through the ground below the flight (north 0, down 0)
    c, s = np.cos(angle), np.sin(angle)
    G = np.eye(4)
    G[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    base = _problem(T, P, ok, ol, opx, rng, perturb=False)
    prob = replace(
        base,
        T_world_cam=np.einsum("ij,njk->nik", G, T),
        p_world=P @ G[:3, :3].T,
        anchor=np.zeros(M, bool),
        geo_p_world=ground,
        geo_lever_cam=np.tile(lever, (M, 1)),
    )
    off0 = np.abs(prob.T_world_cam[:, 0, 3] - T[:, 0, 3]).mean()
    assert off0 > 0.45  # 100 m x 0.3 deg
    north_err = {}
    for sigma in (0.003, 0.5):
        sol = solve_window(prob, LbaOptions(w_geo=10.0, gravity_sigma_rad=sigma, marginals=False))
        assert sol.ok
        north_err[sigma] = np.abs(sol.T_world_cam[:, 0, 3] - T[:, 0, 3]).mean()
    # measured 0.03 m and 0.15 m (the images alone hold the turn weakly: the ground's relief)
    assert north_err[0.003] < 0.08
    assert north_err[0.5] > 3 * north_err[0.003]


def test_gauge_covariance_is_the_start_and_the_heading_carried_along_the_lever():
    pivot = np.array([10.0, -20.0, -100.0])
    p = pivot + np.array([30.0, 40.0, 5.0])  # 50 m away
    sig_p, sig_y = 0.7, np.radians(2.0)
    C = gauge_covariance(p, pivot, sig_p, sig_y)
    assert np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > -1e-12)
    # along the lever only the start's error; across it the heading's, 50 m x 2 deg = 1.75 m
    u = np.array([30.0, 40.0]) / 50.0
    v = np.array([-u[1], u[0]])
    assert u @ C[:2, :2] @ u == pytest.approx(sig_p**2)
    assert v @ C[:2, :2] @ v == pytest.approx(sig_p**2 + (50.0 * sig_y) ** 2)
    assert C[5, 5] == pytest.approx(sig_y**2) and C[2, 2] == 0.0 and np.all(C[3:5] == 0.0)
    # first order of the turn itself: sample the start and the heading, turn the map about the pivot
    rng = np.random.default_rng(0)
    n = 40000
    dpsi = rng.normal(0.0, sig_y, n)
    dp0 = rng.normal(0.0, sig_p, (n, 2))
    d = p[:2] - pivot[:2]
    moved = np.stack(
        [np.cos(dpsi) * d[0] - np.sin(dpsi) * d[1], np.sin(dpsi) * d[0] + np.cos(dpsi) * d[1]], 1
    )
    x = np.column_stack([moved + dp0 - d, dpsi])
    S = np.cov(x.T)
    np.testing.assert_allclose(S[:2, :2], C[:2, :2], rtol=0.05, atol=0.02)
    np.testing.assert_allclose(S[:2, 2], C[:2, 5], rtol=0.05, atol=1e-3)
    # turned to the right heading since: the lever's share stays, the heading's own goes
    C_turned = gauge_covariance(p, pivot, sig_p, sig_y, heading_known=True)
    np.testing.assert_array_equal(C_turned[:2, :2], C[:2, :2])
    assert np.all(C_turned[5] == 0.0) and np.all(C_turned[:, 5] == 0.0)
    # known heading and position: nothing to add; no compass: capped (heading uniform over the turn, the
    # lever's sigma at most its length)
    assert np.all(gauge_covariance(p, pivot, 0.0, 0.0) == 0.0)
    C_free = gauge_covariance(p, pivot, 0.0, np.pi)
    assert C_free[5, 5] == pytest.approx(np.pi**2 / 3.0)
    assert np.sqrt(np.trace(C_free[:2, :2])) <= 50.0 + 1e-9


def _fly_backend_over_noisy_fixes(options: list[BackendOptions], fix_noise_m: float, n_kf: int = 12) -> list:
    """The back-end over key frames 2.. of scene 5, each with a fix drawn ``fix_noise_m`` around its true
    position, once per entry of ``options``: the last result of each."""
    T, P, ok, ol, opx, rng = _scene(5, n_kf=n_kf)
    fixes = {i: T[i, :3, 3] + rng.normal(0, fix_noise_m, 3) for i in range(len(T))}
    snap_all = _snapshot(T, P, ok, ol, opx)
    current = {"k": 0}

    def locate(image, R, p, alt, solve_rotation_scale):
        return _Fix(fixes[current["k"]])

    out = []
    for opt in options:
        be = Backend(opt, locate)
        for k in range(2, len(T)):
            current["k"] = k
            res = be.process(_first_kfs_job(snap_all, T, k))
        out.append(res)
    return out


@pytest.mark.parametrize("fix_noise_m", [0.05, 1.0])
def test_reported_covariance_grows_when_the_fixes_scatter_beyond_their_sigma(fix_noise_m):
    """The a-posteriori variance factor of the window's geo term scales the covariance reported for the
    newest key frame when the fixes scatter more than their sigma (sigma0 / sqrt(w_G) = 0.32 m here), and
    leaves it when they scatter less; the adjustment itself is the same either way."""
    opts = [
        BackendOptions(lba=LbaOptions(w_geo=10.0), variance_factor=vf, geo_sigma_adapt=False)
        for vf in (False, True)
    ]
    off, on = _fly_backend_over_noisy_fixes(opts, fix_noise_m)
    out = {False: off, True: on}
    assert out[True].counters["fix_accepted"] >= 6
    np.testing.assert_array_equal(out[True].T_world_cam, out[False].T_world_cam)
    ratio = out[True].cov_newest / out[False].cov_newest
    np.testing.assert_allclose(ratio, ratio[0, 0], rtol=1e-9)  # one factor on the whole covariance
    if fix_noise_m < 0.3:
        assert ratio[0, 0] == 1.0
    else:
        assert 3.0 < ratio[0, 0] < 30.0  # about (1.0 / 0.32)^2 less what the adjustment fits


@pytest.mark.parametrize("fix_noise_m", [0.1, 1.0])
def test_geo_redundancy_estimates_how_far_the_fixes_scatter_beyond_their_sigma(fix_noise_m):
    """Helmert's variance component of the geo term: the fixes' whitened squared residuals over their
    redundancy estimate (true fix variance) / (variance the adjustment gave them); here sigma 0.32 m
    (geo_cov 1 m^2 / w_G 10), fixes drawn at 0.1 and 1.0 m: ratios 0.1 and 10. Pooled over six windows
    (about 100 fixes) the estimate is good to about 15 %. White fixes and the white model
    (``geo_bias_share`` 0): with the default bias share the estimate counts the redundancy the bias
    variables take as the fixes' (0.06 instead of 0.1 on the 0.1-m fixes; docs/benchmarks.md, session 40)."""
    q_sum, red_sum = 0.0, 0.0
    for seed in range(6):
        T, P, ok, ol, opx, rng = _scene(seed)
        prob = _problem(T, P, ok, ol, opx, rng, geo_sigma=fix_noise_m, perturb=False)
        sol = solve_window(prob, LbaOptions(w_geo=10.0, geo_bias_share=0.0))
        q, red = geo_redundancy(prob, sol, 10.0)
        assert 0.0 < red <= 2.0 * (len(T) - 2)
        q_sum, red_sum = q_sum + q, red_sum + red
    expected = fix_noise_m**2 / 0.1
    assert 0.6 * expected < q_sum / red_sum < 1.6 * expected


@pytest.mark.parametrize("fix_noise_m", [0.05, 1.0])
def test_backend_learns_the_fixes_sigma_from_their_scatter(fix_noise_m):
    """With ``geo_sigma_adapt`` the sigma the adjustment gives the fixes (reported as ``fix_sigma_m``) grows
    from sigma0 / sqrt(w_G) = 0.32 m towards what they scatter when that is more (1 m fixes), and stays when
    it is less (5 cm fixes: the range's floor is 1, the fixes are never trusted more than w_G says); without
    it, it stays."""
    opts = [
        BackendOptions(lba=LbaOptions(w_geo=10.0), geo_sigma_adapt=adapt, geo_gate_chi2=1e6)
        for adapt in (False, True)
    ]
    off, on = _fly_backend_over_noisy_fixes(opts, fix_noise_m, n_kf=30)
    sigma = {False: off.geo["fix_sigma_m"], True: on.geo["fix_sigma_m"]}
    assert sigma[False] == pytest.approx(1.0 / np.sqrt(10.0))
    if fix_noise_m > 0.3:
        assert 0.6 < sigma[True] < 1.6
    else:
        assert sigma[True] == sigma[False]


def test_reported_variance_factor_stays_against_the_nominal_sigma_when_the_sigma_is_learnt():
    """With the fixes' sigma learnt (the default), 1 m fixes raise it to about 1 m, so against the learnt
    sigma the variance factor would be ~1; the reported covariance still takes it against the nominal 0.32 m
    (the fixes' errors are correlated in time), and the adjustment is the same either way."""
    opts = [BackendOptions(lba=LbaOptions(w_geo=10.0), variance_factor=vf) for vf in (False, True)]
    assert all(o.geo_sigma_adapt for o in opts)
    off, on = _fly_backend_over_noisy_fixes(opts, 1.0)
    out = {False: off, True: on}
    assert out[True].geo["fix_sigma_m"] > 0.6  # learnt well above the nominal 0.32 m
    np.testing.assert_array_equal(out[True].T_world_cam, out[False].T_world_cam)
    assert (out[True].cov_newest / out[False].cov_newest)[0, 0] > 3.0


def test_quality_var_scale_is_relative_to_the_recent_peaks_and_capped():
    """A fix's variance grows by (q_ref / q)^(2 power) below q_ref, the recent peaks' percentile capped at
    ``ref_max``: on terrain where every peak is low, the usual ones count fully."""
    good = np.full(30, 0.6)
    assert quality_var_scale(0.6, good, 75.0, 0.35, 1.5) == 1.0
    assert quality_var_scale(0.4, good, 75.0, 0.35, 1.5) == 1.0  # above the cap: no matter
    assert quality_var_scale(0.175, good, 75.0, 0.35, 1.5) == pytest.approx(2.0**3)
    assert quality_var_scale(0.175, good, 75.0, 0.35, 1.0) == pytest.approx(2.0**2)
    low = np.linspace(0.12, 0.22, 30)  # gravel-like terrain: the 75th percentile is 0.195
    assert quality_var_scale(0.2, low, 75.0, 0.35, 1.5) == 1.0
    assert quality_var_scale(0.13, low, 75.0, 0.35, 1.5) == pytest.approx((0.195 / 0.13) ** 3)
    assert quality_var_scale(0.0, low, 75.0, 0.35, 1.5) > 1e6  # no division by zero


def test_quality_var_scale_trusts_a_peak_above_the_recent_ones_and_the_cap_more():
    """A fix matched well above the recent fixes' percentile and the cap counts more, by (q_hi / q)^(2 power)
    down to ``bonus_min``; one above the cap but not above the recent peaks does not."""
    low = np.r_[np.linspace(0.12, 0.22, 29), 0.6]  # off a featureless stretch: one strong match
    assert quality_var_scale(0.6, low, 75.0, 0.35, 1.5, 0.25) == 0.25  # (0.35 / 0.6)^3 = 0.2, floored
    assert quality_var_scale(0.42, low, 75.0, 0.35, 1.5, 0.25) == pytest.approx((0.35 / 0.42) ** 3)
    assert quality_var_scale(0.6, low, 75.0, 0.35, 1.5) == 1.0  # bonus off
    good = np.full(30, 0.6)
    assert quality_var_scale(0.6, good, 75.0, 0.35, 1.5, 0.25) == 1.0  # as good as the recent ones
    assert quality_var_scale(0.9, good, 75.0, 0.35, 1.5, 0.25) == pytest.approx((0.6 / 0.9) ** 3)


def test_backend_weights_low_peak_fixes_less():
    """Every other fix has a low peak and is 1.5 m off to the east (as a bad match is, in a run); the
    good ones scatter 0.1 m. Weighted by their peaks the window stays near the good fixes; weighted alike it
    is pulled about halfway to the bad ones."""
    T, P, ok, ol, opx, rng = _scene(5, n_kf=30)
    low = {i: i % 2 == 1 for i in range(len(T))}
    fixes = {
        i: T[i, :3, 3] + (np.array([0.0, 1.5, 0.0]) if low[i] else rng.normal(0, 0.1, 3))
        for i in range(len(T))
    }
    snap_all = _snapshot(T, P, ok, ol, opx)
    current = {"k": 0}

    def locate(image, R, p, alt, solve_rotation_scale):
        f = _Fix(fixes[current["k"]])
        f.quality = 0.15 if low[current["k"]] else 0.5
        return f

    east_err = {}
    for window in (0, 30):
        be = Backend(BackendOptions(lba=LbaOptions(w_geo=10.0), geo_quality_window=window), locate)
        for k in range(2, len(T)):
            current["k"] = k
            res = be.process(_first_kfs_job(snap_all, T, k))
        assert res.counters["fix_rejected"] == 0  # the gate takes the nominal sigma: none is gated
        idx = res.kf_ids.astype(int)
        east_err[window] = float(np.mean(res.T_world_cam[:, 1, 3] - T[idx, 1, 3]))
    assert east_err[0] > 0.5
    assert abs(east_err[30]) < 0.25
    # the covariance sent still counts the weak fixes' scatter in full: its variance factor is the same
    # with their larger sigma forgotten
    solved = SimpleNamespace(kf_ids=res.kf_ids, T_world_cam=res.T_world_cam)
    assert max(f[6] for f in be.fixes.values()) > 10.0
    vf = be._variance_factor(solved)
    for f in be.fixes.values():
        f[6] = 1.0
    assert vf > 2.0 and vf == be._variance_factor(solved)


def test_biased_geo_factor_jacobian_matches_numerical_derivative():
    lever = np.array([0.05, -0.1, 100.0])
    g = np.array([3.0, -2.0, -2.0])
    noise = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
    f = biased_geo_factor(X(0), B(0), g, lever, noise)
    rng = np.random.default_rng(5)
    for _ in range(5):
        pose = gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(0, 0.5, 3)), rng.normal(0, 5, 3))
        b = rng.normal(0, 0.5, 3)
        v = gtsam.Values()
        v.insert(X(0), pose)
        v.insert(B(0), b)
        np.testing.assert_allclose(
            f.unwhitenedError(v), pose.rotation().matrix() @ lever + pose.translation() + b - g, atol=1e-9
        )
        A, _ = f.linearize(v).jacobian()

        def err(p: gtsam.Pose3, b: np.ndarray = b) -> np.ndarray:
            return p.rotation().matrix() @ lever + p.translation() + b - g

        np.testing.assert_allclose(A[:, :6], numericalDerivative11(err, pose), atol=1e-5)
        np.testing.assert_allclose(A[:, 6:], np.eye(3), atol=1e-12)


def test_fix_bias_model_recovers_the_window_and_reports_horizontal_biases():
    T, P, ok, ol, opx, rng = _scene(0)
    prob = _problem(T, P, ok, ol, opx, rng)
    sol = solve_window(prob, LbaOptions(w_geo=10.0, geo_bias_share=0.5))
    assert sol.ok and sol.geo_bias is not None
    assert np.abs(sol.T_world_cam[:, :3, 3] - T[:, :3, 3]).max() < 0.25
    assert sol.geo_bias.shape == (len(T), 3)
    assert np.all(sol.geo_bias[prob.anchor] == 0.0)  # anchors carry no fix, so no bias
    assert np.abs(sol.geo_bias[:, 2]).max() < 0.01  # horizontal only
    assert np.abs(sol.geo_bias[~prob.anchor, :2]).max() > 1e-4  # the fixes' white noise is partly taken
    assert np.all(np.isfinite(sol.geo_whitened[~prob.anchor]))
