"""fpcc train --prototype: the prototype cross-entropy joins the embedding loss, and every
validation reports how many part points lie nearest their own part (val_nearest_own)."""
import csv

import pytest

torch = pytest.importorskip("torch")

from fpcc_ros.cli import main as fpcc  # noqa: E402
from fpcc_ros.training.train import load_checkpoint  # noqa: E402
from test_dataset import write_fake_scenes  # noqa: E402
from test_export import TRAIN_ARGS, _one_thread  # noqa: E402,F401 (one torch thread)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    write_fake_scenes(root / "train", count=2)
    write_fake_scenes(root / "val", count=1)
    return root


def _train(scenes, run, *extra):
    assert fpcc(["train", "--data", str(scenes / "train"), "--val", str(scenes / "val"),
                 "--out", str(run), "--epochs", "1", "--seed", "3", *extra, *TRAIN_ARGS]) == 0
    with open(run / "history.csv") as fh:
        return list(csv.DictReader(fh))[-1]


def test_prototype_term_is_recorded_and_added_to_the_embedding_loss(scenes, tmp_path):
    plain = _train(scenes, tmp_path / "plain")
    with_term = _train(scenes, tmp_path / "proto", "--prototype", "0.5")
    assert load_checkpoint(tmp_path / "proto" / "checkpoint_last.pt")["config"]["prototype"] == 0.5
    assert load_checkpoint(tmp_path / "plain" / "checkpoint_last.pt")["config"]["prototype"] == 0.0
    # an untrained net is far from 0 cross-entropy, so the term shows in L_EF
    assert float(with_term["val_loss_ef"]) > float(plain["val_loss_ef"]) + 0.05
    for row in (plain, with_term):
        assert 0.0 < float(row["val_nearest_own"]) <= 1.0
