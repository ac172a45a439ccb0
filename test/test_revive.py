"""Dead channels come back to life without changing the network's outputs (issue 23)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from fpcc_ros.training.health import channel_health  # noqa: E402
from fpcc_ros.training.model import TINY, FPCCNet, NetConfig  # noqa: E402
from fpcc_ros.training.revive import channel_readers, revive_dead_channels  # noqa: E402
from fpcc_ros.training.train import load_checkpoint, model_from_checkpoint  # noqa: E402
from net_factory import random_block, trained_like_net  # noqa: E402

KILLED = {"edge1b": 3, "edge2b": 2, "edge3": 4, "glob": 20, "point1": 30, "point2": 10,
          "emb_hidden": 12, "score_hidden": 5}
# what the shipped default had lost before its revival (issue 23; model_health.py on it)
DEFAULT_KILLED = {"edge1b": 1, "edge2a": 1, "edge3": 4, "glob": 892, "point1": 410, "point2": 156,
                  "emb_hidden": 87, "score_hidden": 66}


def _collapsed_net(net: FPCCNet | None = None, killed: dict[str, int] = KILLED) -> FPCCNet:
    """A trained-looking net (TINY unless given) with channels killed as the shipped one's were:
    input weights zero, scale ~1e-38, running variance at the floor, a nonzero shift (so the
    constant they output matters to the layers reading them)."""
    net = trained_like_net(net=net)
    with torch.no_grad():
        for name, count in killed.items():
            layer = getattr(net, name)
            layer.linear.weight[:count] = 0.0
            layer.bn.weight[:count] = 1e-38
            layer.bn.running_var[:count] = 6e-45
            layer.bn.bias[:count] = 0.3
    return net.eval()


def test_readers_cover_every_dense_layer_but_the_inputs() -> None:
    readers = channel_readers(FPCCNet(TINY))
    assert set(readers) == {"edge1a", "edge1b", "edge2a", "edge2b", "edge3", "glob", "point1",
                            "point2", "emb_hidden", "score_hidden"}
    # point1 reads [x1, x2, x3, glob]: the offsets must tile its input exactly
    e = TINY.edge_dim
    offsets = sorted(off for layer in readers.values() for r, off, _ in layer if r == "point1")
    assert offsets == [0, e, 2 * e, 3 * e]


def test_revived_net_computes_the_same_and_is_alive() -> None:
    net = _collapsed_net()
    features, knn = random_block(96, batch=2)
    emb_before, score_before = net(features, knn)
    assert {name: live for name, (live, _) in channel_health(net).items()}["glob"] == \
        TINY.global_dim - KILLED["glob"]
    revived = revive_dead_channels(net, torch.Generator().manual_seed(3))
    assert revived == KILLED
    emb_after, score_after = net(features, knn)
    torch.testing.assert_close(emb_after, emb_before, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(score_after, score_before, atol=1e-6, rtol=1e-5)
    assert all(live == total for live, total in channel_health(net).values())
    assert revive_dead_channels(net) == {}            # nothing left to revive


def test_revived_channels_get_gradient() -> None:
    net = _collapsed_net()
    revive_dead_channels(net, torch.Generator().manual_seed(3))
    net.train()
    features, knn = random_block(96, batch=2)
    emb, score = net(features, knn)
    (emb.square().mean() + score.mean()).backward()
    glob_reads = net.point1.linear.weight.grad[:, 3 * TINY.edge_dim:][:, :KILLED["glob"]]
    assert glob_reads.abs().amax() > 0                # the cleared read weights learn at once
    assert net.glob.linear.weight.grad[:KILLED["glob"]].abs().amax() == 0   # inputs: after them
    assert net.emb_out.weight.grad[:, :KILLED["emb_hidden"]].abs().amax() > 0


def test_dead_channels_without_revival_get_no_gradient() -> None:
    net = _collapsed_net().train()
    features, knn = random_block(96, batch=2)
    emb, score = net(features, knn)
    (emb.square().mean() + score.mean()).backward()
    assert net.glob.linear.weight.grad[:KILLED["glob"]].abs().amax() < 1e-20
    assert net.glob.bn.weight.grad[:KILLED["glob"]].abs().amax() < 1e-20


def test_full_width_net_killed_as_the_shipped_one_was_revives_to_the_same_outputs() -> None:
    """The shipped net's collapse at full width (DEFAULT_KILLED): 1,617 channels, most of glob."""
    net = _collapsed_net(FPCCNet(NetConfig()), DEFAULT_KILLED)
    assert {name: total - live for name, (live, total) in channel_health(net).items()
            if live < total} == DEFAULT_KILLED
    torch.manual_seed(2)
    features = torch.rand(1, 512, 6) - 0.5
    knn = torch.randint(0, 512, (1, 512, 16))
    knn[..., 0] = torch.arange(512)
    emb_before, score_before = net(features, knn)
    assert revive_dead_channels(net, torch.Generator().manual_seed(0)) == DEFAULT_KILLED
    emb_after, score_after = net(features, knn)
    torch.testing.assert_close(emb_after, emb_before, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(score_after, score_before, atol=1e-5, rtol=1e-4)
    assert all(live == total for live, total in channel_health(net).values())


def test_the_command_writes_a_live_checkpoint_fpcc_train_can_start_from(tmp_path) -> None:
    script = Path(__file__).resolve().parent.parent / "scripts" / "revive_net.py"
    src, dst = tmp_path / "collapsed.pt", tmp_path / "revived.pt"
    torch.save({"model": _collapsed_net().state_dict(), "net": TINY.to_dict(),
                "optimizer": {"state": {}}}, src)
    result = subprocess.run([sys.executable, str(script), str(src), str(dst)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert f"{sum(KILLED.values())} channels revived" in result.stdout
    state = load_checkpoint(dst)
    assert "optimizer" not in state and state["revived"] == KILLED
    net = model_from_checkpoint(state)
    assert all(live == total for live, total in channel_health(net).values())
