"""Paper 1 Tables 4, 5 and 7 analogues: VO only (w_G = 0) vs terrain-aided LBA (``terrain_lba``).

Frames are rendered over the simulated scenes (``sim_bridge.terrain`` / ``sim_bridge.render``, sensor noise
on) at 15 Hz from about 100 m above the mean ground at 4 m/s; the estimator gets the degraded DEM
(``degrade_dem``: 4x coarser, noise, holes), the autopilot's attitude with the simulated autopilot's noise
and compass bias, and the altimeter range with its noise. Every method sees the very same frames (they run
in lock-step on each rendered frame). The back-end runs in its worker process with its result applied a
fixed number of frames after its key frame (deterministic), so the per-frame figures include the
contention of a real back-end.

Accuracy: APE of the body position (evo, ``PoseRelation.translation_part``) against the truth at each
frame's capture time, WITHOUT any alignment: both methods start at the known initial position and report
in the world frame, as a navigation system must. (evo's SE(3) Umeyama-aligned APE, what trajectory papers
often quote for VO/SLAM, is reported beside it as ``aligned``.) Frames before the VO is initialised have no
estimate; ``coverage`` says how many frames had one.

Speed: ``fps`` = frames / total time inside ``on_frames`` (the per-frame path: tracking, PnP, key-frame
decisions, applying adjustments); ``p99_ms`` its 99th percentile latency. Rendering is not timed.

    python -m bench terrain_slam [--quick] [--json bench/results/terrain_slam.json]
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D
from scipy.signal import lfilter

from bench.common import parser, table, write_json
from companion.constants import GRAVITY_MPS2, R_BODY_CAM_NADIR
from companion.estimators.terrain_lba import GeoFixRecord, TerrainLbaEstimator, TerrainLbaOptions
from companion.geometry import CameraIntrinsics, camera_pose, rot_from_rpy, rpy_from_rot
from companion.metrics import covariance_consistency
from companion.types import AltimeterSample, AttitudeSample, Frame
from sim_bridge.autopilot_link import SimNoise
from sim_bridge.render import VisibleRenderer
from sim_bridge.terrain import SCENE_IDS, degrade_dem, make_scene
from sim_bridge.trajectory import Trajectory, circular, forward, scanning

CAMERA_HZ = 15.0
SPEED_MPS = 4.0
HEIGHT_M = 100.0
RADIUS_M = 120.0
CONFIDENCES = (0.0, 1.0, 10.0, 100.0, 1000.0)
STAT_KEYS = ("max", "median", "min", "mean", "rmse", "std")


@dataclass(frozen=True)
class FlightSpec:
    scene_id: str
    trajectory: str  # circular | forward | scanning
    duration_s: float
    seed: int = 0
    # attitude errors the estimator cannot see (``bench attitude_errors``): a constant roll / pitch bias in the
    # autopilot's ATTITUDE (rad, added to every sample), and the camera's true mounting rotation beyond nadir
    # (roll, pitch, yaw in the body frame, rad; composed as ``CameraConfig.R_body_cam``) while the estimator
    # is told the nominal nadir mount unless the method is listed in ``run_flight``'s ``mount_known``
    tilt_bias_rad: tuple[float, float] = (0.0, 0.0)
    # a roll / pitch error that wanders (an AHRS's slow error: warm-up, vibration): a first-order Gauss-Markov
    # process per axis with this stationary sigma (rad) and time constant (s), on top of the white noise and
    # drawn from its own generator, so the flight's other draws stay those of the plain flight
    tilt_wander_rad: float = 0.0
    tilt_wander_tau_s: float = 10.0
    mount_error_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # the compass's bias (rad, on the initial yaw and every ATTITUDE yaw); None: drawn from ``SimNoise``
    yaw_bias_rad: float | None = None


def gauss_markov(n: int, dt_s: float, sigma: float, tau_s: float, seed: int) -> np.ndarray:
    """(n, 2) a stationary first-order Gauss-Markov process per axis: x_k+1 = a x_k + sqrt(1 - a^2) sigma w_k,
    a = exp(-dt / tau). Zeros when sigma is 0 (no draws at all)."""
    if sigma <= 0:
        return np.zeros((n, 2))
    rng = np.random.default_rng([seed, 11])
    a = float(np.exp(-dt_s / tau_s))
    u = rng.normal(0.0, 1.0, (n, 2)) * sigma * np.sqrt(1.0 - a * a)
    u[0] /= np.sqrt(1.0 - a * a)  # the first sample from the stationary distribution
    return lfilter([1.0], [1.0, -a], u, axis=0)


def make_trajectory(kind: str, duration_s: float, ground_m: float) -> Trajectory:
    """Paper 1's three flights, centred on the 600 m scene, ~100 m above the mean ground, 4 m/s."""
    alt = ground_m + HEIGHT_M
    g = GRAVITY_MPS2["mars"]
    if kind == "circular":
        return circular((0.0, 0.0), RADIUS_M, alt, SPEED_MPS, duration_s, gravity_mps2=g)
    if kind == "forward":
        # diagonal across the scene, starting 170 m south-west of the centre
        h = np.radians(30.0)
        return forward(
            (-170.0 * np.cos(h), -170.0 * np.sin(h)), h, alt, SPEED_MPS, duration_s, gravity_mps2=g
        )
    if kind == "scanning":
        return scanning((-120.0, -150.0), 240.0, 60.0, alt, SPEED_MPS, duration_s, gravity_mps2=g)
    raise ValueError(f"unknown trajectory {kind!r}")


