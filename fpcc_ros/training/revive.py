"""Bring a collapsed network's dead channels back to life without changing what it computes.

A dead channel (norm scale ~0 or a constant input, see :mod:`fpcc_ros.training.health`) outputs
the constant ``act(beta)`` and gets no gradient, so training alone never revives it (issue 23).
Here each dead channel gets fresh input weights and a unit norm, and every layer that reads it
gets a zero weight for it instead, with the constant it used to read moved into that layer's
norm mean (or bias): the network's outputs are unchanged, and the zero read weights receive
gradient from the first step, after which the channel trains like any other. This is the
"recycling dormant neurons" remedy (ReDo, Sokar et al., ICML 2023) applied to batch-norm layers.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from fpcc_ros.training.health import dead_channels, dense_layers
from fpcc_ros.training.model import Dense, FPCCNet


def channel_readers(model: FPCCNet) -> dict[str, list[tuple[str, int, int | None]]]:
    """Layer -> the layers reading its output: (reader, column offset, second offset or None).

    The second offset is an EdgeConv's [x_i, x_j - x_i] half, where a constant channel
    contributes nothing (x_j - x_i = 0) but the column must still be cleared.
    """
    e = model.config.edge_dim
    return {
        "edge1a": [("edge1b", 0, None)],
        "edge1b": [("edge2a", 0, e), ("glob", 0, None), ("point1", 0, None)],
        "edge2a": [("edge2b", 0, None)],
        "edge2b": [("edge3", 0, e), ("glob", e, None), ("point1", e, None)],
        "edge3": [("glob", 2 * e, None), ("point1", 2 * e, None)],
        "glob": [("point1", 3 * e, None)],
        "point1": [("point2", 0, None)],
        "point2": [("emb_hidden", 0, None), ("score_hidden", 0, None)],
        "emb_hidden": [("emb_out", 0, None)],
        "score_hidden": [("score_out", 0, None)],
    }


@torch.no_grad()
def revive_dead_channels(model: FPCCNet, generator: torch.Generator | None = None) -> dict[str, int]:
    """Re-initialise every dead channel of ``model`` in place, keeping its eval-mode outputs.

    Returns layer -> channels revived (layers with none left out).
    """
    layers = dense_layers(model)
    dead = {name: dead_channels(layer.bn) for name, layer in layers.items()}
    # what each dead channel outputs now: its norm's shift through the activation
    constant = {name: layers[name].act(layers[name].bn.bias) for name in layers}
    for name, readers in channel_readers(model).items():
        rows = torch.nonzero(dead[name]).flatten()
        if rows.numel() == 0:
            continue
        for reader_name, offset, second in readers:
            reader = getattr(model, reader_name)
            linear = reader.linear if isinstance(reader, Dense) else reader
            cols = rows + offset
            shift = linear.weight[:, cols] @ constant[name][rows]
            if isinstance(reader, Dense):       # the norm subtracts its mean: keep pre - mean
                reader.bn.running_mean -= shift
            else:                               # a plain output linear: fold into its bias
                reader.bias += shift
            linear.weight[:, cols] = 0.0
            if second is not None:
                linear.weight[:, rows + second] = 0.0
    for name, layer in layers.items():
        rows = torch.nonzero(dead[name]).flatten()
        if rows.numel():
            _fresh_rows(layer, rows, generator)
    return {name: int(mask.sum()) for name, mask in dead.items() if mask.any()}


def _fresh_rows(layer: Dense, rows: torch.Tensor, generator: torch.Generator | None) -> None:
    """``nn.Linear``'s default initialisation for the given output rows, and a unit norm."""
    fan_in = layer.linear.weight.shape[1]
    bound = 1.0 / math.sqrt(fan_in)
    fresh = torch.rand(len(rows), fan_in, generator=generator) * 2 * bound - bound
    layer.linear.weight[rows] = fresh.to(layer.linear.weight.dtype)
    bn: nn.BatchNorm1d = layer.bn
    bn.weight[rows], bn.bias[rows] = 1.0, 0.0
    bn.running_mean[rows], bn.running_var[rows] = 0.0, 1.0
