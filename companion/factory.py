"""Build the configured estimator. Imports each estimator lazily, so a daemon running one estimator
does not load the others' dependencies."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from companion.config import CompanionConfig
from companion.georef.shading import Sun
from companion.types import Estimator


def _initial_position(cfg: CompanionConfig) -> np.ndarray:
    p = cfg.estimator.initial_position_ned_m
    return np.zeros(3) if p is None else np.asarray(p, float)


def load_configured_dem(cfg: CompanionConfig):
    from companion.io.dem_store import load_dem

    assert cfg.dem is not None
    origin_en = None
    if cfg.dem.origin_east_m is not None and cfg.dem.origin_north_m is not None:
        origin_en = (cfg.dem.origin_east_m, cfg.dem.origin_north_m)
    return load_dem(cfg.dem.path, origin_en=origin_en, origin_alt_m=cfg.dem.origin_alt_m)


def build_estimator(cfg: CompanionConfig) -> Estimator:
    """The estimator named by ``cfg.estimator.kind``, ready for frames."""
    kind = cfg.estimator.kind
    sun = Sun.from_degrees(cfg.sun.intensity, cfg.sun.azimuth_deg, cfg.sun.elevation_deg)
    yaw0 = float(np.radians(cfg.estimator.initial_yaw_deg))
    if kind == "georef":
        from companion.estimators.georef_cv import GeorefEstimator, GeorefEstimatorOptions
        from companion.georef.georef import GeoReferencer, GeorefOptions

        cam = cfg.cameras["nadir"]
        g = cfg.estimator.georef
        geo = GeoReferencer(
            load_configured_dem(cfg),
            sun,
            cam.intrinsics(),
            cam.R_body_cam(),
            GeorefOptions(min_quality=g.matcher_min_quality),
        )
        opt = GeorefEstimatorOptions(
            attitude_sigma_rad=float(np.radians(g.attitude_sigma_deg)),
            max_coast_s=g.max_coast_s,
        )
        return GeorefEstimator(opt, geo, _initial_position(cfg))
    if kind == "terrain_lba":
        from companion.estimators.terrain_lba import TerrainLbaEstimator, TerrainLbaOptions

        cam = cfg.cameras["nadir"]
        t = cfg.estimator.terrain_lba
        lba_opt = TerrainLbaOptions(
            window_size=t.window_size,
            w_geo=t.w_geo,
            min_frames_between_kf=t.min_frames_between_kf,
            min_features_kf=t.min_features_kf,
            max_tracked_ratio_kf=t.max_tracked_ratio_kf,
            terrain_sigma_m=t.terrain_sigma_m,
            terrain_sigma_horizontal_m=t.terrain_sigma_horizontal_m,
            attitude_sigma_rad=t.attitude_sigma_rad,
            gravity_frames=t.gravity_frames,
            attitude_floor_sigma_rad=t.attitude_floor_sigma_rad,
            vo_tilt_sigma_rad=t.vo_tilt_sigma_rad,
            compass_sigma_rad=float(np.radians(t.compass_sigma_deg)),
            backend_apply=t.backend_apply,
            backend_delay_frames=t.backend_delay_frames,
        )
        lba_opt = replace(
            lba_opt,
            georef=replace(
                lba_opt.georef,
                joint_shift=t.joint_shift,
                rs_sweep_deg=t.heading_search_deg,
                relief_scales_m=tuple(t.relief_scales_m),
            ),
            backend=replace(
                lba_opt.backend,
                heading_from_matcher=t.heading_from_matcher,
                geo_sigma_adapt=t.fix_sigma_adapt,
                geo_quality_window=lba_opt.backend.geo_quality_window if t.fix_peak_weighting else 0,
                lba=replace(
                    lba_opt.backend.lba,
                    geo_bias_share=t.fix_bias_share,
                    geo_bias_corr_kf=t.fix_bias_corr_keyframes,
                ),
            ),
        )
        return TerrainLbaEstimator(
            lba_opt,
            cam.intrinsics(),
            cam.R_body_cam(),
            load_configured_dem(cfg),
            sun,
            _initial_position(cfg),
            yaw0,
        )
    if kind == "vis_thermal_ekf":
        from companion.constants import GRAVITY_MPS2
        from companion.ekf.options import cameras_for_mode
        from companion.estimators.vis_thermal_ekf import EkfOptions, VisThermalEkfEstimator

        e = cfg.estimator.ekf
        cams = cameras_for_mode(e.mode)
        # every [estimator.ekf] key but the daemon's pair_tolerance_ms is the EkfOptions field of that name
        keys = e.model_dump(exclude={"pair_tolerance_ms"})
        ekf_opt = EkfOptions(**{**keys, "patch_cameras": tuple(e.patch_cameras)})
        planet = cfg.origin.planet if cfg.origin is not None else "europa"
        p0 = cfg.estimator.initial_position_ned_m
        # no configured start: the filter starts from the autopilot's LOCAL_POSITION_NED (a hand-over from
        # the vehicle's navigation); velocity from it too, attitude from ATTITUDE (yaw0 without one)
        return VisThermalEkfEstimator(
            ekf_opt,
            {c: cfg.cameras[c].intrinsics() for c in cams},
            {c: cfg.cameras[c].R_body_cam() for c in cams},
            None if p0 is None else np.asarray(p0, float),
            initial_yaw_rad=yaw0,
            gravity_mps2=GRAVITY_MPS2[planet],
        )
    raise ValueError(f"unknown estimator kind {kind!r}")
