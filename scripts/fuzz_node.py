#!/usr/bin/env python3
"""Fuzz the live `segmenter` node over DDS with malformed and valid PointCloud2 messages.

Starts the node in its own process (own ROS_DOMAIN_ID, localhost discovery), sends the mutation
catalogue of test/cloud_factory.py interleaved with valid clouds, and checks, message by message:

* malformed (per cloud_factory.expected_valid, an independent statement of the input contract):
  nothing is published for its stamp, and the node's log has a warning naming the problem;
* well-formed: exactly one output on each topic with its stamp, correct per
  cloud_factory.check_output; the canary (the same cloud every time) gives identical labels
  throughout the run, so malformed input in between changes nothing;
* the node never dies; its exit totals account for every message; RSS before/after.

Messages are sent one at a time (a valid one waits for its outputs, a malformed one is followed by
a short gap) so the node's keep-last-1 input never replaces one of them unexamined.

    .venv/bin/python scripts/fuzz_node.py                      # the full run: 2,000 messages
    .venv/bin/python scripts/fuzz_node.py --messages 200 --big 1

test/test_fuzz_node.py runs a shortened version through :func:`run_fuzz`.
"""
from __future__ import annotations

import argparse
import os
import random
import re
import sys
import threading
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
for _p in (REPO, REPO / "test"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))
os.environ.setdefault("ROS_DOMAIN_ID", str(random.Random(os.getpid()).randint(1, 101)))
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from geometry_msgs.msg import PoseArray  # noqa: E402
from rclpy.context import Context  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import PointCloud2  # noqa: E402
from visualization_msgs.msg import MarkerArray  # noqa: E402

import cloud_factory as cf  # noqa: E402
from fpcc_ros.node_shutdown import spin_until_stopped  # noqa: E402
from fpcc_ros.replay import NodeProcess  # noqa: E402

TINY_MODEL = REPO / "test" / "data" / "tiny_fpcc.onnx"
OUTPUTS = {"segmented_points": PointCloud2, "instances": PoseArray,
           "instance_markers": MarkerArray}
MALFORMED_WARNING = "dropped a malformed PointCloud2"
THROTTLE_PERIOD_S = 5.0


def rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process in MB, from /proc/<pid>/status."""
    values = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, rest = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            values[key] = int(rest.split()[0]) / 1024
    return values["VmRSS"], values["VmHWM"]


def _out_stamp(msg: Any) -> int | None:
    """Header stamp in ns (a MarkerArray's is its first marker's; None if it has none)."""
    if isinstance(msg, MarkerArray):
        if not msg.markers:
            return None
        msg = msg.markers[0]
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


class Collector(Node):
    """Publishes clouds on `points` and keeps the node's outputs by stamp until taken."""

    def __init__(self, context: Context, keep_outputs: bool = True):
        super().__init__(f"fpcc_fuzz_{os.getpid()}", context=context)
        reliable = dict(history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = self.create_publisher(PointCloud2, "points", QoSProfile(depth=10, **reliable))
        self.keep_outputs = keep_outputs
        self.outputs: dict[int, dict[str, Any]] = defaultdict(dict)
        self.arrivals: dict[int, dict[str, float]] = defaultdict(dict)
        self.duplicates: list[tuple[str, int | None]] = []
        self._cond = threading.Condition()
        for name, msg_type in OUTPUTS.items():
            self.create_subscription(msg_type, name, lambda m, n=name: self._on_output(n, m),
                                     QoSProfile(depth=50, **reliable))
        self._executor = SingleThreadedExecutor(context=context)
        self._executor.add_node(self)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=spin_until_stopped, daemon=True,
                                        args=(self._executor, self._stop.is_set))
        self._thread.start()

    def _on_output(self, name: str, msg: Any) -> None:
        now = time.perf_counter()
        stamp = _out_stamp(msg)
        with self._cond:
            if stamp is None or name in self.arrivals[stamp]:
                self.duplicates.append((name, stamp))
            else:
                self.arrivals[stamp][name] = now
                if self.keep_outputs:
                    self.outputs[stamp][name] = msg
            self._cond.notify_all()

    def wait_connected(self, timeout: float = 60.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.pub.get_subscription_count() > 0 and all(
                    self.count_publishers(s.topic_name) > 0 for s in self.subscriptions):
                return True
            time.sleep(0.1)
        return False

    def take(self, stamp: int, timeout: float) -> dict[str, Any] | None:
        """The three outputs for ``stamp`` (removed from the store), or None on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while len(self.arrivals.get(stamp, ())) < len(OUTPUTS):
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(timeout=min(left, 0.5))
            return self.outputs.pop(stamp, {})

    def stamps_seen(self) -> set[int]:
        with self._cond:
            return set(self.arrivals)

    def close(self) -> None:
        """Stop spinning, wait for the spinning thread, then destroy (ros2/rclpy#663)."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        self._executor.shutdown()
        self.destroy_node()


@dataclass
class KindRow:
    sent: int = 0
    expected_valid: int = 0
    outputs: int = 0
    correct: int = 0
    problems: list[str] = field(default_factory=list)


@dataclass
class FuzzReport:
    rows: dict[str, KindRow]
    messages: int
    invalid_sent: int
    valid_sent: int
    outputs_for_invalid: int
    missing_outputs: int
    wrong_outputs: int
    canary_changed: int
    crashes: int
    exit_code: int | None
    rss_before_mb: float
    rss_mid_mb: float
    rss_after_mb: float
    rss_peak_mb: float
    rss_after_last_big_mb: float    # 10 messages after the last two-million-point output
    messages_after_last_big: int
    totals: dict[str, int]
    warnings: int
    warned_kinds_missing: list[str]
    duration_s: float
    log: str

    @property
    def superseded(self) -> int:
        """Malformed messages the node never examined: a newer message replaced them in its
        keep-last-1 input first (by design; counted so the fuzz claims only what it tested)."""
        return self.invalid_sent - self.totals.get("invalid", 0)

    @property
    def ok(self) -> bool:
        t = self.totals
        return (self.crashes == 0 and self.outputs_for_invalid == 0 and self.missing_outputs == 0
                and self.wrong_outputs == 0 and not self.warned_kinds_missing
                and t.get("published") == self.valid_sent and t.get("failed") == 0
                and 0 <= self.superseded <= max(2, self.invalid_sent // 20)
                and self.rss_after_mb - self.rss_after_last_big_mb < 20.0)

    def table(self) -> str:
        lines = [f"{'kind':42s} {'sent':>5s} {'valid':>5s} {'outputs':>7s} {'correct':>7s}  problems"]
        for name, r in self.rows.items():
            probs = "; ".join(sorted(set(r.problems)))[:100]
            lines.append(f"{name:42s} {r.sent:5d} {r.expected_valid:5d} {r.outputs:7d} "
                         f"{r.correct:7d}  {probs}")
        t = self.totals
        lines += [
            "",
            f"messages sent                 {self.messages} ({self.invalid_sent} malformed, "
            f"{self.valid_sent} well-formed) over {len(self.rows)} kinds in {self.duration_s:.0f} s",
            f"crashes                       {self.crashes} (node exit code {self.exit_code})",
            f"outputs for malformed inputs  {self.outputs_for_invalid}",
            f"well-formed without output    {self.missing_outputs}",
            f"well-formed, wrong output     {self.wrong_outputs} (canary changed: "
            f"{self.canary_changed})",
            f"malformed warnings logged     {self.warnings} (throttled; kinds never named: "
            f"{self.warned_kinds_missing or 'none'})",
            f"malformed examined            {t.get('invalid', 0)} of {self.invalid_sent} "
            f"({self.superseded} superseded by a newer message before the node looked)",
            f"node totals                   " + ", ".join(f"{k} {v}" for k, v in t.items()),
            f"node RSS                      before {self.rss_before_mb:.1f} MB (after warm-up), "
            f"mid-run {self.rss_mid_mb:.1f} MB, after {self.rss_after_mb:.1f} MB "
            f"({self.rss_after_mb - self.rss_before_mb:+.1f} MB overall, "
            f"{self.rss_after_mb - self.rss_mid_mb:+.1f} MB over the second half), "
            f"peak {self.rss_peak_mb:.1f} MB; "
            f"{self.rss_after_mb - self.rss_after_last_big_mb:+.1f} MB over the "
            f"last {self.messages_after_last_big} messages (from the 10th after the last 2M "
            f"cloud)",
        ]
        return "\n".join(lines)


WARMUP = cf.Kind("warmup_640x480", True,
                 lambda r: cf.make_cloud(cf.scene_xyz(480, 640, seed=7), "xyz32"))


def plan(messages: int, big: int, rng: np.random.Generator) -> list[cf.Kind]:
    """Every kind at least twice, the rest drawn at random (malformed ~60%); a canary every
    ~20 messages and first of all (after one 640x480 warm-up cloud); ``big`` two-million-point clouds spread through the run."""
    malformed = [k for k in cf.KINDS if k.valid is not True]
    wellformed = [k for k in cf.KINDS if k.valid is True]
    seq = [k for k in cf.KINDS for _ in range(2)]
    while len(seq) < messages - messages // 20 - big - 1:
        pool = malformed if rng.random() < 0.6 else wellformed
        seq.append(pool[int(rng.integers(len(pool)))])
    order = rng.permutation(len(seq))
    seq = [seq[i] for i in order]
    canary = cf.Kind("canary", True, lambda r: cf.canary())
    for pos in range(0, len(seq) + messages // 20, 20):
        seq.insert(min(pos, len(seq)), canary)
    for pos in sorted(rng.integers(len(seq) // 4, len(seq), big).tolist(), reverse=True):
        seq.insert(pos, cf.TWO_MILLION)
    seq.insert(0, canary)
    seq.insert(0, WARMUP)   # sizes onnxruntime's arena for full blocks before RSS "before"
    return seq


def parse_totals(log: str) -> dict[str, int]:
    m = re.findall(r"totals: (.*)", log)
    if not m:
        return {}
    return {k: int(v) for k, v in re.findall(r"(\w+) (\d+)", m[-1])}


def run_fuzz(messages: int = 2000, big: int = 2, seed: int = 0, model: Path = TINY_MODEL,
             log_path: Path | None = None, gap_s: float = 0.03, valid_timeout_s: float = 60.0,
             progress: bool = False) -> FuzzReport:
    rng = np.random.default_rng(seed)
    log_path = log_path or Path(f"/tmp/fpcc_fuzz_{os.getpid()}.log")
    (lo, hi) = cf.FUZZ_ROI
    args = ["-p", f"model:={Path(model).resolve()}", "-p", "min_points:=5",
            "-p", f"roi_min:=[{lo[0]!r},{lo[1]!r},{lo[2]!r}]",
            "-p", f"roi_max:=[{hi[0]!r},{hi[1]!r},{hi[2]!r}]"]
    seq = plan(messages, big, rng)
    rows: dict[str, KindRow] = {k.name: KindRow() for k in (*cf.KINDS, cf.TWO_MILLION)}
    rows = {WARMUP.name: KindRow(), "canary": KindRow(), **rows}
    sent_invalid: dict[int, str] = {}
    canary_labels: np.ndarray | None = None
    counts = Counter()
    context = Context()
    rclpy.init(context=context)
    t0 = time.monotonic()
    rss_before = rss_mid = rss_after = peak = rss_big = float("nan")
    after_big = -10**9   # counts messages after the last 2M cloud
    exit_code, crashes = None, 0
    try:
        with NodeProcess(args, log_path=log_path) as node:
            collector = Collector(context)
            try:
                if not collector.wait_connected():
                    raise RuntimeError(f"node did not connect:\n{node.log()}")
                for i, kind in enumerate(seq):
                    if not node.alive():
                        crashes = 1
                        break
                    msg = kind.build(rng)
                    stamp = 1_000_000_000_000 + i * 1000
                    cf.set_stamp(msg, stamp)
                    valid = cf.expected_valid(msg)
                    row = rows[kind.name]
                    row.sent += 1
                    row.expected_valid += valid
                    collector.pub.publish(msg)
                    if valid:
                        counts["valid"] += 1
                        timeout = valid_timeout_s * (4 if kind is cf.TWO_MILLION else 1)
                        out = collector.take(stamp, timeout)
                        if out is None:
                            row.problems.append("no output")
                            counts["missing"] += 1
                            continue
                        row.outputs += 1
                        try:
                            labels = cf.check_output(msg, out, kind, roi=cf.FUZZ_ROI)
                            if kind.name == "canary":
                                if canary_labels is None:
                                    canary_labels = labels
                                elif not np.array_equal(labels, canary_labels):
                                    counts["canary_changed"] += 1
                                    raise AssertionError("canary labels changed")
                            row.correct += 1
                            if kind is cf.TWO_MILLION:
                                after_big = -1
                        except AssertionError as exc:
                            counts["wrong"] += 1
                            row.problems.append(str(exc).splitlines()[0][:80] or "wrong output")
                    else:
                        counts["invalid"] += 1
                        sent_invalid[stamp] = kind.name
                        time.sleep(gap_s)
                    after_big += 1
                    if after_big == 10:   # the node no longer holds the 2M message
                        rss_big = rss_mb(node.proc.pid)[0]
                    if i == 1:
                        rss_before = rss_mb(node.proc.pid)[0]
                    if i == len(seq) // 2:
                        rss_mid = rss_mb(node.proc.pid)[0]
                    if progress and i % 100 == 0:
                        rss = rss_mb(node.proc.pid)[0]
                        print(f"  {i}/{len(seq)} sent, node RSS {rss:.1f} MB", flush=True)
                time.sleep(1.0)  # stray outputs for the last malformed messages would be here
                if node.alive():
                    rss_after, peak = rss_mb(node.proc.pid)
                else:
                    crashes = 1
                seen = collector.stamps_seen()
                for stamp, name in sent_invalid.items():
                    if stamp in seen:
                        rows[name].outputs += 1
                        rows[name].problems.append("published for a malformed message")
            finally:
                collector.close()
            exit_code = node.stop()
            log = node.log()
    finally:
        rclpy.try_shutdown(context=context)
    if exit_code not in (0, None):
        crashes = 1
    warnings = log.count(MALFORMED_WARNING)
    missing_phrases = sorted({k.name for k in cf.KINDS if k.valid is False and rows[k.name].sent
                              and k.warning not in log})
    return FuzzReport(
        rows={k: r for k, r in rows.items() if r.sent}, messages=len(seq),
        invalid_sent=counts["invalid"], valid_sent=counts["valid"],
        outputs_for_invalid=sum(1 for s in sent_invalid if s in seen),
        missing_outputs=counts["missing"], wrong_outputs=counts["wrong"],
        canary_changed=counts["canary_changed"], crashes=crashes, exit_code=exit_code,
        rss_before_mb=rss_before, rss_mid_mb=rss_mid, rss_after_mb=rss_after, rss_peak_mb=peak,
        rss_after_last_big_mb=rss_big if not np.isnan(rss_big) else rss_before,
        messages_after_last_big=after_big - 10 if not np.isnan(rss_big) else len(seq) - 1,
        totals=parse_totals(log), warnings=warnings, warned_kinds_missing=missing_phrases,
        duration_s=time.monotonic() - t0, log=log)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=2000)
    ap.add_argument("--big", type=int, default=2, help="two-million-point clouds to include")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model", type=Path, default=TINY_MODEL)
    ap.add_argument("--log", type=Path, default=None, help="keep the node's log here")
    args = ap.parse_args()
    report = run_fuzz(args.messages, args.big, args.seed, args.model, args.log, progress=True)
    print(report.table())
    print("PASS" if report.ok else "FAIL")
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
