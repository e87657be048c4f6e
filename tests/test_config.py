"""Configuration: every shipped config validates; mistakes are refused with key, value and expectation."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion.cli import apply_overrides
from companion.config import ConfigError, load_config, parse_config

ROOT = Path(__file__).resolve().parents[1]
MINIMAL = {"cameras": {"nadir": {"key": "uav/camera/nadir"}}, "dem": {"path": "dem.npz"}}


@pytest.mark.parametrize("path", sorted((ROOT / "configs").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_configs_validate(path: Path) -> None:
    cfg = load_config(path)
    assert cfg.cameras


def test_typo_in_key_is_refused_with_its_name() -> None:
    data = {**MINIMAL, "mavlink": {"conection": "udpout:127.0.0.1:14550"}}
    with pytest.raises(ConfigError) as e:
        parse_config(data, "x.toml")
    assert "mavlink.conection" in str(e.value) and "unknown key" in str(e.value)


def test_wrong_type_and_range_are_refused_with_value_and_expectation() -> None:
    data = {**MINIMAL, "mavlink": {"max_rate_hz": 200}, "cameras": {"nadir": {"key": "k", "width": "wide"}}}
    with pytest.raises(ConfigError) as e:
        parse_config(data)
    msg = str(e.value)
    assert "mavlink.max_rate_hz = 200" in msg and "less than or equal to 50" in msg
    assert "cameras.nadir.width = 'wide'" in msg


def test_bad_connection_string_and_signing_key() -> None:
    with pytest.raises(ConfigError, match="mavlink.connection"):
        parse_config({**MINIMAL, "mavlink": {"connection": "com3"}})
    with pytest.raises(ConfigError, match="64 hex digits"):
        parse_config({**MINIMAL, "mavlink": {"signing_key_hex": "abc"}})


def test_estimator_needs_its_cameras_and_dem() -> None:
    with pytest.raises(ConfigError, match="needs a \\[dem\\]"):
        parse_config({"cameras": {"nadir": {"key": "k"}}})
    with pytest.raises(ConfigError, match="cameras.thermal"):
        parse_config({"cameras": {"visible": {"key": "v"}}, "estimator": {"kind": "vis_thermal_ekf"}})


def test_camera_geometry_from_config() -> None:
    cfg = parse_config(MINIMAL)
    intr = cfg.cameras["nadir"].intrinsics()
    assert intr.fx == pytest.approx(480.0)
    R = cfg.cameras["nadir"].R_body_cam()
    # nadir: the optical axis is body down
    np.testing.assert_allclose(R[:, 2], [0, 0, 1], atol=1e-12)


def test_a_calibrated_camera_gives_its_own_pinhole_matrix() -> None:
    cam = {"key": "uav/camera/nadir", "width": 640, "height": 480}
    calib = {"fx_px": 552.1, "fy_px": 551.4, "cx_px": 322.7, "cy_px": 236.9}
    cfg = parse_config({**MINIMAL, "cameras": {"nadir": {**cam, **calib}}})
    np.testing.assert_allclose(
        cfg.cameras["nadir"].intrinsics().K, np.array([[552.1, 0, 322.7], [0, 551.4, 236.9], [0, 0, 1.0]])
    )
    with pytest.raises(ConfigError, match="all four, or none"):
        parse_config({**MINIMAL, "cameras": {"nadir": {**cam, "fx_px": 552.1}}})
    with pytest.raises(ConfigError, match="outside the 640x480 image"):
        parse_config({**MINIMAL, "cameras": {"nadir": {**cam, **calib, "cx_px": 700.0}}})


def test_overrides_are_validated_too() -> None:
    cfg = parse_config(MINIMAL)
    cfg2 = apply_overrides(
        cfg, ['mavlink.connection="tcp:127.0.0.1:5760"', "estimator.initial_yaw_deg=45"], "x"
    )
    assert cfg2.mavlink.connection == "tcp:127.0.0.1:5760" and cfg2.estimator.initial_yaw_deg == 45
    with pytest.raises(ConfigError, match="mavlink.sysid"):
        apply_overrides(cfg, ["mavlink.sysid=0"], "x")


def test_every_ekf_key_reaches_the_filter_options() -> None:
    """Each [estimator.ekf] key set away from its default arrives in the estimator's EkfOptions."""
    from companion.config import EkfConfig
    from companion.factory import build_estimator

    changed = {
        "mode": "thermal",
        "max_landmarks_per_camera": 20,
        "sampling": "uniform",
        "diversity_over_map": False,
        "one_point_ransac": False,
        "ransac_threshold_px": 0.8,
        "pixel_sigma_px": 1.5,
        "pixel_sigma_thermal_px": 0.6,
        "pixel_sigma_size_ref_px": 4.0,
        "anchor_descriptor": False,
        "patch_cameras": ("visible",),
        "patch_min_score": 0.9,
        "sift_nfeatures_visible": 500,
        "sift_nfeatures_thermal": 300,
        "sift_contrast_threshold_visible": 0.03,
        "sift_contrast_threshold_thermal": 0.01,
        "altimeter_sigma_m": 0.3,
        "facet_error_state": False,
        "facet_error_rel_sigma": 0.03,
        "facet_error_tau_s": 1.0,
        "altimeter_white_rel_sigma": 0.01,
        "facet_rel_sigma": 0.2,
        "altimeter_bias_sigma_m": 0.2,
        "accel_noise_density": 4e-3,
        "gyro_noise_density": 3e-4,
        "accel_bias_walk": 2e-4,
        "gyro_bias_walk": 4e-6,
        "estimate_imu_bias": False,
        "accel_bias_sigma0": 0.05,
        "gyro_bias_sigma0": 1e-3,
        "initial_position_sigma_m": 0.5,
        "initial_velocity_sigma_mps": 0.2,
        "initial_tilt_sigma_rad": 0.02,
        "initial_yaw_sigma_rad": 0.1,
        "detect_scale": 0.75,
        "initial_attitude_window_s": 0.5,
        "start_wait_s": 3.0,
        "imu_hold_max_s": 0.2,
        "no_imu_accel_noise_density": 1.0,
        "no_imu_gyro_noise_density": 0.1,
        "init_rho_rel_sigma": 0.7,
    }
    assert set(changed) | {"pair_tolerance_ms"} == set(EkfConfig.model_fields)  # a new key must join here
    cfg = parse_config(
        {
            "cameras": {"thermal": {"key": "t", "width": 640, "height": 480}},
            "estimator": {"kind": "vis_thermal_ekf", "ekf": changed},
        }
    )
    est = build_estimator(cfg)
    try:
        for key, value in changed.items():
            assert getattr(est.options, key) == value, key  # type: ignore[attr-defined]
    finally:
        est.close()


