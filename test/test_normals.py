"""Surface normals as network inputs (fpcc train --normals): the features, the widening of
6-input weights, the card, and the runtime path with a model that takes them."""
from dataclasses import replace

import numpy as np
import pytest
import torch

from fpcc_ros.cli import main as fpcc
from fpcc_ros.features import (FEATURE_NAMES, FEATURE_NAMES_WITH_NORMALS, block_features,
                               knn_graph, surface_normals)
from fpcc_ros.model_card import ModelCard, ModelCardError, card_path_for, load_card
from fpcc_ros.onnx_model import FpccModel
from fpcc_ros.pipeline import Pipeline, PipelineConfig
from fpcc_ros.training.export import export_checkpoint, export_untrained
from fpcc_ros.training.model import TINY, FPCCNet, with_normal_inputs
from fpcc_ros.training.train import TrainConfig, load_checkpoint, train
from test_dataset import write_fake_scenes
from test_export import SMALL, TRAIN_ARGS, _one_thread  # noqa: F401 (autouse: one torch thread)


def _plane(normal: np.ndarray, n: int = 400, seed: int = 0) -> np.ndarray:
    """Points on the plane through (0, 0, 1) with this normal, over a 0.1 m patch."""
    rng = np.random.default_rng(seed)
    normal = normal / np.linalg.norm(normal)
    u = np.cross(normal, [0.0, 1.0, 0.0] if abs(normal[1]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    a, b = rng.uniform(-0.05, 0.05, (2, n))
    return np.array([0.0, 0.0, 1.0]) + a[:, None] * u + b[:, None] * v


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.3, 0.0, -1.0), (1.0, 1.0, 1.0)])
def test_normals_are_the_planes_facing_the_camera(normal):
    xyz = _plane(np.array(normal))
    got = surface_normals(xyz, knn_graph(xyz, 16, near=8, reach=48))
    facing = np.array(normal) / np.linalg.norm(normal)
    facing = -facing if facing[2] > 0 else facing          # the camera looks along +z
    assert np.allclose(got, facing, atol=1e-6)


def test_normals_turn_at_a_crease():
    """Two faces meeting at a right angle: each point away from the edge gets its own face's
    normal, which xyz columns alone do not carry."""
    rng = np.random.default_rng(1)
    a = rng.uniform(0, 0.05, (300, 2))
    left = np.c_[-a[:, 0], a[:, 1], 1.0 + a[:, 0]]       # normal (1, 0, 1)/sqrt 2 -> (-1, 0, -1)
    right = np.c_[a[:, 0], a[:, 1], 1.0 + a[:, 0]]       # normal (-1, 0, 1)/sqrt 2 -> (1, 0, -1)
    xyz = np.r_[left, right]
    got = surface_normals(xyz, knn_graph(xyz, 16))
    away = np.r_[a[:, 0] > 0.01, a[:, 0] > 0.01]
    want = np.r_[np.tile([-1, 0, -1], (300, 1)), np.tile([1, 0, -1], (300, 1))] / np.sqrt(2)
    assert np.allclose(got[away], want[away], atol=1e-6)


def test_block_features_take_normals_only_when_asked():
    xyz = _plane(np.array([0.0, 0.0, 1.0]))
    knn = knn_graph(xyz, 16)
    plain, with_normals = block_features(xyz, 0.05), block_features(xyz, 0.05, knn)
    assert plain.shape == (len(xyz), 6) and with_normals.shape == (len(xyz), 9)
    assert np.array_equal(with_normals[:, :6], plain)
    assert np.allclose(with_normals[:, 6:], [0.0, 0.0, -1.0], atol=1e-6)


def test_widened_weights_compute_the_same_and_learn_the_new_columns():
    torch.manual_seed(0)
    net = FPCCNet(TINY).eval()
    xyz = _plane(np.array([0.2, 0.1, 1.0]), n=300)
    knn = knn_graph(xyz, 16)
    feats = torch.from_numpy(block_features(xyz, 0.05, knn))[None]
    knn_t = torch.from_numpy(knn)[None]
    wide = with_normal_inputs(net)
    assert wide.config.in_features == 9 and net.config.in_features == 6
    with torch.no_grad():
        for a, b in zip(net(feats[..., :6], knn_t), wide(feats, knn_t)):
            assert torch.allclose(a, b, atol=1e-6)
    w = wide.edge1a.linear.weight
    new_columns = [6, 7, 8, 15, 16, 17]
    assert torch.all(w[:, new_columns] == 0)
    wide.train()
    emb, score = wide(feats, knn_t)
    (emb.square().mean() + score.mean()).backward()
    assert w.grad[:, new_columns].abs().sum() > 0   # gradient reaches the new inputs


