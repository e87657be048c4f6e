"""The key-frame back-end of terrain-aided SLAM (paper 1 sections 4.3): geo-reference each new key frame
against the DEM, gate the fix, align the VO frame to the world (eq. 21) once enough fixes agree, and run
the local bundle adjustment with the geo-referencing term (eqs. 22-24).

It is fed ``BackendJob``s (one per key frame, built by the front-end from its map) and returns
``BackendResult``s the front-end writes back. It keeps the few things that outlive a window: the accepted
fixes, the marginal covariance of each key frame (the prior of a key frame once it becomes an anchor),
the alignment state and the counters. The geo-referencer is passed in (``Locator``), so the back-end is
pure math and runs the same inline, in a thread or in a worker process.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from companion.geometry import make_T, rot_from_rpy, wrap_pi
from companion.georef.dem import Dem
from companion.lba.align import align_yaw_translation
from companion.lba.window import LbaOptions, WindowProblem, geo_redundancy, solve_window
from companion.vo.odometry import WindowSnapshot

Locator = Callable[[np.ndarray, np.ndarray, np.ndarray, float | None, bool], Any]
"""``locate(image, R_world_body, p_pred_world, alt_agl_m, solve_rotation_scale) -> GeoFix``
(companion.georef.georef)."""


def ground_below(dem: Dem, p_world: np.ndarray) -> np.ndarray:
    """(N, 5) per NED point: north, east, down of the DEM surface below it and the slopes dh/dn, dh/de
    (central differences over one cell); NaN rows off the DEM or in its holes."""
    p = np.asarray(p_world, float).reshape(-1, 3)
    n, e = p[:, 0], p[:, 1]
    d = 0.5 * dem.cell_m
    h = dem.height_at(n, e)
    dh_dn = (dem.height_at(n + d, e) - dem.height_at(n - d, e)) / (2 * d)
    dh_de = (dem.height_at(n, e + d) - dem.height_at(n, e - d)) / (2 * d)
    return np.stack([n, e, -h, dh_dn, dh_de], axis=1)


@dataclass(frozen=True)
class BackendOptions:
    lba: LbaOptions = field(default_factory=LbaOptions)
    geo_sigma_m: float = 1.0  # sigma0 of a geo-fix, north and east (m), before the w_G weighting:
    # the geo term's sigma is sigma0 / sqrt(w_G) (eq. 23 with unit pixel weights, as in the paper)
    geo_sigma_z_m: float = 2.0  # sigma0 of the fix's down component (DEM + altimeter, eq. 18; a 1 % altimeter
    # alone is 1 m at 100 m)
    geo_min_quality: float = 0.0  # extra gate on the phase-correlation peak, on top of the matcher's own
    # a fix counts less the lower its phase-correlation peak q: its sigma0 grows by (q_ref / q)^power when
    # q < q_ref, q_ref the ``geo_quality_percentile``-th percentile of the last ``geo_quality_window`` fixes'
    # peaks, at most ``geo_quality_ref_max`` (``quality_var_scale``). Within one terrain a fix's error grows
    # steeply as its peak falls (scratch replays of the Table 7 flights, both seeds, fixes used, horizontal RMS with
    # errors capped at 3 m, at q < 0.15 / 0.18-0.22 / 0.22-0.3 / 0.3-0.5: scene 02 1.71 / 0.84 / 0.66 / 0.28 m,
    # 05 1.40 / 0.76 / 0.42 / none, 08 none / 0.56 / 0.40 / 0.21 m: log-log slopes 1.4-1.8), while above 0.3
    # it hardly does (03: 0.28 m at 0.3-0.5, 0.23 m above). Relative to the recent peaks, not to one q: where
    # every peak is low (05) the learnt sigma already says so, and a fixed q_ref of 0.35 made 05 worse
    # (scratch, paired: 0.472 -> 0.527 m seed 0, 0.456 -> 0.657 m seed 1). The gate takes the fix's nominal
    # sigma (a low peak's far-off fix is still gated). Window 0 = off.
    geo_quality_window: int = 30
    geo_quality_percentile: float = 75.0
    geo_quality_ref_max: float = 0.35
    geo_quality_power: float = 1.5
    # and a fix counts more when its peak stands above both that percentile and ``geo_quality_ref_max``: its
    # variance shrinks by (q_hi / q)^(2 power), q_hi the larger of the two, to at most this factor (1 = off).
    # A fix matched much better than the recent ones (scene 07 coming off its featureless stretch: peaks
    # 0.5-0.65 whose fixes were 0.05 m off, while the sigma learnt on the stretch kept the estimate 0.3 m
    # away) or than the cap; where every peak is low (05) no fix passes the cap. Scratch, paired, the 18
    # Table 7 flights: 07 0.313 -> 0.287 m (seed 0), 0.373 -> 0.356 m (seed 1), the others within 0.015 m.
    geo_quality_bonus_min: float = 0.25
    pin_rotation_until_yaw_aligned: bool = True  # start-up key frames keep their rotation until the yaw is
    # aligned (measured: scene 05, 150 s, 21.8 -> 1.5 m: a few biased early fixes had turned the map 4 deg)
    # the reported covariance (not the adjustment) times the a-posteriori variance factor of the window's
    # geo term, sum of the fixes' squared whitened horizontal residuals / (2 n - 3), when above 1: fixes that
    # scatter more than their sigma say the pose is known less well than the marginal claims. Measured
    # (scratch 120 s circular flights, seed 0): gravel plain 05, errors inside the 95 % ellipse 31 -> 84 %
    # (NEES 10.2 -> 4.1); 08 96 -> 96 % (1.92 -> 1.78); 01 unchanged (its fixes scatter less than claimed)
    variance_factor: bool = True
    # the fixes' horizontal sigma learnt from their own scatter (Helmert's variance component estimate,
    # ``window.geo_redundancy``): after each adjustment the sigma the adjustment gives them is scaled towards
    # the one their residuals show, by (residuals / redundancy)^gain per key frame, within the range. How
    # well the matcher fixes a key frame depends on the terrain (Table 7 seed 0: mean ground error 0.10 m on
    # the plain 01, 1.0 m on the gravel 05), so one sigma is too tight where the terrain matches badly; w_G
    # stays the starting point. Scratch screen (Table 7 flights, paired): seed 0 02 0.494 -> 0.355, 05 0.810
    # -> 0.714, 07 +0.016, 08 -0.013, the others within 0.003 m; seed 1 02 -0.035, 05 -0.100, 07 -0.008.
    geo_sigma_adapt: bool = True
    geo_adapt_gain: float = 0.3
    geo_adapt_scale_range: tuple[float, float] = (1.0, 30.0)  # of the variance, relative to sigma0^2 / w_G:
    # never below 1 (scratch, seed 0: letting the well-fixed scenes 01 and 06 tighten their fixes to the 0.1 m
    # their scatter shows cost 0.04 and 0.03 m: their errors are correlated in time, which a scatter about the
    # VO does not see)
    geo_adapt_min_redundancy: float = 2.0  # the window's fixes must carry this much redundancy to update
    geo_adapt_q_cap: float = 13.8  # a fix's whitened squared residual counts at most this (2 dof, p 0.001)
    geo_gate_chi2: float = 16.27  # Mahalanobis gate of a fix against the prediction (3 dof, p = 0.001)
    align_min_fixes: int = 3  # eq. 21 alignment once this many key frames have fixes
    align_huber_m: float = 1.0  # robust threshold of the alignment
    align_max_rms_m: float = 2.0  # an alignment worse than this is not trusted (wait for more fixes)
    align_min_spread_m: float = 25.0  # the yaw is aligned only when the fixes spread this far (RMS about
    # their centre): with fixes good to ~0.5 m, a shorter base turns the yaw by more than the compass is off
    # start-up heading from the matcher: until the yaw is aligned, each key frame's fix also recovers the
    # heading error of the map (``GeoReferencer.locate(solve_rotation_scale=True)``, Fourier-Mellin then a
    # peak search); once the median of these estimates is known to ``heading_max_se_deg`` the map is turned
    # by it (``_try_heading``), and before the first alignment two agreeing estimates far off turn it at once
    # (``heading_coarse_*``). Mars has no compass worth the name: the terrain gives the heading long before
    # the fixes spread ``align_min_spread_m``.
    heading_from_matcher: bool = True
    heading_min_samples: int = 5  # estimates needed (their median is robust to a wrong peak or two)
    heading_min_quality: float = 0.3  # an estimate counts when the translation peak at it is this high:
    # below, on the dunes, gravel and canyon scenes (peaks 0.19-0.25), the recovered rotation is off by
    # 0.6-0.9 deg median with wild outliers, no better than a compass; from 0.3 up, 0.1-0.35 deg
    heading_max_se_deg: float = 0.5  # standard error of the median (1.25 x robust sigma / sqrt(n)) to act
    heading_coarse_deg: float = 5.0  # before the first alignment, two consecutive estimates beyond this
    heading_coarse_agree_deg: float = 2.0  # that agree to this turn the map at once (a compass far off)
    # until the yaw is known, each fix is matched at the heading the matcher's estimates so far give (their
    # median, shrunk towards the compass by the two spreads) instead of at the compass's. A heading error
    # turns the frame against the reference about the optical axis, and the correlation peak then follows
    # whichever part of the footprint matches best: measured (scratch, key frames of the Table 7 flights
    # matched at the true pose but the yaw, +-2 deg), 0.2-0.8 m of fix error per degree on 01 and 08, 1.0-1.2
    # over the first six key frames of 02 (0.6-0.9 on two later ones), the same way over consecutive key
    # frames; so a compass 1.36 deg off put the first three fixes of 02 (seed 2) 1.9-2.4 m west, and the map
    # with them.
    heading_for_fixes: bool = True
    heading_prior_sigma_rad: float = float(np.radians(2.0))  # the compass's (``TerrainLbaOptions``)
    heading_sample_sigma_deg: float = 1.0  # one estimate's spread, until three show their own
    heading_sample_sigma_floor_deg: float = 0.1
    realign_after_rejections: int = 6  # this many gated fixes in a row that agree with each other:
    # the VO frame is off, not the fixes -> eq. 21 again on them
    drift_sigma_per_m: float = 0.02  # VO position sigma growth per metre since the last adjusted key frame
    min_anchors: int = 2  # with fewer anchors (start-up), the oldest window key frames are held: two
    # pinned poses fix the gauge including the monocular scale set by the altimeter
    initial_sigma_m: float = 1.0  # once geo-referenced, a start-up key frame (pinned so far) is held by this
    initial_sigma_rad: float = 0.02  # prior instead, so that the fixes can move it
    geo_on_ground: bool = True  # eq. 24 at the ground point the geo-fix locates on the optical axis (at
    # the altimeter's range) rather than at the camera: then an attitude error of the pose the fix was
    # computed with (h x angle: 0.5 m for 0.3 deg at 100 m) does not pass into the fix. False: at the body.


def _repeatable(rotation_rad: float) -> float:
    """The matcher's heading estimate rounded to 1 microradian. Its last digits are not repeatable in the
    back-end's worker process: the same key frames gave estimates 1e-10 rad apart in about one run in
    three (measured; the same inputs replayed in one process repeat to the bit, the cause is not found).
    Since each estimate now sets the heading of the next fixes, that noise turned a run that repeats to
    the bit (``backend_apply = "fixed_delay"``) into one that does not; 1 microradian is under 1e-3 of the
    estimates' own accuracy (0.1 deg, 1.7 mrad, at best)."""
    return round(float(rotation_rad), 6)


