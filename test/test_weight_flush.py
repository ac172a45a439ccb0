"""Tiny float weights are zeroed at export and at load (issue 25): denormals cost Intel ~30x."""
import shutil
from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import numpy_helper  # noqa: E402

from fpcc_ros.model_card import card_path_for  # noqa: E402
from fpcc_ros.onnx_model import FpccModel, default_model_path  # noqa: E402
from fpcc_ros.weight_flush import count_tiny_weights, dead_channels, flush_tiny_weights  # noqa: E402

TINY_MODEL = Path(__file__).parent / "data" / "tiny_fpcc.onnx"
FLOAT32_TINY = np.finfo(np.float32).tiny


def _float_initializers(model_bytes: bytes) -> dict[str, np.ndarray]:
    model = onnx.load_from_string(model_bytes)
    return {i.name: numpy_helper.to_array(i) for i in model.graph.initializer
            if i.data_type == onnx.TensorProto.FLOAT}


def _with_tiny_weights(tmp_path: Path, zeros: bool = False) -> tuple[Path, dict[str, np.ndarray]]:
    """The committed tiny model with 7 denormal and 5 merely tiny weights planted in its largest
    matrix (as a collapsed channel leaves them), or exact zeros in their place (``zeros``);
    returns the path and the planted arrays."""
    model = onnx.load(str(TINY_MODEL))
    big = max((i for i in model.graph.initializer if i.data_type == onnx.TensorProto.FLOAT),
              key=lambda i: numpy_helper.to_array(i).size)
    values = numpy_helper.to_array(big).copy()
    flat = values.reshape(-1)
    flat[:7] = 0 if zeros else np.float32(3e-39)      # denormal
    flat[7:12] = 0 if zeros else np.float32(-4e-25)   # normal; its products are denormal
    big.CopyFrom(numpy_helper.from_array(values, big.name))
    path = tmp_path / ("zeros.onnx" if zeros else "planted.onnx")
    onnx.save(model, str(path))
    shutil.copyfile(card_path_for(TINY_MODEL), card_path_for(path))
    return path, {big.name: values}


def test_flush_zeroes_exactly_the_tiny_weights(tmp_path):
    path, planted = _with_tiny_weights(tmp_path)
    original = path.read_bytes()
    flushed, found = flush_tiny_weights(original)
    assert (found.denormal, found.flushed) == (7, 12)
    before, after = _float_initializers(original), _float_initializers(flushed)
    for name, values in before.items():
        expected = np.where((np.abs(values) < 1e-20), np.float32(0), values)
        assert np.array_equal(after[name], expected), name
    assert len(flushed) == len(original)
    assert count_tiny_weights(flushed).flushed == 0


def test_model_load_flushes_in_memory_with_the_same_outputs(tmp_path):
    path, _ = _with_tiny_weights(tmp_path)
    model = FpccModel(path, threads=1)
    assert (model.flush.denormal, model.flush.flushed) == (7, 12)
    clean = FpccModel(_with_tiny_weights(tmp_path, zeros=True)[0], threads=1)
    assert clean.flush.flushed == 0
    rng = np.random.default_rng(0)
    features = rng.normal(size=(1, 200, 6)).astype(np.float32)
    knn = rng.integers(0, 200, (1, 200, clean.card.k)).astype(np.int64)
    for a, b in zip(model.run(features, knn), clean.run(features, knn)):
        np.testing.assert_array_equal(a, b)


def test_not_an_onnx_file_is_a_load_error(tmp_path):
    path = tmp_path / "garbage.onnx"
    path.write_bytes(b"\xff" * 64)
    shutil.copyfile(card_path_for(TINY_MODEL), card_path_for(path))
    from fpcc_ros.onnx_model import ModelLoadError
    with pytest.raises(ModelLoadError, match="re-export"):
        FpccModel(path)


def test_shipped_model_has_no_tiny_weights():
    weights = _float_initializers(default_model_path().read_bytes())
    denormal = sum(int(((w != 0) & (np.abs(w) < FLOAT32_TINY)).sum()) for w in weights.values())
    tiny = sum(int(((w != 0) & (np.abs(w) < 1e-20)).sum()) for w in weights.values())
    assert (denormal, tiny) == (0, 0)


def test_shipped_model_has_no_dead_channels():
    """The collapse of issue 23: the previous default had 892 of its 1024 global channels (and
    six more matrices) producing a constant; ../shared/tools/model_health.py counts the same."""
    assert dead_channels(default_model_path().read_bytes()) == {}


def test_optimize_file_writes_no_tiny_weights(tmp_path):
    from fpcc_ros.graph_rewrite import optimize_file
    path, _ = _with_tiny_weights(tmp_path)
    result = optimize_file(path, tmp_path / "fixed.onnx")
    # the 5 normal tiny ones always; the 7 denormals too unless an earlier onnxruntime session
    # with set_denormal_as_zero left this thread's CPU flushing denormals (numpy's copies in the
    # rewrite then zero them before they are counted)
    assert result["flushed"] - result["denormal"] == 5 and result["denormal"] in (0, 7)
    weights = _float_initializers((tmp_path / "fixed.onnx").read_bytes())
    assert sum(int(((w != 0) & (np.abs(w) < 1e-20)).sum()) for w in weights.values()) == 0
