"""Offline replay of a recorded flight through the configured estimator (``companion replay``).

A researcher with a recording (rosbag2, MCAP or sqlite3) of a flight wants to run the estimator on it again
on a bench: after changing a setting, on another machine, as fast as the machine goes and with the same
result every time. ``python -m sim_bridge replay`` publishes a bag's images on Zenoh for a live daemon, in
real time; that serves the terrain estimators, which need only the images and the attitude. The
visible + thermal EKF also needs the autopilot's IMU and range finder, which reach a live daemon over
MAVLink and which a vehicle's bag holds as ROS messages. This module reads all of them from the bag and
drives the estimator the way the daemon does:

- images (``sensor_msgs/msg/Image`` / ``CompressedImage``) are decoded by the daemon's decoder and paired by
  capture time in the daemon's ``FrameHandoff`` (one camera or a synchronised pair);
- every IMU, attitude, range, odometry sample stamped at or before a frame set reaches the estimator before it, in
  stamp order (what the daemon's inbox gives when the telemetry is on time);
- each estimate is written to an estimates log in the daemon's format (``estimates.csv``; the TUM file holds
  those the daemon would have sent) and, when the bag has a ground-truth pose topic, compared with it.

Frame conventions of the ROS messages: ``companion.io.ros_msgs``. The samples are stamped by their header
stamps (the bag must hold every sensor in one clock, as a ROS 2 system's header stamps are).
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import Reader
from scipy.spatial.transform import Rotation

from companion.config import CompanionConfig
from companion.daemon import estimator_report, feed_sample
from companion.handoff import FrameHandoff
from companion.io import ros_msgs
from companion.io.frames import COMPRESSED_MSGTYPE, IMAGE_MSGTYPE, FrameError, decode_frame
from companion.metrics import covariance_consistency, error_stats
from companion.types import AltimeterSample, AttitudeSample, Estimator, Frame, ImuSample, LocalPositionSample
from companion.undistort import frame_undistorter

log = logging.getLogger(__name__)

Sample = AttitudeSample | ImuSample | AltimeterSample | LocalPositionSample


class ReplayError(ValueError):
    """The bag cannot be replayed with this configuration (a topic missing or ambiguous); the message says
    what to pass."""


@dataclass(frozen=True)
class ReplayTopics:
    """The bag's topics each input comes from. ``None``: that input is not in the bag."""

    images: dict[str, str]
    """camera name (the config's) -> image topic"""
    imu: str | None = None
    attitude: str | None = None
    """a QuaternionStamped topic; without one, the Imu messages' orientation gives the attitude"""
    range: str | None = None
    odometry: str | None = None
    truth: str | None = None


def replay_config(cfg: CompanionConfig, rate: float) -> tuple[CompanionConfig, bool]:
    """The configuration a replay runs with, and whether it changed it: at full speed (``rate`` 0) the
    terrain estimator's adjustment is used a fixed number of frames after its key frame instead of when ready
    (``backend_apply``), so the estimates do not depend on the machine's load and two replays agree."""
    t = cfg.estimator.terrain_lba
    if cfg.estimator.kind != "terrain_lba" or rate > 0 or t.backend_apply != "when_ready":
        return cfg, False
    t = t.model_copy(update={"backend_apply": "fixed_delay"})
    return cfg.model_copy(update={"estimator": cfg.estimator.model_copy(update={"terrain_lba": t})}), True


def config_from_bag(bag: str | Path, source: str = "") -> CompanionConfig | None:
    """The configuration a daemon recorded in its input record (``/companion/config``), or None when the bag
    has none. Raises ConfigError if it does not validate (a record from another version of the companion)."""
    from companion.config import parse_config
    from companion.io.input_recorder import CONFIG_TOPIC

    with Reader(Path(bag)) as reader:
        conns = [c for c in reader.connections if c.topic == CONFIG_TOPIC]
        for _conn, _log_ns, raw in reader.messages(connections=conns):
            msg: Any = ros_msgs.TYPESTORE.deserialize_cdr(bytes(raw), ros_msgs.STRING_MSGTYPE)
            return parse_config(json.loads(msg.data), source or f"{bag}:{CONFIG_TOPIC}")
    return None


