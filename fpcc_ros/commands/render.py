"""`fpcc render IN --out PNG`: a picture of a scene or a segmentation result.

IN is a scene NPZ (ground truth, or the `*_segmented.npz` that `fpcc segment` writes: labels in
`instance`), a PLY/PCD/TXT file with label fields, or a rosbag2 bag with `segmented_points`
(the frame chosen with --index). Panels: instances in the node's palette and center scores;
with --ground-truth SCENE.npz the ground truth is drawn beside the prediction.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("input", type=Path, help="scene/segmented NPZ, PLY/PCD/TXT, or a bag")
    parser.add_argument("--out", type=Path, default=None, help="PNG path (default: IN.png)")
    parser.add_argument("--index", type=int, default=0, help="which segmented frame of a bag")
    parser.add_argument("--topic", default="/segmented_points", help="labelled cloud topic in a bag")
    parser.add_argument("--ground-truth", type=Path, default=None,
                        help="scene NPZ whose `instance` is drawn as a ground-truth panel")
    parser.add_argument("--title", default=None)


def run(args: argparse.Namespace) -> int:
    from msg_tools.bag import BagError
    from msg_tools.formats import FormatError
    from fpcc_ros.render import render_segmentation

    try:
        xyz, labels, scores, shape = _load(args)
        gt = None
        if args.ground_truth is not None:
            gt = np.load(args.ground_truth)["instance"].reshape(-1)
            if gt.size != labels.size:
                raise ValueError(f"--ground-truth has {gt.size} points, {args.input} has "
                                 f"{labels.size}; pass the scene the prediction was made from")
    except (BagError, FormatError, ValueError, KeyError, OSError) as exc:
        print(f"fpcc render: {exc}", file=sys.stderr)
        return 2
    out = args.out or args.input.with_suffix(".png")
    k = len(np.unique(labels[labels > 0]))
    render_segmentation(out, xyz, labels, scores, shape=shape, ground_truth=gt,
                        title=args.title or f"{args.input.name}: {k} instances")
    print(f"wrote {out}")
    return 0


def _load(args: argparse.Namespace):
    path = args.input
    if not path.exists():
        raise ValueError(f"{path} does not exist")
    if path.is_dir() or path.suffix == ".mcap":
        from msg_tools.bag import read_messages
        from msg_tools.point_cloud2 import read_points, read_xyz
        for i, (_, _, _, msg) in enumerate(read_messages(path, [args.topic])):
            if i == args.index:
                pts = read_points(msg)
                names = pts.dtype.names or ()
                if "label" not in names:
                    raise ValueError(f"{args.topic} in {path} has no 'label' field; render the "
                                     "output of the node or of `fpcc segment`")
                scores = pts["center_score"] if "center_score" in names else None
                return read_xyz(msg), pts["label"].astype(np.int64), scores, (msg.height, msg.width)
        raise ValueError(f"{path} has no message {args.index} on {args.topic}")
    from msg_tools.formats import read_scene
    xyz, extra = read_scene(path)
    shape = xyz.shape[:2] if xyz.ndim == 3 else None
    labels = next((extra[k] for k in ("instance", "label", "labels") if k in extra), None)
    if labels is None:
        raise ValueError(f"{path} has no instance/label values to draw")
    scores = extra.get("center_score")
    return (xyz.reshape(-1, 3), np.asarray(labels).reshape(-1).astype(np.int64),
            None if scores is None else np.asarray(scores).reshape(-1), shape)
