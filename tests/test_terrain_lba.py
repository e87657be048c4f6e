"""The terrain_lba estimator end to end on rendered frames: it recovers a known trajectory within bounds
and does better than VO only, its covariance comes from the adjustment, the same seed gives the same
output (inline back-end and worker process alike), and with w_G = 0 no geo-fix is ever made."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from companion.constants import R_BODY_CAM_NADIR
from companion.estimators.terrain_lba import FixDrought, TerrainLbaEstimator, TerrainLbaOptions
from companion.geometry import CameraIntrinsics, camera_pose, rpy_from_rot
from companion.georef.shading import Sun
from companion.types import AltimeterSample, AttitudeSample, EstimateStatus, Frame

INTR = CameraIntrinsics.from_focal_sensor(480, 480, 36, 36)
RATE_HZ = 7.5  # half the benchmark's camera rate keeps the test short; 0.5 m (2.5 px) between frames


def _render(duration_s: float = 22.0, seed: int = 0):
    from sim_bridge.render import VisibleRenderer
    from sim_bridge.terrain import degrade_dem, make_scene
    from sim_bridge.trajectory import forward

    scene = make_scene("01", seed=seed, size_m=320.0)
    dem_est, _ = degrade_dem(scene.dem, factor=4, seed=seed + 1)
    rend = VisibleRenderer(scene.dem, scene.albedo, scene.sun, INTR)
    traj = forward((-60.0, -40.0), np.radians(35.0), 100.0, 4.0, duration_s)
    rng = np.random.default_rng(seed)
    yaw_bias = rng.normal(0.0, 0.01)
    frames = []
    for k, t in enumerate(np.arange(0.0, duration_s, 1.0 / RATE_HZ)):
        s = traj.state_at(t)
        R_wc, p_c = camera_pose(s.R_world_body, s.p_world)
        stamp = int(round(t * 1e6))
        rpy = rpy_from_rot(s.R_world_body) + rng.normal(0.0, [0.003, 0.003, 0.005])
        down = s.R_world_body[:, 2]
        h = -s.p_world[2] - float(scene.dem.height_at(s.p_world[0], s.p_world[1])[0])
        frames.append(
            (
                AttitudeSample(stamp, float(rpy[0]), float(rpy[1]), float(rpy[2] + yaw_bias)),
                AltimeterSample(stamp, float(h / down[2] * (1.0 + rng.normal(0.0, 0.005)))),
                Frame(stamp, "nadir", rend.render(R_wc, p_c, seed=k), k),
                s.p_world.copy(),
            )
        )
    return scene, dem_est, frames, float(rpy_from_rot(traj.state_at(0.0).R_world_body)[2] + yaw_bias)


@pytest.fixture(scope="module")
def flight():
    return _render()


def _estimator(flight, options: TerrainLbaOptions, synchronous: bool) -> TerrainLbaEstimator:
    scene, dem_est, frames, yaw0 = flight
    return TerrainLbaEstimator(
        options,
        INTR,
        R_BODY_CAM_NADIR,
        dem_est,
        scene.sun,
        frames[0][3],
        yaw0,
        synchronous_backend=synchronous,
    )


def _run(flight, options: TerrainLbaOptions, synchronous: bool = True):
    frames = flight[2]
    est = _estimator(flight, options, synchronous)
    out = []
    try:
        for att, alt, frame, p_true in frames:
            est.on_attitude(att)
            est.on_altimeter(alt)
            pe = est.on_frames({"nadir": frame})
            out.append((pe, p_true))
        counters = est.backend_counters()
    finally:
        est.close()
    return out, counters


def _errors(out):
    return np.array(
        [np.linalg.norm(pe.p_body_in_world_m - p) for pe, p in out if pe is not None and pe.is_sendable()]
    )


OPT = replace(TerrainLbaOptions(), backend_apply="fixed_delay", backend_delay_frames=3)


@pytest.fixture(scope="module")
def lba_run(flight):
    return _run(flight, OPT)


def test_recovers_trajectory_and_beats_vo_only(flight, lba_run):
    out, counters = lba_run
    e = _errors(out)
    assert len(e) > 0.7 * len(out)
    assert counters["fix_accepted"] >= 4 and counters["alignments"] >= 1
    assert np.mean(e[len(e) // 2 :]) < 1.5  # second half: geo-referenced
    vo_out, vo_counters = _run(flight, replace(OPT, w_geo=0.0))
    assert vo_counters["fix_attempts"] == 0  # w_G = 0: terrain-free, no geo-referencing at all
    e_vo = _errors(vo_out)
    assert np.mean(e[len(e) // 2 :]) < np.mean(e_vo[len(e_vo) // 2 :])


def test_covariance_from_marginals_not_constant(lba_run):
    out, _ = lba_run
    covs = np.array([pe.covariance for pe, _ in out if pe is not None and pe.is_sendable()])
    assert np.all(np.isfinite(covs))
    sig = np.sqrt(covs[:, 0, 0])
    assert sig.max() - sig.min() > 0.02  # it changes along the flight
    for C in covs[::10]:
        np.testing.assert_allclose(C, C.T, atol=1e-9)
        assert np.all(np.linalg.eigvalsh(C) > 0)
    # estimates before the initialisation are marked and never sendable
    first = out[0][0]
    assert first.status is EstimateStatus.INITIALISING and not first.is_sendable()


def test_covariance_owns_the_compass_heading_until_the_terrain_gives_it(lba_run):
    """Until the fixes place the map, the marginals are relative to the pinned start: the covariance sent
    adds the start's error and the compass's carried out from it (``companion.lba.gauge``)."""
    out, counters = lba_run
    assert counters["alignments"] >= 2  # placed, and the heading found, within the flight
    sent = [pe for pe, _ in out if pe is not None and pe.is_sendable()]
    sig_h = np.array([np.sqrt(pe.covariance[0, 0] + pe.covariance[1, 1]) for pe in sent])
    sig_yaw = np.degrees([np.sqrt(pe.covariance[5, 5]) for pe in sent])
    before = np.array([pe.info["geo"] in (None, "pending") for pe in sent])
    assert before[0] and not before[-1]
    assert np.all(sig_yaw[before] >= 2.0)  # the compass's 2 deg (compass_sigma_rad)
    assert np.all(sig_h[before] >= OPT.initial_sigma_m)  # the start's 1 m
    n0 = int(before.sum())
    assert sig_h[n0 - 1] > sig_h[0] + 0.1  # the heading's share grows with the distance from the start
    # the terrain gave the heading and the fixes the place: well under the compass, under the start's error
    assert np.all(sig_yaw[-20:] < 1.0) and np.all(sig_h[-20:] < 0.7 * OPT.initial_sigma_m)


def test_deterministic_inline_and_in_worker_process(flight, lba_run):
    out_a, _ = lba_run
    short = (flight[0], flight[1], flight[2][:90], flight[3])
    out_b, _ = _run(short, OPT)
    out_c, _ = _run(short, OPT, synchronous=False)  # worker process, fixed delay
    out_d, _ = _run(short, OPT, synchronous=False)
    for (a, _), (b, _), (c, _), (d, _) in zip(out_a, out_b, out_c, out_d):
        # same mode, same seed: bit-identical
        np.testing.assert_array_equal(a.p_body_in_world_m, b.p_body_in_world_m)
        np.testing.assert_array_equal(a.covariance, b.covariance)
        np.testing.assert_array_equal(c.p_body_in_world_m, d.p_body_in_world_m)
        np.testing.assert_array_equal(c.covariance, d.covariance)
        # inline vs worker: the same adjustments at the same frames, but the worker's libraries round the
        # last bit differently (1e-14 m at the first adjustments), which the flight amplifies to millimetres
        np.testing.assert_allclose(b.p_body_in_world_m, c.p_body_in_world_m, atol=0.05)


def _over_a_slope() -> tuple[Any, TerrainLbaEstimator, np.ndarray]:
    """A DEM rising 20 % to the east, an estimator on it (no geo term), and a tilted body attitude."""
    from companion.geometry import rot_from_rpy
    from companion.georef.dem import Dem

    n = 401
    east = (np.arange(n) - 200) * 1.0
    dem = Dem(np.tile(0.2 * east, (n, 1)).astype(np.float32), 200.0, -200.0, 1.0)
    est = TerrainLbaEstimator(
        TerrainLbaOptions(w_geo=0.0), INTR, R_BODY_CAM_NADIR, dem, Sun.from_degrees(10, 0, 60), np.zeros(3)
    )
    return dem, est, rot_from_rpy(np.radians(3.0), np.radians(-2.0), 0.4)


def test_key_frame_height_averages_the_altimeter_samples_since_the_previous_key_frame() -> None:
    # a tilted vehicle 100 m over a 20 % slope, a 1 % range finder (1 m sigma): the key frame's height above
    # ground is the mean over the ~20 samples since the previous key frame, not the last sample alone
    dem, est, R = _over_a_slope()
    try:
        p = np.array([5.0, 10.0, -(2.0 + 100.0)])  # ground at east 10 m is 2 m high
        true_range = dem.beam_range(p, R[:, 2])
        rng = np.random.default_rng(3)
        errors_single = []
        for k in range(20):
            r = true_range + rng.normal(0.0, 1.0)
            est.on_altimeter(AltimeterSample(k * 50_000, r))
            errors_single.append(abs(dem.height_above_ground(p, R, r) - 100.0))
            est._gather_altimeter(k * 50_000, p, R)
        agl = est._key_frame_agl(p)
    finally:
        est.close()
    assert agl is not None and abs(agl - 100.0) < 0.5 * float(np.mean(errors_single)), (agl, errors_single)


def test_key_frame_height_keeps_the_samples_from_before_a_correction_moved_with_the_map() -> None:
    # ten altimeter samples taken while the map sat 0.4 m high and 0.6 m west, then an adjustment moves the
    # map (and the current pose) onto the truth, then ten more samples: the key frame's height above ground
    # is the trimmed mean over all twenty, each as if taken at its corrected pose
    from scipy.stats import trim_mean

    dem, est, R = _over_a_slope()
    try:
        p_true = np.array([5.0, 10.0, -(2.0 + 100.0)])
        C = np.eye(4)
        C[:3, 3] = [0.0, 0.6, 0.4]  # the correction: 0.6 m east, 0.4 m down
        p_before = p_true - C[:3, 3]
        true_range = dem.beam_range(p_true, R[:, 2])
        ranges = true_range + np.random.default_rng(5).normal(0.0, 1.0, 20)
        for k, r in enumerate(ranges):
            if k == 10:
                est._move_alt_samples(C)
            est.on_altimeter(AltimeterSample(k * 50_000, float(r)))
            est._gather_altimeter(k * 50_000, p_before if k < 10 else p_true, R)
        agl = est._key_frame_agl(p_true)
    finally:
        est.close()
    want = trim_mean([dem.height_above_ground(p_true, R, float(r)) for r in ranges], 0.1)
    assert agl is not None and abs(agl - want) < 1e-9, (agl, want)


@pytest.mark.parametrize("how", ["killed", "hung"])
def test_back_end_worker_lost_in_flight_is_replaced_and_the_frames_go_on(flight, how) -> None:
    # the OOM killer (or a crash in a native library) takes the back-end worker while it holds a job, or the
    # worker stops answering (SIGSTOP here; an endless loop in a library alike): the frames must not raise or
    # stall, the loss is counted, and a new worker takes over the adjustments. Frames are fed at the camera
    # rate, as the daemon gets them.
    import os
    import signal
    import time

    frames = flight[2]
    opt = replace(TerrainLbaOptions(), backend_apply="when_ready", backend_reply_timeout_s=2.0)
    est = _estimator(flight, opt, synchronous=False)
    lost_at = None
    applied_at_loss = 0
    worst_s = 0.0
    sendable_after = 0
    try:
        for i, (att, alt, frame, _) in enumerate(frames):
            t0 = time.monotonic()
            if lost_at is None and est.counters["backend_applied"] >= 1 and est._in_flight is not None:
                if how == "killed":
                    os.kill(est._proc.pid, signal.SIGKILL)
                    est._proc.join(timeout=5.0)
                else:
                    os.kill(est._proc.pid, signal.SIGSTOP)
                lost_at, applied_at_loss = i, est.counters["backend_applied"]
            est.on_attitude(att)
            est.on_altimeter(alt)
            tc = time.monotonic()
            pe = est.on_frames({"nadir": frame})
            worst_s = max(worst_s, time.monotonic() - tc)
            if lost_at is not None and pe is not None and pe.is_sendable():
                sendable_after += 1
            time.sleep(max(0.0, 1.0 / RATE_HZ - (time.monotonic() - t0)))
        counters = est.counters
    finally:
        est.close()
    assert lost_at is not None, "no job was ever in flight"
    assert counters["backend_restarts"] == 1
    assert sendable_after == len(frames) - lost_at  # every frame after the loss still has an estimate
    assert counters["backend_applied"] > applied_at_loss  # the new worker's results are applied
    assert counters["lba_runs"] >= counters["backend_applied"]  # totals carry over the lost worker's
    assert worst_s < 0.5  # the restart happens off the frames (a start blocks its caller ~1 s)


def test_back_end_worker_that_cannot_start_fails_at_once_with_its_exit_code() -> None:
    # a worker that dies while building its back-end (here: the matcher's reference map, from an option
    # only the worker uses, a zero local-relief scale that OpenCV's blur rejects) must not leave the caller
    # waiting for the start-up timeout
    import time

    from companion.georef.dem import Dem

    dem = Dem(np.zeros((50, 50), np.float32), 25.0, -25.0, 1.0)
    opt = TerrainLbaOptions(backend_start_timeout_s=100.0)
    opt = replace(opt, georef=replace(opt.georef, relief_scales_m=(0.0,)))
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="exit code 1"):
        TerrainLbaEstimator(opt, INTR, R_BODY_CAM_NADIR, dem, Sun.from_degrees(10, 0, 60), np.zeros(3))
    assert time.monotonic() - t0 < 60.0


def test_alignment_and_start_up_heading_are_logged_for_the_pilot(caplog) -> None:
    caplog.set_level("INFO", logger="companion.estimators.terrain_lba")
    TerrainLbaEstimator._log_alignment({"status": "accepted"})
    assert not caplog.records  # an ordinary fix says nothing
    TerrainLbaEstimator._log_alignment({"status": "aligned", "heading_coarse_deg": 19.6, "heading_deg": 0.42})
    text = caplog.text
    assert "map turned by +19.6 deg (coarse)" in text and "map turned by +0.42 deg" in text
    assert "map aligned to the geo-fixes" in text


def test_fix_drought_tells_when_the_terrain_stops_and_starts_giving_fixes() -> None:
    d = FixDrought(4)
    # no geo-referencing asked: nothing either way
    assert [d.update(s) for s in ("none", "", "accepted")] == [None] * 3
    notes = [d.update(s) for s in ("failed:low_quality", "rejected", "failed:low_quality", "failed:off_dem")]
    assert notes[:3] == [None] * 3 and notes[3] is not None
    assert notes[3].startswith("no terrain fix used in the last 4 key frames (low_quality 2, ")
    assert "off_dem 1" in notes[3] and "refused by the gate 1" in notes[3]
    # said once per run, and the end of the run is said too
    assert d.update("failed:low_quality") is None
    assert d.update("aligned") == "terrain fixes again, after 5 key frames without"
    # a run shorter than the threshold says nothing
    assert [d.update(s) for s in ("rejected", "rejected", "accepted")] == [None] * 3
    # fixes that wait for an alignment they never get (a compass far off) count too
    notes = [d.update(s) for s in ("pending", "failed:low_quality", "pending", "pending")]
    assert notes[3] is not None and "not yet aligned 3" in notes[3]
