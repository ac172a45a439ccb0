"""`fpcc`: the command-line entry point (DESIGN.md §5).

Each subcommand lives in ``fpcc_ros/commands/<name>.py`` with ``add_arguments`` and ``run``.
They are imported only when chosen, so `fpcc segment` never pays for torch or pybullet.
"""
from __future__ import annotations

import argparse
import importlib
import sys

from fpcc_ros.heap import retain_freed_memory

COMMANDS = {
    "segment": ("segment", "segment a bag / NPZ / PLY / PCD / TXT file, write labelled output"),
    "demo": ("demo", "start the node, replay the demo bag through it, record, summarise, render"),
    "synth": ("synth", "generate synthetic bin scenes from a mesh or a built-in part"),
    "train": ("train", "train FPCC-Net on synthetic scenes"),
    "export": ("export", "export a trained checkpoint to ONNX + model card"),
    "calibrate": ("calibrate", "choose score threshold, feature gate and screening factor on "
                  "validation scenes; --write stores them in the model card"),
    "eval": ("evaluate", "precision/recall at IoU 0.5, MUCov, MWCov vs tuned clustering baselines"),
    "render": ("render", "PNG of labels and center scores of a scene or segmented output"),
    "bench": ("bench", "latency per stage, end to end, memory and accuracy"),
    "part-info": ("part_info", "d_max of a part mesh and a suggested part_radius"),
}

# Commands that segment frame after frame in this process keep freed frame memory for the next
# frame (fpcc_ros.heap); training and scene generation keep the C library's defaults, whose
# per-thread arenas suit torch's and pybullet's threads.
RETAIN_FREED_MEMORY = ("segment", "eval", "calibrate", "bench")


def _chosen(argv: list[str]) -> str | None:
    return next((a for a in argv if a in COMMANDS), None)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fpcc", description=__doc__.splitlines()[0])
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen = _chosen(sys.argv[1:])
    for name, (module, help_text) in COMMANDS.items():
        sub = subparsers.add_parser(name, help=help_text, description=help_text)
        if name == chosen:  # only the chosen command's module is imported
            _module(module).add_arguments(sub)
    return parser


def _module(name: str):
    return importlib.import_module(f"fpcc_ros.commands.{name}")


def main(argv: list[str] | None = None) -> int:
    if argv is not None:
        sys.argv = [sys.argv[0], *argv]
    if _chosen(sys.argv[1:]) in RETAIN_FREED_MEMORY:
        retain_freed_memory()  # before the command's imports start threads: see fpcc_ros.heap
    parser = build_parser()
    args = parser.parse_args()
    if not args.command:
        parser.print_help()
        return 2
    try:
        return int(_module(COMMANDS[args.command][0]).run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
