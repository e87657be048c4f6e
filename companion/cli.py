"""Command line of the companion daemon.

    companion run --config configs/sim_mars.toml [--set key=value ...]
    companion check-config configs/sim_mars.toml
    companion check-autopilot --config configs/vehicle_serial_geotiff.toml [--timeout 15]
    companion watch --connect tcp/192.168.1.10:7447 [--count N] [--json]
    companion replay runs/flight-bag --config configs/europa_dual_ekf.toml [--out runs/replay]

``--set`` overrides one key of the file (dotted path, TOML/JSON value), e.g.
``--set mavlink.connection='"serial:/dev/ttyAMA0:921600"'`` or ``--set estimator.kind='"georef"'``.
Exit codes: 0 clean stop, 2 configuration error, 1 failure at start-up.
check-autopilot connects as the daemon would, reads the autopilot's external-vision parameters and prints
what each means for us (``companion.io.autopilot_params``); exit 0 when nothing stops the autopilot from
using the estimates (warnings included), 1 on an error or no autopilot heard, 2 configuration error.
watch prints the status line of a running daemon from anywhere its Zenoh network reaches (the JSON it
publishes on ``companion/status``); exit 1 when none arrives within ``--timeout``.
replay runs the configured estimator over a recorded flight (rosbag2: images, and the IMU, range finder,
odometry and ground truth as ROS messages; ``companion.replay``) as fast as the machine goes, writes the
estimates log and prints the error against the truth when the bag has one; exit 0 when it ran, 2 when the
bag or its topics do not fit the configuration.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import queue
import signal
import sys
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

from companion.config import CompanionConfig, ConfigError, MavlinkConfig, load_config, parse_config

log = logging.getLogger("companion")


def _parse_value(text: str) -> Any:
    """A TOML value (``3``, ``"udpout:..."``, ``[1, 2]``, ``true``) or, failing that, JSON, else the bare string."""
    with contextlib.suppress(tomllib.TOMLDecodeError):
        return tomllib.loads(f"v = {text}")["v"]
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def apply_overrides(cfg: CompanionConfig, sets: list[str], source: str) -> CompanionConfig:
    """Return ``cfg`` with ``key.path=value`` overrides applied and the result validated again."""
    if not sets:
        return cfg
    data = cfg.model_dump(mode="python")
    for item in sets:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected key.path=value")
        key, text = item.split("=", 1)
        node = data
        parts = key.strip().split(".")
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                node[p] = {} if node.get(p) is None else node[p]
            node = node[p]
        node[parts[-1]] = _parse_value(text)
    return parse_config(data, f"{source} (with --set)")


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper()),
        format="%(asctime)s %(levelname)-7s %(name)s: %(message)s",
        stream=sys.stderr,
    )


def cmd_check(path: str, sets: list[str]) -> int:
    cfg = apply_overrides(load_config(path), sets, path)
    cams = ", ".join(f"{n} <- {c.key} ({c.width}x{c.height})" for n, c in cfg.cameras.items())
    print(f"{path}: OK")
    print(f"  estimator {cfg.estimator.kind}; cameras {cams}")
    print(
        f"  mavlink {cfg.mavlink.connection} as {cfg.mavlink.sysid}/{cfg.mavlink.compid}, {cfg.mavlink.message}"
    )
    print(f"  zenoh {cfg.zenoh.mode} connect {cfg.zenoh.connect} listen {cfg.zenoh.listen}")
    if cfg.dem is not None:
        print(f"  dem {cfg.dem.path}")
    records = [
        f"{what} {path}"
        for what, path in (
            ("estimates", cfg.daemon.estimates_log),
            ("inputs", cfg.daemon.record_inputs),
            ("mavlink", cfg.mavlink.tlog),
        )
        if path
    ]
    print(f"  records: {'; '.join(records) if records else 'none'}")
    return 0


def estimator_cameras(cfg: CompanionConfig) -> tuple[str, ...]:
    """Names of the configured cameras the estimator uses (first: the one the autopilot's offset is for)."""
    from companion.ekf.options import cameras_for_mode

    return cameras_for_mode(cfg.estimator.ekf.mode) if cfg.estimator.kind == "vis_thermal_ekf" else ("nadir",)


def link_config(cfg: CompanionConfig) -> MavlinkConfig:
    """The ``[mavlink]`` section as the daemon uses it: the IMU is asked for only by the estimator that
    propagates with it (``vis_thermal_ekf``; the others take their attitude from ATTITUDE)."""
    if cfg.estimator.kind == "vis_thermal_ekf":
        return cfg.mavlink
    return cfg.mavlink.model_copy(update={"request_imu_hz": 0.0})


SENSOR_WATCH_S = 4.0
"""How long ``check-autopilot`` watches the autopilot's sensor streams after reading its parameters (the
link asks for a missing IMU 2 s after the autopilot is first heard)."""


def sensor_findings(cfg: CompanionConfig, received: dict[str, int], seconds: float, link: Any) -> list[Any]:
    """What the estimator needs from the autopilot's streams, from the messages counted over ``seconds``:
    ATTITUDE (the terrain estimators' attitude; the EKF's start), the IMU (the EKF's propagation), the downward
    DISTANCE_SENSOR (every estimator's height above ground)."""
    from companion.io.autopilot_params import ERROR, INFO, OK, WARNING, Finding
    from companion.io.mavlink import IMU_SOURCES

    def rate(name: str) -> float:
        return received.get(name, 0) / seconds

    ekf = cfg.estimator.kind == "vis_thermal_ekf"
    out = []
    att = rate("ATTITUDE")
    out.append(
        Finding("ATTITUDE", f"{att:.0f} Hz", OK, "roll, pitch, yaw")
        if att > 0
        else Finding(
            "ATTITUDE",
            "none",
            WARNING if ekf else ERROR,
            "stream it (ArduPilot SRn_EXTRA1, PX4 onboard mode)",
        )
    )
    src = link.imu_source
    if src is not None and rate(src) > 0:
        out.append(
            Finding(
                "IMU", f"{rate(src):.0f} Hz", OK, f"{src}" + (", the filter's propagation" if ekf else "")
            )
        )
    else:
        asked = (
            f"asked for it {link.imu_requests}x, answer {link.imu_request_result}"
            if link.imu_requests
            else "not asked"
        )
        msg = f"no {'/'.join(IMU_SOURCES)} ({asked}); ArduPilot: SRn_RAW_SENS, PX4: onboard mode"
        out.append(
            Finding(
                "IMU", "none", ERROR if ekf else INFO, msg if ekf else "not used by " + cfg.estimator.kind
            )
        )
    rng = rate("DISTANCE_SENSOR")
    bad = rate("DISTANCE_SENSOR_out_of_range")
    if rng > 0:
        out.append(Finding("DISTANCE_SENSOR", f"{rng:.0f} Hz", OK, "downward range"))
    elif bad > 0:
        out.append(Finding("DISTANCE_SENSOR", "out of range", INFO, "outside its min/max (on the ground?)"))
    else:
        out.append(
            Finding(
                "DISTANCE_SENSOR",
                "none",
                WARNING,
                "no downward rangefinder (RNGFNDn_ORIENT 25; ArduPilot SRn_EXTRA3): height from the estimate",
            )
        )
    return out


def cmd_check_autopilot(cfg: CompanionConfig, timeout_s: float) -> int:
    """Read the autopilot's parameters over the configured link, watch its sensor streams for
    ``SENSOR_WATCH_S``, and print the findings."""
    import time

    from companion.io.autopilot import AutopilotLinkAdapter
    from companion.io.autopilot_params import ERROR

    offset = cfg.cameras[estimator_cameras(cfg)[0]].position_in_body_m
    # the check is not a flight: no MAVLink log of it
    mav_cfg = link_config(cfg).model_copy(update={"tlog": ""})
    link = AutopilotLinkAdapter(mav_cfg, cfg.origin, camera_offset_m=offset)
    link.link.start()
    sensors: list[Any] = []
    try:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and link.check_autopilot() is None:
            time.sleep(0.05)
        findings = link.check_autopilot()
        hb = link.link.autopilot_heartbeat
        if findings is not None:
            heard = link.link.heard_mono or time.monotonic()
            # past the link's IMU request (2 s after the first heartbeat) and its answer, then count
            time.sleep(max(0.0, heard + link.link.options.imu_request_after_s + 1.0 - time.monotonic()))
            before = dict(link.link.received)
            time.sleep(SENSOR_WATCH_S)
            counted = {k: v - before.get(k, 0) for k, v in link.link.received.items()}
            sensors = sensor_findings(cfg, counted, SENSOR_WATCH_S, link.link)
    finally:
        link.stop()
    if findings is None:
        what = "no HEARTBEAT" if hb is None else f"HEARTBEAT from autopilot type {int(hb.autopilot)}"
        print(f"{cfg.mavlink.connection}: {what} within {timeout_s:g} s; only ArduPilot and PX4 are checked")
        return 1
    print(f"{cfg.mavlink.connection}: {link.link.flavour}, {len(link.link.params)} parameters read")
    everything = findings + sensors
    width = max(len(f.param) for f in everything)
    for f in everything:
        print(f"  {f.severity.upper():7s} {f.param:{width}s} = {f.value:10s} {f.message}")
    return 1 if any(f.severity == ERROR for f in everything) else 0


def _print_statuses(inbox: Any, key: str, connect: list[str], count: int, timeout_s: float, raw: bool) -> int:
    """Print status messages from ``inbox`` until ``count`` (0: forever) or ``timeout_s`` without one."""
    from companion.daemon import format_status_line

    shown = 0
    while count <= 0 or shown < count:
        try:
            st = inbox.get(timeout=timeout_s)
        except queue.Empty:
            where = ", ".join(connect) or "multicast scouting"
            print(f"companion watch: no status on {key!r} within {timeout_s:g} s ({where})", file=sys.stderr)
            return 1 if shown == 0 else 0
        if raw:
            line = json.dumps(st, sort_keys=True)
        else:
            try:
                line = format_status_line(st)
            except (KeyError, TypeError, ValueError):
                line = json.dumps(st, sort_keys=True)  # another version's status: show it whole
        print(line, flush=True)
        shown += 1
    return 0


def cmd_watch(connect: list[str], key: str, count: int, timeout_s: float, raw: bool) -> int:
    """Print each status message of a running daemon (its status line, or the JSON with ``raw``)."""
    from companion.io.zenoh_io import StatusSubscriber, open_session

    inbox: queue.Queue[dict[str, Any]] = queue.Queue()
    session = open_session("peer", connect, [], multicast_scouting=not connect)
    sub = StatusSubscriber(session, inbox.put, key)
    code = 0
    try:
        with contextlib.suppress(KeyboardInterrupt):  # Ctrl-C ends the watch, exit 0
            code = _print_statuses(inbox, key, connect, count, timeout_s, raw)
    finally:
        sub.close()
        session.close()
    return code


def configure_opencv(threads: int) -> None:
    """OpenCV's threads per call (``daemon.opencv_threads``); 0 = OpenCV's default, one per core."""
    import cv2

    cv2.setNumThreads(threads if threads > 0 else -1)  # OpenCV: a negative count restores its default


def cmd_run(cfg: CompanionConfig, stop: threading.Event | None = None) -> int:
    """Run the daemon until SIGINT/SIGTERM (or ``stop`` is set). Returns the exit code."""
    from companion.clock import CompanionClock
    from companion.daemon import Daemon
    from companion.factory import build_estimator
    from companion.handoff import FrameHandoff
    from companion.io.autopilot import AutopilotLinkAdapter
    from companion.io.frames import StampGate
    from companion.io.zenoh_io import CameraTopic, FrameSubscriber, StatusPublisher, open_session
    from companion.undistort import frame_undistorter

    stop = stop or threading.Event()
    configure_opencv(cfg.daemon.opencv_threads)
    estimator = build_estimator(cfg)
    estimate_log = None
    if cfg.daemon.estimates_log:
        from companion.io.estimate_log import EstimateLog

        estimate_log = EstimateLog(cfg.daemon.estimates_log)  # OSError: a wrong path fails here, at start
        log.info("recording estimates in %s and %s", estimate_log.csv_path, estimate_log.tum_path)
    tol_us = int(cfg.estimator.ekf.pair_tolerance_ms * 1000)
    handoff = FrameHandoff(tuple(estimator.cameras), pair_tolerance_us=tol_us)
    recorder = None
    if cfg.daemon.record_inputs:
        from companion.io.input_recorder import InputRecorder

        # OSError: a wrong or existing path fails here, at start
        recorder = InputRecorder(
            cfg.daemon.record_inputs,
            {c: "/" + cfg.cameras[c].key.lstrip("/") for c in estimator.cameras},
            config_json=cfg.model_dump_json(),
            min_free_mb=cfg.daemon.record_min_free_mb,
            frames=cfg.daemon.record_frames,
        )
        log.info("recording the estimator's inputs in %s (companion replay reads it)", recorder.path)

    offset = cfg.cameras[estimator_cameras(cfg)[0]].position_in_body_m
    # one time for the frames, the link and the records, without the wall clock's steps
    clock = CompanionClock()
    link = AutopilotLinkAdapter(link_config(cfg), cfg.origin, camera_offset_m=offset, clock_us=clock.now_us)
    if link.link.tlog is not None:
        log.info("logging the autopilot link's messages in %s (mavlogdump.py reads it)", link.link.tlog.path)
    z = cfg.zenoh
    session = open_session(z.mode, z.connect, z.listen, z.multicast_scouting)
    status_pub = StatusPublisher(session, z.status_key)
    topics = {
        name: CameraTopic(cfg.cameras[name].key, cfg.cameras[name].message == "compressed")
        for name in estimator.cameras
    }
    d = cfg.daemon
    subscriber = FrameSubscriber(
        session,
        topics,
        stamp_gate=lambda: StampGate(
            max_future_us=int(d.max_future_ms * 1000), max_age_us=int(d.max_frame_age_ms * 1000)
        ),
        sink=handoff.put,
        clock_us=clock.now_us,
        stamp_from_wall=clock.from_wall,
    )

    def frame_counters() -> dict[str, Any]:
        st = subscriber.stats()
        return {
            # decode failures and stamp refusals, by camera and reason
            "decode_errors": {f"{cam}:{r}": n for cam, s in st.items() for r, n in s["errors"].items()},
            "per_camera": st,
        }

    def publish_status(text: str) -> None:
        status_pub.publish(json.loads(text))

    daemon = Daemon(
        estimator,
        handoff,
        link,
        max_rate_hz=cfg.mavlink.max_rate_hz,
        status_period_s=d.status_period_s,
        publish_status=publish_status,
        frame_counters=frame_counters,
        estimate_log=estimate_log,
        input_recorder=recorder,
        prepare=frame_undistorter({c: cfg.cameras[c].undistorter() for c in estimator.cameras}),
        clock=clock,
    )

    def on_signal(signum: int, _frame: object) -> None:
        log.info("signal %s: stopping", signal.Signals(signum).name)
        stop.set()

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, on_signal)
        signal.signal(signal.SIGTERM, on_signal)
    daemon.start()
    try:
        stop.wait()
    finally:
        daemon.stop()
        subscriber.close()
        status_pub.close()
        session.close()
    return 0


