#!/usr/bin/env python3
"""Re-initialise a trained FPCC-Net's dead channels, keeping its outputs, as a warm start.

A collapsed net (the shipped default of issue 23: 80-87 % of its wide layers dead) cannot be
repaired by training it further: a dead channel gets no gradient. This gives each dead channel
fresh input weights and the layers that read it a zero weight (see
fpcc_ros/training/revive.py), so the written checkpoint computes what the source did and every
channel trains from the first step:

    .venv/bin/python scripts/revive_net.py models/fpcc_default.pt revived.pt
    .venv/bin/python -m fpcc_ros.cli train --init revived.pt --data DIR ... --out runs/revived
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import torch  # noqa: E402 - after the checkout is on the path

from fpcc_ros.training.health import channel_health, health_line  # noqa: E402
from fpcc_ros.training.revive import revive_dead_channels  # noqa: E402
from fpcc_ros.training.train import load_checkpoint, model_from_checkpoint  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("src", help="a checkpoint or the .pt beside an exported model")
    parser.add_argument("dst", help="the revived checkpoint to write")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fresh input weights")
    args = parser.parse_args()
    state = load_checkpoint(args.src)
    model = model_from_checkpoint(state)
    print(f"before: {health_line(channel_health(model))}")
    revived = revive_dead_channels(model, torch.Generator().manual_seed(args.seed))
    out = {key: value for key, value in state.items()
           if key not in ("optimizer", "partial", "torch_rng")}   # a warm start, not a resume
    out["model"] = model.state_dict()
    out["revived"] = revived
    torch.save(out, args.dst)
    print(f"after:  {health_line(channel_health(model))}")
    print(f"wrote {args.dst}: {sum(revived.values())} channels revived "
          f"({', '.join(f'{k} {v}' for k, v in revived.items()) or 'none were dead'}); "
          "train it (fpcc train --init) to put them to use")
    return 0


if __name__ == "__main__":
    sys.exit(main())
