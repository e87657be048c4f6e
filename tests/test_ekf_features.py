"""SIFT front end: thermal normalisation, detection, prediction-guided matching with Mahalanobis gating."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from companion.ekf.features import (
    Detections,
    SiftDetector,
    match_predicted,
    ncc_search,
    reference_patch,
    to_uint8,
    warp_template,
)
from companion.ekf.options import EkfOptions


def _texture(seed: int, shape=(480, 640)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = np.zeros(shape, np.float32)
    for sigma, w in ((2.0, 1.0), (6.0, 1.5), (15.0, 2.0)):
        img += w * cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), sigma) * sigma
    img = (img - img.min()) / (img.max() - img.min())
    return img


def test_to_uint8_stretches_thermal_counts_robustly():
    t = (10000 + 500 * _texture(0)).astype(np.uint16)  # ~100-105 K in centi-kelvin
    t[5, 5] = 65535  # hot pixel
    t[6, 6] = 0  # dead pixel
    out = to_uint8(t)
    assert out.dtype == np.uint8 and out.shape == t.shape
    assert np.percentile(out, 1) <= 1 and np.percentile(out, 99) >= 253
    assert out.std() > 40  # contrast survives the outliers
    vis = (255 * _texture(1)).astype(np.uint8)
    assert to_uint8(vis) is vis  # visible frames pass through untouched
    assert np.all(to_uint8(np.full((10, 10), 7, np.uint16)) == 0)  # flat frame: no division by zero


def test_sift_detects_and_scales_back():
    img = (255 * _texture(2)).astype(np.uint8)
    det = SiftDetector(EkfOptions(detect_scale=1.0), "visible").detect(img)
    assert 150 <= len(det) <= EkfOptions().sift_nfeatures_visible
    assert det.desc.shape == (len(det), 128) and det.desc.dtype == np.float32
    half = SiftDetector(EkfOptions(detect_scale=0.5), "visible").detect(img)
    assert len(half) > 50
    assert half.uv[:, 0].max() > 500 and half.uv[:, 1].max() > 380  # pixels in full-resolution units
    blank = SiftDetector(EkfOptions(), "visible").detect(np.zeros((480, 640), np.uint8))
    assert len(blank) == 0 and blank.desc.shape == (0, 128)


def test_active_search_recovers_a_known_shift():
    """Image shifted by (7, -4) px: predicting each keypoint at its shifted place finds the same blob."""
    img = (255 * _texture(3)).astype(np.uint8)
    shift = np.array([7.0, -4.0])
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    img2 = cv2.warpAffine(img, M, (640, 480), borderMode=cv2.BORDER_REFLECT)
    sift = SiftDetector(EkfOptions(), "visible")
    d1, d2 = sift.detect(img), sift.detect(img2)
    keep = (d1.uv[:, 0] > 20) & (d1.uv[:, 0] < 610) & (d1.uv[:, 1] > 20) & (d1.uv[:, 1] < 460)
    lm_uv, lm_desc = d1.uv[keep][:40], d1.desc[keep][:40]
    S = np.tile(np.eye(2) * 4.0, (len(lm_uv), 1, 1))
    m = match_predicted(lm_uv + shift, S, lm_desc, d2, 9.21, 250.0, 0.85)
    ok = m >= 0
    assert ok.sum() >= 25
    err = np.linalg.norm(d2.uv[m[ok]] - (lm_uv[ok] + shift), axis=1)
    assert np.median(err) < 0.5 and np.max(err) < 4.0
    assert len(set(m[ok].tolist())) == ok.sum()  # one keypoint per landmark
    # a wrong prediction (30 px off, tight gate) finds nothing rather than a wrong blob
    miss = match_predicted(lm_uv + shift + 30.0, S, lm_desc, d2, 9.21, 250.0, 0.85)
    assert np.sum(miss >= 0) <= 2


def test_matching_gate_ratio_and_one_to_one():
    desc = np.eye(4, 128, dtype=np.float32) * 500
    det = Detections(np.array([[100.0, 100.0], [103.0, 100.0], [300.0, 300.0], [100.0, 101.0]]), desc.copy())
    S = np.tile(np.eye(2) * 9.0, (3, 1, 1))
    # landmark 0 predicted at kp 0 with kp 0's descriptor; landmark 1 wants kp 0 too but its descriptor is
    # kp 3's; landmark 2 sits far from its keypoint (outside the gate)
    lm_desc = np.stack([desc[0], desc[3], desc[2]])
    pred = np.array([[100.0, 100.0], [100.0, 100.5], [200.0, 200.0]])
    m = match_predicted(pred, S, lm_desc, det, 9.21, 250.0, 0.85)
    assert m.tolist() == [0, 3, -1]
    # two equally good candidates inside the gate: the ratio test refuses to choose
    det2 = Detections(det.uv[:2], np.stack([desc[0], desc[0]]))
    assert match_predicted(pred[:1], S[:1], desc[:1], det2, 9.21, 250.0, 0.85).tolist() == [-1]


def test_each_camera_gets_its_own_sift_settings():
    """The thermal detector's lower contrast threshold finds more keypoints in a faint image than the visible
    settings do; each camera's keypoint cap holds; an unknown camera is refused."""
    faint = (110 + 60 * _texture(4)).astype(np.uint8)
    opts = EkfOptions(detect_scale=1.0, sift_nfeatures_visible=2000, sift_nfeatures_thermal=2000)
    n_vis = len(SiftDetector(opts, "visible").detect(faint))
    n_tir = len(SiftDetector(opts, "thermal").detect(faint))
    assert n_vis > 0 and n_tir > 5 * n_vis
    capped = EkfOptions(detect_scale=1.0, sift_nfeatures_visible=60, sift_nfeatures_thermal=40)
    assert len(SiftDetector(capped, "visible").detect(faint)) <= 60
    assert len(SiftDetector(capped, "thermal").detect(faint)) <= 40
    with pytest.raises(ValueError, match="camera"):
        SiftDetector(opts, "lidar")


