#!/usr/bin/env python3
"""Soak the `segmenter` node's shutdown: start it, feed it clouds, stop it with SIGINT or SIGTERM.

Every cycle starts a fresh node process (own ROS_DOMAIN_ID, localhost discovery), feeds it
640x480 clouds and sends one signal at a chosen moment:

* ``start``       right after the node is up and listening (no frame yet),
* ``idle``        after a frame has been published, the worker waiting for the next one,
* ``mid_frame``   while a frame is inside the pipeline (a random fraction of the latency the
                  warm-up frame took),
* ``mid_publish`` as soon as the first of a frame's three outputs has arrived here (the worker
                  is publishing the other two),
* ``stream``      while clouds stream in at 15 Hz, at a random time.

A cycle is clean when the node exits with code 0 within the time limit, leaves no core dump,
prints its "totals" line, the totals account for every frame it received, every frame it counts
as published arrived here complete (all three outputs), no frame arrived partly, and the log has
no traceback or C++ termination. The table gives the counts per signal and moment.

    .venv/bin/python scripts/soak_shutdown.py                      # 200 cycles
    .venv/bin/python scripts/soak_shutdown.py --cycles 40 --load 2  # two busy loops beside it
    .venv/bin/python scripts/soak_shutdown.py --moments mid_publish --signals SIGTERM

Core dumps are enabled for the node (RLIMIT_CORE unlimited, each node runs in its own folder);
with a core_pattern that pipes cores elsewhere (apport, systemd-coredump) a crash still shows as
a negative exit code (-11, -6). ``--keep`` keeps the folders (log, core) of unclean cycles.
test/test_shutdown_soak.py runs a few cycles through :func:`run_soak`.
"""
from __future__ import annotations