@dataclass(frozen=True)
class BackendJob:
    """One key frame's work.

    snapshot: the window (front-end map, VO frame). newest_kf: the key frame just made. image: its frame
    (None: no geo-referencing). R_world_body, p_body_in_world: its VO pose (world NED). alt_agl_m: vertical
    height above ground from the altimeter (None: unknown); range_m: the altimeter's slant range along the
    optical axis (None: unknown). dist_since_prev_kf_m: path length since the previous key frame.
    p_body_in_cam: (3,) body origin in the camera frame. epoch: map epoch (bumped at each re-initialisation).
    """

    snapshot: WindowSnapshot
    newest_kf: int
    image: np.ndarray | None
    R_world_body: np.ndarray
    p_body_in_world: np.ndarray
    alt_agl_m: float | None
    range_m: float | None
    dist_since_prev_kf_m: float
    p_body_in_cam: np.ndarray
    K: np.ndarray
    epoch: int = 0


@dataclass(frozen=True)
class BackendResult:
    """What the front-end writes back (see ``VisualOdometry.apply_correction``).

    T_align: (4, 4) eq. 21 transform applied to the map before the adjustment (identity when none).
    kf_ids / T_world_cam: solved key frames; lm_ids / p_world: solved points; outlier_kf / outlier_lm:
    observations to drop. cov_newest: (6, 6) Pose3-tangent marginal of the newest key frame (NaN if none).
    geo: dict with the fix outcome ("none", "failed:<reason>", "pending", "accepted", "rejected",
    "aligned" (eq. 21, translation, and yaw when the fixes spread enough), "aligned_yaw" (eq. 21 again with
    the yaw, once they do), "realigned"), its quality and residuals, and "heading_deg" when the matcher's
    start-up heading turned the map by that much ("heading_coarse_deg": its coarse turn, a compass far off).
    counters: running totals. ms_*: compute times.
    located / yaw_known: the fixes have placed the map (eq. 21) / its heading is known from the terrain (eq.
    21 with the yaw, or the matcher's heading); until then the marginals are relative to the pinned start
    (``companion.lba.gauge``). pivot_world: (3,) the centre of the fixes that placed it (NaN before).
    """

    newest_kf: int
    epoch: int
    T_align: np.ndarray
    kf_ids: np.ndarray
    T_world_cam: np.ndarray
    lm_ids: np.ndarray
    p_world: np.ndarray
    outlier_kf: np.ndarray
    outlier_lm: np.ndarray
    cov_newest: np.ndarray
    geo: dict
    counters: dict
    lba_ok: bool
    lba_iterations: int
    ms_geo: float
    ms_lba: float
    located: bool = False
    yaw_known: bool = False
    pivot_world: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))