def test_every_terrain_lba_key_reaches_the_estimator_options(tmp_path: Path) -> None:
    """Each [estimator.terrain_lba] key set away from its default arrives in the estimator's options (and
    the adjustment's, for the ones it passes on)."""
    import numpy as np

    from companion.config import TerrainLbaConfig
    from companion.factory import build_estimator
    from companion.georef.dem import Dem
    from companion.io.dem_store import save_dem_npz

    changed: dict[str, Any] = {
        "window_size": 12,
        "w_geo": 5.0,
        "fix_sigma_adapt": False,
        "fix_peak_weighting": False,
        "min_frames_between_kf": 15,
        "min_features_kf": 60,
        "max_tracked_ratio_kf": 0.8,
        "joint_shift": False,
        "relief_scales_m": [30.0],
        "heading_from_matcher": False,
        "heading_search_deg": 12.0,
        "compass_sigma_deg": 5.0,
        "terrain_sigma_m": 0.7,
        "terrain_sigma_horizontal_m": 0.3,
        "attitude_sigma_rad": 0.004,
        "gravity_frames": 5,
        "attitude_floor_sigma_rad": 0.0,
        "vo_tilt_sigma_rad": 0.002,
        "fix_bias_share": 0.5,
        "fix_bias_corr_keyframes": 20.0,
        "backend_apply": "fixed_delay",
        "backend_delay_frames": 7,
    }
    assert set(changed) == set(TerrainLbaConfig.model_fields)  # a new key must join here
    dem_path = tmp_path / "dem.npz"
    save_dem_npz(dem_path, Dem(np.zeros((50, 50), np.float32), 25.0, -25.0, 1.0))
    cfg = parse_config(
        {
            "cameras": {"nadir": {"key": "k"}},
            "dem": {"path": str(dem_path)},
            "estimator": {"kind": "terrain_lba", "terrain_lba": changed},
        }
    )
    est = build_estimator(cfg)
    try:
        opt = est.opt  # type: ignore[attr-defined]
        lba = opt.backend.lba
        for key, value in changed.items():
            if key == "joint_shift":
                assert opt.georef.joint_shift is value
            elif key == "relief_scales_m":
                assert opt.georef.relief_scales_m == (30.0,)
            elif key == "heading_from_matcher":
                assert opt.backend.heading_from_matcher is value
            elif key == "fix_sigma_adapt":
                assert opt.backend.geo_sigma_adapt is value
            elif key == "fix_peak_weighting":
                assert opt.backend.geo_quality_window == 0
            elif key == "heading_search_deg":
                assert opt.georef.rs_sweep_deg == value
            elif key == "fix_bias_share":
                assert lba.geo_bias_share == value
            elif key == "fix_bias_corr_keyframes":
                assert lba.geo_bias_corr_kf == value
            elif key == "compass_sigma_deg":
                assert opt.compass_sigma_rad == pytest.approx(np.radians(value))
                # the prior the start-up fixes' heading is shrunk towards
                assert opt.backend.heading_prior_sigma_rad == pytest.approx(np.radians(value))
            else:
                assert getattr(opt, key) == value, key
        assert (lba.w_geo, lba.terrain_sigma_m, lba.terrain_sigma_horizontal_m) == (5.0, 0.7, 0.3)
        assert lba.gravity_sigma_rad == pytest.approx(0.004 / np.sqrt(5))  # floor 0: the noise over 5 frames
        assert opt.vo.gravity_frames == 5
    finally:
        est.close()


