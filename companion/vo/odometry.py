"""Monocular visual odometry by frame-to-frame tracking (paper 1 section 4.2), aided by the autopilot's
attitude and the altimeter.

Per frame: Lucas-Kanade tracking of the live features, then the camera pose by PnP (EPnP in RANSAC, LM
refinement) on the tracked map points (eq. 12). At key frames (``keyframes.py``): new map points are
triangulated from their first key-frame observation and the current one, and new corners are detected
to keep ``max_features`` tracks alive. The map (key-frame poses, points, key-frame observations) is what
the local bundle adjustment refines; ``apply_correction`` writes its result back.

Initialisation: from the first frame (pose known: the initial position and the autopilot's attitude)
until the features have moved ``init_parallax_px``; the displacement direction comes from the epipolar
constraint, the second view's rotation refined from the matches with the autopilot's attitude as its prior
(``geometry.relative_pose_rotation_prior``), and its length from the altimeter range (the depth of the
ground at the image centre): monocular scale is fixed there, once.

World frame NED; poses ``T_world_cam`` (4, 4). Pure math (numpy + OpenCV), no I/O.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from companion.geometry import make_T
from companion.vo.geometry import (
    PnpOptions,
    TriangulationOptions,
    TwoViewOptions,
    relative_pose_rotation_prior,
    reproject,
    solve_pnp,
    triangulate,
)
from companion.vo.keyframes import KeyframeOptions, is_keyframe
from companion.vo.tracking import TrackerOptions, detect, prepare, track


@dataclass(frozen=True)
class VoOptions:
    tracker: TrackerOptions = field(default_factory=TrackerOptions)
    pnp: PnpOptions = field(default_factory=PnpOptions)
    triangulation: TriangulationOptions = field(default_factory=TriangulationOptions)
    two_view: TwoViewOptions = field(default_factory=TwoViewOptions)
    keyframes: KeyframeOptions = field(default_factory=KeyframeOptions)
    init_parallax_px: float = 25.0  # median feature displacement that triggers the two-view initialisation
    init_max_frames: int = 200  # give up (restart from the current frame) after this many frames
    init_min_points: int = 40  # triangulated points needed to accept the initialisation
    init_centre_points: int = 30  # points nearest the image centre whose median depth meets the altimeter
    max_keyframes_kept: int = 60  # older key frames (and points only they see) are forgotten
    # a key frame's gravity direction (the adjustment's roll / pitch prior) from the autopilot attitude of
    # this many recent tracked frames, each carried into the key frame by the VO's rotation since: averages
    # the attitude's frame-to-frame noise (1 = the key frame's own sample only)
    gravity_frames: int = 1


@dataclass
class KeyFrame:
    """A key frame of the map. T_world_cam (4, 4) is refined by the bundle adjustment."""

    kf_id: int
    frame_index: int
    stamp_us: int
    T_world_cam: np.ndarray
    down_cam: np.ndarray  # (3,) gravity in the camera frame from the autopilot's attitude (NaN if none)
    ids: np.ndarray  # (N,) track ids observed here
    px: np.ndarray  # (N, 2) their pixels
    # (N,) False where the adjustment dropped the observation as an outlier (``VisualOdometry.obs`` no longer
    # holds it); the window snapshot reads these arrays rather than walking ``obs`` point by point
    valid: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def __post_init__(self) -> None:
        if len(self.valid) != len(self.ids):
            self.valid = np.ones(len(self.ids), bool)


@dataclass(frozen=True)
class VoStatus:
    """Outcome of one frame. state: "initialising", "tracking" or "lost". T_world_cam: (4, 4) or None.
    n_tracks: live tracks; n_inliers: PnP inliers; keyframe_id: set when the frame became a key frame."""

    state: str
    T_world_cam: np.ndarray | None
    n_tracks: int
    n_inliers: int
    keyframe_id: int | None
    rms_px: float = float("nan")


@dataclass(frozen=True)
class WindowSnapshot:
    """The map part a local bundle adjustment needs (indices refer to these arrays).

    kf_ids: (M,); T_world_cam: (M, 4, 4); anchor: (M,) bool (outside the window); down_cam: (M, 3);
    lm_ids: (L,); p_world: (L, 3); obs_kf, obs_lm: (O,) indices; obs_px: (O, 2).
    """

    kf_ids: np.ndarray
    T_world_cam: np.ndarray
    anchor: np.ndarray
    down_cam: np.ndarray
    lm_ids: np.ndarray
    p_world: np.ndarray
    obs_kf: np.ndarray
    obs_lm: np.ndarray
    obs_px: np.ndarray


def down_in_cam(R_world_cam: np.ndarray | None) -> np.ndarray:
    """(3,) world down (NED +z) in the camera frame, NaN without an attitude."""
    if R_world_cam is None:
        return np.full(3, np.nan)
    return R_world_cam.T @ np.array([0.0, 0.0, 1.0])


def gravity_in_cam(R_world_cam: np.ndarray, downs_world: list[np.ndarray] | deque[np.ndarray]) -> np.ndarray:
    """(3,) unit world-down in the camera frame of ``R_world_cam`` from several frames' views of it.

    downs_world: per frame j, the down direction its attitude sample gives, put in the VO's world frame,
    R_vo_j R_att_j^T e_z (R_vo: the VO's R_world_cam, R_att: the autopilot's). A tilt of the whole map cancels
    (it is in R_vo_j and in R_world_cam alike); the attitude's noise averages out; the VO's rotation error
    between frame j and this one enters. No library does this three-line average: written here."""
    g = np.mean(np.asarray(downs_world, float), axis=0)
    return R_world_cam.T @ (g / np.linalg.norm(g))


def tilt_toward(T_world_cam: np.ndarray, down_cam: np.ndarray, weight: float, depth_m: float) -> np.ndarray:
    """(4, 4) the camera pose turned so that its world-down moves ``weight`` (0..1) of the way to ``down_cam``.

    down_cam: (3,) unit world-down in this camera's frame from another source (the attitude average). The turn
    is the smallest one (about a horizontal axis: no yaw) and pivots about the point ``depth_m`` along the
    optical axis, the ground the camera sees: a nadir camera's tilt and its sideways position trade for the
    same image, so the ground point stays and the camera moves by depth x angle."""
    R, p = T_world_cam[:3, :3], T_world_cam[:3, 3]
    d_vo = R.T @ np.array([0.0, 0.0, 1.0])
    axis = np.cross(d_vo, down_cam)
    angle = np.arctan2(np.linalg.norm(axis), float(d_vo @ down_cam))
    if angle < 1e-12:
        return T_world_cam.copy()
    # B turns d_vo toward down_cam in the camera frame; the new camera R' = R B^T has R'^T e_z = B d_vo
    B = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle * weight).as_matrix()
    Q = R @ B.T @ R.T  # the same turn in the world frame
    c = p + R[:, 2] * depth_m
    out = np.eye(4)
    out[:3, :3] = Q @ R
    out[:3, 3] = c + Q @ (p - c)
    return out


class VisualOdometry:
    """Tracks a nadir camera. Call ``process`` once per frame, in capture order."""

    def __init__(self, options: VoOptions, K: np.ndarray) -> None:
        self.opt = options
        self.K = np.asarray(K, float)
        self.frame_index = -1
        self.state = "initialising"
        self.T: np.ndarray | None = None  # current camera pose
        self.kfs: dict[int, KeyFrame] = {}
        self.lm: dict[int, np.ndarray] = {}  # track id -> (3,) world point, for triangulated tracks
        self.lm_born_kf: dict[int, int] = {}  # key frame at which the point was triangulated
        self.obs: dict[int, dict[int, np.ndarray]] = {}  # track id -> {kf id: (2,) pixel}
        self._prev: np.ndarray | None = None
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._next_id = 0
        self._next_kf = 0
        self._last_kf_frame = 0
        self._init: dict | None = None
        self._p_start: np.ndarray | None = None
        self._R_prev: np.ndarray | None = None
        self._gravity: deque[np.ndarray] = deque(maxlen=max(int(options.gravity_frames), 1))

    # ------------------------------------------------------------------------------------------------
    # public

    @property
    def last_kf(self) -> KeyFrame | None:
        return self.kfs[max(self.kfs)] if self.kfs else None

    def averaged_down(self) -> np.ndarray | None:
        """(3,) world down in the current camera frame from the recent frames' attitude (``gravity_frames``)."""
        if self.T is None or not self._gravity:
            return None
        return gravity_in_cam(self.T[:3, :3], self._gravity)

    def reset(self) -> None:
        """Forget the map and start a new initialisation at the next frame."""
        self.state = "initialising"
        self.T = None
        self.kfs.clear()
        self.lm.clear()
        self.lm_born_kf.clear()
        self.obs.clear()
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._init = None
        self._gravity.clear()

    def process(
        self,
        image: np.ndarray,
        stamp_us: int,
        R_att: np.ndarray | None,
        range_m: float | None,
        p_cam_init: np.ndarray | None,
    ) -> VoStatus:
        """One frame. R_att: camera attitude R_world_cam from the autopilot (or None); range_m: altimeter range
        along the optical axis (or None); p_cam_init: camera position to (re)start from while initialising
        (remembered: None keeps the last one given)."""
        self.frame_index += 1
        if p_cam_init is not None:
            self._p_start = np.asarray(p_cam_init, float)
        img = prepare(image, self.opt.tracker)
        if self._prev is not None and len(self._pts):
            pred = None
            R_prev = (
                self._R_prev if self._R_prev is not None else (None if self.T is None else self.T[:3, :3])
            )
            if R_att is not None and R_prev is not None:
                # rotation-only prediction (the infinite homography): the features' motion in a fast turn
                H = self.K @ R_att.T @ R_prev @ np.linalg.inv(self.K)
                h = np.c_[self._pts, np.ones(len(self._pts))] @ H.T
                pred = h[:, :2] / h[:, 2:]
            pts, ok = track(self._prev, img, self._pts, self.opt.tracker, pred)
            self._pts, self._ids = pts[ok], self._ids[ok]
        self._prev = img
        self._R_prev = R_att
        if self.state != "tracking":
            return self._initialise(img, stamp_us, R_att, range_m, self._p_start)
        return self._track(img, stamp_us, R_att)

    def snapshot(self, window_size: int, max_anchors: int) -> WindowSnapshot:
        """The last ``window_size`` key frames, the map points they see, and up to ``max_anchors`` older key
        frames that also see them (held fixed-ish by the adjustment). Observations are ordered by point, then
        key frame; a point needs two of them in the snapshot.

        Built from the key frames' arrays (``ids``, ``px``, ``valid``) with numpy: it runs on the per-frame
        path (the frame after a key frame), where walking ``obs`` point by point cost 6-12 ms per window."""
        kf_sorted = sorted(self.kfs)
        win = kf_sorted[-window_size:]
        win_set = set(win)
        kfs = [self.kfs[k] for k in kf_sorted]
        seen = np.unique(np.concatenate([kf.ids for kf in kfs[-window_size:]]))
        lm_ids = np.array([t for t in seen.tolist() if t in self.lm], np.int64)
        # every key frame's observations in one array, tagged with the key frame's position in kf_sorted
        a_t = np.concatenate([kf.ids for kf in kfs]).astype(np.int64)
        a_pos = np.repeat(np.arange(len(kfs)), [len(kf.ids) for kf in kfs])
        sees = np.concatenate([kf.valid for kf in kfs]) & np.isin(a_t, lm_ids)
        n_seen = np.bincount(a_pos[sees], minlength=len(kfs))
        older = [k for k, n in zip(kf_sorted, n_seen) if k not in win_set and n > 0]
        anchors = sorted(older, reverse=True)[:max_anchors]
        kf_ids = sorted(anchors) + win
        slot = np.full(len(kfs), -1, np.int64)  # position in kf_sorted -> index in kf_ids (-1: not taken)
        pos_of = {k: i for i, k in enumerate(kf_sorted)}
        slot[[pos_of[k] for k in kf_ids]] = np.arange(len(kf_ids))
        m = sees & (slot[a_pos] >= 0)
        o_kf = slot[a_pos[m]]
        o_px = np.concatenate([kf.px for kf in kfs]).reshape(-1, 2)[m]
        o_j = np.searchsorted(lm_ids, a_t[m])
        keep = np.bincount(o_j, minlength=len(lm_ids)) >= 2
        new_j = np.cumsum(keep) - 1
        m = keep[o_j]
        o_kf, o_j, o_px = o_kf[m], new_j[o_j[m]], o_px[m]
        order = np.lexsort((o_kf, o_j))  # by point, then key frame (the key frames are in id order)
        keep_lm = lm_ids[keep]
        anchor = np.array([k not in win_set for k in kf_ids], bool)
        return WindowSnapshot(
            np.array(kf_ids, np.int64),
            np.stack([self.kfs[k].T_world_cam for k in kf_ids]),
            anchor,
            np.stack([self.kfs[k].down_cam for k in kf_ids]),
            keep_lm,
            np.stack([self.lm[int(t)] for t in keep_lm]) if len(keep_lm) else np.zeros((0, 3)),
            o_kf[order],
            o_j[order],
            np.asarray(o_px[order], float),
        )

    def apply_correction(
        self,
        snapshot_newest_kf: int,
        T_align: np.ndarray,
        kf_ids: np.ndarray,
        T_world_cam: np.ndarray,
        lm_ids: np.ndarray,
        p_world: np.ndarray,
        outlier_kf: np.ndarray,
        outlier_lm: np.ndarray,
    ) -> np.ndarray:
        """Write an adjustment back. Everything of the map not in the solution is first moved by ``T_align``
        (eq. 21 re-alignment, identity if none); the solved key frames and points take their new values;
        key frames, points and the current pose created after ``snapshot_newest_kf`` follow the correction
        of that key frame. Outlier observations (key-frame id, point id) are dropped. Returns the (4, 4)
        correction applied to the current pose."""
        T_old_newest = (
            self.kfs[snapshot_newest_kf].T_world_cam.copy() if snapshot_newest_kf in self.kfs else None
        )
        solved_kf = {int(k) for k in kf_ids}
        solved_lm = {int(t) for t in lm_ids}
        R_a, t_a = T_align[:3, :3], T_align[:3, 3]
        if not np.allclose(T_align, np.eye(4)):
            for k, kf in self.kfs.items():
                if k not in solved_kf and k <= snapshot_newest_kf:
                    kf.T_world_cam = T_align @ kf.T_world_cam
            for t, p in self.lm.items():
                if t not in solved_lm and self.lm_born_kf.get(t, -1) <= snapshot_newest_kf:
                    self.lm[t] = R_a @ p + t_a
        for k, T in zip(kf_ids, T_world_cam):
            if int(k) in self.kfs:
                self.kfs[int(k)].T_world_cam = np.array(T, float)
        for t, p in zip(lm_ids, p_world):
            if int(t) in self.lm:
                self.lm[int(t)] = np.array(p, float)
        C = np.eye(4)
        if T_old_newest is not None:
            C = self.kfs[snapshot_newest_kf].T_world_cam @ np.linalg.inv(T_old_newest)
        R_c, t_c = C[:3, :3], C[:3, 3]
        for k, kf in self.kfs.items():
            if k > snapshot_newest_kf:
                kf.T_world_cam = C @ kf.T_world_cam
        for t in self.lm:
            if self.lm_born_kf.get(t, -1) > snapshot_newest_kf:
                self.lm[t] = R_c @ self.lm[t] + t_c
        if self.T is not None:
            self.T = C @ self.T
        # the recent frames' gravity follows the current pose it will be compared with
        self._gravity = deque((R_c @ g for g in self._gravity), maxlen=self._gravity.maxlen)
        for k, t in zip(outlier_kf, outlier_lm):
            o = self.obs.get(int(t))
            if o is not None:
                if o.pop(int(k), None) is not None and int(k) in self.kfs:
                    kf = self.kfs[int(k)]
                    kf.valid[kf.ids == int(t)] = False
                if len(o) < 2 and int(t) in self.lm:
                    # too few consistent views left: the track goes back to being a candidate
                    del self.lm[int(t)]
                    self.lm_born_kf.pop(int(t), None)
        return C

    # ------------------------------------------------------------------------------------------------
    # initialisation

    def _detect_more(self, img: np.ndarray) -> None:
        n_new = self.opt.tracker.max_features - len(self._pts)
        new = detect(img, self._pts, n_new, self.opt.tracker)
        if len(new):
            ids = np.arange(self._next_id, self._next_id + len(new), dtype=np.int64)
            self._next_id += len(new)
            self._pts = np.concatenate([self._pts, new.astype(np.float32)])
            self._ids = np.concatenate([self._ids, ids])

    def _initialise(
        self,
        img: np.ndarray,
        stamp_us: int,
        R_att: np.ndarray | None,
        range_m: float | None,
        p_cam_init: np.ndarray | None,
    ) -> VoStatus:
        st = self._init
        restart = st is None or self.frame_index - st["frame"] > self.opt.init_max_frames
        if restart:
            if R_att is None or range_m is None or p_cam_init is None:
                return VoStatus("initialising", None, len(self._pts), 0, None)
            self._pts = np.zeros((0, 2), np.float32)
            self._ids = np.zeros(0, np.int64)
            self._detect_more(img)
            self._init = {
                "frame": self.frame_index,
                "stamp": stamp_us,
                "T0": make_T(R_att, np.asarray(p_cam_init, float)),
                "range0": float(range_m),
                "ids0": self._ids.copy(),
                "px0": self._pts.copy(),
            }
            return VoStatus("initialising", None, len(self._pts), 0, None)
        assert st is not None
        if R_att is None or len(self._ids) < self.opt.init_min_points:
            if len(self._ids) < self.opt.init_min_points:
                self._init = None  # lost the features: start again
            return VoStatus("initialising", None, len(self._pts), 0, None)
        pos0 = {int(t): i for i, t in enumerate(st["ids0"])}
        i0 = np.array([pos0[int(t)] for t in self._ids])
        px0 = st["px0"][i0].astype(float)
        px1 = self._pts.astype(float)
        T0 = st["T0"]
        # parallax: displacement left once the rotation between the views is undone (the multicopter
        # tilts by tens of degrees when it accelerates in low gravity)
        H = self.K @ R_att.T @ T0[:3, :3] @ np.linalg.inv(self.K)
        h = np.c_[px0, np.ones(len(px0))] @ H.T
        flow = np.median(np.linalg.norm(px1 - h[:, :2] / h[:, 2:], axis=1))
        if flow < self.opt.init_parallax_px:
            return VoStatus("initialising", None, len(self._pts), 0, None)
        R1, d, inl = relative_pose_rotation_prior(self.K, T0[:3, :3], R_att, px0, px1, self.opt.two_view)
        if inl.sum() < self.opt.init_min_points:
            self._init = None
            return VoStatus("initialising", None, len(self._pts), 0, None)
        T1u = make_T(R1, T0[:3, 3] + d)
        # unit baseline: depth limits do not apply yet (the scale comes next)
        unit = replace(self.opt.triangulation, min_depth_m=1e-9, max_depth_m=np.inf)
        X, ok = triangulate(self.K, T0, T1u, px0, px1, unit)
        ok &= inl
        if ok.sum() < self.opt.init_min_points:
            return VoStatus("initialising", None, len(self._pts), 0, None)
        # scale: the depth of the ground at the image centre (median over the points nearest to it)
        # must equal the altimeter range measured at the first frame
        _, z0 = reproject(self.K, T0, X[ok])
        r_c = np.linalg.norm(px0[ok] - self.K[:2, 2], axis=1)
        near = np.argsort(r_c)[: self.opt.init_centre_points]
        scale = st["range0"] / float(np.median(z0[near]))
        c0 = T0[:3, 3]
        T1 = make_T(R1, c0 + scale * d)
        X = c0 + scale * (X - c0)
        # two key frames and the first map points
        self._add_kf(st["frame"], st["stamp"], T0, down_in_cam(T0[:3, :3]), st["ids0"], st["px0"])
        kf1 = self._add_kf(self.frame_index, stamp_us, T1, down_in_cam(R_att), self._ids, self._pts)
        for t, p in zip(self._ids[ok], X[ok]):
            self.lm[int(t)] = p
            self.lm_born_kf[int(t)] = kf1
        self.T = T1
        self.state = "tracking"
        self._init = None
        self._last_kf_frame = self.frame_index
        self._detect_more(img)
        self._register_new_tracks(kf1)
        return VoStatus("tracking", T1.copy(), len(self._pts), int(ok.sum()), kf1)

    # ------------------------------------------------------------------------------------------------
    # tracking

    def _add_kf(
        self,
        frame_index: int,
        stamp_us: int,
        T: np.ndarray,
        down_cam: np.ndarray,
        ids: np.ndarray,
        px: np.ndarray,
    ) -> int:
        k = self._next_kf
        self._next_kf += 1
        self.kfs[k] = KeyFrame(k, frame_index, stamp_us, T.copy(), down_cam, ids.copy(), px.astype(float))
        for t, p in zip(ids, px):
            self.obs.setdefault(int(t), {})[k] = np.asarray(p, float)
        return k

    def _register_new_tracks(self, k: int) -> None:
        """Tracks detected at key frame ``k`` after it was created get their first observation there."""
        kf = self.kfs[k]
        have = set(int(t) for t in kf.ids)
        new = np.array([int(t) not in have for t in self._ids], bool)
        if new.any():
            kf.ids = np.concatenate([kf.ids, self._ids[new]])
            kf.px = np.concatenate([kf.px, self._pts[new].astype(float)])
            kf.valid = np.concatenate([kf.valid, np.ones(int(new.sum()), bool)])
            for t, p in zip(self._ids[new], self._pts[new]):
                self.obs.setdefault(int(t), {})[k] = np.asarray(p, float)

    def _track(self, img: np.ndarray, stamp_us: int, R_att: np.ndarray | None) -> VoStatus:
        has = np.array([int(t) in self.lm for t in self._ids], bool)
        n_lm = int(has.sum())
        if n_lm < self.opt.pnp.min_inliers:
            self.state = "lost"
            return VoStatus("lost", None, len(self._pts), 0, None)
        P = np.stack([self.lm[int(t)] for t in self._ids[has]])
        res = solve_pnp(self.K, P, self._pts[has], self.opt.pnp)
        if not res.ok:
            self.state = "lost"
            return VoStatus("lost", None, len(self._pts), 0, None)
        self.T = res.T_world_cam
        if R_att is not None:
            # world down as the autopilot saw it, in the world frame of the VO (R_vo R_att^T e_z)
            self._gravity.append(self.T[:3, :3] @ down_in_cam(R_att))
        # PnP outliers: drop the track (the point keeps its key-frame observations for the adjustment)
        keep = np.ones(len(self._ids), bool)
        keep[np.flatnonzero(has)[~res.inliers]] = False
        self._pts, self._ids = self._pts[keep], self._ids[keep]
        n_inl = int(res.inliers.sum())
        ref = self.last_kf
        assert ref is not None
        ref_ids = set(int(t) for t in ref.ids if int(t) in self.lm)
        n_ref_tracked = sum(1 for t in self._ids if int(t) in ref_ids)
        since = self.frame_index - self._last_kf_frame
        kf_id = None
        if is_keyframe(since, n_inl, n_ref_tracked, len(ref_ids), self.opt.keyframes):
            kf_id = self._make_keyframe(img, stamp_us, R_att)
        return VoStatus("tracking", self.T.copy(), len(self._pts), n_inl, kf_id, res.rms_px)

    def _make_keyframe(self, img: np.ndarray, stamp_us: int, R_att: np.ndarray | None) -> int:
        assert self.T is not None
        down = down_in_cam(R_att)
        if R_att is not None and len(self._gravity) > 1:
            down = gravity_in_cam(self.T[:3, :3], self._gravity)
        k = self._add_kf(self.frame_index, stamp_us, self.T, down, self._ids, self._pts)
        self._last_kf_frame = self.frame_index
        # triangulate candidate tracks from their first key-frame view and this one
        cand = [i for i, t in enumerate(self._ids) if int(t) not in self.lm]
        if cand:
            firsts = []
            for i in cand:
                o = self.obs.get(int(self._ids[i]))
                if not o:
                    continue
                k0 = min(o)
                firsts.append((i, k0, o[k0]))
            by_kf: dict[int, list[tuple[int, np.ndarray]]] = {}
            for i, k0, px0 in firsts:
                if k0 != k and k0 in self.kfs:
                    by_kf.setdefault(k0, []).append((i, px0))
            for k0, items in by_kf.items():
                idx = np.array([i for i, _ in items])
                px0 = np.stack([p for _, p in items])
                X, ok = triangulate(
                    self.K,
                    self.kfs[k0].T_world_cam,
                    self.T,
                    px0,
                    self._pts[idx].astype(float),
                    self.opt.triangulation,
                )
                for i, p in zip(idx[ok], X[ok]):
                    t = int(self._ids[i])
                    self.lm[t] = p
                    self.lm_born_kf[t] = k
        self._detect_more(img)
        self._register_new_tracks(k)
        self._forget_old()
        return k

    def _forget_old(self) -> None:
        if len(self.kfs) <= self.opt.max_keyframes_kept:
            return
        live = set(int(t) for t in self._ids)
        for k in sorted(self.kfs)[: len(self.kfs) - self.opt.max_keyframes_kept]:
            kf = self.kfs.pop(k)
            for t in kf.ids:
                o = self.obs.get(int(t))
                if o is None:
                    continue
                o.pop(k, None)
                if not o and int(t) not in live:
                    del self.obs[int(t)]
                    self.lm.pop(int(t), None)
                    self.lm_born_kf.pop(int(t), None)
