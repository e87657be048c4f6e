"""The companion daemon: wiring, threads, health and clean start/stop.

Threads (see docs/architecture.md):
- Zenoh callback threads decode frames and ``put`` them in a ``FrameHandoff`` (latest wins, drops counted);
- the MAVLink link's reader thread delivers attitude / IMU / altimeter samples into a bounded inbox;
- the estimator thread takes a complete frame set, feeds the estimator the samples that arrived before it,
  runs ``on_frames`` and sends the estimate (rate-capped) — one estimate per frame, sent as soon as it exists;
- the status thread logs one line a second and publishes the same as JSON on Zenoh.
Nothing upstream waits on anything downstream.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from companion.clock import CompanionClock
from companion.handoff import FrameHandoff
from companion.types import (
    AltimeterSample,
    AttitudeSample,
    Estimator,
    Frame,
    ImuSample,
    LocalPositionSample,
    PoseEstimate,
)

Sample = AttitudeSample | ImuSample | AltimeterSample | LocalPositionSample
"""What the autopilot link delivers to the estimator thread."""

log = logging.getLogger("companion")


def _params_note(check: dict[str, Any] | None) -> str:
    """Status-line suffix when the autopilot's parameter check found problems (details in the log)."""
    if not check or not check.get("problems"):
        return ""
    return f"  AUTOPILOT PARAMS {check['worst'].upper()}: {', '.join(sorted(check['problems']))}"


def _record_note(rec: dict[str, Any] | None) -> str:
    """Status-line suffix while the inputs are recorded: its size, and what went wrong with it."""
    if not rec:
        return ""
    if rec.get("stopped"):
        return f"  REC STOPPED ({rec['stopped']})"
    lost = rec.get("dropped", 0) + rec.get("errors", 0)
    return f"  rec {rec.get('mbytes', 0):.0f} MB" + (f" LOST {lost}" if lost else "")


def _tlog_note(tlog: dict[str, Any] | None) -> str:
    """Status-line suffix when the link's MAVLink log (``mavlink.tlog``) failed and stopped."""
    return "  TLOG STOPPED" if tlog and tlog.get("errors") else ""


def _clock_note(st: dict[str, Any]) -> str:
    """Status-line suffix once the wall clock has been stepped (``CompanionClock``): the last step, how many."""
    n = st.get("clock_steps") or 0
    if not n:
        return ""
    return f"  clock stepped {st.get('clock_step_s', 0.0):+.1f} s" + (f" ({n} steps)" if n > 1 else "")


def _sigma_note(sigma_h_m: float | None) -> str:
    """The estimate's own horizontal 1-sigma (root of the trace of its north-east covariance), if any."""
    if sigma_h_m is None or not math.isfinite(sigma_h_m):
        return ""
    return f" sigma {sigma_h_m:.2f} m"


def format_status_line(st: dict[str, Any]) -> str:
    """The one-line summary of a status dict (``Daemon.status``; what ``companion watch`` prints too)."""
    link = st["link"]
    reasons = st["frames"].get("decode_errors", {})
    bad = sum(reasons.values())
    bad_s = f"{bad}" + (f" ({', '.join(f'{k} {v}' for k, v in sorted(reasons.items()))})" if bad else "")
    not_sent = sum(v for k, v in st["not_sent"].items() if k != "no_estimate")
    return (
        f"in {st['fps_in']:5.1f} fps  out {st['fps_out']:5.1f} fps  "
        f"lat p50 {st['latency_p50_ms']:5.1f} ms p99 {st['latency_p99_ms']:5.1f} ms  "
        f"drop {st['frames_dropped_stale']}  bad {bad_s}  unsent {not_sent}  q {st['quality']:.2f}  "
        f"est {st['estimate_status']}{_sigma_note(st.get('sigma_h_m'))}  link {link.get('state', '?')}"
        f"{'' if link.get('timesync', True) else ' (no timesync)'}"
        f"{_params_note(link.get('params_check'))}"
        f"{''.join(f'  {w}' for w in st.get('estimator', {}).get('warnings', {}).values())}"
        f"{_record_note(st.get('inputs_record'))}"
        f"{_tlog_note(link.get('tlog'))}"
        f"{_clock_note(st)}"
    )


