"""Is the network alive? Dead channels per layer, and the optimizer that does not kill them.

The shipped model of sessions 1-16 trained with ``Adam(weight_decay=1e-4)``: coupled L2, whose
decay term goes through Adam's per-weight normalisation, so every weight with a small loss
gradient -- batch-norm scales and biases included -- moved towards zero by about ``lr`` per step
whatever its size. 80-87 % of the wide layers' channels ended with a scale near 1e-38 and a
constant input (issue 23). A dead channel never comes back by training alone (no gradient
reaches it; :mod:`fpcc_ros.training.revive` re-initialises it), so this module gives training
two things: :func:`make_optimizer` (AdamW, decoupled decay on the linear
weight matrices only, never on norm parameters or biases) and :func:`channel_health` (live
channels per layer), which ``fpcc train`` records every epoch and ``fpcc export`` checks.
"""
from __future__ import annotations

import torch
from torch import nn

from fpcc_ros.training.model import Dense, FPCCNet

# A channel is dead when its norm scale has decayed to nothing or its input no longer varies
# (running variance at float32's floor): either way it outputs a constant.
DEAD_SCALE = 1e-3
DEAD_VARIANCE = 1e-12
WARN_DEAD_SHARE = 0.10     # fpcc train warns above this per layer
EXPORT_DEAD_SHARE = 0.25   # fpcc export refuses above this per layer unless forced


def make_optimizer(model: nn.Module, lr: float, weight_decay: float) -> torch.optim.Optimizer:
    """AdamW with decoupled decay on weight matrices only; norm scales/shifts and biases get none.

    Decoupled decay shrinks a weight by ``lr * weight_decay`` of itself per step (1e-7 at the
    defaults), independently of Adam's normalisation, so a weight is never pushed to zero at a
    rate set by the learning rate alone.
    """
    decay, no_decay = [], []
    for module in model.modules():
        for name, param in module.named_parameters(recurse=False):
            if not param.requires_grad:
                continue
            is_matrix = name == "weight" and param.ndim >= 2 and not isinstance(
                module, nn.modules.batchnorm._NormBase)
            (decay if is_matrix else no_decay).append(param)
    groups = [{"params": decay, "weight_decay": weight_decay},
              {"params": no_decay, "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=lr)


def dense_layers(model: FPCCNet) -> dict[str, Dense]:
    """The network's linear -> norm -> activation layers by attribute name (edge1a ... score_hidden)."""
    return {name: module for name, module in model.named_children() if isinstance(module, Dense)}


def dead_channels(bn: nn.BatchNorm1d) -> torch.Tensor:
    """Boolean mask of the norm's channels that output a constant."""
    dead = bn.weight.abs() < DEAD_SCALE
    if bn.running_var is not None:
        dead |= bn.running_var < DEAD_VARIANCE
    return dead


@torch.no_grad()
def channel_health(model: FPCCNet) -> dict[str, tuple[int, int]]:
    """Layer name -> (live channels, channels), judged by each layer's batch norm."""
    out = {}
    for name, layer in dense_layers(model).items():
        bn = layer.bn
        if not isinstance(bn, nn.BatchNorm1d):   # folded for export: judge the folded weights
            row = layer.linear.weight.abs().amax(dim=1)
            dead = row < 1e-20
        else:
            dead = dead_channels(bn)
        out[name] = (int((~dead).sum()), int(dead.numel()))
    return out


def dead_layers(health: dict[str, tuple[int, int]], share: float) -> dict[str, float]:
    """Layers whose dead share exceeds ``share``, with that share."""
    return {name: 1 - live / total for name, (live, total) in health.items()
            if total and 1 - live / total > share}


def health_line(health: dict[str, tuple[int, int]]) -> str:
    """``edge1a 64/64, ..., glob 1021/1024`` (live of all channels per layer)."""
    return ", ".join(f"{name} {live}/{total}" for name, (live, total) in health.items())


def gradient_norm(model: nn.Module) -> float:
    """The L2 norm of all parameter gradients (after backward)."""
    norms = [p.grad.detach().norm() for p in model.parameters() if p.grad is not None]
    return float(torch.linalg.vector_norm(torch.stack(norms))) if norms else 0.0
