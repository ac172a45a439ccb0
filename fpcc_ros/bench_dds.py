"""The live node over DDS: clouds at a fixed camera rate in, outputs timed on arrival.

For each rate a fresh `segmenter` process is started (own ROS_DOMAIN_ID, localhost discovery,
the shipped shared-memory Fast DDS profile for ~5 MB clouds). This process publishes the demo
bag's frames at the rate, each with a new stamp, and subscribes to the three outputs like a
consumer (RViz) would. Measured:

* latency: arrival of a frame's last output minus the moment it was published (so it includes
  transport both ways; the node's own receive-to-publish median is read from its log too);
* output rate and frames dropped (sent, never answered: the node keeps only the newest frame);
* the age of the newest processed frame at each output (= its latency) and whether it grows over
  the run -- a node that queues frames shows ages rising by one period per frame;
* the node's RSS (sampled) and peak RSS (VmHWM).
"""
from __future__ import annotations

import os
import random
import re
import threading
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SHM_PROFILE = REPO / "config" / "fastdds_large_clouds.xml"
OUTPUTS = ("segmented_points", "instances", "instance_markers")


def node_rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process in MB."""
    values = {"VmRSS": float("nan"), "VmHWM": float("nan")}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in values:
                values[key] = int(rest.split()[0]) / 1024
    except (OSError, ValueError):
        pass
    return values["VmRSS"], values["VmHWM"]


def minor_faults(pid: int) -> int | None:
    """A process's minor page faults so far (/proc/<pid>/stat field 10): memory the kernel had to
    map and zero, which per frame should be near 0 (fpcc_ros.heap)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        return int(stat.rsplit(")", 1)[1].split()[7])
    except (OSError, ValueError, IndexError):
        return None


def parse_node_log(log: str) -> dict[str, Any]:
    """The node's exit totals and its last reported receive-to-publish median latency."""
    out: dict[str, Any] = {}
    totals = re.findall(r"totals: (.*)", log)
    if totals:
        for part in totals[-1].split(","):
            m = re.match(r"\s*([a-z_]+) (\d+)", part)
            if m:
                out[m.group(1)] = int(m.group(2))
    lat = re.findall(r"latency median (\d+(?:\.\d+)?) ms", log)
    out["node_latency_median_ms"] = float(lat[-1]) if lat else None
    return out


def _stamp_ns(msg: Any) -> int | None:
    if hasattr(msg, "header"):
        h = msg.header
    elif getattr(msg, "markers", None):
        h = msg.markers[0].header
    else:
        return None
    return int(h.stamp.sec) * 1_000_000_000 + int(h.stamp.nanosec)


