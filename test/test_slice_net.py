"""scripts/slice_net.py: a trained net cut to narrower layers, as a warm start for a faster one."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from fpcc_ros.training.model import TINY  # noqa: E402
from fpcc_ros.training.train import load_checkpoint, model_from_checkpoint  # noqa: E402
from net_factory import random_block, trained_like_net  # noqa: E402

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "slice_net.py"
_spec = importlib.util.spec_from_file_location("slice_net", SCRIPT)
slice_net = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(slice_net)


def _trained_like_state(seed: int = 0) -> dict:
    return {"model": trained_like_net(seed).state_dict(), "net": TINY.to_dict()}


_block = random_block


def test_cutting_to_the_same_widths_gives_the_same_network():
    state = _trained_like_state()
    same = slice_net.slice_state(state, TINY.edge_dim, TINY.global_dim)
    features, knn = _block()
    with torch.no_grad():
        before = model_from_checkpoint(state).eval()(features, knn)
        after = model_from_checkpoint(same).eval()(features, knn)
    for a, b in zip(before, after):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_a_cut_net_has_the_new_widths_and_keeps_the_strongest_channels():
    state = _trained_like_state()
    with torch.no_grad():   # silence three of edge1a's channels and five of the global ones
        state["model"]["edge1a.bn.weight"][[0, 5, 9]] = 0.0
        state["model"]["glob.bn.weight"][:5] = 0.0
    cut = slice_net.slice_state(state, 12, 48)
    net = model_from_checkpoint(cut).eval()
    assert (net.config.edge_dim, net.config.global_dim) == (12, 48)
    assert cut["sliced_from"]["net"]["edge_dim"] == TINY.edge_dim
    # the kept edge1a rows are the original rows of every channel but the silenced ones
    full = state["model"]["edge1a.linear.weight"]
    kept = cut["model"]["edge1a.linear.weight"]
    source = [next(i for i in range(TINY.edge_dim) if torch.equal(kept[j], full[i]))
              for j in range(12)]
    assert source == sorted(source) and not {0, 5, 9} & set(source), source
    kept_glob = cut["model"]["glob.bn.weight"]
    assert (kept_glob != 0).all()
    features, knn = _block()
    with torch.no_grad():
        embedding, score = net(features, knn)
    assert embedding.shape == (1, 64, TINY.embedding_dim) and score.shape == (1, 64)
    assert torch.isfinite(embedding).all()


def test_the_command_writes_a_checkpoint_fpcc_train_can_start_from(tmp_path):
    src, dst = tmp_path / "full.pt", tmp_path / "narrow.pt"
    torch.save(_trained_like_state(), src)
    result = subprocess.run([sys.executable, str(SCRIPT), str(src), str(dst), "--edge", "8",
                             "--global", "32"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "train it" in result.stdout
    state = load_checkpoint(dst)
    assert state["net"]["edge_dim"] == 8 and state["net"]["global_dim"] == 32
    too_wide = subprocess.run([sys.executable, str(SCRIPT), str(src), str(dst), "--edge",
                               str(TINY.edge_dim + 1)], capture_output=True, text=True, timeout=120)
    assert too_wide.returncode == 2 and "--edge" in too_wide.stderr