def ape_stats(t_ref: np.ndarray, p_ref: np.ndarray, t_est: np.ndarray, p_est: np.ndarray) -> dict[str, Any]:
    """evo APE (translation part) stats in metres, unaligned and SE(3)-aligned."""
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t_ref), 1))
    ref = PoseTrajectory3D(positions_xyz=p_ref, orientations_quat_wxyz=q, timestamps=t_ref)
    est = PoseTrajectory3D(
        positions_xyz=p_est,
        orientations_quat_wxyz=np.tile([1.0, 0.0, 0.0, 0.0], (len(t_est), 1)),
        timestamps=t_est,
    )
    ref, est = sync.associate_trajectories(ref, est, max_diff=1e-3)
    out: dict[str, Any] = {}
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    s = ape.get_all_statistics()
    out.update({k: float(s[k]) for k in STAT_KEYS})
    d = est.positions_xyz - ref.positions_xyz  # NED: the split says whether height or position dominates
    out["horizontal_mean"] = float(np.mean(np.hypot(d[:, 0], d[:, 1])))
    out["vertical_mean"] = float(np.mean(np.abs(d[:, 2])))
    est_al = copy.deepcopy(est)
    est_al.align(ref, correct_scale=False)
    ape_al = metrics.APE(metrics.PoseRelation.translation_part)
    ape_al.process_data((ref, est_al))
    sa = ape_al.get_all_statistics()
    out["aligned"] = {k: float(sa[k]) for k in STAT_KEYS}
    out["errors_m"] = np.asarray(ape.error)
    return out


