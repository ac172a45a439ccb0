"""The segmenter's health for `/diagnostics`, worked out from its frame counters.

The node's per-frame path only counts (fpcc_ros.segmenter._Stats); once a second a timer hands a
:class:`Reading` of those cumulative counters to :class:`HealthReporter`, which keeps the last
window of readings (:class:`CounterWindow`), turns the differences into a level and a message
(:func:`evaluate`) and publishes one diagnostic_msgs/DiagnosticArray. Everything except
:class:`HealthReporter` is plain Python, testable without a ROS graph.
"""
from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from fpcc_ros.model_card import card_path_for

OK, WARN, ERROR = 0, 1, 2          # diagnostic_msgs/DiagnosticStatus levels
COUNTERS = ("received", "published", "dropped_stale", "skipped_old", "invalid", "failed")
PERIOD_S = 1.0                     # one DiagnosticArray a second, as diagnostic_updater does
MAX_TEXT = 300                     # a hostile header's text must not bloat every status


@dataclass(frozen=True)
class ThresholdSpec:
    """A node parameter for one threshold (declared, ranged and validated by the node)."""

    name: str
    default: float
    low: float
    high: float
    description: str


THRESHOLD_PARAMS = (
    ThresholdSpec("diagnostics_window", 5.0, 1.0, 600.0,
                  "Seconds of history behind /diagnostics: rates, latency median and p90, and "
                  "the WARN/ERROR rules count the frames of this window."),
    ThresholdSpec("stale_warn_fraction", 0.5, 0.0, 1.0,
                  "/diagnostics WARN 'falling behind the camera' when more than this fraction "
                  "of the clouds received in the window were dropped as stale (a newer one "
                  "came first, or older than max_input_age). 0 = any, 1 = never."),
    ThresholdSpec("input_timeout", 10.0, 0.0, 3600.0,
                  "/diagnostics WARN 'no input' when no cloud has arrived for this many seconds "
                  "while the node takes frames. 0 = off (a camera triggered once per pick)."),
)


@dataclass(frozen=True)
class Thresholds:
    """The values of THRESHOLD_PARAMS (defaults and ranges live there)."""

    window_s: float
    stale_warn_fraction: float
    input_timeout_s: float

    @classmethod
    def from_params(cls, values: Mapping[str, Any]) -> "Thresholds":
        return cls(window_s=float(values["diagnostics_window"]),
                   stale_warn_fraction=float(values["stale_warn_fraction"]),
                   input_timeout_s=float(values["input_timeout"]))


@dataclass(frozen=True)
class ModelInfo:
    path: str
    name: str
    card: str
    providers: tuple[str, ...]

    @classmethod
    def of(cls, model: Any) -> "ModelInfo":
        """From a loaded fpcc_ros.onnx_model.FpccModel."""
        return cls(path=str(model.path), name=model.card.name,
                   card=str(card_path_for(model.path)), providers=tuple(model.active_providers))


@dataclass
class Reading:
    """What the node knows at one tick: cumulative counters and the state of its parts."""

    counters: Mapping[str, int]
    latencies_ms: Sequence[float]       # receive-to-publish, newest last (at least the window's)
    last_instances: int
    input_topic: str
    thresholds: Thresholds
    model: ModelInfo | None = None      # None: no model loaded (a managed node, unconfigured)
    view_axes: Mapping[str, str] = field(default_factory=dict)   # frame_id -> axis used
    view_axis_setting: str = "auto"
    last_invalid: str = ""              # why the last malformed cloud was dropped
    last_failure: str = ""              # the last frame failure (exception type: text)
    state: str = "active"               # lifecycle state; the plain node is always active
    state_error: str = ""               # why the last lifecycle transition failed


@dataclass(frozen=True)
class Window:
    """The differences over the last window of readings."""

    seconds: float                      # time actually covered (less than asked at start-up)
    deltas: Mapping[str, int]
    latencies_ms: Sequence[float]       # the frames published in the window
    since_input_s: float                # since a cloud last arrived (or frames were first taken)

    @property
    def input_rate_hz(self) -> float:
        return self.deltas["received"] / self.seconds if self.seconds > 0 else math.nan

    @property
    def output_rate_hz(self) -> float:
        return self.deltas["published"] / self.seconds if self.seconds > 0 else math.nan


class CounterWindow:
    """Cumulative counters at each tick, kept for the last ``window_s``; differences on demand.

    The input clock (time since a cloud last arrived) runs only while the node takes frames, so
    an inactive managed node is not reported as having lost its camera on activation.
    """

    def __init__(self, start: float):
        self._readings: deque[tuple[float, dict[str, int]]] = deque(
            [(start, dict.fromkeys(COUNTERS, 0))])
        self._last_received = 0
        self._input_clock = start

    def update(self, now: float, counters: Mapping[str, int], latencies_ms: Sequence[float],
               window_s: float, taking_frames: bool = True) -> Window:
        current = {k: int(counters[k]) for k in COUNTERS}
        if current["received"] != self._last_received or not taking_frames:
            self._input_clock = now
        self._last_received = current["received"]
        self._readings.append((now, current))
        # keep one reading at or before the window's start as its base
        while len(self._readings) > 2 and self._readings[1][0] <= now - window_s:
            self._readings.popleft()
        base_t, base = self._readings[0]
        deltas = {k: current[k] - base[k] for k in COUNTERS}
        n = min(deltas["published"], len(latencies_ms))
        recent = list(latencies_ms)[len(latencies_ms) - n:] if n > 0 else []
        return Window(seconds=now - base_t, deltas=deltas, latencies_ms=recent,
                      since_input_s=now - self._input_clock)


