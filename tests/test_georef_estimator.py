"""The georef estimator on rendered frames: accurate while fixes come, LOST when they stop, recovers,
gates a wrong fix, and re-initialises (bumping reset_counter) when the fixes consistently disagree."""

from __future__ import annotations

import numpy as np
import pytest

from companion.estimators.georef_cv import GeorefEstimator, GeorefEstimatorOptions
from companion.geometry import CameraIntrinsics, camera_pose, rpy_from_rot
from companion.georef.georef import GeoReferencer
from companion.georef.shading import Sun
from companion.types import AltimeterSample, AttitudeSample, EstimateStatus, Frame
from sim_bridge.render import VisibleRenderer
from sim_bridge.terrain import degrade_dem, make_scene
from sim_bridge.trajectory import forward

INTR = CameraIntrinsics.from_focal_sensor(480, 480, 36.0, 36.0)
RATE_HZ = 5.0


@pytest.fixture(scope="module")
def world():
    scene = make_scene("08", seed=0)
    dem, _ = degrade_dem(scene.dem, seed=7)
    ground = float(np.nanmean(scene.dem.height_m))
    traj = forward((-60.0, -20.0), 0.3, ground + 100.0, 4.0, 30.0)
    renderer = VisibleRenderer(scene.dem, scene.albedo, scene.sun, INTR)
    geo = GeoReferencer(dem, Sun.from_degrees(10.0, 0.0, 60.0), INTR)
    return scene, traj, renderer, geo


def feed(est: GeorefEstimator, scene, traj, renderer, t_s: float, image: np.ndarray | None = None):
    s = traj.state_at(t_s)
    t_us = int(round(t_s * 1e6))
    rpy = rpy_from_rot(s.R_world_body)
    est.on_attitude(AttitudeSample(t_us, *rpy))
    est.on_altimeter(AltimeterSample(t_us, scene.dem.beam_range(s.p_world, s.R_world_body[:, 2])))
    if image is None:
        R_wc, p_c = camera_pose(s.R_world_body, s.p_world)
        image = renderer.render(R_wc, p_c, seed=t_us)
    return est.on_frames({"nadir": Frame(t_us, "nadir", image)}), s


def make_estimator(traj, geo) -> GeorefEstimator:
    s0 = traj.state_at(0.0)
    return GeorefEstimator(GeorefEstimatorOptions(), geo, s0.p_world + np.array([2.0, -1.5, 0.0]))


def test_tracks_then_lost_on_blank_frames_then_recovers(world) -> None:
    scene, traj, renderer, geo = world
    est = make_estimator(traj, geo)
    errors = []
    t = 0.0
    while t < 8.0:
        e, s = feed(est, scene, traj, renderer, t)
        if t > 2.0:
            assert e is not None and e.status is EstimateStatus.OK and e.is_sendable()
            errors.append(np.linalg.norm(e.p_body_in_world_m[:2] - s.p_world[:2]))
        t += 1.0 / RATE_HZ
    assert np.median(errors) < 1.0, errors
    # a blank sky: no fix; the covariance grows while coasting, then the estimate is LOST (never sent)
    blank = np.full((480, 480), 128, np.uint8)
    sigmas, statuses = [], []
    while t < 11.5:
        e, _ = feed(est, scene, traj, renderer, t, image=blank)
        assert e is not None
        sigmas.append(np.sqrt(e.covariance[0, 0]))
        statuses.append(e.status)
        t += 1.0 / RATE_HZ
    assert all(b > a for a, b in zip(sigmas, sigmas[1:])), "coasting covariance must grow"
    assert statuses[0] is EstimateStatus.OK and statuses[-1] is EstimateStatus.LOST
    assert est.no_fix_reasons.get("blank", 0) >= len(statuses)
    # textured ground again: fixes resume and the estimate is OK
    for _ in range(6):
        e, s = feed(est, scene, traj, renderer, t)
        t += 1.0 / RATE_HZ
    assert e.status is EstimateStatus.OK
    # the constant-velocity prediction coasted ~3.5 s at 4 m/s; the fixes pulled it back
    assert np.linalg.norm(e.p_body_in_world_m[:2] - s.p_world[:2]) < 3.0


def test_wrong_fixes_are_gated_then_reinitialise(world) -> None:
    scene, traj, renderer, geo = world
    est = make_estimator(traj, geo)
    t = 0.0
    while t < 4.0:
        e, _ = feed(est, scene, traj, renderer, t)
        t += 1.0 / RATE_HZ
    assert e.reset_counter == 0
    # frames actually taken 25 m east of where the vehicle is: the fixes disagree with the filter
    shift = np.array([0.0, 25.0, 0.0])
    gated_before = est.counters["gated"]
    outs = []
    for _ in range(12):
        s = traj.state_at(t)
        R_wc, p_c = camera_pose(s.R_world_body, s.p_world + shift)
        img = renderer.render(R_wc, p_c, seed=int(t * 1e6))
        e, s = feed(est, scene, traj, renderer, t, image=img)
        outs.append((e, s))
        t += 1.0 / RATE_HZ
    first, s_first = outs[0]
    # the first wrong fix is gated: the estimate stays with the vehicle
    assert est.counters["gated"] > gated_before
    assert np.linalg.norm(first.p_body_in_world_m[:2] - s_first.p_world[:2]) < 3.0
    # after several consistent disagreeing fixes the filter re-initialises on them and says so
    last, s_last = outs[-1]
    assert last.reset_counter >= 1 and est.counters["reinit"] >= 1
    assert np.linalg.norm(last.p_body_in_world_m[:2] - (s_last.p_world[:2] + shift[:2])) < 3.0


def test_no_estimate_without_the_autopilots_attitude(world) -> None:
    _, traj, _, geo = world
    est = make_estimator(traj, geo)
    frame = Frame(1_000_000, "nadir", np.full((480, 480), 90, np.uint8))
    assert est.on_frames({"nadir": frame}) is None
    assert est.no_fix_reasons == {"no_attitude": 1}
