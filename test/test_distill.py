"""fpcc train --teacher: a (narrower) net learns a trained net's outputs as well as the labels."""
import csv
from dataclasses import asdict, replace

import pytest

torch = pytest.importorskip("torch")

from fpcc_ros.cli import main as fpcc  # noqa: E402
from fpcc_ros.training.dataset import collate, load_scene, scene_blocks  # noqa: E402
from fpcc_ros.training.loss import distill_loss  # noqa: E402
from fpcc_ros.training.model import TINY, FPCCNet, NetConfig  # noqa: E402
from fpcc_ros.training.train import (TrainConfig, load_checkpoint, load_teacher,  # noqa: E402
                                     model_from_checkpoint, train)
from test_dataset import write_fake_scenes  # noqa: E402
from test_export import SMALL, TRAIN_ARGS, _one_thread  # noqa: E402,F401 (one torch thread)

NARROW = replace(TINY, edge_dim=TINY.edge_dim // 2)  # a student narrower than its teacher


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    write_fake_scenes(root / "train", count=2)
    return root


@pytest.fixture(scope="module")
def teacher_path(tmp_path_factory):
    """A TINY net with fixed random weights standing in for a trained teacher."""
    torch.manual_seed(7)
    net = FPCCNet(TINY).eval()
    path = tmp_path_factory.mktemp("teacher") / "teacher.pt"
    torch.save({"model": net.state_dict(), "net": TINY.to_dict()}, path)
    return path


def test_distill_loss_is_the_mean_squared_gap_over_real_points():
    embedding = torch.tensor([[[1.0, 0.0], [0.0, 2.0], [9.0, 9.0]]])
    target = torch.tensor([[[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]])
    score, target_score = torch.tensor([[0.5, 1.0, 0.0]]), torch.tensor([[0.0, 0.0, 7.0]])
    valid = torch.tensor([[True, True, False]])   # the third row is padding
    # rows: |(1,0)|^2 = 1 and |(0,2)|^2 = 4 -> 2.5; scores: 0.25 and 1 -> 0.625
    assert distill_loss(embedding, score, target, target_score, valid).item() == pytest.approx(3.125)


def _gap_to_teacher(model: FPCCNet, teacher: FPCCNet, scenes) -> float:
    """Mean squared embedding gap between a student and the teacher over the scenes' blocks."""
    scene = load_scene(next((scenes / "train").glob("*.npz")))
    batch = collate(scene_blocks(scene, SMALL).blocks[:4])
    with torch.no_grad():
        student, _ = model.eval()(batch["features"], batch["knn"])
        target, _ = teacher(batch["features"], batch["knn"])
    return float(((student - target)[batch["valid"]] ** 2).sum(-1).mean())


def test_a_student_with_a_teacher_ends_closer_to_it_than_one_without(scenes, teacher_path,
                                                                     tmp_path):
    teacher = load_teacher(teacher_path, NARROW, SMALL)
    gaps = {}
    for name, source in (("labels", ""), ("teacher", str(teacher_path))):
        config = TrainConfig(epochs=4, batch=4, lr=3e-3, data=SMALL, net=NARROW, threads=1,
                             seed=3, teacher=source, distill=10.0)
        train(config, [scenes / "train"], tmp_path / name, progress=False)
        state = load_checkpoint(tmp_path / name / "checkpoint_last.pt")
        gaps[name] = _gap_to_teacher(model_from_checkpoint(state), teacher, scenes)
    assert gaps["teacher"] < 0.5 * gaps["labels"], gaps
    with open(tmp_path / "teacher" / "history.csv") as fh:
        rows = list(csv.DictReader(fh))
    kd = [float(r["loss_kd"]) for r in rows]
    assert kd[-1] < kd[0], kd
    with open(tmp_path / "labels" / "history.csv") as fh:
        assert all(r["loss_kd"] == "" for r in csv.DictReader(fh))


def test_cli_teacher_is_kept_when_a_run_resumes(scenes, teacher_path, tmp_path):
    run = tmp_path / "run"
    assert fpcc(["train", "--data", str(scenes / "train"), "--out", str(run), "--epochs", "1",
                 "--teacher", str(teacher_path), "--distill", "2", *TRAIN_ARGS]) == 0
    saved = load_checkpoint(run / "checkpoint_last.pt")["config"]
    assert (saved["teacher"], saved["distill"]) == (str(teacher_path), 2.0)
    assert fpcc(["train", "--out", str(run), "--epochs", "2", "--resume", "--threads", "1"]) == 0
    with open(run / "history.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and all(float(r["loss_kd"]) > 0 for r in rows), rows


def test_a_teacher_of_another_embedding_width_is_refused(scenes, teacher_path, tmp_path, capsys):
    wide = TINY.to_dict()
    wide["embedding_dim"] = TINY.embedding_dim * 2
    torch.save({"model": FPCCNet(NetConfig.from_dict(wide)).state_dict(), "net": wide},
               tmp_path / "wide.pt")
    assert fpcc(["train", "--data", str(scenes / "train"), "--out", str(tmp_path / "run"),
                 "--teacher", str(tmp_path / "wide.pt"), *TRAIN_ARGS]) == 2
    assert "embedding" in capsys.readouterr().err


def test_a_teacher_trained_on_another_graph_is_refused(scenes, tmp_path, capsys):
    other = {**asdict(SMALL), "k": SMALL.k * 2}
    torch.save({"model": FPCCNet(TINY).state_dict(), "net": TINY.to_dict(),
                "config": {"data": other}}, tmp_path / "other.pt")
    assert fpcc(["train", "--data", str(scenes / "train"), "--out", str(tmp_path / "run"),
                 "--teacher", str(tmp_path / "other.pt"), *TRAIN_ARGS]) == 2
    assert f"k {SMALL.k * 2} (the run: {SMALL.k})" in capsys.readouterr().err
