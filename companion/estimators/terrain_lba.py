"""The ``terrain_lba`` estimator: paper 1's terrain-aided SLAM (section 4).

Per frame (the fast path): Lucas-Kanade tracking and PnP against the map (``companion.vo``), so every
frame's pose is the VO pose on the map as last corrected by the adjustment. Per key frame (off the
per-frame path): geo-referencing against the DEM, eq. 21 alignment, and the GTSAM local bundle adjustment
with the geo term of eq. 23 weighted by w_G (``companion.lba``); its result is written back into the map.
The covariance sent with each estimate is the newest key frame's marginal from the adjustment, grown with
the distance flown since.

The back-end runs in a worker process (GTSAM's solver holds the GIL, so a thread would stall the frames),
and its result is applied either as soon as it arrives (``backend_apply="when_ready"``, the daemon's
default) or exactly ``backend_delay_frames`` frames after its key frame (``"fixed_delay"``: waits if it is
late, so the output is the same for the same input, run after run). ``synchronous_backend=True`` runs the
back-end inline at the key frame and applies it with the same fixed delay (same results as "fixed_delay").

The autopilot's attitude gives the initial rotation and the gravity prior of the adjustment; the altimeter
gives the monocular scale at initialisation and the height above ground of each geo-fix (eq. 18).

The worker is supervised: if it dies (killed by the OOM killer, a crash inside a native library) or stops
answering (no result ``backend_reply_timeout_s`` after the job, or after it is due with "fixed_delay"), it is counted
(``backend_restarts``), a new one is started without blocking the frames, and the estimates go on from the
VO alone meanwhile (their covariance grows with the distance flown); the new back-end aligns itself to the
map again from the next geo-fixes.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
import threading
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from scipy.stats import trim_mean
from threadpoolctl import threadpool_limits

from companion.estimators.history import SampleHistory
from companion.geometry import CameraIntrinsics, rot_from_rpy, rpy_from_rot
from companion.georef.dem import Dem
from companion.georef.georef import GeoReferencer, GeorefOptions
from companion.georef.shading import Sun
from companion.lba.backend import Backend, BackendJob, BackendOptions, BackendResult
from companion.lba.gauge import gauge_covariance
from companion.lba.window import LbaOptions, body_covariance
from companion.types import (
    AltimeterSample,
    AttitudeSample,
    EstimateStatus,
    Frame,
    ImuSample,
    LocalPositionSample,
    PoseEstimate,
)
from companion.vo.odometry import VisualOdometry, VoOptions, tilt_toward

log = logging.getLogger(__name__)

RESTART_BACKOFF_S = 5.0  # a replacement worker that failed to start is retried after this
# key-frame geo-fixes kept in ``geo_fixes``: >= 44 min of flight (key frames >= 20 frames apart, 15 Hz)
GEO_FIX_LOG_LEN = 2000


@dataclass(frozen=True)
class GeoFixRecord:
    """One key frame's geo-fix as the back-end used it. stamp_us: the key frame's stamp. status: the
    back-end's outcome ("accepted", "rejected", "pending", "aligned", ...). p_fix_world: (3,) body position
    by the fix (NED, eq. 18 at the key frame's VO attitude). ground_fix_world: (3,) the ground point the
    fix locates on the optical axis at the altimeter's range (what the adjustment holds; NaN without a
    range). fix_sigma_m: the horizontal sigma the adjustment gave fixes after this key frame (learnt from
    their scatter, ``BackendOptions.geo_sigma_adapt``; NaN when not reported). unfollowed_world: (3,) the
    fix's point minus where the adjustment put it (the part of the fix the adjusted key frame did not
    follow; NaN when the key frame was not the window's newest or the fix was not used)."""

    stamp_us: int
    status: str
    quality: float
    p_fix_world: np.ndarray
    ground_fix_world: np.ndarray
    fix_sigma_m: float = float("nan")
    unfollowed_world: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))

    @staticmethod
    def of(stamp_us: int, geo: dict) -> GeoFixRecord:
        return GeoFixRecord(
            int(stamp_us),
            str(geo.get("status", "")),
            float(geo.get("quality", float("nan"))),
            np.asarray(geo["p_fix_world"], float),
            np.asarray(geo.get("ground_fix_world", [np.nan] * 3), float),
            float(geo.get("fix_sigma_m", float("nan"))),
            np.asarray(geo.get("post_residual_m", [np.nan] * 3), float),
        )


class FixDrought:
    """Tells the pilot when the terrain stops giving fixes, and when it gives them again.

    ``update`` takes each key frame's back-end outcome ("accepted", "failed:low_quality", "rejected", ...)
    and returns a line for the log, or None: one when ``threshold`` key frames in a row had no fix the
    adjustment used (failed, refused by the gate, or still waiting for fixes that agree on the first
    alignment: a compass far off gives fixes that never do), naming why, and one when a fix is used again
    after such a run. "none" (no geo-referencing asked) is not counted either way."""

    USABLE = ("accepted", "aligned", "aligned_yaw", "realigned")
    REASONS = {"pending": "not yet aligned", "rejected": "refused by the gate"}

    def __init__(self, threshold: int) -> None:
        self.threshold = max(int(threshold), 1)
        self.run = 0
        self.why: dict[str, int] = {}

    def update(self, status: str) -> str | None:
        if status in ("", "none"):
            return None
        if status in self.USABLE:
            n, self.run, self.why = self.run, 0, {}
            if n >= self.threshold:
                return f"terrain fixes again, after {n} key frames without"
            return None
        self.run += 1
        reason = self.REASONS.get(status, status.removeprefix("failed:"))
        self.why[reason] = self.why.get(reason, 0) + 1
        if self.run == self.threshold:
            why = ", ".join(f"{k} {v}" for k, v in sorted(self.why.items(), key=lambda kv: -kv[1]))
            return (
                f"no terrain fix used in the last {self.run} key frames ({why}): position from the visual "
                "odometry alone, its sigma growing with the distance flown"
            )
        return None


