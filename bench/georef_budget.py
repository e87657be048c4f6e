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
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from bench.common import parser, table, write_json
from bench.georef import AGL_M, DEGRADATION, INTR, PRESUMED_SUN, sample_frames
from companion.georef.georef import GeoReferencer, GeorefOptions
from sim_bridge.render import VisibleRenderer
from sim_bridge.terrain import SCENE_IDS, degrade_dem, make_scene

UNIFORM_ALBEDO = 0.25  # the scenes' base Mars albedo

VARIANTS: dict[str, dict[str, bool]] = {
    # name: (true DEM, coarsen only, uniform albedo, known sun)
    "as_benchmarked": dict(true_dem=False, coarse_only=False, uniform_albedo=False, known_sun=False),
    "known_sun": dict(true_dem=False, coarse_only=False, uniform_albedo=False, known_sun=True),
    "true_dem": dict(true_dem=True, coarse_only=False, uniform_albedo=False, known_sun=False),
    "uniform_albedo": dict(true_dem=False, coarse_only=False, uniform_albedo=True, known_sun=False),
    "coarse_dem_uniform_albedo": dict(true_dem=False, coarse_only=True, uniform_albedo=True, known_sun=False),
    "ideal": dict(true_dem=True, coarse_only=False, uniform_albedo=True, known_sun=True),
}


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
    errs, ms = [], []
    for fr in frames:
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
    )


HEADERS = ["variant", "fixes", "bias_along", "bias_across", "std_along", "std_across", "mean_px", "success"]


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
