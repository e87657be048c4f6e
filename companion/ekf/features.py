"""SIFT detection and prediction-guided matching (paper 2 section 3.2). No cross-modal matching:
each camera's landmarks are matched only against that camera's keypoints.

SIFT is OpenCV's ``cv2.SIFT.create`` (= ``cv2.SIFT_create``) with the settings in ``EkfOptions`` (sift_*), per
camera: the best 800 (visible) / 400 (thermal) keypoints by contrast, contrast threshold 0.02 (visible; half
OpenCV's 0.04, because icy scenes are low in contrast) / 0.005 (thermal: the diffused temperature field is
smoother still), 3 layers per octave (Lowe), edge threshold 10 and sigma 1.6 (OpenCV / Lowe defaults).
Visible frames are used as they come (8-bit grey; the paper applies no other pre-processing).
Thermal frames (uint16 counts) are stretched per frame to 8 bit between the 1st and 99th percentile
(``to_uint8``): robust to a few dead or hot pixels and independent of the camera's absolute scale.

Matching is active search (Davison; Civera et al. 2008): each landmark's predicted pixel and 2x2
innovation covariance S define a Mahalanobis gate; among the keypoints inside it, the nearest
descriptor wins if it passes an absolute distance threshold and Lowe's ratio test against the
second-nearest gated candidate; a keypoint claimed by two landmarks goes to the closer descriptor.

Patch search (optional, ``EkfOptions.patch_cameras``): a landmark with no SIFT match is looked for with the
image patch cut around its keypoint when it was created (``reference_patch``), warped to the predicted view
(``warp_template``) and correlated inside the same gate (``ncc_search``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.ekf.options import EkfOptions
from companion.geometry import project


@dataclass(frozen=True)
class Detections:
    """Keypoints of one image. uv: (N,2) float64 pixels (full-resolution image); desc: (N,128) float32;
    size_px: (N,) SIFT keypoint diameter in full-resolution pixels (None when unknown); image: the (H,W)
    8-bit full-resolution image they were found in, for the patch search (None: no patch search)."""

    uv: np.ndarray
    desc: np.ndarray
    size_px: np.ndarray | None = None
    image: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.uv)


def to_uint8(image: np.ndarray, low_percentile: float = 1.0, high_percentile: float = 99.0) -> np.ndarray:
    """8-bit version of an image for SIFT: uint8 passes through, anything else is percentile-stretched."""
    if image.dtype == np.uint8:
        return image
    img = image.astype(np.float32)
    lo, hi = np.percentile(img, [low_percentile, high_percentile])
    if not np.isfinite(lo) or not np.isfinite(hi) or hi <= lo:
        return np.zeros(image.shape, np.uint8)
    out = (img - lo) * (255.0 / (hi - lo))
    return np.clip(out, 0.0, 255.0).astype(np.uint8)


class SiftDetector:
    """One SIFT instance per camera (OpenCV detectors keep buffers; do not share between threads), with that
    camera's settings (``EkfOptions.sift_settings``)."""

    def __init__(self, options: EkfOptions, camera: str) -> None:
        o = options
        nfeatures, contrast = o.sift_settings(camera)
        self._sift = cv2.SIFT.create(
            nfeatures=nfeatures,
            nOctaveLayers=o.sift_octave_layers,
            contrastThreshold=contrast,
            edgeThreshold=o.sift_edge_threshold,
            sigma=o.sift_sigma,
        )
        self._scale = float(o.detect_scale)
        self._pct = (o.thermal_low_percentile, o.thermal_high_percentile)

    def detect(self, image: np.ndarray) -> Detections:
        """SIFT keypoints and descriptors of a (H,W) uint8 or uint16 image."""
        img = full = to_uint8(image, *self._pct)
        if self._scale != 1.0:
            img = cv2.resize(img, None, fx=self._scale, fy=self._scale, interpolation=cv2.INTER_AREA)
        kps, desc = self._sift.detectAndCompute(img, None)
        if desc is None or len(kps) == 0:
            return Detections(np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0), full)
        uv = np.array([k.pt for k in kps], dtype=np.float64)
        size = np.array([k.size for k in kps], dtype=np.float64)
        if self._scale != 1.0:
            # resized pixel centres: u_full = (u_small + 0.5) / s - 0.5
            uv = (uv + 0.5) / self._scale - 0.5
            size = size / self._scale
        return Detections(uv, desc.astype(np.float32), size, full)