class Simulation:
    """One flight's world and sensors: scene, the estimator's degraded DEM, renderer, trajectory, noise."""

    def __init__(self, spec: FlightSpec) -> None:
        self.spec = spec
        self.scene = make_scene(spec.scene_id, spec.seed)
        self.dem_est, self.degradation = degrade_dem(self.scene.dem, factor=4, seed=spec.seed + 1)
        ground = float(np.nanmean(self.scene.dem.height_m))
        self.traj = make_trajectory(spec.trajectory, spec.duration_s, ground)
        self.intr = CameraIntrinsics.from_focal_sensor(480, 480, 36, 36)
        self.renderer = VisibleRenderer(self.scene.dem, self.scene.albedo, self.scene.sun, self.intr)
        self.noise = SimNoise()  # the simulated autopilot's telemetry noise (attitude, compass bias, range)
        self.rng = np.random.default_rng([spec.seed, 7, int(spec.scene_id)])
        self.yaw_bias = float(self.rng.normal(0.0, self.noise.yaw_bias_rad))  # drawn always: same rng stream
        if spec.yaw_bias_rad is not None:
            self.yaw_bias = float(spec.yaw_bias_rad)
        self.times = np.arange(0.0, self.traj.duration_s, 1.0 / CAMERA_HZ)
        self.states = self.traj.states(self.times)
        self.p_true = np.stack([s.p_world for s in self.states])
        self.yaw0 = float(rpy_from_rot(self.states[0].R_world_body)[2]) + self.yaw_bias
        self.R_body_cam_true = rot_from_rpy(*spec.mount_error_rpy_rad) @ R_BODY_CAM_NADIR
        self.tilt_wander = gauss_markov(
            len(self.times), 1.0 / CAMERA_HZ, spec.tilt_wander_rad, spec.tilt_wander_tau_s, spec.seed
        )
        self.render_s = 0.0

    def estimator(self, options: TerrainLbaOptions, mount_known: bool = False) -> TerrainLbaEstimator:
        """The estimator as the daemon builds it: degraded DEM, known start, compass yaw, and the scene's
        sun (a vehicle knows the sun's direction from the time and its position; paper 1's presumed sun is
        the geo-referencing benchmark's condition, not this one's). The camera mount it is given: nominal
        nadir, or with ``mount_known`` the true one (a calibrated ``cameras.nadir.extra_rpy_deg``)."""
        return TerrainLbaEstimator(
            options,
            self.intr,
            self.R_body_cam_true if mount_known else R_BODY_CAM_NADIR,
            self.dem_est,
            self.scene.sun,
            self.states[0].p_world.copy(),
            self.yaw0,
            synchronous_backend=False,
        )

    def true_axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R_world_cam (F, 3, 3), p_cam (F, 3), range along the optical axis to the surface (F,)) per frame."""
        poses = [camera_pose(s.R_world_body, s.p_world, self.R_body_cam_true) for s in self.states]
        R = np.stack([q[0] for q in poses])
        p = np.stack([q[1] for q in poses])
        rng = np.array([self.scene.dem.beam_range(pc, Rc[:, 2]) for Rc, pc in zip(R, p)])
        return R, p, rng

    def samples(self):
        """Yield (t_s, AttitudeSample, AltimeterSample, Frame) per camera frame (rendering timed apart)."""
        n = self.noise
        for k, (t, s) in enumerate(zip(self.times, self.states)):
            stamp = int(round(t * 1e6))
            R_wc, p_c = camera_pose(s.R_world_body, s.p_world, self.R_body_cam_true)
            tr = time.perf_counter()
            img = self.renderer.render(R_wc, p_c, seed=k)
            self.render_s += time.perf_counter() - tr
            rpy = rpy_from_rot(s.R_world_body) + self.rng.normal(
                0.0, [n.roll_pitch_rad, n.roll_pitch_rad, n.yaw_rad]
            )
            rpy[:2] += np.asarray(self.spec.tilt_bias_rad) + self.tilt_wander[k]
            att = AttitudeSample(stamp, float(rpy[0]), float(rpy[1]), float(rpy[2] + self.yaw_bias))
            r = self.scene.dem.beam_range(s.p_world, s.R_world_body[:, 2])
            r += self.rng.normal(0.0, n.range_m + n.range_frac * r)
            yield float(t), att, AltimeterSample(stamp, float(r)), Frame(stamp, "nadir", img, k)


def run_flight(
    spec: FlightSpec,
    methods: dict[str, TerrainLbaOptions],
    log: bool = True,
    mount_known: tuple[str, ...] = (),
) -> dict[str, Any]:
    """Render one flight and run every method on it in lock-step; returns per-method results. The methods
    named in ``mount_known`` are given the camera's true mount (``FlightSpec.mount_error_rpy_rad``)."""
    t0 = time.perf_counter()
    sim = Simulation(spec)
    est = {name: sim.estimator(opt, name in mount_known) for name, opt in methods.items()}
    setup_s = time.perf_counter() - t0
    lat: dict[str, list[float]] = {n: [] for n in methods}
    got: dict[str, list[tuple[float, np.ndarray, np.ndarray]]] = {n: [] for n in methods}  # t, p, cov NE
    times, p_true, traj, scene = sim.times, sim.p_true, sim.traj, sim.scene
    for k, (t, att, alt, frame) in enumerate(sim.samples()):
        for n, e in est.items():
            e.on_attitude(att)
            e.on_altimeter(alt)
            tc = time.perf_counter()
            pe = e.on_frames({"nadir": frame})
            lat[n].append(time.perf_counter() - tc)
            if pe is not None and pe.is_sendable():
                got[n].append((t, pe.p_body_in_world_m.copy(), pe.covariance[:2, :2].copy()))
        if log and k % 300 == 0 and k:
            errs = {
                n: float(np.linalg.norm(g[-1][1] - p_true[k])) if g and g[-1][0] == t else float("nan")
                for n, g in got.items()
            }
            print(f"    t={t:6.1f}s " + " ".join(f"{n}={v:.2f}m" for n, v in errs.items()), flush=True)
    render_s = sim.render_s
    deg = sim.degradation
    spec_yaw_bias = sim.yaw_bias
    distance = traj.distance_m()
    out: dict[str, Any] = {}
    axes = sim.true_axes() if any(e.geo_fixes for e in est.values()) else None  # once for every method
    yaw_true = np.array([rpy_from_rot(st.R_world_body)[2] for st in sim.states])
    for n, e in est.items():
        counters = e.backend_counters()
        records = list(e.geo_fixes)
        e.close()
        lt = np.array(lat[n])
        res: dict[str, Any] = {"n_frames": len(times), "n_estimates": len(got[n])}
        res["coverage"] = len(got[n]) / len(times)
        if got[n]:
            te = np.array([g[0] for g in got[n]])
            pe_ = np.stack([g[1] for g in got[n]])
            res.update(ape_stats(times, p_true, te, pe_))
            res["t_s"] = te
            # mean error along the body's heading (forward, right): a tilt the estimator does not know
            k_est = np.clip(np.searchsorted(times, te - 1e-9), 0, len(times) - 1)
            d_ne = pe_[:, :2] - p_true[k_est, :2]
            res["mean_error_forward_right_m"] = mean_forward_right(d_ne, yaw_true[k_est])
            # does the covariance sent with each estimate cover its error (sim_bridge.sim)
            res["covariance_consistency"] = covariance_consistency(d_ne, np.stack([g[2] for g in got[n]]))
            # distance flown (truth) at each estimate, for the drift plot
            cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p_true, axis=0), axis=1))])
            res["distance_at_estimate_m"] = np.interp(te, times, cum)
        else:
            res.update({k: float("nan") for k in STAT_KEYS})
        res["distance_m"] = distance
        res["fps"] = float(len(lt) / lt.sum())
        res["p99_ms"] = float(np.percentile(lt, 99) * 1e3)
        res["mean_ms"] = float(lt.mean() * 1e3)
        res["max_ms"] = float(lt.max() * 1e3)
        res["backend"] = counters
        res["w_geo"] = methods[n].w_geo
        if records and axes is not None:
            res["geo_fix"] = fix_errors(records, times, p_true, *axes, yaw_true)
        out[n] = res
    out["_flight"] = {
        "scene": spec.scene_id,
        "name": scene.name,
        "trajectory": spec.trajectory,
        "duration_s": spec.duration_s,
        "distance_m": distance,
        "frames": len(times),
        "dem": deg.describe(),
        "sun_deg": [
            scene.sun.intensity,
            float(np.degrees(scene.sun.azimuth_rad)),
            float(np.degrees(scene.sun.elevation_rad)),
        ],
        "yaw_bias_deg": float(np.degrees(spec_yaw_bias)),
        "tilt_bias_deg": [float(np.degrees(x)) for x in spec.tilt_bias_rad],
        "tilt_wander_deg_tau_s": [float(np.degrees(spec.tilt_wander_rad)), spec.tilt_wander_tau_s],
        "mount_error_rpy_deg": [float(np.degrees(x)) for x in spec.mount_error_rpy_rad],
        "setup_s": setup_s,
        "render_ms_per_frame": render_s / len(times) * 1e3,
        "wall_s": time.perf_counter() - t0,
    }
    return out


