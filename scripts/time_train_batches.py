#!/usr/bin/env python3
"""Training throughput per batch size, on real blocks, before a training budget is spent on one.

A training step is forward, loss, backward and an AdamW step of the full-width FPCC-Net (with
the surface-normal inputs, as the shipped default), in the precision `fpcc train --precision
auto` picks. Each batch size runs on the same blocks (the first scenes' blocks of `--data`,
without augmentation), interleaved round by round so a busy second core costs every size
alike. It prints the CPU (vendor, model, vector extensions): the speed of a batch size is the
CPU's cache as much as its cores. Accuracy is not measured: a size worth its speed still has to
be trained and evaluated (README, "Train it for your part").

    .venv/bin/python scripts/time_train_batches.py --data WORK/data/gear_shaft/train
    .venv/bin/python scripts/time_train_batches.py --data DIR --batches 1 2 4 8 --rounds 5
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", required=True, metavar="DIR",
                        help="scene folders (fpcc synth's output); their first blocks are used")
    parser.add_argument("--batches", type=int, nargs="+", default=[2, 4], metavar="B",
                        help="batch sizes (blocks per step) to compare; the first is the 1.00x")
    parser.add_argument("--blocks", type=int, default=32,
                        help="blocks each size trains on per round (a multiple of every size)")
    parser.add_argument("--rounds", type=int, default=3, help="timed rounds (one more warms up)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    args = parser.parse_args()
    if min(args.batches) < 1 or any(args.blocks % b for b in args.batches):
        parser.error(f"--blocks {args.blocks} must be a multiple of every --batches size "
                     f"{args.batches} (sizes >= 1)")

    import torch

    from fpcc_ros.bench import cpu_description, cpu_vendor
    from fpcc_ros.training.dataset import DataConfig, collate, find_scenes, load_scene, scene_blocks
    from fpcc_ros.training.health import make_optimizer
    from fpcc_ros.training.loss import batch_loss
    from fpcc_ros.training.model import FPCCNet, NetConfig
    from fpcc_ros.training.train import resolve_precision

    torch.set_num_threads(args.threads)
    config = DataConfig(normals=True)
    blocks: list = []
    for path in find_scenes(args.data):
        blocks += scene_blocks(load_scene(path), config).blocks
        if len(blocks) >= args.blocks:
            break
    if len(blocks) < args.blocks:
        parser.error(f"--data holds {len(blocks)} blocks, fewer than --blocks {args.blocks}")
    blocks = blocks[:args.blocks]
    points = sum(len(b.xyz) for b in blocks)
    precision = resolve_precision("auto")
    torch.manual_seed(0)
    net = FPCCNet(NetConfig(in_features=len(blocks[0].features[0]))).train()
    optimizer = make_optimizer(net, 1e-4, 1e-4)

    def train_on(batch_size: int) -> float:
        start = time.perf_counter()
        for first in range(0, len(blocks), batch_size):
            batch = collate(blocks[first:first + batch_size])
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
                embedding, score = net(batch["features"], batch["knn"])
            loss = batch_loss(embedding.float(), score.float(), batch)[0]
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        return time.perf_counter() - start

    seconds: dict[int, list[float]] = {b: [] for b in args.batches}
    for round_ in range(args.rounds + 1):
        for b in args.batches:
            elapsed = train_on(b)
            if round_ > 0:
                seconds[b].append(elapsed)
    cpuinfo = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    model, vector = cpu_description(cpuinfo)
    print(f"CPU: {cpu_vendor(cpuinfo) or '?'} {model or '?'} ({' '.join(vector) or 'no AVX'}), "
          f"{args.threads} torch threads, {precision}")
    print(f"{len(blocks)} blocks ({points} points), median of {args.rounds} interleaved rounds:")
    base = None
    for b, values in seconds.items():
        median = float(np.median(values))
        rate = points / median
        base = base or rate
        print(f"  batch {b:<3} {median / (len(blocks) // b) * 1e3:7.0f} ms/step "
              f"{rate:8.0f} points/s  {rate / base:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
