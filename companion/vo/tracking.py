"""Frame-to-frame feature tracking (paper 1 section 4.2): pyramidal Lucas-Kanade between consecutive
frames with a forward-backward check, and corner detection (ORB as in the paper, or Shi-Tomasi) at key
frames to top the tracks up. Images are (H, W) uint8; points are (N, 2) float32 pixels (x right, y down).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class TrackerOptions:
    win_px: int = 15  # Lucas-Kanade window side
    pyramid_levels: int = 2  # pyramid levels above the full image (motion is a few pixels per frame)
    max_iterations: int = 30
    epsilon: float = 0.01  # LK convergence, pixels
    fb_check: bool = True  # track back and compare (doubles the cost; PnP RANSAC and the adjustment also
    # reject bad tracks)
    fb_max_px: float = 0.5  # forward-backward disagreement above this drops the track
    border_px: int = 8  # tracks closer than this to the image border are dropped
    detector: str = "gftt"  # "orb" (the paper's choice) or "gftt" (Shi-Tomasi corners); both tracked by KLT.
    # Measured on scene 08 (150 s circular): gftt 0.52 m / 8.9 m (terrain LBA / VO only), orb 0.54 / 11.5 m
    max_features: int = 300  # tracks kept alive; new corners fill up to this at key frames
    min_distance_px: int = 15  # minimum spacing between corners (and from existing tracks)
    gftt_quality: float = 0.005  # Shi-Tomasi quality level relative to the strongest corner
    orb_fast_threshold: int = 10
    blur_sigma_px: float = 1.0  # Gaussian pre-blur against sensor noise (0 = none): measured better on
    # the rendered frames (shot noise), at ~1 ms


def _criteria(options: TrackerOptions) -> tuple[int, int, float]:
    return (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, options.max_iterations, options.epsilon)


def prepare(image: np.ndarray, options: TrackerOptions) -> np.ndarray:
    """The image the tracker works on: uint8, optionally blurred (uint16 frames are scaled down)."""
    img = image
    if img.dtype != np.uint8:
        img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    if options.blur_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), options.blur_sigma_px)
    return img


def track(
    prev_img: np.ndarray,
    cur_img: np.ndarray,
    pts: np.ndarray,
    options: TrackerOptions = TrackerOptions(),
    predicted: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Track (N, 2) points from ``prev_img`` into ``cur_img``.

    predicted: (N, 2) initial guesses in ``cur_img`` (e.g. the rotation between the frames applied from the
    autopilot's attitude), so that a fast turn does not exceed what the pyramid can follow.
    Returns ((N, 2) float32 new positions, (N,) bool ok): ok requires LK convergence, a position inside
    the border and (``fb_check``) a forward-backward error below ``fb_max_px``.
    """
    n = len(pts)
    if n == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, bool)
    p0 = np.ascontiguousarray(pts, dtype=np.float32).reshape(-1, 1, 2)
    win = (options.win_px, options.win_px)
    crit = _criteria(options)
    if predicted is not None:
        guess = np.ascontiguousarray(predicted, dtype=np.float32).reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(
            prev_img,
            cur_img,
            p0,
            guess,
            winSize=win,
            maxLevel=options.pyramid_levels,
            criteria=crit,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
    else:
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(
            prev_img, cur_img, p0, None, winSize=win, maxLevel=options.pyramid_levels, criteria=crit
        )
    p1 = p1.reshape(-1, 2)
    ok = st1.ravel() == 1
    if options.fb_check:
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(
            cur_img,
            prev_img,
            p1.reshape(-1, 1, 2),
            None,
            winSize=win,
            maxLevel=options.pyramid_levels,
            criteria=crit,
        )
        fb = np.linalg.norm(p0b.reshape(-1, 2) - p0.reshape(-1, 2), axis=1)
        ok &= (st2.ravel() == 1) & (fb < options.fb_max_px)
    h, w = cur_img.shape[:2]
    b = options.border_px
    ok &= (p1[:, 0] >= b) & (p1[:, 0] < w - b) & (p1[:, 1] >= b) & (p1[:, 1] < h - b)
    return p1, ok


def detect(
    image: np.ndarray, existing: np.ndarray, n_wanted: int, options: TrackerOptions = TrackerOptions()
) -> np.ndarray:
    """Up to ``n_wanted`` new corners (M, 2) float32, at least ``min_distance_px`` from (N, 2) ``existing``
    points and from each other, away from the border. Strongest first."""
    if n_wanted <= 0:
        return np.zeros((0, 2), np.float32)
    h, w = image.shape[:2]
    mask = np.zeros((h, w), np.uint8)
    b = options.border_px + options.win_px // 2
    mask[b : h - b, b : w - b] = 255
    for x, y in np.asarray(existing, float).reshape(-1, 2):
        cv2.circle(mask, (int(round(x)), int(round(y))), options.min_distance_px, 0, -1)
    if options.detector == "orb":
        orb = cv2.ORB.create(
            nfeatures=4 * n_wanted,
            fastThreshold=options.orb_fast_threshold,
            edgeThreshold=b,
            scoreType=cv2.ORB_HARRIS_SCORE,
        )
        kps = orb.detect(image, mask)
        kps = sorted(kps, key=lambda k: -k.response)
        out: list[tuple[float, float]] = []
        occ = mask.copy()
        for k in kps:
            x, y = k.pt
            if occ[int(y), int(x)] == 0:
                continue
            out.append((x, y))
            cv2.circle(occ, (int(round(x)), int(round(y))), options.min_distance_px, 0, -1)
            if len(out) >= n_wanted:
                break
        return np.array(out, np.float32).reshape(-1, 2)
    if options.detector == "gftt":
        c = cv2.goodFeaturesToTrack(
            image, n_wanted, options.gftt_quality, options.min_distance_px, mask=mask, blockSize=7
        )
        if c is None:
            return np.zeros((0, 2), np.float32)
        c = c.reshape(-1, 2)
        # sub-pixel corner positions give sub-pixel tracks from the first frame
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.01)
        return cv2.cornerSubPix(image, c.copy(), (5, 5), (-1, -1), crit).astype(np.float32)
    raise ValueError(f"unknown detector {options.detector!r}, expected 'orb' or 'gftt'")