import argparse
import os
import random
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
for _p in (REPO / "scripts", REPO, REPO / "test"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

from fuzz_node import TINY_MODEL, Collector, parse_totals  # noqa: E402  (sets the ROS env)

import numpy as np  # noqa: E402
import rclpy  # noqa: E402
from rclpy.context import Context  # noqa: E402

import cloud_factory as cf  # noqa: E402
from fpcc_ros.replay import NodeProcess, isolated_ros_env  # noqa: E402

MOMENTS = ("start", "idle", "mid_frame", "mid_publish", "stream")
SIGNALS = {"SIGINT": signal.SIGINT, "SIGTERM": signal.SIGTERM}
CRASH_SIGNALS = {signal.SIGSEGV, signal.SIGABRT, signal.SIGBUS, signal.SIGFPE, signal.SIGILL}
BAD_LOG = ("Traceback", "Exception in thread", "terminate called", "Fatal Python error",
           "Failed to publish")
TOTAL_KEYS = ("published", "invalid", "failed", "dropped_stale", "skipped_old",
              "dropped_at_shutdown")


@dataclass
class Cycle:
    index: int
    signal: str
    moment: str
    exit_code: int | None = None
    hung: bool = False            # still running after the time limit (then killed)
    core: bool = False            # a core file, or killed by a crashing signal
    exit_s: float = float("nan")  # signal to exit
    sent: int = 0
    complete: int = 0             # frames with all three outputs here
    partial: int = 0              # frames with one or two outputs: a torn publish
    totals: dict[str, int] = field(default_factory=dict)
    in_flight: int = 0            # "still being processed" at exit (not in the totals)
    landed: bool = True           # mid_publish: the signal went out between two outputs
    problems: list[str] = field(default_factory=list)

    @property
    def clean(self) -> bool:
        return not self.problems


def _judge(c: Cycle, log: str) -> None:
    if c.hung:
        c.problems.append("hung")
    if c.core:
        c.problems.append("core dump")
    if c.exit_code != 0:
        c.problems.append(f"exit {c.exit_code}")
    if not c.totals:
        c.problems.append("no totals line")
    else:
        accounted = c.in_flight + sum(c.totals.get(k, 0) for k in TOTAL_KEYS)
        if accounted != c.totals.get("received"):
            c.problems.append(f"totals do not add up ({accounted} vs received "
                              f"{c.totals.get('received')})")
        if c.totals.get("received", 0) > c.sent:
            c.problems.append(f"received {c.totals.get('received')} frames, {c.sent} sent")
        if c.totals.get("published", 0) != c.complete:
            c.problems.append(f"published {c.totals.get('published')}, complete here "
                              f"{c.complete}")
    if c.partial:
        c.problems.append(f"{c.partial} frame(s) with partial outputs")
    for bad in BAD_LOG:
        if bad in log:
            c.problems.append(f"log: {bad}")


def _busy_loops(n: int) -> list[subprocess.Popen]:
    """``n`` processes spinning a core each (the machine already runs other jobs)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _core_files(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if p.name == "core" or p.name.startswith("core.")]


def run_cycle(index: int, sig_name: str, moment: str, rng: random.Random, work: Path,
              args: list[str], clouds: list, latency_s: float, timeout_s: float
              ) -> tuple[Cycle, str, float]:
    """One node process, one signal. Returns the cycle, the node's log and the warm-up
    frame's latency (for the next cycle's mid_frame timing)."""
    c = Cycle(index, sig_name, moment)
    folder = work / f"cycle_{index:04d}"
    folder.mkdir(parents=True, exist_ok=True)
    log_path = folder / "node.log"
    stamp0 = 1_000_000_000 * (index + 1)
    sent: list[int] = []
    # topics of this run only: a session elsewhere on the machine with the same domain id
    # (picked at random, 1 in 101) must not feed our node or see our clouds
    remap = ["-r", f"__ns:=/soak_{os.getpid()}"]
    context = Context()
    rclpy.init(context=context, args=["--ros-args", *remap])
    try:
        with NodeProcess([*args, *remap], env=isolated_ros_env(), log_path=log_path,
                         cwd=folder) as node:
            collector = Collector(context, keep_outputs=False)
            try:
                if not collector.wait_connected(60):
                    c.problems.append("node never connected")

                def send(i: int) -> int:
                    stamp = stamp0 + i * 1_000_000
                    collector.pub.publish(cf.set_stamp(clouds[i % len(clouds)], stamp))
                    sent.append(stamp)
                    return stamp

                if moment == "start":
                    time.sleep(rng.uniform(0.0, 0.3))
                else:
                    t0 = time.perf_counter()
                    if collector.take(send(0), 60) is None:
                        c.problems.append("no output for the warm-up frame")
                    latency_s = time.perf_counter() - t0
                    if moment == "idle":
                        time.sleep(rng.uniform(0.05, 1.0))
                    elif moment == "mid_frame":
                        send(1)
                        time.sleep(rng.uniform(0.05, 0.9) * latency_s)
                    elif moment == "mid_publish":
                        stamp = send(1)
                        deadline = time.monotonic() + 60
                        while not collector.arrivals.get(stamp) and time.monotonic() < deadline:
                            time.sleep(0.0005)
                        c.landed = 0 < len(collector.arrivals.get(stamp, ())) < 3
                    elif moment == "stream":
                        until = time.monotonic() + rng.uniform(0.3, 2.5)
                        i = 1
                        while time.monotonic() < until:
                            send(i)
                            i += 1
                            time.sleep(1 / 15)
                signalled = time.monotonic()
                node.proc.send_signal(SIGNALS[sig_name])
                if moment == "stream":       # clouds keep coming while it shuts down
                    for i in range(len(sent), len(sent) + 4):
                        send(i)
                        time.sleep(1 / 15)
                try:
                    node.proc.wait(timeout=timeout_s)
                except subprocess.TimeoutExpired:
                    c.hung = True
                    node.proc.kill()
                    node.proc.wait()
                c.exit_s = time.monotonic() - signalled
                c.exit_code = node.proc.returncode
                time.sleep(0.3)              # outputs still in transit arrive
                counts = [len(collector.arrivals.get(s, ())) for s in sent]
                c.sent, c.complete = len(sent), counts.count(3)
                c.partial = sum(1 for n in counts if 0 < n < 3)
            finally:
                collector.close()
    finally:
        rclpy.try_shutdown(context=context)
    log = log_path.read_text(errors="replace")
    c.totals = parse_totals(log)
    c.in_flight = 1 if "still being processed" in log else 0
    cores = _core_files(folder)
    c.core = bool(cores) or (c.exit_code is not None and -c.exit_code in CRASH_SIGNALS)
    _judge(c, log)
    return c, log, latency_s


@dataclass
class SoakReport:
    cycles: list[Cycle]
    load: int
    seconds: float
    kept: Path | None

    @property
    def ok(self) -> bool:
        return bool(self.cycles) and all(c.clean for c in self.cycles)

    def table(self) -> str:
        groups: dict[tuple[str, str], list[Cycle]] = defaultdict(list)
        for c in self.cycles:
            groups[(c.signal, c.moment)].append(c)
        head = (f"{'signal':8s} {'moment':12s} {'cycles':>6s}  {'exit codes':22s} {'cores':>5s} "
                f"{'hung':>4s} {'partial':>7s} {'lost':>4s} {'totals':>6s} {'log':>4s} "
                f"{'exit s (max)':>12s}")
        lines = [head]
        for key in sorted(groups):
            cs = groups[key]
            codes = Counter(c.exit_code for c in cs)
            code_text = ", ".join(f"{k}: {v}" for k, v in sorted(codes.items(), key=str))
            lost = sum(1 for c in cs if any(p.startswith("published") for p in c.problems))
            no_totals = sum(1 for c in cs if not c.totals)
            bad_log = sum(1 for c in cs if any(p.startswith("log:") for p in c.problems))
            exits = [c.exit_s for c in cs if not np.isnan(c.exit_s)]
            lines.append(
                f"{key[0]:8s} {key[1]:12s} {len(cs):6d}  {code_text:22s} "
                f"{sum(c.core for c in cs):5d} {sum(c.hung for c in cs):4d} "
                f"{sum(c.partial for c in cs):7d} {lost:4d} {len(cs) - no_totals:6d} "
                f"{bad_log:4d} {max(exits) if exits else float('nan'):12.2f}")
        codes = Counter(c.exit_code for c in self.cycles)
        mp = [c for c in self.cycles if c.moment == "mid_publish"]
        unclean = [c for c in self.cycles if not c.clean]
        lines += [
            "",
            f"cycles {len(self.cycles)} in {self.seconds:.0f} s, busy loops beside the node: "
            f"{self.load}; exit codes " + ", ".join(f"{k}: {v}" for k, v in
                                                    sorted(codes.items(), key=str)),
            f"core dumps {sum(c.core for c in self.cycles)}, hung {sum(c.hung for c in self.cycles)}"
            f", partial frames {sum(c.partial for c in self.cycles)}, totals lines "
            f"{sum(1 for c in self.cycles if c.totals)}/{len(self.cycles)}, frames sent "
            f"{sum(c.sent for c in self.cycles)}, complete {sum(c.complete for c in self.cycles)}",
            f"mid_publish signals that went out between a frame's outputs: "
            f"{sum(c.landed for c in mp)}/{len(mp)}",
            f"unclean cycles {len(unclean)}" + (f" (kept in {self.kept})" if self.kept and unclean
                                                else ""),
        ]
        for c in unclean[:20]:
            lines.append(f"  cycle {c.index} {c.signal} {c.moment}: " + "; ".join(c.problems))
        return "\n".join(lines)


def run_soak(cycles: int = 200, seed: int = 0, signals: tuple[str, ...] = tuple(SIGNALS),
             moments: tuple[str, ...] = MOMENTS, load: int = 0, model: Path = TINY_MODEL,
             size: tuple[int, int] = (480, 640), keep: Path | None = None,
             timeout_s: float = 20.0, core_dumps: bool = True,
             progress: bool = False) -> SoakReport:
    """``cycles`` node processes, the (signal, moment) pairs balanced and shuffled by ``seed``.
    ``keep``: a folder for the log and core of each unclean cycle (else all are deleted).
    ``core_dumps``: raise this process's core limit so the nodes inherit it (the test suite
    leaves it: a crash still shows as a negative exit code)."""
    rng = random.Random(seed)
    pairs = [(s, m) for s in signals for m in moments]
    plan = [pairs[i % len(pairs)] for i in range(cycles)]
    rng.shuffle(plan)
    clouds = [cf.make_cloud(cf.scene_xyz(size[0], size[1], seed=s, spheres=15), "xyz32")
              for s in range(3)]
    args = ["-p", f"model:={Path(model).resolve()}"]
    if core_dumps:
        resource.setrlimit(resource.RLIMIT_CORE,
                           (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    work = Path(tempfile.mkdtemp(prefix="fpcc_soak_"))
    busy = _busy_loops(load)
    done: list[Cycle] = []
    latency = 0.5
    t0 = time.monotonic()
    try:
        for i, (sig_name, moment) in enumerate(plan):
            c, log, latency = run_cycle(i, sig_name, moment, rng, work, args, clouds, latency,
                                        timeout_s)
            done.append(c)
            folder = work / f"cycle_{i:04d}"
            if keep is not None and not c.clean:
                keep.mkdir(parents=True, exist_ok=True)
                shutil.move(str(folder), str(keep / folder.name))
            else:
                shutil.rmtree(folder, ignore_errors=True)
            if progress:
                state = "ok" if c.clean else "; ".join(c.problems)
                print(f"  {i + 1}/{len(plan)} {sig_name} {moment}: exit {c.exit_code} in "
                      f"{c.exit_s:.2f} s, {c.complete}/{c.sent} frames complete; {state}",
                      flush=True)
    finally:
        for p in busy:
            p.kill()
            p.wait()
        shutil.rmtree(work, ignore_errors=True)
    return SoakReport(done, load, time.monotonic() - t0, keep)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--signals", nargs="+", choices=list(SIGNALS), default=list(SIGNALS))
    ap.add_argument("--moments", nargs="+", choices=MOMENTS, default=list(MOMENTS))
    ap.add_argument("--load", type=int, default=0,
                    help="busy-loop processes to run beside the node (2 = both cores busy)")
    ap.add_argument("--model", type=Path, default=TINY_MODEL)
    ap.add_argument("--keep", type=Path, default=None,
                    help="keep each unclean cycle's folder (node.log, core) here")
    ap.add_argument("--domain-id", type=int, default=None,
                    help="ROS_DOMAIN_ID for this run (default: one picked from the pid)")
    args = ap.parse_args()
    if args.domain_id is not None:
        os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    print(f"ROS_DOMAIN_ID {os.environ['ROS_DOMAIN_ID']}, discovery "
          f"{os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE']}", flush=True)
    report = run_soak(args.cycles, args.seed, tuple(args.signals), tuple(args.moments),
                      args.load, args.model, keep=args.keep, progress=True)
    print(report.table())
    print("PASS" if report.ok else "FAIL")
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