def timing_run(spec: FlightSpec, modes: tuple[str, ...] = ("when_ready", "fixed_delay")) -> dict[str, Any]:
    """The per-frame path as the daemon runs it: one terrain_lba estimator fed at the camera rate (15 Hz,
    frames pre-rendered), its back-end working in its process meanwhile. Per mode: latency of
    ``on_frames`` (p50, p99, max), the rate it could sustain (1 / mean latency), frames over the budget.
    OpenCV's threads per call as the daemon sets them (``daemon.opencv_threads``, also the worker's); the
    flights of Tables 4, 5 and 7 keep OpenCV's default."""
    from companion.cli import configure_opencv
    from companion.config import DaemonConfig

    threads_before = cv2.getNumThreads()
    configure_opencv(DaemonConfig().opencv_threads)
    try:
        return _timing_modes(spec, modes)
    finally:
        cv2.setNumThreads(threads_before)


def _timing_modes(spec: FlightSpec, modes: tuple[str, ...]) -> dict[str, Any]:
    sim = Simulation(spec)
    frames = list(sim.samples())
    out: dict[str, Any] = {"scene": spec.scene_id, "trajectory": spec.trajectory, "frames": len(frames)}
    for mode in modes:
        e = sim.estimator(replace(TerrainLbaOptions(), backend_apply=mode))
        lat = []
        errs = []
        period = 1.0 / CAMERA_HZ
        t_next = time.perf_counter()
        for k, (_, att, alt, frame) in enumerate(frames):
            now = time.perf_counter()
            if now < t_next:
                time.sleep(t_next - now)
            t_next += period
            e.on_attitude(att)
            e.on_altimeter(alt)
            tc = time.perf_counter()
            pe = e.on_frames({"nadir": frame})
            lat.append(time.perf_counter() - tc)
            if pe is not None and pe.is_sendable():
                errs.append(float(np.linalg.norm(pe.p_body_in_world_m - sim.p_true[k])))
        e.close()
        lt = np.array(lat) * 1e3
        out[mode] = {
            "fps": float(1e3 / lt.mean()),
            "mean_ms": float(lt.mean()),
            "p50_ms": float(np.percentile(lt, 50)),
            "p99_ms": float(np.percentile(lt, 99)),
            "max_ms": float(lt.max()),
            "over_budget_frames": int((lt > 1e3 * period).sum()),
            "mean_error_m": float(np.mean(errs)) if errs else float("nan"),
        }
    out["opencv_threads"] = int(cv2.getNumThreads())
    return out


