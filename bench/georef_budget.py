"""Geo-referencing error budget: which part of the simulation costs how much accuracy.

``python -m bench georef_budget [--quick] [--json PATH] [--seed N] [--frames N] [--scenes 02,05,08]``

The Table 3 analogue (``python -m bench georef``) measures the matcher against everything at once: a degraded
DEM, an albedo texture that the DEM knows nothing about, the scene's own lighting against the presumed sun,
sensor noise. This benchmark switches those effects off one at a time on the same frames poses, so that the
error of ``GeoReferencer.locate`` can be attributed:

- ``as_benchmarked``: exactly the Table 3 setting;
- ``known_sun``: the reference drawn under the scene's true sun instead of the presumed one;
- ``true_dem``: the estimator given the surface the renderer used (no coarsening, noise or holes);
- ``uniform_albedo``: frames rendered with a constant albedo (shading only);
- ``coarse_dem_uniform_albedo``: the DEM only coarsened (4x, no noise, no holes), constant albedo;
- ``ideal``: true DEM, constant albedo, known sun (what is left: rendering, sensor noise, rectification).

The error is split along the sun's horizontal direction and across it: a component of the frame that the
reference does not model but that is correlated with the relief (topography-correlated albedo, slope
roughness below the DEM's cell) is in quadrature with the shading and shifts the correlation peak along the
sun azimuth, so the bias there is the signature to look for. All errors in frame pixels (true GSD), over the
fixes the matcher accepted; ``success`` is the fraction of ALL frames with an accepted fix under 1 px.

Beside each variant's measured errors, an information bound on the same frames (``shift_fisher``): the
frame rectified at its TRUE pose, the reference fitted to it there with the matcher's own model
(``illumination.fit_reference``: five DEM-derived images, real coefficients per frequency ring), and the
Cramer-Rao bound of the shift from their coherence per (ring, orientation) cell over every frequency the
DEM carries (Knapp & Carter's time-delay bound, in two dimensions). ``bound_px``: the median over the frames
of the bound's larger standard deviation; ``bound_success``: the mean over the frames of the chance that an
unbiased matcher meeting the bound lands within 1 px. That raw bound is optimistic: the fit is made at the
truth, the window's edges count as signal (on synthetic pairs with a known template it comes out 0.75-0.85x
the exact bound, ``tests/test_georef_bound.py``), and an estimated coherence is never zero: the same
computation on the frame with its Fourier phases scrambled (``FLOOR_SURROGATES`` copies: no match left in
it) still finds information, ``bound_floor_px``. So a goal the raw bound puts out of reach is out of reach
of any unbiased matcher of this model. ``bound_net_px`` / ``bound_net_success``: the floor's information
taken off the raw bound's, frame by frame: closer to what the frame really holds, but an estimate, not a
guaranteed bound.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench.common import parser, table, write_json
from bench.georef import AGL_M, DEGRADATION, INTR, PRESUMED_SUN, sample_frames
from companion.georef import illumination, phase
from companion.georef.georef import GeoReferencer, GeorefOptions
from sim_bridge.render import VisibleRenderer
from sim_bridge.terrain import SCENE_IDS, degrade_dem, make_scene

UNIFORM_ALBEDO = 0.25  # the scenes' base Mars albedo
BOUND_RINGS, BOUND_SECTORS = 8, 8  # coherence cells of the information bound
BOUND_F_LO_CYCLES = 2.0  # lowest frequency of the bound: cycles across the grid
FLOOR_SURROGATES = 4  # phase-scrambled copies of each frame on which the bound's floor is measured

VARIANTS: dict[str, dict[str, bool]] = {
    # name: (true DEM, coarsen only, uniform albedo, known sun)
    "as_benchmarked": dict(true_dem=False, coarse_only=False, uniform_albedo=False, known_sun=False),
    "known_sun": dict(true_dem=False, coarse_only=False, uniform_albedo=False, known_sun=True),
    "true_dem": dict(true_dem=True, coarse_only=False, uniform_albedo=False, known_sun=False),
    "uniform_albedo": dict(true_dem=False, coarse_only=False, uniform_albedo=True, known_sun=False),
    "coarse_dem_uniform_albedo": dict(true_dem=False, coarse_only=True, uniform_albedo=True, known_sun=False),
    "ideal": dict(true_dem=True, coarse_only=False, uniform_albedo=True, known_sun=True),
}


def shift_fisher(
    f_frame: np.ndarray, f_ref: np.ndarray, bins: illumination.Bins, window: np.ndarray
) -> np.ndarray:
    """(2, 2) Fisher information (per squared grid cell, (col, row) axes) of the shift between a frame and a
    reference, from their half-plane spectra ALIGNED at the true shift and the window both were taken with.

    Knapp & Carter (1976): a frequency bin whose two spectra have magnitude-squared coherence g carries
    (2 pi f)^2 g / (1 - g) of information on the delay; summed over the full plane (Hermitian multiplicity
    of the half-plane bins). The coherence is the real one (the in-phase part: what is in quadrature at the
    truth is bias or noise to a matcher) pooled per (ring, sector) cell. The window makes neighbouring bins
    dependent: the sum is scaled by the effective sample fraction (sum w^2)^2 / (N sum w^4)."""
    # the pooled coherence per cell, rho^2 / (1 - rho^2) per bin: the matcher's own weights without a floor
    g = illumination.coherence_weight(f_frame, f_ref.ravel()[bins.index], bins, np.zeros(2), floor=0.0)
    w2 = np.asarray(window, float) ** 2
    k_eff = w2.sum() ** 2 / (w2.size * (w2 * w2).sum())
    f = np.stack([bins.fx, bins.fy])
    return k_eff * (2.0 * np.pi) ** 2 * (f * (bins.mult * g)) @ f.T


def disc_probability(cov: np.ndarray, radius: float = 1.0, n_angles: int = 256) -> float:
    """P(|e| < radius) for e ~ N(0, cov) in 2-D: along each direction u the radial integral is closed-form,
    (1 - exp(-q R^2 / 2)) / q with q = u^T cov^-1 u, leaving one smooth integral over the angle."""
    cov = np.asarray(cov, float)
    det = float(np.linalg.det(cov))
    if not det > 0.0:
        return 1.0 if np.all(np.abs(cov) < 1e-12) else float("nan")
    th = (np.arange(n_angles) + 0.5) * (2.0 * np.pi / n_angles)
    u = np.stack([np.cos(th), np.sin(th)])
    q = np.einsum("in,ij,jn->n", u, np.linalg.inv(cov), u)
    radial = -np.expm1(-0.5 * q * radius * radius) / q
    return float(np.clip(radial.mean() / np.sqrt(det), 0.0, 1.0))


def frame_bound(geo: GeoReferencer, fr: dict[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """(J_truth, J_floor): (2, 2) shift information (frame px^-2) of a frame, rectified at its true pose as
    ``locate`` would, with the reference fitted to it there over every frequency up to the DEM's Nyquist;
    and the same computed on phase-scrambled copies of the frame (``FLOOR_SURROGATES``), which is what the
    estimate gives for no real match at all: the coherence of a few bins per cell, and a fit of five
    coefficients per ring, are never zero. None when the frame cannot be rectified."""
    img = geo.preprocess(geo.work_image(fr["image"]))
    ne = np.asarray(fr["p"], float)[:2]
    ground = geo.ground_height(ne[0], ne[1])
    pair = geo.rectify(img, fr["R"], ne, ground + fr["agl"], fr["agl"])
    if isinstance(pair, str):
        return None
    n = pair.grid.size
    f_hi = min(0.5 * pair.grid.gsd_m / geo.dem.cell_m, 0.49)
    bins = illumination.Bins.make((n, n), BOUND_F_LO_CYCLES / n, f_hi, BOUND_RINGS, BOUND_SECTORS)
    f_img = phase.spectrum(pair.frame, pair.weight)
    f_bases = [phase.spectrum(b, pair.weight) for b in geo.ref.sample_bases(pair.grid, pair.reference)]
    to_frame_px = geo.opt.work_scale**2  # information per grid cell^2 -> per frame px^2
    a = f_img.ravel()[bins.index]

    def information(a_bins: np.ndarray) -> np.ndarray:
        spectrum = illumination.scatter(a_bins, bins, (n, n))
        ref = illumination.scatter(
            illumination.fit_reference(spectrum, f_bases, bins, np.zeros(2)), bins, (n, n)
        )
        return shift_fisher(spectrum, ref, bins, pair.weight) * to_frame_px

    # surrogates: the frame's amplitude spectrum with random phases (fixed seeds: runs repeat)
    floor = np.mean(
        [
            information(np.abs(a) * np.exp(2j * np.pi * np.random.default_rng(k).random(a.size)))
            for k in range(FLOOR_SURROGATES)
        ],
        axis=0,
    )
    return information(a), floor


def bound_stats(info: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """Per-variant summary of ``frame_bound``'s results: medians over the frames of the larger standard
    deviation (px) and means of the chance within 1 px, for the raw bound, its floor, and the bound with
    the floor's information taken off (a frame left with none counts as infinitely uncertain)."""
    nan = float("nan")
    if not info:
        return dict(
            bound_px=nan, bound_success=nan, bound_floor_px=nan, bound_net_px=nan, bound_net_success=nan
        )
    sd: dict[str, list[float]] = {"raw": [], "floor": [], "net": []}
    success: dict[str, list[float]] = {"raw": [], "net": []}
    for j_truth, j_floor in info:
        for key, J in (("raw", j_truth), ("floor", j_floor), ("net", j_truth - j_floor)):
            lam = np.linalg.eigvalsh(J)
            if lam[0] <= 0.0:
                sd[key].append(float("inf"))
                if key in success:
                    success[key].append(0.0)
                continue
            cov = np.linalg.inv(J)
            sd[key].append(float(1.0 / np.sqrt(lam[0])))
            if key in success:
                success[key].append(disc_probability(cov))
    return dict(
        bound_px=float(np.median(sd["raw"])),
        bound_success=float(np.mean(success["raw"])),
        bound_floor_px=float(np.median(sd["floor"])),
        bound_net_px=float(np.median(sd["net"])),
        bound_net_success=float(np.mean(success["net"])),
    )