def feed_sample(estimator: Estimator, s: Sample) -> None:
    """Hand one autopilot sample to the estimator's method for its kind (the daemon's inbox, the replay)."""
    if isinstance(s, AttitudeSample):
        estimator.on_attitude(s)
    elif isinstance(s, ImuSample):
        estimator.on_imu(s)
    elif isinstance(s, AltimeterSample):
        estimator.on_altimeter(s)
    else:
        estimator.on_local_position(s)


def estimator_report(estimator: Estimator) -> dict[str, Any]:
    """The estimator's counters, no-fix reasons and warnings, those it has (status topic, replay summary)."""
    return {
        k: dict(v)
        for k in ("counters", "no_fix_reasons", "warnings")
        if isinstance(v := getattr(estimator, k, None), dict)
    }


class AutopilotLink(Protocol):
    """What the daemon needs from the MAVLink side (``companion.io.autopilot.AutopilotLinkAdapter``)."""

    def start(
        self, on_attitude: Callable, on_imu: Callable, on_altimeter: Callable, on_local_position: Callable
    ) -> None: ...

    def send_estimate(self, estimate: PoseEstimate) -> str | None:
        """Send; return None when sent, else the reason it was not (e.g. 'no_timesync', 'link_down')."""
        ...

    def status(self) -> dict[str, Any]: ...

    def stop(self) -> None: ...


