"""Landmark sampling (paper 2 eq. 8): the KDE, the diversity score and its preference for empty regions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from companion.ekf.sampling import (
    budget_bandwidth,
    diversity,
    kde_log_density,
    sample_new_landmarks,
    scott_bandwidth,
)


def test_kde_matches_a_sum_of_gaussians():
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 640, (7, 2))
    q = rng.uniform(0, 640, (20, 2))
    h = 40.0
    ref = np.mean([multivariate_normal(p, h * h * np.eye(2)).pdf(q) for p in pts], axis=0)
    np.testing.assert_allclose(np.exp(kde_log_density(q, pts, h)), ref, rtol=1e-10)


def test_diversity_is_finite_far_away_and_higher_in_empty_space():
    pts = np.array([[100.0, 100.0], [120.0, 90.0], [90.0, 130.0]])
    q = np.array([[105.0, 105.0], [600.0, 450.0], [1e5, 1e5]])
    D = diversity(q, pts, 20.0, 640 * 480)
    assert np.all(np.isfinite(D))
    assert D[0] < 0 < D[1] < D[2]  # crowded: denser than uniform over the image; empty: sparser
    # uniform reference: a KDE of points spread evenly gives D ~ 0 in the middle
    g = np.stack(np.meshgrid(np.arange(20, 640, 40.0), np.arange(20, 480, 40.0)), -1).reshape(-1, 2)
    assert abs(diversity(np.array([[320.0, 240.0]]), g, 40.0, 640 * 480)[0]) < 0.2


def test_bandwidth_floor_cap_and_budget():
    assert budget_bandwidth(640 * 480, 32) == pytest.approx(49.0, abs=0.1)
    assert scott_bandwidth(np.zeros((0, 2)), 16.0, 48.0) == 48.0
    assert scott_bandwidth(np.array([[5.0, 5.0]]), 16.0, 48.0) == 48.0
    assert scott_bandwidth(np.array([[5.0, 5.0], [5.5, 5.0], [5.0, 5.5]]), 16.0, 48.0) == 16.0
    cluster = np.random.default_rng(1).normal(300, 50, (32, 2))
    assert 16.0 < scott_bandwidth(cluster, 16.0, 48.0) < 48.0
    spread = np.random.default_rng(1).uniform(0, 640, (32, 2))
    assert scott_bandwidth(spread, 16.0, 48.0) == 48.0


def _right_half_fraction(method: str, seeds: int = 40) -> float:
    """Tracked landmarks crowd the left half; candidates cover the whole image. Fraction of the new
    landmarks that land in the (empty) right half."""
    fr = []
    for s in range(seeds):
        rng = np.random.default_rng(s)
        tracked = np.column_stack([rng.uniform(0, 300, 24), rng.uniform(0, 480, 24)])
        cand = np.column_stack([rng.uniform(0, 640, 300), rng.uniform(0, 480, 300)])
        idx = sample_new_landmarks(cand, tracked, 8, method, rng)
        assert len(set(idx.tolist())) == len(idx) == 8
        fr.append(np.mean(cand[idx, 0] > 320))
    return float(np.mean(fr))


def test_kde_sampling_prefers_empty_regions_uniform_does_not():
    kde = _right_half_fraction("kde")
    uni = _right_half_fraction("uniform")
    assert 0.4 < uni < 0.6
    assert kde > 0.7
    assert kde > uni + 0.15


def test_kde_sampling_spreads_the_first_batch():
    """With no tracked landmarks the picks still push each other apart (each pick joins the KDE)."""
    rng = np.random.default_rng(3)
    cand = np.column_stack([rng.uniform(0, 640, 400), rng.uniform(0, 480, 400)])
    d_kde, d_uni = [], []
    for s in range(20):
        for method, out in (("kde", d_kde), ("uniform", d_uni)):
            idx = sample_new_landmarks(cand, np.zeros((0, 2)), 16, method, np.random.default_rng(s))
            p = cand[idx]
            d = np.linalg.norm(p[:, None] - p[None], axis=2) + np.eye(16) * 1e9
            out.append(d.min(axis=1).mean())
    assert np.mean(d_kde) > 1.3 * np.mean(d_uni)


def test_sampling_edge_cases():
    rng = np.random.default_rng(0)
    cand = rng.uniform(0, 100, (5, 2))
    assert len(sample_new_landmarks(cand, np.zeros((0, 2)), 10, "kde", rng)) == 5
    assert len(sample_new_landmarks(cand, cand[:2], 0, "kde", rng)) == 0
    assert len(sample_new_landmarks(np.zeros((0, 2)), cand, 3, "uniform", rng)) == 0
    a = sample_new_landmarks(cand, cand[:2], 3, "kde", np.random.default_rng(9))
    b = sample_new_landmarks(cand, cand[:2], 3, "kde", np.random.default_rng(9))
    np.testing.assert_array_equal(a, b)