USED_FIX = ("accepted", "aligned", "aligned_yaw", "realigned")
"""Back-end outcomes of a key frame whose fix entered the adjustment (``BackendResult.geo``)."""


def mean_forward_right(d_ne: np.ndarray, yaw_rad: np.ndarray) -> list[float]:
    """Mean of horizontal errors d_ne (N, 2; north, east) along the vehicle's heading yaw_rad (N,) and to its
    right: a body-fixed bias (a tilt, a lever, a lag) turns with the vehicle in a circular flight and
    averages out in north / east, not here."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    fwd = d_ne[:, 0] * c + d_ne[:, 1] * s
    right = -d_ne[:, 0] * s + d_ne[:, 1] * c
    return [float(fwd.mean()), float(right.mean())]


def fix_errors(
    records: list[GeoFixRecord],
    times_s: np.ndarray,
    p_body: np.ndarray,
    R_world_cam: np.ndarray,
    p_cam: np.ndarray,
    ground_range_m: np.ndarray,
    yaw_rad: np.ndarray | None = None,
) -> dict[str, Any]:
    """How good the key frames' geo-fixes were, against the truth at their frames.

    records: the estimator's ``geo_fixes``. times_s (F,), p_body (F, 3), R_world_cam (F, 3, 3), p_cam (F, 3):
    the true frame times and poses; ground_range_m (F,): true range along each frame's optical axis to the
    surface. ``ground_m``: horizontal error of the ground point the fix locates on the optical axis (the
    matcher's own error: what the adjustment holds); ``body_m``: horizontal error of the body position the
    fix gives at the key frame's estimated attitude (adds height x that attitude's tilt error). Means over
    the fixes the adjustment used, ``bias_ne_m`` the mean ground error vector (north, east);
    ``sigma_m_median`` / ``sigma_m_last``: the horizontal sigma the adjustment gave the fixes (learnt from
    their scatter, ``BackendOptions.geo_sigma_adapt``) over the flight and at its end (NaN when none was reported).
    ``unfollowed_m`` / ``unfollowed_ne_m``: mean horizontal length / vector of what the adjustment did not follow of
    each used fix (``GeoFixRecord.unfollowed_world``). With ``yaw_rad`` (F,), the true heading at each frame,
    ``ground_fwd_right_m`` and ``unfollowed_fwd_right_m``: the same means along the vehicle's heading and to
    its right: a bias that turns with the vehicle (a tilt, a lever, a lag) shows there and averages out in
    north / east over a circle."""
    used = [r for r in records if r.status in USED_FIX]
    if not used:
        return {"n_used": 0, "n_reported": len(records)}
    t_fix = np.array([r.stamp_us for r in used]) * 1e-6
    k = np.abs(times_s[None, :] - t_fix[:, None]).argmin(axis=1)  # the frame nearest each key frame's stamp
    p_fix = np.stack([r.p_fix_world for r in used])
    g_fix = np.stack([r.ground_fix_world for r in used])
    g_true = p_cam[k] + ground_range_m[k, None] * R_world_cam[k, :, 2]
    d_g = g_fix[:, :2] - g_true[:, :2]
    d_b = p_fix[:, :2] - p_body[k, :2]
    ok = np.isfinite(d_g).all(axis=1)
    sig = np.array([r.fix_sigma_m for r in records], float)
    sig = sig[np.isfinite(sig)]
    d_u = np.stack([r.unfollowed_world for r in used])[:, :2]
    ok_u = np.isfinite(d_u).all(axis=1)
    nan2 = [float("nan")] * 2
    extra: dict[str, Any] = {
        "unfollowed_m": float(np.linalg.norm(d_u[ok_u], axis=1).mean()) if ok_u.any() else float("nan"),
        "unfollowed_ne_m": d_u[ok_u].mean(axis=0).tolist() if ok_u.any() else nan2,
    }
    if yaw_rad is not None:
        extra["ground_fwd_right_m"] = mean_forward_right(d_g[ok], yaw_rad[k][ok]) if ok.any() else nan2
        extra["unfollowed_fwd_right_m"] = (
            mean_forward_right(d_u[ok_u], yaw_rad[k][ok_u]) if ok_u.any() else nan2
        )
    return {
        "n_used": len(used),
        "n_reported": len(records),
        "ground_m": float(np.linalg.norm(d_g[ok], axis=1).mean()) if ok.any() else float("nan"),
        "body_m": float(np.linalg.norm(d_b, axis=1).mean()),
        "bias_ne_m": d_g[ok].mean(axis=0).tolist() if ok.any() else [float("nan")] * 2,
        "quality_mean": float(np.mean([r.quality for r in used])),
        "sigma_m_median": float(np.median(sig)) if len(sig) else float("nan"),
        "sigma_m_last": float(sig[-1]) if len(sig) else float("nan"),
        **extra,
    }


def _public(res: dict[str, Any]) -> dict[str, Any]:
    """Per-method result without the per-frame arrays (for JSON)."""
    return {k: v for k, v in res.items() if k not in ("errors_m", "t_s", "distance_at_estimate_m")}


FIX_HEAD = [
    "scene",
    "fixes used",
    "ground err/m",
    "bias N/m",
    "bias E/m",
    "body err/m",
    "fix sigma/m",
    "unfollowed fwd/m",
    "unfollowed right/m",
    "APE horiz/m",
]
FIX_TITLE = (
    "terrain_lba's key-frame geo-fixes against the truth (horizontal; means over the fixes used); unfollowed: "
    "the fix minus where the adjustment put it, along the heading and to the right"
)


def _fix_row(scene: str, r: dict[str, Any]) -> list[Any]:
    g = r.get("geo_fix", {})
    bias = g.get("bias_ne_m", [float("nan")] * 2)
    nan = float("nan")
    return [
        scene,
        g.get("n_used", 0),
        g.get("ground_m", nan),
        bias[0],
        bias[1],
        g.get("body_m", nan),
        g.get("sigma_m_median", nan),
        *g.get("unfollowed_fwd_right_m", [nan, nan]),
        r.get("horizontal_mean", nan),
    ]


CONS_HEAD = ["method", "sigma/m", "horiz err/m", "NEES mean", "NEES median", "in 95 %"]
CONS_TITLE = (
    "covariance sent vs the error (horizontal): mean 1-sigma, mean error, NEES (2 when right), errors inside "
    "the estimate's own 95 % ellipse"
)


def _consistency_row(name: str, r: dict[str, Any]) -> list[Any]:
    c = r.get("covariance_consistency", {})
    nan = float("nan")
    return [
        name,
        c.get("sigma_mean_m", nan),
        r.get("horizontal_mean", nan),
        c.get("nees_mean", nan),
        c.get("nees_median", nan),
        c.get("within_95", nan),
    ]


def _row(name: str, r: dict[str, Any]) -> list[Any]:
    return (
        [name]
        + [r.get(k, float("nan")) for k in STAT_KEYS]
        + [r["distance_m"], r["fps"], r["p99_ms"], r["coverage"]]
    )


HEAD = ["method", *[f"{k}/m" for k in STAT_KEYS], "dist/m", "fps", "p99/ms", "cover"]


def drift_plot(path: Path, flights: list[tuple[str, dict[str, Any]]]) -> None:
    """Error against distance flown for VO only and terrain LBA."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for label, res in flights:
        for n, style in (("vo_only", "-"), ("terrain_lba", "-")):
            r = res.get(n)
            if r is None or "errors_m" not in r:
                continue
            ax.plot(r["distance_at_estimate_m"], r["errors_m"], style, lw=1, label=f"{label} {n}")
    ax.set_xlabel("distance flown (m)")
    ax.set_ylabel("position error, no alignment (m)")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("terrain_slam: error vs distance flown")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