def quality_var_scale(
    q: float, recent_q: np.ndarray, percentile: float, ref_max: float, power: float, bonus_min: float = 1.0
) -> float:
    """How much a fix's variance grows for its phase-correlation peak q (``BackendOptions.geo_quality_*``):
    ((q_ref / q)^power)^2 when q < q_ref, with q_ref the ``percentile``-th percentile of the recent fixes'
    peaks ``recent_q`` (q's own included), at most ``ref_max``; ((q_hi / q)^power)^2, at least ``bonus_min``,
    when q > q_hi, the larger of that percentile and ``ref_max``; else 1."""
    q_p = float(np.percentile(recent_q, percentile))
    q_hi = max(q_p, ref_max)
    if q > q_hi:
        return max(bonus_min, (q_hi / q) ** (2.0 * power))
    return max(1.0, min(q_p, ref_max) / max(q, 1e-3)) ** (2.0 * power)


def _turn_about(c: np.ndarray, angle_rad: float) -> np.ndarray:
    """(4, 4) turn by angle_rad about the down axis through the point c (true yaw = yaw + angle)."""
    R = rot_from_rpy(0.0, 0.0, angle_rad)
    return make_T(R, c - R @ c)


def _transform_snapshot(s: WindowSnapshot, T: np.ndarray) -> WindowSnapshot:
    """The snapshot moved by T (4, 4); itself when T is the identity."""
    if np.allclose(T, np.eye(4)):
        return s
    return replace(
        s,
        T_world_cam=np.einsum("ij,njk->nik", T, s.T_world_cam),
        p_world=s.p_world @ T[:3, :3].T + T[:3, 3],
    )


