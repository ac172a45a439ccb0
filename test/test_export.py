"""End to end on tiny synthetic scenes: overfit, train, resume, time limit, export, onnxruntime."""
import csv
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

import fpcc_ros.training.train as train_mod
from fpcc_ros.cli import main as fpcc
from fpcc_ros.model_card import card_path_for, load_card
from fpcc_ros.training.dataset import DataConfig, collate, load_scene, scene_blocks
from fpcc_ros.training.export import check_onnx, export_checkpoint, export_onnx, export_untrained
from fpcc_ros.training.loss import batch_loss
from fpcc_ros.training.model import TINY, FPCCNet
from fpcc_ros.training.train import TrainConfig, load_checkpoint, model_from_checkpoint, resolve_init, train
from test_dataset import A, write_fake_scenes

# floor kept: these tests exercise step counting, and the fake floor would vanish into few blocks
SMALL = DataConfig(k=8, block_size=256, voxel_factor=0.15, remove_floor=False)
TINY_CONFIG = TrainConfig(epochs=1, batch=4, data=SMALL, net=TINY, threads=1)
TRAIN_ARGS = ["--net", "tiny", "--k", "8", "--block-size", "256", "--voxel-factor", "0.15",
              "--threads", "1"]
COMMITTED = Path(__file__).parent / "data" / "tiny_fpcc.onnx"


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """One torch thread: the machine is shared and spinning OpenMP threads stall under load."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    write_fake_scenes(root / "train", count=3)
    write_fake_scenes(root / "val", count=1, organised_first=False)
    return root


def _ort(path):
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def _history(run):
    with open(run / "history.csv") as fh:
        return list(csv.DictReader(fh))


def test_overfit_one_block(scenes):
    torch.manual_seed(0)
    scene = load_scene(next((scenes / "train").glob("*.npz")))
    batch = collate(scene_blocks(scene, SMALL).blocks[:2])
    model = FPCCNet(TINY).train()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        loss = batch_loss(*model(batch["features"], batch["knn"]), batch)[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5])


def test_cli_train_resume_export(scenes, tmp_path):
    run = tmp_path / "run"
    assert fpcc(["train", "--data", str(scenes / "train"), "--val", str(scenes / "val"),
                 "--out", str(run), "--epochs", "2", *TRAIN_ARGS]) == 0
    for name in ("checkpoint_last.pt", "checkpoint_best.pt", "history.csv", "history.png"):
        assert (run / name).is_file(), name
    rows = _history(run)
    assert [r["epoch"] for r in rows] == ["1", "2"]
    for r in rows:
        # the default center-loss weight reaches the loss the trainer reports
        assert float(r["loss"]) == pytest.approx(
            float(r["loss_ef"]) + TrainConfig().alpha * float(r["loss_cs"]), rel=1e-6)
        assert r["val_loss"] and r["val_precision"] and r["val_recall"] and r["val_center_mae"]
        # health columns: a fresh tiny net has every channel alive; gradients flowed
        assert int(r["live_glob"]) == TINY.global_dim and int(r["live_edge1a"]) == TINY.edge_dim
        assert float(r["grad_norm"]) > 0
    state = torch.load(run / "checkpoint_last.pt", weights_only=True)   # plain types only
    assert state["epoch"] == 2 and state["step"] == 0

    assert fpcc(["train", "--out", str(run), "--epochs", "3", "--resume", "--threads", "1"]) == 0
    resumed = _history(run)
    assert len(resumed) == 3 and resumed[:2] == rows

    onnx_path = tmp_path / "models" / "fake.onnx"
    assert fpcc(["export", str(run / "checkpoint_last.pt"), "--out", str(onnx_path)]) == 0
    card = load_card(card_path_for(onnx_path))
    assert (card.name, card.k, card.block_size, card.voxel_factor) == ("fake", 8, 256, 0.15)
    assert card.part_radius == A          # float32 in the NPZ, written as its 7 digits
    assert card.trained_on["num_scenes"] == 3 and card.trained_on["part_names"] == ["ellipsoid"]
    assert card.training["epochs"] == 3 and card.training["command"].startswith("fpcc train --out")
    assert "val_loss" in card.metrics and "val_precision" in card.metrics

    # onnxruntime agrees with torch on a real block of the validation scene, at another N and B
    model = model_from_checkpoint(load_checkpoint(run / "checkpoint_last.pt")).eval()
    block = scene_blocks(load_scene(next((scenes / "val").glob("*.npz"))), SMALL).blocks[0]
    for b, n in ((1, len(block.xyz)), (3, 50)):
        feats = np.repeat(block.features[None, :n], b, 0)
        knn = np.repeat(np.minimum(block.knn[None, :n], n - 1), b, 0)
        emb, score = _ort(onnx_path).run(["embedding", "center_score"], {"features": feats, "knn": knn})
        with torch.no_grad():
            t_emb, t_score = model(torch.from_numpy(feats), torch.from_numpy(knn))
        assert emb.shape == (b, n, 128) and score.shape == (b, n)
        assert np.abs(emb - t_emb.numpy()).max() < 1e-4 and np.abs(score - t_score.numpy()).max() < 1e-4

    # the torch weights beside the ONNX are what --init uses
    pt = resolve_init(onnx_path)
    assert pt == onnx_path.with_suffix(".pt")
    for key, value in load_checkpoint(pt)["model"].items():
        torch.testing.assert_close(value, model.state_dict()[key])
    summary = train(TrainConfig(epochs=1, batch=4, data=SMALL, threads=1), [scenes / "val"],
                    tmp_path / "run2", init=onnx_path, progress=False)
    assert summary["status"] == "done"
    assert load_checkpoint(tmp_path / "run2" / "checkpoint_last.pt")["net"] == TINY.to_dict()


def test_cli_alpha_weights_the_center_loss(scenes, tmp_path):
    run = tmp_path / "run"
    assert fpcc(["train", "--data", str(scenes / "train"), "--out", str(run), "--epochs", "1",
                 "--alpha", "3", *TRAIN_ARGS]) == 0
    row = _history(run)[0]
    assert float(row["loss"]) == pytest.approx(float(row["loss_ef"]) + 3 * float(row["loss_cs"]),
                                               rel=1e-6)
    assert load_checkpoint(run / "checkpoint_last.pt")["config"]["alpha"] == 3.0


def test_time_limit_stops_mid_epoch_and_resume_is_exact(scenes, tmp_path, monkeypatch):
    train(TINY_CONFIG, [scenes / "train"], tmp_path / "whole", progress=False)

    ticks = iter(range(0, 10**6, 10))          # a clock that advances 10 s per reading
    monkeypatch.setattr(train_mod, "_now", lambda: next(ticks))
    limited = TrainConfig(**{**TINY_CONFIG.__dict__, "time_limit_min": 0.5})
    summary = train(limited, [scenes / "train"], tmp_path / "cut", progress=False)
    assert summary["status"] == "time_limit"
    state = load_checkpoint(tmp_path / "cut" / "checkpoint_last.pt")
    assert state["epoch"] == 0 and 0 < state["step"] < 6
    monkeypatch.undo()
    # the card says the weights are past the last validated epoch (here: none)
    card = export_checkpoint(tmp_path / "cut" / "checkpoint_last.pt", tmp_path / "cut.onnx",
                             part_radius=0.05, save_torch=False, check=False)
    assert card.training["epochs"] == 0
    assert card.training["steps_after_last_epoch"] == state["step"]

    assert train(TINY_CONFIG, None, tmp_path / "cut", resume=True, progress=False)["status"] == "done"
    whole = load_checkpoint(tmp_path / "whole" / "checkpoint_last.pt")["model"]
    cut = load_checkpoint(tmp_path / "cut" / "checkpoint_last.pt")["model"]
    for key in whole:
        torch.testing.assert_close(cut[key], whole[key], atol=1e-6, rtol=1e-5)


def test_full_size_network_exports_and_agrees(tmp_path):
    torch.manual_seed(0)
    model = FPCCNet().eval()
    path = export_onnx(model, tmp_path / "full.onnx", k=16)
    assert check_onnx(model, path, k=16, batch=2, points=300) < 1e-4
    assert path.stat().st_size < 5_000_000


def _run_random(path, k, n=200, seed=0):
    rng = np.random.default_rng(seed)
    feats = rng.uniform(0, 1, size=(2, n, 6)).astype(np.float32)
    knn = np.concatenate([np.broadcast_to(np.arange(n)[None, :, None], (2, n, 1)),
                          rng.integers(0, n, size=(2, n, k - 1))], axis=2).astype(np.int64)
    return _ort(path).run(["embedding", "center_score"], {"features": feats, "knn": knn})


def test_export_untrained_small_and_valid(tmp_path):
    path = tmp_path / "tiny.onnx"
    card = export_untrained(path, k=16, seed=0, part_radius=0.05)
    assert path.stat().st_size < 300_000
    loaded = load_card(card_path_for(path))
    assert loaded == card and loaded.k == 16 and loaded.part_radius == 0.05
    emb, score = _run_random(path, 16)
    assert emb.shape == (2, 200, 128) and np.isfinite(emb).all()
    assert (score >= 0).all() and (score <= 1).all() and score.std() > 0.01


def test_committed_tiny_model_is_reproducible(tmp_path):
    """test/data/tiny_fpcc.onnx is export_untrained(k=16, seed=0, part_radius=0.05)."""
    card = load_card(card_path_for(COMMITTED))
    assert COMMITTED.stat().st_size < 300_000 and card.k == 16
    fresh = tmp_path / "tiny.onnx"
    export_untrained(fresh, k=16, seed=0, part_radius=0.05)
    for a, b in zip(_run_random(COMMITTED, 16), _run_random(fresh, 16)):
        np.testing.assert_allclose(a, b, atol=1e-4, rtol=1e-3)  # float noise of thread counts


def test_validate_scores_the_postprocess_labels(scenes):
    scene = load_scene(next((scenes / "val").glob("*.npz")))
    model = FPCCNet(TINY)
    perfect = train_mod.validate(model, [scene], TINY_CONFIG, postprocess=lambda sc, pred, cfg: sc.instance)
    assert perfect["val_precision"] == 1.0 and perfect["val_recall"] == 1.0
    assert perfect["val_loss"] > 0 and 0 <= perfect["val_center_mae"] <= 1
    assert 0 < perfect["val_nearest_own"] <= 1
    seen = []

    def nothing(sc, pred, cfg):
        seen.append(pred)
        return np.zeros(len(sc.xyz), np.int32)

    empty = train_mod.validate(model, [scene], TINY_CONFIG, postprocess=nothing)
    assert empty["val_precision"] == 0.0 and empty["val_recall"] == 0.0
    pred = seen[0]                 # per downsampled point, mapped back to every scene point
    assert pred.embedding.shape == (len(pred.rep), 128) and pred.inverse.shape == (len(scene.xyz),)
    np.testing.assert_array_equal(pred.xyz, scene.xyz[pred.rep])
    assert "val_precision" not in train_mod.validate(model, [scene], TINY_CONFIG, postprocess=None)


def test_cosine_learning_rate():
    cfg = TrainConfig(epochs=10, lr=1e-3, min_lr_fraction=0.01)
    assert train_mod.lr_at(cfg, 0) == pytest.approx(1e-3)
    assert train_mod.lr_at(cfg, 5) == pytest.approx(0.5 * (1e-3 + 1e-5))
    assert train_mod.lr_at(cfg, 10) == pytest.approx(1e-5)


def test_cosine_learning_rate_ends_by_the_time_limit():
    cfg = TrainConfig(epochs=10, lr=1e-3, min_lr_fraction=0.01, time_limit_min=30,
                      anneal_by_time=True)
    # without the option the clock does not matter (a cut run resumes exactly)
    assert train_mod.lr_at(TrainConfig(epochs=10, lr=1e-3, min_lr_fraction=0.01,
                                       time_limit_min=30), 2, elapsed_s=30 * 60) > 0.9e-3
    # half the time gone at epoch 2: the schedule follows the clock
    assert train_mod.lr_at(cfg, 2, elapsed_s=15 * 60) == pytest.approx(0.5 * (1e-3 + 1e-5))
    assert train_mod.lr_at(cfg, 3, elapsed_s=30 * 60) == pytest.approx(1e-5)
    # epochs ahead of the clock: the epochs lead, as without a limit
    assert train_mod.lr_at(cfg, 5, elapsed_s=60) == pytest.approx(0.5 * (1e-3 + 1e-5))
    assert train_mod.lr_at(cfg, 2.5, elapsed_s=0) == pytest.approx(
        1e-5 + 0.5 * (1e-3 - 1e-5) * (1 + np.cos(np.pi * 0.25)))


def test_a_run_stopped_by_its_time_limit_ends_with_its_learning_rate_decayed(
        scenes, tmp_path, monkeypatch):
    clock = iter(range(0, 10**6, 5))                   # every reading of the clock: 5 s later
    monkeypatch.setattr(train_mod, "_now", lambda: float(next(clock)))
    cfg = TrainConfig(epochs=50, batch=4, data=SMALL, net=TINY, threads=1, lr=1e-3,
                      time_limit_min=3.0, anneal_by_time=True)
    summary = train(cfg, [scenes / "val"], tmp_path / "run", progress=False)
    assert summary["status"] == "time_limit" and 3 <= summary["epochs_done"] < 50
    lrs = [row["lr"] for row in load_checkpoint(tmp_path / "run" / "checkpoint_last.pt")["history"]]
    assert lrs and lrs[-1] < 0.5e-3 and lrs == sorted(lrs, reverse=True)


def test_fine_tuning_keeps_the_init_models_graph_unless_told_otherwise(scenes, tmp_path, capsys):
    dilated = DataConfig(k=8, block_size=256, voxel_factor=0.15, remove_floor=False,
                         knn_near=4, knn_reach=12)
    train(TrainConfig(epochs=1, batch=4, data=dilated, net=TINY, threads=1), [scenes / "val"],
          tmp_path / "base", progress=False)
    base = tmp_path / "base" / "checkpoint_last.pt"

    # `fpcc train --init` with no graph options: the run is built like the init model's
    assert fpcc(["train", "--data", str(scenes / "val"), "--out", str(tmp_path / "tuned"),
                 "--epochs", "1", "--init", str(base), "--net", "tiny", "--threads", "1"]) == 0
    tuned = load_checkpoint(tmp_path / "tuned" / "checkpoint_last.pt")["config"]["data"]
    assert {f: tuned[f] for f in train_mod.GRAPH_FIELDS} == \
        {"k": 8, "block_size": 256, "voxel_factor": 0.15, "knn_near": 4, "knn_reach": 12,
         "normals": False}
    capsys.readouterr()

    # an explicit setting wins, with a warning when it departs from the init weights
    changed = train_mod.data_config_for(base, k=10, knn_reach=None)
    assert (changed.k, changed.knn_reach, changed.block_size) == (10, 12, 256)
    assert "--k 10 differs from the --init weights' 8" in capsys.readouterr().err
    # no init: the shipped model's settings
    fresh = train_mod.data_config_for(None)
    assert (fresh.k, fresh.block_size, fresh.voxel_factor, fresh.knn_near, fresh.knn_reach) == \
        (16, 2048, 0.1, 8, 48)


def test_checkpoints_from_before_the_dilated_graph_read_as_plain_knn():
    old = TrainConfig.from_dict({"epochs": 3, "data": {"k": 16, "block_size": 4096,
                                                       "voxel_factor": 0.08, "unknown_key": 1}})
    assert (old.data.knn_near, old.data.knn_reach, old.data.block_size) == (0, 0, 4096)


def test_init_default_is_the_shipped_models_weights():
    from fpcc_ros.onnx_model import default_model_path
    from fpcc_ros.training.model import NetConfig

    pt = resolve_init("default")
    assert pt == default_model_path().with_suffix(".pt") and pt.is_file()
    state = load_checkpoint(pt)
    card = load_card(card_path_for(default_model_path()))
    saved = state["config"]["data"]
    # the weights are the ONNX model's: same widths and the same graph as its card declares
    assert NetConfig.from_dict(state["net"]).embedding_dim == card.embedding_dim
    assert (saved["k"], saved["knn_near"], saved["knn_reach"], saved["block_size"]) == \
        (card.k, card.knn_near, card.knn_reach, card.block_size)


def test_precision_auto_follows_the_cpu(monkeypatch):
    from fpcc_ros.training.train import resolve_precision

    monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda: False, raising=False)
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False, raising=False)
    assert resolve_precision("auto") == "fp32"
    monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda: True, raising=False)
    assert resolve_precision("auto") == "bf16"
    assert resolve_precision("fp32") == "fp32"
    with pytest.raises(ValueError, match="precision 'fp16' is not one of"):
        resolve_precision("fp16")


def test_bf16_training_runs_in_bf16_and_matches_fp32_closely(scenes, tmp_path):
    runs = {}
    for precision in ("fp32", "bf16"):
        config = TrainConfig(**{**TINY_CONFIG.__dict__, "precision": precision})
        summary = train(config, [scenes / "train"], tmp_path / precision, progress=False)
        assert summary["precision"] == precision
        state = load_checkpoint(tmp_path / precision / "checkpoint_last.pt")
        assert state["config"]["precision"] == precision      # a resumed run keeps it
        runs[precision] = (summary["last"]["loss"], state["model"])
    (loss32, w32), (loss16, w16) = runs["fp32"], runs["bf16"]
    assert np.isfinite(loss16) and loss16 == pytest.approx(loss32, rel=0.05)
    moved = max((w16[k].float() - w32[k].float()).abs().max().item() for k in w32
                if w32[k].is_floating_point())
    assert moved > 0          # autocast really ran: rounding changed the updates


def test_checkpoints_from_before_the_precision_option_resume_in_fp32():
    body = TINY_CONFIG.to_dict()
    del body["precision"]
    assert TrainConfig.from_dict(body).precision == "fp32"


def test_val_every_validates_every_nth_epoch_and_the_last(scenes, tmp_path):
    cfg = TrainConfig(**{**TINY_CONFIG.__dict__, "epochs": 5, "val_every": 2})
    train(cfg, [scenes / "train"], tmp_path / "run", val=[scenes / "val"], progress=False)
    rows = _history(tmp_path / "run")
    assert [row["epoch"] for row in rows] == ["1", "2", "3", "4", "5"]
    validated = [row["epoch"] for row in rows if row["val_loss"] != ""]
    assert validated == ["2", "4", "5"]
    assert load_checkpoint(tmp_path / "run" / "checkpoint_best.pt")["epoch"] in (2, 4, 5)


def test_val_every_below_one_is_a_clear_error(scenes, tmp_path, capsys):
    assert fpcc(["train", "--data", str(scenes / "train"), "--out", str(tmp_path / "run"),
                 "--val-every", "0", *TRAIN_ARGS]) == 2
    assert "--val-every 0: must be >= 1" in capsys.readouterr().err
