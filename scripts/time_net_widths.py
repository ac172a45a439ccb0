#!/usr/bin/env python3
"""Network time per block for narrower FPCC-Nets, before anyone spends hours training one.

Each width is built with random weights, exported and rewritten exactly as `fpcc export` does,
and run on the same camera-like block, interleaved, on onnxruntime's CPU provider. Accuracy is
not measured here: a width worth its speed still has to be trained and evaluated.

    .venv/bin/python scripts/time_net_widths.py                  # 3,200-point block
    .venv/bin/python scripts/time_net_widths.py --points 2500 --runs 20
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

WIDTHS = {   # name: NetConfig overrides (the paper's widths: edge 64, global 1024, 512/256)
    "shipped": {},
    "global 512": {"global_dim": 512},
    "edge 48": {"edge_dim": 48},
    "edge 32": {"edge_dim": 32},
    "edge 32, global 512": {"edge_dim": 32, "global_dim": 512},
    "all but edge halved": {"global_dim": 512, "point_dims": (256, 128)},
}


def camera_like_block(points: int, k: int = 16, near: int = 8, reach: int = 48
                      ) -> tuple[np.ndarray, np.ndarray]:
    from fpcc_ros.features import block_features, knn_graph, select_neighbours

    rng = np.random.default_rng(0)
    xyz = rng.uniform(0.0, 0.3, (points, 3))
    xyz[:, 2] *= 0.1   # a shallow slab: a pile seen from above
    return (block_features(xyz, 0.05)[None],
            select_neighbours(knn_graph(xyz, reach), k, near, reach)[None])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=3200, help="points per block")
    parser.add_argument("--runs", type=int, default=10, help="timed runs per width")
    args = parser.parse_args()

    import onnxruntime as ort
    import torch

    from fpcc_ros.training.export import export_onnx
    from fpcc_ros.training.model import FPCCNet, NetConfig, fold_batchnorm

    torch.manual_seed(0)
    features, knn = camera_like_block(args.points)
    sessions = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i, (name, overrides) in enumerate(WIDTHS.items()):
            net = fold_batchnorm(FPCCNet(NetConfig(**overrides)).eval())
            path = export_onnx(net, Path(tmp) / f"width{i}.onnx", knn.shape[-1])
            options = ort.SessionOptions()
            options.add_session_config_entry("session.force_spinning_stop", "1")
            sessions[name] = ort.InferenceSession(str(path), options,
                                                  providers=["CPUExecutionProvider"])
    times: dict[str, list[float]] = {name: [] for name in sessions}
    for run in range(args.runs + 2):   # interleaved; the first two warm up
        for name, session in sessions.items():
            t0 = time.perf_counter()
            session.run(None, {"features": features, "knn": knn})
            if run >= 2:
                times[name].append((time.perf_counter() - t0) * 1e3)
    base = float(np.median(times["shipped"]))
    print(f"{args.points}-point block, median of {args.runs} interleaved runs:")
    for name, values in times.items():
        median = float(np.median(values))
        print(f"  {name:<22} {median:7.1f} ms  {median / base:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