def _only_topic(types: dict[str, str], msgtype: str, what: str, option: str) -> str | None:
    found = sorted(t for t, m in types.items() if m == msgtype)
    if len(found) > 1:
        raise ReplayError(f"{len(found)} {what} topics ({', '.join(found)}): choose one with {option}")
    return found[0] if found else None


def choose_topics(
    types: dict[str, str],
    cfg: CompanionConfig,
    cameras: tuple[str, ...],
    overrides: dict[str, str] | None = None,
) -> ReplayTopics:
    """Which topic of the bag (``types``: topic -> message type) feeds which input.

    Images: each camera's configured key as a topic (``uav/camera/visible`` -> ``/uav/camera/visible``, how
    zenoh-bridge-ros2dds names it), unless ``overrides["camera:<name>"]`` names another. IMU, attitude,
    range, odometry, truth: ``overrides["imu" | "attitude" | "range" | "odometry" | "truth"]`` or the bag's
    only topic of that type (an empty override string: do not use it). Raises ReplayError naming what is missing or ambiguous."""
    ov = dict(overrides or {})
    images: dict[str, str] = {}
    for cam in cameras:
        topic = ov.get(f"camera:{cam}") or "/" + cfg.cameras[cam].key.lstrip("/")
        want = COMPRESSED_MSGTYPE if cfg.cameras[cam].message == "compressed" else IMAGE_MSGTYPE
        if types.get(topic) not in (IMAGE_MSGTYPE, COMPRESSED_MSGTYPE):
            have = sorted(t for t, m in types.items() if m in (IMAGE_MSGTYPE, COMPRESSED_MSGTYPE))
            raise ReplayError(
                f"camera {cam!r}: no {want} topic {topic} in the bag (image topics: {', '.join(have) or 'none'});"
                f" name it with --camera-topic {cam}=/topic"
            )
        images[cam] = topic
    picked: dict[str, str | None] = {}
    for name, msgtype in (
        ("imu", ros_msgs.IMU_MSGTYPE),
        ("attitude", ros_msgs.QUATERNION_MSGTYPE),
        ("range", ros_msgs.RANGE_MSGTYPE),
        ("odometry", ros_msgs.ODOMETRY_MSGTYPE),
        ("truth", ros_msgs.POSE_MSGTYPE),
    ):
        if name in ov:
            chosen = ov[name] or None
            if chosen is not None and types.get(chosen) != msgtype:
                raise ReplayError(
                    f"--{name}-topic {chosen}: not a {msgtype} topic of the bag ({types.get(chosen)})"
                )
            picked[name] = chosen
        else:
            picked[name] = _only_topic(types, msgtype, msgtype, f"--{name}-topic")
    return ReplayTopics(images, **picked)


@dataclass
class ReplaySummary:
    """What a replay read, what the estimator made of it and, with a truth topic, how right it was."""

    bag: str
    topics: dict[str, Any]
    messages: dict[str, int] = field(default_factory=dict)
    """Messages used per input (images per camera, imu, range, odometry, truth)."""
    bad: dict[str, int] = field(default_factory=dict)
    """Messages skipped, by input and reason (``imu:bad_message``, ``visible:truncated``, ...)."""
    frame_sets: int = 0
    frames_unpaired: int = 0
    estimates: int = 0
    would_send: int = 0
    not_sent: dict[str, int] = field(default_factory=dict)
    estimator_errors: int = 0
    estimator: dict[str, Any] = field(default_factory=dict)
    wall_s: float = 0.0
    flight_s: float = 0.0
    ms_per_frame_set: float = float("nan")
    error_m: dict[str, Any] | None = None
    covariance_consistency: dict[str, Any] | None = None
    distance_m: float | None = None
    estimates_csv: str = ""
    estimates_tum: str = ""
    plot: str = ""
    """``trajectory.png``: the track (over the truth, with the error, when there is one) and the 1-sigma sent."""

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def _count(d: dict[str, int], key: str) -> None:
    d[key] = d.get(key, 0) + 1


