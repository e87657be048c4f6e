"""The EKF on the synthetic point scene: IMU propagation consistency, filter consistency (NEES within its
chi-square bounds), first-estimate Jacobians, determinism and time handling."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2
from test_ekf_scene import G, camera_model, detections, make_scene, straight_flight

from companion.ekf import landmarks as lmk
from companion.ekf.features import Detections
from companion.ekf.filter import InverseDepthEkf
from companion.ekf.options import EkfOptions
from companion.ekf.slam import VisThermalSlam
from companion.ekf.so3 import quat_from_rot, rot_log
from sim_bridge.trajectory import ImuNoise, imu_samples

SCENE = make_scene(0, relief_m=0.0)


def _error(truth_p, truth_R, ekf) -> np.ndarray:
    """(6,) truth minus estimate: position, then local attitude (R_true = R_est Exp(e))."""
    return np.concatenate([truth_p - ekf.r, rot_log(ekf.R_world_body.T @ truth_R)])


def _fly(
    seed: int,
    opts: EkfOptions,
    speed_mps: float,
    duration_s: float = 16.0,
    imu_noise: ImuNoise | None = None,
    cam_hz: float = 2.0,
    imu_delay_s: float = 0.0,
    outlier_px: float = 0.0,
    imu_gap_s: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray, VisThermalSlam]:
    """Run the SLAM over the synthetic scene; returns per-frame NEES (F, 2) for (position, attitude), the
    per-frame estimated positions (F, 3) and the SLAM. The initial error is drawn from the filter's prior.
    With ``outlier_px`` a seventh of the keypoints of each frame (a different seventh each frame) is that
    far off its point, in a random direction (a mismatch, or a keypoint on a glint or a shadow's edge). With
    ``imu_gap_s`` = (t0, t1) the IMU is silent from t0 to t1 s, and its last sample before the gap reads a pitch
    rate of 0.05 rad/s more (a wobbling vehicle's rate of the moment, which holding it turns into a tilt)."""
    traj = straight_flight(duration_s=duration_s, speed_mps=speed_mps)
    imu = imu_samples(traj, 100.0, imu_noise, seed)
    slam = VisThermalSlam(opts, {"visible": camera_model()}, G)
    st0 = traj.state_at(0.0)
    slam.start(0, st0.p_world, st0.v_world, quat_from_rot(st0.R_world_body))
    ekf = slam.ekf
    assert ekf is not None
    dx = np.random.default_rng(seed + 1000).multivariate_normal(np.zeros(9), ekf.P[:9, :9])
    ekf._inject(-np.concatenate([dx, np.zeros(ekf.vdim - 9)]))
    rng = np.random.default_rng(seed + 2000)
    t_frames = np.arange(0.5, traj.t1_s, 1.0 / cam_hz)
    t_alt = np.arange(0.05, traj.t1_s, 0.1)
    delay_us = int(imu_delay_s * 1e6)
    keep = np.ones(len(imu.t_us), bool)
    if imu_gap_s is not None:
        keep = (imu.t_us < imu_gap_s[0] * 1e6) | (imu.t_us >= imu_gap_s[1] * 1e6)
        imu.gyro_rps[np.flatnonzero(imu.t_us < imu_gap_s[0] * 1e6)[-1], 1] += 0.05
    events = [(int(t) + delay_us, 0, i) for i, t in enumerate(imu.t_us) if keep[i]]
    events += [(int(t * 1e6), 1, i) for i, t in enumerate(t_alt)]
    events += [(int(t * 1e6), 2, i) for i, t in enumerate(t_frames)]
    events.sort()
    nees: list[list[float]] = []
    est = []
    for arrival, kind, i in events:
        if kind == 0:
            slam.add_imu(int(imu.t_us[i]), imu.accel_mps2[i], imu.gyro_rps[i])
        elif kind == 1:
            st = traj.state_at(arrival * 1e-6)
            slam.add_altimeter(arrival, float(-st.p_world[2] / st.R_world_body[2, 2]) + rng.normal(0, 0.1))
        else:
            st = traj.state_at(arrival * 1e-6)
            det, ids = detections(SCENE, st.R_world_body, st.p_world, rng, pixel_sigma=0.7)
            if outlier_px:
                bad = (ids + len(nees)) % 7 == 0
                ang = rng.uniform(0, 2 * np.pi, int(bad.sum()))
                det.uv[bad] += outlier_px * np.column_stack([np.cos(ang), np.sin(ang)])
            pose = slam.process_frame(arrival, {"visible": det})
            e = _error(st.p_world, st.R_world_body, ekf)
            P = ekf.covariance()[:6, :6]
            nees.append(
                [
                    float(e[:3] @ np.linalg.solve(P[:3, :3], e[:3])),
                    float(e[3:] @ np.linalg.solve(P[3:, 3:], e[3:])),
                ]
            )
            est.append(pose.p_world)
    return np.array(nees), np.array(est), slam


def _bounds(dof: int, runs: int, p: float = 0.995) -> tuple[float, float]:
    """Two-sided bounds of the run-averaged NEES (chi-square with dof * runs degrees of freedom, / runs)."""
    return chi2.ppf(1 - p, dof * runs) / runs, chi2.ppf(p, dof * runs) / runs


def test_imu_propagation_is_consistent():
    traj = straight_flight(duration_s=15.0)
    opts = EkfOptions(initial_position_sigma_m=1e-4, initial_velocity_sigma_mps=1e-4, initial_tilt_sigma_rad=1e-5,
                      initial_yaw_sigma_rad=1e-5, accel_bias_sigma0=0.02, gyro_bias_sigma0=1e-3)  # fmt: skip
    runs = 24
    nees = []
    for seed in range(runs):
        imu = imu_samples(traj, 100.0, ImuNoise(), seed)
        st0 = traj.state_at(0.0)
        f = InverseDepthEkf(opts, st0.p_world, quat_from_rot(st0.R_world_body), st0.v_world, G)
        for k in range(len(imu.t_us) - 1):
            f.propagate(imu.accel_mps2[k], imu.gyro_rps[k], 0.01)
        st = traj.state_at(imu.t_us[-1] * 1e-6)
        e = np.concatenate([_error(st.p_world, st.R_world_body, f), st.v_world - f.v])
        P = f.P[:9, :9]
        nees.append([e[s] @ np.linalg.solve(P[s, s], e[s]) for s in (slice(0, 3), slice(3, 6), slice(6, 9))])
    lo, hi = _bounds(3, runs)
    m = np.mean(nees, axis=0)
    assert np.all(m > lo) and np.all(m < hi), m


def test_slam_is_consistent_on_a_synthetic_flight():
    """Run-averaged NEES of position and attitude within the 99 % chi-square bounds (plus 30 % margin on top
    for the time correlation of the frames and the mild overconfidence EKF-SLAM keeps even with FEJ: we
    measure ~6 for 3 dof), flying at 3 m/s with every IMU error and pixel noise."""
    runs = 5
    opts = EkfOptions(mode="visible", pixel_sigma_px=0.7, seed=0)
    nees = np.mean([_fly(s, opts, 3.0)[0].mean(axis=0) for s in range(runs)], axis=0)
    lo, hi = _bounds(3, runs)
    assert np.all(nees < 1.3 * hi), nees
    assert np.all(nees > 0.5 * lo), nees  # not grossly pessimistic either


def test_first_estimate_jacobians_keep_a_hovering_filter_consistent():
    """With a biased gyro, re-linearising landmarks at their current estimate lets the filter believe a drifting
    position (NEES ~ 90); first-estimate Jacobians keep it honest."""
    imu = ImuNoise(accel_noise_density=1e-7, gyro_noise_density=1e-9, accel_bias_sigma=0.0, gyro_bias_sigma=1e-3,
                   accel_bias_walk=0.0, gyro_bias_walk=0.0)  # fmt: skip
    base = EkfOptions(mode="visible", pixel_sigma_px=0.7, accel_noise_density=1e-7, gyro_noise_density=1e-9,
                      accel_bias_sigma0=1e-6)  # fmt: skip
    runs = 3
    fej = np.mean([_fly(s, base, 0.1, imu_noise=imu)[0][-5:, 0].mean() for s in range(runs)])
    plain = np.mean(
        [
            _fly(s, replace(base, first_estimate_jacobians=False), 0.1, imu_noise=imu)[0][-5:, 0].mean()
            for s in range(runs)
        ]
    )
    _, hi = _bounds(3, runs)
    assert fej < hi, fej
    assert plain > fej


def test_same_seed_same_estimates():
    opts = EkfOptions(mode="visible", seed=3)
    a = _fly(4, opts, 3.0, duration_s=6.0)[1]
    b = _fly(4, opts, 3.0, duration_s=6.0)[1]
    np.testing.assert_array_equal(a, b)


def test_imu_arriving_after_the_frame_changes_little():
    """IMU samples delivered 30 ms late (after the frame) are held over the gap: the estimate stays close to the
    on-time one (the runs drift apart slowly as different landmarks get picked) and stays consistent."""
    opts = EkfOptions(mode="visible", seed=1)
    on_time = _fly(2, opts, 3.0, duration_s=8.0)
    late = _fly(2, opts, 3.0, duration_s=8.0, imu_delay_s=0.03)
    gap = np.linalg.norm(on_time[1] - late[1], axis=1)
    assert gap[0] < 0.01 and np.max(gap[:6]) < 0.1 and np.max(gap) < 1.5, gap
    assert np.mean(late[0][:, 0]) < 2 * _bounds(3, 1)[1]
    assert late[2].counters.late_imu > 0  # samples older than the frame that was processed
    assert on_time[2].counters.stale_frames == 0


def test_an_imu_that_stops_for_two_seconds_is_stood_in_for_by_the_motion_model():
    """IMU silent from 6 to 8.5 s: the filter propagates a constant velocity with the motion model's noise
    (EkfOptions.imu_hold_max_s), keeps matching and stays near the flight with the IMU; holding the last
    sample instead (the hold never expiring) turns its rate into a tilt that leaves the landmarks' gates."""
    opts = EkfOptions(mode="visible", seed=1)
    nees, est, slam = _fly(3, opts, 2.0, duration_s=14.0)
    traj = straight_flight(duration_s=14.0, speed_mps=2.0)
    truth = np.array([traj.state_at(t).p_world for t in np.arange(0.5, traj.t1_s, 0.5)])
    ref = np.linalg.norm(est - truth, axis=1)
    nees_g, est_g, slam_g = _fly(3, opts, 2.0, duration_s=14.0, imu_gap_s=(6.0, 8.5))
    err = np.linalg.norm(est_g - truth, axis=1)
    assert slam.counters.steps_without_imu == 0 and slam_g.counters.steps_without_imu >= 5
    assert np.max(err) < max(0.3, 3 * np.max(ref)), (err, ref)
    assert np.mean(nees_g[:, 0]) < 2 * _bounds(3, 1)[1]
    held = _fly(3, replace(opts, imu_hold_max_s=1e9), 2.0, duration_s=14.0, imu_gap_s=(6.0, 8.5))
    assert np.max(np.linalg.norm(held[1] - truth, axis=1)) > 2 * np.max(err)


def _noiseless_frames(opts: EkfOptions, t_end_s: float, size_px: float | None = None):
    """Run the SLAM (both cameras given; the mode picks) on the straight flight with a noiseless IMU and
    altimeter, a frame every 0.5 s up to ``t_end_s``; yields (slam, pose) after each frame. ``size_px``: every
    keypoint's SIFT size (None: unknown)."""
    traj = straight_flight(duration_s=16.0)
    slam = VisThermalSlam(opts, {"visible": camera_model(), "thermal": camera_model()}, G)
    st0 = traj.state_at(0.0)
    slam.start(0, st0.p_world, st0.v_world, quat_from_rot(st0.R_world_body))
    rng = np.random.default_rng(0)
    imu = imu_samples(traj, 100.0, None, 0)
    k = 0
    for t in np.arange(0.5, t_end_s, 0.5):
        t_us = int(t * 1e6)
        while k < len(imu.t_us) and imu.t_us[k] <= t_us:
            slam.add_imu(int(imu.t_us[k]), imu.accel_mps2[k], imu.gyro_rps[k])
            k += 1
        st = traj.state_at(t)
        slam.add_altimeter(t_us, float(-st.p_world[2] / st.R_world_body[2, 2]))
        det, _ = detections(SCENE, st.R_world_body, st.p_world, rng)
        if size_px is not None:
            det = Detections(det.uv, det.desc, np.full(len(det), size_px))
        yield slam, slam.process_frame(t_us, {c: det for c in slam.camera_names})


@pytest.mark.parametrize("mode", ["visible", "dual"])
def test_landmark_budget_and_bookkeeping(mode):
    for slam, pose in _noiseless_frames(EkfOptions(mode=mode, max_landmarks_per_camera=12, seed=0), 7.0):
        ekf = slam.ekf
        assert ekf.P.shape == (19 + 6 * ekf.n_landmarks,) * 2  # the vehicle, the facet error, the landmarks
        assert len(ekf.y_first) == len(ekf.lm_id) == ekf.n_landmarks
        for ci, c in enumerate(slam.camera_names):
            assert pose.n_landmarks[c] == int(np.sum(ekf.lm_cam == ci)) <= 12
        assert set(slam._desc) == set(ekf.lm_id.tolist())
        np.testing.assert_allclose(pose.covariance, pose.covariance.T)
        assert np.all(np.linalg.eigvalsh(pose.covariance) > 0)
    assert sum(pose.matched.values()) >= 8 * len(slam.camera_names)


def _cross_camera_spacing(over_map: bool, seed: int) -> float:
    """Mean pixel distance from each thermal landmark to the nearest visible one after the first dual frame
    (both cameras see the same keypoints; visible samples first, then thermal)."""
    opts = EkfOptions(mode="dual", max_landmarks_per_camera=12, seed=seed, diversity_over_map=over_map)
    slam, _ = next(_noiseless_frames(opts, 0.6))
    ekf = slam.ekf
    uv = {}
    for ci, c in enumerate(slam.camera_names):
        idx = np.flatnonzero(ekf.lm_cam == ci)
        uv[c] = lmk.project(ekf.y[idx], ekf.r, ekf.R_world_body, slam.cameras[c]).uv
    d = np.linalg.norm(uv["thermal"][:, None, :] - uv["visible"][None, :, :], axis=2)
    return float(d.min(axis=1).mean())


def test_dual_diversity_counts_the_other_cameras_landmarks():
    """Paper 2 eq. 8 over the dual map: thermal's new landmarks go where visible has none, so the two
    cameras' layouts interleave instead of piling up on the same spots."""
    joint = np.mean([_cross_camera_spacing(True, s) for s in range(6)])
    separate = np.mean([_cross_camera_spacing(False, s) for s in range(6)])
    assert joint > 1.3 * separate, (joint, separate)


@pytest.mark.parametrize("anchor", [True, False])
def test_landmarks_are_matched_against_their_first_descriptor(anchor):
    """By default a landmark keeps the descriptor it was created with; with ``anchor_descriptor=False`` it
    takes each matched keypoint's (the synthetic keypoints carry fresh descriptor noise every frame)."""
    opts = EkfOptions(mode="visible", max_landmarks_per_camera=12, seed=0, anchor_descriptor=anchor)
    first: dict[int, np.ndarray] = {}
    kept, changed = 0, 0
    for slam, _ in _noiseless_frames(opts, 5.0):
        for lid, d in slam._desc.items():
            if lid not in first:
                first[lid] = d.copy()
            elif np.array_equal(first[lid], d):
                kept += 1
            else:
                changed += 1
    assert kept + changed > 50
    assert (changed == 0) if anchor else (changed > 5 * kept)  # the unmatched ones keep theirs


def test_imu_before_the_first_frame_is_bounded():
    """A camera that never starts must not make the IMU queue grow without bound."""
    slam = VisThermalSlam(EkfOptions(mode="visible"), {"visible": camera_model()}, G)
    for k in range(5000):
        slam.add_imu(k * 10_000, np.array([0.0, 0.0, -G]), np.zeros(3))
    assert len(slam._queue) <= 26
    assert slam.latest_imu() is not None


def test_match_sigma_follows_the_keypoint_size():
    o = EkfOptions(pixel_sigma_px=0.8, pixel_sigma_thermal_px=0.4)
    assert o.match_sigma("visible", 30.0) == 0.8  # 0 (the default): every match the camera's sigma
    o = replace(o, pixel_sigma_size_ref_px=7.2)
    assert o.match_sigma("visible", 7.2) == pytest.approx(0.8)
    assert o.match_sigma("visible", 14.4) == pytest.approx(1.6)
    assert o.match_sigma("thermal", 14.4) == pytest.approx(0.8)
    assert o.match_sigma("visible", 1.0) == pytest.approx(0.4)  # at least half the camera's sigma
    assert o.match_sigma("visible", 100.0) == pytest.approx(3.2)  # at most four times
    assert o.match_sigma("visible", None) == 0.8  # size unknown
    with pytest.raises(ValueError, match="pixel_sigma_size_ref_px"):
        EkfOptions(pixel_sigma_size_ref_px=-1.0)


@pytest.mark.parametrize("size_px, looser", [(28.8, True), (3.6, False)])
def test_matches_are_weighed_by_their_keypoints_size(size_px, looser):
    """With ``pixel_sigma_size_ref_px`` the same matches of coarse keypoints (4x the reference) leave the
    filter less sure of its position than one sigma for all, those of fine keypoints (half of it) surer."""
    sigma = {}
    for ref in (0.0, 7.2):
        opts = EkfOptions(mode="visible", max_landmarks_per_camera=16, pixel_sigma_size_ref_px=ref, seed=0)
        pose = list(_noiseless_frames(opts, 5.0, size_px=size_px))[-1][1]
        assert sum(pose.matched.values()) >= 8
        sigma[ref] = float(np.sqrt(np.trace(pose.covariance[:3, :3])))
    assert (sigma[7.2] > 1.1 * sigma[0.0]) if looser else (sigma[7.2] < 0.9 * sigma[0.0]), sigma


def test_pixel_sigma_per_camera():
    o = EkfOptions(pixel_sigma_px=1.2)
    assert (o.pixel_sigma("visible"), o.pixel_sigma("thermal")) == (1.2, 1.2)  # 0: the same for both
    o = EkfOptions(pixel_sigma_px=1.2, pixel_sigma_thermal_px=0.5)
    assert (o.pixel_sigma("visible"), o.pixel_sigma("thermal")) == (1.2, 0.5)


@pytest.mark.parametrize("sigma", [0.8, np.array([0.8, 0.4, 0.8, 0.4])])  # one for all, or per camera
def test_sparse_landmark_update_equals_the_dense_update(sigma):
    import copy

    from companion.ekf.landmarks import initialise, project

    rng = np.random.default_rng(4)
    traj = straight_flight(duration_s=20.0)
    st = traj.state_at(0.0)
    f = InverseDepthEkf(EkfOptions(), st.p_world, quat_from_rot(st.R_world_body), st.v_world, G)
    cam = camera_model()
    uv = rng.uniform([20, 20], [620, 460], (10, 2))
    y, Jp, Ju = initialise(uv, np.full(10, 0.01), f.r, f.R_world_body, cam)
    f.add_landmarks(y, Jp, Ju, 1.0, np.full(10, 0.003), 0)
    for _ in range(50):  # some propagation so the cross terms are non-trivial
        f.propagate(np.array([0.1, -0.05, -G]), np.array([0.01, 0.0, -0.02]), 0.01)
    sel = np.array([1, 4, 5, 8])
    pr = project(f.y[sel], f.r, f.R_world_body, cam)
    res = rng.normal(0, 1.0, (4, 2))
    a, b = copy.deepcopy(f), copy.deepcopy(f)
    S = a.landmark_innovation_covariances(sel, pr.H_pose, pr.H_lm, sigma)
    a.update_landmarks(sel, pr.H_pose, pr.H_lm, res, sigma)
    H = np.zeros((8, b.P.shape[0]))
    for k, i in enumerate(sel):
        H[2 * k : 2 * k + 2, :6] = pr.H_pose[k]
        H[2 * k : 2 * k + 2, b.lm_slice(int(i))] = pr.H_lm[k]
    R = np.diag(np.repeat(np.broadcast_to(sigma, (4,)) ** 2, 2))
    S_dense = b.innovation_covariance(H, R)
    for k in range(4):
        np.testing.assert_allclose(S[k], S_dense[2 * k : 2 * k + 2, 2 * k : 2 * k + 2], rtol=1e-10)
    b.update(H, res.ravel(), R)
    np.testing.assert_allclose(a.P, b.P, atol=1e-12)
    np.testing.assert_allclose(a.y, b.y, atol=1e-12)
    np.testing.assert_allclose(a.r, b.r, atol=1e-12)


@pytest.mark.parametrize("m, facet_state", [(1, False), (2, False), (1, True)])
def test_column_update_equals_the_dense_update(m, facet_state):
    """``update_columns`` (the altimeter's path; in-place rank-1 form for one row) = ``update`` with dense H,
    also with the facet error state between the vehicle and the landmarks."""
    import copy

    from companion.ekf.landmarks import initialise

    rng = np.random.default_rng(5)
    st = straight_flight(duration_s=20.0).state_at(0.0)
    f = InverseDepthEkf(
        EkfOptions(facet_error_state=facet_state), st.p_world, quat_from_rot(st.R_world_body), st.v_world, G
    )
    assert f.vdim == (19 if facet_state else 18)
    if facet_state:
        f.reset_facet_error(0.8)
    uv = rng.uniform([20, 20], [620, 460], (6, 2))
    y, Jp, Ju = initialise(uv, np.full(6, 0.01), f.r, f.R_world_body, camera_model())
    f.add_landmarks(y, Jp, Ju, 1.0, np.full(6, 0.003), 0)
    for _ in range(30):
        f.propagate(np.array([0.1, -0.05, -G]), np.array([0.01, 0.0, -0.02]), 0.01)
    cols = np.r_[0:6, f.lm_slice(2), f.lm_slice(4)] if not facet_state else np.r_[0:6, 18, f.lm_slice(2)]
    Hc = rng.normal(0, 1.0, (m, len(cols)))
    res, Rm = rng.normal(0, 0.1, m), np.eye(m) * 0.05
    a, b = copy.deepcopy(f), copy.deepcopy(f)
    H = np.zeros((m, b.P.shape[0]))
    H[:, cols] = Hc
    np.testing.assert_allclose(a.innovation_covariance_columns(cols, Hc, Rm), b.innovation_covariance(H, Rm))
    a.update_columns(cols, Hc, res, Rm)
    b.update(H, res, Rm)
    np.testing.assert_allclose(a.P, b.P, atol=1e-12)
    np.testing.assert_allclose(a.y, b.y, atol=1e-12)
    np.testing.assert_allclose(a.r, b.r, atol=1e-12)
    assert a.facet_c == pytest.approx(b.facet_c, abs=1e-12)
    assert (a.facet_c != 0.0) == facet_state  # the correction reaches c only when it is a state


def test_facet_error_is_a_gauss_markov_state_reset_per_facet():
    """c keeps its stationary sigma while it decays toward 0 with tau; a new facet makes it independent of the
    rest of the state again."""
    st = straight_flight(duration_s=20.0).state_at(0.0)
    opts = EkfOptions(facet_error_state=True, facet_error_tau_s=2.0)
    f = InverseDepthEkf(opts, st.p_world, quat_from_rot(st.R_world_body), st.v_world, G)
    f.reset_facet_error(0.5)
    H = np.zeros((1, f.vdim))
    H[0, 2], H[0, 18] = -1.0, 1.0  # a range: minus the height, plus c
    f.update(H, np.array([0.3]), np.array([[0.01]]))
    assert f.facet_c > 0 and f.P[18, 2] != 0.0  # c and the height now correlated
    c0, var0 = f.facet_c, f.P[18, 18]
    for _ in range(100):  # 1 s
        f.propagate(np.array([0.0, 0.0, -G]), np.zeros(3), 0.01)
    assert f.facet_c == pytest.approx(c0 * np.exp(-0.5), rel=1e-9)
    phi2 = np.exp(-1.0)  # variance: phi^2 var0 + sigma^2 (1 - phi^2), sigma the stationary 0.5 m
    assert f.P[18, 18] == pytest.approx(phi2 * var0 + 0.25 * (1 - phi2), rel=1e-6)
    f.reset_facet_error(0.7)
    assert f.facet_c == 0.0 and f.P[18, 18] == pytest.approx(0.49)
    assert not np.any(np.delete(f.P[18], 18)) and not np.any(np.delete(f.P[:, 18], 18))


@pytest.mark.parametrize("rows", [1, 3])
def test_altimeter_bias_is_a_consider_state(rows):
    """Schmidt update: every block of P and every correction as the optimal update gives them, except the
    bias's own variance (unchanged) and its correction (none), on both update paths."""
    import copy

    rng = np.random.default_rng(7)
    st = straight_flight(duration_s=20.0).state_at(0.0)
    opts = EkfOptions(facet_error_state=True, altimeter_bias_sigma_m=0.3)
    f = InverseDepthEkf(opts, st.p_world, quat_from_rot(st.R_world_body), st.v_world, G)
    assert f.vdim == 20 and f.idx_bias == 19 and f.P[19, 19] == pytest.approx(0.09)
    f.reset_facet_error(0.8)
    for _ in range(30):
        f.propagate(np.array([0.1, -0.05, -G]), np.array([0.01, 0.0, -0.02]), 0.01)
    assert f.P[19, 19] == pytest.approx(0.09)  # constant: no process noise
    cols = np.array([0, 2, 4, 18, 19])
    Hc = rng.normal(0, 1.0, (rows, len(cols)))
    Hc[:, 3:] = 1.0  # measured = ... + c + b
    res, Rm = rng.normal(0, 0.3, rows), np.eye(rows) * 0.02
    H = np.zeros((rows, f.vdim))
    H[:, cols] = Hc
    P0 = f.covariance().copy()
    S = H @ P0 @ H.T + Rm
    K = P0 @ H.T @ np.linalg.inv(S)
    P_opt = P0 - K @ S @ K.T
    dx_opt = K @ res
    r0 = f.r.copy()
    for which in ("columns", "dense"):
        g = copy.deepcopy(f)
        dx = g.update_columns(cols, Hc, res, Rm) if which == "columns" else g.update(H, res, Rm)
        assert dx[19] == 0.0, which
        np.testing.assert_allclose(dx[:19], dx_opt[:19], atol=1e-12)
        np.testing.assert_allclose(g.r, r0 + dx_opt[:3], atol=1e-12)
        assert g.P[19, 19] == pytest.approx(0.09, abs=1e-15), which
        np.testing.assert_allclose(g.P[:19, :], P_opt[:19, :], atol=1e-12)
        np.testing.assert_allclose(g.P[:19, 19], P_opt[:19, 19], atol=1e-12)
    assert np.any(P_opt[:19, 19] != P0[:19, 19])  # the cross-covariance did change: the test sees it


def test_facet_reuse_check_follows_the_beam():
    from companion.ekf.altimeter import facet_encloses_beam, select_facet

    R = np.eye(3)  # level, body down = world down
    pts = np.array([[10.0, 0.0, 50.0], [-6.0, 8.0, 50.0], [-6.0, -8.0, 50.0], [30.0, 30.0, 50.0]])
    idx = select_facet(pts, np.zeros(3), R)
    assert idx is not None and sorted(idx.tolist()) == [0, 1, 2]
    assert facet_encloses_beam(pts[idx], np.zeros(3), R)
    assert not facet_encloses_beam(pts[idx], np.array([20.0, 0.0, 0.0]), R)  # beam has left the triangle
    assert not facet_encloses_beam(pts[idx], np.array([0.0, 0.0, 60.0]), R)  # points above the vehicle
