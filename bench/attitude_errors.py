"""Terrain SLAM against attitude errors it cannot see: an autopilot tilt bias and a misaligned camera mount.

``python -m bench attitude_errors [--quick] [--json PATH] [--scene 08] [--degrees 0.2] [--duration-s 190]``

The ``terrain_slam`` benchmark gives the estimator the autopilot's attitude with white noise (0.003 rad
per sample) and a camera mounted exactly as configured. On a vehicle neither holds: an autopilot's roll and
pitch carry a slowly varying error (accelerometer bias, board-level trim, vibration), and a camera is
mounted to within a fraction of a degree of where its configuration says. For a nadir camera a small tilt
and a sideways shift look nearly alike in the image, so the estimator cannot find either error from the
frames: the geo-fixes pin the ground point under the camera, and the body is placed about height x angle
away from where it is (0.35 m per 0.2 degree at 100 m). This benchmark measures that on the Table 7 flight
(circular, 190 s, 100 m above ground, the scene's lighting):

- ``none``: the ``terrain_slam`` setting;
- ``tilt bias``: every ATTITUDE sample's roll off by ``--degrees`` (as a whole flight's bias), flown twice:
  with the defaults, and with ``attitude_floor_sigma_rad`` set to that angle (the estimator told its
  autopilot's attitude may be that far off beyond its noise);
- ``tilt wander``: roll and pitch off by a first-order Gauss-Markov error of ``--degrees`` (1 sigma) and
  ``--wander-tau-s`` (10 s), a slowly wandering AHRS horizon, the same two ways;
- ``mount error``: the camera pitched forward by ``--degrees`` on the vehicle, the estimator told nadir;
- ``mount error, calibrated``: the same frames, the estimator given the true mount (what
  ``cameras.nadir.extra_rpy_deg`` in the configuration is for);
- ``compass bias``: the compass (initial yaw and every ATTITUDE yaw) off by each of ``--compass-degrees``
  (default 5 and 20) for the whole flight, over ``--compass-scene`` (default 01: the start-up heading search
  needs the matcher's peak at 0.3 or more, which 08 is at the edge of), with the heading search
  (``heading_from_matcher``, trying headings within ``heading_search_deg`` = 30 of the compass's) and without;
- ``no compass``: the same with the heading ``--no-compass-degrees`` (120) off, as on Mars with no heading
  reference worth the name, the search over the whole turn (``heading_search_deg`` = 180).

Per case the APE (evo, no alignment) mean / rmse / max, its horizontal and vertical parts, and the mean
horizontal error in the vehicle's heading frame (forward, right; ``mean_error_forward_right_m``): a roll bias
leaves the body off to one side all the way round the circle, which the mean north / east error would average
out. And whether the covariance sent with the estimates owns up to the error: its mean horizontal 1-sigma and
the share of estimates whose error lies inside their own 95 % ellipse (``covariance_consistency``; 95 % when
right, far less when over-confident: a compass off by more than its ``compass_sigma_deg`` (2) says so).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np

from bench.common import parser, table, write_json
from bench.terrain_slam import FlightSpec, _public, run_flight
from companion.estimators.terrain_lba import TerrainLbaOptions


def main(argv: list[str] | None = None) -> int:
    p = parser("attitude_errors", __doc__.splitlines()[0])
    p.add_argument("--scene", default="08", help="scene id (default 08, the Tables 4 and 5 scene)")
    p.add_argument("--degrees", type=float, default=0.2, help="size of the tilt bias and the mount error")
    p.add_argument("--duration-s", type=float, default=None, help="flight duration (default 190, quick 30)")
    p.add_argument(
        "--compass-degrees",
        type=float,
        nargs="+",
        default=[5.0, 20.0],
        help="compass biases of the compass cases",
    )
    p.add_argument("--compass-scene", default="01", help="scene of the compass case")
    p.add_argument(
        "--no-compass-degrees",
        type=float,
        default=120.0,
        help="heading error of the no-compass case, searched over +-180 deg (0: no such case)",
    )
    p.add_argument("--wander-tau-s", type=float, default=10.0, help="time constant of the tilt wander case")
    p.add_argument(
        "--cases",
        nargs="+",
        default=None,
        help="run only these cases (none, tilt_bias, tilt_wander, mount_error, compass_bias_5, ...)",
    )
    a = p.parse_args(argv)
    dur = a.duration_s or (30.0 if a.quick else 190.0)
    ang = float(np.radians(a.degrees))
    lba = replace(TerrainLbaOptions(), backend_apply="fixed_delay", w_geo=10.0)
    cases: list[tuple[str, FlightSpec, dict[str, str], tuple[str, ...]]] = [
        ("none", FlightSpec(a.scene, "circular", dur, a.seed), {"terrain_lba": "none"}, ()),
        (
            "tilt_bias",
            FlightSpec(a.scene, "circular", dur, a.seed, tilt_bias_rad=(ang, 0.0)),
            {
                "default": f"tilt bias (roll {a.degrees:g} deg)",
                "floor": f"tilt bias (roll {a.degrees:g} deg), attitude floor set to it",
            },
            (),
        ),
        (
            "tilt_wander",
            FlightSpec(
                a.scene, "circular", dur, a.seed, tilt_wander_rad=ang, tilt_wander_tau_s=a.wander_tau_s
            ),
            {
                "default": f"tilt wander ({a.degrees:g} deg, {a.wander_tau_s:g} s)",
                "floor": f"tilt wander ({a.degrees:g} deg, {a.wander_tau_s:g} s), attitude floor set to it",
            },
            (),
        ),
        (
            "mount_error",
            FlightSpec(a.scene, "circular", dur, a.seed, mount_error_rpy_rad=(0.0, ang, 0.0)),
            {
                "assumed_nadir": f"mount error (pitch {a.degrees:g} deg)",
                "calibrated": f"mount error (pitch {a.degrees:g} deg), calibrated",
            },
            ("calibrated",),
        ),
    ]
    compass = [(f"compass_bias_{d:g}", d, f"compass {d:g} deg off") for d in a.compass_degrees]
    if a.no_compass_degrees:
        d = a.no_compass_degrees
        compass.append((f"no_compass_{d:g}", d, f"no compass: heading {d:g} deg off, search +-180"))
    cases += [
        (
            case,
            FlightSpec(a.compass_scene, "circular", dur, a.seed, yaw_bias_rad=float(np.radians(deg))),
            {
                "heading_search": f"{what} (scene {a.compass_scene})",
                "compass_only": f"{what}, no heading search",
            },
            (),
        )
        for case, deg, what in compass
    ]
    no_heading = replace(lba, backend=replace(lba.backend, heading_from_matcher=False))
    # without a compass the search covers the whole turn (``estimator.terrain_lba.heading_search_deg``)
    # and trusts no heading until the terrain gives one (``compass_sigma_deg`` 180)
    lba_360 = replace(lba, georef=replace(lba.georef, rs_sweep_deg=180.0), compass_sigma_rad=float(np.pi))
    # told how far the autopilot's roll / pitch may be off beyond its noise (``attitude_floor_sigma_rad``)
    floor = replace(lba, attitude_floor_sigma_rad=ang)

    def options(case: str, name: str) -> TerrainLbaOptions:
        if name == "compass_only":
            return no_heading
        if name == "floor":
            return floor
        return lba_360 if case.startswith("no_compass") else lba

    unknown = set(a.cases or ()) - {c[0] for c in cases}
    if unknown:
        p.error(f"unknown case(s) {sorted(unknown)}; the cases: {[c[0] for c in cases]}")
    cases = [c for c in cases if not a.cases or c[0] in a.cases]
    results: dict[str, Any] = {"quick": a.quick, "seed": a.seed, "scene": a.scene, "degrees": a.degrees}
    rows = []
    for case, spec, names, known in cases:
        print(f"  {case}: scene {spec.scene_id} circular {dur:.0f}s", flush=True)
        r = run_flight(
            spec,
            {n: options(case, n) for n in names},
            log=False,
            mount_known=known,
        )
        f = r["_flight"]
        print(f"    done in {f['wall_s']:.0f}s", flush=True)
        for n, label in names.items():
            res = _public(r[n])
            key = case if len(names) == 1 else f"{case}/{n}"
            results[key] = {"label": label, "flight": f, "terrain_lba": res}
            rows.append(
                [label]
                + [
                    res.get(k, float("nan"))
                    for k in ("mean", "rmse", "max", "horizontal_mean", "vertical_mean")
                ]
                + [*res.get("mean_error_forward_right_m", [float("nan")] * 2)]
                + [
                    res.get("covariance_consistency", {}).get(k, float("nan"))
                    for k in ("sigma_mean_m", "within_95")
                ]
            )
        write_json(a.json, results)
    print(
        table(
            [
                "case",
                "mean/m",
                "rmse/m",
                "max/m",
                "horiz/m",
                "vert/m",
                "fwd/m",
                "right/m",
                "sigma/m",
                "in 95 %",
            ],
            rows,
            f"terrain_lba, scene {a.scene} circular {dur:.0f}s, attitude errors the estimator does not know",
        )
    )
    return 0
