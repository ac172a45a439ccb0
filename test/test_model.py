"""FPCC-Net shapes, ranges, equivariance, and the fast layer forms against their naive definitions."""
import numpy as np
import pytest
import torch

from fpcc_ros.features import block_features, knn_graph
from fpcc_ros.training.model import (TINY, Dense, FPCCNet, NetConfig, edge_conv, edge_features,
                                     fold_batchnorm, gather_neighbors, global_split)

N, K = 64, 8


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """One torch thread: the machine is shared and spinning OpenMP threads stall under load."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _inputs(batch=2, n=N, k=K, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 0.2, size=(batch, n, 3))
    feats = np.stack([block_features(x, 0.05) for x in xyz])
    knn = np.stack([knn_graph(x, k) for x in xyz])
    return torch.from_numpy(feats), torch.from_numpy(knn)


def _trained_bn_model(config=TINY, seed=0):
    """A model whose batch norms hold non-trivial statistics, in eval mode."""
    torch.manual_seed(seed)
    model = FPCCNet(config)
    model.train()
    with torch.no_grad():
        for s in range(3):
            model(*_inputs(seed=10 + s))
    return model.eval()


def test_gather_neighbors_hand_case():
    x = torch.tensor([[[1.0], [2.0], [3.0]], [[10.0], [20.0], [30.0]]])  # (2, 3, 1)
    knn = torch.tensor([[[0, 2], [1, 0], [2, 1]], [[0, 1], [1, 2], [2, 0]]])
    got = gather_neighbors(x, knn)[..., 0]
    assert got.tolist() == [[[1, 3], [2, 1], [3, 2]], [[10, 20], [20, 30], [30, 10]]]


def test_edge_features_definition():
    x = torch.tensor([[[1.0, 0.0], [3.0, 1.0]]])
    knn = torch.tensor([[[0, 1], [1, 0]]])
    got = edge_features(x, knn)
    assert got[0, 0, 1].tolist() == [1.0, 0.0, 2.0, 1.0]   # [x_0, x_1 - x_0]
    assert got[0, 1, 1].tolist() == [3.0, 1.0, -2.0, -1.0]  # [x_1, x_0 - x_1]


@pytest.mark.parametrize("config", [TINY, NetConfig()])
def test_output_shapes_and_score_range(config):
    model = FPCCNet(config).eval()
    feats, knn = _inputs()
    emb, score = model(feats, knn)
    assert emb.shape == (2, N, 128) and emb.dtype == torch.float32
    assert score.shape == (2, N)
    assert (score > 0).all() and (score < 1).all()


def test_train_mode_backward_reaches_every_parameter():
    model = FPCCNet(TINY).train()
    emb, score = model(*_inputs())
    (emb.square().mean() + score.mean()).backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert missing == []


def test_permutation_equivariance():
    model = _trained_bn_model()
    feats, knn = _inputs(batch=1)
    perm = torch.from_numpy(np.random.default_rng(1).permutation(N))
    inv = torch.argsort(perm)
    # point i of the permuted block is point perm[i]; its neighbours are renamed through inv
    knn_p = inv[knn[:, perm]]
    emb, score = model(feats, knn)
    emb_p, score_p = model(feats[:, perm], knn_p)
    torch.testing.assert_close(emb_p, emb[:, perm], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(score_p, score[:, perm], atol=1e-6, rtol=1e-5)


def test_edge_conv_equals_linear_on_naive_edge_features():
    torch.manual_seed(0)
    layer = Dense(2 * 5, 7).eval()
    layer.bn.running_mean.uniform_(-1, 1)
    layer.bn.running_var.uniform_(0.5, 2)
    x = torch.randn(2, 20, 5)
    knn = torch.randint(0, 20, (2, 20, 4))
    naive = layer(edge_features(x, knn))
    torch.testing.assert_close(edge_conv(layer, x, knn), naive, atol=1e-5, rtol=1e-5)


def test_global_split_equals_concat_and_conv():
    torch.manual_seed(0)
    layer = Dense(6 + 9, 4).eval()
    layer.bn.running_mean.uniform_(-1, 1)
    local, glob = torch.randn(3, 11, 6), torch.randn(3, 1, 9)
    naive = layer(torch.cat([local, glob.expand(3, 11, 9)], dim=-1))  # tiled global feature
    torch.testing.assert_close(global_split(layer, local, glob), naive, atol=1e-5, rtol=1e-5)


def test_fold_batchnorm_keeps_outputs():
    model = _trained_bn_model()
    feats, knn = _inputs(seed=5)
    folded = fold_batchnorm(model)
    assert not any(isinstance(m, torch.nn.BatchNorm1d) for m in folded.modules())
    with torch.no_grad():
        (e1, s1), (e2, s2) = model(feats, knn), folded(feats, knn)
    torch.testing.assert_close(e2, e1, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(s2, s1, atol=1e-6, rtol=1e-4)


def test_block_size_independent_of_batch_in_eval():
    """Each block is processed on its own in eval mode (global max-pool per block)."""
    model = _trained_bn_model()
    feats, knn = _inputs(batch=2)
    with torch.no_grad():
        emb, _ = model(feats, knn)
        emb0, _ = model(feats[:1], knn[:1])
    torch.testing.assert_close(emb[:1], emb0, atol=1e-5, rtol=1e-5)
