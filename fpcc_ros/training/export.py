"""Export FPCC-Net to ONNX with its model card, and check onnxruntime agrees with torch.

The exported graph has batch norms folded into the linear layers (``model.fold_batchnorm``),
inputs ``features`` (B, N, 6) float32 and ``knn`` (B, N, K) int64 and outputs ``embedding``
(B, N, 128) and ``center_score`` (B, N); B and N are dynamic, K is fixed by the card.
The unfolded torch weights are saved beside the ONNX as ``<name>.pt`` so a shipped model can be
the ``--init`` of further training (ONNX weights cannot be trained).
"""
from __future__ import annotations

import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fpcc_ros.features import block_inputs, feature_names, takes_normals
from fpcc_ros.model_card import ModelCard, card_path_for
from fpcc_ros.weight_flush import FLUSH_BELOW, TINY as TINY_FLOAT
from fpcc_ros.training.health import EXPORT_DEAD_SHARE, channel_health, dead_layers, health_line
from fpcc_ros.training.model import TINY, FPCCNet, NetConfig, fold_batchnorm

OPSET = 17
WEIGHTS_FORMAT = "fpcc_ros/weights/1"


def export_onnx(model: FPCCNet, path: str | Path, k: int) -> Path:
    """Write ``model`` (eval mode, norms folded) as ONNX with dynamic batch and point axes;
    float weights under 1e-20 are written as 0 (graph_rewrite.optimize_file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    folded = fold_batchnorm(model)
    features, knn = _example_inputs(2, max(4 * k, 64), k, seed=0, normals=model.config.normals)
    kwargs: dict[str, Any] = dict(input_names=["features", "knn"],
                                  output_names=["embedding", "center_score"], opset_version=OPSET)
    dynamic_axes = {"features": {0: "batch", 1: "points"}, "knn": {0: "batch", 1: "points"},
                    "embedding": {0: "batch", 1: "points"}, "center_score": {0: "batch", 1: "points"}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy exporter's deprecation notice
        try:
            torch.onnx.export(folded, (features, knn), str(path), dynamo=False,
                              dynamic_axes=dynamic_axes, do_constant_folding=True, **kwargs)
        except (TypeError, RuntimeError, NotImplementedError) as legacy_error:
            # the TorchScript exporter is deprecated; the dynamo one needs a matching onnxscript
            # (with torch 2.13 the pinned onnxscript 0.5.6 lacks torch_2_11 support)
            batch, points = torch.export.Dim("batch"), torch.export.Dim("points")
            shapes = {"features": {0: batch, 1: points}, "knn": {0: batch, 1: points}}
            try:
                program = torch.onnx.export(folded, (features, knn), dynamo=True,
                                            dynamic_shapes=shapes, external_data=False, **kwargs)
                program.save(str(path))
            except Exception as dynamo_error:
                raise RuntimeError(f"ONNX export failed: legacy exporter: {legacy_error}; dynamo "
                                   f"exporter: {dynamo_error}") from dynamo_error
    # exact graph rewrite for onnxruntime's CPU kernels (global max-pool as GlobalMaxPool);
    # optimize_file checks the rewritten outputs against the original before replacing it
    from fpcc_ros.graph_rewrite import optimize_file
    optimize_file(path, path)
    return path


@torch.no_grad()
def tiny_weights(model: FPCCNet) -> dict[str, int]:
    """Folded float weights the export writes as 0: under 1e-20, and of those the denormal ones
    (the remains of collapsed channels; see fpcc_ros.weight_flush)."""
    values = torch.cat([p.flatten() for p in fold_batchnorm(model).parameters()]).abs()
    nonzero = values != 0
    return {"tiny_weights_flushed": int((nonzero & (values < FLUSH_BELOW)).sum()),
            "denormal_weights_flushed": int((nonzero & (values < TINY_FLOAT)).sum())}


def check_onnx(model: FPCCNet, path: str | Path, k: int, batch: int = 2, points: int = 300,
               seed: int = 1) -> float:
    """Max |onnxruntime - torch| over both outputs on a random block of real geometry."""
    import onnxruntime as ort

    features, knn = _example_inputs(batch, points, k, seed, normals=model.config.normals)
    model = model.eval()
    with torch.no_grad():
        emb, score = model(features, knn)
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1  # a correctness check: no thread pool to spin up
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    o_emb, o_score = session.run(["embedding", "center_score"],
                                 {"features": features.numpy(), "knn": knn.numpy()})
    return float(max(np.abs(o_emb - emb.numpy()).max(), np.abs(o_score - score.numpy()).max()))


def export_checkpoint(checkpoint: str | Path, out: str | Path, part_radius: float | None = None,
                      name: str | None = None, block_size: int | None = None,
                      save_torch: bool = True, check: bool = True, tolerance: float = 1e-4,
                      force: bool = False) -> ModelCard:
    """Export a training checkpoint to ``out`` (.onnx) with its card (and ``.pt`` weights).

    A network with a layer more than 25 % dead (health.EXPORT_DEAD_SHARE) is refused unless
    ``force``: such a model answers, slowly and badly, and users cannot tell why."""
    from fpcc_ros.training.train import TrainConfig, load_checkpoint, model_from_checkpoint

    state = load_checkpoint(checkpoint)
    model = model_from_checkpoint(state).eval()
    config = TrainConfig.from_dict(state.get("config", {}))
    trained_on = dict(state.get("trained_on", {}))
    if part_radius is None:
        part_radius = trained_on.get("part_radius")
        if part_radius is None:
            raise ValueError(f"{checkpoint} does not record the training part radius; pass --part-radius")
    health = channel_health(model)
    dying = dead_layers(health, EXPORT_DEAD_SHARE)
    if dying and not force:
        worst = ", ".join(f"{name} {share:.0%}" for name, share in dying.items())
        raise ValueError(f"{checkpoint}: dead channels in {worst} (more than "
                         f"{EXPORT_DEAD_SHARE:.0%} of a layer outputs a constant; live: "
                         f"{health_line(health)}); retrain from scratch with this release's "
                         "optimizer, or pass --force to export it anyway")
    out = Path(out)
    export_onnx(model, out, config.data.k)
    if check:
        diff = check_onnx(model, out, config.data.k)
        if diff >= tolerance:
            raise RuntimeError(f"exported {out}: onnxruntime and torch differ by {diff:.2e} "
                               f"(>= {tolerance:.0e}); the ONNX model is not trustworthy")
    history = state.get("history", [])
    last = history[-1] if history else {}
    card = ModelCard(
        name=name or out.stem, k=config.data.k, part_radius=float(part_radius),
        feature_names=feature_names(model.config.normals),
        knn_near=config.data.knn_near, knn_reach=config.data.knn_reach,
        block_size=int(block_size or config.data.block_size), voxel_factor=config.data.voxel_factor,
        screening_factor=config.screening_factor, score_threshold=config.score_threshold,
        feature_gate=config.feature_gate,
        description="FPCC-Net (DGCNN backbone on one xyz kNN graph, embedding + center-score heads)",
        trained_on=trained_on,
        # a run stopped by --time-limit saves its weights mid-epoch: the metrics (the last
        # validated epoch's) then describe weights this many steps older
        training={"command": " ".join(state.get("command", [])), "epochs": len(history),
                  "steps_after_last_epoch": int(state.get("step", 0)),
                  "wall_time_s": round(float(state.get("wall_time_s", 0.0)), 1),
                  "config": config.to_dict(), "checkpoint": str(checkpoint),
                  "health": {"live_channels": {n: list(v) for n, v in health.items()},
                             **tiny_weights(model)}},
        metrics={k: v for k, v in last.items() if k.startswith("val_") or k.startswith("loss")},
    )
    card.save(card_path_for(out))
    if save_torch:
        torch.save({"format": WEIGHTS_FORMAT, "model": model.state_dict(), "net": model.config.to_dict(),
                    "config": config.to_dict(), "trained_on": trained_on, "history": history,
                    "command": state.get("command", []), "wall_time_s": state.get("wall_time_s", 0.0)},
                   out.with_suffix(".pt"))
    return card


def export_untrained(path: str | Path, k: int = 16, seed: int = 0, part_radius: float = 0.05,
                     net: NetConfig = TINY, block_size: int = 4096) -> ModelCard:
    """A small untrained model + card for tests. Batch-norm statistics are calibrated on random
    blocks so outputs have realistic spread (some center scores above 0.6, distinct embeddings)."""
    torch.manual_seed(seed)
    model = FPCCNet(net)
    for module in model.modules():
        if isinstance(module, torch.nn.BatchNorm1d):
            module.momentum = None  # cumulative average over the calibration passes
    model.train()
    with torch.no_grad():
        for i in range(4):
            model(*_example_inputs(2, 256, k, seed=seed + 100 + i, part_radius=part_radius,
                                   normals=net.normals))
    model.eval()
    path = Path(path)
    export_onnx(model, path, k)
    card = ModelCard(name=path.stem, k=k, part_radius=part_radius, block_size=block_size,
                     feature_names=feature_names(net.normals),
                     description="UNTRAINED FPCC-Net for tests: right inputs and outputs, "
                     "meaningless predictions", trained_on={}, training={"untrained": True, "seed": seed,
                                                                         "net": net.to_dict()})
    card.save(card_path_for(path))
    return card


def _example_inputs(batch: int, points: int, k: int, seed: int, part_radius: float = 0.05,
                    normals: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Blocks of random points on a few spheres (real features and kNN graphs)."""
    rng = np.random.default_rng(seed)
    feats, knns = [], []
    for _ in range(batch):
        centers = rng.uniform(0, 4 * part_radius, size=(4, 3))
        dirs = rng.normal(size=(points, 3))
        xyz = centers[rng.integers(0, 4, points)] + part_radius * dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
        features, knn = block_inputs(xyz, part_radius, k, normals)
        feats.append(features)
        knns.append(knn)
    return torch.from_numpy(np.stack(feats)), torch.from_numpy(np.stack(knns))


def time_onnx(path: str | Path, points: int = 4096, k: int = 16, threads: int = 2,
              repeats: int = 10) -> float:
    """Median seconds of one onnxruntime run on one block of ``points`` points."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    width = {i.name: i.shape for i in session.get_inputs()}["features"][-1]
    features, knn = _example_inputs(1, points, k, seed=3, normals=takes_normals(width))
    feed = {"features": features.numpy(), "knn": knn.numpy()}
    session.run(None, feed)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        session.run(None, feed)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