class _Probe:
    """Publisher of clouds and subscriber of the outputs; keeps arrival times only."""

    def __init__(self, context: Any):
        from geometry_msgs.msg import PoseArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from visualization_msgs.msg import MarkerArray

        self.node = Node(f"fpcc_bench_dds_{os.getpid()}", context=context)
        reliable = dict(history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.node.create_publisher(PointCloud2, "points", QoSProfile(depth=10, **reliable))
        self.arrivals: dict[int, dict[str, float]] = {}
        self._lock = threading.Condition()
        for name, cls in zip(OUTPUTS, (PointCloud2, PoseArray, MarkerArray)):
            self.node.create_subscription(cls, name, lambda m, n=name: self._on(n, m),
                                          QoSProfile(depth=50, **reliable))
        self._executor = SingleThreadedExecutor(context=context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()

    def _on(self, name: str, msg: Any) -> None:
        now = time.perf_counter()
        stamp = _stamp_ns(msg)
        with self._lock:
            if stamp is not None:
                self.arrivals.setdefault(stamp, {}).setdefault(name, now)
            self._lock.notify_all()

    def connected(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.pub.get_subscription_count() > 0 and all(
                    self.node.count_publishers(s.topic_name) > 0 for s in self.node.subscriptions):
                return True
            time.sleep(0.1)
        return False

    def wait_output(self, stamp: int, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        with self._lock:
            while len(self.arrivals.get(stamp, ())) < len(OUTPUTS):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._lock.wait(timeout=min(left, 0.5))
        return True

    def close(self) -> None:
        self._executor.shutdown()
        self.node.destroy_node()


def _with_stamp(msg: Any, stamp_ns: int) -> Any:
    """The same cloud (data shared, not copied) under a new header stamp."""
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Header

    header = Header(frame_id=msg.header.frame_id,
                    stamp=Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000))
    return PointCloud2(header=header, height=msg.height, width=msg.width, fields=msg.fields,
                       is_bigendian=msg.is_bigendian, point_step=msg.point_step,
                       row_step=msg.row_step, data=msg.data, is_dense=msg.is_dense)


def run_rate(clouds: Sequence[Any], rate_hz: float, seconds: float, node_args: Sequence[str],
             log_path: Path, connect_timeout: float = 60.0, warmup_timeout: float = 180.0
             ) -> dict[str, Any]:
    """One node process, clouds at ``rate_hz`` for ``seconds``; the measurements as a dict."""
    import rclpy
    from rclpy.context import Context

    from fpcc_ros.replay import NodeProcess, isolated_ros_env

    env = isolated_ros_env(random.randint(1, 101))
    os.environ["ROS_DOMAIN_ID"] = env["ROS_DOMAIN_ID"]
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = env["ROS_AUTOMATIC_DISCOVERY_RANGE"]
    context = Context()
    rclpy.init(context=context)
    sent: dict[int, float] = {}
    rss: list[tuple[float, float]] = []
    try:
        with NodeProcess(node_args, env=env, log_path=log_path) as node:
            probe = _Probe(context)
            try:
                if not probe.connected(connect_timeout):
                    raise RuntimeError(f"the node did not connect within {connect_timeout:.0f} s:"
                                       f"\n{node.log()[-2000:]}")
                stamp = time.time_ns()
                probe.pub.publish(_with_stamp(clouds[0], stamp))
                if not probe.wait_output(stamp, warmup_timeout):
                    raise RuntimeError(f"no output for the warm-up frame within "
                                       f"{warmup_timeout:.0f} s:\n{node.log()[-2000:]}")
                time.sleep(0.5)
                with probe._lock:
                    probe.arrivals.clear()
                pid = node.proc.pid
                faults_before = minor_faults(pid)
                start = time.perf_counter()
                next_rss, i = start, 0
                while True:
                    now = time.perf_counter()
                    if now - start >= seconds:
                        break
                    if now >= next_rss:
                        rss.append((now - start, node_rss_mb(pid)[0]))
                        next_rss += 0.5
                    due = start + i / rate_hz
                    if now < due:
                        time.sleep(min(due - now, 0.005))
                        continue
                    stamp = time.time_ns()
                    msg = _with_stamp(clouds[i % len(clouds)], stamp)
                    sent[stamp] = time.perf_counter()
                    probe.pub.publish(msg)
                    i += 1
                elapsed = time.perf_counter() - start
                last = max(sent)
                probe.wait_output(last, 5.0)  # the frame in flight at the end comes out
                peak = node_rss_mb(pid)[1]
                faults_after = minor_faults(pid)
            finally:
                probe.close()
            exit_code = node.stop()
            log = node.log()
    finally:
        rclpy.try_shutdown(context=context)
    faults = None if faults_before is None or faults_after is None \
        else faults_after - faults_before
    return summarise(rate_hz, seconds=elapsed, sent=sent, arrivals=probe.arrivals, rss=rss,
                     peak_rss_mb=peak, log=log, exit_code=exit_code, minor_faults=faults)


def summarise(rate_hz: float, seconds: float, sent: dict[int, float],
              arrivals: dict[int, dict[str, float]], rss: list[tuple[float, float]],
              peak_rss_mb: float, log: str, exit_code: int | None,
              minor_faults: int | None = None) -> dict[str, Any]:
    """Latency, rate, drops and queue check from send and arrival times (all perf_counter s)."""
    complete = {s: max(a.values()) for s, a in arrivals.items()
                if len(a) == len(OUTPUTS) and s in sent}
    order = sorted(complete, key=complete.get)
    t_out = np.array([complete[s] for s in order])
    ages = np.array([complete[s] - sent[s] for s in order])
    start = min(sent.values()) if sent else 0.0
    period = float(np.median(np.diff(t_out))) if len(t_out) > 2 else float("nan")
    slope = float(np.polyfit(t_out - start, ages, 1)[0]) if len(ages) > 3 else float("nan")
    thirds = np.array_split(ages, 3) if len(ages) >= 6 else []
    growth = float(np.median(thirds[-1]) - np.median(thirds[0])) if len(thirds) else float("nan")
    # outputs that arrived while frames were being sent: a queue drained afterwards is no rate
    out_rate = float((t_out <= start + seconds).sum()) / seconds if seconds else float("nan")
    age_limit = 2.0 * period + 0.25 if math_ok(period) else float("nan")
    no_queue = bool(len(ages) >= 3 and math_ok(period) and float(np.percentile(ages, 90)) <= age_limit
                    and (not math_ok(growth) or growth <= max(0.5 * period, 0.05)))
    keeps_up = out_rate >= 0.95 * len(sent) / seconds if seconds and sent else False
    verdict = ("keeps up" if keeps_up else "drops stale frames") + \
        (", no queue" if no_queue else ", QUEUE or late outputs")
    rss_values = [r for _, r in rss if math_ok(r)]
    return {
        "rate_hz": rate_hz, "seconds": seconds, "frames_sent": len(sent),
        "send_rate_hz": len(sent) / seconds if seconds else float("nan"),
        "outputs": len(order), "output_rate_hz": out_rate,
        "dropped": len(sent) - len(order),
        "incomplete_outputs": sum(1 for s, a in arrivals.items() if len(a) < len(OUTPUTS)),
        "latency_ms": _q(ages * 1e3), "processing_period_ms": period * 1e3,
        "age_of_newest_processed_ms": _q(ages * 1e3),
        "age_trend_ms_per_s": slope * 1e3, "age_growth_last_vs_first_third_ms": growth * 1e3,
        "age_limit_ms": age_limit * 1e3, "keeps_up": keeps_up, "no_queue": no_queue,
        "verdict": verdict,
        "node_rss_mb": _q(np.array(rss_values)) if rss_values else {},
        "node_rss_peak_mb": peak_rss_mb, "node": parse_node_log(log), "node_exit_code": exit_code,
        "node_minor_faults_per_output": minor_faults / len(order)
        if minor_faults is not None and order else None,
    }


def math_ok(value: float) -> bool:
    return value == value and value not in (float("inf"), float("-inf"))


def _q(values: np.ndarray) -> dict[str, float]:
    if len(values) == 0:
        return {}
    return {"median": float(np.median(values)), "p90": float(np.percentile(values, 90)),
            "max": float(np.max(values)), "min": float(np.min(values))}


def demo_clouds() -> tuple[list[Any], float]:
    """The demo bag's frames as rclpy messages and the part radius from bags/demo.json."""
    import json

    from fpcc_ros.replay import bag_clouds_as_rclpy

    bag = REPO / "bags" / "demo"
    info = json.loads(bag.with_suffix(".json").read_text())
    return [msg for _, msg in bag_clouds_as_rclpy(bag)], float(info["part_radius"])


def run_dds(model: Path | str, rates: Sequence[float] = (5.0, 10.0), seconds: float = 20.0,
            threads: int = 0, provider: str = "cpu", voxel_size: float | None = None,
            clouds: Sequence[Any] | None = None, part_radius: float | None = None,
            transport: str = "shm", log_dir: Path | None = None,
            progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Every rate in turn, each with a fresh node; the report's ``dds`` section."""
    if transport == "shm":
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(SHM_PROFILE)
    if clouds is None:
        clouds, radius = demo_clouds()
        part_radius = part_radius or radius
    providers = {"cpu": "[CPUExecutionProvider]",
                 "cuda": "[CUDAExecutionProvider, CPUExecutionProvider]"}[provider]
    args = ["-p", f"model:={Path(model).resolve()}", "-p", f"threads:={int(threads)}",
            "-p", f"providers:={providers}"]
    if part_radius:
        args += ["-p", f"part_radius:={float(part_radius)}"]
    if voxel_size is not None:
        args += ["-p", f"voxel_size:={float(voxel_size)}"]
    log_dir = Path(log_dir or f"/tmp/fpcc_bench_dds_{os.getpid()}")
    log_dir.mkdir(parents=True, exist_ok=True)
    results = []
    for rate in rates:
        if progress:
            progress(f"DDS: {rate:g} Hz for {seconds:g} s ...")
        results.append(run_rate(clouds, rate, seconds, args, log_dir / f"node_{rate:g}hz.log"))
    h, w = int(clouds[0].height), int(clouds[0].width)
    return {"clouds": f"{len(clouds)} demo frames, {w}x{h}", "transport":
            "shared memory (config/fastdds_large_clouds.xml)" if transport == "shm" else "default",
            "node_args": args, "logs": str(log_dir), "rates": results}


def dds_table(dds: dict[str, Any]) -> str:
    lines = [f"live node over DDS ({dds['clouds']}, {dds['transport']}); latency = publish -> "
             "last output received"]
    head = (f"{'rate':>6} {'sent':>5} {'out':>5} {'out Hz':>7} {'dropped':>7} {'lat med':>8} "
            f"{'lat p90':>8} {'lat max':>8} {'node med':>8} {'period':>7} {'age trend':>10} "
            f"{'RSS med':>8} {'RSS peak':>8} {'faults':>7}  verdict")
    lines += [head, "-" * len(head)]
    for r in dds["rates"]:
        lat, rss = r["latency_ms"], r["node_rss_mb"]
        node_med = r["node"].get("node_latency_median_ms")
        faults = r.get("node_minor_faults_per_output")
        lines.append(
            f"{r['rate_hz']:>4g}Hz {r['frames_sent']:>5} {r['outputs']:>5} {r['output_rate_hz']:>7.2f} "
            f"{r['dropped']:>7} {lat.get('median', float('nan')):>8.0f} {lat.get('p90', float('nan')):>8.0f} "
            f"{lat.get('max', float('nan')):>8.0f} "
            f"{(f'{node_med:.0f}' if node_med is not None else '-'):>8} "
            f"{r['processing_period_ms']:>7.0f} {r['age_trend_ms_per_s']:>8.1f}/s "
            f"{rss.get('median', float('nan')):>8.0f} {r['node_rss_peak_mb']:>8.0f} "
            f"{(f'{faults:.0f}' if faults is not None else '-'):>7}  {r['verdict']}")
    lines.append("ms unless noted; 'node med' = the node's own receive-to-publish median (its "
                 "log); age trend = slope of frame age over the run (a queue grows it); faults = "
                 "the node's minor page faults per output frame (memory mapped afresh)")
    return "\n".join(lines)
