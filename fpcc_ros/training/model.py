"""FPCC-Net in torch: DGCNN's feature extractor with an embedding head and a center-score head.

Deliberate differences from the paper's DGCNN backbone (same outputs, cheaper, documented):

* One kNN graph on xyz (``fpcc_ros.features.knn_graph``) is an input and all three EdgeConv
  layers reuse it. DGCNN recomputes kNN in feature space for layers 2-3; a dense N x N feature
  distance per layer dominated CPU inference time, and the graph built once with a KD-tree is the
  same thing the runtime passes to the ONNX model.
* The first linear layer of an EdgeConv acts on [x_i, x_j - x_i]; we never build that (N, K, 2C)
  tensor: W [x_i; x_j - x_i] = (W_a - W_b) x_i + W_b x_j, so we project each point once and
  gather the projections. Mathematically identical (tested against the naive form).
* The 1216 -> 512 layer after the global max-pool is W_local @ local + W_global @ global; the
  global part is one (B, 1, 512) row per block, broadcast over the points instead of tiling the
  1024-d global feature N times. Identical to concat + conv on the same weights (tested).
* The embedding head ends in a plain linear layer. The reference ends it with ReLU, which makes
  embeddings non-negative and wastes most of the 128-d space for the hinge loss.

Layers are ``Linear`` over the last axis of (B, N, C) / (B, N, K, C) tensors, each followed by
batch norm and LeakyReLU(0.2) as in DGCNN; ``fold_batchnorm`` merges the norms into the linears
for export.
"""
from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils.fusion import fuse_linear_bn_eval

from fpcc_ros.features import NORMAL_NAMES, NUM_FEATURES, takes_normals
from fpcc_ros.model_card import EMBEDDING_DIM


@dataclass(frozen=True)
class NetConfig:
    """Layer widths. The defaults are the paper's; smaller ones make tiny test models."""

    edge_dim: int = 64
    global_dim: int = 1024
    point_dims: tuple[int, int] = (512, 256)
    head_dim: int = 128
    embedding_dim: int = EMBEDDING_DIM
    in_features: int = NUM_FEATURES   # 9 with surface normals (fpcc train --normals)

    @property
    def normals(self) -> bool:
        """Whether the network takes surface normals (features.surface_normals) as inputs."""
        return takes_normals(self.in_features)

    def to_dict(self) -> dict:
        body = asdict(self)
        body["point_dims"] = list(self.point_dims)
        return body

    @classmethod
    def from_dict(cls, body: dict) -> "NetConfig":
        body = dict(body)
        if "point_dims" in body:
            body["point_dims"] = tuple(body["point_dims"])
        return cls(**body)


TINY = NetConfig(edge_dim=16, global_dim=64, point_dims=(64, 32), head_dim=32)


def gather_neighbors(x: torch.Tensor, knn: torch.Tensor) -> torch.Tensor:
    """(B, N, C) values and (B, N, K) indices into the same block -> (B, N, K, C) neighbour values."""
    b, n, c = x.shape
    offset = torch.arange(b, device=x.device).view(b, 1, 1) * n
    flat = (knn + offset).reshape(-1)
    return x.reshape(b * n, c)[flat].reshape(b, n, knn.shape[-1], c)


def edge_features(x: torch.Tensor, knn: torch.Tensor) -> torch.Tensor:
    """DGCNN's edge feature [x_i, x_j - x_i], (B, N, K, 2C). The network avoids building it (see
    ``edge_conv``); kept as the readable definition the fast form is tested against."""
    neighbors = gather_neighbors(x, knn)
    center = x.unsqueeze(2).expand_as(neighbors)
    return torch.cat([center, neighbors - center], dim=-1)


