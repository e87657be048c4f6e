"""Typed configuration, loaded once from TOML and validated at start-up.

A bad file is refused with the key, the value and what was expected (``ConfigError``). Unknown keys are
errors too, so a typo never silently falls back to a default. Angles are degrees here (configs are for
people); the code converts to radians where it builds its options.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from companion.constants import R_BODY_CAM_NADIR
from companion.ekf.options import EkfOptions
from companion.geometry import CameraIntrinsics, rot_from_rpy

if TYPE_CHECKING:
    from companion.undistort import Undistorter


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message names the key, value and expectation."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class OriginConfig(_Strict):
    """Geodetic origin of the local NED world frame."""

    lat_deg: Annotated[float, Field(ge=-90, le=90)]
    lon_deg: Annotated[float, Field(ge=-180, le=180)]
    alt_m: float = 0.0
    planet: Literal["earth", "mars", "moon", "europa"] = "mars"


class ZenohConfig(_Strict):
    mode: Literal["peer", "client"] = "peer"
    connect: list[str] = []
    listen: list[str] = []
    multicast_scouting: bool = False
    status_key: str = "companion/status"


class CameraConfig(_Strict):
    """One camera: its Zenoh key (the ROS topic without the leading slash) and its geometry."""

    key: str
    message: Literal["image", "compressed"] = "image"
    width: Annotated[int, Field(gt=0, le=10000)] = 480
    height: Annotated[int, Field(gt=0, le=10000)] = 480
    focal_mm: Annotated[float, Field(gt=0)] = 36.0
    sensor_mm: Annotated[float, Field(gt=0)] = 36.0
    mount: Literal["nadir"] = "nadir"
    extra_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # where the camera sits, body FRD metres. The estimates are this camera's position; the autopilot moves
    # them to its body origin with VISO_POS_* / EKF2_EV_POS_*, which must say the same (the daemon checks)
    position_in_body_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # a calibrated camera: its pinhole matrix in pixels, all four or none; they replace focal_mm / sensor_mm
    # (square pixels, centred). Frames published rectified: camera_info's P. Frames published raw: camera_info's
    # K, with its lens distortion below
    fx_px: Annotated[float, Field(gt=0)] | None = None
    fy_px: Annotated[float, Field(gt=0)] | None = None
    cx_px: float | None = None
    cy_px: float | None = None
    # the lens distortion of raw frames, OpenCV / ROS plumb_bob order: k1, k2, p1, p2[, k3[, k4, k5, k6]]
    # (camera_info's D); the companion undistorts each frame before the estimator (companion.undistort), to
    # the pinhole matrix that keeps every pixel valid. Needs fx_px..cy_px (K). [] = frames already pinhole
    distortion: Annotated[list[float], Field(max_length=8)] = []

    @model_validator(mode="after")
    def _pinhole(self) -> CameraConfig:
        given = [v is not None for v in (self.fx_px, self.fy_px, self.cx_px, self.cy_px)]
        if any(given) and not all(given):
            raise ValueError("fx_px, fy_px, cx_px and cy_px go together (all four, or none)")
        if all(given) and not (0 <= self.cx_px < self.width and 0 <= self.cy_px < self.height):  # type: ignore[operator]
            raise ValueError(
                f"the principal point ({self.cx_px}, {self.cy_px}) is outside the {self.width}x{self.height} image"
            )
        if self.distortion:
            if len(self.distortion) not in (4, 5, 8):
                raise ValueError(
                    f"distortion has {len(self.distortion)} coefficients: 4, 5 or 8 (OpenCV's order)"
                )
            if not all(given):
                raise ValueError(
                    "distortion needs the calibrated matrix it goes with: fx_px, fy_px, cx_px, cy_px"
                )
        return self

    def raw_intrinsics(self) -> CameraIntrinsics:
        """The pinhole matrix of the frames as published (K of a raw, distorted camera)."""
        if self.fx_px is not None:
            assert self.fy_px is not None and self.cx_px is not None and self.cy_px is not None
            return CameraIntrinsics(self.width, self.height, self.fx_px, self.fy_px, self.cx_px, self.cy_px)
        return CameraIntrinsics.from_focal_sensor(self.width, self.height, self.focal_mm, self.sensor_mm)

    def intrinsics(self) -> CameraIntrinsics:
        """The pinhole matrix of the frames the estimator gets (undistorted when ``distortion`` is given)."""
        if self.distortion:
            from companion.undistort import rectified_intrinsics

            return rectified_intrinsics(self.raw_intrinsics(), np.asarray(self.distortion, float))
        return self.raw_intrinsics()

    def undistorter(self) -> Undistorter | None:
        """The map from raw to undistorted frames, or None when the frames are pinhole already."""
        if not self.distortion:
            return None
        from companion.undistort import Undistorter

        return Undistorter.build(self.raw_intrinsics(), np.asarray(self.distortion, float))

    def R_body_cam(self) -> np.ndarray:
        """Nadir mount, then an optional small mounting rotation (roll, pitch, yaw in the body frame)."""
        extra = rot_from_rpy(*np.radians(self.extra_rpy_deg))
        return extra @ R_BODY_CAM_NADIR


class MavlinkConfig(_Strict):
    connection: str = "udpout:127.0.0.1:14550"
    sysid: Annotated[int, Field(ge=1, le=255)] = 1
    compid: Annotated[int, Field(ge=1, le=255)] = 197
    message: Literal["vision_position_estimate", "odometry"] = "vision_position_estimate"
    max_rate_hz: Annotated[float, Field(gt=0, le=50)] = (
        30.0  # ArduPilot: <= 45 (EKF3 drops samples < 20 ms apart)
    )
    signing_key_hex: str = ""
    set_origin_if_missing: bool = True
    link_timeout_s: Annotated[float, Field(gt=0)] = 3.0
    # estimates of frames captured longer ago than this are not sent, counted as "too_old" (ArduPilot's EKF3
    # discards external-nav samples 500 ms behind its fusion time); 0 = send whatever the age
    max_estimate_age_ms: Annotated[float, Field(ge=0)] = 500.0
    # vis_thermal_ekf (the estimator that uses the IMU): no IMU message from the autopilot 2 s after it is
    # first heard, ask it for its IMU at this rate on this link (MAV_CMD_SET_MESSAGE_INTERVAL: RAW_IMU from
    # ArduPilot, HIGHRES_IMU from PX4); 0 = never ask
    request_imu_hz: Annotated[float, Field(ge=0, le=400)] = 50.0
    # log every message of this link, both directions, as a MAVLink telemetry log (mavlogdump.py, MAVExplorer
    # and Mission Planner read it); "{time}" in the path is the start time, ".tlog" is added; "" = off
    tlog: str = ""

    @field_validator("connection")
    @classmethod
    def _connection(cls, v: str) -> str:
        kinds = ("udpin:", "udpout:", "udp:", "tcp:", "tcpin:", "serial:")
        if not v.startswith(kinds):
            raise ValueError(f"must start with one of {', '.join(kinds)} (e.g. serial:/dev/ttyAMA0:921600)")
        return v

    @field_validator("signing_key_hex")
    @classmethod
    def _key(cls, v: str) -> str:
        if v and (len(v) != 64 or any(c not in "0123456789abcdefABCDEF" for c in v)):
            raise ValueError("must be empty or 64 hex digits (a 32-byte MAVLink 2 signing key)")
        return v


class SunConfig(_Strict):
    """Presumed lighting for the reference shading (paper 1: intensity 10, azimuth 0, elevation 60)."""

    intensity: Annotated[float, Field(gt=0)] = 10.0
    azimuth_deg: float = 0.0
    elevation_deg: Annotated[float, Field(ge=-90, le=90)] = 60.0


class DemConfig(_Strict):
    """The DEM the estimator uses: a GeoTIFF or an .npz written by sim_bridge."""

    path: str
    origin_east_m: float | None = None
    origin_north_m: float | None = None
    origin_alt_m: float = 0.0


class GeorefEstimatorConfig(_Strict):
    # the matcher's own threshold on its peak; low enough that the filter's innovation gate, not the
    # matcher, rejects the outliers (the matcher's covariance grows as the quality falls)
    matcher_min_quality: Annotated[float, Field(ge=0, le=1)] = 0.15
    attitude_sigma_deg: Annotated[float, Field(gt=0)] = 2.0
    max_coast_s: Annotated[float, Field(gt=0)] = 2.0


class TerrainLbaConfig(_Strict):
    window_size: Annotated[int, Field(ge=2, le=100)] = 15
    w_geo: Annotated[float, Field(ge=0)] = 10.0
    # the fixes' sigma (1 m / sqrt(w_geo) to start) grows to the scatter the fixes show about the visual
    # odometry, where the terrain matches worse (docs/benchmarks.md); false: fixed by w_geo
    fix_sigma_adapt: bool = True
    # each fix's sigma grows as its match peak falls below the recent fixes' (docs/benchmarks.md); false: every fix alike
    fix_peak_weighting: bool = True
    min_frames_between_kf: Annotated[int, Field(ge=1)] = 20
    min_features_kf: Annotated[int, Field(ge=1)] = 50
    max_tracked_ratio_kf: Annotated[float, Field(gt=0, le=1)] = 0.9
    joint_shift: bool = True  # key-frame fixes: shift fitted jointly with the reference (docs/benchmarks.md)
    # the scales (m) at which the matcher models reflectance tied to the relief (dust in hollows): its
    # fitted reference has a local-relief image, h - blur(h), per scale. Keep them several DEM cells wide
    relief_scales_m: Annotated[list[Annotated[float, Field(gt=0)]], Field(min_length=1, max_length=4)] = [
        20.0,
        5.0,
    ]
    # at start-up, turn the map by the heading error the matcher recovers from the terrain, and match each
    # fix at the heading its estimates so far give (docs/benchmarks.md); false: keep the compass heading for both until
    # the fixes have spread 25 m
    heading_from_matcher: bool = True
    # how far off the compass may be (deg): the matcher's start-up heading search tries headings this far
    # either side of it (180: no compass); each 2 deg more costs a match per start-up key frame (1.5-3 ms)
    heading_search_deg: Annotated[float, Field(ge=0, le=180)] = 30.0
    # the compass's 1-sigma error (deg): until the terrain gives the heading, the covariance sent to the
    # autopilot carries it out along the distance from the start, and the start-up fixes weigh the compass
    # against the matcher's heading estimates by it (180: no compass)
    compass_sigma_deg: Annotated[float, Field(gt=0, le=180)] = 2.0
    # landmarks held on the DEM in the adjustment: the DEM's vertical / horizontal error (m); 0 = off
    terrain_sigma_m: Annotated[float, Field(ge=0)] = 0.5
    terrain_sigma_horizontal_m: Annotated[float, Field(ge=0)] = 0.5
    # the share of each fix's horizontal variance the adjustment models as a bias that the fixes of
    # neighbouring key frames share (correlation length ``fix_bias_corr_keyframes``), so that a run of fixes
    # that agree with each other counts as fewer. 0 = independent fixes; 0.5 (the default) was better on 22
    # of 27 replayed Table 7 flights than 0 (docs/benchmarks.md, "Session 39")
    fix_bias_share: Annotated[float, Field(ge=0, lt=1)] = 0.5
    fix_bias_corr_keyframes: Annotated[float, Field(gt=0)] = 10.0
    # when the adjustment's result (it runs in a worker process beside the frames) is used: "when_ready", at the
    # first frame after it finishes (in flight: the lowest latency), or "fixed_delay", exactly
    # backend_delay_frames frames after its key frame, waiting if it is late (the same estimates run after
    # run, whatever the machine's load: what a bench replay at full speed wants; companion replay sets it
    # when no --rate is given)
    backend_apply: Literal["when_ready", "fixed_delay"] = "when_ready"
    backend_delay_frames: Annotated[int, Field(ge=1, le=1000)] = 10
    # the autopilot's roll/pitch noise per sample (rad, 1 sigma, frame to frame), the source of the
    # adjustment's gravity prior per key frame: at 100 m a tilt error of 0.1 deg moves the camera 0.17 m
    # sideways for the same ground point (set from your AHRS)
    attitude_sigma_rad: Annotated[float, Field(gt=0)] = 0.003
    # that prior's roll/pitch: the autopilot attitude of this many recent frames averaged (each carried to the
    # key frame by the visual odometry's rotation since); averages the attitude's noise, not a bias; 1 = the
    # key frame's own sample
    gravity_frames: Annotated[int, Field(ge=1, le=200)] = 20
    # the part of that average's error that more frames do not shrink (rad, 1 sigma): the AHRS's slow error
    # (a bias, a vibration-driven drift) and the VO's rotation error over the frames. Raise it for an AHRS
    # whose roll/pitch wander: the prior's sigma is sqrt(attitude^2 / gravity_frames + floor^2)
    attitude_floor_sigma_rad: Annotated[float, Field(ge=0)] = 0.001
    # each frame's output roll/pitch: the visual odometry's (this 1 sigma) fused with that average, the camera
    # turned about the ground it sees; 0 = the odometry's alone
    vo_tilt_sigma_rad: Annotated[float, Field(ge=0)] = 0.001


_EKF = EkfOptions()
"""The estimator's defaults, which the configuration's defaults repeat."""


class EkfConfig(_Strict):
    mode: Literal["visible", "thermal", "dual"] = "dual"
    max_landmarks_per_camera: Annotated[int, Field(ge=4, le=256)] = 32
    sampling: Literal["kde", "uniform"] = "kde"
    # dual: the diversity density over both cameras' landmarks (paper 2's map), false: each camera's own
    diversity_over_map: bool = True
    pair_tolerance_ms: Annotated[float, Field(gt=0)] = 5.0
    one_point_ransac: bool = True  # refuse matches the other matches disagree with (Civera et al. 2010)
    ransac_threshold_px: Annotated[float, Field(gt=0)] = 0.5
    # keypoint position noise per axis, px: the visible camera's, and the thermal camera's (0 = the same);
    # set from your cameras' matches (a sharper camera's matches weigh more in dual mode)
    pixel_sigma_px: Annotated[float, Field(gt=0)] = 1.0
    pixel_sigma_thermal_px: Annotated[float, Field(ge=0)] = 0.0
    # > 0: a match's sigma follows its SIFT keypoint's size, the camera's sigma x size / this (px; 0.5x to
    # 4x): coarse keypoints weigh less, fine ones more. 7.2 suits a visible-only vehicle (measured in
    # docs/benchmarks.md, session 51); 0 = every match the camera's sigma
    pixel_sigma_size_ref_px: Annotated[float, Field(ge=0)] = 0.0
    # match a landmark against the descriptor it was created with (false: the last matched keypoint's)
    anchor_descriptor: bool = True
    # a landmark SIFT misses is searched for with its first image patch (warped by the predicted motion,
    # normalised cross-correlation inside the gate); the correlation a found place must reach
    patch_cameras: list[Literal["visible", "thermal"]] = []
    patch_min_score: Annotated[float, Field(gt=0, le=1)] = 0.8
    # SIFT per camera: keypoints kept per image (best by contrast) and the contrast threshold; set from your
    # cameras (a faint, smooth thermal image wants a lower threshold)
    sift_nfeatures_visible: Annotated[int, Field(ge=10, le=5000)] = 800
    sift_nfeatures_thermal: Annotated[int, Field(ge=10, le=5000)] = 800
    sift_contrast_threshold_visible: Annotated[float, Field(gt=0, lt=1)] = 0.02
    sift_contrast_threshold_thermal: Annotated[float, Field(gt=0, lt=1)] = 0.005
    # the altimeter (DISTANCE_SENSOR): its range noise, m, 1 sigma (from the datasheet). The range is compared
    # with the plane through three landmarks around the beam; that plane's error is a state drawn afresh for
    # each new plane (this fraction of the range, 1 sigma) that decays with tau (s), plus a white part (this
    # fraction of the range: the ground under the moving beam). Rough ground wants larger fractions.
    altimeter_sigma_m: Annotated[float, Field(gt=0)] = 0.1
    facet_error_state: bool = True
    facet_error_rel_sigma: Annotated[float, Field(gt=0, le=1)] = 0.02
    facet_error_tau_s: Annotated[float, Field(ge=0)] = 2.0
    altimeter_white_rel_sigma: Annotated[float, Field(ge=0, le=1)] = 0.005
    # facet_error_state = false: the plane's error taken as white, this fraction of the range
    facet_rel_sigma: Annotated[float, Field(gt=0, le=1)] = 0.10
    # the altimeter's constant range offset, m, 1 sigma (what is left after calibrating it), carried in the
    # covariance sent to the autopilot and in the filter's gains, never estimated; 0 = not modelled
    altimeter_bias_sigma_m: Annotated[float, Field(ge=0, le=10)] = 0.0
    # the IMU's error model, from its datasheet (defaults: the simulated ICM-42688-class MEMS part): white
    # noise densities, bias random walks, and the biases' prior spread at the start (the filter estimates
    # them; false: the filter takes the IMU as unbiased, paper 2's state)
    accel_noise_density: Annotated[float, Field(gt=0)] = _EKF.accel_noise_density  # m/s^2/sqrt(Hz)
    gyro_noise_density: Annotated[float, Field(gt=0)] = _EKF.gyro_noise_density  # rad/s/sqrt(Hz)
    accel_bias_walk: Annotated[float, Field(ge=0)] = _EKF.accel_bias_walk  # m/s^3/sqrt(Hz)
    gyro_bias_walk: Annotated[float, Field(ge=0)] = _EKF.gyro_bias_walk  # rad/s^2/sqrt(Hz)
    estimate_imu_bias: bool = _EKF.estimate_imu_bias
    accel_bias_sigma0: Annotated[float, Field(gt=0)] = _EKF.accel_bias_sigma0  # m/s^2
    gyro_bias_sigma0: Annotated[float, Field(gt=0)] = _EKF.gyro_bias_sigma0  # rad/s
    # without an IMU sample for imu_hold_max_s (s): a constant-velocity motion model whose noise says how hard
    # the vehicle may manoeuvre unseen (velocity sigma after a second, m/s; attitude sigma after a second, rad)
    imu_hold_max_s: Annotated[float, Field(gt=0, le=10)] = _EKF.imu_hold_max_s
    no_imu_accel_noise_density: Annotated[float, Field(gt=0)] = _EKF.no_imu_accel_noise_density
    no_imu_gyro_noise_density: Annotated[float, Field(gt=0)] = _EKF.no_imu_gyro_noise_density
    # how well the start is known (the autopilot's LOCAL_POSITION_NED and ATTITUDE at the hand-over, or the
    # configured start), 1 sigma per axis: position m, velocity m/s, roll and pitch rad, yaw rad
    initial_position_sigma_m: Annotated[float, Field(gt=0)] = _EKF.initial_position_sigma_m
    initial_velocity_sigma_mps: Annotated[float, Field(gt=0)] = _EKF.initial_velocity_sigma_mps
    initial_tilt_sigma_rad: Annotated[float, Field(gt=0, le=1)] = _EKF.initial_tilt_sigma_rad
    initial_yaw_sigma_rad: Annotated[float, Field(gt=0, le=3.2)] = _EKF.initial_yaw_sigma_rad
    # the start's attitude: the autopilot's ATTITUDE samples within this many seconds of the first frame set
    # averaged, each carried to it by the IMU's gyro (averages the attitude's sample-to-sample jitter, not a
    # bias); 0 = the nearest sample alone
    initial_attitude_window_s: Annotated[float, Field(ge=0, le=5)] = _EKF.initial_attitude_window_s
    # with no ATTITUDE sample yet at the first frame set, wait this long (s) for one before starting from the
    # IMU's gravity and [estimator] initial_yaw_deg (a heading the cameras cannot correct)
    start_wait_s: Annotated[float, Field(ge=0, le=600)] = _EKF.start_wait_s
    # a new landmark's inverse-depth prior: flat ground at the altimeter's height, with this relative sigma
    # (the ground's relief over the height, roughly); raise it over rough ground
    init_rho_rel_sigma: Annotated[float, Field(gt=0, le=2)] = _EKF.init_rho_rel_sigma
    # SIFT on the image scaled by this (0.5: the pyramid starts at the camera's resolution, ~2.6x faster than
    # 1.0); raise it on a computer with time to spare
    detect_scale: Annotated[float, Field(gt=0.1, le=1)] = _EKF.detect_scale


class EstimatorConfig(_Strict):
    kind: Literal["georef", "terrain_lba", "vis_thermal_ekf"] = "georef"
    initial_position_ned_m: tuple[float, float, float] | None = None
    initial_yaw_deg: float = 0.0
    georef: GeorefEstimatorConfig = GeorefEstimatorConfig()
    terrain_lba: TerrainLbaConfig = TerrainLbaConfig()
    ekf: EkfConfig = EkfConfig()


class DaemonConfig(_Strict):
    status_period_s: Annotated[float, Field(gt=0)] = 1.0
    max_frame_age_ms: Annotated[float, Field(gt=0)] = 500.0
    max_future_ms: Annotated[float, Field(gt=0)] = 200.0
    log_level: Literal["debug", "info", "warning", "error"] = "info"
    # record every estimate: "<path>.csv" (all, with what became of each) and "<path>.tum" (the ones sent,
    # for evo); "{time}" in the path is the start time; "" = off (``companion.io.estimate_log``)
    estimates_log: str = ""
    # record what the estimator is given (camera frames, IMU, attitude, range, local position) as a rosbag2
    # (MCAP) directory for ``companion replay``; "{time}" in the path is the start time; "" = off
    # (``companion.io.input_recorder``; with PNG frames ~1.2 MB/s for the Europa camera pair at 2 Hz)
    record_inputs: str = ""
    # the recorded camera frames: "png" (lossless, 2/3 of the bytes for 6 ms of the writer thread's CPU per
    # 480 x 480 8-bit frame, 11 ms per 640 x 480) or "raw" (sensor_msgs/Image, no encoding; bench "recorder")
    record_frames: Literal["png", "raw"] = "png"
    # the input record closes itself (readable) when the disk has less free space than this, MB
    record_min_free_mb: Annotated[float, Field(ge=0)] = 500.0
    # threads OpenCV may use inside one call (cv2.setNumThreads), 0 = its default, one per core. One saves CPU
    # per frame for the rest of the companion (the terrain back-end, Zenoh, MAVLink) at the same latency with
    # georef and a few ms more with terrain_lba (``python -m bench latency --opencv-threads N``; docs/benchmarks.md)
    opencv_threads: Annotated[int, Field(ge=0, le=64)] = 1


class CompanionConfig(_Strict):
    """The whole companion configuration (one TOML file)."""

    name: str = "companion"
    origin: OriginConfig | None = None
    zenoh: ZenohConfig = ZenohConfig()
    cameras: dict[str, CameraConfig]
    mavlink: MavlinkConfig = MavlinkConfig()
    estimator: EstimatorConfig = EstimatorConfig()
    dem: DemConfig | None = None
    sun: SunConfig = SunConfig()
    daemon: DaemonConfig = DaemonConfig()

    @model_validator(mode="after")
    def _consistent(self) -> CompanionConfig:
        kind = self.estimator.kind
        if kind in ("georef", "terrain_lba"):
            if "nadir" not in self.cameras:
                raise ValueError(f"estimator.kind = {kind!r} needs a [cameras.nadir] section")
            if self.dem is None:
                raise ValueError(f"estimator.kind = {kind!r} needs a [dem] section with the terrain model")
        if kind == "vis_thermal_ekf":
            need = {"visible": ["visible"], "thermal": ["thermal"], "dual": ["visible", "thermal"]}
            for cam in need[self.estimator.ekf.mode]:
                if cam not in self.cameras:
                    raise ValueError(
                        f"estimator.ekf.mode = {self.estimator.ekf.mode!r} needs a [cameras.{cam}] section"
                    )
        return self


def _format_errors(err: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid configuration"]
    for e in err.errors():
        key = ".".join(str(p) for p in e["loc"]) or "(top level)"
        if e["type"] == "extra_forbidden":
            lines.append(f"  {key} = {e.get('input')!r}: unknown key (check the spelling)")
        elif e["type"] == "missing":
            lines.append(f"  {key}: required key is missing")
        else:
            lines.append(f"  {key} = {e.get('input')!r}: {e['msg']}")
    return "\n".join(lines)


def parse_config(data: dict[str, Any], source: str = "<config>") -> CompanionConfig:
    """Validate a parsed TOML document. Raises ConfigError with every problem listed."""
    try:
        return CompanionConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_errors(err, source)) from None


def load_config(path: str | Path) -> CompanionConfig:
    """Read and validate a TOML file. Raises ConfigError (missing file, bad TOML, bad values)."""
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as e:
        raise ConfigError(f"{p}: cannot read configuration: {e.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML: {e}") from None
    cfg = parse_config(data, str(p))
    if cfg.dem is not None and not Path(cfg.dem.path).is_absolute():
        # relative DEM paths are relative to the config file, so configs can travel with their data
        cfg = cfg.model_copy(
            update={"dem": cfg.dem.model_copy(update={"path": str(p.parent / cfg.dem.path)})}
        )
    return cfg
