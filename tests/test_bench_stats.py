"""The EKF benchmark's statistics: "dual worse than the better single camera beyond noise", and the
uncertainty of the averaged improvements; what every benchmark JSON says about the machine."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import ttest_rel

from bench.thermal_ekf import (
    bench_options,
    holm_adjusted,
    improvement,
    improvement_bootstrap,
    options_of_runs,
    paired_worse,
    parse_option,
    runs_seeds,
    sift_of_runs,
)


def test_paired_worse_is_scipys_one_sided_paired_t() -> None:
    rng = np.random.default_rng(3)
    b = rng.normal(0.2, 0.1, 30)
    a = b + rng.normal(0.03, 0.05, 30)
    got = paired_worse(a, b)
    ref = ttest_rel(a, b, alternative="greater")
    assert got["t"] == pytest.approx(ref.statistic, rel=1e-9)
    assert got["p"] == pytest.approx(ref.pvalue, rel=1e-9)
    assert got["diff"] == pytest.approx(np.mean(a - b))
    # a NaN trial (a run that produced no estimate) is left out of the pair, not propagated
    a2 = np.append(a, np.nan)
    b2 = np.append(b, 0.1)
    assert paired_worse(a2, b2)["t"] == pytest.approx(got["t"])


def test_holm_adjusted_known_values() -> None:
    # Holm (1979) step-down by hand: sorted p 0.005, 0.01, 0.03, 0.04 times 4, 3, 2, 1 -> 0.02, 0.03,
    # 0.06, 0.04 -> monotone 0.02, 0.03, 0.06, 0.06; returned in the input order
    assert holm_adjusted([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjusted([0.5, 0.9]) == pytest.approx([1.0, 1.0])  # capped at 1
    assert holm_adjusted([]) == []


def test_one_significant_trajectory_of_ten_survives_holm_only_when_strong() -> None:
    p = [0.5] * 9
    assert holm_adjusted(p + [0.004])[-1] == pytest.approx(0.04)  # 0.004 x 10: still below 0.05
    assert holm_adjusted(p + [0.0064])[-1] > 0.05  # a t = 2.65 over 30 trials alone is not


def _flights(rng: np.random.Generator, trials: int, noise: float) -> dict[str, dict[str, np.ndarray]]:
    """Two trajectories with true E visible / thermal / dual 0.30 / 0.20 / 0.15 and 0.20 / 0.16 / 0.12 %."""
    true = {"1": (0.30, 0.20, 0.15), "2": (0.20, 0.16, 0.12)}
    return {
        k: {c: e + rng.normal(0.0, noise, trials) for c, e in zip(("visible", "thermal", "dual"), v)}
        for k, v in true.items()
    }


def test_improvement_interval_is_a_point_without_trial_noise() -> None:
    E = _flights(np.random.default_rng(0), 30, 0.0)
    ci = improvement_bootstrap(E, n_boot=200)
    want = np.mean([improvement(0.30, 0.15), improvement(0.20, 0.12)])  # 50 % and 40 %
    assert ci["I_vis_vs_dual"] == pytest.approx([want, want])
    assert ci["I_vis_vs_dual_of_mean_E"] == pytest.approx([improvement(0.25, 0.135)] * 2)


def test_improvement_interval_covers_the_estimate_and_narrows_with_trials() -> None:
    rng = np.random.default_rng(1)
    widths = []
    for trials in (30, 480):
        E = _flights(rng, trials, 0.05)
        ci = improvement_bootstrap(E, n_boot=1000)
        est = np.mean([improvement(E[k]["visible"].mean(), E[k]["dual"].mean()) for k in E])
        lo, hi = ci["I_vis_vs_dual"]
        assert lo < est < hi
        widths.append(hi - lo)
    # the interval's width falls as 1 / sqrt(trials): 4x narrower for 16x the trials (loose margins)
    assert 2.5 < widths[0] / widths[1] < 6.5


def test_runs_seeds_reports_what_the_records_say() -> None:
    """A summary of pooled runs logs names every seed; a log without seeds is not labelled with a guess."""
    assert runs_seeds([{"seed": 1}, {"seed": 1}]) == 1
    assert runs_seeds([{"seed": 1}, {"seed": 0}, {"seed": 1}]) == [0, 1]
    assert runs_seeds([{"seed": 0}, {"name": "1"}]) is None
    assert runs_seeds([]) is None


def test_sift_of_runs_names_the_settings_only_when_every_trial_agrees() -> None:
    """Pooled runs logs of two SIFT settings, or older logs without the field, are not labelled with one."""
    a = {"visible": [800, 0.02], "thermal": [800, 0.005]}
    b = {"visible": [800, 0.02], "thermal": [400, 0.005]}
    assert sift_of_runs([{"sift": a}, {"sift": dict(a)}]) == a
    assert sift_of_runs([{"sift": a}, {"sift": b}]) is None
    assert sift_of_runs([{"sift": a}, {"name": "1"}]) is None


def test_option_overrides_reach_the_estimator_options_with_their_types() -> None:
    """--option KEY=VALUE: the field's own type, every configuration's options, and a clear error otherwise."""
    pairs = tuple(
        parse_option(x)
        for x in (
            "altimeter_bias_sigma_m=0.3",
            "facet_error_state=false",
            "max_landmarks_per_camera=24",
            "patch_cameras=visible,thermal",
        )  # fmt: skip
    )
    assert pairs == (
        ("altimeter_bias_sigma_m", 0.3),
        ("facet_error_state", False),
        ("max_landmarks_per_camera", 24),
        ("patch_cameras", ("visible", "thermal")),
    )
    o = bench_options(None, None, pairs)
    assert o.altimeter_bias_sigma_m == 0.3 and not o.facet_error_state and o.max_landmarks_per_camera == 24
    assert bench_options().altimeter_bias_sigma_m == 0.2  # the benchmark's own setting untouched
    for bad, words in (("nosuch=1", "EkfOptions field"), ("facet_error_state=yes", "true or false"),
                       ("max_landmarks_per_camera=2.5", "cannot read"), ("mode=visible", "per configuration"),
                       ("altimeter_bias_sigma_m", "KEY=VALUE")):  # fmt: skip
        with pytest.raises(ValueError, match=words):
            parse_option(bad)
    assert options_of_runs([{"options": {"a": 1}}, {"options": {"a": 1}}]) == {"a": 1}
    assert options_of_runs([{"options": {"a": 1}}, {"name": "1"}]) is None
    assert options_of_runs([{"name": "1"}]) == {}


def test_ekf_patch_summary_pairs_each_variant_with_sift_only() -> None:
    """Known runs: the variant's paired difference and its standard error, per mode; sift_only has none."""
    from scipy.stats import sem

    from bench.ekf_patch import KEYS, MODES, VARIANTS, summarise

    rng = np.random.default_rng(0)
    runs = []
    for i in range(6):
        r = {}
        for v, shift in zip(VARIANTS, (0.0, -0.1, 0.05)):
            r[v] = {
                m: {k: 1.0 + i + shift + 0.01 * rng.standard_normal() for k in (*KEYS, "filter_s_per_frame")}
                for m in MODES
            }
        runs.append(r)
    s = summarise(runs)
    for m in MODES:
        assert "E_percent_diff" not in s[m]["sift_only"]
        d = np.array([r["patch_visible"][m]["E_percent"] - r["sift_only"][m]["E_percent"] for r in runs])
        assert s[m]["patch_visible"]["E_percent_diff"] == pytest.approx(d.mean())
        assert s[m]["patch_visible"]["E_percent_diff_sem"] == pytest.approx(sem(d))
        assert s[m]["patch_visible"]["E_percent_diff"] == pytest.approx(-0.1, abs=0.03)
        assert s[m]["patch_both"]["mean_error_m_diff"] == pytest.approx(0.05, abs=0.03)