class LastDimBatchNorm(nn.BatchNorm1d):
    """Batch norm over the channel (last) axis of a (..., C) tensor."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return super().forward(x.reshape(-1, x.shape[-1])).reshape(x.shape)


class Dense(nn.Module):
    """Linear -> batch norm -> activation over the last axis (DGCNN's conv-bn-act)."""

    def __init__(self, cin: int, cout: int, act: str = "leaky"):
        super().__init__()
        self.linear = nn.Linear(cin, cout, bias=False)
        self.bn: nn.Module = LastDimBatchNorm(cout)
        self.act = nn.LeakyReLU(0.2) if act == "leaky" else nn.ReLU()

    def finish(self, pre: torch.Tensor) -> torch.Tensor:
        """Norm and activation of an already computed ``linear`` output."""
        return self.act(self.bn(pre))

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return self.finish(self.linear(x))


def edge_conv(layer: Dense, x: torch.Tensor, knn: torch.Tensor) -> torch.Tensor:
    """``layer`` applied to ``edge_features(x, knn)`` without materialising them:
    W [x_i; x_j - x_i] = (W_a - W_b) x_i + W_b x_j, so project each point once, then gather."""
    c = x.shape[-1]
    w = layer.linear.weight
    center = F.linear(x, w[:, :c] - w[:, c:], layer.linear.bias)
    neighbors = gather_neighbors(F.linear(x, w[:, c:]), knn)
    return layer.finish(center.unsqueeze(2) + neighbors)


def global_split(layer: Dense, local: torch.Tensor, glob: torch.Tensor) -> torch.Tensor:
    """``layer`` applied to concat(local (B,N,L), tiled glob (B,1,G)) without tiling:
    W [l; g] = W_l l + W_g g, with W_g g computed once per block and broadcast."""
    c = local.shape[-1]
    w = layer.linear.weight
    return layer.finish(F.linear(local, w[:, :c], layer.linear.bias) + F.linear(glob, w[:, c:]))


class FPCCNet(nn.Module):
    """forward(features (B,N,6 or 9), knn (B,N,K)) -> (embedding (B,N,128), center_score (B,N))."""

    def __init__(self, config: NetConfig = NetConfig()):
        super().__init__()
        self.config = config
        e, (p1, p2), h = config.edge_dim, config.point_dims, config.head_dim
        self.edge1a, self.edge1b = Dense(2 * config.in_features, e), Dense(e, e)
        self.edge2a, self.edge2b = Dense(2 * e, e), Dense(e, e)
        self.edge3 = Dense(2 * e, e)
        self.glob = Dense(3 * e, config.global_dim)
        self.point1, self.point2 = Dense(3 * e + config.global_dim, p1), Dense(p1, p2)
        self.emb_hidden = Dense(p2, h, act="relu")
        self.emb_out = nn.Linear(h, config.embedding_dim)
        self.score_hidden = Dense(p2, h, act="relu")
        self.score_out = nn.Linear(h, 1)

    def forward(self, features: torch.Tensor, knn: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x1 = self._max(self.edge1b(edge_conv(self.edge1a, features, knn)), dim=2)
        x2 = self._max(self.edge2b(edge_conv(self.edge2a, x1, knn)), dim=2)
        x3 = self._max(edge_conv(self.edge3, x2, knn), dim=2)
        local = torch.cat([x1, x2, x3], dim=-1)                      # (B, N, 3e)
        glob = self.glob(local).amax(dim=1, keepdim=True)            # (B, 1, global_dim)
        point = self.point2(global_split(self.point1, local, glob))  # (B, N, 256)
        embedding = self.emb_out(self.emb_hidden(point))
        center_score = torch.sigmoid(self.score_out(self.score_hidden(point))).squeeze(-1)
        return embedding, center_score

    def _max(self, x: torch.Tensor, dim: int) -> torch.Tensor:
        """Max over neighbours. Same values either way: max() has the cheaper backward (indices,
        not equality masks), amax() exports to a single ReduceMax."""
        return x.max(dim=dim).values if self.training else x.amax(dim=dim)


@torch.no_grad()
def with_normal_inputs(model: FPCCNet) -> FPCCNet:
    """A copy of a 6-input ``model`` that takes the surface normals too and computes exactly
    what ``model`` does: the first EdgeConv's weights on the new columns (the normal n_i and
    n_j - n_i) start at zero, and training then learns to read them. So a healthy trained net
    can be fine-tuned with normals instead of trained again from scratch."""
    if model.config.normals:
        return model
    c, extra = model.config.in_features, len(NORMAL_NAMES)
    widened = FPCCNet(replace(model.config, in_features=c + extra))
    state = model.state_dict()
    w = state["edge1a.linear.weight"]                      # (e, 2c): [x_i, x_j - x_i]
    zeros = w.new_zeros(w.shape[0], extra)
    state["edge1a.linear.weight"] = torch.cat([w[:, :c], zeros, w[:, c:], zeros], dim=1)
    widened.load_state_dict(state)
    return widened.train(model.training)


def fold_batchnorm(model: FPCCNet) -> FPCCNet:
    """An eval-mode copy with every batch norm merged into the linear before it (for export).

    Valid for the split layers too: the norm acts on the summed pre-activation, and both parts
    of the split weight are slices of the one folded weight.
    """
    folded = copy.deepcopy(model).eval()
    for module in folded.modules():
        if isinstance(module, Dense) and isinstance(module.bn, nn.BatchNorm1d):
            module.linear = fuse_linear_bn_eval(module.linear, module.bn)
            module.bn = nn.Identity()
    return folded


def count_parameters(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())
