"""Drive a live `segmenter` node over DDS: start it in its own process, feed it clouds, collect
its outputs by stamp. Used by `fpcc demo`, the integration tests and the DDS benchmark.
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import rclpy
from geometry_msgs.msg import PoseArray
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from visualization_msgs.msg import MarkerArray

from msg_tools.msg_types import stamp_ns

from fpcc_ros.node_shutdown import spin_until_stopped

OUTPUT_TOPICS = {"segmented_points": PointCloud2, "instances": PoseArray,
                 "instance_markers": MarkerArray}


def isolated_ros_env(domain_id: int | None = None) -> dict[str, str]:
    """Environment for a node process that only talks to us: own domain, localhost discovery."""
    env = dict(os.environ)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_DOMAIN_ID", str(random.randint(1, 101)))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return env


class NodeProcess:
    """The segmenter in a child process (``python -m fpcc_ros.segmenter --ros-args ...``)."""

    def __init__(self, ros_args: Iterable[str] = (), env: dict[str, str] | None = None,
                 log_path: Path | None = None, cwd: Path | None = None):
        """``cwd``: the child's working directory (where a core dump lands with the kernel's
        default core_pattern; scripts/soak_shutdown.py counts them there)."""
        self.cmd = [sys.executable, "-m", "fpcc_ros.segmenter", "--ros-args", *ros_args]
        self.env = env or isolated_ros_env()
        repo = str(Path(__file__).resolve().parent.parent)
        self.env["PYTHONPATH"] = os.pathsep.join(filter(None, [repo, self.env.get("PYTHONPATH")]))
        # a crash in C code (rclpy, DDS, onnxruntime) leaves the Python stacks in the log
        self.env.setdefault("PYTHONFAULTHANDLER", "1")
        self.log_path = log_path
        self.cwd = cwd
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> "NodeProcess":
        out = open(self.log_path, "w") if self.log_path else subprocess.DEVNULL
        self.proc = subprocess.Popen(self.cmd, env=self.env, stdout=out, stderr=subprocess.STDOUT,
                                     cwd=self.cwd)
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, sig: int = signal.SIGINT, timeout: float = 10.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path and \
            self.log_path.exists() else ""


@dataclass
class FrameRecord:
    """One input cloud and what the node published for it (matched by header stamp)."""

    input: PointCloud2
    sent_at: float
    outputs: dict[str, Any] = field(default_factory=dict)
    received_at: dict[str, float] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return set(self.outputs) == set(OUTPUT_TOPICS)

    @property
    def latency_s(self) -> float:
        return max(self.received_at.values()) - self.sent_at if self.received_at else float("nan")


class CloudClient(Node):
    """Publishes clouds to the node and collects its outputs, keyed by input stamp."""

    def __init__(self, input_topic: str = "points", namespace: str = "",
                 publisher_qos: QoSProfile | None = None):
        super().__init__(f"fpcc_client_{os.getpid()}")
        qos = publisher_qos or QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                                          reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(PointCloud2, _join(namespace, input_topic), qos)
        self.records: dict[int, FrameRecord] = {}
        self.unmatched: list[tuple[str, Any]] = []
        self._lock = threading.Condition()
        out_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                             reliability=ReliabilityPolicy.RELIABLE)
        for name, msg_type in OUTPUT_TOPICS.items():
            self.create_subscription(msg_type, _join(namespace, name),
                                     lambda msg, n=name: self._on_output(n, msg), out_qos)
        self._executor = SingleThreadedExecutor()
        self._executor.add_node(self)
        self._stop = threading.Event()
        self._spinner = threading.Thread(target=spin_until_stopped, daemon=True,
                                         args=(self._executor, self._stop.is_set))
        self._spinner.start()

    def _on_output(self, name: str, msg: Any) -> None:
        now = time.perf_counter()
        with self._lock:
            record = self.records.get(output_stamp_ns(msg))
            if record is None or name in record.outputs:
                self.unmatched.append((name, msg))
            else:
                record.outputs[name] = msg
                record.received_at[name] = now
            self._lock.notify_all()

    def wait_connected(self, timeout: float = 30.0) -> bool:
        """True once the node subscribes to our input and publishes all three outputs to us."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            outputs_ok = all(self.count_publishers(s.topic_name) > 0 for s in self.subscriptions)
            if self.pub.get_subscription_count() > 0 and outputs_ok:
                return True
            time.sleep(0.1)
        return False

    def send(self, msg: PointCloud2) -> FrameRecord:
        record = FrameRecord(input=msg, sent_at=time.perf_counter())
        with self._lock:
            self.records[stamp_ns(msg.header)] = record
        self.pub.publish(msg)
        return record

    def wait_complete(self, record: FrameRecord, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._lock:
            while not record.complete:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._lock.wait(timeout=left)
        return True

    def close(self) -> None:
        """Stop spinning, wait for the spinning thread, then destroy (ros2/rclpy#663)."""
        self._stop.set()
        self._spinner.join(timeout=5.0)
        self._executor.shutdown()
        self.destroy_node()


def output_stamp_ns(msg: Any) -> int | None:
    """Stamp of an output message; a MarkerArray carries it on its markers (DELETEALL first)."""
    if hasattr(msg, "header"):
        return stamp_ns(msg.header)
    markers = getattr(msg, "markers", None)
    return stamp_ns(markers[0].header) if markers else None


def _join(namespace: str, topic: str) -> str:
    return f"{namespace.rstrip('/')}/{topic}" if namespace else topic


def bag_clouds_as_rclpy(bag_dir: Path, topic: str | None = None) -> list[tuple[int, PointCloud2]]:
    """(timestamp_ns, rclpy PointCloud2) for every cloud on ``topic`` (the only cloud topic if
    None), converted through CDR so the bytes are exactly what a recorder stored."""
    from rclpy.serialization import deserialize_message

    from msg_tools.bag import pick_cloud_topic, read_messages
    from msg_tools.msg_types import ROSBAGS

    topic = pick_cloud_topic(bag_dir, topic)
    clouds = []
    for _, msgtype, ts, msg in read_messages(bag_dir, [topic]):
        raw = ROSBAGS.typestore.serialize_cdr(msg, msgtype)
        clouds.append((ts, deserialize_message(bytes(raw), PointCloud2)))
    return clouds


def ensure_rclpy() -> None:
    if not rclpy.ok():
        rclpy.init()
