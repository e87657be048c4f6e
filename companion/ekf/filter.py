"""Error-state EKF with inverse-depth landmarks (paper 2 section 3.1).

Nominal state: r (3, world NED position of the body), q (4, R_world_body, Hamilton w,x,y,z),
v (3, world velocity), omega (3, body angular rate), b_a (3), b_g (3) accelerometer / gyro biases,
then N inverse-depth landmarks y_i (6 each, see ``landmarks``).
Error state (Solà's ESKF, local attitude error): dx = (dr, dtheta, dv, domega, db_a, db_g, dy_1..dy_N),
18 + 6N long; ``P`` is its covariance. With ``EkfOptions.facet_error_state`` the vehicle part has a 19th entry,
c (m), the error of the altimeter's facet model (see ``slam``), and with ``altimeter_bias_sigma_m`` > 0 one more,
the altimeter's constant range bias b (m), a consider state; both before the landmarks (``InverseDepthEkf.vdim``).

Consider state (Schmidt 1966, the "Schmidt-Kalman filter" of spacecraft navigation): b is in P and in every gain,
so the covariance carries what an unknown range offset does to the map's scale, but its estimate is never
corrected (it stays 0) and its variance never shrinks. In an update that is the ordinary one with the
correction of b set to 0 and P_bb restored; the other blocks (P_xx, P_xb) come out as the Schmidt form gives them.
Why not estimate b: it cannot be told from the facet errors, ~1 % of the range and renewed every ~2 s (estimated,
it wandered and made every mode less accurate; docs/benchmarks.md).

Propagation implements eqs. 1-4 with the IMU as control input:
    r += v dt + a dt^2/2,  v += a dt,  q = q (x) Exp(omega dt),  omega = omega_m - b_g,
    a = R(q) (f_m - b_a) + g.
Paper 2 writes eq. 2 as q + 1/2 omega (x) q dt; we use the exact body-frame exponential (same to
first order). The biases are an addition of ours (``EkfOptions.estimate_imu_bias``): the paper's
state has none, but any real MEMS IMU, and the simulated one, has them. With biases off their
blocks stay zero and the filter is the paper's.

Landmark measurement Jacobians may be evaluated at each landmark's first estimate (FEJ; Huang,
Mourikis, Roumeliotis, "Analysis and improvement of the consistency of extended Kalman filter based
SLAM", ICRA 2008): re-linearising a landmark at its changing estimate gives the filter spurious
information along the unobservable directions (global position, yaw), and with a biased gyro we
measured a position NEES of ~90 instead of 3 after 20 s of hover on the synthetic scene; with
first-estimate Jacobians it is ~2 (tests/test_ekf_filter.py checks this). ``y_first`` keeps them.

Landmarks are static, so propagation only touches the 18x18 vehicle block; the vehicle-landmark
cross terms are multiplied by the accumulated transition Phi once, just before the next update.
"""

from __future__ import annotations

import math

import numpy as np

from companion.ekf.landmarks import LANDMARK_DIM
from companion.ekf.options import EkfOptions
from companion.ekf.so3 import quat_exp, quat_mul, quat_normalised, rot_from_quat, skew

VEHICLE_DIM = 18
"""Error-state length of the vehicle's motion: dr, dtheta, dv, domega, db_a, db_g."""

IDX_R = slice(0, 3)
IDX_TH = slice(3, 6)
IDX_V = slice(6, 9)
IDX_W = slice(9, 12)
IDX_BA = slice(12, 15)
IDX_BG = slice(15, 18)
IDX_C = 18
"""Index of the facet model error c, when it is a state (``vdim`` 19)."""


def pixel_noise_blocks(sigma_px: float | np.ndarray, k: int) -> np.ndarray:
    """(k,2,2) sigma_i^2 I of k pixel measurements; sigma_px: one for all or (k,) (per camera)."""
    s2 = np.broadcast_to(np.asarray(sigma_px, float), (k,)) ** 2
    return s2[:, None, None] * np.eye(2)


