"""A synthetic point-landmark scene for the EKF tests (no images): seeded ground points with random
SIFT-like descriptors, a nadir camera flown along a ``sim_bridge.trajectory`` path, noisy keypoints.

Imported by the other tests/test_ekf_*.py files; its own tests check determinism and visibility.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.constants import GRAVITY_MPS2, R_BODY_CAM_NADIR
from companion.ekf.features import Detections
from companion.ekf.landmarks import CameraModel
from companion.geometry import CameraIntrinsics, project
from sim_bridge.trajectory import ImuNoise, Trajectory, forward, imu_samples

G = GRAVITY_MPS2["europa"]
INTR = CameraIntrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)


def camera_model(intr: CameraIntrinsics = INTR) -> CameraModel:
    return CameraModel(intr.K, intr.width, intr.height, R_BODY_CAM_NADIR.copy(), np.zeros(3))


@dataclass(frozen=True)
class PointScene:
    """points: (M,3) world NED; desc: (M,128) float32 descriptors (norm ~512, like OpenCV SIFT);
    strength: (M,) fixed detector response (the strongest points in view are the ones detected, as SIFT's
    nfeatures keeps the highest-contrast keypoints)."""

    points: np.ndarray
    desc: np.ndarray
    strength: np.ndarray


def make_scene(
    seed: int, extent_m: float = 1200.0, n_points: int = 30000, relief_m: float = 15.0
) -> PointScene:
    rng = np.random.default_rng(seed)
    ne = rng.uniform(-extent_m / 2, extent_m / 2, (n_points, 2))
    elev = relief_m * np.sin(ne[:, 0] / 90.0) * np.cos(ne[:, 1] / 70.0) + rng.normal(0, 1.0, n_points)
    pts = np.column_stack([ne, -elev])
    d = np.abs(rng.normal(0, 1, (n_points, 128))).astype(np.float32)
    d *= 512.0 / np.linalg.norm(d, axis=1, keepdims=True)
    return PointScene(pts, d, rng.random(n_points))


def detections(
    scene: PointScene,
    R_world_body: np.ndarray,
    p_body: np.ndarray,
    rng: np.random.Generator,
    pixel_sigma: float = 0.7,
    desc_sigma: float = 8.0,
    max_kp: int = 400,
) -> tuple[Detections, np.ndarray]:
    """Keypoints of the points in view (pixel noise, descriptor noise); returns (detections, point ids)."""
    R_wc = R_world_body @ R_BODY_CAM_NADIR
    uv, z = project(INTR.K, R_wc, p_body, scene.points)
    ok = (
        (z > 0)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] <= INTR.width - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= INTR.height - 1)
    )
    ids = np.flatnonzero(ok)
    if len(ids) > max_kp:
        ids = np.sort(ids[np.argsort(-scene.strength[ids])[:max_kp]])
    uv_n = uv[ids] + rng.normal(0, pixel_sigma, (len(ids), 2))
    desc = scene.desc[ids] + rng.normal(0, desc_sigma, (len(ids), 128)).astype(np.float32)
    return Detections(uv_n, desc.astype(np.float32)), ids


def straight_flight(
    duration_s: float = 60.0, speed_mps: float = 5.0, altitude_m: float = 100.0
) -> Trajectory:
    return forward((-200.0, -100.0), 0.4, altitude_m, speed_mps, duration_s, ramp_s=5.0, gravity_mps2=G)


def imu(traj: Trajectory, seed: int, rate_hz: float = 100.0, noise: ImuNoise | None = None):
    return imu_samples(traj, rate_hz, noise, seed)


def test_scene_is_deterministic():
    a, b = make_scene(3, n_points=500), make_scene(3, n_points=500)
    assert np.array_equal(a.points, b.points) and np.array_equal(a.desc, b.desc)


def test_scene_fills_the_view():
    scene = make_scene(0)
    traj = straight_flight()
    st = traj.state_at(10.0)
    det, _ = detections(scene, st.R_world_body, st.p_world, np.random.default_rng(0))
    assert len(det) >= 200