@dataclass(frozen=True)
class TerrainLbaOptions:
    window_size: int = 15  # key frames in the sliding window of the adjustment (paper: 15)
    w_geo: float = 10.0  # eq. 23 confidence w_G of the geo-referencing term (Table 4: 10); 0 = VO only
    # landmark-on-DEM term of the adjustment (``LbaOptions.terrain_sigma_m``): the DEM's vertical and
    # horizontal error (m); 0 = off. Only once the map is aligned to the world (position and yaw).
    terrain_sigma_m: float = 0.5
    terrain_sigma_horizontal_m: float = 0.5
    # the autopilot's roll/pitch noise per sample (rad, 1 sigma, frame to frame): the gravity prior's source
    attitude_sigma_rad: float = 0.003
    # the gravity prior's roll / pitch from the autopilot attitude of this many recent frames, carried to the
    # key frame through the VO's rotation since (``VoOptions.gravity_frames``): averages the attitude's
    # frame-to-frame noise, not its bias; 1 = the key frame's own sample. Paired Table 7 flights: docs/benchmarks.md
    gravity_frames: int = 20
    # what of that average's error does not shrink with more frames (rad, 1 sigma): the autopilot's slow
    # error and the VO's rotation error over the averaged frames. The adjustment's prior (and the output
    # blend below) weighs the average by ``gravity_sigma_rad`` = sqrt(attitude^2 / gravity_frames + floor^2)
    attitude_floor_sigma_rad: float = 0.001
    # each frame's output roll/pitch: the VO's tilt (1 sigma against true gravity; measured 0.8 mrad per axis
    # on scenes 01 and 07 after the adjustment) fused with the same attitude average, the camera turned
    # about the ground point it sees (``tilt_toward``); the VO and its map keep their own. 0 = the VO's alone
    vo_tilt_sigma_rad: float = 0.001
    min_frames_between_kf: int = 20  # key-frame criterion 1 (paper / ORB-SLAM)
    min_features_kf: int = 50  # key-frame criterion 2
    max_tracked_ratio_kf: float = 0.9  # key-frame criterion 3
    max_anchors: int = 10  # older key frames seeing the window's points, held by their marginal prior
    backend_apply: str = "when_ready"  # "when_ready" (lowest latency) or "fixed_delay" (deterministic)
    backend_delay_frames: int = 10  # "fixed_delay" / synchronous: frames between a key frame and its result
    backend_start_timeout_s: float = 120.0  # the worker must be up within this (imports gtsam, builds maps)
    backend_reply_timeout_s: float = 30.0  # no result this long after the job (fixed delay: after due) = hung
    attitude_max_age_us: int = 100_000  # attitude further than this from a frame's stamp is not used
    altimeter_max_age_us: int = 200_000
    initial_sigma_m: float = 1.0  # 1-sigma of the initial position (covariance before any adjustment)
    initial_sigma_rad: float = float(np.radians(1.0))
    # 1-sigma of the compass heading the map starts from: until the terrain gives the heading, the estimate's
    # covariance carries it out along the lever from the start (``companion.lba.gauge``); no compass: pi
    compass_sigma_rad: float = float(np.radians(2.0))
    drift_sigma_per_m: float = 0.02  # position covariance growth per metre flown since the adjusted key frame
    drift_rad_per_m: float = 1e-4  # attitude covariance growth per metre
    fix_drought_keyframes: int = 10  # key frames in a row without a usable fix before the log says so (~13 s)
    vo: VoOptions = field(default_factory=VoOptions)
    backend: BackendOptions = field(default_factory=BackendOptions)
    georef: GeorefOptions = field(
        default_factory=lambda: replace(
            GeorefOptions(), min_quality=0.1, joint_shift=True, rs_sweep_deg=30.0, relief_scales_m=(20.0, 5.0)
        )
    )
    # the back-end gates every fix against the VO prediction (and the adjustment's loss is robust), so the
    # matcher's own quality floor, calibrated for a standalone estimator, is relaxed: measured on scenes 07
    # and 08 (190 s circular): 0.25 -> 0.1 took the mean APE from 1.01 to 0.46 m and 0.47 to 0.40 m.
    # joint_shift (GeorefOptions): a key frame's fix with the shift estimated jointly with the fitted
    # reference; the adjustment averages fixes over its window, so a smaller bias is worth more noise:
    # ``bench terrain_slam`` Table 7 mean APE 0.524 -> 0.454 m (better in 8 of 9 scenes, 05 1.35 -> 0.92 m).
    # relief_scales_m: a second local-relief basis (5 m beside 20 m) for reflectance tied to the relief at a
    # smaller scale than the first models (dust in small hollows): such a term left unexplained pulls the
    # joint shift along the sun (``test_joint_shift_needs_the_relief_at_the_reflectance_scale``); paired
    # scratch flights with and without it: docs/benchmarks.md, terrain SLAM.
    # rs_sweep_deg: the start-up heading search (``BackendOptions.heading_from_matcher``) tries headings
    # within this of the compass's (measured, scene 01, compass 10 deg off: without the sweep the search
    # stays near the compass and the flight never aligns)

    @property
    def gravity_sigma_rad(self) -> float:
        """1 sigma of a key frame's (or a frame's) attitude average: its noise over the frames plus the floor."""
        return float(
            np.hypot(
                self.attitude_sigma_rad / np.sqrt(max(self.gravity_frames, 1)), self.attitude_floor_sigma_rad
            )
        )

    def resolved(self) -> TerrainLbaOptions:
        """Copy with the top-level fields pushed into the nested options they control."""
        kf = replace(
            self.vo.keyframes,
            min_frames_between=self.min_frames_between_kf,
            min_features=self.min_features_kf,
            max_tracked_ratio=self.max_tracked_ratio_kf,
        )
        lba: LbaOptions = replace(
            self.backend.lba,
            w_geo=self.w_geo,
            terrain_sigma_m=self.terrain_sigma_m,
            terrain_sigma_horizontal_m=self.terrain_sigma_horizontal_m,
            gravity_sigma_rad=self.gravity_sigma_rad,
        )
        return replace(
            self,
            vo=replace(
                self.vo,
                keyframes=kf,
                gravity_frames=self.gravity_frames,
                # the map's first two views: the relative rotation of two attitude samples, sqrt(2) x the
                # roll/pitch noise, with room for the yaw's jitter (larger than roll/pitch's in an AHRS)
                two_view=replace(self.vo.two_view, rotation_prior_sigma_rad=2.0 * self.attitude_sigma_rad),
            ),
            backend=replace(
                self.backend,
                lba=lba,
                drift_sigma_per_m=self.drift_sigma_per_m,
                heading_prior_sigma_rad=self.compass_sigma_rad,
            ),
        )


