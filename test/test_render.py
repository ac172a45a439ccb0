"""`fpcc render`: a PNG from a scene NPZ, and clear errors."""
import numpy as np

from fpcc_ros.cli import main as fpcc


def _scene(path, h=24, w=32):
    rng = np.random.default_rng(0)
    gx, gy = np.meshgrid(np.linspace(-1, 1, w), np.linspace(-1, 1, h))
    pts = np.dstack([gx, gy, np.ones((h, w))])
    inst = (rng.random((h, w)) * 4).astype(np.int32)
    np.savez(path, points=pts.astype(np.float32), instance=inst,
             center_score=rng.random((h, w)).astype(np.float32), part_radius=np.float32(0.1))


def test_render_scene_writes_a_png(tmp_path, capsys):
    _scene(tmp_path / "s.npz")
    assert fpcc(["render", str(tmp_path / "s.npz"), "--out", str(tmp_path / "s.png")]) == 0
    assert (tmp_path / "s.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_render_refuses_a_mismatched_ground_truth(tmp_path, capsys):
    _scene(tmp_path / "a.npz")
    _scene(tmp_path / "b.npz", h=10, w=10)
    rc = fpcc(["render", str(tmp_path / "a.npz"), "--ground-truth", str(tmp_path / "b.npz")])
    assert rc == 2 and "pass the scene the prediction was made from" in capsys.readouterr().err


def test_render_missing_input(tmp_path, capsys):
    assert fpcc(["render", str(tmp_path / "nope.npz")]) == 2
    assert "does not exist" in capsys.readouterr().err