def match_predicted(
    pred_uv: np.ndarray,
    S: np.ndarray,
    lm_desc: np.ndarray,
    det: Detections,
    gate_chi2: float,
    max_descriptor_distance: float,
    ratio: float,
) -> np.ndarray:
    """Active-search matching. pred_uv (L,2), S (L,2,2), lm_desc (L,128) -> (L,) keypoint index or -1."""
    L = len(pred_uv)
    out = np.full(L, -1, dtype=int)
    if L == 0 or len(det) == 0:
        return out
    Sinv = np.linalg.inv(S)
    diff = det.uv[None, :, :] - pred_uv[:, None, :]  # (L,K,2)
    dx, dy = diff[..., 0], diff[..., 1]
    maha = (
        Sinv[:, 0, 0, None] * dx * dx
        + (Sinv[:, 0, 1] + Sinv[:, 1, 0])[:, None] * dx * dy
        + Sinv[:, 1, 1, None] * dy * dy
    )
    gated = maha <= gate_chi2
    if not gated.any():
        return out
    a2 = np.sum(lm_desc.astype(np.float64) ** 2, axis=1)[:, None]
    b2 = np.sum(det.desc.astype(np.float64) ** 2, axis=1)[None, :]
    dd = np.sqrt(np.maximum(a2 + b2 - 2.0 * lm_desc.astype(np.float64) @ det.desc.T.astype(np.float64), 0.0))
    dd = np.where(gated, dd, np.inf)
    order = np.argsort(dd, axis=1)
    best = order[:, 0]
    d1 = dd[np.arange(L), best]
    d2 = dd[np.arange(L), order[:, 1]] if dd.shape[1] > 1 else np.full(L, np.inf)
    ok = (d1 <= max_descriptor_distance) & (d1 < ratio * d2)
    # one keypoint, one landmark: the smallest descriptor distance keeps it
    for li in np.argsort(np.where(ok, d1, np.inf)):
        if not ok[li]:
            break
        if best[li] in out:
            continue
        out[li] = best[li]
    return out


# --- patch search: the fallback for a landmark SIFT did not find again ------------------------------------
# Hand-written on OpenCV's warpAffine / matchTemplate: MonoSLAM's active search with a feature's first patch,
# warped by the predicted motion (Davison et al., T-PAMI 2007, section 3.4; Civera et al. 2008 keep it), has
# no library implementation.