class InverseDepthEkf:
    """The filter. Mutable: ``propagate``, ``update``, ``add_landmarks``, ``remove_landmarks``.

    Landmarks carry a camera index (``lm_cam``, (N,) int) and a unique id (``lm_id``, (N,) int).
    """

    def __init__(
        self,
        options: EkfOptions,
        p_world: np.ndarray,
        q_world_body: np.ndarray,
        v_world: np.ndarray,
        gravity_mps2: float,
    ) -> None:
        o = options
        self.opts = o
        self.r = np.asarray(p_world, float).copy()
        self.q = quat_normalised(np.asarray(q_world_body, float))
        self.v = np.asarray(v_world, float).copy()
        self.w = np.zeros(3)
        self.ba = np.zeros(3)
        self.bg = np.zeros(3)
        self.g_world = np.array([0.0, 0.0, gravity_mps2])
        self.y = np.zeros((0, LANDMARK_DIM))
        self.y_first = np.zeros((0, LANDMARK_DIM))  # first estimates, for FEJ measurement Jacobians
        self.lm_cam = np.zeros(0, dtype=int)
        self.lm_id = np.zeros(0, dtype=int)
        self._next_id = 0
        self.facet_c = 0.0  # m, the facet model error (a state only with facet_error_state)
        self.facet_c_sigma_m = 0.0  # m, its stationary sigma (set by ``reset_facet_error``)
        self.vdim = (
            VEHICLE_DIM + (1 if o.facet_error_state else 0) + (1 if o.altimeter_bias_sigma_m > 0 else 0)
        )
        """Error-state length of the vehicle: 18, +1 with the facet error, +1 with the altimeter bias; landmarks
        follow it."""
        self.idx_bias: int | None = self.vdim - 1 if o.altimeter_bias_sigma_m > 0 else None
        """Column of the altimeter bias (a consider state, the vehicle part's last), None without it."""
        P = np.zeros((self.vdim, self.vdim))
        P[IDX_R, IDX_R] = np.eye(3) * o.initial_position_sigma_m**2
        P[IDX_V, IDX_V] = np.eye(3) * o.initial_velocity_sigma_mps**2
        P[IDX_W, IDX_W] = np.eye(3) * (o.gyro_bias_sigma0**2 + 1e-6)
        if o.estimate_imu_bias:
            P[IDX_BA, IDX_BA] = np.eye(3) * o.accel_bias_sigma0**2
            P[IDX_BG, IDX_BG] = np.eye(3) * o.gyro_bias_sigma0**2
        # dtheta is in body axes; the prior is on world tilt and yaw: yaw is about world down = R^T e3
        # (the filter's own share of the yaw prior: ``EkfOptions.filter_yaw_sigma_rad``)
        yaw_dir = rot_from_quat(self.q)[2, :]
        yaw_sigma = min(o.initial_yaw_sigma_rad, o.filter_yaw_sigma_rad)
        P[IDX_TH, IDX_TH] = np.eye(3) * o.initial_tilt_sigma_rad**2 + np.outer(yaw_dir, yaw_dir) * (
            yaw_sigma**2 - o.initial_tilt_sigma_rad**2
        )
        if self.idx_bias is not None:
            P[self.idx_bias, self.idx_bias] = o.altimeter_bias_sigma_m**2
        self.P = P
        self._Phi = np.eye(self.vdim)
        self._phi_pending = False
        # see _dt_terms: ((dt, noise_density), F_dt, Q) of the last step
        self._dt_cache: tuple[tuple[float, tuple[float, float] | None], np.ndarray, np.ndarray] = (
            (float("nan"), None),
            P,
            P,
        )

    # ------------------------------------------------------------------ accessors
    @property
    def n_landmarks(self) -> int:
        return len(self.y)

    @property
    def R_world_body(self) -> np.ndarray:
        return rot_from_quat(self.q)

    def lm_slice(self, i: int) -> slice:
        """Columns of landmark i in the error state."""
        s = self.vdim + LANDMARK_DIM * i
        return slice(s, s + LANDMARK_DIM)

    def covariance(self) -> np.ndarray:
        """The full (vdim+6N)^2 covariance with the pending propagation applied."""
        self._flush()
        return self.P

    # ------------------------------------------------------------------ propagation (eqs. 1-4)
    def propagate(
        self,
        f_body: np.ndarray,
        omega_body: np.ndarray,
        dt: float,
        noise_density: tuple[float, float] | None = None,
    ) -> None:
        """Advance by ``dt`` seconds with IMU specific force f_body (3,) m/s^2 and rate omega_body (3,) rad/s.
        noise_density: (accel, gyro) white-noise densities in place of the options' IMU ones (a motion model
        standing in for a missing IMU)."""
        if dt <= 0.0:
            return
        o = self.opts
        R = rot_from_quat(self.q)
        a_b = f_body - self.ba
        w = omega_body - self.bg
        a_w = R @ a_b + self.g_world
        self.r = self.r + self.v * dt + 0.5 * a_w * dt * dt  # eq. 1
        self.v = self.v + a_w * dt  # eq. 3
        dq = quat_exp(w * dt)
        self.q = quat_normalised(quat_mul(self.q, dq))  # eq. 2
        self.w = w  # eq. 4
        # error-state transition (Solà 2017, eq. 269 with the rate as a state); the entries that depend on
        # dt only come from a per-dt template (the IMU loop runs this 100-200 times a second: np.eye and
        # block assembly dominated it), the attitude-dependent blocks are written in place
        F_dt, Q = self._dt_terms(dt, noise_density)
        F = F_dt.copy()
        Rax = R @ skew(a_b)
        F[IDX_R, IDX_TH] = (-0.5 * dt * dt) * Rax
        F[IDX_V, IDX_TH] = -dt * Rax
        F[IDX_TH, IDX_TH] = rot_from_quat(dq).T  # Exp(w dt)^T
        if o.estimate_imu_bias:
            F[IDX_R, IDX_BA] = (-0.5 * dt * dt) * R
            F[IDX_V, IDX_BA] = -dt * R
        if o.facet_error_state and o.facet_error_tau_s > 0:
            # first-order Gauss-Markov: c decays toward 0 with time constant tau, stationary sigma kept
            phi = math.exp(-dt / o.facet_error_tau_s)
            F[IDX_C, IDX_C] = phi
            self.facet_c *= phi
            Q = Q.copy()
            Q[IDX_C, IDX_C] = self.facet_c_sigma_m**2 * (1.0 - phi * phi)
        V = self.vdim
        self.P[:V, :V] = F @ self.P[:V, :V] @ F.T + Q
        if self.n_landmarks:
            self._Phi = F @ self._Phi
            self._phi_pending = True

    def _dt_terms(
        self, dt: float, noise_density: tuple[float, float] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(F_dt, Q): the transition's entries that depend on dt only (vdim,vdim) and the discrete process noise
        of one step (vdim,vdim): accel white noise -> dv, dr; gyro white noise -> dtheta, domega; bias random
        walks (the facet error's entries are set in ``propagate``). Cached for the last dt (the IMU period
        rarely changes)."""
        if self._dt_cache[0] == (dt, noise_density):
            return self._dt_cache[1], self._dt_cache[2]
        o = self.opts
        accel_density, gyro_density = (
            (o.accel_noise_density, o.gyro_noise_density) if noise_density is None else noise_density
        )
        I3 = np.eye(3)
        F = np.eye(self.vdim)
        F[IDX_R, IDX_V] = I3 * dt
        F[IDX_W, IDX_W] = 0.0
        if o.estimate_imu_bias:
            F[IDX_TH, IDX_BG] = -dt * I3
            F[IDX_W, IDX_BG] = -I3
        else:
            F[IDX_BA, IDX_BA] = 0.0
            F[IDX_BG, IDX_BG] = 0.0
        qa = accel_density**2 / dt
        qg = gyro_density**2 / dt
        Q = np.zeros((self.vdim, self.vdim))
        Q[IDX_V, IDX_V] = I3 * (qa * dt * dt)
        Q[IDX_R, IDX_R] = I3 * (qa * 0.25 * dt**4)
        Q[IDX_R, IDX_V] = Q[IDX_V, IDX_R] = I3 * (qa * 0.5 * dt**3)
        Q[IDX_TH, IDX_TH] = I3 * (qg * dt * dt)
        Q[IDX_W, IDX_W] = I3 * qg
        Q[IDX_TH, IDX_W] = Q[IDX_W, IDX_TH] = I3 * (qg * dt)
        if o.estimate_imu_bias:
            Q[IDX_BA, IDX_BA] = I3 * (o.accel_bias_walk**2 * dt)
            Q[IDX_BG, IDX_BG] = I3 * (o.gyro_bias_walk**2 * dt)
        self._dt_cache = ((dt, noise_density), F, Q)
        return F, Q

    def _flush(self) -> None:
        """Apply the accumulated transition to the vehicle-landmark cross covariance."""
        if self._phi_pending:
            V = self.vdim
            self.P[:V, V:] = self._Phi @ self.P[:V, V:]
            self.P[V:, :V] = self.P[:V, V:].T
            self._Phi = np.eye(V)
            self._phi_pending = False

    # ------------------------------------------------------------------ update
    def update(self, H: np.ndarray, residual: np.ndarray, R_meas: np.ndarray) -> np.ndarray:
        """EKF update with Jacobian H (m, vdim+6N), residual z - h (m,), noise covariance R_meas (m, m).

        Returns the applied error-state correction (vdim+6N,). Joseph-free form, symmetrised.
        """
        self._flush()
        PHt = self.P @ H.T
        return self._correct(PHt, H @ PHt + R_meas, residual)

    def _correct(self, PHt: np.ndarray, S: np.ndarray, residual: np.ndarray) -> np.ndarray:
        """Gain K = P H^T S^-1, P -= K H P (symmetrised), inject K r; returns the correction K r."""
        K = np.linalg.solve(S, PHt.T).T
        dx = K @ residual
        P_bb = self._consider_variance()
        self.P = self.P - K @ PHt.T
        self.P = 0.5 * (self.P + self.P.T)
        self._consider_restore(P_bb, dx)
        self._inject(dx)
        return dx

    def _consider_variance(self) -> float:
        """P_bb of the consider state before an update (NaN without one)."""
        return float(self.P[self.idx_bias, self.idx_bias]) if self.idx_bias is not None else math.nan

    def _consider_restore(self, P_bb: float, dx: np.ndarray) -> None:
        """Schmidt update of the consider state: no correction, its variance as it was (see the module doc)."""
        if self.idx_bias is not None:
            self.P[self.idx_bias, self.idx_bias] = P_bb
            dx[self.idx_bias] = 0.0

    def update_columns(
        self, cols: np.ndarray, H_cols: np.ndarray, residual: np.ndarray, R_meas: np.ndarray
    ) -> np.ndarray:
        """``update`` for a Jacobian that is zero outside the error-state columns ``cols`` (c,): H_cols is
        its (m, c) non-zero part. Same result as the dense form, without the (m, n) H and its n^2 products.

        Returns the correction (vdim+6N,)."""
        self._flush()
        cols = np.asarray(cols, int)
        PHt = self.P[:, cols] @ H_cols.T  # (n, m)
        S = H_cols @ PHt[cols] + R_meas
        if len(S) == 1:
            # scalar measurement (the altimeter): P -= b b^T with b = P H^T / sqrt(S), in place; b b^T is
            # exactly symmetric, so only the vehicle block (propagated as F P F^T + Q) is symmetrised
            s = float(S[0, 0])
            dx = PHt[:, 0] * (float(residual[0]) / s)
            b = PHt[:, 0] * (1.0 / math.sqrt(s))
            P_bb = self._consider_variance()
            self.P -= np.outer(b, b)
            V = self.vdim
            self.P[:V, :V] = 0.5 * (self.P[:V, :V] + self.P[:V, :V].T)
            self._consider_restore(P_bb, dx)
            self._inject(dx)
            return dx
        return self._correct(PHt, S, residual)

    def innovation_covariance_columns(
        self, cols: np.ndarray, H_cols: np.ndarray, R_meas: np.ndarray
    ) -> np.ndarray:
        """S = H P H^T + R (m, m) for H zero outside ``cols`` (see ``update_columns``)."""
        self._flush()
        cols = np.asarray(cols, int)
        return H_cols @ self.P[np.ix_(cols, cols)] @ H_cols.T + R_meas

    def _landmark_columns(self, lm_index: np.ndarray) -> np.ndarray:
        """(k,12) error-state columns (dr, dtheta, then the landmark's 6) of each landmark's 2-row block."""
        lm = self.vdim + LANDMARK_DIM * np.asarray(lm_index, int)[:, None] + np.arange(LANDMARK_DIM)
        return np.concatenate([np.tile(np.arange(6), (len(lm), 1)), lm], axis=1)

    def landmark_innovation_covariances(
        self, lm_index: np.ndarray, H_pose: np.ndarray, H_lm: np.ndarray, sigma_px: float | np.ndarray
    ) -> np.ndarray:
        """(k,2,2) S_i = H_i P H_i^T + sigma_i^2 I of one pixel measurement per landmark, from the 12x12 blocks
        of P that the sparse H_i touches. H_pose, H_lm: (k,2,6); sigma_px: one for all or (k,)."""
        self._flush()
        cols = self._landmark_columns(lm_index)
        Pk = self.P[cols[:, :, None], cols[:, None, :]]  # (k,12,12)
        Hk = np.concatenate([H_pose, H_lm], axis=2)  # (k,2,12)
        return Hk @ Pk @ Hk.transpose(0, 2, 1) + pixel_noise_blocks(sigma_px, len(lm_index))

    def landmark_batch_terms(
        self, lm_index: np.ndarray, H_pose: np.ndarray, H_lm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(P H^T (n, 2k), H P H^T (2k, 2k)) of one pixel measurement (2 rows) per landmark, from the sparse
        blocks (P H^T by gathering 12 columns per landmark). lm_index: (k,); H_pose, H_lm: (k,2,6)."""
        self._flush()
        k = len(lm_index)
        cols = self._landmark_columns(lm_index)  # (k,12)
        Hk = np.concatenate([H_pose, H_lm], axis=2)  # (k,2,12)
        n = self.P.shape[0]
        # P H^T: (n, 2k); column pair i = P[:, cols_i] @ Hk_i^T
        PHt = np.einsum("nkc,kic->nki", self.P[:, cols.ravel()].reshape(n, k, 12), Hk).reshape(n, 2 * k)
        # H P H^T: row pair i = Hk_i @ PHt[cols_i, :]
        HPHt = np.einsum("kic,kcm->kim", Hk, PHt[cols]).reshape(2 * k, 2 * k)
        return PHt, 0.5 * (HPHt + HPHt.T)

    def update_landmarks(
        self,
        lm_index: np.ndarray,
        H_pose: np.ndarray,
        H_lm: np.ndarray,
        residual: np.ndarray,
        sigma_px: float | np.ndarray,
        terms: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Batch update with one pixel measurement (2 rows) per landmark; same result as ``update`` with the
        dense H, computed from the sparse blocks (``landmark_batch_terms``).

        lm_index: (k,); H_pose, H_lm: (k,2,6); residual: (k,2) z - h; sigma_px: one or (k,). terms: ``landmark_batch_terms`` of
        these very landmarks on the current state, when the caller has them already (else computed).
        Returns the correction."""
        k = len(lm_index)
        PHt, HPHt = self.landmark_batch_terms(lm_index, H_pose, H_lm) if terms is None else terms
        R = np.diag(np.repeat(np.broadcast_to(np.asarray(sigma_px, float), (k,)) ** 2, 2))
        return self._correct(PHt, HPHt + R, residual.reshape(2 * k))

    def innovation_covariance(self, H: np.ndarray, R_meas: np.ndarray) -> np.ndarray:
        """S = H P H^T + R for a candidate measurement (m, m)."""
        self._flush()
        return H @ self.P @ H.T + R_meas

    def _inject(self, dx: np.ndarray) -> None:
        self.r = self.r + dx[IDX_R]
        self.q = quat_normalised(quat_mul(self.q, quat_exp(dx[IDX_TH])))
        self.v = self.v + dx[IDX_V]
        self.w = self.w + dx[IDX_W]
        if self.opts.estimate_imu_bias:
            self.ba = self.ba + dx[IDX_BA]
            self.bg = self.bg + dx[IDX_BG]
        if self.opts.facet_error_state:
            self.facet_c += float(dx[IDX_C])
        if self.n_landmarks:
            self.y = self.y + dx[self.vdim :].reshape(-1, LANDMARK_DIM)
        # Solà's reset Jacobian (I - [dtheta/2]x) is ~I for the small corrections seen here; omitted.

    # ------------------------------------------------------------------ landmarks
    def add_landmarks(
        self,
        y_new: np.ndarray,
        J_pose: np.ndarray,
        J_uv: np.ndarray,
        sigma_px: float,
        sigma_rho: np.ndarray,
        cam_index: int,
    ) -> np.ndarray:
        """Append (k,6) landmarks with their initialisation Jacobians (see ``landmarks.initialise``).

        P_new,new = Jp P_pose Jp^T + Ju R_px Ju^T + sigma_rho^2 e6 e6^T, P_new,x = Jp P_pose,x.
        Landmarks of one batch are correlated through the pose. Returns the new ids (k,).
        """
        self._flush()
        k = len(y_new)
        if k == 0:
            return np.zeros(0, dtype=int)
        n = self.P.shape[0]
        pose_rows = self.P[0:6, :]  # (6, n): dr, dtheta rows
        Jp = J_pose.reshape(k * LANDMARK_DIM, 6)
        cross = Jp @ pose_rows  # (6k, n)
        Pnn = Jp @ self.P[0:6, 0:6] @ Jp.T
        Ju = J_uv * sigma_px
        for i in range(k):
            s = slice(LANDMARK_DIM * i, LANDMARK_DIM * (i + 1))
            Pnn[s, s] += Ju[i] @ Ju[i].T
            Pnn[LANDMARK_DIM * i + 5, LANDMARK_DIM * i + 5] += sigma_rho[i] ** 2
        P = np.zeros((n + LANDMARK_DIM * k, n + LANDMARK_DIM * k))
        P[:n, :n] = self.P
        P[n:, :n] = cross
        P[:n, n:] = cross.T
        P[n:, n:] = Pnn
        self.P = P
        self.y = np.concatenate([self.y, y_new], axis=0)
        self.y_first = np.concatenate([self.y_first, y_new], axis=0)
        ids = np.arange(self._next_id, self._next_id + k)
        self._next_id += k
        self.lm_cam = np.concatenate([self.lm_cam, np.full(k, cam_index, dtype=int)])
        self.lm_id = np.concatenate([self.lm_id, ids])
        return ids

    def remove_landmarks(self, keep: np.ndarray) -> None:
        """Keep only landmarks where ``keep`` (N,) bool is True (landmark deletion)."""
        keep = np.asarray(keep, bool)
        if keep.all():
            return
        self._flush()
        cols = np.concatenate(
            [np.arange(self.vdim), self.vdim + (np.flatnonzero(keep)[:, None] * 6 + np.arange(6)).ravel()]
        )
        self.P = self.P[np.ix_(cols, cols)]
        self.y = self.y[keep]
        self.y_first = self.y_first[keep]
        self.lm_cam = self.lm_cam[keep]
        self.lm_id = self.lm_id[keep]

    def reset_facet_error(self, sigma_m: float) -> None:
        """A new facet: its model error is independent of the last one's, c = 0 with variance sigma_m^2."""
        self._flush()
        self.P[IDX_C, :] = 0.0
        self.P[:, IDX_C] = 0.0
        self.P[IDX_C, IDX_C] = sigma_m**2
        self.facet_c = 0.0
        self.facet_c_sigma_m = float(sigma_m)

    def is_finite(self) -> bool:
        return bool(
            np.all(np.isfinite(self.r))
            and np.all(np.isfinite(self.q))
            and np.all(np.isfinite(self.v))
            and np.all(np.isfinite(self.P))
            and np.all(np.isfinite(self.y))
            and math.isfinite(self.facet_c)
        )

    def position_sigma_max_m(self) -> float:
        """Largest 1-sigma position uncertainty (m), from the position block's largest eigenvalue."""
        return math.sqrt(max(0.0, float(np.linalg.eigvalsh(self.P[IDX_R, IDX_R])[-1])))