def test_cli_exits_2_with_a_clear_message(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('[cameras.nadir]\nkey = "k"\nwidht = 480\n[dem]\npath = "d.npz"\n')
    r = subprocess.run(
        [sys.executable, "-m", "companion", "run", "--config", str(bad)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2
    assert "cameras.nadir.widht" in r.stderr and "unknown key" in r.stderr
    missing = subprocess.run(
        [sys.executable, "-m", "companion", "run", "--config", str(tmp_path / "nope.toml")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert missing.returncode == 2 and "cannot read" in missing.stderr
    notoml = tmp_path / "broken.toml"
    notoml.write_text("[cameras\n")
    r = subprocess.run(
        [sys.executable, "-m", "companion", "check-config", str(notoml)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 2 and "not valid TOML" in r.stderr


def test_check_config_names_the_records_it_turns_on(capsys: pytest.CaptureFixture[str]) -> None:
    from companion.cli import cmd_check

    path = str(ROOT / "configs" / "vehicle_serial_geotiff.toml")
    assert cmd_check(path, []) == 0
    line = capsys.readouterr().out.splitlines()[-1]
    assert line == (
        "  records: estimates /var/lib/companion/flights/estimates-{time}; "
        "mavlink /var/lib/companion/flights/mavlink-{time}"
    )
    assert cmd_check(path, ['daemon.estimates_log=""', 'mavlink.tlog=""']) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "  records: none"


def test_opencv_threads_from_the_config() -> None:
    import cv2

    from companion.cli import configure_opencv

    cfg = parse_config(MINIMAL)
    assert cfg.daemon.opencv_threads == 1
    with pytest.raises(ConfigError, match="opencv_threads"):
        apply_overrides(cfg, ["daemon.opencv_threads=-2"], "test")
    before = cv2.getNumThreads()
    try:
        configure_opencv(apply_overrides(cfg, ["daemon.opencv_threads=3"], "test").daemon.opencv_threads)
        assert cv2.getNumThreads() == 3
        configure_opencv(cfg.daemon.opencv_threads)
        assert cv2.getNumThreads() == 1
        configure_opencv(0)  # OpenCV's default: one per core
        assert cv2.getNumThreads() == cv2.getNumberOfCPUs()
    finally:
        cv2.setNumThreads(before)
