"""Command line of the simulator.

- ``sim``: the simulated vehicle (autopilot + camera) as its own process, for a companion to fly with;
  ``--world europa`` flies paper 2's visible + thermal camera pair over Europa (``--trajectory 1..10``);
- ``demo``: the README's main job — starts ``sim`` and ``companion run`` on loopback, shows progress,
  prints the error table at the end (computed with evo) and writes a plot and TUM trajectories;
- ``record`` / ``replay``: Zenoh camera frames to and from rosbag2 (MCAP) bags, ``recover``: a readable bag
  from one whose recorder was killed (sim_bridge.recording);
- ``flight-bag``: a simulated Europa flight written as a rosbag2 with its IMU, range finder, odometry and
  truth, for ``companion replay`` (sim_bridge.flight_bag);
- ``sitl-camera``: the nadir camera for an ArduPilot / PX4 SITL (sim_bridge.sitl_bridge, deploy/SITL.md).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from pathlib import Path

from sim_bridge.autopilot_link import IMU_MESSAGES
from sim_bridge.sim import WORLDS, SimConfig, world_defaults

MARS_TRAJECTORIES = ["circular", "forward", "scanning"]
EUROPA_TRAJECTORIES = [str(i) for i in range(1, 11)]


def _add_sim_args(p: argparse.ArgumentParser, worlds: bool = False) -> None:
    """The flight options. worlds: also ``--world`` (mars | europa), whose defaults then fill the
    options left out (``sim``; the demo flies Mars only)."""
    d = SimConfig()
    p.add_argument("--scene", default=d.scene_id, help="built-in Mars scene 01..09 (default %(default)s)")
    p.add_argument("--seed", type=int, default=d.seed, help="terrain / site and noise seed")
    if worlds:
        eu = world_defaults("europa")
        p.add_argument("--world", default="mars", choices=list(WORLDS), help="(default %(default)s)")
        p.add_argument(
            "--trajectory",
            default=None,
            choices=MARS_TRAJECTORIES + EUROPA_TRAJECTORIES,
            help=f"mars: {', '.join(MARS_TRAJECTORIES)} (default {d.trajectory}); europa: paper 2's 1..10 "
            f"(default {eu['trajectory']})",
        )
        p.add_argument(
            "--duration",
            type=float,
            default=None,
            help=f"seconds (mars default {d.duration_s:g}; europa: the trajectory, {eu['duration_s']:g}, cut here)",
        )
    else:
        p.add_argument("--trajectory", default=d.trajectory, choices=MARS_TRAJECTORIES)
        p.add_argument("--duration", type=float, default=d.duration_s, help="seconds (default %(default)s)")
    p.add_argument("--speed", type=float, default=d.speed_mps, help="m/s (default %(default)s; mars)")
    p.add_argument("--height", type=float, default=d.height_agl_m, help="m above mean ground (mars)")
    if worlds:
        p.add_argument(
            "--camera-rate",
            type=float,
            default=None,
            help=f"Hz (mars default {d.camera_rate_hz:g}, europa {eu['camera_rate_hz']:g}: frame pairs)",
        )
    else:
        p.add_argument("--camera-rate", type=float, default=d.camera_rate_hz, help="Hz (default %(default)s)")
    p.add_argument("--start-delay", type=float, default=None, help="s before take-off (sim: 0, demo: 2)")
    p.add_argument(
        "--compass-offset",
        type=float,
        default=0.0,
        help="the simulated compass this many degrees off for the whole flight (demo: the companion's "
        "initial heading too)",
    )
    p.add_argument(
        "--imu-message",
        default="highres",
        choices=list(IMU_MESSAGES),
        help="the autopilot's IMU stream: highres (HIGHRES_IMU, PX4), raw (RAW_IMU, ArduPilot's default "
        "SRn_RAW_SENS stream), scaled (SCALED_IMU) or none until a peer asks with "
        "MAV_CMD_SET_MESSAGE_INTERVAL (default %(default)s)",
    )
    p.add_argument(
        "--wait-companion",
        type=float,
        default=0.0,
        help="wait up to this many s for a companion's HEARTBEAT before the start delay",
    )


def sim_config_from_args(a: argparse.Namespace, **kw) -> SimConfig:
    """The flight the common options describe (``sim`` and ``demo`` share them); options left out take
    the world's defaults (``sim_bridge.sim.world_defaults``)."""
    world = getattr(a, "world", "mars")
    wd = world_defaults(world)
    trajectory = wd["trajectory"] if a.trajectory is None else a.trajectory
    valid = MARS_TRAJECTORIES if world == "mars" else EUROPA_TRAJECTORIES
    if trajectory not in valid:
        raise SystemExit(
            f"sim_bridge: --trajectory {trajectory!r} is not a {world} trajectory ({', '.join(valid)})"
        )
    return SimConfig(
        scene_id=a.scene,
        seed=a.seed,
        trajectory=trajectory,
        duration_s=wd["duration_s"] if a.duration is None else a.duration,
        speed_mps=a.speed,
        height_agl_m=a.height,
        camera_rate_hz=wd["camera_rate_hz"] if a.camera_rate is None else a.camera_rate,
        world=world,
        origin_lat_lon_alt=wd["origin_lat_lon_alt"],
        compass_offset_deg=a.compass_offset,
        imu_message=a.imu_message,
        **kw,
    )


