"""TINY FPCC-Nets and input blocks for the tests of the torch-side tools (slice, revive)."""
from __future__ import annotations

import torch

from fpcc_ros.training.model import TINY, FPCCNet


def trained_like_net(seed: int = 0, net: FPCCNet | None = None) -> FPCCNet:
    """A net (TINY unless given) whose batch norms carry non-trivial statistics, as after training."""
    torch.manual_seed(seed)
    net = FPCCNet(TINY) if net is None else net
    with torch.no_grad():
        for module in net.modules():
            if isinstance(module, torch.nn.BatchNorm1d):
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.2, 0.2)
                module.running_mean.uniform_(-0.1, 0.1)
                module.running_var.uniform_(0.5, 2.0)
    return net


def random_block(points: int = 64, k: int = 8, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Random features and a kNN index with each point its own first neighbour (seeded)."""
    torch.manual_seed(1)
    features = torch.rand(batch, points, 6)
    knn = torch.randint(0, points, (batch, points, k))
    knn[..., 0] = torch.arange(points)
    return features, knn
