"""The ``vis_thermal_ekf`` estimator end to end on the simulated Europa: rendered visible + thermal frames,
IMU and altimeter, through the daemon's entry points (``on_frames`` ...) and the offline ``run_sequence``."""

from __future__ import annotations

import numpy as np
import pytest

from companion.constants import GRAVITY_MPS2, R_BODY_CAM_NADIR
from companion.ekf.options import EkfOptions
from companion.estimators.vis_thermal_ekf import VisThermalEkfEstimator, run_sequence
from companion.geometry import camera_pose, rpy_from_rot
from companion.types import AltimeterSample, AttitudeSample, EstimateStatus, Frame, ImuSample
from sim_bridge.europa import EuropaCameras, make_europa
from sim_bridge.europa.sensors import altimeter_samples
from sim_bridge.europa.trajectories import paper_trajectories
from sim_bridge.trajectory import imu_samples

N_FRAMES = 10


@pytest.fixture(scope="module")
def flight():
    """Trajectory 1 (linear descent) over a 0.5 m-grid site: 10 frame pairs at 1 Hz, IMU 100 Hz, altimeter 10 Hz."""
    world = make_europa(seed=0, size_m=400.0, cell_m=0.5)
    cams = EuropaCameras(world)
    traj = paper_trajectories(world, seed=0)["1"]
    imu = imu_samples(traj, 100.0, None, seed=1)
    alt_t, alt_r = altimeter_samples(traj, world, 10.0, None, 2, cams.tracer)
    t = traj.t0_s + np.arange(N_FRAMES)
    states = traj.states(t)
    frames = []
    for i, st in enumerate(states):
        R_wc, p_c = camera_pose(st.R_world_body, st.p_world, R_BODY_CAM_NADIR)
        vis, tir = cams.render(R_wc, p_c, seed=i)
        t_us = int(round(st.t_s * 1e6))
        frames.append(
            (t_us, {"visible": Frame(t_us, "visible", vis), "thermal": Frame(t_us, "thermal", tir)})
        )
    t_end = frames[-1][0]
    return {
        "cams": cams,
        "intr": cams.intrinsics,
        "states": states,
        "frames": frames,
        "imu": [
            ImuSample(int(a), f, g) for a, f, g in zip(imu.t_us, imu.accel_mps2, imu.gyro_rps) if a <= t_end
        ],
        "alt": [
            AltimeterSample(int(a), float(r)) for a, r in zip(alt_t, alt_r) if np.isfinite(r) and a <= t_end
        ],
    }


def _estimator(flight, mode: str, **kw) -> VisThermalEkfEstimator:
    st0 = flight["states"][0]
    intr = flight["intr"]
    return VisThermalEkfEstimator(
        EkfOptions(mode=mode, **kw),
        {"visible": intr, "thermal": intr},
        {"visible": R_BODY_CAM_NADIR, "thermal": R_BODY_CAM_NADIR},
        st0.p_world,
        st0.v_world,
        rpy_from_rot(st0.R_world_body),
        gravity_mps2=GRAVITY_MPS2["europa"],
    )


class _Feeder:
    """Hands the flight's IMU and altimeter samples to the estimator in stamp order, up to a frame's time."""

    def __init__(self, est: VisThermalEkfEstimator, flight) -> None:
        self.est, self.imu, self.alt = est, flight["imu"], flight["alt"]
        self.ii = self.ia = 0

    def until(self, t_us: int) -> None:
        while self.ii < len(self.imu) and self.imu[self.ii].stamp_us <= t_us:
            self.est.on_imu(self.imu[self.ii])
            self.ii += 1
        while self.ia < len(self.alt) and self.alt[self.ia].stamp_us <= t_us:
            self.est.on_altimeter(self.alt[self.ia])
            self.ia += 1