def test_ekf_start_summary_pairs_each_variant_with_the_reference() -> None:
    """Known runs: each variant's mean, worst flight and paired difference to the reference (mean, sem)."""
    from scipy.stats import sem

    from bench.ekf_start import VARIANTS, summarise

    rng = np.random.default_rng(1)
    runs = [
        {v: {"mean_error_m": 0.5 + 0.1 * i + k + 0.01 * rng.standard_normal(), "E_percent": 0.1, "estimates": 180 - k}
         for k, v in enumerate(VARIANTS)}
        for i in range(5)
    ]  # fmt: skip
    s = summarise(runs)
    assert s["reference"]["diff_m"] == 0.0
    d = np.array([r["attitude_late_at_once"]["mean_error_m"] - r["reference"]["mean_error_m"] for r in runs])
    assert s["attitude_late_at_once"]["diff_m"] == pytest.approx(d.mean()) == pytest.approx(2.0, abs=0.03)
    assert s["attitude_late_at_once"]["diff_sem_m"] == pytest.approx(sem(d))
    assert s["imu_late"]["worst_mean_error_m"] == max(r["imu_late"]["mean_error_m"] for r in runs)
    assert s["attitude_late_wait"]["estimates"] == 177


def test_covariance_consistency_scores_a_right_and_an_over_confident_covariance() -> None:
    from companion.metrics import CHI2_2DOF_95, covariance_consistency

    assert CHI2_2DOF_95 == pytest.approx(5.991, abs=1e-3)
    rng = np.random.default_rng(4)
    n = 4000
    # errors drawn from the covariances they come with (each its own, correlated and elongated)
    a = rng.uniform(0.1, 2.0, n)
    b = rng.uniform(0.1, 2.0, n)
    th = rng.uniform(0, np.pi, n)
    R = np.stack([np.stack([np.cos(th), -np.sin(th)], -1), np.stack([np.sin(th), np.cos(th)], -1)], -1)
    cov = np.einsum("nij,nj,nkj->nik", R, np.stack([a**2, b**2], -1), R)
    err = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((n, 2)))
    right = covariance_consistency(err, cov)
    assert right["count"] == n
    assert right["nees_mean"] == pytest.approx(2.0, abs=0.15)
    assert right["within_95"] == pytest.approx(0.95, abs=0.015)
    assert right["sigma_mean_m"] == pytest.approx(np.mean(np.sqrt(a**2 + b**2)), rel=1e-9)
    # the same errors claimed ten times smaller: NEES x 100, few inside the ellipse
    over = covariance_consistency(err, cov / 100.0)
    assert over["nees_mean"] == pytest.approx(100.0 * right["nees_mean"], rel=1e-9)
    assert over["within_95"] < 0.1
    # an estimate sent without a covariance (NaN, MAVLink's "unknown") is left out, not counted as inside
    cov_nan = cov.copy()
    cov_nan[:10] = np.nan
    assert covariance_consistency(err, cov_nan)["count"] == n - 10
    assert covariance_consistency(err[:0], cov[:0]) == {"count": 0}


