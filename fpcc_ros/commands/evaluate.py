"""`fpcc eval --data DIR`: FPCC vs the tuned classical baselines on labelled scene NPZs.

Prints a per-scene table and a summary with FPCC beside the stronger baseline (Euclidean
clustering or DBSCAN, each tuned on the first scenes) under the paper and visible protocols
(DESIGN.md §4b), and writes the full report, both baselines included, as JSON.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from fpcc_ros.commands._pipeline_options import (add_pipeline_arguments, build_pipeline,
                                                 positive_int)
from fpcc_ros.oracle import ORACLE_HEADS

SEGMENT_OUTPUT_SUFFIX = "_segmented.npz"  # written by `fpcc segment`: predictions, not ground truth


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True, metavar="DIR",
                        help="directory of scene NPZ files with ground truth (DESIGN.md §4), or "
                        "of labelled text scenes (.txt, with --part-radius); its sub-folders "
                        "are searched too")
    parser.add_argument("--columns", choices=["paper", "peer"], default="paper",
                        help="columns of .txt scenes: paper = x y z center_score instance (the "
                        "FPCC authors' format), peer = x y z instance center_score")
    parser.add_argument("--out", type=Path, default=None, metavar="REPORT.json",
                        help="JSON report (default: DIR/eval_<model stem>.json, or ./ when DIR "
                        "is read-only)")
    parser.add_argument("--limit", type=positive_int, default=None, metavar="N",
                        help="evaluate only the first N scenes (sorted by name)")
    parser.add_argument("--protocol", choices=["visible", "paper", "both"], default="both",
                        help="visible: GT instances under 300 points at 640x480 removed; paper: "
                        "every GT instance counts (default: both)")
    parser.add_argument("--baseline-eps", "--baseline-tolerances", dest="baseline_tolerances",
                        type=float, nargs="+", default=None, metavar="M",
                        help="link distances to sweep, metres: DBSCAN's eps and the Euclidean "
                        "clustering tolerance (default: 2-20%% of the median part radius, 10 "
                        "steps)")
    parser.add_argument("--baseline-min-samples", type=positive_int, nargs="+",
                        default=None, metavar="N",
                        help="DBSCAN min_samples to sweep: points within eps, the point itself "
                        "included, as in scikit-learn (default: 1 2 3 5 8 12 20 30 45)")
    parser.add_argument("--baseline-min-cluster", type=positive_int, nargs="+",
                        default=None, metavar="N",
                        help="minimum cluster sizes to sweep for both baselines, input points "
                        "(default: 1 25 50 100 200 300 400 600 800)")
    parser.add_argument("--baseline-tune", type=positive_int, default=3,
                        metavar="N", help="tune the baselines on the first N scenes of each "
                        "part (a scene's part_name, else its sub-folder), then run each part's "
                        "settings on all its scenes (default: %(default)s)")
    parser.add_argument("--no-baseline", action="store_true", help="evaluate FPCC only")
    oracle = parser.add_mutually_exclusive_group()
    oracle.add_argument("--oracle-embeddings", action="store_true",
                        help="ground truth in place of the network: each scene's center scores "
                        "and a one-hot embedding per instance go through the same NMS and "
                        "clustering, so FPCC's figures are the ceiling of --clustering on "
                        "these scenes (the model is loaded for its card only)")
    oracle.add_argument("--oracle-head", choices=ORACLE_HEADS, default=None,
                        help="ground truth for this one of the network's outputs, the network's "
                        "own for the other: which head limits the model (compare with the "
                        "network alone and with --oracle-embeddings)")
    add_pipeline_arguments(parser)


def default_report_path(data: Path, model_path: Path) -> Path:
    """Beside the scenes, unless their folder is read-only (a shared dataset): then the working
    directory, so a long evaluation does not end in a write error."""
    name = f"eval_{model_path.stem}.json"
    return data / name if os.access(data, os.W_OK) else Path.cwd() / name


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from fpcc_ros.evaluation import EvalError, evaluate
    from fpcc_ros.onnx_model import ModelLoadError, default_model_path
    from fpcc_ros.pipeline import ConfigError

    def fail(message: str) -> int:
        print(f"fpcc eval: {message}", file=sys.stderr)
        return 2

    data: Path = args.data
    if not data.is_dir():
        return fail(f"--data {data} is not a directory; point it at a folder of scene .npz files")
    # sub-folders too, as `fpcc train` and `fpcc calibrate` read --data: a validation set of
    # several parts (scripts/make_default_dataset.sh) is one folder per part
    found = [p for p in data.rglob("*") if p.suffix in (".npz", ".txt") and p.is_file()]
    scenes = sorted(p for p in found if not p.name.endswith(SEGMENT_OUTPUT_SUFFIX))
    ignored = len(found) - len(scenes)
    if ignored:
        print(f"ignoring {ignored} *{SEGMENT_OUTPUT_SUFFIX} file(s): `fpcc segment` outputs hold "
              "predictions, not ground truth", file=sys.stderr)
    if not scenes:
        return fail(f"--data {data} holds no scene .npz or .txt files, nor do its sub-folders "
                    "(make some with `fpcc synth`)")
    if args.limit:
        scenes = scenes[:args.limit]
    protocols = ("paper", "visible") if args.protocol == "both" else (args.protocol,)
    model_path = Path(args.model) if args.model else default_model_path()
    out: Path = args.out or default_report_path(data, model_path)

    sweep = {k: v for k, v in (("min_samples", args.baseline_min_samples),
                               ("min_cluster_sizes", args.baseline_min_cluster)) if v}
    try:
        pipeline = build_pipeline(args)
        report = evaluate(scenes, pipeline, tolerances=args.baseline_tolerances,
                          protocols=protocols, baseline=not args.no_baseline,
                          tune_scenes=args.baseline_tune, **sweep,
                          fixed_part_radius=args.part_radius is not None,
                          progress=lambda it: tqdm(it, desc="eval", unit="scene", file=sys.stderr),
                          warn=lambda msg: tqdm.write(f"warning: {msg}", file=sys.stderr),
                          columns=args.columns, oracle=_oracle_heads(args), root=data)
    except (ModelLoadError, ConfigError, EvalError) as exc:
        return fail(str(exc))

    print(report.table())
    print()
    print(report.summary())
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(report.to_json(), indent=2) + "\n")
    except OSError as exc:
        return fail(f"cannot write the report to {out} ({exc}); choose another --out")
    print(f"wrote {out}")
    return 0


def _oracle_heads(args: argparse.Namespace) -> tuple[str, ...]:
    """The network outputs ground truth replaces: both, one, or none."""
    if args.oracle_embeddings:
        return ORACLE_HEADS
    return (args.oracle_head,) if args.oracle_head else ()