def _param(text: str) -> tuple[str, float]:
    """NAME=VALUE of ``--param``."""
    name, sep, value = text.partition("=")
    try:
        if not sep or not name.strip():
            raise ValueError
        return name.strip().upper(), float(value)
    except ValueError:
        raise SystemExit(f"sim_bridge: --param wants NAME=VALUE (e.g. VISO_TYPE=0), got {text!r}") from None


def cmd_sim(a: argparse.Namespace) -> int:
    """Run the simulated vehicle; progress as JSON lines on stdout (the demo reads them)."""
    from sim_bridge.sim import SimVehicle, save_result

    cfg = sim_config_from_args(
        a,
        zenoh_listen=tuple(a.zenoh_listen),
        mavlink=a.mavlink,
        camera_key=a.camera_key,
        visible_key=a.visible_key,
        thermal_key=a.thermal_key,
        out_dir=a.out,
        drop_every=a.drop_every,
        start_delay_s=a.start_delay or 0.0,
        wait_companion_s=a.wait_companion,
        autopilot_params=tuple(_param(x) for x in a.param),
    )

    def progress(rep: dict) -> None:
        print(json.dumps({"progress": rep}), flush=True)

    vehicle = SimVehicle(cfg, progress=progress)
    signal.signal(signal.SIGTERM, lambda *_: vehicle.stop())
    signal.signal(signal.SIGINT, lambda *_: vehicle.stop())
    # SIGUSR1 reboots the simulated autopilot (its clock restarts at 0): for tests and demos of recovery
    signal.signal(signal.SIGUSR1, lambda *_: vehicle.autopilot.reboot())
    print(json.dumps({"ready": True, "distance_m": vehicle.distance_m()}), flush=True)
    res = vehicle.run()
    summary = save_result(res, Path(cfg.out_dir), cfg, vehicle.traj, vehicle.t0_us)
    print(json.dumps({"done": summary}), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="sim_bridge", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    ps = sub.add_parser("sim", help="run the simulated autopilot + camera (or Europa's camera pair)")
    _add_sim_args(ps, worlds=True)
    ps.add_argument("--zenoh-listen", action="append", default=None, help="Zenoh endpoint to listen on")
    ps.add_argument(
        "--mavlink",
        default=SimConfig().mavlink,
        help="autopilot side: udpin:HOST:PORT, tcpin:..., serial:...",
    )
    ps.add_argument("--camera-key", default=SimConfig().camera_key, help="mars: the nadir camera's key")
    ps.add_argument("--visible-key", default=SimConfig().visible_key, help="europa: the visible camera's key")
    ps.add_argument("--thermal-key", default=SimConfig().thermal_key, help="europa: the thermal camera's key")
    ps.add_argument("--drop-every", type=int, default=0, help="skip publishing every n-th frame")
    ps.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set a simulated autopilot parameter (e.g. VISO_TYPE=0 to see a misconfigured vehicle)",
    )
    ps.add_argument("--out", default="runs/sim", help="directory for truth.tum, estimate.tum, summary")
    pd = sub.add_parser("demo", help="fly the companion against the simulator on loopback (README main job)")
    _add_sim_args(pd)
    pd.add_argument("--estimator", default="terrain_lba", choices=["georef", "terrain_lba"])
    pd.add_argument("--out", default=None, help="run directory (default runs/demo-<time>)")
    pd.add_argument("--config", default="configs/sim_mars.toml", help="companion config template")
    pd.add_argument(
        "--record-inputs",
        action="store_true",
        help="the companion records what its estimator is given (RUN/inputs, ~2.3 MB/s) for companion replay",
    )
    from sim_bridge.flight_bag import add_flight_bag_parser
    from sim_bridge.recording import add_record_parser, add_recover_parser, add_replay_parser
    from sim_bridge.sitl_bridge import add_sitl_camera_parser

    add_flight_bag_parser(sub)
    add_record_parser(sub)
    add_replay_parser(sub)
    add_recover_parser(sub)
    add_sitl_camera_parser(sub)
    a = ap.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stderr
    )
    if getattr(a, "func", None) is not None:  # flight-bag / record / replay / recover / sitl-camera
        return int(a.func(a))
    if a.cmd == "sim":
        if a.zenoh_listen is None:
            a.zenoh_listen = list(SimConfig().zenoh_listen)
        return cmd_sim(a)
    from sim_bridge.demo import run_demo

    return run_demo(a)
