"""The optimizer must not kill channels, and training must see it when channels die (issue 23)."""
import torch

from fpcc_ros.training.health import channel_health, dead_layers, make_optimizer
from fpcc_ros.training.model import TINY, FPCCNet


def _steps_with_no_loss_gradient_on_norms(optimizer_for, steps: int = 300) -> torch.Tensor:
    """Train a linear -> batch norm where the loss ignores the norm's scale: what happens to a
    channel the loss does not defend. Returns the scale after ``steps``."""
    torch.manual_seed(0)
    layer = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.BatchNorm1d(8))
    optimizer = optimizer_for(layer)
    x = torch.randn(32, 4)
    for _ in range(steps):
        optimizer.zero_grad()
        loss = 0.0 * layer(x).sum()       # the loss gradient is zero everywhere
        loss.backward()
        optimizer.step()
    return layer[1].weight.detach()


def test_coupled_adam_decay_kills_an_undefended_scale() -> None:
    # the set-up the shipped model trained with: 300 steps at lr 1e-3 take ~0.3 off each scale
    gamma = _steps_with_no_loss_gradient_on_norms(
        lambda m: torch.optim.Adam(m.parameters(), lr=1e-3, weight_decay=1e-4))
    assert gamma.max() < 0.8


def test_make_optimizer_leaves_norm_scales_alone() -> None:
    gamma = _steps_with_no_loss_gradient_on_norms(lambda m: make_optimizer(m, 1e-3, 1e-4))
    assert torch.equal(gamma, torch.ones(8))


def test_make_optimizer_decays_only_weight_matrices() -> None:
    net = FPCCNet(TINY)
    optimizer = make_optimizer(net, 1e-3, 1e-4)
    decayed = {id(p) for g in optimizer.param_groups if g["weight_decay"] > 0 for p in g["params"]}
    assert id(net.glob.linear.weight) in decayed and id(net.emb_out.weight) in decayed
    assert id(net.glob.bn.weight) not in decayed and id(net.glob.bn.bias) not in decayed
    assert id(net.emb_out.bias) not in decayed
    assert len(decayed) == 12          # 10 Dense layers + 2 output linears
    assert sum(len(g["params"]) for g in optimizer.param_groups) == len(list(net.parameters()))


def test_channel_health_counts_collapsed_channels() -> None:
    net = FPCCNet(TINY)
    with torch.no_grad():
        net.glob.bn.weight[:10] = 1e-38          # scale decayed to nothing
        net.point1.bn.running_var[:3] = 6e-45    # constant input
    health = channel_health(net)
    assert health["glob"] == (TINY.global_dim - 10, TINY.global_dim)
    assert health["point1"] == (TINY.point_dims[0] - 3, TINY.point_dims[0])
    assert health["edge1a"] == (TINY.edge_dim, TINY.edge_dim)
    assert set(dead_layers(health, 0.1)) == {"glob"}       # 10 of 64 dead; point1 3 of 64
    assert set(dead_layers(health, 0.01)) == {"glob", "point1"}
