"""Lens distortion: the companion's undistortion of raw frames (companion.undistort), its configuration, and a
replayed flight whose cameras have a real lens model (the simulator distorts its rendered images)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.config import ConfigError, load_config, parse_config
from companion.factory import build_estimator
from companion.geometry import CameraIntrinsics
from companion.replay import replay_bag
from companion.undistort import Undistorter
from sim_bridge.flight_bag import DistortingLens, FlightBagOptions, write_flight_bag

ROOT = Path(__file__).resolve().parents[1]
RAW = CameraIntrinsics(640, 480, 554.0, 553.0, 321.0, 238.0)
LENS = (-0.12, 0.05, 0.001, -0.0005, -0.01)  # a wide-angle lens's barrel distortion


def _sample(im: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Bilinear values of ``im`` at the pixels ``p`` (N, 2)."""
    x, y = (p[:, i].astype(np.float32).reshape(-1, 1) for i in (0, 1))
    return np.asarray(cv2.remap(im.astype(np.float32), x, y, cv2.INTER_LINEAR)).ravel()


def test_undistorted_pixels_hold_what_the_lens_put_where_the_model_says() -> None:
    u = Undistorter.build(RAW, np.array(LENS))
    rng = np.random.default_rng(0)
    raw = cv2.GaussianBlur((rng.random((480, 640)) * 255).astype(np.uint8), (0, 0), 3)
    und = u.apply(raw)
    assert und.shape == raw.shape and und.dtype == raw.dtype
    uv = rng.uniform([10, 10], [630, 470], (300, 2))
    d = u.distort_points(uv)

    # OpenCV's fixed-point maps (1/32 px): within a grey level or so on a smooth image
    assert np.max(np.abs(_sample(und, uv) - _sample(raw, d))) < 2.0
    # the pinhole matrix keeps only valid pixels: every rectified pixel's ray lands inside the raw image
    w, h = RAW.width, RAW.height
    edge = np.concatenate([[(x, 0) for x in range(w)], [(x, h - 1) for x in range(w)],
                           [(0, y) for y in range(h)], [(w - 1, y) for y in range(h)]]).astype(float)  # fmt: skip
    de = u.distort_points(edge)
    assert de[:, 0].min() >= -0.5 and de[:, 0].max() <= w - 0.5 and de[:, 1].min() >= -0.5
    assert de[:, 1].max() <= h - 0.5
    with pytest.raises(ValueError, match="calibration 640x480"):
        u.apply(np.zeros((480, 648), np.uint8))


def test_the_simulators_lens_is_the_inverse_of_the_companions() -> None:
    lens = DistortingLens(RAW, LENS)
    u = Undistorter.build(RAW, np.array(LENS))
    rng = np.random.default_rng(1)
    wide = cv2.GaussianBlur(
        (rng.random((lens.wide.height, lens.wide.width)) * 60000).astype(np.uint16), (0, 0), 4
    )
    raw = lens.apply(wide)
    und = u.apply(raw)
    # the undistorted image is the pinhole rendering seen through the rectified matrix P
    P, W = u.rectified, lens.wide
    uv = rng.uniform([20, 20], [620, 460], (300, 2))
    in_wide = np.column_stack(
        [(uv[:, 0] - P.cx) / P.fx * W.fx + W.cx, (uv[:, 1] - P.cy) / P.fy * W.fy + W.cy]
    )
    a, b = _sample(und, uv), _sample(wide, in_wide)
    assert np.median(np.abs(a - b)) < 0.01 * 60000 / 4  # two resamplings of a smooth image


def test_distortion_configuration_is_checked() -> None:
    cam = {"key": "k", "width": 640, "height": 480}
    k = {"fx_px": 554.0, "fy_px": 553.0, "cx_px": 321.0, "cy_px": 238.0}
    base = {"estimator": {"kind": "vis_thermal_ekf", "ekf": {"mode": "visible"}}}
    with pytest.raises(ConfigError, match="needs the calibrated matrix"):
        parse_config({**base, "cameras": {"visible": {**cam, "distortion": list(LENS)}}})
    with pytest.raises(ConfigError, match="4, 5 or 8"):
        parse_config({**base, "cameras": {"visible": {**cam, **k, "distortion": [0.1, 0.0, 0.0]}}})
    cfg = parse_config({**base, "cameras": {"visible": {**cam, **k, "distortion": list(LENS)}}})
    c = cfg.cameras["visible"]
    assert c.raw_intrinsics() == RAW and c.intrinsics() == Undistorter.build(RAW, np.array(LENS)).rectified
    assert (
        parse_config({**base, "cameras": {"visible": {**cam, **k}}}).cameras["visible"].undistorter() is None
    )


@pytest.fixture(scope="module")
def distorted_flight(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("lens") / "europa"
    s = write_flight_bag(out, FlightBagOptions(trajectory="1", duration_s=20.0, distortion=LENS))
    return out, s


def test_a_flight_through_a_lens_replays_accurately_only_with_its_lens_model(
    distorted_flight: tuple[Path, dict], tmp_path: Path
) -> None:
    bag, made = distorted_flight
    K = made["camera_K"]
    cal = {"fx_px": K["fx"], "fy_px": K["fy"], "cx_px": K["cx"], "cy_px": K["cy"], "distortion": list(LENS)}
    plain = load_config(ROOT / "configs/europa_dual_ekf.toml")
    data = plain.model_dump()
    for cam in ("visible", "thermal"):
        data["cameras"][cam].update(cal)
    lensed = parse_config(data)
    with_lens = replay_bag(bag, lensed, build_estimator(lensed), tmp_path / "lens")
    without = replay_bag(bag, plain, build_estimator(plain), tmp_path / "pinhole")
    assert with_lens.estimator_errors == 0 and with_lens.would_send == 38
    e1, e0 = with_lens.error_m, without.error_m
    assert e1 is not None and e0 is not None
    # measured on 60 s of this flight: 0.35 m mean with the lens model, 2.7 m without (NEES 0.25 against 63)
    assert e1["mean"] < 1.0 and e0["mean"] > 2 * e1["mean"], (e1, e0)


def test_frames_of_another_size_than_the_calibration_are_counted_not_estimated(
    distorted_flight: tuple[Path, dict], tmp_path: Path
) -> None:
    bag, _ = distorted_flight
    data = load_config(ROOT / "configs/europa_dual_ekf.toml").model_dump()
    data["cameras"]["visible"].update(
        {
            "width": 648,
            "fx_px": 554.0,
            "fy_px": 554.0,
            "cx_px": 324.0,
            "cy_px": 240.0,
            "distortion": list(LENS),
        }
    )
    cfg = parse_config(data)
    s = replay_bag(bag, cfg, build_estimator(cfg), tmp_path)
    assert s.not_sent == {"bad_frame_size": 41} and s.estimates == 0 and s.estimator_errors == 0
