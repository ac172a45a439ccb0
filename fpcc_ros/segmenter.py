"""The `segmenter` node (`fpcc_segmenter`): PointCloud2 in, instances out (DESIGN.md §3).

Thin on purpose: parameters, pub/sub, a newest-frame slot and timing. The per-frame work is
:func:`fpcc_ros.frame.process_cloud`. The subscription callback only parks the newest cloud in
a one-message slot; a worker thread segments whatever is newest when it is free, so the node
never works through a queue of stale frames (dropped frames are counted and reported).
"""
from __future__ import annotations

# First, before numpy's and rclpy's threads exist: one malloc arena for all threads, so that the
# worker's frames reuse freed memory (fpcc_ros.heap); a thread that allocated earlier keeps an
# arena of its own, which the worker could be given. (The imports below come after it on purpose.)
from fpcc_ros.heap import retain_freed_memory

retain_freed_memory()

import math
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy
from geometry_msgs.msg import PoseArray
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import (HistoryPolicy, QoSProfile, ReliabilityPolicy, DurabilityPolicy)
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from msg_tools.msg_types import RCLPY
from msg_tools.point_cloud2 import CloudFormatError

from fpcc_ros.frame import process_cloud
from fpcc_ros.model_card import MAX_GLOBAL_STRIDE
from fpcc_ros.node_shutdown import StopRequest, spin_until_stopped
from fpcc_ros.node_diagnostics import (THRESHOLD_PARAMS, HealthReporter, ModelInfo, Reading,
                                       Thresholds)
from fpcc_ros.onnx_model import FpccModel, ModelLoadError, default_model_path
from fpcc_ros.pipeline import AUTO_VOXEL, ConfigError, Pipeline, PipelineConfig

NODE_NAME = "fpcc_segmenter"
# Reliable + keep-last-1: a reliable camera driver's ~5 MB clouds arrive intact across processes
# (best-effort loses most UDP fragments), and depth 1 means the newest frame replaces older ones.
INPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                       reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                        reliability=ReliabilityPolicy.RELIABLE)
PIPELINE_PARAMS = ("part_radius", "screening_factor", "score_threshold", "min_points", "roi_min",
                   "roi_max", "voxel_size", "feature_gate", "center_merge", "center_prototype",
                   "view_axis", "global_stride", "clustering")
MODEL_PARAMS = ("model", "providers", "threads")


@dataclass(frozen=True)
class _Param:
    name: str
    kind: int
    description: str
    low: float | None = None
    high: float | None = None
    read_only: bool = False


def _describe(p: _Param) -> ParameterDescriptor:
    desc = ParameterDescriptor(name=p.name, type=p.kind, description=p.description,
                               read_only=p.read_only)
    if p.kind == ParameterType.PARAMETER_DOUBLE and p.low is not None:
        desc.floating_point_range = [FloatingPointRange(from_value=float(p.low),
                                                        to_value=float(p.high), step=0.0)]
    if p.kind == ParameterType.PARAMETER_INTEGER and p.low is not None:
        desc.integer_range = [IntegerRange(from_value=int(p.low), to_value=int(p.high), step=1)]
    return desc