def test_write_json_names_the_machine_and_library_versions(tmp_path) -> None:
    """A flight's figures depend on the CPU and the numerics libraries' builds (README, Benchmarks): every
    benchmark JSON says which ones made it, and the versions are the installed ones."""
    import json
    from importlib import metadata

    from bench.common import write_json

    out = tmp_path / "r.json"
    write_json(out, {"x": float("nan")})
    doc = json.loads(out.read_text())
    m = doc["machine"]
    assert doc["x"] is None
    assert m["packages"]["opencv-python-headless"] == metadata.version("opencv-python-headless")
    assert m["packages"]["gtsam"] == metadata.version("gtsam")
    assert m["packages"]["numpy"] == m["numpy"]
    assert isinstance(m["cpu_model"], str) and m["cpu_model"]
    assert m["numpy_simd_found"] is None or isinstance(m["numpy_simd_found"], list)


def test_specular_fraction_reaches_the_visible_renderer_only() -> None:
    """--specular-fraction 0: the same site without glints in the visible image, the thermal image unchanged;
    a share outside 0 .. 1 refused before anything runs."""
    from bench.thermal_ekf import _world, main
    from companion.constants import R_BODY_CAM_NADIR
    from companion.geometry import camera_pose

    world, cams = _world()
    world0, cams0 = _world(0.0)
    assert world0.reflectance.specular_fraction == 0.0 and world.reflectance.specular_fraction > 0.0
    assert np.array_equal(world0.dem.height_m, world.dem.height_m)
    R_wc, p_c = camera_pose(np.eye(3), np.array([0.0, 0.0, -80.0]), R_BODY_CAM_NADIR)
    vis, temp = cams.radiance(R_wc, p_c)
    vis0, temp0 = cams0.radiance(R_wc, p_c)
    assert np.array_equal(temp, temp0)
    lobe = vis - vis0  # the specular lobe alone: never negative, and glints somewhere in the view
    assert float(np.nanmin(lobe)) >= 0.0 and float(np.nanmax(lobe)) > 0.1
    with pytest.raises(SystemExit):
        main(["--specular-fraction", "1.5"])