def _make_backend(options: BackendOptions, geo_args: tuple | None) -> Backend:
    locate = None
    terrain = None
    if geo_args is not None and options.lba.w_geo > 0:
        dem, sun, intrinsics, R_body_cam, georef_options = geo_args
        geo = GeoReferencer(dem, sun, intrinsics, R_body_cam, georef_options)

        def locate(image, R_world_body, p_pred_world, alt_agl_m, solve_rotation_scale):  # noqa: ANN001, ANN202
            return geo.locate(image, R_world_body, p_pred_world, alt_agl_m, solve_rotation_scale)

        # the landmark-on-DEM term reads the matcher's smoothed, hole-filled DEM (its noise would be
        # slopes), holes put back
        h = geo.ref.height_m.copy()
        h[geo.ref.holes > 0] = np.nan
        terrain = Dem(h, dem.north0_m, dem.east0_m, dem.cell_m)

    return Backend(options, locate, terrain)


def _worker_main(conn: Any, options: BackendOptions, geo_args: tuple | None, opencv_threads: int) -> None:
    """Worker process: build the back-end, then answer jobs until None. ``opencv_threads``: the parent's
    OpenCV thread count (``daemon.opencv_threads``), which a spawned interpreter does not inherit."""
    cv2.setNumThreads(opencv_threads)
    # One BLAS thread for the whole worker: OpenBLAS's extra thread spin-waits after each call and, on a
    # two-core companion, takes the core the per-frame path runs on. Measured (60-s timing flight, scene 08):
    # per-frame p99 38.4 -> 29.9 ms, Lucas-Kanade p99 24.4 -> 14.6 ms (docs/benchmarks.md, terrain SLAM).
    threadpool_limits(limits=1, user_api="blas")
    backend = _make_backend(options, geo_args)
    conn.send("ready")
    while True:
        try:
            job = conn.recv()
        except EOFError:
            return
        if job is None:
            return
        try:
            conn.send(backend.process(job))
        except Exception as e:  # noqa: BLE001 - reported to the front-end, counted, never fatal
            conn.send(f"{type(e).__name__}: {e}")