PARAMS = (
    _Param("model", ParameterType.PARAMETER_STRING,
           "Path to the FPCC-Net .onnx (its card .json beside it). Empty = the shipped default. "
           "Changing it loads and checks the new model, then swaps it in between frames."),
    _Param("providers", ParameterType.PARAMETER_STRING_ARRAY,
           "onnxruntime execution providers in priority order, e.g. [CUDAExecutionProvider, "
           "CPUExecutionProvider]. The active ones are logged."),
    _Param("part_radius", ParameterType.PARAMETER_DOUBLE,
           "d_max of the part in metres: farthest surface point from its geometric center "
           "(`fpcc part-info MESH` prints it). Default: the model card's.", 0.0001, 10.0),
    _Param("screening_factor", ParameterType.PARAMETER_DOUBLE,
           "gamma: NMS suppresses other center candidates within gamma * part_radius.", 0.05, 5.0),
    _Param("score_threshold", ParameterType.PARAMETER_DOUBLE,
           "theta: points with a predicted center score above this are center candidates "
           "(paper: 0.6).", 0.0, 0.999),
    _Param("min_points", ParameterType.PARAMETER_INTEGER,
           "Instances with fewer input points get label 0.", 0, 10_000_000),
    _Param("roi_min", ParameterType.PARAMETER_DOUBLE_ARRAY,
           "[x, y, z] lower corner of the crop box in the cloud's frame (m). Empty = no lower bound."),
    _Param("roi_max", ParameterType.PARAMETER_DOUBLE_ARRAY,
           "[x, y, z] upper corner of the crop box in the cloud's frame (m). Empty = no upper bound."),
    _Param("voxel_size", ParameterType.PARAMETER_DOUBLE,
           "Voxel edge (m) for downsampling before the network; labels are carried back to "
           "every input point. 0 = off, -1 = auto (the card's voxel_factor * part_radius).",
           -1.0, 1.0),
    _Param("feature_gate", ParameterType.PARAMETER_DOUBLE,
           "Points farther than this from every nearby center in embedding space get no "
           "instance (rejects tote and floor). Default: the model card's.", 0.01, 100.0),
    _Param("center_merge", ParameterType.PARAMETER_DOUBLE,
           "Two centers within 2 part_radius whose embeddings are closer than this are one part "
           "(lets a small screening_factor separate parallel elongated parts without splitting "
           "each). 0 = off. Default: the model card's.", 0.0, 10.0),
    _Param("center_prototype", ParameterType.PARAMETER_DOUBLE,
           "Each center is compared with the points by the mean embedding of its neighbours "
           "within this many part radii that lie within the loss's pull margin (0.5) of it "
           "(less noisy than one point's). 0 = the center point's own, as in the paper. "
           "Default: the model card's.", 0.0, 2.0),
    _Param("global_stride", ParameterType.PARAMETER_INTEGER,
           "The network's global feature (a max over each block) taken over every s-th point "
           "of the block instead of all: 1 = every point, exact; 4 cuts the network's time by "
           "about a sixth at no measured accuracy cost for the shipped model (8 cost 2.6 F1 "
           "points). Needs a model whose graph takes it (scripts/optimize_onnx.py). Default: "
           "the model card's.", 1, MAX_GLOBAL_STRIDE),
    _Param("view_axis", ParameterType.PARAMETER_STRING,
           "The direction the camera looks along in the cloud's frame: +z (a camera optical "
           "frame), -z (a z-up world or robot-base frame, camera above the bin), +x, -x, +y, -y; "
           "auto = +z when the points sit in front of the frame's origin as a camera sees them, "
           "else -z. The network sees the cloud turned into the camera's view; outputs stay in "
           "the cloud's frame."),
    _Param("clustering", ParameterType.PARAMETER_STRING,
           "paper: every point to the nearest center in feature space (paper §3.2); connected: "
           "geometric fragments (DBSCAN) of which each goes to the center its points agree on, "
           "touching parts split by their centers, a fragment without a center its own instance "
           "(fragment settings from the model card). Default: the model card's."),
    _Param("threads", ParameterType.PARAMETER_INTEGER,
           "onnxruntime intra-op threads (0 = onnxruntime's default: all cores).", 0, 256),
    _Param("max_input_age", ParameterType.PARAMETER_DOUBLE,
           "Skip frames whose header stamp is older than this many seconds (0 = off).",
           0.0, 3600.0),
    *(_Param(t.name, ParameterType.PARAMETER_DOUBLE, t.description, t.low, t.high)
      for t in THRESHOLD_PARAMS),
)


class _WarnThrottle:
    """One warning per distinct problem per period, with a count of the ones held back.

    ``key`` must come from a small fixed set (a problem kind, an exception type), never from
    message text: text carries the publisher's values, which would defeat the throttle.
    """

    MAX_TEXT = 600  # a hostile header (thousands of fields, huge names) must not flood the log

    def __init__(self, logger: Any, period_s: float = 5.0):
        self._logger, self._period = logger, period_s
        self._last: dict[str, tuple[float, int]] = {}
        self._lock = threading.Lock()
        self._closed = False

    def close(self) -> None:
        """No more warnings (shutdown: the worker must not log through a node being destroyed);
        returns once a warning being written is out."""
        with self._lock:
            self._closed = True

    def warn(self, key: str, text: str) -> None:
        with self._lock:
            if not self._closed:
                self._warn(key, text)

    def _warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        last, held = self._last.get(key, (-math.inf, 0))
        if now - last >= self._period:
            more = f" ({held} more like this since the last warning)" if held else ""
            if len(text) > self.MAX_TEXT:
                text = text[:self.MAX_TEXT] + "..."
            self._logger.warning(text + more)
            self._last[key] = (now, 0)
        else:
            self._last[key] = (last, held + 1)