def _affine(angle_deg: float, scale: float, shift: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(2,3) map reference pixel -> current pixel: rotate and scale about ``centre``, then shift."""
    a = np.deg2rad(angle_deg)
    L = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return np.hstack([L, (centre + shift - L @ centre)[:, None]])


@pytest.mark.parametrize("angle_deg, scale", [(0.0, 1.0), (12.0, 1.0), (-8.0, 1.15), (20.0, 0.85)])
def test_patch_search_finds_a_feature_after_a_known_rotation_scale_and_subpixel_shift(angle_deg, scale):
    """The reference image moved by a known affine map (sub-pixel shift included): the warped first patch is
    found where the map sends each feature, to 0.15 px, with the prediction off by a couple of pixels."""
    ref = (255 * _texture(4)).astype(np.uint8)
    A = _affine(angle_deg, scale, np.array([5.3, -3.7]), np.array([320.0, 240.0]))
    cur = cv2.warpAffine(ref, A, (640, 480), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    L_ref_from_cur = np.linalg.inv(A[:, :2])
    rng = np.random.default_rng(0)
    errors = []
    for _ in range(30):
        uv_ref = rng.uniform([200, 150], [440, 330])
        truth = A[:, :2] @ uv_ref + A[:, 2]
        patch, origin = reference_patch(ref, uv_ref, 21)
        template = warp_template(patch, origin, uv_ref, L_ref_from_cur, 7)
        pred = truth + rng.normal(0, 2.0, 2)
        uv = ncc_search(cur, template, pred, np.eye(2) * 9.0, 9.21, 24, 0.8, 0.05)
        assert uv is not None
        errors.append(np.linalg.norm(uv - truth))
    assert np.median(errors) < 0.15 and max(errors) < 0.5


def test_patch_search_refuses_flat_repeated_and_out_of_gate():
    rng = np.random.default_rng(1)
    tex = (255 * _texture(5)).astype(np.uint8)
    patch, origin = reference_patch(tex, np.array([300.0, 200.0]), 21)
    template = warp_template(patch, origin, np.array([300.0, 200.0]), np.eye(2), 7)
    # the feature is there, but the gate (1 px sigma around a point 12 px away) does not reach it
    assert ncc_search(tex, template, np.array([312.0, 200.0]), np.eye(2), 9.21, 24, 0.8, 0.05) is None
    assert ncc_search(tex, template, np.array([301.0, 200.0]), np.eye(2), 9.21, 24, 0.8, 0.05) is not None
    # a flat template: nothing to correlate
    flat = np.full((15, 15), 90.0, np.float32)
    assert ncc_search(tex, flat, np.array([300.0, 200.0]), np.eye(2) * 9.0, 9.21, 24, 0.8, 0.05) is None
    # vertical stripes 6 px apart: the same score at several places inside the gate
    x = np.arange(640)
    stripes = np.tile((128 + 100 * np.sin(2 * np.pi * x / 6.0)).astype(np.uint8), (480, 1))
    stripes = np.clip(stripes + rng.normal(0, 2, stripes.shape), 0, 255).astype(np.uint8)
    patch, origin = reference_patch(stripes, np.array([300.0, 200.0]), 21)
    template = warp_template(patch, origin, np.array([300.0, 200.0]), np.eye(2), 7)
    assert (
        ncc_search(stripes, template, np.array([300.0, 200.0]), np.eye(2) * 25.0, 9.21, 24, 0.8, 0.05) is None
    )
    # a different texture: no place correlates well enough
    other = (255 * _texture(6)).astype(np.uint8)
    assert ncc_search(other, template, np.array([300.0, 200.0]), np.eye(2) * 9.0, 9.21, 24, 0.8, 0.05) is None