def test_card_names_either_feature_set_and_rejects_others(tmp_path):
    for names, normals in ((FEATURE_NAMES, False), (FEATURE_NAMES_WITH_NORMALS, True)):
        card = ModelCard(name="m", k=8, part_radius=0.05, feature_names=names)
        path = tmp_path / f"m{len(names)}.json"
        card.save(path)
        loaded = load_card(path)
        assert loaded.uses_normals is normals
        assert loaded.to_json()["inputs"]["features"]["shape"][-1] == len(names)
    ModelCard(name="m", k=8, part_radius=0.05, feature_names=FEATURE_NAMES[:5]).save(
        tmp_path / "bad.json")
    with pytest.raises(ModelCardError, match="feature_names"):
        load_card(tmp_path / "bad.json")


def test_the_pipeline_feeds_a_normals_model_nine_columns(tmp_path):
    path = tmp_path / "normals.onnx"
    card = export_untrained(path, k=16, part_radius=0.05, net=replace(TINY, in_features=9))
    assert card.uses_normals
    model = FpccModel(path)
    seen = []
    run = model.run

    def spy(features, knn, global_stride=1):
        seen.append(features.shape[-1])
        return run(features, knn, global_stride=global_stride)

    model.run = spy
    xyz = np.r_[_plane(np.array([0.0, 0.0, 1.0]), 800), _plane(np.array([0.3, 0.0, 1.0]), 800, 1)
                + [0.2, 0.0, 0.0]]
    result = Pipeline(model, PipelineConfig.from_card(model.card)).segment(xyz)
    assert seen and set(seen) == {9}
    assert result.labels.shape == (len(xyz),)


def test_train_normals_from_6_input_weights_widens_them_and_exports(tmp_path):
    write_fake_scenes(tmp_path / "scenes", count=2)
    base = tmp_path / "base"
    train(TrainConfig(epochs=1, batch=4, data=SMALL, net=TINY, threads=1),
          [tmp_path / "scenes"], base, progress=False)
    assert fpcc(["train", "--data", str(tmp_path / "scenes"), "--out", str(tmp_path / "wide"),
                 "--epochs", "1", "--init", str(base / "checkpoint_last.pt"), "--normals",
                 *TRAIN_ARGS]) == 0
    state = load_checkpoint(tmp_path / "wide" / "checkpoint_last.pt")
    assert state["net"]["in_features"] == 9 and state["config"]["data"]["normals"] is True
    assert state["model"]["edge1a.linear.weight"].shape[1] == 18
    card = export_checkpoint(tmp_path / "wide" / "checkpoint_last.pt", tmp_path / "wide.onnx",
                             force=True)
    assert card.feature_names == FEATURE_NAMES_WITH_NORMALS
    assert load_card(card_path_for(tmp_path / "wide.onnx")).uses_normals
    # fine-tuning the widened weights keeps their normals without being told again
    assert fpcc(["train", "--data", str(tmp_path / "scenes"), "--out", str(tmp_path / "again"),
                 "--epochs", "1", "--init", str(tmp_path / "wide.onnx"), *TRAIN_ARGS]) == 0
    assert load_checkpoint(tmp_path / "again" / "checkpoint_last.pt")["net"]["in_features"] == 9


def test_closed_form_least_eigenvectors_match_numpy():
    from fpcc_ros.features import _least_eigenvectors
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(2000, 8, 3)) * rng.uniform(0.01, 1.0, (2000, 1, 3))
    pts -= pts.mean(axis=1, keepdims=True)
    s = np.einsum("nmi,nmj->nij", pts, pts)
    want = np.linalg.eigh(s)[1][:, :, 0]
    got = _least_eigenvectors(s[:, 0, 0], s[:, 1, 1], s[:, 2, 2], s[:, 0, 1], s[:, 0, 2],
                              s[:, 1, 2])
    assert np.allclose(np.abs(np.einsum("ni,ni->n", got, want)), 1.0, atol=1e-6)
    # no unique least direction: all points on one line, or all in one place
    line = np.outer(np.linspace(-1, 1, 8), [1.0, 2.0, 0.5])
    for cloud in (line, np.zeros((8, 3))):
        sc = cloud.T @ cloud
        assert np.allclose(_least_eigenvectors(*(np.array([sc[i, j]]) for i, j in
                                                 ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)))),
                           [[0.0, 0.0, 1.0]])