class SegmenterNode(Node):
    """Loads the model and starts taking frames at construction (the managed variant,
    fpcc_ros.managed_segmenter, does the same steps on lifecycle transitions)."""

    def __init__(self, **kwargs: Any):
        super().__init__(NODE_NAME, **kwargs)
        self._setup()
        self._pipeline = self._build_pipeline(self._param_values())
        self._log_model(self._pipeline)
        self._create_outputs(self.create_publisher)
        self._create_input()
        self._start_worker()

    def _setup(self) -> None:
        """Parameters, the frame slot, counters, the periodic log and /diagnostics: what the
        node has before (and without) a model."""
        self._throttle = _WarnThrottle(self.get_logger())
        self._declare_parameters()
        self._pipeline: Pipeline | None = None
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self._slot_lock = threading.Condition()
        self._newest: tuple[PointCloud2, float] | None = None
        self._publish_gate = threading.Lock()   # held by the worker while it publishes
        self._publishing = True                 # False once shutdown() closed the gate
        self._running = False
        self._worker: threading.Thread | None = None
        self._sub = None
        self.stats = _Stats()
        self._view_axes: dict[str, str] = {}   # frame_id -> the last view axis logged
        self._report_timer = self.create_timer(10.0, self._report)
        self._health = HealthReporter(self, self._diagnostic_reading)

    def _create_outputs(self, create_publisher: Any) -> None:
        """``create_publisher``: the node's own, or a lifecycle node's create_lifecycle_publisher."""
        self._pub_cloud, self._pub_instances, self._pub_markers = (
            create_publisher(msg_type, topic, OUTPUT_QOS,
                             qos_overriding_options=QoSOverridingOptions.with_default_policies())
            for msg_type, topic in ((PointCloud2, "segmented_points"), (PoseArray, "instances"),
                                    (MarkerArray, "instance_markers")))

    def _create_input(self) -> None:
        self._sub = self.create_subscription(
            PointCloud2, "points", self._on_cloud, INPUT_QOS,
            qos_overriding_options=QoSOverridingOptions.with_default_policies(),
            event_callbacks=SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible_qos))
        self.get_logger().info(f"listening on {self._sub.topic_name}")

    def _start_worker(self) -> None:
        self._running = True
        self._worker = threading.Thread(target=self._work, name="fpcc_worker", daemon=True)
        self._worker.start()

    # ---- parameters -------------------------------------------------------------------------
    def _declare_parameters(self) -> None:
        """Card-derived defaults (part_radius, θ, γ, gate, merge, prototype) come from the card of the model
        the node starts with (`-p model:=...`), so a per-part model runs with its own
        calibration unless a parameter says otherwise."""
        from fpcc_ros.model_card import card_path_for, load_card, ModelCardError
        model_param = next(p for p in PARAMS if p.name == "model")
        start_model = self.declare_parameter("model", "", _describe(model_param)).value
        try:
            card = load_card(card_path_for(Path(start_model) if start_model
                                           else default_model_path()))
        except (ModelCardError, OSError):
            card = None  # reported when the model loads
        defaults: dict[str, Any] = {
            "model": "", "providers": ["CPUExecutionProvider"],
            "part_radius": card.part_radius if card else 0.05,
            "screening_factor": card.screening_factor if card else 1.0,
            "score_threshold": card.score_threshold if card else 0.6,
            "min_points": PipelineConfig.min_points, "voxel_size": AUTO_VOXEL,
            "feature_gate": card.feature_gate if card else 1.0,
            "center_merge": card.center_merge if card else 0.0,
            "center_prototype": card.center_prototype if card else 0.0,
            "view_axis": PipelineConfig.view_axis,
            "global_stride": card.global_stride if card else 1,
            "clustering": card.clustering if card else PipelineConfig.clustering,
            "threads": 0, "max_input_age": 0.0,
            **{t.name: t.default for t in THRESHOLD_PARAMS},
        }
        for p in PARAMS:
            if p.name == "model":
                continue
            if p.kind == ParameterType.PARAMETER_DOUBLE_ARRAY:
                self.declare_parameter(p.name, Parameter.Type.DOUBLE_ARRAY, _describe(p))
            else:
                self.declare_parameter(p.name, defaults[p.name], _describe(p))

    def _param_values(self) -> dict[str, Any]:
        # Array parameters declared without a value (no crop) read back as None.
        return {p.name: self.get_parameter_or(p.name, Parameter(p.name, value=None)).value
                for p in PARAMS}

    def _build_pipeline(self, values: dict[str, Any], model: FpccModel | None = None) -> Pipeline:
        """Raises ModelLoadError or ConfigError with a message fit for the user."""
        if model is None:
            path = values["model"] or str(default_model_path())
            model = FpccModel(path, providers=list(values["providers"] or []) or None,
                              threads=int(values["threads"]))
        pipeline_values = {k: values[k] for k in PIPELINE_PARAMS}
        for key in ("roi_min", "roi_max"):
            pipeline_values[key] = list(pipeline_values[key]) if pipeline_values[key] else None
        config = PipelineConfig.from_card(model.card, **pipeline_values)
        return Pipeline(model, config)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        current = self._pipeline
        if current is None:   # no model yet: the values are checked when it loads (configure)
            return SetParametersResult(successful=True)
        values = self._param_values()
        values.update({p.name: p.value for p in params})
        try:
            if any(p.name in MODEL_PARAMS for p in params):
                candidate = self._build_pipeline(values)
                self._log_model(candidate)
            else:
                candidate = self._build_pipeline(values, model=current.model)
        except (ModelLoadError, ConfigError, TypeError, ValueError) as exc:
            self.get_logger().warning(f"parameter change rejected: {exc}")
            return SetParametersResult(successful=False, reason=str(exc))
        self._pipeline = candidate   # one reference swap: the worker picks it up next frame
        return SetParametersResult(successful=True)

    def _log_model(self, pipeline: Pipeline) -> None:
        m, c = pipeline.model, pipeline.config
        self.get_logger().info(
            f"model {m.path} ({m.card.name}), providers {m.active_providers}, part_radius "
            f"{c.part_radius:.4f} m, voxel {c.effective_voxel_size * 1000:.1f} mm; "
            f"health: {m.health_line()}")
        if m.collapsed:
            self.get_logger().warning(
                f"model {m.path}: more than 10 % of a layer's channels are dead (the network "
                "collapsed in training): expect poor instances; retrain it with this release")

    # ---- frames -----------------------------------------------------------------------------
    def _on_cloud(self, msg: PointCloud2) -> None:
        with self._slot_lock:
            if self._newest is not None:
                self.stats.dropped_stale += 1
            self._newest = (msg, time.perf_counter())
            self.stats.received += 1
            self._slot_lock.notify()

    def _on_incompatible_qos(self, event: Any) -> None:
        self._throttle.warn("qos", (
            f"a publisher on {self._sub.topic_name} has incompatible QoS (policy "
            f"{event.last_policy_kind}); camera drivers that publish best effort need "
            f"-p qos_overrides.{self._sub.topic_name}.subscription.reliability:=best_effort "
            "and the shared-memory Fast DDS profile (README: 'Large clouds')"))

    def _work(self) -> None:
        while True:
            with self._slot_lock:
                while self._newest is None and self._running:
                    self._slot_lock.wait(timeout=0.5)
                if not self._running:
                    self._drop_pending()
                    return
                msg, received_at = self._newest
                self._newest = None
            try:
                self._process(msg, received_at)
            except Exception as exc:  # noqa: BLE001 - the worker must outlive any one frame
                if not self._running or not self.context.ok():
                    # shutting down (SIGINT/SIGTERM): the frame in flight cannot be published
                    self.stats.dropped_at_shutdown += 1
                    with self._slot_lock:
                        self._drop_pending()
                    return
                self._frame_failed(exc)

    def _drop_pending(self) -> None:
        """At shutdown: count the frame still waiting in the slot (call with the lock held)."""
        if self._newest is not None:
            self.stats.dropped_at_shutdown += 1
            self._newest = None

    def _process(self, msg: PointCloud2, received_at: float) -> None:
        max_age = float(self.get_parameter("max_input_age").value)
        if max_age > 0 and self._age_s(msg) > max_age:
            self.stats.skipped_old += 1
            self._throttle.warn("age", f"skipping a frame {self._age_s(msg):.2f} s old "
                                       f"(max_input_age={max_age} s)")
            return
        pipeline = self._pipeline
        try:
            out = process_cloud(msg, pipeline, RCLPY)
        except CloudFormatError as exc:
            self.stats.invalid += 1
            self.stats.last_invalid = str(exc)
            self._throttle.warn(f"bad:{exc.kind}", f"dropped a malformed PointCloud2: {exc}")
            return
        except Exception as exc:  # noqa: BLE001 - one bad frame must not stop the node
            self._frame_failed(exc)
            return
        with self._publish_gate:
            if not self._publishing:   # shutdown() gave up waiting for this frame
                self.stats.dropped_at_shutdown += 1
                return
            self._note_view_axis(msg.header.frame_id, out.result.view_axis,
                                 pipeline.config.view_axis)
            self._pub_cloud.publish(out.cloud)
            self._pub_instances.publish(out.instances)
            self._pub_markers.publish(out.markers)
            self.stats.record(time.perf_counter() - received_at, out.result.num_instances)

    def _frame_failed(self, exc: Exception) -> None:
        self.stats.failed += 1
        self.stats.last_failure = f"{type(exc).__name__}: {exc}"
        self._throttle.warn(f"err:{type(exc).__name__}",
                            f"frame failed ({self.stats.last_failure}); continuing")

    def _note_view_axis(self, frame_id: str, axis: str, setting: str) -> None:
        """Log the camera direction the network was shown, once per frame id and whenever it
        changes: a wrong one (view_axis auto on an unusual frame) costs most of the accuracy."""
        if self._view_axes.get(frame_id) == axis:
            return
        self._view_axes[frame_id] = axis
        how = "detected (view_axis auto)" if setting == "auto" else "from view_axis"
        self.get_logger().info(
            f"frame '{frame_id}': the camera looks along {axis} ({how}); the network sees the "
            "cloud turned into that view. Set -p view_axis:=+z (camera optical frame) or -z "
            "(z-up world frame, camera above the bin) if this is wrong")

    def _age_s(self, msg: PointCloud2) -> float:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        return self.get_clock().now().nanoseconds * 1e-9 - stamp

    def _report(self) -> None:
        s = self.stats.snapshot()
        if s["received"]:
            self.get_logger().info(
                f"{s['published']} frames out, {s['dropped_stale']} stale dropped, "
                f"{s['invalid']} invalid, {s['failed']} failed; latency median "
                f"{s['latency_ms_median']:.0f} ms, last {s['last_instances']} instances")

    def _diagnostic_reading(self, state: str = "active", state_error: str = "") -> Reading:
        """For /diagnostics (fpcc_ros.node_diagnostics), on the executor thread: copies of
        counters and references only, never a wait on the worker."""
        pipeline, values = self._pipeline, self._param_values()
        return Reading(
            counters=self.stats.snapshot(), latencies_ms=self.stats.latencies_ms(),
            last_instances=self.stats.last_instances,
            input_topic=self.resolve_topic_name("points"),
            thresholds=Thresholds.from_params(values),
            model=ModelInfo.of(pipeline.model) if pipeline else None,
            view_axes=dict(self._view_axes), view_axis_setting=values["view_axis"],
            last_invalid=self.stats.last_invalid, last_failure=self.stats.last_failure,
            state=state, state_error=state_error)

    def totals(self) -> str:
        """One line accounting for every frame received (none lost silently); logged at exit."""
        s = self.stats.snapshot()
        return (
            f"totals: received {s['received']}, published {s['published']}, invalid "
            f"{s['invalid']}, failed {s['failed']}, dropped_stale {s['dropped_stale']}, "
            f"skipped_old {s['skipped_old']}, dropped_at_shutdown {s['dropped_at_shutdown']}")

    def stop_worker(self, timeout_s: float = 5.0) -> bool:
        """Stop taking frames and wait for the one in flight; False if it is still running."""
        with self._slot_lock:
            self._running = False
            self._slot_lock.notify()
        if self._worker is None:
            return True
        self._worker.join(timeout=timeout_s)
        return not self._worker.is_alive()

    def shutdown(self, timeout_s: float = 5.0, flush_s: float = 3.0) -> bool:
        """Stop the node's own work, in the order that leaves no rclpy object in use by another
        thread (issue 26); then destroy_node() is safe. Call it on the thread that spun the
        node, after spinning stopped (no callback can run), with the context still valid.

        The frame in flight is finished and published (up to ``timeout_s``); then the worker may
        no longer publish or log (a frame still inside the network is counted as dropped when it
        comes out), the outputs already published are waited for until matched reliable
        subscribers acknowledged them (up to ``flush_s``: destroying a writer discards what it
        has not delivered, which tore the last frame of a shutdown), and the subscription,
        timers and output publishers are destroyed. False if a frame was still being processed.
        A second call only reports whether the worker has finished.
        """
        if getattr(self, "_shut_down", False):
            return self._worker is None or not self._worker.is_alive()
        self._shut_down = True
        if self._sub is not None:
            self.destroy_subscription(self._sub)   # no new frames reach the slot
            self._sub = None
        finished = self.stop_worker(timeout_s)
        with self._publish_gate:
            self._publishing = False
        self._throttle.close()
        deadline = time.monotonic() + flush_s
        publishers = [p for p in (getattr(self, name, None) for name in
                                  ("_pub_cloud", "_pub_instances", "_pub_markers")) if p]
        unacked = [pub.topic_name for pub in publishers if not pub.wait_for_all_acked(
            Duration(nanoseconds=int(max(0.0, deadline - time.monotonic()) * 1e9)))]
        if unacked:
            self.get_logger().warning(
                f"outputs on {', '.join(unacked)} not acknowledged by every subscriber within "
                f"{flush_s:g} s of shutdown; a subscriber may miss the last frame")
        for timer in list(self.timers):
            self.destroy_timer(timer)
        for pub in publishers:
            self.destroy_publisher(pub)
        return finished