@dataclass(frozen=True)
class Status:
    level: int
    message: str
    values: list[tuple[str, str]]


def quantiles_ms(latencies_ms: Sequence[float]) -> tuple[float, float]:
    """(median, p90) of the window's latencies, NaN when none (numpy's linear interpolation)."""
    if len(latencies_ms) == 0:
        return math.nan, math.nan
    values = np.asarray(latencies_ms, dtype=np.float64)
    return float(np.median(values)), float(np.percentile(values, 90))


def _frames(n: int, what: str = "frames") -> str:
    return f"{n} {what[:-1] if n == 1 else what}"


def _short(text: str) -> str:
    return text if len(text) <= MAX_TEXT else text[:MAX_TEXT] + "..."


def evaluate(reading: Reading, window: Window) -> Status:
    """Level and message from the window's differences; key-values from the totals."""
    t, d, span = reading.thresholds, window.deltas, f"{window.seconds:.0f} s"
    problems: list[tuple[int, str]] = []
    if reading.state != "active":
        if reading.state_error:
            problems.append((ERROR, _short(reading.state_error)))
        else:
            what = "model loaded" if reading.model else "no model loaded"
            problems.append((OK, f"{reading.state}: {what}, not taking frames"))
    else:
        if d["failed"]:
            problems.append((ERROR, f"{_frames(d['failed'])} failed in the last {span} "
                                    f"(last: {_short(reading.last_failure)})"))
        stale = d["dropped_stale"] + d["skipped_old"]
        if d["received"] and stale / d["received"] > t.stale_warn_fraction:
            problems.append((WARN, f"falling behind the camera: {stale} of {d['received']} "
                                   f"clouds in the last {span} dropped as stale"))
        if t.input_timeout_s > 0 and window.since_input_s >= t.input_timeout_s:
            problems.append((WARN, f"no input on {reading.input_topic} for "
                                   f"{window.since_input_s:.0f} s"))
        if d["invalid"]:
            problems.append((WARN, f"{_frames(d['invalid'], 'malformed clouds')} in the last "
                                   f"{span} (last: {_short(reading.last_invalid)})"))
    level = max((lvl for lvl, _ in problems), default=OK)
    if problems:   # the worst first
        message = "; ".join(text for _, text in sorted(problems, key=lambda p: -p[0]))
    elif d["published"]:
        message = f"ok: {_frames(d['published'])} out in the last {span}"
    else:
        message = f"ok: waiting for clouds on {reading.input_topic}"
    return Status(level, message, key_values(reading, window))


def key_values(reading: Reading, window: Window) -> list[tuple[str, str]]:
    c = reading.counters
    median, p90 = quantiles_ms(window.latencies_ms)
    model = reading.model
    axes = ", ".join(f"{axis} (frame '{frame}')" for frame, axis in sorted(
        reading.view_axes.items())) or "none yet"
    return [
        ("state", reading.state),
        ("frames received", str(c["received"])),
        ("frames published", str(c["published"])),
        ("frames dropped stale", str(c["dropped_stale"])),
        ("frames skipped old", str(c["skipped_old"])),
        ("frames invalid", str(c["invalid"])),
        ("frames failed", str(c["failed"])),
        ("window (s)", f"{window.seconds:.1f}"),
        ("latency median (ms)", f"{median:.1f}"),
        ("latency p90 (ms)", f"{p90:.1f}"),
        ("input rate (Hz)", f"{window.input_rate_hz:.2f}"),
        ("output rate (Hz)", f"{window.output_rate_hz:.2f}"),
        ("since last input (s)", f"{window.since_input_s:.1f}"),
        ("instances in last frame", str(reading.last_instances)),
        ("model", model.path if model else ""),
        ("model name", model.name if model else ""),
        ("model card", model.card if model else ""),
        ("execution providers", ", ".join(model.providers) if model else ""),
        ("view axis", f"{axes}; setting {reading.view_axis_setting}"),
        ("last malformed input", _short(reading.last_invalid)),
        ("last failure", _short(reading.last_failure)),
    ]


def to_msg(status: Status, name: str, hardware_id: str, stamp: Any) -> Any:
    from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

    array = DiagnosticArray()
    array.header.stamp = stamp
    array.status = [DiagnosticStatus(
        level=bytes([status.level]), name=name, message=status.message,
        hardware_id=hardware_id, values=[KeyValue(key=k, value=v) for k, v in status.values])]
    return array


class HealthReporter:
    """A timer on the node that publishes its DiagnosticArray on `/diagnostics` each second.

    ``read`` is called on the executor thread; it must only copy counters and references, so
    the worker's frames are never waited on.
    """

    def __init__(self, node: Any, read: Callable[[], Reading], period_s: float = PERIOD_S):
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile
        from rclpy.qos_overriding_options import QoSOverridingOptions

        self._node, self._read = node, read
        qualified = node.get_fully_qualified_name().lstrip("/")
        self.name = f"{qualified}: segmentation"
        self._hardware_id = qualified
        self._window = CounterWindow(time.monotonic())
        self._pub = node.create_publisher(
            DiagnosticArray, "/diagnostics", QoSProfile(depth=10),
            qos_overriding_options=QoSOverridingOptions.with_default_policies())
        self._timer = node.create_timer(period_s, self.publish)

    def publish(self) -> None:
        reading = self._read()
        window = self._window.update(time.monotonic(), reading.counters, reading.latencies_ms,
                                     reading.thresholds.window_s,
                                     taking_frames=reading.state == "active")
        status = evaluate(reading, window)
        self._pub.publish(to_msg(status, self.name, self._hardware_id,
                                 self._node.get_clock().now().to_msg()))