class TerrainLbaEstimator:
    """Implements ``companion.types.Estimator`` for one nadir camera."""

    cameras: tuple[str, ...] = ("nadir",)

    def __init__(
        self,
        options: TerrainLbaOptions,
        intrinsics: CameraIntrinsics,
        R_body_cam: np.ndarray,
        dem: Dem,
        sun: Sun,
        initial_p_world: np.ndarray,
        initial_yaw_rad: float = 0.0,
        synchronous_backend: bool = False,
    ) -> None:
        if options.backend_apply not in ("when_ready", "fixed_delay"):
            raise ValueError(
                f"backend_apply must be 'when_ready' or 'fixed_delay', got {options.backend_apply!r}"
            )
        self.opt = options.resolved()
        self.intr = intrinsics
        self.K = intrinsics.K
        self.R_body_cam = np.asarray(R_body_cam, float)
        self.p_body_in_cam = np.zeros(3)  # the camera sits at the body origin (no lever arm configured)
        self.vo = VisualOdometry(self.opt.vo, self.K)
        # each frame's tilt fusion: inverse-variance weight of the attitude average (``_output_tilt``)
        s_vo2 = self.opt.vo_tilt_sigma_rad**2
        self._tilt_weight = s_vo2 / (s_vo2 + self.opt.gravity_sigma_rad**2) if s_vo2 > 0 else 0.0
        self._dem = dem.filled()
        self.initial_p_world = np.asarray(initial_p_world, float)
        self.initial_yaw_rad = float(initial_yaw_rad)
        self.synchronous = synchronous_backend
        self.fixed_delay = synchronous_backend or self.opt.backend_apply == "fixed_delay"
        geo_args = (dem, sun, intrinsics, self.R_body_cam, self.opt.georef) if self.opt.w_geo > 0 else None
        self._backend: Backend | None = None
        self._proc: Any = None
        self._conn: Any = None
        self._geo_args = geo_args
        self._worker_ready = False
        self._worker_started = 0.0
        self._dead_totals: dict[str, int] = {}  # back-end counters of the workers that were replaced
        self._starter: threading.Thread | None = None  # starts a replacement worker off the frames
        self._in_flight_since = 0.0
        self._sender: threading.Thread | None = None  # sends the job in flight
        self._send_error: str | None = None
        self._closing = threading.Event()
        if synchronous_backend:
            self._backend = _make_backend(self.opt.backend, geo_args)
        else:
            self._start_worker()
            self._wait_ready()
        self._attitude = SampleHistory()
        self._range = SampleHistory()
        # altimeter samples not yet matched to a frame
        self._alt_pending: deque[tuple[int, float]] = deque(maxlen=200)
        # the altimeter samples since the previous key frame, each with the body pose it was taken at:
        # (p_body (3,) NED, the body's down axis in the world (3,), range m); moved with the map by each
        # correction
        self._alt_samples: list[tuple[np.ndarray, np.ndarray, float]] = []
        self.frame_index = -1
        self.epoch = 0
        self.reset_counter = 0
        self._last_p_body: np.ndarray | None = None
        self._dist_m = 0.0
        self._kf_dist: dict[int, float] = {}
        self._kf_frame: dict[int, dict] = {}  # key frame id -> what its back-end job needs
        self._wanted: int | None = None  # newest key frame waiting for the back-end
        self._in_flight: tuple[int, int, int] | None = None  # (kf id, epoch, due frame)
        self._sync_result: BackendResult | str | None = None
        self._cov_kf: tuple[int, np.ndarray] | None = None  # (kf id, body covariance) of the last result
        # where the map sits in the world until the fixes place it (``companion.lba.gauge``): its start and
        # that start's 1-sigma; then the centre of the fixes that placed it. Once placed (or turned by the
        # terrain), so until a re-initialisation: a replacement worker places the same map again.
        self._gauge_pivot = self.initial_p_world.copy()
        self._gauge_sigma_m = self.opt.initial_sigma_m
        self._located = False
        self._yaw_known = False
        self._fix_pivot = np.full(3, np.nan)
        self._last_cov: np.ndarray | None = None
        self.last_result: BackendResult | None = None
        self._drought = FixDrought(self.opt.fix_drought_keyframes)
        # the key frames' geo-fixes as the back-end reported them (the newest GEO_FIX_LOG_LEN), for replays
        self.geo_fixes: deque[GeoFixRecord] = deque(maxlen=GEO_FIX_LOG_LEN)
        # front-end totals; ``counters`` adds the back-end's (see there)
        self._fe = {
            "frames": 0,
            "lost": 0,
            "reinit": 0,
            "no_attitude": 0,
            "keyframes": 0,  # made by the VO (a key frame made while the back-end is busy is not sent)
            "backend_jobs": 0,  # key frames sent to the back-end
            "backend_applied": 0,  # results written back into the map
            "backend_stale": 0,  # results for a map that was reset meanwhile (dropped)
            "backend_errors": 0,
            "backend_restarts": 0,  # worker processes found dead or hung and replaced
        }

    # -- inputs from the autopilot ------------------------------------------------------------------
    def on_attitude(self, s: AttitudeSample) -> None:
        self._attitude.add(s.stamp_us, (s.roll_rad, s.pitch_rad, s.yaw_rad))

    def on_imu(self, s: ImuSample) -> None:
        """Not used: attitude comes from ATTITUDE, motion from the images."""

    def on_local_position(self, s: LocalPositionSample) -> None:
        """Not used: the configured start and the terrain fixes give the position."""

    def on_altimeter(self, s: AltimeterSample) -> None:
        if np.isfinite(s.range_m) and s.range_m > 0:
            self._range.add(s.stamp_us, float(s.range_m))
            self._alt_pending.append((s.stamp_us, float(s.range_m)))

    def _gather_altimeter(self, t_us: int, p_body: np.ndarray, R_world_body: np.ndarray) -> None:
        """Keep the altimeter samples up to this frame, each with this frame's body pose, for the next key
        frame's height above ground (``_key_frame_agl``)."""
        lo = t_us - self.opt.altimeter_max_age_us
        while self._alt_pending and self._alt_pending[0][0] <= t_us:
            stamp, rng = self._alt_pending.popleft()
            if stamp >= lo:
                self._alt_samples.append((p_body.copy(), R_world_body[:, 2].copy(), rng))

    def _move_alt_samples(self, C: np.ndarray) -> None:
        """An adjustment moved the map (and the current pose) by the world-frame correction ``C`` (4, 4):
        the samples' poses, taken after the key frame it refers to, follow it as the map's frames do."""
        R_c, t_c = C[:3, :3], C[:3, 3]
        self._alt_samples = [(R_c @ p + t_c, R_c @ d, rng) for p, d, rng in self._alt_samples]

    def _key_frame_agl(self, p_body: np.ndarray) -> float | None:
        """Height above the ground below ``p_body`` (a key frame's VO position) from the altimeter samples
        since the previous key frame.

        Each sample gives an offset between the altitude it measures (DEM below + height above it) and the
        VO's altitude at its frame. One sample is noisy (a 1 % range finder: 1 m at 100 m) but the VO's
        altitude is smooth over a key frame interval, so the key frame takes the trimmed mean offset of the
        ~20 samples since the previous key frame (a DEM hole or a stray echo does not pull it): its height
        error shrinks about sqrt(20) times. The samples survive the adjustments applied in between, moved
        with the map (dropping them there left about half of them)."""
        if not self._alt_samples:
            return None
        p = np.stack([s[0] for s in self._alt_samples])
        down = np.stack([s[1] for s in self._alt_samples])
        rng = np.array([s[2] for s in self._alt_samples])
        altitude = self._dem.height_at(p[:, 0], p[:, 1]) + self._dem.heights_above_ground(p, down, rng)
        offsets = altitude + p[:, 2]  # altitude minus the VO's (-z)
        offsets = offsets[np.isfinite(offsets)]  # no DEM below: no altitude
        if not offsets.size:
            return None
        offset = float(trim_mean(offsets, 0.1))
        ground = float(self._dem.height_at(p_body[0], p_body[1])[0])
        return None if not np.isfinite(ground) else -float(p_body[2]) + offset - ground

    def close(self) -> None:
        self._closing.set()
        if self._starter is not None:
            self._starter.join(timeout=10.0)
            self._starter = None
        if self._sender is not None:
            self._sender.join(timeout=5.0)
        if self._proc is not None:
            if self._sender is None or not self._sender.is_alive():  # one writer on the pipe at a time
                with contextlib.suppress(OSError, ValueError):  # the pipe may be gone: the worker then exits
                    self._conn.send(None)
            self._proc.join(timeout=5.0)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(timeout=5.0)
            if self._proc.is_alive():  # a stopped process does not act on SIGTERM
                self._proc.kill()
                self._proc.join(timeout=5.0)
            self._proc = None

    # -- the worker process -------------------------------------------------------------------------
    def _start_worker(self) -> None:
        """Start a worker process; it says "ready" once it has built its back-end. Sets ``_proc`` and
        ``_conn`` last (a restart runs this in a thread: the frames look at them only after it ended)."""
        ctx = mp.get_context("spawn")
        conn, child = ctx.Pipe()
        proc = ctx.Process(
            target=_worker_main,
            args=(child, self.opt.backend, self._geo_args, cv2.getNumThreads()),
            daemon=True,
            name="terrain_lba",
        )
        proc.start()  # blocks until the new interpreter has read its arguments (the DEM): ~1 s
        child.close()
        self._worker_ready = False
        self._worker_started = time.monotonic()
        self._conn, self._proc = conn, proc

    def _wait_ready(self) -> None:
        """Block until the worker is ready (start-up): fails at once if it dies, or after the timeout."""
        deadline = self._worker_started + self.opt.backend_start_timeout_s
        while not self._poll_ready():
            if not self._proc.is_alive():
                code = self._proc.exitcode
                self.close()
                raise RuntimeError(f"terrain_lba back-end worker exited during start-up (exit code {code})")
            if time.monotonic() > deadline:
                self.close()
                raise RuntimeError(
                    f"terrain_lba back-end worker not ready after {self.opt.backend_start_timeout_s:g} s"
                )
            time.sleep(0.05)

    def _poll_ready(self) -> bool:
        """Non-blocking: has the worker said "ready"? (A worker that died before is handled by the caller.)"""
        if self._worker_ready:
            return True
        try:
            if self._conn.poll() and self._conn.recv() == "ready":
                self._worker_ready = True
        except (EOFError, OSError):
            return False
        return self._worker_ready

    def _replace_worker(self, why: str, delay_s: float = 0.0) -> None:
        """The worker died or hung: count it, drop its job, start another one after ``delay_s`` (a worker
        that cannot start is not retried at the frame rate), not waiting for it."""
        self._fe["backend_restarts"] += 1
        log.warning("terrain_lba back-end worker %s: restarting it (VO only until it is back)", why)
        self._dead_totals = self.backend_counters()  # a new dict: the status thread may be reading the old
        self.last_result = None
        self._in_flight = None
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        self._worker_ready = False
        if proc is not None:
            if proc.is_alive():
                proc.kill()
            proc.join(timeout=1.0)
        if self._sender is not None:  # a send blocked on the dead worker fails now (broken pipe)
            self._sender.join(timeout=1.0)
            self._sender = None
        self._send_error = None
        if conn is not None:  # only now: closing it under a blocked send would pull the handle from under it
            with contextlib.suppress(OSError, ValueError):
                conn.close()

        # starting a process blocks its caller for about a second (see _start_worker): not on the frames
        def start() -> None:
            if not self._closing.wait(delay_s):
                self._start_worker()

        self._starter = threading.Thread(target=start, name="terrain_lba-restart", daemon=True)
        self._starter.start()

    def _check_restarting_worker(self) -> bool:
        """While a replacement worker starts: True once it is ready; a replacement that could not be
        started, dies or misses the start-up timeout is replaced again."""
        if self._starter is not None:
            if self._starter.is_alive():
                return False
            self._starter = None
            if self._proc is None:  # the start itself failed (its thread logged why): try again
                self._replace_worker("could not be started", RESTART_BACKOFF_S)
                return False
        if self._poll_ready():
            return True
        if not self._proc.is_alive():
            code = self._proc.exitcode
            self._replace_worker(f"exited during start-up (exit code {code})", RESTART_BACKOFF_S)
        elif time.monotonic() - self._worker_started > self.opt.backend_start_timeout_s:
            self._replace_worker(f"not ready after {self.opt.backend_start_timeout_s:g} s")
        return False

    # -- back-end -----------------------------------------------------------------------------------
    def _submit(self) -> None:
        if self._wanted is None or self._in_flight is not None or self.vo.state != "tracking":
            return
        if self._backend is None and not self._check_restarting_worker():
            return  # a replacement worker is starting: the key frame waits (a newer one replaces it)
        k = self._wanted
        self._wanted = None
        if k not in self.vo.kfs:
            return
        snap = self.vo.snapshot(self.opt.window_size, self.opt.max_anchors)
        if len(snap.kf_ids) < 2 or int(snap.kf_ids[-1]) != k:
            return
        extra = self._kf_frame.pop(k)
        T = self.vo.kfs[k].T_world_cam
        R_wb = T[:3, :3] @ self.R_body_cam.T
        prev = [kk for kk in self._kf_dist if kk < k]
        d_prev = self._kf_dist[k] - self._kf_dist[max(prev)] if prev else 0.0
        rng = extra["range_m"]
        job = BackendJob(
            snapshot=snap,
            newest_kf=k,
            image=extra["image"] if self.opt.w_geo > 0 else None,
            R_world_body=R_wb,
            p_body_in_world=T[:3, :3] @ self.p_body_in_cam + T[:3, 3],
            alt_agl_m=extra["agl_m"]
            if extra["agl_m"] is not None
            else (None if rng is None else self._dem.height_above_ground(T[:3, 3], R_wb, float(rng))),
            range_m=None if rng is None else float(rng),
            dist_since_prev_kf_m=d_prev,
            p_body_in_cam=self.p_body_in_cam,
            K=self.K,
            epoch=self.epoch,
        )
        self._fe["backend_jobs"] += 1
        self._in_flight = (k, self.epoch, self.frame_index + self.opt.backend_delay_frames)
        self._in_flight_since = time.monotonic()
        if self._backend is not None:
            self._sync_result = self._backend.process(job)
        else:
            # sent from a thread: the job (the key frame's image, the window) is larger than a pipe's buffer,
            # so a send waits for the worker to read it, and forever if the worker hangs
            self._send_error = None
            self._sender = threading.Thread(
                target=self._send_job, args=(self._conn, job), name="terrain_lba-send", daemon=True
            )
            self._sender.start()

    def _send_job(self, conn: Any, job: BackendJob) -> None:
        try:
            conn.send(job)
        except Exception as e:  # noqa: BLE001 - BrokenPipeError (the worker is gone) or any: reported, replaced
            self._send_error = f"{type(e).__name__}: {e}"

    def _collect(self) -> None:
        """Apply the in-flight result if it is due (fixed delay: wait for it) or ready (when_ready)."""
        if self._in_flight is None:
            return
        k, epoch, due = self._in_flight
        if self._backend is not None:
            if self.frame_index < due:
                return
            res = self._sync_result
            self._sync_result = None
        else:
            if self._send_error is not None:
                self._replace_worker(f"lost ({self._send_error})")
                return
            if self.fixed_delay and self.frame_index < due:
                return
            try:
                # fixed delay: wait for the result (deterministic output); when ready: only if it is there
                wait_s = self.opt.backend_reply_timeout_s if self.fixed_delay else 0.0
                if not self._conn.poll(wait_s):
                    late = time.monotonic() - self._in_flight_since > self.opt.backend_reply_timeout_s
                    if not self._proc.is_alive():
                        self._replace_worker("died")
                    elif self.fixed_delay or late:
                        self._replace_worker(f"did not answer in {self.opt.backend_reply_timeout_s:g} s")
                    return
                res = self._conn.recv()
            except (EOFError, OSError) as e:  # the pipe closed: the worker died
                code = self._proc.exitcode
                self._replace_worker(f"died (exit code {code}, {type(e).__name__})")
                return
        self._in_flight = None
        if isinstance(res, str) or res is None:
            self._fe["backend_errors"] += 1
            return
        if res.epoch != self.epoch or self.vo.state != "tracking":
            self._fe["backend_stale"] += 1
            return  # the map it refers to was reset
        self._fe["backend_applied"] += 1
        C = self.vo.apply_correction(
            res.newest_kf,
            res.T_align,
            res.kf_ids,
            res.T_world_cam,
            res.lm_ids,
            res.p_world,
            res.outlier_kf,
            res.outlier_lm,
        )
        self._move_alt_samples(C)
        self.last_result = res
        self._log_alignment(res.geo)
        note = self._drought.update(str(res.geo.get("status", "")))
        if note is not None:
            (log.warning if note.startswith("no terrain fix") else log.info)("%s", note)
        if res.located and np.all(np.isfinite(res.pivot_world)):
            self._located = True
            self._fix_pivot = np.asarray(res.pivot_world, float)
        self._yaw_known = self._yaw_known or res.yaw_known
        kf = self.vo.kfs.get(res.newest_kf)
        if "p_fix_world" in res.geo and kf is not None:
            self.geo_fixes.append(GeoFixRecord.of(kf.stamp_us, res.geo))
        if np.all(np.isfinite(res.cov_newest)) and kf is not None:
            T = kf.T_world_cam
            self._cov_kf = (
                res.newest_kf,
                body_covariance(T, res.cov_newest, self.R_body_cam, self.p_body_in_cam),
            )

    # -- frames -------------------------------------------------------------------------------------
    def _covariance(self, p_body: np.ndarray) -> np.ndarray:
        """The adjustment's marginal of the newest key frame, grown by the distance flown since, plus the
        map's own place in the world while the fixes have not given it (``companion.lba.gauge``)."""
        o = self.opt
        if self._cov_kf is not None and self._cov_kf[0] in self._kf_dist:
            base = self._cov_kf[1]
            d = self._dist_m - self._kf_dist[self._cov_kf[0]]
        else:
            base = np.diag([o.initial_sigma_m**2] * 3 + [o.initial_sigma_rad**2] * 3)
            if not self._located:
                base[:2, :2] = base[5, 5] = 0.0  # the start's horizontal error and heading: the gauge's
            d = self._dist_m
        grow = np.diag([(o.drift_sigma_per_m * d) ** 2] * 3 + [(o.drift_rad_per_m * d) ** 2] * 3)
        cov = base + grow
        if not self._located:
            # held at the start: its error, and the compass's carried out from it (a turn by the terrain
            # before the fixes place the map keeps what was flown on the old heading: the lever stays)
            cov = cov + gauge_covariance(
                p_body, self._gauge_pivot, self._gauge_sigma_m, o.compass_sigma_rad, self._yaw_known
            )
        elif not self._yaw_known:
            cov = cov + gauge_covariance(p_body, self._fix_pivot, 0.0, o.compass_sigma_rad)
        self._last_cov = cov
        return cov

    def _reinit(self) -> None:
        self.vo.reset()
        self.epoch += 1
        self.reset_counter += 1
        self._fe["reinit"] += 1
        self._wanted = None
        self._kf_frame.clear()
        self._cov_kf = None
        self._alt_samples = []
        # the new map starts here on the compass heading again, as well known as the last estimate was
        if self._last_p_body is not None:
            self._gauge_pivot = self._last_p_body.copy()
            if self._last_cov is not None:
                self._gauge_sigma_m = float(np.sqrt(np.linalg.eigvalsh(self._last_cov[:2, :2])[-1]))
        self._located = self._yaw_known = False

    def on_frames(self, frames: dict[str, Frame]) -> PoseEstimate | None:
        frame = frames.get("nadir")
        if frame is None:
            return None
        self.frame_index += 1
        self._fe["frames"] += 1
        t = frame.stamp_us
        self._collect()
        rpy_att = self._attitude.nearest(t, self.opt.attitude_max_age_us)
        R_wb_att = None if rpy_att is None else rot_from_rpy(*rpy_att)
        if R_wb_att is None:
            self._fe["no_attitude"] += 1
            if self.vo.state != "tracking":
                R_wb_att = rot_from_rpy(0.0, 0.0, self.initial_yaw_rad) if self._last_p_body is None else None
        R_wc_att = None if R_wb_att is None else R_wb_att @ self.R_body_cam
        rng = self._range.nearest(t, self.opt.altimeter_max_age_us)
        p_start = self.initial_p_world if self._last_p_body is None else self._last_p_body
        if rng is None and self.vo.state != "tracking" and R_wb_att is not None:
            rng = self._range_from_dem(p_start, R_wb_att)
        st = self.vo.process(frame.image, t, R_wc_att, rng, p_start)
        if st.state == "lost":
            self._fe["lost"] += 1
            self._reinit()
            return self._not_ok(t, EstimateStatus.LOST, st)
        if st.T_world_cam is None:
            return self._not_ok(t, EstimateStatus.INITIALISING, st)
        T = self._output_tilt(st.T_world_cam, rng)
        R_wb = T[:3, :3] @ self.R_body_cam.T
        p_body = T[:3, :3] @ self.p_body_in_cam + T[:3, 3]
        if self._last_p_body is not None:
            self._dist_m += float(np.linalg.norm(p_body - self._last_p_body))
        self._last_p_body = p_body
        self._gather_altimeter(t, p_body, R_wb)
        if st.keyframe_id is not None:
            k = st.keyframe_id
            self._fe["keyframes"] += 1
            self._kf_dist[k] = self._dist_m
            for old in [kk for kk in self._kf_dist if kk < k - 4 * self.opt.vo.max_keyframes_kept]:
                del self._kf_dist[old]
            self._kf_frame = {k: {"image": frame.image, "range_m": rng, "agl_m": self._key_frame_agl(p_body)}}
            self._alt_samples = []
            self._wanted = k
        else:
            # the snapshot and the job go out one frame after the key frame, whose own frame already
            # carried the detection and the triangulation (keeps the per-frame tail short)
            self._submit()
        res = self.last_result
        info = {
            "tracks": st.n_tracks,
            "inliers": st.n_inliers,
            "keyframe": st.keyframe_id,
            "distance_m": self._dist_m,
            "geo": None if res is None else res.geo.get("status"),
            # running totals: key frames, fixes accepted / rejected by the gate / failed, alignments
            "backend": None if res is None else res.counters,
        }
        return PoseEstimate(
            stamp_us=t,
            p_body_in_world_m=p_body,
            rpy_rad=rpy_from_rot(R_wb),
            covariance=self._covariance(p_body),
            reset_counter=self.reset_counter,
            quality=float(min(1.0, st.n_inliers / max(self.opt.vo.tracker.max_features, 1))),
            status=EstimateStatus.OK,
            info=info,
        )

    def _output_tilt(self, T_world_cam: np.ndarray, range_m: float | None) -> np.ndarray:
        """The frame's pose with its roll/pitch fused with the recent attitude average (``vo_tilt_sigma_rad``).

        Inverse-variance weights of the two tilts (small angles); the pivot is the ground along the optical
        axis, at the range finder's range or, without one, the DEM's. The recent attitude samples also went
        into the newest key frames' priors, so the two are not quite independent: measured, not derived
        (docs/benchmarks.md, terrain SLAM)."""
        down = self.vo.averaged_down() if self._tilt_weight > 0 else None
        if down is None:
            return T_world_cam
        if range_m is None:
            R_wc, p_c = T_world_cam[:3, :3], T_world_cam[:3, 3]
            range_m = self._range_from_dem(R_wc @ self.p_body_in_cam + p_c, R_wc @ self.R_body_cam.T)
            if range_m is None:
                return T_world_cam
        return tilt_toward(T_world_cam, down, self._tilt_weight, range_m)

    def _range_from_dem(self, p_body: np.ndarray, R_world_body: np.ndarray) -> float | None:
        """Without an altimeter: range along body down to the DEM below ``p_body`` (flat-ground model)."""
        h = float(self._dem.height_at(p_body[0], p_body[1])[0])
        cos_tilt = float(R_world_body[2, 2])
        if not np.isfinite(h) or cos_tilt < 0.3 or -p_body[2] - h <= 0:
            return None
        return (-p_body[2] - h) / cos_tilt

    @staticmethod
    def _log_alignment(geo: dict) -> None:
        """One line when the map is put in the world: what a pilot watching the log wants to know (the
        terrain turned the compass heading by this much; the fixes placed the map)."""
        if "heading_coarse_deg" in geo:
            log.info("heading from the terrain: map turned by %+.1f deg (coarse)", geo["heading_coarse_deg"])
        if "heading_deg" in geo:
            log.info("heading from the terrain: map turned by %+.2f deg", geo["heading_deg"])
        status = geo.get("status")
        if status in ("aligned", "aligned_yaw", "realigned"):
            log.info("map %s to the geo-fixes", status.replace("_yaw", " (with the yaw)"))

    def _not_ok(self, t: int, status: EstimateStatus, st: Any) -> PoseEstimate:
        p = self.initial_p_world if self._last_p_body is None else self._last_p_body
        return PoseEstimate(
            stamp_us=t,
            p_body_in_world_m=np.array(p, float),
            rpy_rad=np.array([0.0, 0.0, self.initial_yaw_rad]),
            covariance=self._covariance(np.asarray(p, float)),
            reset_counter=self.reset_counter,
            quality=0.0,
            status=status,
            info={"tracks": st.n_tracks, "state": st.state},
        )

    @property
    def counters(self) -> dict[str, int]:
        """Running totals for the daemon's status: the front-end's (frames, lost, reinit, no_attitude,
        keyframes made, backend_jobs / applied / stale / errors) and the back-end's as of its last result
        (lba_runs, lba_failed, marginals_failed, fix_attempts / accepted / rejected / failed, alignments,
        realignments). A fresh dict: safe to read from another thread."""
        be = {k: v for k, v in self.backend_counters().items() if k != "keyframes" and "fix_failed_" not in k}
        return {**self._fe, **be}

    @property
    def no_fix_reasons(self) -> dict[str, int]:
        """Geo-fixes that failed, by the matcher's reason (as of the back-end's last result)."""
        p = "fix_failed_"
        return {k[len(p) :]: v for k, v in self.backend_counters().items() if k.startswith(p)}

    def backend_counters(self) -> dict:
        """Running totals of the back-end (key frames, fixes accepted / rejected / failed, alignments), over
        every worker this estimator has had."""
        out = dict(self._dead_totals)
        if self.last_result is not None:
            for k, v in self.last_result.counters.items():
                out[k] = out.get(k, 0) + v
        return out