def _config_of_record(bag: str) -> CompanionConfig:
    """The configuration recorded in a daemon's input record; ConfigError when there is none."""
    from rosbags.rosbag2 import ReaderError

    from companion.replay import config_from_bag

    try:
        cfg = config_from_bag(bag)
    except (ReaderError, FileNotFoundError, ValueError) as e:
        raise ConfigError(f"cannot read the configuration recorded in {bag}: {e}") from None
    if cfg is None:
        raise ConfigError(f"{bag} holds no recorded configuration (not a daemon's record): pass --config")
    return cfg


def replay_overrides(a: Any) -> dict[str, str]:
    """``companion replay``'s topic options as ``companion.replay.choose_topics`` overrides."""
    ov: dict[str, str] = {}
    for item in a.camera_topic:
        cam, sep, topic = item.partition("=")
        if not sep or not cam or not topic.startswith("/"):
            raise ValueError(f"--camera-topic {item!r}: expected CAMERA=/topic")
        ov[f"camera:{cam}"] = topic
    for name in ("imu", "attitude", "range", "odometry", "truth"):
        v = getattr(a, f"{name}_topic")
        if v is not None:
            ov[name] = v
    return ov


def _print_replay(s: Any) -> None:
    print(
        f"bag {s.bag}: {s.flight_s:.1f} s of flight, {s.frame_sets} frame sets in {s.wall_s:.1f} s "
        f"({s.ms_per_frame_set:.1f} ms per set in the estimator)"
    )
    for k, n in sorted(s.messages.items()):
        print(f"  {k:10s} {n:7d} messages")
    if s.bad:
        print(f"  skipped bad messages: {', '.join(f'{k} {v}' for k, v in sorted(s.bad.items()))}")
    missing = [k for k in ("imu", "range", "odometry", "truth") if not s.topics.get(k)]
    missing += [] if s.messages.get("attitude") else ["attitude"]
    if missing:
        print(f"  not in the bag: {', '.join(missing)}")
    ns = ", ".join(f"{k} {v}" for k, v in sorted(s.not_sent.items())) or "none"
    print(
        f"  estimates {s.estimates}: would be sent {s.would_send}; not: {ns}; estimator errors {s.estimator_errors}"
    )
    for w in s.estimator.get("warnings", {}).values():
        print(f"  warning: {w}")
    e = s.error_m
    if e and e.get("count"):
        c = s.covariance_consistency or {}
        print(
            f"  error against the truth over {e['count']} estimates: mean {e['mean']:.3f} m, median "
            f"{e['median']:.3f}, p95 {e['p95']:.3f}, max {e['max']:.3f}, final {e['final']:.3f} m "
            f"over {s.distance_m:.1f} m flown"
        )
        if c.get("count"):
            print(
                f"  its own 1-sigma {c['sigma_mean_m']:.3f} m; errors inside their 95 % ellipse "
                f"{100 * c['within_95']:.0f} % (NEES {c['nees_mean']:.2f}, 2 when right)"
            )
    elif s.topics.get("truth"):
        print("  no estimate to compare with the truth")
    print(f"  estimates log: {s.estimates_csv} (TUM: {s.estimates_tum})")
    if s.plot:
        print(f"  plot: {s.plot}")