def reference_patch(image: np.ndarray, uv: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """The (2 half + 1)^2 pixels of ``image`` around the integer pixel nearest ``uv`` (border replicated) and
    the pixel coordinates of the patch's pixel (0, 0) in the image."""
    c = np.round(np.asarray(uv, float))
    size = 2 * half + 1
    patch = cv2.getRectSubPix(image, (size, size), (float(c[0]), float(c[1])))
    return patch, c - half


def ground_plane_affine(
    X: np.ndarray,
    K: np.ndarray,
    ref_pose: tuple[np.ndarray, np.ndarray],
    cur_pose: tuple[np.ndarray, np.ndarray],
) -> np.ndarray | None:
    """(2,2) map of a small pixel offset in the current image to the reference image around world point X
    (3,): the local affine motion of a horizontal ground plane through X, from three points ~10 px apart
    projected into both cameras (poses (R_world_cam, p_cam_in_world)). None if a point is behind a camera or
    the plane is seen edge-on."""
    step = 10.0 * float(np.linalg.norm(X - cur_pose[1])) / float(K[0, 0])
    P = X + np.array([[0.0, 0.0, 0.0], [step, 0.0, 0.0], [0.0, step, 0.0]])
    uv_ref, z_ref = project(K, *ref_pose, P)
    uv_cur, z_cur = project(K, *cur_pose, P)
    if np.any(z_ref <= 1e-9) or np.any(z_cur <= 1e-9):
        return None
    D_cur = (uv_cur[1:] - uv_cur[0]).T
    if abs(np.linalg.det(D_cur)) < 1.0:
        return None
    return (uv_ref[1:] - uv_ref[0]).T @ np.linalg.inv(D_cur)


def warp_template(
    patch: np.ndarray, origin: np.ndarray, feature_uv: np.ndarray, L_ref_from_cur: np.ndarray, half: int
) -> np.ndarray:
    """A (2 half + 1)^2 float32 template of the feature as the current camera should see it.

    ``patch`` was cut from the reference image with its pixel (0, 0) at ``origin``; the feature is at
    ``feature_uv`` there. ``L_ref_from_cur`` (2,2) maps a small pixel offset in the current image to the
    reference image (the inverse of the predicted local affine motion). The template's centre pixel is the
    feature."""
    M = np.zeros((2, 3))
    M[:, :2] = L_ref_from_cur
    M[:, 2] = (
        np.asarray(feature_uv, float) - np.asarray(origin, float) - L_ref_from_cur @ np.array([half, half])
    )
    size = 2 * half + 1
    return cv2.warpAffine(
        patch.astype(np.float32),
        M,
        (size, size),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )


def ncc_search(
    image: np.ndarray,
    template: np.ndarray,
    pred_uv: np.ndarray,
    S: np.ndarray,
    gate_chi2: float,
    max_radius_px: int,
    min_score: float,
    min_margin: float,
) -> np.ndarray | None:
    """Where ``template``'s centre is in ``image``: the best normalised cross-correlation inside the
    Mahalanobis gate of ``pred_uv`` (innovation covariance S, (2,2)), refined to sub-pixel by a parabola per
    axis. None when the template is flat, the best score is below ``min_score``, or another local maximum
    scores within ``min_margin`` of it (a repeated texture)."""
    if float(np.std(template)) < 1.0:
        return None
    half = template.shape[0] // 2
    lam = float(np.linalg.eigvalsh(S)[-1])
    r = int(min(np.ceil(np.sqrt(gate_chi2 * lam)), max_radius_px))
    c = np.round(np.asarray(pred_uv, float))
    size = 2 * (r + half) + 1
    window = cv2.getRectSubPix(image, (size, size), (float(c[0]), float(c[1]))).astype(np.float32)
    score = cv2.matchTemplate(window, template.astype(np.float32), cv2.TM_CCOEFF_NORMED)  # (2r+1, 2r+1)
    off = np.arange(-r, r + 1, dtype=float)
    dx = c[0] + off[None, :] - pred_uv[0]
    dy = c[1] + off[:, None] - pred_uv[1]
    Si = np.linalg.inv(S)
    maha = Si[0, 0] * dx * dx + (Si[0, 1] + Si[1, 0]) * dx * dy + Si[1, 1] * dy * dy
    score = np.where((maha <= gate_chi2) & np.isfinite(score), score, -np.inf)
    i, j = np.unravel_index(int(np.argmax(score)), score.shape)
    best = float(score[i, j])
    if not best >= min_score:
        return None
    # another local maximum (3 x 3) nearly as good: a repeated texture, the place is ambiguous
    peaks = score >= cv2.dilate(np.where(np.isfinite(score), score, -2.0).astype(np.float32), np.ones((3, 3)))
    peaks[max(i - 1, 0) : i + 2, max(j - 1, 0) : j + 2] = False
    if np.any(score[peaks] >= best - min_margin):
        return None

    def vertex(a: float, b: float, cc: float) -> float:
        den = a - 2.0 * b + cc
        if not (np.isfinite(a) and np.isfinite(cc)) or den >= 0:
            return 0.0
        return float(np.clip(0.5 * (a - cc) / den, -0.5, 0.5))

    n = score.shape[0]
    sx = vertex(score[i, j - 1], best, score[i, j + 1]) if 0 < j < n - 1 else 0.0
    sy = vertex(score[i - 1, j], best, score[i + 1, j]) if 0 < i < n - 1 else 0.0
    return np.array([c[0] + off[j] + sx, c[1] + off[i] + sy])
