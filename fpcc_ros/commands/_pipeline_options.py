"""Model and pipeline options shared by `segment`, `eval` and `bench`."""
from __future__ import annotations

import argparse
from typing import Any

from fpcc_ros.model_card import CLUSTERINGS
from fpcc_ros.onnx_model import FpccModel, default_model_path
from fpcc_ros.pipeline import Pipeline, PipelineConfig
from fpcc_ros.view import VIEW_AXES


def add_pipeline_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("model and pipeline (defaults: the model card)")
    group.add_argument("--model", default=None, help="FPCC-Net .onnx (default: shipped model)")
    group.add_argument("--part-radius", type=float, default=None, help="part d_max in metres")
    group.add_argument("--screening-factor", type=float, default=None, help="NMS gamma")
    group.add_argument("--score-threshold", type=float, default=None, help="NMS theta")
    group.add_argument("--min-points", type=int, default=None, help="smallest instance kept")
    group.add_argument("--voxel-size", type=float, default=None,
                       help="m; 0 = off (full resolution), -1 = auto")
    group.add_argument("--feature-gate", type=float, default=None)
    group.add_argument("--center-merge", type=float, default=None,
                       help="merge centers within d_max closer than this in embedding space (0 off)")
    group.add_argument("--center-prototype", type=float, default=None,
                       help="part radii around a center whose like points' mean embedding "
                       "stands for it (0 = the center point's own)")
    group.add_argument("--global-stride", type=int, default=None,
                       help="the network's global feature over every s-th point of a block "
                       "(1 = every point, exact; default: the model card's)")
    group.add_argument("--clustering", default=None, choices=CLUSTERINGS,
                       help="paper: every point to the nearest center in feature space (§3.2); "
                       "connected: geometric fragments (DBSCAN) decided by the centers' labels "
                       "(default: the model card's)")
    group.add_argument("--fragment-eps", type=float, default=None,
                       help="connected: DBSCAN eps in metres")
    group.add_argument("--fragment-density", type=int, default=None,
                       help="connected: DBSCAN min_samples in input points")
    group.add_argument("--fragment-min-points", type=int, default=None,
                       help="connected: smallest instance without a center, input points")
    group.add_argument("--fragment-join", type=float, default=None,
                       help="connected: a center's fragments join within a box of this "
                       "diagonal, part radii (2 = a whole part)")
    group.add_argument("--fragment-crease", type=float, default=None,
                       help="connected, organized clouds: cut pixels on concave creases sharper "
                       "than this curvature, 1/m (where touching parts meet; 0 = off)")
    group.add_argument("--view-axis", default=None, choices=VIEW_AXES,
                       help="the direction the camera looks along in the cloud's frame: +z for a "
                       "camera optical frame (synth scenes), -z for a z-up world/base frame "
                       "with the camera above the bin; auto (default) tells them apart from "
                       "the points")
    group.add_argument("--roi-min", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"))
    group.add_argument("--roi-max", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"))
    group.add_argument("--threads", type=int, default=0, help="onnxruntime threads (0 = all)")
    group.add_argument("--provider", default="cpu", choices=["cpu", "cuda"],
                       help="onnxruntime execution provider")


def positive_int(text: str) -> int:
    """argparse type for counts (--runs, --limit)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


PROVIDERS = {"cpu": ["CPUExecutionProvider"],
             "cuda": ["CUDAExecutionProvider", "CPUExecutionProvider"]}


def config_overrides(args: argparse.Namespace) -> dict[str, Any]:
    names = ("part_radius", "screening_factor", "score_threshold", "min_points", "voxel_size",
             "feature_gate", "center_merge", "center_prototype", "roi_min",
             "roi_max", "view_axis", "global_stride", "clustering", "fragment_eps",
             "fragment_density", "fragment_min_points", "fragment_join", "fragment_crease")
    return {n: getattr(args, n) for n in names if getattr(args, n, None) is not None}


def build_pipeline(args: argparse.Namespace, **extra: Any) -> Pipeline:
    """Raises ModelLoadError / ConfigError with user-facing messages."""
    model = FpccModel(args.model or default_model_path(), providers=PROVIDERS[args.provider],
                      threads=args.threads)
    return Pipeline(model, PipelineConfig.from_card(model.card, **{**config_overrides(args), **extra}))