@pytest.mark.parametrize("mode", ["visible", "thermal", "dual"])
def test_estimator_tracks_a_rendered_descent(flight, mode):
    est = _estimator(flight, mode)
    res = run_sequence(est, flight["imu"], flight["alt"], [(t, dict(fs)) for t, fs in flight["frames"]])
    est.close()
    assert est.cameras == (("visible", "thermal") if mode == "dual" else (mode,))
    assert len(res.stamp_us) == N_FRAMES
    assert res.status[0] == "initialising" and all(s == "ok" for s in res.status[1:])
    assert np.all(res.matched[1:] >= 12 * len(est.cameras))
    truth = np.stack([st.p_world for st in flight["states"]])
    err = np.linalg.norm(res.p_world - truth, axis=1)
    assert err[-1] < 2.0, err  # ~12 m flown
    cov = res.covariance[-1]
    np.testing.assert_allclose(cov, cov.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert np.sqrt(cov[0, 0] + cov[1, 1] + cov[2, 2]) < 5.0
    assert est.slam.counters.altimeter_updates > 30


def test_detections_path_equals_frames_path(flight):
    """The benchmark feeds precomputed SIFT detections; the daemon feeds frames. Same estimates."""
    a = _estimator(flight, "dual")
    b = _estimator(flight, "dual")
    frames = flight["frames"][:6]
    dets = [(t, a.detect(fs)) for t, fs in frames]
    ra = run_sequence(a, flight["imu"], flight["alt"], dets)
    rb = run_sequence(b, flight["imu"], flight["alt"], frames)
    a.close()
    b.close()
    np.testing.assert_array_equal(ra.p_world, rb.p_world)
    np.testing.assert_array_equal(ra.covariance, rb.covariance)


def test_bad_and_missing_frames_are_survived(flight):
    est = _estimator(flight, "dual")
    feed = _Feeder(est, flight)
    out = []
    for k, (t, fs) in enumerate(flight["frames"][:8]):
        feed.until(t)
        fs = dict(fs)
        if k == 3:
            fs["thermal"] = Frame(t, "thermal", np.zeros((100, 100), np.uint16))  # mis-sized
        if k == 4:
            del fs["visible"]  # the visible frame of this pair never arrived
        if k == 5:
            fs["visible"] = Frame(t, "visible", np.zeros((480, 640), np.uint8))  # blank
        out.append(est.on_frames(fs))
    est.close()
    assert est.counters["bad_frames"] == 1 and est.counters["missing_camera"] == 1
    assert all(e is not None for e in out)
    assert all(e.is_sendable() for e in out[1:])
    truth = flight["states"][7].p_world
    assert np.linalg.norm(out[-1].p_body_in_world_m - truth) < 2.0
    assert est.on_frames({"nadir": flight["frames"][0][1]["visible"]}) is None  # not one of its cameras


def test_frames_without_imu_are_counted_and_reported(flight):
    """An autopilot that stops streaming its IMU (or never did): each frame set with no IMU sample in the
    last imu_gap_s is counted and the status line says so until the samples come back; the same for the
    altimeter."""
    est = _estimator(flight, "visible")
    feed = _Feeder(est, flight)
    warned = []
    for k, (t, fs) in enumerate(flight["frames"][:8]):
        if k <= 3 or k == 7:
            feed.until(t)
        else:  # frames 4-6: the IMU is silent, the altimeter goes on
            feed.ii = next(i for i, s in enumerate(feed.imu) if s.stamp_us > t)
            while feed.ia < len(feed.alt) and feed.alt[feed.ia].stamp_us <= t:
                est.on_altimeter(feed.alt[feed.ia])
                feed.ia += 1
        est.on_frames({"visible": fs["visible"]})
        warned.append(dict(est.warnings))
    est.close()
    assert est.counters["frames_without_imu"] == 3
    assert [bool(w) for w in warned] == [False] * 4 + [True] * 3 + [False]
    assert warned[4] == {"imu": "NO IMU for 1.0 s"} and warned[6] == {"imu": "NO IMU for 3.0 s"}
    assert est.counters["frames_without_altimeter"] == 0
    blind = _estimator(flight, "visible")
    blind.on_frames({"visible": flight["frames"][0][1]["visible"]})
    blind.close()
    assert blind.warnings == {"imu": "NO IMU", "altimeter": "NO ALTIMETER"}
    assert blind.counters["frames_without_imu"] == blind.counters["frames_without_altimeter"] == 1


def test_a_diverged_filter_restarts_at_the_last_good_pose(flight):
    """A filter whose state goes non-finite is restarted at its last good pose: that frame gives no estimate,
    reset_counter moves once, the flight's counters carry on, and the next frames are estimated again."""
    est = _estimator(flight, "dual")
    feed = _Feeder(est, flight)
    out = []
    for k, (t, fs) in enumerate(flight["frames"]):
        feed.until(t)
        if k == 5:
            est.slam.ekf.v[:] = np.nan  # diverged: propagation to this frame spreads it to the whole state
            imu_before = est.slam.counters.imu
        out.append(est.on_frames(dict(fs)))
    est.close()
    assert out[5] is None and all(e is not None for e in out[:5] + out[6:])
    assert est.counters["reinit"] == 1 and out[-1].reset_counter == out[4].reset_counter + 1
    assert est.slam.counters.imu > imu_before  # the same counters, not a fresh set
    assert all(e.is_sendable() for e in out[7:])
    truth = flight["states"][-1].p_world
    assert np.linalg.norm(out[-1].p_body_in_world_m - truth) < 3.0


def test_configuration_errors_and_initial_attitude(flight):
    intr = flight["intr"]
    with pytest.raises(ValueError):
        VisThermalEkfEstimator(
            EkfOptions(mode="dual"), {"visible": intr}, {"visible": R_BODY_CAM_NADIR}, np.zeros(3)
        )
    with pytest.raises(ValueError):
        EkfOptions(mode="infrared")
    with pytest.raises(ValueError):
        EkfOptions(sampling="random")
    # no initial attitude given: the ATTITUDE sample is used (window 0: the nearest sample as it is; the
    # average over a window: test_ekf_handover)
    st0 = flight["states"][0]
    est = VisThermalEkfEstimator(
        EkfOptions(mode="thermal", initial_attitude_window_s=0.0),
        {"thermal": intr},
        {"thermal": R_BODY_CAM_NADIR},
        st0.p_world,
        st0.v_world,
    )
    rpy = rpy_from_rot(st0.R_world_body)
    est.on_attitude(AttitudeSample(0, *rpy))
    t, fs = flight["frames"][0]
    _Feeder(est, flight).until(t)  # the IMU up to the frame (a start waits for one)
    e = est.on_frames({"thermal": fs["thermal"]})
    assert e.status is EstimateStatus.INITIALISING and not e.is_sendable()
    np.testing.assert_allclose(e.rpy_rad, rpy, atol=1e-9)
    est.close()


def test_patch_search_finds_landmarks_sift_missed(flight):
    """With the patch search on the visible camera, landmarks SIFT did not find again are found by their
    first patch: more matches per frame, the same accuracy bound, and no patch search where it is off."""
    runs = {}
    for cams in ((), ("visible",)):
        est = _estimator(flight, "visible", patch_cameras=cams)
        res = run_sequence(est, flight["imu"], flight["alt"], [(t, dict(fs)) for t, fs in flight["frames"]])
        est.close()
        truth = np.stack([st.p_world for st in flight["states"]])
        runs[cams] = (res, est.slam.counters.patch_matches, np.linalg.norm(res.p_world - truth, axis=1))
    (r0, n0, _), (r1, n1, e1) = runs[()], runs[("visible",)]
    assert n0 == 0 and n1 >= 2 * (N_FRAMES - 1)  # a couple a frame at least (SIFT misses ~20 % in view)
    assert r1.matched[1:].sum() > r0.matched[1:].sum()
    assert e1[-1] < 2.0, e1
    assert all(s == "ok" for s in r1.status[1:])


def test_patch_search_finds_the_true_projection_on_rendered_frames(flight):
    """Against the truth: keypoints of the first visible frame, their ground points ray-cast from the true
    pose, projected into the frame 3 s later; the first patch warped with the true poses and searched around a
    prediction 1.5 px off finds most of them, to a fraction of a pixel."""
    import cv2

    from companion.ekf.features import (
        SiftDetector,
        ground_plane_affine,
        ncc_search,
        reference_patch,
        warp_template,
    )
    from companion.geometry import project

    cams, intr = flight["cams"], flight["intr"]
    K = intr.K
    pose = [
        camera_pose(flight["states"][i].R_world_body, flight["states"][i].p_world, R_BODY_CAM_NADIR)
        for i in (0, 3)
    ]
    img = [flight["frames"][i][1]["visible"].image for i in (0, 3)]
    det = SiftDetector(EkfOptions(), "visible")
    d0, d1 = det.detect(img[0]), det.detect(img[1])
    ground = cams.ground_points(*pose[0]).astype(np.float32)
    rng = np.random.default_rng(0)
    found, errors, n = 0, [], 0
    for k in rng.choice(len(d0), 80, replace=False):
        u, v = d0.uv[k]
        X = np.array(
            [cv2.getRectSubPix(ground[..., c], (1, 1), (float(u), float(v)))[0, 0] for c in range(3)]
        )
        truth, _ = project(K, *pose[1], X[None])
        if not np.all(np.isfinite(X)) or not (30 < truth[0, 0] < 610 and 30 < truth[0, 1] < 450):
            continue
        n += 1
        L = ground_plane_affine(X, K, pose[0], pose[1])
        assert L is not None
        patch, origin = reference_patch(d0.image, d0.uv[k], 21)
        template = warp_template(patch, origin, d0.uv[k], L, 7)
        uv = ncc_search(
            d1.image, template, truth[0] + rng.normal(0, 1.5, 2), np.eye(2) * 4.0, 9.21, 24, 0.8, 0.05
        )
        if uv is not None:
            found += 1
            errors.append(float(np.linalg.norm(uv - truth[0])))
    print(
        f"patch search vs truth: {found}/{n} found, median {np.median(errors):.3f} px, p90 {np.percentile(errors, 90):.3f}"
    )
    assert n >= 40
    assert found >= 0.6 * n
    assert np.median(errors) < 0.35 and np.percentile(errors, 90) < 1.0


def test_the_starts_yaw_uncertainty_is_carried_in_the_covariance_sent_not_in_the_filter(flight):
    """EkfOptions.filter_yaw_sigma_rad: the filter starts with that yaw sigma, the rest of initial_yaw_sigma_rad
    turns the map about the start in the covariance sent (lba.gauge: sigma x distance across the track)."""
    from companion.lba.gauge import gauge_covariance

    frames = [(t, dict(fs)) for t, fs in flight["frames"]]
    inside = _estimator(flight, "thermal", initial_yaw_sigma_rad=0.02, filter_yaw_sigma_rad=0.02)
    gauged = _estimator(flight, "thermal", initial_yaw_sigma_rad=0.02)  # the filter's share: 0.01 deg
    tight = _estimator(flight, "thermal", initial_yaw_sigma_rad=1.7453292519943296e-4)
    runs = {}
    for name, est in (("inside", inside), ("gauged", gauged), ("tight", tight)):
        runs[name] = run_sequence(est, flight["imu"], flight["alt"], frames)
        est.close()
    # the filter itself: the same with the yaw gauged out as with a tight prior, to the last bit
    np.testing.assert_array_equal(runs["gauged"].p_world, runs["tight"].p_world)
    # what is sent: the tight filter's covariance plus the turn about the start (0.02 rad)
    p0 = flight["states"][0].p_world
    k = -1
    extra = gauge_covariance(runs["gauged"].p_world[k], p0, 0.0, np.sqrt(0.02**2 - 1.7453292519943296e-4**2))
    np.testing.assert_allclose(runs["gauged"].covariance[k], runs["tight"].covariance[k] + extra, atol=1e-12)
    moved = np.linalg.norm(runs["gauged"].p_world[k, :2] - p0[:2])
    assert moved > 5.0 and runs["gauged"].covariance[k][5, 5] >= 0.02**2 - 1e-9
    # with the whole prior inside the filter, the updates may move its yaw: different estimates
    assert not np.array_equal(runs["inside"].p_world, runs["gauged"].p_world)
