"""The information bound of ``bench georef_budget`` (``shift_fisher``, ``disc_probability``) on cases with a
known answer: an isotropic Gaussian's chance inside a disc, and the Cramer-Rao bound of a shift against a
known template in white noise, which has a closed form in the image domain."""

from __future__ import annotations

import numpy as np
import pytest

from bench.georef_budget import bound_stats, disc_probability, shift_fisher
from companion.georef import illumination, phase

N = 128


def test_disc_probability_matches_closed_form_and_sampling() -> None:
    for sigma in (0.1, 0.4, 1.0, 3.0):
        expected = 1.0 - np.exp(-1.0 / (2.0 * sigma * sigma))
        assert disc_probability(np.eye(2) * sigma**2) == pytest.approx(expected, abs=1e-9)
    cov = np.array([[0.5, 0.2], [0.2, 0.1]])
    e = np.random.default_rng(0).multivariate_normal(np.zeros(2), cov, 200_000)
    assert disc_probability(cov) == pytest.approx(np.mean(np.hypot(e[:, 0], e[:, 1]) < 1.0), abs=0.005)
    assert disc_probability(np.eye(2) * 1e-6) == pytest.approx(1.0)


def _texture(rng: np.random.Generator, blur_px: float) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random texture (unit std) and its exact x derivative, both from one spectrum."""
    fy = np.fft.fftfreq(N)[:, None]
    fx = np.fft.fftfreq(N)[None, :]
    spec = np.fft.fft2(rng.standard_normal((N, N))) * np.exp(-2.0 * (np.pi * blur_px) ** 2 * (fx**2 + fy**2))
    s = np.real(np.fft.ifft2(spec))
    ds = np.real(np.fft.ifft2(spec * 2j * np.pi * fx))
    k = 1.0 / s.std()
    return s * k, ds * k


def _shifted(img: np.ndarray, d: np.ndarray) -> np.ndarray:
    """img moved by d = (dx, dy) pixels, exactly (a phase ramp on its periodic spectrum)."""
    fy = np.fft.fftfreq(N)[:, None]
    fx = np.fft.fftfreq(N)[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(img) * np.exp(-2j * np.pi * (fx * d[0] + fy * d[1]))))


def test_shift_bound_against_the_known_template_bound_and_a_real_matcher() -> None:
    """Frame = template + white noise, reference = the template itself. The exact bound on the x shift is
    noise^2 / sum(w^2 (dS/dx)^2); ``shift_fisher`` estimates it from the pooled coherence and must come out
    at or somewhat below it (optimistic, as documented: 0.82 here), never far off either way; and the
    matcher's own coherence-weighted phase correlation must not beat it (it lands at about 2x)."""
    rng = np.random.default_rng(3)
    window = phase.tukey_window(N, N, 0.5)
    bins = illumination.Bins.make((N, N), 2.0 / N, 0.45, 8, 8)
    band = phase.band_weight(N, N, 2.0 / N, 0.45)
    noise = 0.5
    ratios, bounds, errors = [], [], []
    for _ in range(30):
        s, ds = _texture(rng, 2.0)
        frame = s + noise * rng.standard_normal((N, N))
        f_ref = phase.spectrum(s.astype(np.float32), window)
        f_img = phase.spectrum(frame.astype(np.float32), window)
        cov = np.linalg.inv(shift_fisher(f_img, f_ref, bins, window))
        exact_var = noise**2 / float(np.sum(window**2 * ds**2))
        ratios.append(np.sqrt(cov[0, 0] / exact_var))
        bounds.append(np.sqrt(cov[0, 0]))
        # the same kind of pair at a known sub-pixel shift, located by coherence-weighted phase correlation
        d = rng.uniform(-0.5, 0.5, 2)
        shifted = _shifted(s, d)
        f_shift = phase.spectrum((shifted + noise * rng.standard_normal((N, N))).astype(np.float32), window)
        first = phase.correlate_spectra(f_shift, f_ref, (N, N), band, 16)
        # then weighted by the coherence at that peak, as the matcher's second pass does (GCC-ML weights)
        ref_bins = f_ref.ravel()[bins.index]
        w = illumination.coherence_weight(f_shift, ref_bins, bins, first.shift_px, 0.0)
        corr = phase.correlate_spectra(
            f_shift, f_ref, (N, N), illumination.scatter(w, bins, (N, N), np.float32), 16
        )
        errors.append(corr.shift_px[0] - d[0])
    ratio = float(np.median(ratios))
    assert 0.6 <= ratio <= 1.05, ratio
    rms = float(np.sqrt(np.mean(np.square(errors))))
    assert rms >= float(np.median(bounds)), (rms, np.median(bounds))


def test_bound_stats_takes_the_floor_off_and_counts_a_frame_without_information() -> None:
    j = np.diag([100.0, 25.0])  # sigmas 0.1 and 0.2 px
    none = bound_stats([(j, np.zeros((2, 2)))])
    assert none["bound_px"] == pytest.approx(0.2) and none["bound_net_px"] == pytest.approx(0.2)
    assert none["bound_success"] == pytest.approx(none["bound_net_success"])
    half = bound_stats([(j, np.diag([75.0, 0.0]))])
    assert half["bound_net_px"] == pytest.approx(0.2) and half["bound_floor_px"] == float("inf")
    lost = bound_stats([(j, np.diag([100.0, 30.0])), (j, np.zeros((2, 2)))])
    assert lost["bound_net_px"] == float("inf")  # the median of two frames, one left without information
    assert lost["bound_net_success"] == pytest.approx(0.5 * none["bound_success"])
