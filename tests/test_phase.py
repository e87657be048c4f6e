"""Phase correlation core: sub-pixel shifts, sign convention, quality, Fourier-Mellin."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from companion.georef import phase


def _texture(rng: np.random.Generator, n: int, blur: float) -> np.ndarray:
    return cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), blur)


def _fourier_shift(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Exact band-limited (circular) shift: out(x, y) = img(x - dx, y - dy)."""
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None, :]
    return np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * (fx * dx + fy * dy))).real


def test_circular_subpixel_shift_is_exact() -> None:
    rng = np.random.default_rng(1)
    ref = _texture(rng, 128, 1.5)
    box = np.ones_like(ref)
    for _ in range(5):
        dx, dy = rng.uniform(-10, 10, 2)
        c = phase.phase_correlate(_fourier_shift(ref, dx, dy), ref, window=box, f_hi=0.3)
        assert np.allclose(c.shift_px, [dx, dy], atol=1e-3)
        assert c.peak > 0.98


def test_windowed_subpixel_shift_within_005_px() -> None:
    """Known sub-pixel shifts of a larger scene, cropped (so the content really moves under the window),
    with sensor noise: recovered to 0.05 px."""
    rng = np.random.default_rng(2)
    big = _texture(rng, 256 + 64, 1.5)
    errors = []
    for _ in range(12):
        dx, dy = rng.uniform(-8, 8, 2)
        moved = _fourier_shift(big, dx, dy)[32:-32, 32:-32]
        moved = moved + rng.normal(0.0, 0.05 * moved.std(), moved.shape)
        c = phase.phase_correlate(moved, big[32:-32, 32:-32], f_hi=0.3)
        errors.append(np.hypot(*(c.shift_px - [dx, dy])))
    assert max(errors) < 0.05
    # no systematic bias either
    assert np.mean(errors) < 0.025


def test_sign_matches_cv2_phasecorrelate() -> None:
    rng = np.random.default_rng(3)
    big = _texture(rng, 200, 2.0)
    ref = big[20:148, 20:148]
    img = big[17:145, 25:153]  # content moves right by -5 (left) and down by +3
    c = phase.phase_correlate(img, ref, f_hi=0.3)
    hann = cv2.createHanningWindow((128, 128), cv2.CV_64F)
    (cx, cy), _ = cv2.phaseCorrelate(ref.astype(np.float64), img.astype(np.float64), hann)
    assert np.allclose(c.shift_px, [-5.0, 3.0], atol=0.05)
    assert np.allclose(c.shift_px, [cx, cy], atol=0.3)


def test_peak_is_a_quality() -> None:
    rng = np.random.default_rng(4)
    a = _texture(rng, 128, 1.5)
    b = _texture(rng, 128, 1.5)
    same = phase.phase_correlate(a, a, f_hi=0.3)
    unrelated = phase.phase_correlate(a, b, f_hi=0.3)
    noisy = phase.phase_correlate(a + rng.normal(0, 1.0 * a.std(), a.shape), a, f_hi=0.3)
    assert same.peak > 0.95
    assert unrelated.peak < 0.15
    assert unrelated.peak < noisy.peak < same.peak
    assert same.psr > 5 * unrelated.psr


def test_band_weight_shape_and_range() -> None:
    w = phase.band_weight(64, 64, 0.05, 0.2)
    assert w.shape == (64, 33)
    f = phase.rfreq(64, 64)[2]
    assert w[0, 0] == 0.0
    assert np.all(w[f > 0.2] == 0.0)
    assert np.all(w[(f > 0.08) & (f < 0.15)] == 1.0)
    assert np.all((w >= 0) & (w <= 1))


def test_mismatched_shapes_raise() -> None:
    with pytest.raises(ValueError):
        phase.phase_correlate(np.zeros((8, 8)), np.zeros((8, 9)))


@pytest.mark.parametrize(("angle_deg", "scale"), [(6.0, 1.0), (-9.0, 1.04), (3.0, 0.95), (0.0, 1.06)])
def test_fourier_mellin_rotation_and_scale(angle_deg: float, scale: float) -> None:
    """Rotation within 0.5 deg and scale within 1 % (the sign: content turned clockwise on screen = +)."""
    rng = np.random.default_rng(5)
    n = 480
    big = _texture(rng, n, 2.0)
    # OpenCV's positive angle turns the content anticlockwise on screen (y down)
    M = cv2.getRotationMatrix2D((n / 2, n / 2), angle_deg, scale)
    turned = cv2.warpAffine(big, M, (n, n), flags=cv2.INTER_CUBIC)
    crop = slice(120, 360)
    rs = phase.rotation_scale(turned[crop, crop], big[crop, crop])
    assert abs(np.degrees(rs.angle_rad) + angle_deg) < 0.5
    assert abs(rs.scale / scale - 1.0) < 0.01
    assert rs.quality > 0.05
