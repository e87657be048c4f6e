"""Visual odometry (companion.vo): triangulation, PnP, known-rotation two-view, key-frame criteria,
Lucas-Kanade tracking, and the odometry on rendered frames of a simulated scene."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from companion.constants import R_BODY_CAM_NADIR
from companion.geometry import CameraIntrinsics, camera_pose, make_T, rot_from_rpy
from companion.vo.geometry import (
    PnpOptions,
    TwoViewOptions,
    relative_pose_rotation_prior,
    reproject,
    solve_pnp,
    translation_known_rotation,
    triangulate,
)
from companion.vo.keyframes import KeyframeOptions, is_keyframe
from companion.vo.odometry import VisualOdometry, VoOptions, down_in_cam, gravity_in_cam, tilt_toward
from companion.vo.tracking import TrackerOptions, detect, track

INTR = CameraIntrinsics.from_focal_sensor(480, 480, 36, 36)
K = INTR.K


def _pose(roll, pitch, yaw, p):
    return make_T(rot_from_rpy(roll, pitch, yaw) @ R_BODY_CAM_NADIR, np.asarray(p, float))


def _ground(rng, n=400):
    return np.c_[rng.uniform(-40, 40, n), rng.uniform(-40, 40, n), rng.uniform(-10, 10, n)]


def test_triangulation_recovers_points_and_rejects_bad_ones():
    rng = np.random.default_rng(0)
    T1 = _pose(0.01, -0.02, 0.3, [0.0, 0.0, -100.0])
    T2 = _pose(-0.01, 0.02, 0.32, [6.0, 2.0, -100.5])
    P = _ground(rng)
    uv1, _ = reproject(K, T1, P)
    uv2, _ = reproject(K, T2, P)
    X, ok = triangulate(K, T1, T2, uv1, uv2)
    assert ok.mean() > 0.95
    np.testing.assert_allclose(X[ok], P[ok], atol=1e-6)
    # a mismatched pair does not reproject and is rejected
    uv2_bad = uv2.copy()
    uv2_bad[:10] += 15.0
    _, ok_bad = triangulate(K, T1, T2, uv1, uv2_bad)
    assert not ok_bad[:10].any()
    # no baseline: no parallax, nothing kept
    _, ok0 = triangulate(K, T1, T1, uv1, uv1)
    assert not ok0.any()


def test_pnp_with_outliers():
    rng = np.random.default_rng(1)
    T = _pose(0.05, -0.03, 1.0, [20.0, -5.0, -95.0])
    P = _ground(rng, 300) + np.array([20.0, -5.0, 0.0])
    uv, _ = reproject(K, T, P)
    uv += rng.normal(0, 0.3, uv.shape)
    bad = rng.choice(len(P), 60, replace=False)
    uv[bad] += rng.uniform(-60, 60, (60, 2))
    res = solve_pnp(K, P, uv, PnpOptions())
    assert res.ok
    assert np.linalg.norm(res.T_world_cam[:3, 3] - T[:3, 3]) < 0.3
    dR = res.T_world_cam[:3, :3].T @ T[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.2
    assert res.inliers[bad].mean() < 0.1
    assert res.inliers[np.setdiff1d(np.arange(len(P)), bad)].mean() > 0.95
    assert not solve_pnp(K, P[:5], uv[:5]).ok


@pytest.mark.parametrize("direction", [(1.0, 0.0, 0.0), (0.3, -0.9, 0.05)])
def test_translation_with_known_rotation(direction):
    rng = np.random.default_rng(2)
    d = np.asarray(direction) / np.linalg.norm(direction)
    T0 = _pose(0.02, 0.01, 0.0, [0.0, 0.0, -100.0])
    T1 = _pose(0.05, -0.03, 0.1, T0[:3, 3] + 5.0 * d)
    P = _ground(rng, 300)
    P[:, 2] = rng.uniform(-1.0, 1.0, len(P))  # nearly planar: the case the five-point solver finds hard
    uv0, _ = reproject(K, T0, P)
    uv1, _ = reproject(K, T1, P)
    uv1 += rng.normal(0, 0.3, uv1.shape)
    uv1[:20] += 20.0
    d_hat, inl = translation_known_rotation(K, T0[:3, :3], T1[:3, :3], uv0, uv1)
    assert np.degrees(np.arccos(np.clip(d_hat @ d, -1, 1))) < 1.5
    assert inl[20:].mean() > 0.9 and inl[:20].mean() < 0.2


def test_two_views_with_a_noisy_attitude_take_the_rotation_from_the_matches():
    """The map's first two views, 5 m apart at 100 m over ground with 20 m of relief (the Table 7 start-up:
    25 px of parallax), the second view's attitude 5 mrad off (two attitude samples' noise), ten draws of
    the pixel noise. Taken as exact, that attitude turns the displacement by over 4 degrees; refined from
    the matches with the attitude as a prior the displacement is within a degree (median) and the rotation
    error shrinks to well under the 5 mrad. (Without the prior, the matches alone leave rotation and
    displacement nearly interchangeable over so short a base.)"""
    d = np.array([0.1, -1.0, 0.0]) / np.linalg.norm([0.1, -1.0, 0.0])
    T0 = _pose(0.0, 0.0, -1.57, [0.0, 0.0, -100.0])
    T1 = _pose(-0.03, -0.2, -1.61, T0[:3, 3] + 5.0 * d)
    R1_att = Rotation.from_rotvec([0.004, -0.003, 0.0]).as_matrix() @ T1[:3, :3]

    def angle_deg(a, b):
        return np.degrees(np.arccos(np.clip(a @ b, -1, 1)))

    plain, refined, rot_mrad = [], [], []
    for seed in range(10):
        rng = np.random.default_rng(seed)
        P = _ground(rng, 300)
        uv0, _ = reproject(K, T0, P)
        uv1, _ = reproject(K, T1, P)
        uv0 += rng.normal(0, 0.3, uv0.shape)
        uv1 += rng.normal(0, 0.3, uv1.shape)
        uv1[:15] += 12.0
        R_same, d_plain, _ = relative_pose_rotation_prior(K, T0[:3, :3], R1_att, uv0, uv1, TwoViewOptions())
        assert R_same is R1_att
        R1, d_hat, inl = relative_pose_rotation_prior(
            K, T0[:3, :3], R1_att, uv0, uv1, TwoViewOptions(rotation_prior_sigma_rad=0.006)
        )
        plain.append(angle_deg(d_plain, d))
        refined.append(angle_deg(d_hat, d))
        rot_mrad.append(1e3 * np.linalg.norm(Rotation.from_matrix(R1 @ T1[:3, :3].T).as_rotvec()))
        assert inl[15:].mean() > 0.9 and inl[:15].mean() < 0.2
    assert min(plain) > 4.0
    assert np.median(refined) < 1.0 and max(refined) < 3.0
    assert np.median(rot_mrad) < 2.0


def test_keyframe_criteria():
    o = KeyframeOptions(
        min_frames_between=20, min_features=50, max_tracked_ratio=0.9, force_below_features=30
    )
    assert is_keyframe(20, 200, 170, 200, o)  # all three criteria hold (85 % tracked)
    assert not is_keyframe(19, 200, 170, 200, o)  # too soon
    assert not is_keyframe(20, 50, 40, 200, o)  # too few features (and not weak enough to force)
    assert not is_keyframe(40, 200, 190, 200, o)  # still tracks 95 % of the reference
    assert is_keyframe(5, 20, 20, 200, o)  # weak tracking forces one
    assert not is_keyframe(1, 20, 20, 200, o)


def test_klt_tracks_a_subpixel_shift():
    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (480, 480)).astype(np.float32), (0, 0), 2.0)
    tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)
    img0 = tex.astype(np.uint8)
    shift = np.array([1.37, -0.62])
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    img1 = cv2.warpAffine(tex, M, (480, 480), flags=cv2.INTER_CUBIC).astype(np.uint8)
    o = TrackerOptions()
    pts = detect(img0, np.zeros((0, 2)), 200, o)
    assert len(pts) > 100
    # spacing and border respected
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2) + np.eye(len(pts)) * 1e3
    assert d.min() >= o.min_distance_px / 2  # (sub-pixel refinement moves corners by a few pixels)
    p1, ok = track(img0, img1, pts, o)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(np.median(p1[ok] - pts[ok], axis=0), shift, atol=0.05)
    # ORB detector (the paper's) gives corners too
    orb = detect(img0, np.zeros((0, 2)), 100, TrackerOptions(detector="orb"))
    assert len(orb) > 50


def render_flight():
    """A short forward flight over a small scene: rendered frames, attitude with noise, altimeter."""
    from sim_bridge.render import VisibleRenderer
    from sim_bridge.terrain import make_scene
    from sim_bridge.trajectory import forward

    scene = make_scene("01", seed=0, size_m=300.0)
    rend = VisibleRenderer(scene.dem, scene.albedo, scene.sun, INTR)
    traj = forward((-50.0, -30.0), np.radians(40.0), 100.0, 4.0, 14.0)
    rng = np.random.default_rng(4)
    out = []
    for k, t in enumerate(np.arange(0.0, 14.0, 1 / 7.5)):
        s = traj.state_at(t)
        R_wc, p_c = camera_pose(s.R_world_body, s.p_world)
        img = rend.render(R_wc, p_c, seed=k)
        dR = rot_from_rpy(*rng.normal(0, 0.003, 3))
        h = -s.p_world[2] - float(scene.dem.height_at(s.p_world[0], s.p_world[1])[0])
        out.append((int(t * 1e6), img, dR @ R_wc, h / s.R_world_body[2, 2], s.p_world.copy(), R_wc))
    return out


@pytest.fixture(scope="module")
def flight():
    return render_flight()


def test_odometry_on_rendered_frames(flight):
    vo = VisualOdometry(VoOptions(), K)
    errs, n_kf = [], 0
    for k, (stamp, img, R_att, rng_m, p_true, _R_true) in enumerate(flight):
        st = vo.process(img, stamp, R_att, rng_m, flight[0][4] if k == 0 else None)
        assert st.state != "lost"
        if st.keyframe_id is not None:
            n_kf += 1
        if st.T_world_cam is not None:
            errs.append(np.linalg.norm(st.T_world_cam[:3, 3] - p_true))
    assert vo.state == "tracking"
    assert len(errs) > 0.6 * len(flight)  # initialised within the first seconds
    assert n_kf >= 3
    # about 50 m flown on the front-end alone (no bundle adjustment; altimeter scale, noisy attitude)
    flown = np.linalg.norm(flight[-1][4] - flight[0][4])
    assert np.max(errs) < 0.15 * flown
    assert len(vo.lm) > 100


def _snapshot_by_walking_obs(vo: VisualOdometry, window_size: int, max_anchors: int):
    """The window snapshot written plainly from ``vo.obs`` (point -> {key frame: pixel}): the reference for the
    array-based ``VisualOdometry.snapshot``."""
    win = sorted(vo.kfs)[-window_size:]
    lm_ids = sorted({int(t) for k in win for t in vo.kfs[k].ids if int(t) in vo.lm})
    older = {k for t in lm_ids for k in vo.obs.get(t, {}) if k not in win and k in vo.kfs}
    kf_ids = sorted(sorted(older, reverse=True)[:max_anchors]) + win
    index = {k: i for i, k in enumerate(kf_ids)}
    kept: list[int] = []
    obs: list[tuple[int, int, object]] = []
    for t in lm_ids:
        o = [(index[k], px) for k, px in vo.obs[t].items() if k in index]
        if len(o) >= 2:
            obs += [(i, len(kept), px) for i, px in o]
            kept.append(t)
    return kf_ids, kept, obs


def test_window_snapshot_equals_the_observation_map_after_outliers_are_dropped(flight):
    vo = VisualOdometry(VoOptions(), K)
    for k, (stamp, img, R_att, rng_m, _p, _R) in enumerate(flight):
        vo.process(img, stamp, R_att, rng_m, flight[0][4] if k == 0 else None)
    assert len(vo.kfs) >= 4
    # the adjustment drops some observations as outliers (nothing moves): the snapshot must forget them
    rng = np.random.default_rng(0)
    pairs = [(k, int(t)) for k, kf in vo.kfs.items() for t in kf.ids if int(t) in vo.lm]
    drop = [pairs[i] for i in rng.choice(len(pairs), 40, replace=False)]
    kf_ids = np.array(sorted(vo.kfs))
    lm_ids = np.array(sorted(vo.lm))
    vo.apply_correction(
        int(kf_ids[-1]),
        np.eye(4),
        kf_ids,
        np.stack([vo.kfs[k].T_world_cam for k in kf_ids]),
        lm_ids,
        np.stack([vo.lm[t] for t in lm_ids]),
        np.array([k for k, _ in drop]),
        np.array([t for _, t in drop]),
    )
    for window, anchors in ((3, 2), (2, 0), (100, 5)):
        snap = vo.snapshot(window, anchors)
        ref_kf, ref_lm, ref_obs = _snapshot_by_walking_obs(vo, window, anchors)
        assert snap.kf_ids.tolist() == ref_kf
        assert snap.lm_ids.tolist() == ref_lm
        assert list(zip(snap.obs_kf.tolist(), snap.obs_lm.tolist())) == [(i, j) for i, j, _ in ref_obs]
        np.testing.assert_array_equal(snap.obs_px, np.array([px for _, _, px in ref_obs]))
        np.testing.assert_array_equal(snap.p_world, np.stack([vo.lm[t] for t in ref_lm]))
        assert snap.anchor.tolist() == [k not in sorted(vo.kfs)[-window:] for k in ref_kf]
        dropped = {(k, t) for k, t in drop}
        assert not dropped & {
            (int(snap.kf_ids[i]), int(snap.lm_ids[j])) for i, j in zip(snap.obs_kf, snap.obs_lm)
        }


def test_key_frame_gravity_averages_the_attitude_noise_and_ignores_the_map_tilt():
    """Known answer: frames along a turn, the VO's rotations exact but the whole map tilted 20 mrad, the
    autopilot's roll / pitch with 3 mrad of white noise: 20 frames' average is within the noise over
    sqrt(20) of the true down in the newest frame, one sample is not, and the map's tilt is gone."""
    rng = np.random.default_rng(3)
    R_map = rot_from_rpy(0.02, -0.015, 0.0)  # the VO's world, tilted
    e_z = np.array([0.0, 0.0, 1.0])
    one, avg = [], []
    for trial in range(200):
        R_true = [rot_from_rpy(0.1 + 0.01 * j, -0.05, 0.3 * j + trial) @ R_BODY_CAM_NADIR for j in range(20)]
        R_att = [rot_from_rpy(*rng.normal(0, 0.003, 2), 0.0) @ R for R in R_true]
        downs = [R_map @ R @ down_in_cam(Ra) for R, Ra in zip(R_true, R_att)]
        truth = R_true[-1].T @ e_z
        avg.append(np.arccos(np.clip(gravity_in_cam(R_map @ R_true[-1], downs) @ truth, -1, 1)))
        one.append(np.arccos(np.clip(gravity_in_cam(R_map @ R_true[-1], downs[-1:]) @ truth, -1, 1)))
    # mean of a 2-D Gaussian's norm: sigma * sqrt(pi / 2)
    assert np.mean(one) == pytest.approx(0.003 * np.sqrt(np.pi / 2), rel=0.15)
    assert np.mean(avg) == pytest.approx(0.003 / np.sqrt(20) * np.sqrt(np.pi / 2), rel=0.15)