def run_variant(
    scene, variant: dict[str, bool], n: int, seed: int, opts: GeorefOptions, cache: dict[Any, Any]
) -> dict[str, Any]:
    """Errors of ``locate`` over n frames (the same poses for every variant of a scene: same rng seed).
    ``cache`` keeps the matchers and renderers shared between variants of one scene."""
    dem_kind = "true" if variant["true_dem"] else "coarse" if variant["coarse_only"] else "degraded"
    key = ("geo", dem_kind, variant["known_sun"])
    if key not in cache:
        if dem_kind == "true":
            dem = scene.dem
        elif dem_kind == "coarse":
            dem, _ = degrade_dem(
                scene.dem, factor=DEGRADATION["factor"], noise_sigma_m=0.0, hole_fraction=0.0
            )
        else:
            dem, _ = degrade_dem(scene.dem, seed=seed, **DEGRADATION)
        sun = scene.sun if variant["known_sun"] else PRESUMED_SUN
        cache[key] = GeoReferencer(dem, sun, INTR, options=opts)
    geo = cache[key]
    rkey = ("renderer", variant["uniform_albedo"])
    if rkey not in cache:
        albedo = np.full_like(scene.albedo, UNIFORM_ALBEDO) if variant["uniform_albedo"] else scene.albedo
        cache[rkey] = VisibleRenderer(scene.dem, albedo, scene.sun, INTR)
    renderer = cache[rkey]
    frames = sample_frames(scene, renderer, n, np.random.default_rng([seed, int(scene.scene_id)]))
    az = scene.sun.azimuth_rad
    along = np.array([np.cos(az), np.sin(az)])  # (north, east) towards the sun
    across = np.array([-np.sin(az), np.cos(az)])
    errs, ms, info = [], [], []
    for fr in frames:
        fb = frame_bound(geo, fr)
        if fb is not None:
            info.append(fb)
        fix = geo.locate(fr["image"], fr["R"], fr["pred"], fr["agl"])
        ms.append(fix.ms)
        if fix.ok:
            e_ne = (fix.p_world[:2] - fr["p"][:2]) / (fr["agl"] / INTR.fx)
            errs.append([float(e_ne @ along), float(e_ne @ across)])
    e = np.asarray(errs, float).reshape(-1, 2)
    d = np.hypot(e[:, 0], e[:, 1])
    nan = float("nan")
    return dict(
        n=n,
        fixes=len(e),
        bias_along_sun_px=float(e[:, 0].mean()) if len(e) else nan,
        bias_across_sun_px=float(e[:, 1].mean()) if len(e) else nan,
        std_along_sun_px=float(e[:, 0].std()) if len(e) > 1 else nan,
        std_across_sun_px=float(e[:, 1].std()) if len(e) > 1 else nan,
        mean_px=float(d.mean()) if len(e) else nan,
        success_rate=float((d < 1.0).sum() / n),
        ms_per_frame=float(np.mean(ms)),
        **bound_stats(info),
    )