def _decode_sample(msgtype: str, raw: bytes, imu_attitude: bool) -> list[Sample]:
    """One telemetry message -> the samples it gives (an Imu with an orientation gives two, unless
    ``imu_attitude`` is False: the attitude comes from its own topic)."""
    msg = ros_msgs.TYPESTORE.deserialize_cdr(raw, msgtype)
    if msgtype == ros_msgs.IMU_MSGTYPE:
        r = ros_msgs.imu_reading(msg)
        return [r.imu] if r.attitude is None or not imu_attitude else [r.imu, r.attitude]
    if msgtype == ros_msgs.QUATERNION_MSGTYPE:
        return [ros_msgs.attitude_sample(msg)]
    if msgtype == ros_msgs.RANGE_MSGTYPE:
        return [ros_msgs.altimeter_sample(msg)]
    return [ros_msgs.local_position_sample(msg)]


def _read_telemetry(
    reader: Reader, conns: dict[str, Any], summary: ReplaySummary
) -> tuple[list[tuple[int, Sample]], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every IMU / attitude / range / odometry sample with its log time (ns), in log-time order, and the truth (stamps us, positions NED,
    attitude quaternions x y z w of R_world_body)."""
    samples: list[tuple[int, Sample]] = []
    t_truth: list[int] = []
    p_truth: list[np.ndarray] = []
    q_truth: list[np.ndarray] = []
    names = {c.topic: name for name, c in conns.items()}
    for conn, log_ns, raw in reader.messages(connections=list(conns.values())):
        name = names[conn.topic]
        try:
            if name == "truth":
                t, p, R = ros_msgs.pose_ned(ros_msgs.TYPESTORE.deserialize_cdr(bytes(raw), conn.msgtype))
                if not np.all(np.isfinite(p)):
                    raise ValueError("non-finite position")
                t_truth.append(t)
                p_truth.append(p)
                q_truth.append(Rotation.from_matrix(R).as_quat())  # R_world_body, x y z w as TUM wants
            else:
                got = _decode_sample(conn.msgtype, bytes(raw), "attitude" not in conns)
                samples.extend((int(log_ns), g) for g in got)
                if name == "imu" and len(got) == 2:
                    _count(summary.messages, "attitude")
        except Exception as exc:  # noqa: BLE001 - a bad message of any kind is counted and skipped
            _count(summary.bad, f"{name}:bad_message")
            log.debug("replay: %s: skipped: %s", conn.topic, exc)
            continue
        _count(summary.messages, name)
    samples.sort(key=lambda s: s[0])  # log-time order (stable: an Imu's two samples stay together)
    order = np.argsort(np.array(t_truth, dtype=np.int64), kind="stable")
    truth = (
        np.array(t_truth, dtype=np.int64)[order],
        np.array(p_truth, float).reshape(-1, 3)[order],
        np.array(q_truth, float).reshape(-1, 4)[order],
    )
    return samples, truth


def _image_frames(
    reader: Reader, conns: dict[str, Any], summary: ReplaySummary
) -> Iterator[tuple[Frame, int]]:
    """Decoded frames with their log times (ns) in the bag's order; undecodable ones counted by camera and
    reason."""
    cams = {c.topic: cam for cam, c in conns.items()}
    seq: dict[str, int] = {}
    for conn, log_ns, raw in reader.messages(connections=list(conns.values())):
        cam = cams[conn.topic]
        seq[cam] = seq.get(cam, 0) + 1
        try:
            frame = decode_frame(bytes(raw), cam, compressed=conn.msgtype == COMPRESSED_MSGTYPE, seq=seq[cam])
        except FrameError as exc:
            _count(summary.bad, f"{cam}:{exc.reason}")
            continue
        _count(summary.messages, cam)
        yield frame, int(log_ns)


def _outcome(est: Any) -> str:
    if est.is_sendable():
        return "would_send"
    return f"status_{est.status.value}" if est.status.value != "ok" else "not_finite"


def replay_bag(
    bag: str | Path,
    cfg: CompanionConfig,
    estimator: Estimator,
    out_dir: str | Path,
    overrides: dict[str, str] | None = None,
    progress: Callable[[ReplaySummary, float], None] | None = None,
    order: str = "arrival",
    rate: float = 0.0,
    truth_tum: str | Path | None = None,
) -> ReplaySummary:
    """Run ``estimator`` over the flight in ``bag`` as fast as it goes. Writes ``out_dir/estimates.csv`` and
    ``.tum`` (and ``truth.tum`` with a truth topic). ``progress(summary, flight_s)`` after each frame set.

    order: which samples reach the estimator before a frame set. "arrival": those logged (received) before the
    set's frames were, in stamp order (what a live daemon does with its inbox; a recording made by the
    daemon, ``daemon.record_inputs``, logs each frame set when the estimator took it, so its replay gives the
    daemon's own estimates). "stamp": every sample stamped at or before the frame set (telemetry always on
    time, as the benchmark feeds its filter).

    rate: 0 = as fast as the estimator goes; R > 0 = each frame set no earlier than its recorded (log) time
    divided by R after the first. An estimator whose back-end runs beside the frames (``terrain_lba``: the
    adjustment in its worker process, applied when ready) uses at each frame what its back-end has finished:
    at ``rate=1`` the back-end has the time between frames it had in flight, as fast as possible less (its
    results come more frames late).

    truth_tum: a TUM file of the truth (Unix seconds, NED, the body's quaternion x y z w) instead of the bag's
    truth topic (``python -m sim_bridge sim`` writes ``truth_clock.tum``).

    Raises ReplayError (topics, an output directory that holds a replay already), rosbags' ReaderError /
    FileNotFoundError (the bag cannot be opened). Closes ``estimator`` in every case."""
    try:
        return _replay(bag, cfg, estimator, out_dir, overrides, progress, order, rate, truth_tum)
    finally:
        estimator.close()


def _replay(
    bag: str | Path,
    cfg: CompanionConfig,
    estimator: Estimator,
    out_dir: str | Path,
    overrides: dict[str, str] | None,
    progress: Callable[[ReplaySummary, float], None] | None,
    order: str,
    rate: float,
    truth_tum: str | Path | None,
) -> ReplaySummary:
    from companion.io.estimate_log import EstimateLog

    if order not in ("arrival", "stamp"):
        raise ValueError(f"order {order!r}: expected arrival or stamp")
    if not rate >= 0:
        raise ValueError(f"rate must be >= 0, got {rate}")
    out = Path(out_dir)
    if (out / "estimates.csv").exists():  # the estimates log appends: never mix two replays in one file
        raise ReplayError(f"{out} holds a replay already (estimates.csv): choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    cams = tuple(estimator.cameras)
    tol_us = int(cfg.estimator.ekf.pair_tolerance_ms * 1000)
    handoff = FrameHandoff(cams, pair_tolerance_us=tol_us)
    prepare = frame_undistorter({c: cfg.cameras[c].undistorter() for c in cams})  # as the daemon does
    with Reader(Path(bag)) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        topics = choose_topics(types, cfg, cams, overrides)
        by_topic = {c.topic: c for c in reader.connections}
        summary = ReplaySummary(
            str(bag),
            {
                **{f"camera:{k}": v for k, v in topics.images.items()},
                "imu": topics.imu,
                "attitude": topics.attitude,
                "range": topics.range,
                "odometry": topics.odometry,
                "truth": topics.truth,
            },
        )
        tele = {
            n: by_topic[t]
            for n in ("imu", "attitude", "range", "odometry", "truth")
            if (t := getattr(topics, n))
        }
        if truth_tum is not None:
            tele.pop("truth", None)
            summary.topics["truth"] = f"file:{truth_tum}"
        samples, (t_truth, p_truth, q_truth) = _read_telemetry(reader, tele, summary)
        if truth_tum is not None:
            t_truth, p_truth, q_truth = read_tum(truth_tum)
        if not samples and not len(t_truth):
            log.warning("replay: no telemetry in %s: the estimator sees images only", bag)
        if order == "stamp":
            samples.sort(key=lambda x: x[1].stamp_us)
        elog = EstimateLog(str(out / "estimates"), tum_outcomes=("would_send",))
        rows: list[tuple[int, np.ndarray, np.ndarray]] = []
        frame_log: dict[tuple[str, int], int] = {}
        pace0: tuple[int, float] | None = None
        k = 0
        spent = 0.0
        t_first: int | None = None
        wall0 = time.perf_counter()
        try:
            image_conns = {c: by_topic[t] for c, t in topics.images.items()}
            for frame, log_ns in _image_frames(reader, image_conns, summary):
                frame_log[(frame.camera, frame.seq)] = log_ns
                handoff.put(frame)
                fs = handoff.take(timeout_s=0.0)
                if fs is None:
                    continue
                stamp = max(f.stamp_us for f in fs.values())
                set_log = max(frame_log.pop((f.camera, f.seq)) for f in fs.values())
                batch: list[Sample] = []
                while k < len(samples) and (
                    samples[k][0] <= set_log if order == "arrival" else samples[k][1].stamp_us <= stamp
                ):
                    batch.append(samples[k][1])
                    k += 1
                if rate > 0:
                    pace0 = pace0 or (set_log, time.perf_counter())
                    wait_s = pace0[1] + (set_log - pace0[0]) * 1e-9 / rate - time.perf_counter()
                    if wait_s > 0:
                        time.sleep(wait_s)
                for sample in sorted(batch, key=lambda x: x.stamp_us):  # stable, as the daemon's inbox
                    feed_sample(estimator, sample)
                summary.frame_sets += 1
                t_first = stamp if t_first is None else t_first
                if prepare is not None:
                    try:
                        fs = prepare(fs)
                    except ValueError as exc:  # a frame of another size than its calibration, as the daemon
                        _count(summary.not_sent, "bad_frame_size")
                        log.warning("frame set skipped: %s", exc)
                        continue
                t0 = time.perf_counter()
                try:
                    est = estimator.on_frames(fs)
                except Exception:  # noqa: BLE001 - as the daemon: count, log, go on with the next frame set
                    summary.estimator_errors += 1
                    log.exception(
                        "estimator failed on frame set at %s", {c: f.stamp_us for c, f in fs.items()}
                    )
                    continue
                finally:
                    spent += time.perf_counter() - t0
                summary.flight_s = (stamp - t_first) * 1e-6
                if est is not None:
                    summary.estimates += 1
                    outcome = _outcome(est)
                    elog.write(est, outcome)
                    if outcome == "would_send":
                        summary.would_send += 1
                        rows.append(
                            (est.stamp_us, np.asarray(est.p_body_in_world_m, float), est.covariance[:2, :2])
                        )
                    else:
                        _count(summary.not_sent, outcome)
                else:
                    _count(summary.not_sent, "no_estimate")
                if progress is not None:
                    progress(summary, summary.flight_s)
        finally:
            elog.close()
    summary.wall_s = time.perf_counter() - wall0
    summary.ms_per_frame_set = 1000.0 * spent / summary.frame_sets if summary.frame_sets else float("nan")
    summary.frames_unpaired = handoff.counters.dropped_unpaired
    summary.estimator = estimator_report(estimator)
    summary.estimates_csv, summary.estimates_tum = str(elog.csv_path), str(elog.tum_path)
    if len(t_truth) >= 2:
        _compare(summary, rows, t_truth, p_truth, q_truth, out)
    elif rows:  # a real flight has no truth: the track and the 1-sigma sent
        t, p, cov = _rows_arrays(rows)
        summary.plot = str(_plot(summary, t, p, cov, np.zeros(0, np.int64), np.zeros((0, 3)), out))
    return summary


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A TUM trajectory (``t x y z qx qy qz qw`` per line, t in seconds) as (stamps us, positions, quaternions),
    sorted by time. Raises ValueError on a file that is not one."""
    a = np.loadtxt(path, ndmin=2)
    if a.shape[1] != 8 or not len(a):
        raise ValueError(f"{path}: not a TUM trajectory ({a.shape[1]} columns, {len(a)} lines)")
    a = a[np.argsort(a[:, 0], kind="stable")]
    return np.round(a[:, 0] * 1e6).astype(np.int64), a[:, 1:4], a[:, 4:8]


def truth_at(t_truth: np.ndarray, p_truth: np.ndarray, t_us: np.ndarray) -> np.ndarray:
    """Truth positions interpolated linearly at ``t_us``; NaN outside the truth's time span."""
    t_us = np.asarray(t_us, np.int64)
    out = np.stack([np.interp(t_us, t_truth, p_truth[:, i]) for i in range(3)], axis=1)
    out[(t_us < t_truth[0]) | (t_us > t_truth[-1])] = np.nan
    return out


def _compare(
    summary: ReplaySummary,
    rows: list[tuple[int, np.ndarray, np.ndarray]],
    t_truth: np.ndarray,
    p_truth: np.ndarray,
    q_truth: np.ndarray,
    out: Path,
) -> None:
    """Errors of the estimates that would have been sent against the truth at their own stamps (no
    alignment: both are in the world frame), their covariance's consistency, the path length; truth.tum and
    trajectory.png."""
    with open(out / "truth.tum", "w") as f:
        for t, p, q in zip(t_truth, p_truth, q_truth, strict=True):
            f.write(f"{t * 1e-6:.6f} " + " ".join(f"{v:.6f}" for v in (*p, *q)) + "\n")
    if not rows:
        summary.error_m = {"count": 0}
        return
    t, p, cov = _rows_arrays(rows)
    pt = truth_at(t_truth, p_truth, t)
    ok = np.all(np.isfinite(pt), axis=1)
    e = p[ok] - pt[ok]
    summary.error_m = error_stats(np.linalg.norm(e, axis=1))
    summary.covariance_consistency = covariance_consistency(e[:, :2], cov[ok])
    inside = (t_truth >= t[0]) & (t_truth <= t[-1])
    summary.distance_m = float(np.sum(np.linalg.norm(np.diff(p_truth[inside], axis=0), axis=1)))
    summary.plot = str(_plot(summary, t, p, cov, t_truth, p_truth, out))


def _rows_arrays(rows: list[tuple[int, np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The estimates that would have been sent as arrays: stamps (N,) us, positions (N,3), horizontal
    covariances (N,2,2)."""
    return (
        np.array([r[0] for r in rows], np.int64),
        np.stack([r[1] for r in rows]),
        np.stack([r[2] for r in rows]),
    )


def _plot(
    summary: ReplaySummary,
    t: np.ndarray,
    p: np.ndarray,
    cov: np.ndarray,
    t_truth: np.ndarray,
    p_truth: np.ndarray,
    out: Path,
) -> Path:
    """``trajectory.png``: the estimates that would have been sent (and the truth, when there is one)."""
    from companion.report import trajectory_plot

    sigma_h = np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))
    title = f"replay of {Path(summary.bag).name}: {len(t)} estimates" + ("" if len(t_truth) else ", no truth")
    return trajectory_plot(out / "trajectory.png", t_truth * 1e-6, p_truth, t * 1e-6, p, title, sigma_h)