def test_tilt_toward_turns_the_camera_about_the_ground_it_sees():
    """Known answer: a nadir camera 100 m up, seen 2 mrad tilted with its position shifted so that the ground
    at the image centre is right (the PnP ambiguity). All the way to the true down gives back the true pose;
    half way halves the tilt; the ground point on the optical axis and the heading never move."""
    T_true = _pose(0.0, 0.0, 0.7, [10.0, -4.0, -100.0])
    ground = T_true[:3, 3] + T_true[:3, 2] * 100.0
    tilt = Rotation.from_rotvec([0.0012, -0.0016, 0.0]).as_matrix()  # 2 mrad about a horizontal axis
    T_seen = make_T(tilt @ T_true[:3, :3], ground + tilt @ (T_true[:3, 3] - ground))
    down_true = T_true[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    full = tilt_toward(T_seen, down_true, 1.0, 100.0)
    np.testing.assert_allclose(full, T_true, atol=1e-9)
    half = tilt_toward(T_seen, down_true, 0.5, 100.0)
    ang = np.arccos(np.clip(half[:3, :3].T @ np.array([0.0, 0.0, 1.0]) @ down_true, -1, 1))
    assert ang == pytest.approx(0.001, rel=1e-3)
    np.testing.assert_allclose(half[:3, 3] + half[:3, 2] * 100.0, ground, atol=1e-9)
    assert np.linalg.norm(half[:2, 3] - T_true[:2, 3]) == pytest.approx(0.1, rel=1e-2)  # 1 mrad x 100 m
    yaw = [np.arctan2(T[1, 0], T[0, 0]) for T in (T_seen, half, full)]  # camera x (image right) keeps heading
    np.testing.assert_allclose(yaw, yaw[0], atol=2e-6)
    np.testing.assert_allclose(tilt_toward(T_seen, down_true, 0.0, 100.0), T_seen, atol=1e-12)
