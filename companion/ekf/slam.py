"""Visible / thermal / dual inverse-depth EKF-SLAM (paper 2): IMU propagation, altimeter updates,
per-camera landmark tracking (eqs. 6-7), landmark deletion and diversity sampling (eq. 8).

Pure logic on numpy arrays and timestamps (integer microseconds); no I/O, no clock. The daemon's
estimator (``companion.estimators.vis_thermal_ekf``) and the offline runner both drive this class.

Time handling. IMU samples are zero-order held: a sample stamped t_k is used from t_k until the next
one. Samples are queued and only integrated once they are ``imu_max_lag_s`` older than the newest
sample, or when a frame / altimeter reading asks for the state at its stamp; so a frame that arrives
after the IMU samples that follow it is still processed at its own capture time, with the IMU up to
that time. A frame older than the filter (older than the lag) is processed at the filter's time and
counted in ``stale_frames``; an IMU sample older than the filter is dropped and counted.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass, field

import numpy as np

from companion.ekf import landmarks as lmk
from companion.ekf.altimeter import facet_encloses_beam, facet_range, select_facet
from companion.ekf.features import (
    Detections,
    ground_plane_affine,
    match_predicted,
    ncc_search,
    reference_patch,
    warp_template,
)
from companion.ekf.filter import IDX_C, InverseDepthEkf
from companion.ekf.options import EkfOptions, cameras_for_mode
from companion.ekf.ransac import low_innovation_inliers
from companion.ekf.sampling import budget_bandwidth, sample_new_landmarks
from companion.ekf.so3 import euler_rate_matrix, rot_from_quat
from companion.geometry import camera_pose, rpy_from_rot


@dataclass(frozen=True)
class SlamPose:
    """Filter output at one frame time.

    p_world: (3,) NED m; rpy_rad: (3,); covariance: (6,6) over (x, y, z, roll, pitch, yaw);
    matched: visual matches used per camera; n_landmarks per camera; tracking: at least one match.
    """

    stamp_us: int
    p_world: np.ndarray
    v_world: np.ndarray
    rpy_rad: np.ndarray
    covariance: np.ndarray
    matched: dict[str, int]
    n_landmarks: dict[str, int]
    position_sigma_max_m: float
    frames_since_match: int


@dataclass(frozen=True)
class _PatchRef:
    """A landmark's first appearance: the 8-bit patch around its keypoint (pixel (0, 0) at ``origin``), the
    keypoint ``uv`` and the camera pose then (R_world_cam, p_cam in world) as the filter had it."""

    patch: np.ndarray
    origin: np.ndarray
    uv: np.ndarray
    R_world_cam: np.ndarray
    p_cam: np.ndarray


@dataclass
class SlamCounters:
    """Health counters (monotonic)."""

    frames: int = 0
    stale_frames: int = 0
    late_imu: int = 0
    imu: int = 0
    # propagation steps on the motion model, no IMU sample close enough (``_step``)
    steps_without_imu: int = 0
    altimeter_updates: int = 0
    altimeter_rejected: int = 0
    altimeter_no_facet: int = 0
    landmarks_added: dict[str, int] = field(default_factory=dict)
    landmarks_deleted: dict[str, int] = field(default_factory=dict)
    deleted_out_of_view: int = 0
    deleted_unmatched: int = 0
    ransac_rejected: int = 0  # gated matches the 1-point RANSAC refused (``ransac``)
    patch_matches: int = 0  # landmarks SIFT missed that their patch found (``patch_cameras``), used
    matches: dict[str, int] = field(default_factory=dict)


class VisThermalSlam:
    """One flight's SLAM. ``cameras`` maps camera name to ``landmarks.CameraModel``.

    Call ``add_imu`` / ``add_altimeter`` as samples arrive and ``process_frame`` with each frame set's
    detections; ``start`` fixes the initial state (position, velocity, attitude quaternion).
    """

    def __init__(self, options: EkfOptions, cameras: dict[str, lmk.CameraModel], gravity_mps2: float) -> None:
        self.opts = options
        self.camera_names = cameras_for_mode(options.mode)
        missing = [c for c in self.camera_names if c not in cameras]
        if missing:
            raise ValueError(f"mode {options.mode!r} needs camera models for {missing}")
        self.cameras = {c: cameras[c] for c in self.camera_names}
        self.gravity_mps2 = gravity_mps2
        self.rng = np.random.default_rng(options.seed)
        self.ekf: InverseDepthEkf | None = None
        self.t_us: int | None = None
        self._queue: list[tuple[int, np.ndarray, np.ndarray]] = []  # sorted by stamp
        self._hold: tuple[np.ndarray, np.ndarray] | None = None
        self._hold_stamp = -(2**62)
        self._desc: dict[int, np.ndarray] = {}
        self._misses: dict[int, int] = {}
        self._patches: dict[int, _PatchRef] = {}
        self._last_range: tuple[int, float] | None = None
        self._facet_ids: np.ndarray | None = None  # lm_id of the altimeter facet in use
        self._frames_since_match = 0
        self.counters = SlamCounters(
            landmarks_added=dict.fromkeys(self.camera_names, 0),
            landmarks_deleted=dict.fromkeys(self.camera_names, 0),
            matches=dict.fromkeys(self.camera_names, 0),
        )

    # ------------------------------------------------------------------ set-up
    @property
    def started(self) -> bool:
        return self.ekf is not None

    def start(
        self, stamp_us: int, p_world: np.ndarray, v_world: np.ndarray, q_world_body: np.ndarray
    ) -> None:
        """Initialise the filter at ``stamp_us`` with the given state and ``EkfOptions`` priors."""
        self.ekf = InverseDepthEkf(self.opts, p_world, q_world_body, v_world, self.gravity_mps2)
        self.t_us = int(stamp_us)
        older = [s for s in self._queue if s[0] <= stamp_us]
        if older:
            self._hold, self._hold_stamp = (older[-1][1], older[-1][2]), older[-1][0]
        self._queue = [s for s in self._queue if s[0] > stamp_us]

    def restarted(self) -> VisThermalSlam:
        """A new, unstarted SLAM with the same options and cameras (no landmarks, no queued IMU) that keeps
        the flight's health counters and the last altimeter range (the depth prior of the first landmarks)."""
        slam = VisThermalSlam(self.opts, self.cameras, self.gravity_mps2)
        slam._last_range = self._last_range
        slam.counters = self.counters
        return slam

    # ------------------------------------------------------------------ inputs
    def add_imu(self, stamp_us: int, accel_mps2: np.ndarray, gyro_rps: np.ndarray) -> None:
        """Queue one IMU sample (body FRD specific force m/s^2 and rate rad/s)."""
        self.counters.imu += 1
        sample = (int(stamp_us), np.asarray(accel_mps2, float), np.asarray(gyro_rps, float))
        if self.t_us is not None and stamp_us <= self.t_us:
            self.counters.late_imu += 1
            if stamp_us > self._hold_stamp:  # newest information about the current interval
                self._hold, self._hold_stamp = (sample[1], sample[2]), sample[0]
            return
        keys = [s[0] for s in self._queue]
        self._queue.insert(bisect.bisect_right(keys, sample[0]), sample)
        horizon = self._queue[-1][0] - int(self.opts.imu_max_lag_s * 1e6)
        if self.ekf is not None:
            if self._queue[0][0] < horizon:
                self._propagate_to(horizon)
        else:
            # not started (no frame yet): keep only the lag window, the newest older sample becomes the hold
            while len(self._queue) > 1 and self._queue[0][0] < horizon:
                t, acc, gyr = self._queue.pop(0)
                self._hold, self._hold_stamp = (acc, gyr), t

    def latest_imu(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Most recent (accel, gyro) seen, for attitude initialisation from gravity."""
        if self._queue:
            return self._queue[-1][1], self._queue[-1][2]
        return self._hold

    def _propagate_to(self, stamp_us: int) -> None:
        assert self.ekf is not None and self.t_us is not None
        while self._queue and self._queue[0][0] <= stamp_us:
            t, acc, gyr = self._queue.pop(0)
            if t > self.t_us:
                self._step((t - self.t_us) * 1e-6)
                self.t_us = t
            self._hold, self._hold_stamp = (acc, gyr), t
        if stamp_us > self.t_us:
            self._step((stamp_us - self.t_us) * 1e-6)
            self.t_us = stamp_us

    def _step(self, dt: float) -> None:
        """Propagate ``dt`` s from ``t_us`` with the held IMU sample; a step that ends more than
        ``imu_hold_max_s`` after that sample (or with none yet) uses the constant-velocity motion model instead:
        no rotation, the velocity kept (the specific force that cancels gravity), and the motion's own noise."""
        assert self.ekf is not None and self.t_us is not None
        o = self.opts
        end_us = self.t_us + dt * 1e6
        if self._hold is None or end_us - self._hold_stamp > o.imu_hold_max_s * 1e6:
            self.counters.steps_without_imu += 1
            f = -self.ekf.R_world_body.T @ self.ekf.g_world
            density = (o.no_imu_accel_noise_density, o.no_imu_gyro_noise_density)
            self.ekf.propagate(f, np.zeros(3), dt, density)
        else:
            self.ekf.propagate(self._hold[0], self._hold[1], dt)

    def add_altimeter(self, stamp_us: int, range_m: float) -> None:
        """Range (m) along body down; kept for depth priors and used in a facet update (``altimeter``)."""
        if not np.isfinite(range_m) or range_m <= 0:
            return
        self._last_range = (int(stamp_us), float(range_m))
        if self.ekf is None or self.t_us is None:
            return
        if stamp_us > self.t_us:
            self._propagate_to(int(stamp_us))
        self._altimeter_update(float(range_m))

    def _altimeter_update(self, range_m: float) -> None:
        ekf = self.ekf
        assert ekf is not None
        if ekf.n_landmarks < 3:
            self.counters.altimeter_no_facet += 1
            return
        R = ekf.R_world_body
        # the previous facet while its three landmarks are alive, valid and still around the beam; else a
        # new Delaunay selection over the whole map
        idx = None
        previous = self._facet_ids
        if self._facet_ids is not None:
            # lm_id is increasing (ids are issued in order, deletion keeps the order)
            idx = np.minimum(np.searchsorted(ekf.lm_id, self._facet_ids), ekf.n_landmarks - 1)
            if np.any(ekf.lm_id[idx] != self._facet_ids) or np.any(ekf.y[idx, 5] <= 1e-6):
                idx = None
            else:
                pts = lmk.to_euclidean(ekf.y[idx])
                if not facet_encloses_beam(pts, ekf.r, R):
                    idx = None
        if idx is None:
            valid = ekf.y[:, 5] > 1e-6
            cand = np.flatnonzero(valid)
            pts_all = lmk.to_euclidean(ekf.y[cand])
            sel = select_facet(pts_all, ekf.r, R)
            if sel is None:
                self._facet_ids = None
                self.counters.altimeter_no_facet += 1
                return
            idx = cand[sel]
            pts = pts_all[sel]
            self._facet_ids = ekf.lm_id[idx].copy()
        fr = facet_range(pts, ekf.r, R, np.zeros(3))
        o = self.opts
        if o.facet_error_state and (previous is None or not np.array_equal(previous, ekf.lm_id[idx])):
            ekf.reset_facet_error(o.facet_error_rel_sigma * range_m)
        if fr is None:
            self.counters.altimeter_no_facet += 1
            return
        J = lmk.to_euclidean_jacobian(ekf.y[idx])  # (3,3,6)
        # H is non-zero only on the pose (dr, dtheta), the facet error and the altimeter bias when they are
        # states (measured = facet range + c + b, so +1 each) and the three facet landmarks: 24 to 26 columns
        lm_cols = (ekf.vdim + 6 * idx[:, None] + np.arange(6)).ravel()
        extra = ([IDX_C] if o.facet_error_state else []) + (
            [ekf.idx_bias] if ekf.idx_bias is not None else []
        )
        cols = np.concatenate([np.arange(6), np.asarray(extra, int), lm_cols])
        parts = [fr.H_pose[0], np.ones(len(extra))] + [fr.H_points[k] @ J[k] for k in range(len(idx))]
        H = np.concatenate(parts)[None, :]
        if o.facet_error_state:  # white part only: the facet's own error is c
            sigma2 = o.altimeter_sigma_m**2 + (o.altimeter_white_rel_sigma * range_m) ** 2
        else:
            sigma2 = o.altimeter_sigma_m**2 + (o.facet_rel_sigma * range_m) ** 2
        Rm = np.array([[sigma2]])
        S = ekf.innovation_covariance_columns(cols, H, Rm)
        res = np.array([range_m - (fr.range_m + ekf.facet_c)])
        if float(res @ np.linalg.solve(S, res)) > o.altimeter_gate_chi2:
            self.counters.altimeter_rejected += 1
            return
        ekf.update_columns(cols, H, res, Rm)
        self.counters.altimeter_updates += 1

    # ------------------------------------------------------------------ frames
    def process_frame(self, stamp_us: int, detections: dict[str, Detections]) -> SlamPose:
        """One frame (or synchronised pair): propagate to its stamp, match, update, delete, sample."""
        assert self.ekf is not None and self.t_us is not None, "call start() first"
        ekf = self.ekf
        self.counters.frames += 1
        if stamp_us < self.t_us:
            self.counters.stale_frames += 1
        else:
            self._propagate_to(int(stamp_us))
        o = self.opts
        R_wb = ekf.R_world_body
        matched_count = dict.fromkeys(self.camera_names, 0)
        # --- predict and match, per camera -------------------------------------------------------
        rows_lm: list[int] = []
        rows_Hp: list[np.ndarray] = []
        rows_Hl: list[np.ndarray] = []
        rows_res: list[np.ndarray] = []
        rows_cam: list[str] = []
        rows_patch: list[bool] = []
        rows_sigma: list[float] = []
        keep = np.ones(ekf.n_landmarks, bool)
        used_kp: dict[str, np.ndarray] = {}
        tracked_uv: dict[str, list[np.ndarray]] = {c: [] for c in self.camera_names}
        for ci, cam_name in enumerate(self.camera_names):
            cam = self.cameras[cam_name]
            det = detections.get(cam_name)
            idx = np.flatnonzero(ekf.lm_cam == ci)
            used = np.zeros(len(det) if det is not None else 0, bool)
            used_kp[cam_name] = used
            if len(idx) == 0:
                continue
            proj = lmk.project(ekf.y[idx], ekf.r, R_wb, cam)
            if o.first_estimate_jacobians:
                # FEJ: predicted pixels from the current estimate, Jacobians at the first landmark estimate
                pj = lmk.project(ekf.y_first[idx], ekf.r, R_wb, cam)
                proj = lmk.Projection(proj.uv, proj.depth, pj.H_pose, pj.H_lm)
            m = o.image_margin_px
            inside = (
                (proj.depth > 0)
                & (proj.uv[:, 0] >= m)
                & (proj.uv[:, 0] <= cam.width - 1 - m)
                & (proj.uv[:, 1] >= m)
                & (proj.uv[:, 1] <= cam.height - 1 - m)
                & (ekf.y[idx, 5] > 0)
            )
            keep[idx[~inside]] = False
            self.counters.deleted_out_of_view += int(np.sum(~inside))
            if det is None:
                # camera missing from this set: keep the in-view landmarks untouched
                continue
            vis = np.flatnonzero(inside)
            if len(vis) == 0:
                continue
            # innovation covariances S_i = H_i P H_i^T + R (2x2 each), from the sparse blocks
            gi = idx[vis]
            S = ekf.landmark_innovation_covariances(
                gi, proj.H_pose[vis], proj.H_lm[vis], o.pixel_sigma(cam_name)
            )
            lm_desc = np.stack([self._desc[int(ekf.lm_id[li])] for li in gi])
            match = match_predicted(
                proj.uv[vis], S, lm_desc, det, o.gate_chi2, o.max_descriptor_distance, o.descriptor_ratio
            )
            found = (
                self._patch_search(cam, gi, proj.uv[vis], S, match, det.image)
                if cam_name in o.patch_cameras and det.image is not None
                else {}
            )
            for k, li in enumerate(gi):
                lid = int(ekf.lm_id[li])
                j = match[k]
                if j >= 0:
                    rows_lm.append(int(li))
                    rows_Hp.append(proj.H_pose[vis[k]])
                    rows_Hl.append(proj.H_lm[vis[k]])
                    rows_res.append(det.uv[j] - proj.uv[vis[k]])
                    rows_cam.append(cam_name)
                    used[j] = True
                    if not o.anchor_descriptor:
                        self._desc[lid] = det.desc[j]
                    tracked_uv[cam_name].append(det.uv[j])
                    rows_patch.append(False)
                    size = None if det.size_px is None else float(det.size_px[j])
                    rows_sigma.append(o.match_sigma(cam_name, size))
                elif k in found:
                    rows_lm.append(int(li))
                    rows_Hp.append(proj.H_pose[vis[k]])
                    rows_Hl.append(proj.H_lm[vis[k]])
                    rows_res.append(found[k] - proj.uv[vis[k]])
                    rows_cam.append(cam_name)
                    tracked_uv[cam_name].append(found[k])
                    rows_patch.append(True)
                    rows_sigma.append(o.pixel_sigma(cam_name))
                else:
                    self._missed(int(li), keep)
                    if keep[li]:
                        tracked_uv[cam_name].append(proj.uv[vis[k]])
        # --- batch update with every camera's matches (one map, eq. 7) ---------------------------
        if rows_lm:
            lm_rows = np.array(rows_lm)
            accepted = self._update_matches(
                lm_rows, np.stack(rows_Hp), np.stack(rows_Hl), np.stack(rows_res), np.array(rows_sigma)
            )
            for li, cam_name, ok, by_patch in zip(lm_rows, rows_cam, accepted, rows_patch):
                if ok:
                    self._misses[int(ekf.lm_id[li])] = 0
                    matched_count[cam_name] += 1
                    self.counters.patch_matches += int(by_patch)
                else:
                    self._missed(int(li), keep)
        for ci, cam_name in enumerate(self.camera_names):
            self.counters.matches[cam_name] += matched_count[cam_name]
            self.counters.landmarks_deleted[cam_name] += int(np.sum(~keep & (ekf.lm_cam == ci)))
        for lid in ekf.lm_id[~keep]:
            self._desc.pop(int(lid), None)
            self._misses.pop(int(lid), None)
            self._patches.pop(int(lid), None)
        ekf.remove_landmarks(keep)
        # --- new landmarks (eq. 8) ------------------------------------------------------------------
        for ci, cam_name in enumerate(self.camera_names):
            det = detections.get(cam_name)
            if det is None or len(det) == 0:
                continue
            self._add_landmarks(ci, cam_name, det, used_kp[cam_name], tracked_uv[cam_name])
        self._frames_since_match = 0 if sum(matched_count.values()) > 0 else self._frames_since_match + 1
        return self.pose(int(stamp_us), matched_count)

    def _missed(self, li: int, keep: np.ndarray) -> None:
        """Landmark ``li`` was not matched (or its match was refused): delete it after too many in a row."""
        assert self.ekf is not None
        lid = int(self.ekf.lm_id[li])
        self._misses[lid] = self._misses.get(lid, 0) + 1
        if self._misses[lid] > self.opts.max_consecutive_misses and keep[li]:
            keep[li] = False
            self.counters.deleted_unmatched += 1

    def _patch_search(
        self,
        cam: lmk.CameraModel,
        gi: np.ndarray,
        pred_uv: np.ndarray,
        S: np.ndarray,
        match: np.ndarray,
        image: np.ndarray,
    ) -> dict[int, np.ndarray]:
        """Pixels found by patch search for the landmarks ``gi[k]`` SIFT left unmatched (``match[k] < 0``):
        {k: (2,) uv}. The first patch is warped by the local affine motion of the ground plane (horizontal,
        through the landmark's current estimate) from the camera that created it to the predicted one."""
        ekf = self.ekf
        assert ekf is not None
        o = self.opts
        cur_pose = camera_pose(ekf.R_world_body, ekf.r, cam.R_body_cam, cam.p_cam_in_body)
        found: dict[int, np.ndarray] = {}
        for k in np.flatnonzero(match < 0):
            ref = self._patches.get(int(ekf.lm_id[gi[k]]))
            if ref is None:
                continue
            X = lmk.to_euclidean(ekf.y[gi[k] : gi[k] + 1])[0]
            L = ground_plane_affine(X, cam.K, (ref.R_world_cam, ref.p_cam), cur_pose)
            if L is None:
                continue
            tmpl = warp_template(ref.patch, ref.origin, ref.uv, L, o.patch_half_px)
            uv = ncc_search(
                image,
                tmpl,
                pred_uv[k],
                S[k],
                o.gate_chi2,
                o.patch_max_radius_px,
                o.patch_min_score,
                o.patch_min_margin,
            )
            if uv is not None:
                found[int(k)] = uv
        return found

    def _update_matches(
        self, lm: np.ndarray, Hp: np.ndarray, Hl: np.ndarray, res: np.ndarray, sig: np.ndarray
    ) -> np.ndarray:
        """EKF update with the gated matches of every camera (k of them, sig: (k,) their pixel
        sigmas); returns (k,) bool, the ones used.

        Without ``one_point_ransac`` all of them, in one batch. With it (``ransac``): the low-innovation
        inliers in a first batch, then the others that pass their gate again against the corrected state
        (each on its own) in a second."""
        ekf = self.ekf
        assert ekf is not None
        o = self.opts
        k = len(lm)
        if not o.one_point_ransac or k < o.ransac_min_matches:
            ekf.update_landmarks(lm, Hp, Hl, res, sig)
            return np.ones(k, bool)
        PHt, HPHt = ekf.landmark_batch_terms(lm, Hp, Hl)
        low = low_innovation_inliers(HPHt, res, sig, o.ransac_threshold_px)
        # the first batch's terms are the rows / columns of the low-innovation ones (no second P H^T)
        rows = np.flatnonzero(np.repeat(low, 2))
        terms = (PHt[:, rows], HPHt[np.ix_(rows, rows)])
        dx = ekf.update_landmarks(lm[low], Hp[low], Hl[low], res[low], sig[low], terms)
        accepted = low.copy()
        rest = np.flatnonzero(~low)
        if len(rest):
            # high-innovation inliers: residuals moved by the correction (first order, H dx), gated with the
            # corrected covariance
            lm_dx = dx[ekf.vdim :].reshape(-1, lmk.LANDMARK_DIM)[lm[rest]]
            r2 = (
                res[rest]
                - np.einsum("kij,j->ki", Hp[rest], dx[:6])
                - np.einsum("kij,kj->ki", Hl[rest], lm_dx)
            )
            S2 = ekf.landmark_innovation_covariances(lm[rest], Hp[rest], Hl[rest], sig[rest])
            chi2 = np.einsum("ki,ki->k", r2, np.linalg.solve(S2, r2[:, :, None])[:, :, 0])
            high = rest[chi2 <= o.gate_chi2]
            if len(high):
                ekf.update_landmarks(lm[high], Hp[high], Hl[high], r2[chi2 <= o.gate_chi2], sig[high])
                accepted[high] = True
        self.counters.ransac_rejected += int(k - accepted.sum())
        return accepted

    def _other_cameras_uv(self, ci: int) -> np.ndarray:
        """(M, 2) pixels in camera ``ci``'s image of the other cameras' landmarks that project into it (in front
        of it, inside the image): with co-registered cameras, where their own keypoints are."""
        ekf = self.ekf
        assert ekf is not None
        idx = np.flatnonzero(ekf.lm_cam != ci)
        if len(idx) == 0:
            return np.zeros((0, 2))
        cam = self.cameras[self.camera_names[ci]]
        proj = lmk.project(ekf.y[idx], ekf.r, ekf.R_world_body, cam)
        uv = proj.uv
        inside = (
            (proj.depth > 0)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] <= cam.width - 1)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] <= cam.height - 1)
        )
        return np.asarray(uv[inside], float).reshape(-1, 2)

    def _add_landmarks(
        self,
        ci: int,
        cam_name: str,
        det: Detections,
        used: np.ndarray,
        tracked: list[np.ndarray],
    ) -> None:
        """New landmarks for camera ``ci`` (eq. 8) among its unused keypoints. ``tracked``: its own tracked
        landmarks' pixels. With ``diversity_over_map`` and KDE sampling the other cameras' landmarks in its
        image count in the diversity density too, but not in the separation from tracked points (the
        cameras are not matched against each other)."""
        ekf = self.ekf
        assert ekf is not None
        o = self.opts
        cam = self.cameras[cam_name]
        free = o.max_landmarks_per_camera - int(np.sum(ekf.lm_cam == ci))
        if free <= 0:
            return
        m = o.image_margin_px
        cand = (
            ~used
            & (det.uv[:, 0] >= m)
            & (det.uv[:, 0] <= cam.width - 1 - m)
            & (det.uv[:, 1] >= m)
            & (det.uv[:, 1] <= cam.height - 1 - m)
        )
        tracked_arr = np.asarray(tracked, float).reshape(-1, 2)
        if len(tracked_arr):
            d2 = np.min(np.sum((det.uv[:, None, :] - tracked_arr[None]) ** 2, axis=2), axis=1)
            cand &= d2 >= o.min_new_separation_px**2
        cidx = np.flatnonzero(cand)
        if len(cidx) == 0:
            return
        # near-duplicate keypoints (SIFT reports one blob at several orientations): keep the first
        uv_c = det.uv[cidx]
        _, first = np.unique(np.round(uv_c / 2.0), axis=0, return_index=True)
        cidx = cidx[np.sort(first)]
        # the other cameras' landmarks only where they are used: after the free-slot check, for KDE sampling
        others_uv = (
            self._other_cameras_uv(ci) if o.diversity_over_map and o.sampling == "kde" else np.zeros((0, 2))
        )
        map_uv = np.vstack([tracked_arr, others_uv]) if len(others_uv) else tracked_arr
        n_map = o.max_landmarks_per_camera * (len(self.camera_names) if len(others_uv) else 1)
        pick = sample_new_landmarks(
            det.uv[cidx],
            map_uv,
            free,
            o.sampling,
            self.rng,
            o.kde_min_bandwidth_px,
            budget_bandwidth(cam.width * cam.height, n_map),
            float(cam.width * cam.height),
        )
        if len(pick) == 0:
            return
        sel = cidx[pick]
        uv = det.uv[sel]
        rho0, sigma_rho = self._depth_prior(uv, cam)
        y, J_pose, J_uv = lmk.initialise(uv, rho0, ekf.r, ekf.R_world_body, cam)
        ids = ekf.add_landmarks(y, J_pose, J_uv, o.pixel_sigma(cam_name), sigma_rho, ci)
        image = det.image if cam_name in o.patch_cameras else None
        if image is not None:
            R_wc, p_cam = camera_pose(ekf.R_world_body, ekf.r, cam.R_body_cam, cam.p_cam_in_body)
        for lid, j in zip(ids, sel):
            # a copy: a row view would keep the whole frame's descriptor array alive as long as the landmark
            self._desc[int(lid)] = det.desc[j].copy()
            self._misses[int(lid)] = 0
            if image is not None:
                patch, origin = reference_patch(image, det.uv[j], o.patch_ref_half_px)
                self._patches[int(lid)] = _PatchRef(patch, origin, det.uv[j].copy(), R_wc, p_cam)
        self.counters.landmarks_added[cam_name] += len(ids)

    def _depth_prior(self, uv: np.ndarray, cam: lmk.CameraModel) -> tuple[np.ndarray, np.ndarray]:
        """Inverse-depth prior for new rays: flat ground at the altimeter's height, else Civera's default."""
        ekf = self.ekf
        assert ekf is not None
        o = self.opts
        n = len(uv)
        if self._last_range is None:
            return np.full(n, o.init_rho_no_altimeter), np.full(n, o.init_rho_sigma_no_altimeter)
        R_wb = ekf.R_world_body
        height = self._last_range[1] * max(R_wb[2, 2], 0.2)  # vertical height above the ground below
        K = cam.K
        h_cam = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(n)], axis=1)
        h_world = h_cam @ (R_wb @ cam.R_body_cam).T
        down = h_world[:, 2] / np.linalg.norm(h_world, axis=1)
        depth = height / np.maximum(down, 0.2)
        rho0 = 1.0 / depth
        return rho0, o.init_rho_rel_sigma * rho0

    # ------------------------------------------------------------------ output
    def pose(self, stamp_us: int, matched: dict[str, int] | None = None) -> SlamPose:
        """Current pose with the (6,6) position/attitude covariance (m^2, rad^2) in roll/pitch/yaw."""
        ekf = self.ekf
        assert ekf is not None
        P = ekf.covariance()
        R = rot_from_quat(ekf.q)
        rpy = rpy_from_rot(R)
        W = euler_rate_matrix(rpy)
        T = np.zeros((6, 6))
        T[:3, :3] = np.eye(3)
        T[3:, 3:] = W
        cov = T @ P[:6, :6] @ T.T
        cov = 0.5 * (cov + cov.T)
        nl = {c: int(np.sum(ekf.lm_cam == i)) for i, c in enumerate(self.camera_names)}
        return SlamPose(
            stamp_us=stamp_us,
            p_world=ekf.r.copy(),
            v_world=ekf.v.copy(),
            rpy_rad=rpy,
            covariance=cov,
            matched=dict(matched or dict.fromkeys(self.camera_names, 0)),
            n_landmarks=nl,
            position_sigma_max_m=ekf.position_sigma_max_m(),
            frames_since_match=self._frames_since_match,
        )
