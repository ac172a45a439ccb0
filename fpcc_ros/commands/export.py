"""`fpcc export`: a training checkpoint -> ONNX model + model card (+ torch weights beside it)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", help="checkpoint_*.pt from `fpcc train`")
    parser.add_argument("--out", required=True, metavar="MODEL.onnx",
                        help="ONNX file to write; the card (.json) and weights (.pt) go beside it")
    parser.add_argument("--part-radius", type=float, default=None, metavar="M",
                        help="default part radius in the card (default: the training scenes')")
    parser.add_argument("--name", default=None, help="model name in the card (default: file stem)")
    parser.add_argument("--block-size", type=int, default=None,
                        help="runtime block size in the card (default: the training block size)")
    parser.add_argument("--no-weights", action="store_true", help="do not write the .pt beside the ONNX")
    parser.add_argument("--force", action="store_true",
                        help="export even when a layer has more than 25%% dead channels")


def run(args: argparse.Namespace) -> int:
    from fpcc_ros.model_card import card_path_for
    from fpcc_ros.training.export import export_checkpoint

    out = Path(args.out)
    if out.suffix != ".onnx":
        print(f"fpcc export: --out {out} should end in .onnx", file=sys.stderr)
        return 2
    try:
        card = export_checkpoint(args.checkpoint, out, part_radius=args.part_radius, name=args.name,
                                 block_size=args.block_size, save_torch=not args.no_weights,
                                 force=args.force)
    except (FileNotFoundError, ValueError, RuntimeError) as exc:
        print(f"fpcc export: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB), card {card_path_for(out)}"
          + ("" if args.no_weights else f", weights {out.with_suffix('.pt')}"))
    health = card.training["health"]
    print("live channels: " + ", ".join(f"{n} {live}/{total}"
                                        for n, (live, total) in health["live_channels"].items())
          + f"; {health['tiny_weights_flushed']} tiny weights set to 0 "
          f"({health['denormal_weights_flushed']} denormal)")
    print(f"k={card.k} block_size={card.block_size} voxel_factor={card.voxel_factor} "
          f"part_radius={card.part_radius} metrics={card.metrics}")
    return 0