class Backend:
    """Stateful back-end; one per flight. ``locate`` may be None (VO only: no geo-referencing).
    ``terrain``: the DEM of the landmark-on-DEM term (``LbaOptions.terrain_sigma_m``), None = no term."""

    def __init__(self, options: BackendOptions, locate: Locator | None, terrain: Dem | None = None) -> None:
        self.opt = options
        self.locate = locate if options.lba.w_geo > 0 else None
        self.terrain = terrain if options.lba.terrain_sigma_m > 0 else None
        self.counters = {
            "keyframes": 0,
            "lba_runs": 0,
            "fix_attempts": 0,
            "fix_failed": 0,
            "fix_accepted": 0,
            "fix_rejected": 0,
            "fix_heading_rescued": 0,  # failed at the compass heading, found at the matcher's (start-up)
            "heading_coarse_turns": 0,  # start-up turns by two agreeing heading estimates far off
            "alignments": 0,
            "realignments": 0,
            "lba_failed": 0,
            "marginals_failed": 0,
        }
        self.fail_reasons: dict[str, int] = {}
        # the learnt scale of the fixes' horizontal variance (``geo_sigma_adapt``); kept across map
        # re-initialisations: it belongs to the terrain and the camera, not to the map
        self.geo_var_scale = 1.0
        # the peaks of the last fixes (``geo_quality_window``): like the sigma, a property of the terrain
        self.recent_quality: deque[float] = deque(maxlen=max(self.opt.geo_quality_window, 1))
        self._reset_state()

    def _reset_state(self) -> None:
        self.epoch = -1
        # fixes by key frame, each (7,): the geo-referenced world point, the camera-frame point it locates,
        # and its variance scale (quality)
        self.fixes: dict[int, np.ndarray] = {}  # accepted (world frame)
        self.pending: dict[int, np.ndarray] = {}  # waiting for the first alignment
        self.rejected: dict[int, np.ndarray] = {}  # consecutive gated ones
        self.cov: dict[int, np.ndarray] = {}  # last marginal covariance per key frame
        self.aligned = False
        self.yaw_aligned = False
        self.pivot = np.full(3, np.nan)  # centre of the fixes the map was last placed by (eq. 21)
        self.startup_kfs: set[int] = set()
        # the matcher's heading errors (rad) while the yaw is not known
        self.heading_samples: list[float] = []
        self.cov_pos_newest: np.ndarray | None = None  # world position covariance of the last newest kf

    def _fix_cov(self, adapted: bool = True) -> np.ndarray:
        """A fix's covariance before the w_G weighting; ``adapted``: its horizontal part scaled as learnt
        (``geo_sigma_adapt``)."""
        h = self.opt.geo_sigma_m**2 * (self.geo_var_scale if adapted else 1.0)
        return np.diag([h, h, self.opt.geo_sigma_z_m**2])

    @staticmethod
    def _vo_points(s: WindowSnapshot, fixes: dict[int, np.ndarray], kf_ids: list[int]) -> np.ndarray:
        """(N, 3) where the VO poses put the camera-frame points the fixes locate."""
        idx = {int(k): i for i, k in enumerate(s.kf_ids)}
        T = s.T_world_cam
        return np.stack([T[idx[k], :3, :3] @ fixes[k][3:6] + T[idx[k], :3, 3] for k in kf_ids])

    def _try_align(
        self, s: WindowSnapshot, fixes: dict[int, np.ndarray], min_spread_m: float
    ) -> tuple[np.ndarray, list[int], bool] | None:
        """Eq. 21 from the fixes of key frames in the snapshot: (T_world_vo, inlier kf ids, yaw estimated),
        or None when too few fixes agree. The down axis is whitened by the fixes' sigmas (a fix's height,
        DEM + altimeter, is much noisier than its north and east)."""
        in_snap = set(int(k) for k in s.kf_ids)
        ks = [k for k in sorted(fixes) if k in in_snap]
        if len(ks) < self.opt.align_min_fixes:
            return None
        S = np.array([1.0, 1.0, self.opt.geo_sigma_m / self.opt.geo_sigma_z_m])
        p_vo = self._vo_points(s, fixes, ks) * S
        p_geo = np.stack([fixes[k][:3] for k in ks]) * S
        a = align_yaw_translation(p_vo, p_geo, huber_m=self.opt.align_huber_m, min_spread_m=min_spread_m)
        if a.rms_m > self.opt.align_max_rms_m or a.inliers.sum() < self.opt.align_min_fixes:
            return None
        T = a.T_world_vo.copy()
        T[:3, 3] /= S  # the rotation is about down, so it commutes with the scaling of down
        return T, [k for k, ok in zip(ks, a.inliers) if ok], a.yaw_observable

    def _release_startup_rotations(self) -> None:
        """The yaw is known: the start-up key frames' rotation may now be moved by the adjustment."""
        released = np.diag([self.opt.initial_sigma_rad**2] * 3 + [self.opt.initial_sigma_m**2] * 3)
        for kk in self.startup_kfs:
            if kk in self.cov:
                self.cov[kk] = released

    def _try_heading(self, s: WindowSnapshot) -> tuple[np.ndarray, float] | None:
        """(T_world_vo turning the map by the matcher's median heading error, that angle), or None while the
        estimates are too few or too scattered. The turn is about the fixes' centre once the map is aligned
        (it keeps them in place), else about the newest key frame (the first alignment will place it)."""
        r = np.asarray(self.heading_samples, float)
        if len(r) < max(self.opt.heading_min_samples, 1):
            return None
        # the median about the samples' circular mean: a heading error near 180 deg (no compass) wraps
        mean = float(np.angle(np.exp(1j * r).sum()))
        r = np.asarray(wrap_pi(r - mean), float)
        m = float(np.median(r))
        d = float(wrap_pi(m + mean))
        se = 1.2533 * 1.4826 * float(np.median(np.abs(r - m))) / np.sqrt(len(r))
        if se > np.radians(self.opt.heading_max_se_deg):
            return None
        in_snap = set(int(k) for k in s.kf_ids)
        ks = [k for k in sorted(self.fixes) if k in in_snap]
        if self.aligned and not ks:
            return None
        c = self._vo_points(s, self.fixes, ks).mean(axis=0) if self.aligned else s.T_world_cam[-1, :3, 3]
        return _turn_about(c, d), d

    def fix_heading(self) -> float:
        """The heading error (rad, true yaw = map yaw + it) a fix is matched at while the yaw is not known:
        the median of the matcher's estimates, shrunk towards 0 (the compass) by the compass's variance
        against the median's (each estimate's spread: ``heading_sample_sigma_deg`` until three show their
        own, robustly). 0 without estimates or with ``heading_for_fixes`` off."""
        r = np.asarray(self.heading_samples, float)
        if not self.opt.heading_for_fixes or len(r) == 0:
            return 0.0
        mean = float(np.angle(np.exp(1j * r).sum()))
        r = np.asarray(wrap_pi(r - mean), float)
        m = float(np.median(r))
        if len(r) >= 3:
            floor = float(np.radians(self.opt.heading_sample_sigma_floor_deg))
            s = max(1.4826 * float(np.median(np.abs(r - m))), floor)
        else:
            s = float(np.radians(self.opt.heading_sample_sigma_deg))
        var_median = (1.2533 * s) ** 2 / len(r)
        prior = self.opt.heading_prior_sigma_rad**2
        return float(wrap_pi(m + mean)) * prior / (prior + var_median)

    def _coarse_heading(self) -> float | None:
        """The mean of the last two heading estimates (across +-180 deg too) when they agree to
        ``heading_coarse_agree_deg`` and are beyond ``heading_coarse_deg``, else None."""
        r = self.heading_samples
        if len(r) < 2:
            return None
        gap = float(wrap_pi(r[-1] - r[-2]))
        d = float(wrap_pi(r[-2] + 0.5 * gap))
        if abs(gap) < np.radians(self.opt.heading_coarse_agree_deg) and abs(d) > np.radians(
            self.opt.heading_coarse_deg
        ):
            return d
        return None

    def _geo(self, job: BackendJob) -> tuple[dict, np.ndarray]:
        """Geo-reference the newest key frame; returns (outcome, T_align)."""
        want_heading = self.opt.heading_from_matcher and not self.yaw_aligned
        out, T_align = self._geo_fix(job, want_heading)
        d = self._coarse_heading() if want_heading and not self.aligned else None
        if d is not None:
            # far off (no compass): every second flown on the wrong heading takes the VO further from the
            # terrain the matcher searches, so two agreeing estimates turn the map at once; the fine turn
            # below follows from estimates measured at the new heading
            c = _transform_snapshot(job.snapshot, T_align).T_world_cam[-1, :3, 3]
            T_align = _turn_about(c, d) @ T_align
            self.heading_samples.clear()
            self.pending.clear()
            self.counters["heading_coarse_turns"] += 1
            out["heading_coarse_deg"] = float(np.degrees(d))
        if want_heading and not self.yaw_aligned:
            res = self._try_heading(_transform_snapshot(job.snapshot, T_align))
            if res is not None:
                T_align = res[0] @ T_align
                self.yaw_aligned = True
                if self.aligned:
                    self._release_startup_rotations()
                else:
                    # a compass far off (measured: 10 deg on scene 01) biases the plain fixes so that they
                    # never agree on an alignment; those taken at the old heading are dropped, the next
                    # ones are matched at the turned one
                    self.pending.clear()
                self.counters["alignments"] += 1
                out["heading_deg"] = float(np.degrees(res[1]))
        return out, T_align

    def _geo_fix(self, job: BackendJob, want_heading: bool) -> tuple[dict, np.ndarray]:
        """The fix of the newest key frame: gate, alignments (eq. 21); returns (outcome, T_align).
        want_heading: also ask the matcher for the heading error (kept in ``heading_samples``)."""
        T_align = np.eye(4)
        if self.locate is None or job.image is None:
            return {"status": "none"}, T_align
        self.counters["fix_attempts"] += 1
        R_fix = job.R_world_body
        rs = None
        if want_heading:
            # a search for the heading (and height) error first: the fix itself is the plain one, at the
            # altimeter's height, and at the heading the estimates so far give (``heading_for_fixes``)
            rs = self.locate(job.image, job.R_world_body, job.p_body_in_world, job.alt_agl_m, True)
            if rs.ok and rs.rotation_scale_quality >= self.opt.heading_min_quality:
                self.heading_samples.append(_repeatable(rs.rotation_rad))
            else:
                rs = None
            d = self.fix_heading()
            if d != 0.0:
                R_fix = rot_from_rpy(0.0, 0.0, d) @ job.R_world_body
        fix = self.locate(job.image, R_fix, job.p_body_in_world, job.alt_agl_m, False)
        if rs is not None and not fix.ok:
            # the compass is so far off that the plain match failed, but the search found the terrain: the
            # plain fix again at the heading it found
            R_found = rot_from_rpy(0.0, 0.0, _repeatable(rs.rotation_rad)) @ job.R_world_body
            fix = self.locate(job.image, R_found, job.p_body_in_world, job.alt_agl_m, False)
            if fix.ok:
                self.counters["fix_heading_rescued"] += 1
        if not fix.ok or fix.quality < self.opt.geo_min_quality:
            reason = fix.reason or "low_quality"
            self.fail_reasons[reason] = self.fail_reasons.get(reason, 0) + 1
            self.counters["fix_failed"] += 1
            return {"status": f"failed:{reason}", "quality": float(fix.quality)}, T_align
        k = job.newest_kf
        p_fix = np.asarray(fix.p_world, float)
        out = {
            "kf": k,
            "quality": float(fix.quality),
            "residual_m": (p_fix - job.p_body_in_world).tolist(),
            # what the fix says, for a replay to check against truth: the body position (eq. 18, at the
            # key frame's VO attitude) and the ground point it locates on the optical axis at the range
            "p_fix_world": p_fix.tolist(),
        }
        # the located camera-frame point and its world position by the fix (see geo_on_ground)
        R_wc = job.snapshot.T_world_cam[-1, :3, :3]
        lever = np.asarray(job.p_body_in_cam, float)
        if self.opt.geo_on_ground and job.range_m is not None:
            lever = np.array([0.0, 0.0, float(job.range_m)])
            p_fix = p_fix + R_wc @ (lever - job.p_body_in_cam)
            out["ground_fix_world"] = p_fix.tolist()
        var_scale = 1.0
        if self.opt.geo_quality_window > 0:
            self.recent_quality.append(float(fix.quality))
            var_scale = quality_var_scale(
                float(fix.quality),
                np.asarray(self.recent_quality),
                self.opt.geo_quality_percentile,
                self.opt.geo_quality_ref_max,
                self.opt.geo_quality_power,
                self.opt.geo_quality_bonus_min,
            )
        entry = np.concatenate([p_fix, lever, [var_scale]])
        p_pred = R_wc @ lever + job.snapshot.T_world_cam[-1, :3, 3]
        if not self.aligned:
            self.pending[k] = entry
            res = self._try_align(job.snapshot, self.pending, self.opt.align_min_spread_m)
            if res is None:
                # keep the most recent ones only: the window moves on
                for old in sorted(self.pending)[: max(len(self.pending) - 2 * self.opt.align_min_fixes, 0)]:
                    del self.pending[old]
                out["status"] = "pending"
                return out, T_align
            T_align, inliers, yaw_estimated = res
            self.yaw_aligned = self.yaw_aligned or yaw_estimated  # (or by the matcher's heading before)
            self.fixes.update({kk: self.pending[kk] for kk in inliers})
            self.pivot = np.mean([self.pending[kk][:3] for kk in inliers], axis=0)
            self.counters["fix_accepted"] += len(inliers)
            self.pending.clear()
            self.aligned = True
            # start-up key frames become movable by the fixes; their rotation only once the yaw is aligned
            # too (a few fixes over a short base must not turn the map: they shift it)
            free = self.yaw_aligned or not self.opt.pin_rotation_until_yaw_aligned
            sig_rot = self.opt.initial_sigma_rad if free else self.opt.lba.pinned_sigma
            init_cov = np.diag([sig_rot**2] * 3 + [self.opt.initial_sigma_m**2] * 3)
            for kk in job.snapshot.kf_ids:
                if int(kk) not in self.cov:
                    self.cov[int(kk)] = init_cov
                    self.startup_kfs.add(int(kk))
            self.counters["alignments"] += 1
            out["status"] = "aligned"
            return out, T_align
        # gate against the prediction: the last adjusted key frame's covariance grown by the distance since
        P_pred = np.eye(3) * 1e-2 if self.cov_pos_newest is None else self.cov_pos_newest
        P_pred = P_pred + np.eye(3) * (self.opt.drift_sigma_per_m * job.dist_since_prev_kf_m) ** 2
        e = p_fix - p_pred
        d2 = float(e @ np.linalg.solve(P_pred + self._fix_cov(adapted=False), e))
        out["mahalanobis2"] = d2
        if d2 <= self.opt.geo_gate_chi2:
            self.fixes[k] = entry
            self.rejected.clear()
            self.counters["fix_accepted"] += 1
            out["status"] = "accepted"
            if not self.yaw_aligned:
                # eq. 21 once more, now with the yaw, as soon as the fixes span enough ground
                res = self._try_align(job.snapshot, self.fixes, self.opt.align_min_spread_m)
                if res is not None and res[2]:
                    T_align = res[0]
                    self.yaw_aligned = True
                    # the start-up key frames' rotation is released now that the yaw is known
                    self._release_startup_rotations()
                    self.counters["alignments"] += 1
                    out["status"] = "aligned_yaw"
            return out, T_align
        self.counters["fix_rejected"] += 1
        self.rejected[k] = entry
        out["status"] = "rejected"
        if len(self.rejected) >= self.opt.realign_after_rejections:
            res = self._try_align(job.snapshot, self.rejected, self.opt.align_min_spread_m)
            if res is not None:
                T_align, inliers, self.yaw_aligned = res
                self.heading_samples.clear()  # measured against the old alignment's yaw
                # the old fixes were taken in the old alignment: they are superseded
                self.fixes = {kk: self.rejected[kk] for kk in inliers}
                self.pivot = np.mean([self.rejected[kk][:3] for kk in inliers], axis=0)
                self.counters["fix_accepted"] += len(inliers)
                self.counters["realignments"] += 1
                out["status"] = "realigned"
            self.rejected.clear()
        return out, T_align

    def _variance_factor(self, solved: WindowSnapshot) -> float:
        """max(1, a-posteriori variance factor of the window's geo-fixes' horizontal residuals), against
        the nominal sigma sigma0 / sqrt(w_G), not the learnt one (``geo_sigma_adapt``): whitened by the learnt
        sigma the factor is ~1 by construction, yet the fixes' errors are correlated in time (a bias that
        drifts with the terrain and the sun), which the window's marginals, built as if each fix were
        independent, do not carry. Measured (Table 7, seed 0): against the learnt sigma, scene 05's errors
        fell inside their 95 % ellipse 51 % of the time, 02's 93 % (against the nominal: 93 % and 99.5 %).
        Nor against a weak match's own larger sigma (``geo_quality_*``): the estimate follows such a fix less,
        but its scatter still says how well the terrain fixes the window (scratch, the Table 7 flights, the
        same estimates: scene 07 inside 82 -> 94 % on seed 0, 76 -> 86 % on seed 1; 02 of seed 1 78 -> 82 %)."""
        ks = [int(k) for k in solved.kf_ids if int(k) in self.fixes]
        if len(ks) < 3:
            return 1.0
        f = np.stack([self.fixes[k] for k in ks])
        r = f[:, :2] - self._vo_points(solved, self.fixes, ks)[:, :2]
        nominal = self._fix_cov(adapted=False)[0, 0]
        r2 = np.sum(r * r, axis=1) * max(self.opt.lba.w_geo, 1e-9) / nominal
        return max(1.0, float(np.sum(r2)) / (2 * len(ks) - 3))

    def process(self, job: BackendJob) -> BackendResult:
        if job.epoch != self.epoch:
            self._reset_state()
            self.epoch = job.epoch
        self.counters["keyframes"] += 1
        t0 = time.perf_counter()
        geo, T_align = self._geo(job)
        t1 = time.perf_counter()
        s = _transform_snapshot(job.snapshot, T_align)
        M = len(s.kf_ids)
        anchor = s.anchor.copy()
        # a window no larger than the held start (the first: the VO's two initial key frames) cannot fix the
        # monocular scale with its newest key frame free: the adjustment slid that key frame along the
        # baseline by whatever Levenberg-Marquardt's steps left it (measured: 0.98 m along a 4.8 m baseline,
        # scene 09 seed 0, written back into the map). Then every key frame is held and only the points move.
        whole_held = M <= self.opt.min_anchors
        if anchor.sum() < self.opt.min_anchors:
            for i in range(M):
                if anchor.sum() >= self.opt.min_anchors or (i == M - 1 and not whole_held):
                    break
                anchor[i] = True
        anchor_cov = np.full((M, 6, 6), np.nan)
        geo_p = np.full((M, 3), np.nan)
        geo_lever = np.zeros((M, 3))
        geo_cov = np.tile(self._fix_cov(), (M, 1, 1))
        for i, k in enumerate(s.kf_ids):
            k = int(k)
            if anchor[i] and k in self.cov:
                anchor_cov[i] = self.cov[k]
            if k in self.fixes:
                geo_p[i], geo_lever[i] = self.fixes[k][:3], self.fixes[k][3:6]
                geo_cov[i] *= self.fixes[k][6]
        problem = WindowProblem(
            T_world_cam=s.T_world_cam,
            anchor=anchor,
            anchor_cov=anchor_cov,
            p_world=s.p_world,
            obs_kf=s.obs_kf,
            obs_lm=s.obs_lm,
            obs_px=s.obs_px,
            K=job.K,
            geo_p_world=geo_p,
            geo_lever_cam=geo_lever,
            geo_cov=geo_cov,
            down_cam=s.down_cam,
            # the map must be in the world (position and yaw) before its points can be put on the DEM
            lm_ground=ground_below(self.terrain, s.p_world)
            if self.terrain is not None and self.aligned and self.yaw_aligned
            else None,
        )
        sol = solve_window(problem, self.opt.lba)
        self.counters["lba_runs"] += 1
        t2 = time.perf_counter()
        if not sol.ok:
            self.counters["lba_failed"] += 1
        elif self.opt.geo_sigma_adapt and self.opt.lba.w_geo > 0:
            q, red = geo_redundancy(problem, sol, self.opt.lba.w_geo, self.opt.geo_adapt_q_cap)
            if red >= self.opt.geo_adapt_min_redundancy:
                step = float(np.clip(q / red, 0.25, 4.0)) ** self.opt.geo_adapt_gain
                lo, hi = self.opt.geo_adapt_scale_range
                self.geo_var_scale = float(np.clip(self.geo_var_scale * step, lo, hi))
        for i, k in enumerate(s.kf_ids):
            if not anchor[i] and np.all(np.isfinite(sol.cov[i])):
                self.cov[int(k)] = sol.cov[i]
        # forget key frames that left the front-end's map
        oldest = int(s.kf_ids.min()) if M else 0
        for d in (self.cov, self.fixes):
            for k in [k for k in d if k < oldest - 200]:
                del d[k]
        cov_newest = np.full((6, 6), np.nan) if whole_held else sol.cov[-1]  # (an empty window is held whole)
        if not np.all(np.isfinite(cov_newest)):
            # the first window is held whole: it has no marginal of its own, expected, not a failure
            if not whole_held:
                self.counters["marginals_failed"] += 1
        else:
            R = sol.T_world_cam[-1, :3, :3]
            self.cov_pos_newest = R @ cov_newest[3:, 3:] @ R.T
        if self.opt.variance_factor and np.all(np.isfinite(cov_newest)):
            cov_newest = cov_newest * self._variance_factor(replace(s, T_world_cam=sol.T_world_cam))
        out_kf = s.kf_ids[s.obs_kf[~sol.obs_inlier]]
        out_lm = s.lm_ids[s.obs_lm[~sol.obs_inlier]]
        if job.newest_kf in self.fixes and int(s.kf_ids[-1]) == job.newest_kf:
            f = self.fixes[job.newest_kf]
            p_new = sol.T_world_cam[-1, :3, :3] @ f[3:6] + sol.T_world_cam[-1, :3, 3]
            geo["post_residual_m"] = (f[:3] - p_new).tolist()
        if self.opt.lba.w_geo > 0:
            geo["fix_sigma_m"] = float(np.sqrt(self._fix_cov()[0, 0] / self.opt.lba.w_geo))
        return BackendResult(
            newest_kf=job.newest_kf,
            epoch=job.epoch,
            T_align=T_align,
            kf_ids=s.kf_ids,
            T_world_cam=sol.T_world_cam,
            lm_ids=s.lm_ids,
            p_world=sol.p_world,
            outlier_kf=out_kf,
            outlier_lm=out_lm,
            cov_newest=cov_newest,
            geo=geo,
            counters={**self.counters, **{f"fix_failed_{r}": n for r, n in self.fail_reasons.items()}},
            lba_ok=sol.ok,
            lba_iterations=sol.iterations,
            ms_geo=(t1 - t0) * 1e3,
            ms_lba=(t2 - t1) * 1e3,
            located=self.aligned,
            yaw_known=self.yaw_aligned,
            pivot_world=self.pivot.copy(),
        )