HEADERS = ["variant", "fixes", "bias_along", "bias_across", "std_along", "std_across", "mean_px", "success"]
HEADERS += ["bound_px", "bound_success", "floor_px", "net_px", "net_success"]


def main(argv: list[str] | None = None) -> int:
    p = parser("georef_budget", "geo-referencing error budget: each simulated effect switched off in turn")
    p.add_argument("--frames", type=int, default=None, help="frames per scene and variant (30, quick 4)")
    p.add_argument("--scenes", type=str, default=None, help="default: all nine (quick: 08)")
    p.add_argument(
        "--joint-shift", action="store_true", help="the matcher's joint_shift option (off by default)"
    )
    args = p.parse_args(argv)
    n = args.frames or (4 if args.quick else 30)
    scene_ids = (
        [s.strip() for s in args.scenes.split(",") if s.strip()]
        if args.scenes
        else (["08"] if args.quick else list(SCENE_IDS))
    )
    opts = GeorefOptions(joint_shift=args.joint_shift)
    results: dict[str, dict[str, Any]] = {}
    for sid in scene_ids:
        t0 = time.perf_counter()
        scene = make_scene(sid, seed=args.seed)
        cache: dict[Any, Any] = {}
        results[sid] = {
            name: run_variant(scene, v, n, args.seed, opts, cache) for name, v in VARIANTS.items()
        }
        rows = [
            [
                name,
                f"{r['fixes']}/{r['n']}",
                r["bias_along_sun_px"],
                r["bias_across_sun_px"],
                r["std_along_sun_px"],
                r["std_across_sun_px"],
                r["mean_px"],
                r["success_rate"],
                r["bound_px"],
                r["bound_success"],
                r["bound_floor_px"],
                r["bound_net_px"],
                r["bound_net_success"],
            ]
            for name, r in results[sid].items()
        ]
        sun = scene.sun
        title = (
            f"scene {sid} ({scene.name}), sun {sun.intensity:g} / az {np.degrees(sun.azimuth_rad):.0f} / "
            f"el {np.degrees(sun.elevation_rad):.0f} deg; errors in frame px (GSD {AGL_M / INTR.fx:.3f} m) "
            f"[{time.perf_counter() - t0:.0f} s]"
        )
        print(table(HEADERS, rows, title=title), flush=True)
        print()
    write_json(
        args.json,
        dict(
            bench="georef_budget",
            quick=bool(args.quick),
            settings=dict(
                frames_per_scene_and_variant=n,
                seed=args.seed,
                agl_m=AGL_M,
                presumed_sun_deg=[10.0, 0.0, 60.0],
                joint_shift=args.joint_shift,
                dem_degradation=DEGRADATION,
                uniform_albedo=UNIFORM_ALBEDO,
                variants=VARIANTS,
                definitions=__doc__,
            ),
            scenes=results,
        ),
    )
    return 0
