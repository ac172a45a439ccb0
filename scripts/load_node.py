#!/usr/bin/env python3
"""Load the live `segmenter` node: 640x480 clouds at 30 Hz from a reliable publisher.

The node must never build a queue: it takes the newest frame whenever it is free, so every
output belongs to a frame no older than about two processing periods (one waiting for the
worker, one being processed), outputs come in stamp order, and memory stays flat.

Measured here, in the publishing process: each output's frame age (arrival of its
segmented_points minus the moment its input was published), the processing period (median
interval between consecutive outputs), output rate, and the node's RSS (/proc/<pid>/status)
sampled every second; growth is counted from the end of the warm-up to the end of the run.

    .venv/bin/python scripts/load_node.py                 # the full run: 2 minutes
    .venv/bin/python scripts/load_node.py --seconds 15
    .venv/bin/python scripts/load_node.py --transport default

Transport: by default both processes use config/fastdds_large_clouds.xml (the shared-memory
profile the package ships for large clouds). With Fast DDS's default transports a 5 MB cloud
travels as UDP fragments; on a busy machine some are lost and reliable repair delivers a frame up
to seconds late -- a delay before the node ever sees the frame, which no node-side policy can
remove. ``--transport default`` measures that case too.

test/test_node_load.py runs a short version through :func:`run_load`.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SHM_PROFILE = REPO / "config" / "fastdds_large_clouds.xml"
for _p in (REPO / "scripts", REPO, REPO / "test"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from fuzz_node import TINY_MODEL, Collector, parse_totals, rss_mb  # noqa: E402  (sets ROS env)

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402

import cloud_factory as cf  # noqa: E402
from fpcc_ros.replay import NodeProcess  # noqa: E402


@dataclass
class LoadReport:
    transport: str
    seconds: float
    rate_hz: float
    frames_sent: int
    send_rate_hz: float
    outputs: int
    incomplete_outputs: int
    out_of_order: int
    unknown_stamps: int
    duplicates: int
    period_s: float            # median interval between consecutive outputs
    age_max_s: float
    age_p50_s: float
    age_p95_s: float
    rss_start_mb: float        # after the warm-up frame
    rss_warm_mb: float         # median over the window after warm_s of load
    rss_end_mb: float          # median over the last window
    rss_window_s: float
    rss_max_mb: float
    totals: dict[str, int]
    failed_frames_logged: int
    exit_code: int | None
    log: str
    ages_s: np.ndarray          # per output, in arrival order
    intervals_s: np.ndarray     # per output: arrival minus the previous output's arrival

    @property
    def output_rate_hz(self) -> float:
        return self.outputs / self.seconds

    @property
    def rss_growth_mb(self) -> float:
        return self.rss_end_mb - self.rss_warm_mb

    @property
    def age_limits_s(self) -> np.ndarray:
        """Per output, 'about two processing periods': twice that frame's processing period
        (its interval since the previous output, at least the median period) plus 0.25 s for
        transport and scheduling on a shared machine. A queue of n frames adds n periods."""
        return 2.0 * np.maximum(self.intervals_s, self.period_s) + 0.25

    @property
    def over_age_limit(self) -> int:
        return int((self.ages_s > self.age_limits_s).sum())

    @property
    def age_in_periods_max(self) -> float:
        return float((self.ages_s / np.maximum(self.intervals_s, self.period_s)).max())

    @property
    def ok(self) -> bool:
        return (self.outputs >= 3 and self.out_of_order == 0 and self.unknown_stamps == 0
                and self.duplicates == 0 and self.incomplete_outputs == 0
                and self.over_age_limit == 0 and self.rss_growth_mb < 20.0
                and self.exit_code == 0 and self.failed_frames_logged == 0)

    def table(self) -> str:
        t = self.totals
        return "\n".join([
            f"clouds                    640x480 ({640 * 480} points, ~5 MB) at {self.rate_hz:g} Hz "
            f"for {self.seconds:.0f} s; Fast DDS transport: {self.transport}",
            f"frames sent               {self.frames_sent} (achieved {self.send_rate_hz:.1f} Hz)",
            f"outputs                   {self.outputs} complete ({self.output_rate_hz:.2f} Hz), "
            f"{self.incomplete_outputs} incomplete, {self.duplicates} duplicates, "
            f"{self.out_of_order} out of stamp order, {self.unknown_stamps} unknown stamps",
            f"processing period         {self.period_s * 1e3:.0f} ms (median interval between "
            f"outputs)",
            f"frame age at output       max {self.age_max_s * 1e3:.0f} ms, p95 "
            f"{self.age_p95_s * 1e3:.0f} ms, median {self.age_p50_s * 1e3:.0f} ms "
            f"; at most {self.age_in_periods_max:.2f} processing periods; "
            f"{self.over_age_limit} over 2 periods + 0.25 s",
            f"node totals               " + ", ".join(f"{k} {v}" for k, v in t.items()),
            f"node RSS                  {self.rss_start_mb:.1f} MB after the warm-up frame; "
            f"median {self.rss_warm_mb:.1f} MB over the first {self.rss_window_s:.0f} s after "
            f"warm-up, {self.rss_end_mb:.1f} MB over the last {self.rss_window_s:.0f} s; max "
            f"{self.rss_max_mb:.1f} MB; growth {self.rss_growth_mb:+.1f} MB (limit < 20 MB)",
            f"node exit code            {self.exit_code}; 'frame failed' warnings: "
            f"{self.failed_frames_logged}",
        ])


def run_load(seconds: float = 120.0, rate_hz: float = 30.0, height: int = 480, width: int = 640,
             model: Path = TINY_MODEL, warm_s: float = 10.0, log_path: Path | None = None,
             progress: bool = False, transport: str = "shm") -> LoadReport:
    """``transport`` "shm": both processes load the shipped shared-memory profile (effective in
    this process only if no DDS participant exists yet: call it first, or from main()).
    "default": Fast DDS's built-in transports (the node process is started without it)."""
    if transport == "shm":
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(SHM_PROFILE)
    else:
        os.environ.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    log_path = log_path or Path(f"/tmp/fpcc_load_{os.getpid()}.log")
    clouds = [cf.make_cloud(cf.scene_xyz(height, width, seed=s, spheres=15), "xyz32")
              for s in range(4)]
    context = Context()
    rclpy.init(context=context)
    sent: dict[int, float] = {}
    rss_samples: list[tuple[float, float]] = []
    try:
        with NodeProcess(["-p", f"model:={Path(model).resolve()}"], log_path=log_path) as node:
            collector = Collector(context, keep_outputs=False)
            try:
                if not collector.wait_connected():
                    raise RuntimeError(f"node did not connect:\n{node.log()}")
                warm = cf.set_stamp(clouds[0], 1)
                collector.pub.publish(warm)
                if collector.take(1, timeout=120) is None:
                    raise RuntimeError(f"no output for the warm-up frame:\n{node.log()}")
                rss_start = rss_mb(node.proc.pid)[0]
                start = time.perf_counter()
                next_rss = start
                i = 0
                while True:
                    now = time.perf_counter()
                    if now - start >= seconds:
                        break
                    if now >= next_rss:
                        rss_samples.append((now - start, rss_mb(node.proc.pid)[0]))
                        next_rss += 1.0
                        if progress and len(rss_samples) % 10 == 0:
                            print(f"  {now - start:.0f} s: {i} sent, "
                                  f"{len(collector.stamps_seen()) - 1} outputs, "
                                  f"RSS {rss_samples[-1][1]:.1f} MB", flush=True)
                    due = start + i / rate_hz
                    if now < due:
                        time.sleep(min(due - now, 0.01))
                        continue
                    stamp = 1_000_000_000 + i * 1_000_000
                    msg = cf.set_stamp(clouds[i % len(clouds)], stamp)
                    sent[stamp] = time.perf_counter()
                    collector.pub.publish(msg)
                    i += 1
                elapsed = time.perf_counter() - start
                time.sleep(5.0)   # the frame in flight at the end comes out
            finally:
                collector.close()
            exit_code = node.stop()
            log = node.log()
    finally:
        rclpy.try_shutdown(context=context)

    arrivals = {s: a for s, a in collector.arrivals.items() if s != 1}
    complete = {s: a for s, a in arrivals.items() if len(a) == 3}
    order = sorted(complete, key=lambda s: complete[s]["segmented_points"])
    out_of_order = sum(1 for a, b in zip(order, order[1:]) if b < a)
    times = np.array([complete[s]["segmented_points"] for s in order])
    ages = np.array([complete[s]["segmented_points"] - sent[s] for s in order if s in sent])
    period = float(np.median(np.diff(times))) if len(times) > 1 else float("nan")
    window = max(1.0, min(10.0, (elapsed - warm_s) / 2))
    warm_rss = [r for t, r in rss_samples if warm_s <= t < warm_s + window] or [rss_start]
    end_rss = [r for t, r in rss_samples if t >= elapsed - window]
    return LoadReport(
        transport="shared memory (config/fastdds_large_clouds.xml)" if transport == "shm"
        else "Fast DDS defaults (UDP fragments)",
        seconds=elapsed, rate_hz=rate_hz, frames_sent=len(sent), send_rate_hz=len(sent) / elapsed,
        outputs=len(complete), incomplete_outputs=len(arrivals) - len(complete),
        out_of_order=out_of_order, unknown_stamps=sum(1 for s in arrivals if s not in sent),
        duplicates=len(collector.duplicates), period_s=period,
        age_max_s=float(ages.max()) if len(ages) else float("nan"),
        age_p50_s=float(np.median(ages)) if len(ages) else float("nan"),
        age_p95_s=float(np.percentile(ages, 95)) if len(ages) else float("nan"),
        rss_start_mb=rss_start, rss_warm_mb=float(np.median(warm_rss)),
        rss_end_mb=float(np.median(end_rss)), rss_window_s=window,
        rss_max_mb=max(r for _, r in rss_samples),
        totals=parse_totals(log), failed_frames_logged=log.count("frame failed"),
        exit_code=exit_code, log=log, ages_s=ages,
        intervals_s=np.diff(times, prepend=times[0] - period) if len(times) else times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--warm", type=float, default=10.0,
                    help="seconds of load before the RSS baseline is taken")
    ap.add_argument("--model", type=Path, default=TINY_MODEL)
    ap.add_argument("--log", type=Path, default=None, help="keep the node's log here")
    ap.add_argument("--transport", choices=["shm", "default"], default="shm",
                    help="shm: both sides use config/fastdds_large_clouds.xml (default); "
                         "default: Fast DDS's built-in transports")
    args = ap.parse_args()
    report = run_load(args.seconds, args.rate, model=args.model, warm_s=args.warm,
                      log_path=args.log, progress=True, transport=args.transport)
    print(report.table())
    print("PASS" if report.ok else "FAIL")
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