def drift_plot_path(plot: Path | None, json_path: Path | None) -> Path | None:
    """Where the drift plot goes: ``--plot`` if given, else beside the JSON (``X.json`` -> ``X_drift.png``), so
    a run with its JSON elsewhere never overwrites the committed plot; no plot when neither is given."""
    if plot is not None:
        return plot
    if json_path is not None:
        return json_path.with_name(f"{json_path.stem}_drift.png")
    return None


def main(argv: list[str] | None = None) -> int:
    p = parser("terrain_slam", __doc__.splitlines()[0])
    p.add_argument("--circular-s", type=float, default=None, help="circular flight duration")
    p.add_argument("--forward-s", type=float, default=None, help="forward flight duration")
    p.add_argument("--scanning-s", type=float, default=None, help="scanning flight duration")
    p.add_argument("--scenes", default=None, help="comma-separated scene ids for Table 7 (default all nine)")
    p.add_argument("--tables", default="4,5,7,t", help="which tables to run (t = per-frame timing run)")
    p.add_argument("--timing-s", type=float, default=None, help="timing run duration")
    p.add_argument(
        "--plot",
        type=Path,
        default=None,
        help="error against distance flown, as PNG (default: beside --json, NAME_drift.png; none without --json)",
    )
    p.add_argument(
        "--no-joint-shift",
        action="store_true",
        help="geo-fixes without the matcher's joint_shift option (terrain_lba's default has it)",
    )
    p.add_argument(
        "--no-terrain-term",
        action="store_true",
        help="the adjustment without the landmark-on-DEM term (terrain_lba's default has it)",
    )
    a = p.parse_args(argv)
    circ_s = a.circular_s or (30.0 if a.quick else 190.0)
    fwd_s = a.forward_s or (40.0 if a.quick else 110.0)
    scan_s = a.scanning_s or (40.0 if a.quick else 150.0)
    tables = {t.strip() for t in a.tables.split(",")}
    scenes = a.scenes.split(",") if a.scenes else (["08"] if a.quick else list(SCENE_IDS))
    confidences = (0.0, 10.0) if a.quick else CONFIDENCES
    base = replace(TerrainLbaOptions(), backend_apply="fixed_delay")
    if a.no_joint_shift:
        base = replace(base, georef=replace(base.georef, joint_shift=False))
    if a.no_terrain_term:
        base = replace(base, terrain_sigma_m=0.0)
    lba = replace(base, w_geo=10.0)
    vo = replace(base, w_geo=0.0)
    t_start = time.perf_counter()
    flights: dict[tuple[str, str], dict[str, Any]] = {}

    def flight(scene: str, kind: str, dur: float, methods: dict[str, TerrainLbaOptions]) -> dict[str, Any]:
        key = (scene, kind)
        if key not in flights:
            print(f"  flight scene {scene} {kind} {dur:.0f}s: {', '.join(methods)}", flush=True)
            flights[key] = run_flight(FlightSpec(scene, kind, dur, a.seed), methods)
            f = flights[key]["_flight"]
            print(
                f"    done in {f['wall_s']:.0f}s (render {f['render_ms_per_frame']:.0f} ms/frame)", flush=True
            )
        return flights[key]

    results: dict[str, Any] = {
        "quick": a.quick,
        "seed": a.seed,
        "joint_shift": base.georef.joint_shift,
        "terrain_sigma_m": base.terrain_sigma_m,
        "terrain_sigma_horizontal_m": base.terrain_sigma_horizontal_m,
        "attitude_sigma_rad": base.attitude_sigma_rad,
        "gravity_frames": base.gravity_frames,
        "attitude_floor_sigma_rad": base.attitude_floor_sigma_rad,
        "vo_tilt_sigma_rad": base.vo_tilt_sigma_rad,
    }
    # scene 08 circular carries Table 4's confidences and both methods of Tables 5 and 7
    if tables & {"4", "5", "7"} and ("08" in scenes or tables & {"4", "5"}):
        methods = {f"w{c:g}": replace(base, w_geo=c) for c in (confidences if "4" in tables else (0.0, 10.0))}
        r08 = flight("08", "circular", circ_s, methods)
        r08["vo_only"] = r08["w0"]
        r08["terrain_lba"] = r08["w10"]
    if "4" in tables:
        r = flights[("08", "circular")]
        rows = {
            f"{c:g}": {"vo_only" if c == 0 else "terrain_lba": _public(r[f"w{c:g}"])} for c in confidences
        }
        results["table4"] = {
            "scene": "08",
            "trajectory": "circular",
            "flight": r["_flight"],
            "confidence": rows,
        }
        print(
            table(
                ["w_G", *HEAD[1:]],
                [_row(c, next(iter(v.values()))) for c, v in rows.items()],
                "Table 4 analogue: scene 08, circular",
            )
        )
        write_json(a.json, results)
    if "5" in tables:
        t5: dict[str, Any] = {}
        for kind, dur in (("circular", circ_s), ("forward", fwd_s), ("scanning", scan_s)):
            if a.quick and kind != "circular":
                continue
            r = flight("08", kind, dur, {"vo_only": vo, "terrain_lba": lba})
            t5[kind] = {
                "flight": r["_flight"],
                "vo_only": _public(r["vo_only"]),
                "terrain_lba": _public(r["terrain_lba"]),
            }
        results["table5"] = {"scene": "08", "trajectory": t5}
        rows5 = [_row(f"{k} {m}", v[m]) for k, v in t5.items() for m in ("vo_only", "terrain_lba")]
        print(table(HEAD, rows5, "Table 5 analogue: scene 08, three trajectories"))
        write_json(a.json, results)
    if "7" in tables:
        t7: dict[str, Any] = {}
        for sid in scenes:
            r = flight(sid, "circular", circ_s, {"vo_only": vo, "terrain_lba": lba})
            t7[sid] = {
                "flight": r["_flight"],
                "vo_only": _public(r["vo_only"]),
                "terrain_lba": _public(r["terrain_lba"]),
                "distance_m": r["_flight"]["distance_m"],
            }
            results["table7_partial"] = {"scene": t7}
            write_json(a.json, results)
        summary: dict[str, Any] = {}
        for m in ("vo_only", "terrain_lba"):
            means = [t7[s][m]["mean"] for s in t7]
            summary[m] = {
                "mean_of_means_m": float(np.nanmean(means)),
                "worst_scene_mean_m": float(np.nanmax(means)),
                "min_fps": float(min(t7[s][m]["fps"] for s in t7)),
                "max_p99_ms": float(max(t7[s][m]["p99_ms"] for s in t7)),
            }
        summary["total_distance_m"] = float(sum(t7[s]["distance_m"] for s in t7))
        summary["scenes"] = list(t7)
        results.pop("table7_partial", None)
        results["table7"] = {"trajectory": "circular", "scene": t7, "summary": summary}
        rows7 = [_row(f"{s} {m}", t7[s][m]) for s in t7 for m in ("vo_only", "terrain_lba")]
        print(table(HEAD, rows7, "Table 7 analogue: all scenes, circular, Table 6 lighting"))
        print(table(FIX_HEAD, [_fix_row(s, t7[s]["terrain_lba"]) for s in t7], FIX_TITLE))
        rows_c = [_consistency_row(f"{s} {m}", t7[s][m]) for s in t7 for m in ("vo_only", "terrain_lba")]
        print(table(CONS_HEAD, rows_c, CONS_TITLE))
        print(
            f"mean APE over {len(t7)} scenes: vo_only {summary['vo_only']['mean_of_means_m']:.3f} m, "
            f"terrain_lba {summary['terrain_lba']['mean_of_means_m']:.3f} m "
            f"(worst scene {summary['terrain_lba']['worst_scene_mean_m']:.3f} m); "
            f"total distance {summary['total_distance_m']:.0f} m"
        )
    if "t" in tables:
        dur = a.timing_s or (10.0 if a.quick else 60.0)
        print(
            f"  timing: scene 08 circular {dur:.0f}s at {CAMERA_HZ:.0f} Hz, one estimator, back-end running",
            flush=True,
        )
        tm = timing_run(FlightSpec("08", "circular", dur, a.seed))
        results["timing"] = tm
        print(
            table(
                ["mode", "fps", "mean/ms", "p50/ms", "p99/ms", "max/ms", "over 66 ms", "err/m"],
                [
                    [
                        m,
                        tm[m]["fps"],
                        tm[m]["mean_ms"],
                        tm[m]["p50_ms"],
                        tm[m]["p99_ms"],
                        tm[m]["max_ms"],
                        tm[m]["over_budget_frames"],
                        tm[m]["mean_error_m"],
                    ]
                    for m in ("when_ready", "fixed_delay")
                ],
                f"Per-frame path at 15 Hz with the LBA running (terrain_lba, worker-process back-end, "
                f"OpenCV threads {tm['opencv_threads']})",
            )
        )
        write_json(a.json, results)
    plot_flights = [(f"{s} {k}", r) for (s, k), r in flights.items() if k == "circular" and s == "08"]
    plot_flights += [(f"{s} {k}", r) for (s, k), r in flights.items() if not (k == "circular" and s == "08")][
        :2
    ]
    plot_path = drift_plot_path(a.plot, a.json)
    if plot_flights and plot_path is not None:
        drift_plot(plot_path, plot_flights)
        results["drift_plot"] = str(plot_path)
    results["wall_s"] = time.perf_counter() - t_start
    write_json(a.json, results)
    return 0