class InputSink(Protocol):
    """Where the daemon records its inputs (``companion.io.input_recorder.InputRecorder``): each autopilot
    sample with its arrival time, each frame set the estimator took with the time its samples were drained."""

    def put(self, item: Any, log_us: int) -> None: ...

    def status(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


class EstimateSink(Protocol):
    """Where the daemon records each estimate and its outcome (``companion.io.estimate_log.EstimateLog``)."""

    def write(self, est: PoseEstimate, outcome: str) -> None: ...

    def status(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


@dataclass
class DaemonCounters:
    estimates: int = 0
    sent: int = 0
    not_sent: dict[str, int] = field(default_factory=dict)
    estimator_errors: int = 0
    samples_dropped: int = 0

    def count_not_sent(self, reason: str) -> None:
        self.not_sent[reason] = self.not_sent.get(reason, 0) + 1


class LatencyWindow:
    """Frame capture to send latency over the last N frames (ms)."""

    def __init__(self, n: int = 500) -> None:
        self._v: deque[float] = deque(maxlen=n)
        self._lock = threading.Lock()

    def add(self, ms: float) -> None:
        with self._lock:
            self._v.append(ms)

    def percentiles(self) -> tuple[float, float]:
        with self._lock:
            if not self._v:
                return float("nan"), float("nan")
            a = np.fromiter(self._v, float)
        return float(np.percentile(a, 50)), float(np.percentile(a, 99))


class Daemon:
    """Runs one estimator between a frame hand-off and an autopilot link."""

    def __init__(
        self,
        estimator: Estimator,
        handoff: FrameHandoff,
        link: AutopilotLink,
        *,
        max_rate_hz: float = 30.0,
        status_period_s: float = 1.0,
        publish_status: Callable[[str], None] | None = None,
        frame_counters: Callable[[], dict[str, Any]] | None = None,
        inbox_size: int = 4096,
        estimate_log: EstimateSink | None = None,
        input_recorder: InputSink | None = None,
        prepare: Callable[[dict[str, Frame]], dict[str, Frame]] | None = None,
        clock: CompanionClock | None = None,
    ) -> None:
        self.estimator = estimator
        self.handoff = handoff
        self.link = link
        self.min_interval_us = int(1e6 / max_rate_hz)
        self.status_period_s = status_period_s
        self.publish_status = publish_status
        self.frame_counters = frame_counters or (lambda: {})
        self.counters = DaemonCounters()
        self.latency = LatencyWindow()
        self.clock = clock or CompanionClock()
        self._clock_steps_seen = 0
        self._inbox: deque[Sample] = deque()
        self._inbox_size = inbox_size
        self._inbox_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._last_sent_stamp_us: int | None = None
        self._last_quality = float("nan")
        self._last_status = ""
        self._rate_prev: tuple[float, int, int] | None = None
        self.last_estimate: PoseEstimate | None = None
        self.estimate_log = estimate_log
        self.input_recorder = input_recorder
        self.prepare = prepare
        """Applied to each frame set before the estimator (lens undistortion, ``companion.undistort``)."""

    # -- inputs from the link thread -----------------------------------------------------------------
    def _enqueue(self, sample: Sample) -> None:
        with self._inbox_lock:
            if len(self._inbox) >= self._inbox_size:
                self._inbox.popleft()
                self.counters.samples_dropped += 1
            self._inbox.append(sample)
            # arrival time taken under the inbox lock: a sample recorded as arriving before a drain's time
            # is one that drain took (the recording then replays in the order the estimator saw)
            arrival_us = self.clock.now_us()
        if self.input_recorder is not None:
            self.input_recorder.put(sample, arrival_us)

    def _drain_inbox(self) -> int:
        """Feed the estimator every sample that has arrived, in stamp order; returns the drain's time (us)."""
        with self._inbox_lock:
            items = list(self._inbox)
            self._inbox.clear()
            drained_us = self.clock.now_us()
        for s in sorted(items, key=lambda s: s.stamp_us):
            feed_sample(self.estimator, s)
        return drained_us

    # -- lifecycle ----------------------------------------------------------------------------------
    def start(self) -> None:
        self.link.start(self._enqueue, self._enqueue, self._enqueue, self._enqueue)
        for target, name in ((self._estimator_loop, "estimator"), (self._status_loop, "status")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        log.info("companion started: estimator cameras %s", ",".join(self.handoff.cameras))

    def stop(self) -> None:
        self._stop.set()
        self.handoff.wake()
        for t in self._threads:
            t.join(timeout=5.0)
        self.link.stop()
        try:
            self.estimator.close()
        except Exception:  # noqa: BLE001 - shutting down: log, never raise
            log.exception("estimator close failed")
        if self.estimate_log is not None:
            self.estimate_log.close()
        if self.input_recorder is not None:
            self.input_recorder.close()
        st = self.status()
        log.info("companion stopped: %s", self.status_line(st))
        log.info("totals: sent %d, not sent %s, estimator %s", st["sent"], st["not_sent"], st["estimator"])

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    # -- the estimator thread -----------------------------------------------------------------------
    def _estimator_loop(self) -> None:
        while not self._stop.is_set():
            frames = self.handoff.take(timeout_s=0.2)
            if frames is None:
                continue
            drained_us = self._drain_inbox()
            if self.input_recorder is not None:
                for frame in frames.values():
                    self.input_recorder.put(frame, drained_us)
            self.process(frames)

    def process(self, frames: dict[str, Frame]) -> PoseEstimate | None:
        """Run the estimator on one frame set, send the result, record it in the estimates log. Never raises."""
        if self.prepare is not None:
            try:
                frames = self.prepare(frames)
            except ValueError as exc:  # a frame of another size than its camera's calibration: count, go on
                self.counters.count_not_sent("bad_frame_size")
                log.warning("frame set skipped: %s", exc)
                return None
        try:
            est = self.estimator.on_frames(frames)
        except Exception:  # noqa: BLE001 - bad input must not kill the daemon: count, log, go on
            self.counters.estimator_errors += 1
            log.exception("estimator failed on frame set at %s", {k: f.stamp_us for k, f in frames.items()})
            return None
        if est is None:
            self.counters.count_not_sent("no_estimate")
            return None
        self.counters.estimates += 1
        self.last_estimate = est
        self._last_quality = est.quality
        outcome = self._send(est, frames)
        if outcome == "sent":
            self.counters.sent += 1
        else:
            self.counters.count_not_sent(outcome)
        if self.estimate_log is not None:
            self.estimate_log.write(est, outcome)
        return est

    def _send(self, est: PoseEstimate, frames: dict[str, Frame]) -> str:
        """Send ``est`` if it may go: "sent", or the reason it did not."""
        if not est.is_sendable():
            return f"status_{est.status.value}" if est.status.value != "ok" else "not_finite"
        if (
            self._last_sent_stamp_us is not None
            and est.stamp_us - self._last_sent_stamp_us < self.min_interval_us
        ):
            # ArduPilot silently drops external-nav samples faster than its minimum interval: cap here
            return "rate_cap"
        reason = self.link.send_estimate(est)
        if reason is not None:
            return reason
        self._last_sent_stamp_us = est.stamp_us
        capture_us = min(f.stamp_us for f in frames.values())
        self.latency.add((self.clock.now_us() - capture_us) / 1000.0)
        return "sent"

    # -- health ------------------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        clk = self.clock
        clk.now_us()  # notices a step even when no frame or message has come since
        if clk.steps != self._clock_steps_seen:
            self._clock_steps_seen = clk.steps
            log.warning(
                "the wall clock was stepped by %+.3f s: the companion's time goes on without the step (its records "
                "are now %.3f s behind the wall clock; frames stamped across the step are refused); keep the clock "
                "from stepping in flight (deploy/README.md, section 2)",
                clk.last_step_us * 1e-6,
                clk.correction_us * 1e-6,
            )
        h = self.handoff.counters
        p50, p99 = self.latency.percentiles()
        t = time.monotonic()
        fps_in = fps_out = float("nan")
        if self._rate_prev is not None:
            dt = t - self._rate_prev[0]
            if dt > 0:
                fps_in = (h.received - self._rate_prev[1]) / dt
                fps_out = (self.counters.sent - self._rate_prev[2]) / dt
        self._rate_prev = (t, h.received, self.counters.sent)
        est = self.last_estimate
        return {
            "fps_in": fps_in,
            "fps_out": fps_out,
            "frames_received": h.received,
            "frames_dropped_stale": h.dropped_stale,
            "frames_dropped_unpaired": h.dropped_unpaired,
            "frame_sets": h.taken,
            "estimates": self.counters.estimates,
            "sent": self.counters.sent,
            "not_sent": dict(self.counters.not_sent),
            "estimator_errors": self.counters.estimator_errors,
            "latency_p50_ms": p50,
            "latency_p99_ms": p99,
            "quality": self._last_quality,
            "estimate_status": est.status.value if est is not None else "none",
            "position_ned_m": None if est is None else [round(float(v), 2) for v in est.p_body_in_world_m],
            # the estimate's own horizontal 1-sigma (m): what the autopilot is told to trust it to
            "sigma_h_m": None if est is None else float(np.sqrt(est.covariance[0, 0] + est.covariance[1, 1])),
            "frames": self.frame_counters(),
            "link": self.link.status(),
            "estimates_log": None if self.estimate_log is None else self.estimate_log.status(),
            "inputs_record": None if self.input_recorder is None else self.input_recorder.status(),
            "estimator": estimator_report(self.estimator),
            # wall-clock steps taken out of the companion's time since start, the last one's size and their sum (s)
            "clock_steps": clk.steps,
            "clock_step_s": clk.last_step_us * 1e-6,
            "clock_behind_wall_s": clk.correction_us * 1e-6,
        }

    def status_line(self, st: dict[str, Any] | None = None) -> str:
        return format_status_line(self.status() if st is None else st)

    def _status_loop(self) -> None:
        while not self._stop.wait(self.status_period_s):
            try:
                st = self.status()
                line = self.status_line(st)
                log.info("%s", line)
                if self.publish_status is not None:
                    self.publish_status(json.dumps(st, default=float))
            except Exception:  # noqa: BLE001 - health reporting must never stop the daemon
                log.exception("status report failed")