def cmd_replay(cfg: CompanionConfig, a: Any) -> int:
    """``companion replay``: 0 when the flight was replayed, 2 when the bag or its topics do not fit."""
    from rosbags.rosbag2 import ReaderError

    from companion.factory import build_estimator
    from companion.replay import ReplayError, replay_bag, replay_config

    configure_opencv(cfg.daemon.opencv_threads)
    a.out = a.out.replace("{time}", time.strftime("%Y%m%d-%H%M%S"))
    cfg, fixed = replay_config(cfg, a.rate)
    lba = cfg.estimator.terrain_lba
    try:
        overrides = replay_overrides(a)
        estimator = build_estimator(cfg)
    except (ValueError, OSError) as e:
        print(f"companion: {e}", file=sys.stderr)
        return 2
    next_s = [0.0]

    def progress(s: Any, flight_s: float) -> None:
        if flight_s >= next_s[0]:
            next_s[0] += 10.0
            print(
                f"  t {flight_s:6.1f} s  frame sets {s.frame_sets:5d}  estimates {s.estimates:5d}", flush=True
            )

    pace = "as fast as it goes" if a.rate <= 0 else f"at x{a.rate:g} the recorded pace"
    print(
        f"replaying {a.bag} through {cfg.estimator.kind} ({', '.join(estimator.cameras)}), {pace}", flush=True
    )
    if fixed:
        print(
            f"  terrain_lba: each adjustment used {lba.backend_delay_frames} frames after its key frame "
            "(backend_apply fixed_delay), so every replay gives the same estimates; in flight it was used when "
            "ready: --rate 1 replays at the flight's pace with it"
        )
    try:
        summary = replay_bag(a.bag, cfg, estimator, a.out, overrides, progress, a.order, a.rate, a.truth_tum)
    except (ReplayError, ValueError) as e:
        print(f"companion: {e}", file=sys.stderr)
        return 2
    except (ReaderError, FileNotFoundError) as e:
        print(
            f"companion: cannot read {e.filename if isinstance(e, FileNotFoundError) else a.bag}: {e}",
            file=sys.stderr,
        )
        bag = Path(a.bag)
        if bag.is_dir() and not (bag / "metadata.yaml").exists() and any(bag.glob("*.mcap")):
            print(
                f"  its recorder did not close it (power lost?): python -m sim_bridge recover {a.bag}",
                file=sys.stderr,
            )
        return 2
    _print_replay(summary)
    with open(f"{a.out}/replay_summary.json", "w") as f:
        json.dump(summary.as_dict(), f, indent=2, default=float)
    if a.json:
        print(json.dumps(summary.as_dict(), default=float))
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="companion", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = ap.add_subparsers(dest="cmd", required=True)
    pr = sub.add_parser("run", help="run the daemon")
    pr.add_argument("--config", required=True, help="TOML configuration file")
    pr.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one key")
    pc = sub.add_parser("check-config", help="validate a configuration file and print a summary")
    pc.add_argument("config")
    pc.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    pa = sub.add_parser(
        "check-autopilot", help="read the autopilot's external-vision parameters and check them"
    )
    pa.add_argument("--config", required=True, help="TOML configuration file (its [mavlink] link is used)")
    pa.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one key")
    pa.add_argument("--timeout", type=float, default=15.0, help="seconds to wait for the autopilot (15)")
    pw = sub.add_parser("watch", help="print the status line of a running daemon (its Zenoh status topic)")
    pw.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh endpoint of the companion, e.g. tcp/192.168.1.10:7447 (default: multicast scouting)",
    )
    pw.add_argument("--key", default="companion/status", help="status key (zenoh.status_key)")
    pw.add_argument("--count", type=int, default=0, help="stop after this many messages (0: until Ctrl-C)")
    pw.add_argument("--timeout", type=float, default=10.0, help="give up after this long without a message")
    pw.add_argument("--json", action="store_true", help="print the whole JSON status instead of the line")
    pp = sub.add_parser(
        "replay", help="run the configured estimator over a recorded flight (rosbag2), as fast as it goes"
    )
    pp.add_argument("bag", help="bag directory (MCAP or sqlite3), e.g. from python -m sim_bridge flight-bag")
    pp.add_argument(
        "--config",
        default=None,
        help="TOML configuration file (cameras, estimator); default: the one a daemon's record holds",
    )
    pp.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override one key")
    pp.add_argument(
        "--out",
        default="runs/replay-{time}",
        help="a new directory for the estimates log; {time} = now (default %(default)s)",
    )
    pp.add_argument(
        "--camera-topic",
        action="append",
        default=[],
        metavar="CAMERA=TOPIC",
        help="a camera's image topic (default: its configured key as a topic, /uav/camera/visible)",
    )
    for name, what in (
        ("imu", "sensor_msgs/Imu"),
        ("attitude", "geometry_msgs/QuaternionStamped (default: the Imu's orientation)"),
        ("range", "sensor_msgs/Range"),
        ("odometry", "nav_msgs/Odometry (the start)"),
        ("truth", "geometry_msgs/PoseStamped ground truth"),
    ):
        pp.add_argument(
            f"--{name}-topic",
            default=None,
            help=f"{what} topic (default: the bag's only one; '' = do not use)",
        )
    pp.add_argument(
        "--order",
        default="arrival",
        choices=["arrival", "stamp"],
        help="samples fed before a frame set: those received before it (arrival, default: what the daemon "
        "saw; a daemon's own recording replays to its estimates) or those stamped before it (stamp)",
    )
    pp.add_argument(
        "--rate",
        type=float,
        default=0.0,
        help="0: as fast as it goes (default); 1: at the recorded pace (terrain_lba's back-end then has the "
        "time it had in flight); 2: twice as fast, ...",
    )
    pp.add_argument(
        "--truth-tum",
        default=None,
        help="the truth as a TUM file (Unix s, NED) instead of a topic, e.g. the simulator's truth_clock.tum",
    )
    pp.add_argument("--json", action="store_true", help="print the whole summary as JSON at the end")
    a = ap.parse_args(argv)
    if a.cmd == "watch":
        return cmd_watch(a.connect, a.key, a.count, a.timeout, a.json)
    try:
        if a.cmd == "check-config":
            return cmd_check(a.config, a.set)
        if a.cmd == "replay" and a.config is None:
            cfg = apply_overrides(_config_of_record(a.bag), a.set, a.bag)
        else:
            cfg = apply_overrides(load_config(a.config), a.set, a.config)
    except ConfigError as e:
        print(f"companion: {e}", file=sys.stderr)
        return 2
    if a.cmd == "check-autopilot":
        _setup_logging("WARNING")
        try:
            return cmd_check_autopilot(cfg, a.timeout)
        except (ValueError, OSError) as e:
            print(f"companion: cannot open {cfg.mavlink.connection}: {e}", file=sys.stderr)
            return 1
    if a.cmd == "replay":
        _setup_logging("WARNING")
        return cmd_replay(cfg, a)
    _setup_logging(cfg.daemon.log_level)
    try:
        return cmd_run(cfg)
    except (ValueError, OSError) as e:
        log.error("cannot start: %s", e)
        return 1
