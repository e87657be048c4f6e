"""Options of the visible / thermal / dual inverse-depth EKF-SLAM (paper 2), one frozen dataclass.

Every default is documented beside it with its unit. The daemon builds this from the TOML config;
the benchmark and the tests build it directly.
"""

from __future__ import annotations

from dataclasses import dataclass

MODES = ("visible", "thermal", "dual")
"""Sensing configurations of paper 2: one camera, the other, or both landmarks in one map (eq. 7)."""

SAMPLING_METHODS = ("kde", "uniform")
"""New-landmark sampling: spatial diversity D(l) = -log f(l) (eq. 8) or uniform (Brunner et al.)."""

MATCH_SIGMA_FACTORS = (0.5, 4.0)
"""Smallest and largest factor ``pixel_sigma_size_ref_px`` puts on a camera's pixel sigma."""


def cameras_for_mode(mode: str) -> tuple[str, ...]:
    """Camera names used by a mode: ("visible",), ("thermal",) or ("visible", "thermal")."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    return ("visible", "thermal") if mode == "dual" else (mode,)


@dataclass(frozen=True)
class EkfOptions:
    """Filter, tracking and sampling settings.

    IMU densities default to the simulated IMU (``sim_bridge.trajectory.ImuNoise``: an ICM-42688-class
    MEMS part); set them from the real IMU's datasheet on a vehicle.
    """

    mode: str = "dual"  # "visible" | "thermal" | "dual"
    max_landmarks_per_camera: int = 32  # N of eqs. 6-7 (paper: 32 per camera, 64 in the dual map)
    sampling: str = "kde"  # "kde" (eq. 8, spatial diversity) | "uniform" (Brunner et al. 2011)
    # --- IMU propagation (eqs. 1-4) ---
    accel_noise_density: float = 2.0e-3  # m/s^2/sqrt(Hz), white noise on the specific force
    gyro_noise_density: float = 1.7e-4  # rad/s/sqrt(Hz), white noise on the angular rate
    accel_bias_walk: float = 1.0e-4  # m/s^3/sqrt(Hz), accelerometer bias random walk
    gyro_bias_walk: float = 2.0e-6  # rad/s^2/sqrt(Hz), gyro bias random walk
    estimate_imu_bias: bool = True  # add accel/gyro biases to the state (the paper's state has none)
    accel_bias_sigma0: float = 0.03  # m/s^2, prior sigma of the accelerometer bias
    gyro_bias_sigma0: float = 2.0e-3  # rad/s, prior sigma of the gyro bias
    # --- initial state uncertainty ---
    initial_position_sigma_m: float = 0.05  # m, per axis
    initial_velocity_sigma_mps: float = 0.1  # m/s, per axis
    initial_tilt_sigma_rad: float = 0.01  # rad, roll and pitch
    initial_yaw_sigma_rad: float = 0.02  # rad
    # the share of that yaw uncertainty the filter itself starts with; the rest is carried outside it, in the
    # covariance sent (``vis_thermal_ekf``: the map turned about the start, ``lba.gauge``). Yaw about gravity is
    # unobservable: a filter started with a 1 deg yaw sigma let the updates move its yaw; on the ten replayed
    # Europa flights the mean error went 1.04 / 1.05 / 1.19 -> 0.79 / 0.70 / 0.73 m (visible / thermal / dual)
    # with 0.01 deg inside (docs/benchmarks.md, session 48)
    filter_yaw_sigma_rad: float = 1.7453292519943296e-4
    # s, the daemon's start from the autopilot: its ATTITUDE samples this close to the first frame set averaged,
    # each carried there by the IMU's gyro (``vis_thermal_ekf.start_attitude``); 0 = the nearest sample alone
    initial_attitude_window_s: float = 1.0
    # s, a start from the autopilot's attitude with no ATTITUDE sample yet (the camera up before the autopilot
    # streams) waits this long after the first frame set for one; then it starts from the IMU's gravity and the
    # configured heading (``initial_yaw_rad``), which the cameras cannot correct
    start_wait_s: float = 10.0
    # --- visual measurements ---
    pixel_sigma_px: float = 1.0  # px, SIFT keypoint position noise (per axis): the visible camera's
    # and the thermal camera's (0 = ``pixel_sigma_px``); see ``pixel_sigma``
    pixel_sigma_thermal_px: float = 0.0
    # px, > 0: a SIFT match's sigma in the update follows its keypoint's size, the camera's sigma x size / this,
    # from 0.5x to 4x (``MATCH_SIGMA_FACTORS``): a keypoint found at a coarser level of the pyramid is located
    # less well (at ``detect_scale`` 0.5 the smallest SIFT keypoints measure ~3.6 px, the next octave's ~7.2 px).
    # The gate and a new landmark's ray keep the camera's sigma (the gate is drawn before a keypoint is
    # chosen). 0 = every match the camera's sigma (the paper's)
    pixel_sigma_size_ref_px: float = 0.0
    first_estimate_jacobians: bool = True  # FEJ on landmarks (Huang et al. 2008), see ``ekf.filter``
    one_point_ransac: bool = True  # refuse matches the others disagree with (Civera et al. 2010; ``ransac``)
    # px, a match supports a one-match hypothesis within this distance: about twice the median error of a
    # visible keypoint against the truth on the simulated Europa (0.28 px; thermal 0.13 px)
    ransac_threshold_px: float = 0.5
    ransac_min_matches: int = 5  # fewer gated matches than this: all are used, no RANSAC
    gate_chi2: float = 9.21  # Mahalanobis gate on the 2-D innovation (chi-square, 2 dof, 99 %)
    max_descriptor_distance: float = 250.0  # SIFT L2 distance (OpenCV descriptors, norm ~512)
    descriptor_ratio: float = 0.85  # Lowe ratio test between the best and second-best gated candidates
    # match every landmark against the descriptor it was created with (MonoSLAM keeps a feature's first
    # patch: Davison et al., T-PAMI 2007). False: against the last matched keypoint's, which lets a track
    # slide a little per frame onto a neighbour that looks alike. On the 300-run benchmark, paired against
    # False: E lower by 0.059 +- 0.017 / 0.020 +- 0.009 / 0.015 +- 0.010 points visible / thermal / dual,
    # mean position error by 0.086 / 0.024 / 0.027 m (docs/benchmarks.md)
    anchor_descriptor: bool = True
    # a landmark SIFT did not find inside its gate is searched for with its first patch (MonoSLAM's active
    # search: the patch cut around its keypoint when it was created, warped by the predicted motion, normalised
    # cross-correlation inside the same gate). SIFT finds a keypoint again in the next frame only so often: on
    # the simulated Europa 20 % (visible) / 14.5 % (thermal) of the in-view landmarks had no keypoint in the gate
    # cameras that do it ("visible", "thermal"); () = none
    patch_cameras: tuple[str, ...] = ()
    patch_half_px: int = 7  # template half size (15 x 15 px)
    patch_ref_half_px: int = 21  # half size of the stored reference patch (the template is warped from it)
    patch_max_radius_px: int = 24  # px, search radius cap (the gate decides below it)
    patch_min_score: float = 0.8  # normalised cross-correlation of an accepted position
    patch_min_margin: float = 0.05  # any other local maximum of the correlation must score this much lower
    max_consecutive_misses: int = 2  # frames a landmark may go unmatched inside the image before deletion
    image_margin_px: float = 8.0  # landmarks predicted closer than this to the border are deleted
    min_new_separation_px: float = 12.0  # new landmarks keep this distance from tracked ones
    # --- landmark initialisation (Civera inverse depth, eq. 5) ---
    init_rho_rel_sigma: float = 0.35  # sigma(rho)/rho of the altimeter-based depth prior (relief)
    init_rho_no_altimeter: float = 0.01  # 1/m, prior inverse depth before any altimeter reading
    init_rho_sigma_no_altimeter: float = 0.01  # 1/m, its sigma (covers 50 m .. infinity at 2 sigma)
    # --- altimeter (range along body down to the ground) ---
    altimeter_sigma_m: float = 0.1  # m, sensor noise
    altimeter_gate_chi2: float = 10.83  # Mahalanobis gate (chi-square, 1 dof, 99.9 %)
    # The range is compared with the plane through three landmarks around the beam (``altimeter``), which misses
    # the rough ground under the beam. That model error is not white: on the simulated Europa the innovation's
    # autocorrelation is 0.82-0.91 / 0.44-0.79 / 0.11-0.40 over 0.1 / 1 / 3 s, a facet lasts ~1.8 s, and the first
    # innovation after a facet change is ~1.1-1.4 % of the range rms (docs/benchmarks.md).
    # facet_error_state (ours, not in the paper): the error is a state c, drawn afresh for every new facet
    # (sigma ``facet_error_rel_sigma`` x range) and decaying with ``facet_error_tau_s`` (a first-order Gauss-Markov
    # process: the beam moves over the ground while the facet lasts; 0 = constant while it lasts, which we
    # measured overconfident); the white part is ``altimeter_sigma_m`` and ``altimeter_white_rel_sigma`` x range.
    facet_error_state: bool = True
    facet_error_rel_sigma: float = 0.02
    facet_error_tau_s: float = 2.0  # s
    altimeter_white_rel_sigma: float = 0.005
    # m, the altimeter's constant range bias (a range finder's offset), carried as a consider state (``filter``):
    # in the covariance and the gains, never estimated. A bias b scales the map by about b / height in every mode;
    # left out, the covariance sent is overconfident. 0 = not modelled
    altimeter_bias_sigma_m: float = 0.0
    # facet_error_state False: the model error is taken as white, this fraction of the range (with 0.02 the
    # filter was overconfident, position NEES 9.3 / 8.4 / 7.5 visible / thermal / dual; 0.10 gave 4.9 / 3.6 / 3.8
    # at about the same E; docs/benchmarks.md)
    facet_rel_sigma: float = 0.10
    # --- diversity sampling (eq. 8) ---
    kde_min_bandwidth_px: float = 16.0  # px, floor of the Scott's-rule kernel width (cap: ``sampling``)
    # dual: the density of eq. 8 over the whole map (paper 2: f of M_{Z,t}, the tracked landmarks of modality Z,
    # both cameras' for Z = dual), the other camera's landmarks projected into the sampling camera's image.
    # False: each camera's own landmarks only (two independent 32-landmark layouts)
    diversity_over_map: bool = True
    # --- SIFT (cv2.SIFT_create) ---
    # keypoints kept per image (best by contrast) and the contrast threshold, per camera. More keypoints per
    # image let a landmark's keypoint be found again in the next frame more often (longer tracks). On the
    # 300-trial benchmark, paired against 400 / 0.02 for both cameras (thermal's keypoints were contrast-limited,
    # ~300 a frame): E lower by 0.073 +- 0.016 / 0.036 +- 0.010 / 0.033 +- 0.010 points visible / thermal /
    # dual, SIFT 43 instead of 34 ms per pair (docs/benchmarks.md). The thermal camera was then at its 400 cap (3 of 4
    # frames sampled on trajectory 1): 800, paired over the 600 trials of seeds 0 and 1, lowered the mean
    # position error by 0.037 +- 0.012 / 0.050 +- 0.012 m thermal and 0.025 +- 0.009 / 0.019 +- 0.009 m dual
    # (E: thermal -0.012 / -0.015, dual -0.005 / -0.002 points), for 14.3-16.5 instead of 19.5-19.7 pairs/s
    # through the daemon path, measured in turn (docs/benchmarks.md)
    sift_nfeatures_visible: int = 800
    sift_nfeatures_thermal: int = 800
    sift_octave_layers: int = 3  # Lowe's value
    # lower than OpenCV's 0.04: icy scenes have little contrast, the diffused thermal image even less
    sift_contrast_threshold_visible: float = 0.02
    sift_contrast_threshold_thermal: float = 0.005
    sift_edge_threshold: float = 10.0  # OpenCV / Lowe default
    sift_sigma: float = 1.6  # OpenCV / Lowe default
    # detect on the image resized by this factor, pixels mapped back. 0.5: OpenCV's SIFT first doubles the
    # image (octave -1), so at 0.5 the pyramid starts at the camera's own resolution; ~2.6x faster than
    # 1.0 (measured 59 vs 155 ms CPU per 640x480 pair), and what brings the dual pair rate past 10/s
    detect_scale: float = 0.5
    thermal_low_percentile: float = 1.0  # uint16 thermal -> 8 bit: this percentile maps to 0
    thermal_high_percentile: float = 99.0  # ... and this one to 255 (per frame, robust to hot pixels)
    # --- time handling and health ---
    imu_max_lag_s: float = 0.25  # IMU samples are buffered this long so late frames find them
    # s, an IMU sample older than this no longer stands for the motion: beyond it (an IMU stream that stops, or has
    # not started) the filter propagates a constant velocity without rotation, with the motion-model noise below
    # in place of the IMU's (MonoSLAM's constant-velocity model, Davison et al. 2007). Holding the last sample
    # instead turned a wobbling lander's rate into degrees of tilt within a second, out of every landmark's gate
    imu_hold_max_s: float = 0.1
    no_imu_accel_noise_density: float = 0.5  # m/s^2/sqrt(Hz): velocity sigma 0.5 m/s after a second without
    no_imu_gyro_noise_density: float = 0.05  # rad/sqrt(s): attitude sigma 0.05 rad (2.9 deg) after a second
    lost_after_frames: int = 5  # consecutive frames with no visual match before the status is LOST
    lost_position_sigma_m: float = 50.0  # m, largest position sigma still reported OK
    seed: int = 0  # landmark sampling RNG

    def pixel_sigma(self, camera: str) -> float:
        """A camera's keypoint position noise, px per axis ("visible" or "thermal")."""
        if camera == "thermal" and self.pixel_sigma_thermal_px > 0:
            return self.pixel_sigma_thermal_px
        return self.pixel_sigma_px

    def match_sigma(self, camera: str, size_px: float | None) -> float:
        """Pixel sigma of one of a camera's matches from its keypoint's size (full-resolution px; None:
        unknown, the camera's sigma), see ``pixel_sigma_size_ref_px``."""
        sigma = self.pixel_sigma(camera)
        if self.pixel_sigma_size_ref_px <= 0 or size_px is None:
            return sigma
        lo, hi = MATCH_SIGMA_FACTORS
        return sigma * min(max(size_px / self.pixel_sigma_size_ref_px, lo), hi)

    def sift_settings(self, camera: str) -> tuple[int, float]:
        """(nfeatures, contrast threshold) of a camera ("visible" or "thermal")."""
        if camera == "visible":
            return self.sift_nfeatures_visible, self.sift_contrast_threshold_visible
        if camera == "thermal":
            return self.sift_nfeatures_thermal, self.sift_contrast_threshold_thermal
        raise ValueError(f"camera must be 'visible' or 'thermal', got {camera!r}")

    def __post_init__(self) -> None:
        cameras_for_mode(self.mode)
        if self.sampling not in SAMPLING_METHODS:
            raise ValueError(f"sampling must be one of {SAMPLING_METHODS}, got {self.sampling!r}")
        bad = [c for c in self.patch_cameras if c not in ("visible", "thermal")]
        if bad:
            raise ValueError(f"patch_cameras may hold 'visible' and 'thermal', got {bad}")
        if (
            self.facet_error_rel_sigma <= 0
            or self.facet_error_tau_s < 0
            or self.altimeter_white_rel_sigma < 0
            or self.altimeter_bias_sigma_m < 0
        ):
            raise ValueError(
                "facet_error_rel_sigma must be > 0; facet_error_tau_s, altimeter_white_rel_sigma and "
                "altimeter_bias_sigma_m >= 0"
            )
        if self.max_landmarks_per_camera < 1:
            raise ValueError("max_landmarks_per_camera must be >= 1")
        if self.start_wait_s < 0:
            raise ValueError("start_wait_s must be >= 0")
        if self.pixel_sigma_size_ref_px < 0:
            raise ValueError("pixel_sigma_size_ref_px must be >= 0 (0: every match the camera's sigma)")