class _Stats:
    """Counters read by the periodic report and by tests."""

    def __init__(self) -> None:
        self.received = self.dropped_stale = self.invalid = self.failed = self.skipped_old = 0
        self.dropped_at_shutdown = 0
        self.published = 0
        self.last_instances = 0
        self.last_invalid = self.last_failure = ""   # what the last one was, for /diagnostics
        self._latency = deque(maxlen=200)

    def record(self, latency_s: float, instances: int) -> None:
        self.published += 1
        self.last_instances = instances
        self._latency.append(latency_s * 1e3)

    def latencies_ms(self) -> list[float]:
        """The last 200 receive-to-publish latencies, newest last."""
        return list(self._latency)

    def snapshot(self) -> dict[str, Any]:
        lat = list(self._latency)
        return {"received": self.received, "published": self.published,
                "dropped_stale": self.dropped_stale, "invalid": self.invalid,
                "failed": self.failed, "skipped_old": self.skipped_old,
                "dropped_at_shutdown": self.dropped_at_shutdown,
                "last_instances": self.last_instances,
                "latency_ms_median": float(np.median(lat)) if lat else math.nan}


def main(args: list[str] | None = None) -> int:
    return run_node(SegmenterNode, args)


def run_node(make_node: Callable[[], "SegmenterNode"], args: list[str] | None = None,
             finished: Callable[["SegmenterNode"], bool] = lambda node: False) -> int:
    """Start ``make_node()``, spin until a signal (or ``finished(node)``), tear down; the exit code.

    SIGINT/SIGTERM only set a flag (fpcc_ros.node_shutdown): rclpy's handlers would shut the
    context down from a thread of their own while this one tears down (issue 26)."""
    stop = StopRequest().install()
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = make_node()
    except (ModelLoadError, ConfigError, ParameterException) as exc:
        # ParameterException: a -p value of the wrong type or out of its declared range
        print(f"[{NODE_NAME}] cannot start: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        spin_until_stopped(executor, lambda: stop.requested or finished(node))
    finally:
        teardown(node, executor)
    return 0


def teardown(node: SegmenterNode, executor: SingleThreadedExecutor) -> None:
    """Stop the worker, log the totals, destroy the node and shut rclpy down (both mains).

    On the thread that spun ``executor``, after it stopped: node.shutdown() (worker joined,
    outputs acknowledged, entities destroyed), then the executor's own guard conditions, the
    node, and last the context -- nothing else is inside rcl by then."""
    finished = node.shutdown()
    totals = node.totals()
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    # After destroy_node: the node logger no longer tries to publish on the (already shut
    # down) /rosout, it only prints.
    logger = rclpy.logging.get_logger(NODE_NAME)
    logger.info(totals)
    if not finished:
        # A frame is still inside onnxruntime/numpy. Letting the interpreter finalize under
        # it aborts in C++ static destructors ("terminate called ..."); leave at once instead.
        logger.warning("1 more frame was still being processed 5 s after shutdown was "
                       "requested; exiting without it")
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
