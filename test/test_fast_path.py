"""Fast paths against straightforward references: the ONNX graph rewrite (same outputs as the
exported graph), and the runtime helpers the benchmark optimised."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
TINY = REPO / "test" / "data" / "tiny_fpcc.onnx"

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")


# ---------------------------------------------------------------------------------------------
# ONNX: global max-pool rewrite
# ---------------------------------------------------------------------------------------------
def _session(model_bytes: bytes):
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    return ort.InferenceSession(model_bytes, options, providers=["CPUExecutionProvider"])


def _ops(model) -> list[str]:
    return [n.op_type for n in model.graph.node]


def test_rewrite_of_the_exported_network_keeps_its_outputs(tmp_path):
    from fpcc_ros.graph_rewrite import optimize_file, sample_blocks
    from fpcc_ros.model_card import card_path_for, load_card
    from fpcc_ros.onnx_model import FpccModel

    dst = tmp_path / "fast.onnx"
    result = optimize_file(TINY, dst)
    # the global pool, then all four max-pools (3 EdgeConv, 1 global) ahead of bias + activation
    # the committed tiny model has no weights under 1e-20: nothing flushed
    assert result == {"fused": 1, "generic": 0, "moved": 4, "strided": 1, "flushed": 0,
                      "denormal": 0, "max_abs_diff": result["max_abs_diff"]}
    rewritten = onnx.load(str(dst))
    ops = _ops(rewritten)
    assert ops.count("GlobalMaxPool") == 1
    # the neighbour max-pools (axis 2) stay, the point-axis one is gone
    for n in rewritten.graph.node:
        if n.op_type == "ReduceMax":
            axes = [a for a in n.attribute if a.name == "axes"][0].ints
            assert list(axes) != [1]
    card = load_card(card_path_for(TINY))
    a, b = _session(TINY.read_bytes()), _session(dst.read_bytes())
    for feed in sample_blocks(card.k, card.part_radius, sizes=(40, 700), batch=2, seed=5):
        for x, y in zip(a.run(None, feed), b.run(None, feed)):
            assert x.shape == y.shape
            np.testing.assert_allclose(y, x, rtol=0, atol=1e-5)
    # no activation or bias add is left on a tensor that still has the neighbour axis
    for n in rewritten.graph.node:
        if n.op_type in ("LeakyRelu", "Add"):
            feeds_pool = any(m.op_type in ("ReduceMax", "GlobalMaxPool") and n.output[0] in m.input
                             for m in rewritten.graph.node)
            assert not feeds_pool, n.name
    # the runtime loads it (its load-time checks included) and reports the rewrite
    (tmp_path / "fast.json").write_text(card_path_for(TINY).read_text())
    model = FpccModel(dst)
    assert model.graph_notes == "global-max-pool,max-first,global-stride"
    assert model.supports_global_stride and not FpccModel(TINY).supports_global_stride
    # rewriting again changes nothing
    again = optimize_file(dst, tmp_path / "again.onnx")
    assert (again["fused"], again["moved"], again["strided"]) == (0, 0, 0)


def test_global_stride_takes_the_global_max_over_every_sth_point(tmp_path):
    """A block whose points all come twice in a row: the max over every 2nd row sees each
    point once, so stride 2 gives what stride 1 gives; on a plain block stride 3 changes the
    outputs (the input is used), and a model without the input refuses a stride."""
    from fpcc_ros.graph_rewrite import optimize_file, sample_blocks
    from fpcc_ros.model_card import card_path_for, load_card
    from fpcc_ros.onnx_model import FpccModel

    dst = tmp_path / "fast.onnx"
    optimize_file(TINY, dst)
    (tmp_path / "fast.json").write_text(card_path_for(TINY).read_text())
    model, plain = FpccModel(dst), FpccModel(TINY)
    card = load_card(card_path_for(TINY))
    feed = sample_blocks(card.k, card.part_radius, sizes=(300,), batch=1, seed=3)[0]
    feats, knn = feed["features"], feed["knn"]
    twice = np.repeat(feats, 2, axis=1)              # rows 2i and 2i+1: point i
    twice_knn = np.repeat(2 * knn, 2, axis=1)         # their neighbours: the copies 2j
    every = model.run(twice, twice_knn)
    second = model.run(twice, twice_knn, global_stride=2)
    for x, y in zip(every, second):
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-5)
    # the copies reproduce the block itself (the doubling is neutral), so the test has teeth
    np.testing.assert_allclose(every[0][:, ::2], plain.run(feats, knn)[0], rtol=0, atol=1e-5)
    strided = model.run(feats, knn, global_stride=3)
    assert np.abs(strided[0] - model.run(feats, knn)[0]).max() > 1e-4
    with pytest.raises(ValueError, match="optimize_onnx"):
        plain.run(feats, knn, global_stride=2)


def _toy_model(keepdims: int, leaky_is_output: bool) -> bytes:
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(0)
    w = rng.normal(size=(5, 7)).astype(np.float32)
    b = rng.normal(size=(7,)).astype(np.float32)
    nodes = [helper.make_node("MatMul", ["x", "w"], ["m"]),
             helper.make_node("Add", ["b", "m"], ["a"]),
             helper.make_node("LeakyRelu", ["a"], ["l"], alpha=0.2),
             helper.make_node("ReduceMax", ["l"], ["y"], axes=[1], keepdims=keepdims)]
    y_dims = ["b", 1, 7] if keepdims else ["b", 7]
    outputs = [helper.make_tensor_value_info("y", TensorProto.FLOAT, y_dims)]
    if leaky_is_output:
        outputs.append(helper.make_tensor_value_info("l", TensorProto.FLOAT, ["b", "n", 7]))
    graph = helper.make_graph(nodes, "toy", [helper.make_tensor_value_info(
        "x", TensorProto.FLOAT, ["b", "n", 5])], outputs,
        initializer=[numpy_helper.from_array(w, "w"), numpy_helper.from_array(b, "b")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    return model.SerializeToString()


@pytest.mark.parametrize("keepdims", [1, 0])
@pytest.mark.parametrize("leaky_is_output", [False, True])
def test_rewrite_variants_match_reducemax(keepdims, leaky_is_output):
    from fpcc_ros.graph_rewrite import rewrite_global_max

    original = _toy_model(keepdims, leaky_is_output)
    model, fused, generic = rewrite_global_max(onnx.load_from_string(original))
    onnx.checker.check_model(model)
    # a chain whose activation is used elsewhere cannot be moved: the generic form is used
    assert (fused, generic) == ((0, 1) if leaky_is_output else (1, 0))
    x = np.random.default_rng(1).normal(size=(2, 33, 5)).astype(np.float32)
    got = _session(model.SerializeToString()).run(None, {"x": x})
    # independent reference in numpy: max over points of LeakyReLU(x w + b)
    inits = {i.name: onnx.numpy_helper.to_array(i) for i in onnx.load_from_string(original).graph.initializer}
    pre = x.astype(np.float64) @ inits["w"] + inits["b"]
    act = np.where(pre > 0, pre, 0.2 * pre)
    want = act.max(axis=1, keepdims=bool(keepdims))
    assert got[0].shape == want.shape
    np.testing.assert_allclose(got[0], want, rtol=0, atol=1e-5)
    if leaky_is_output:
        np.testing.assert_allclose(got[1], act, rtol=0, atol=1e-5)


def _max_tail_model(case: str, opset: int = 17) -> tuple[bytes, dict[str, np.ndarray]]:
    """A (b, n, k, c) tensor through a bias/per-point Add and LeakyRelu into a max over k
    (opset 18 and later take ReduceMax's axes as an input)."""
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(3)
    bias = rng.normal(size=(4,)).astype(np.float32)
    varying = rng.normal(size=(5, 4)).astype(np.float32)      # differs along k: must not move
    inits = [numpy_helper.from_array(bias, "bias"), numpy_helper.from_array(varying, "varying"),
             numpy_helper.from_array(np.array([2], np.int64), "k_axis")]
    x = helper.make_tensor_value_info("x", TensorProto.FLOAT, ["b", "n", 5, 4])
    p = helper.make_tensor_value_info("p", TensorProto.FLOAT, ["b", "n", 4])
    other = {"bias": "bias", "varying": "varying", "per_point": "p_k", "negative": "bias"}[case]
    nodes = [helper.make_node("Unsqueeze", ["p", "k_axis"], ["p_k"]),
             helper.make_node("Add", [other, "x"], ["a"]),
             helper.make_node("LeakyRelu", ["a"], ["l"], alpha=-0.5 if case == "negative" else 0.2),
             helper.make_node("ReduceMax", ["l"], ["y"], axes=[2], keepdims=0) if opset < 18
             else helper.make_node("ReduceMax", ["l", "k_axis"], ["y"], keepdims=0)]
    graph = helper.make_graph(nodes, "tail", [x, p], [helper.make_tensor_value_info(
        "y", TensorProto.FLOAT, ["b", "n", 4])], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)])
    model.ir_version = 8
    feed = {"x": rng.normal(size=(2, 9, 5, 4)).astype(np.float32),
            "p": rng.normal(size=(2, 9, 4)).astype(np.float32)}
    return model.SerializeToString(), feed


@pytest.mark.parametrize("opset", [17, 18])
@pytest.mark.parametrize("case, after_max", [("bias", {"Add", "LeakyRelu"}),
                                             ("per_point", {"Add", "LeakyRelu"}),
                                             ("varying", {"LeakyRelu"}), ("negative", set())])
def test_max_moves_ahead_of_monotone_steps_only(case, after_max, opset):
    """max_k LeakyReLU(z_k + c) = LeakyReLU(max_k z_k + c) when c is the same along k (a bias,
    a per-point term) and the slope is not negative; then the outputs are bit-identical. An
    Add of something that varies along k stays before the max (its activation alone moves)."""
    from fpcc_ros.graph_rewrite import move_max_before_monotone

    original, feed = _max_tail_model(case, opset)
    model, moved = move_max_before_monotone(onnx.load_from_string(original))
    onnx.checker.check_model(model)
    assert moved == int(bool(after_max))
    ops = _ops(model)
    assert {op for op in ("Add", "LeakyRelu") if ops.index(op) > ops.index("ReduceMax")} == after_max
    got = _session(model.SerializeToString()).run(None, feed)[0]
    assert np.array_equal(got, _session(original).run(None, feed)[0])
    # independent reference in numpy
    c = {"bias": lambda: onnx.numpy_helper.to_array(onnx.load_from_string(original).graph.initializer[0]),
         "per_point": lambda: feed["p"][:, :, None, :],
         "varying": lambda: onnx.numpy_helper.to_array(onnx.load_from_string(original).graph.initializer[1]),
         "negative": lambda: onnx.numpy_helper.to_array(onnx.load_from_string(original).graph.initializer[0])}[case]()
    pre = feed["x"] + c
    alpha = -0.5 if case == "negative" else 0.2
    want = np.where(pre >= 0, pre, alpha * pre).max(axis=2)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)


def test_optimize_file_refuses_a_result_it_cannot_verify(tmp_path):
    from fpcc_ros.graph_rewrite import optimize_file

    dst = tmp_path / "out.onnx"
    with pytest.raises(ValueError, match="differs from the original"):
        optimize_file(TINY, dst, tolerance=-1.0)
    assert not dst.exists()


# ---------------------------------------------------------------------------------------------
# NMS and nearest-center assignment
# ---------------------------------------------------------------------------------------------
def _dense_gated_assign(xyz, emb, cxyz, cemb, d_max, gate):
    """The gated rule written plainly: per point, among the centers within d_max in 3D, the
    nearest in feature space; 0 if none or farther than the gate."""
    labels = np.zeros(len(xyz), np.int32)
    for i in range(len(xyz)):
        space = np.linalg.norm(cxyz - xyz[i], axis=1)
        feat = np.linalg.norm(cemb - emb[i], axis=1)
        feat[space > d_max] = np.inf
        j = int(np.argmin(feat))
        if np.isfinite(feat[j]) and feat[j] <= gate:
            labels[i] = j + 1
    return labels


def _clustered_scene(seed, n_centers=9, n_points=700, dim=16):
    rng = np.random.default_rng(seed)
    cxyz = rng.uniform(0, 3, (n_centers, 3))
    cemb = rng.normal(0, 2, (n_centers, dim))
    owner = rng.integers(0, n_centers, n_points)
    xyz = cxyz[owner] + rng.normal(0, 0.35, (n_points, 3))
    emb = cemb[owner] + rng.normal(0, 0.6, (n_points, dim))
    return xyz, emb.astype(np.float32), cxyz, cemb.astype(np.float32)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("chunk", [7, 64, 4096])
def test_assignment_matches_the_plain_gated_rule(seed, chunk, monkeypatch):
    import fpcc_ros.clustering as clustering

    monkeypatch.setattr(clustering, "ROW_CHUNK", chunk)
    xyz, emb, cxyz, cemb = _clustered_scene(seed)
    for gate in (np.inf, 2.5):
        want = _dense_gated_assign(xyz, emb, cxyz, cemb, 0.8, gate)
        got = clustering.assign_to_center_points(xyz, emb, cxyz, cemb, 0.8, gate)
        assert (want > 0).sum() > 100 and (want == 0).sum() > 0  # both outcomes occur
        np.testing.assert_array_equal(got, want)


def test_assignment_agrees_with_the_paper_rule_where_unambiguous(monkeypatch):
    import fpcc_ros.clustering as clustering

    monkeypatch.setattr(clustering, "ROW_CHUNK", 50)
    xyz, emb, cxyz, cemb = _clustered_scene(11, n_points=400)
    allxyz, allemb = np.vstack([cxyz, xyz]), np.vstack([cemb, emb])
    centers = np.arange(len(cxyz))
    ref = clustering.assign_reference(allxyz, allemb, centers, 0.8)
    fast = clustering.assign_to_centers(allxyz, allemb, centers, 0.8)
    unambiguous = ref > 0   # the feature-nearest center is within d_max
    assert unambiguous.sum() > 250
    np.testing.assert_array_equal(fast[unambiguous], ref[unambiguous])


@pytest.fixture
def three_threads(monkeypatch):
    """The clustering's chunk loops split over a pool of 3 threads from 128 rows on (chunks of
    64 rows), whatever this machine's core count."""
    from concurrent.futures import ThreadPoolExecutor

    import fpcc_ros.clustering as clustering

    pool = ThreadPoolExecutor(3, thread_name_prefix="test_pool")
    monkeypatch.setattr(clustering, "_thread_pool", lambda: (pool, 3))
    monkeypatch.setattr(clustering, "ROW_CHUNK", 64)
    monkeypatch.setattr(clustering, "PARALLEL_ROWS", 128)
    yield clustering
    pool.shutdown()


def test_row_ranges_are_whole_chunks_on_pool_threads(three_threads, monkeypatch):
    import threading

    clustering = three_threads
    seen = clustering._over_row_ranges(
        1000, lambda a, b: (a, b, threading.current_thread().name))
    ranges = [(a, b) for a, b, _ in seen]
    # 16 chunks of 64 over 3 threads: 5, 5 and 6 chunks, the last one short
    assert ranges == [(0, 320), (320, 640), (640, 1000)]
    assert all(name.startswith("test_pool") for _, _, name in seen)
    # below PARALLEL_ROWS, under chunk_threads(1), and on a single core (no pool), one range
    assert clustering._over_row_ranges(127, lambda a, b: (a, b)) == [(0, 127)]
    with clustering.chunk_threads(1):
        assert clustering._over_row_ranges(1000, lambda a, b: (a, b)) == [(0, 1000)]
    with clustering.chunk_threads(2):
        assert clustering._over_row_ranges(1000, lambda a, b: (a, b)) == [(0, 512), (512, 1000)]
    monkeypatch.setattr(clustering, "_thread_pool", lambda: None)
    assert clustering._over_row_ranges(1000, lambda a, b: (a, b)) == [(0, 1000)]


@pytest.mark.parametrize("seed", range(3))
def test_split_assignment_gives_the_labels_of_one_thread(seed, three_threads, monkeypatch):
    clustering = three_threads
    xyz, emb, cxyz, cemb = _clustered_scene(seed, n_points=1000)
    split = clustering.assign_to_center_points(xyz, emb, cxyz, cemb, 0.8, 2.5)
    monkeypatch.setattr(clustering, "PARALLEL_ROWS", 10**9)
    np.testing.assert_array_equal(
        split, clustering.assign_to_center_points(xyz, emb, cxyz, cemb, 0.8, 2.5))
    np.testing.assert_array_equal(split, _dense_gated_assign(xyz, emb, cxyz, cemb, 0.8, 2.5))


def test_split_prototypes_match_one_thread(three_threads, monkeypatch):
    clustering = three_threads
    xyz, emb, cxyz, _ = _clustered_scene(5, n_points=1000)
    centers = np.array([0, 100, 200, 300])
    split = clustering.center_prototypes(xyz, emb, centers, radius=0.5, pull=5.0)
    monkeypatch.setattr(clustering, "PARALLEL_ROWS", 10**9)
    whole = clustering.center_prototypes(xyz, emb, centers, radius=0.5, pull=5.0)
    assert not np.allclose(whole, emb[centers])   # neighbours were averaged
    np.testing.assert_allclose(split, whole, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("direct", [0, 2, 64])
@pytest.mark.parametrize("chunk", [16, 1024])
@pytest.mark.parametrize("tiled", [False, True])
def test_nms_direct_and_tree_phases_match_the_literal_algorithm(seed, direct, chunk, tiled,
                                                                monkeypatch):
    import fpcc_ros.nms as nms

    monkeypatch.setattr(nms, "DIRECT_CENTERS", direct)
    monkeypatch.setattr(nms, "NMS_CHUNK", chunk)   # one chunk, or many spread over the cloud
    monkeypatch.setattr(nms, "TILED_CANDIDATES", 0 if tiled else 10**9)  # chunks of tiles
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 1, (500, 3))
    scores = np.round(rng.uniform(0, 1, 500), 2)   # many ties: broken by index
    want = nms.nms_reference(xyz, scores, 0.5, 0.12)
    assert len(want) > 10
    np.testing.assert_array_equal(nms.nms_centers(xyz, scores, 0.5, 0.12), want)


# ---------------------------------------------------------------------------------------------
# features.py: outputs bit-identical to the implementation training used before the speed-ups
# ---------------------------------------------------------------------------------------------
def _voxel_downsample_before(xyz, voxel_size):
    """fpcc_ros.features.voxel_downsample as of commit dc90e62 (np.unique over voxel keys)."""
    n = len(xyz)
    if voxel_size <= 0 or n == 0:
        return np.arange(n), np.arange(n)
    cells = np.floor((xyz - xyz.min(axis=0)) / voxel_size).astype(np.int64)
    dims = cells.max(axis=0) + 1
    keys = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    _, keep, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return keep, inverse.reshape(-1)


def _knn_graph_before(xyz, k):
    """fpcc_ros.features.knn_graph as of commit dc90e62."""
    from scipy.spatial import cKDTree

    n = len(xyz)
    kk = min(k, n)
    _, idx = cKDTree(xyz).query(xyz, k=kk)
    idx = np.asarray(idx, dtype=np.int64).reshape(n, kk)
    if kk < k:
        idx = np.concatenate([idx, np.repeat(idx[:, -1:], k - kk, axis=1)], axis=1)
    return idx


def _clouds():
    rng = np.random.default_rng(3)
    camera = rng.normal(0, 0.3, (20000, 3)) + [0, 0, 1.2]
    quantized = np.round(rng.uniform(-0.5, 0.5, (5000, 3)), 2)          # points on voxel faces
    duplicates = np.repeat(rng.uniform(0, 1, (300, 3)), 4, axis=0)[rng.permutation(1200)]
    flat = np.c_[rng.uniform(0, 1, (3000, 2)), np.zeros(3000)]
    outlier = np.vstack([rng.uniform(0, 0.2, (2000, 3)), [[40.0, -35.0, 60.0]]])  # sparse grid
    return {"camera": camera, "quantized": quantized, "duplicates": duplicates, "flat": flat,
            "outlier": outlier, "one": np.array([[0.1, 0.2, 0.3]]), "empty": np.zeros((0, 3))}


@pytest.mark.parametrize("name", list(_clouds()))
@pytest.mark.parametrize("voxel", [0.0, 0.01, 0.05, 0.25])
def test_voxel_downsample_is_bit_identical_to_before(name, voxel):
    from fpcc_ros.features import voxel_downsample

    xyz = _clouds()[name]
    want, got = _voxel_downsample_before(xyz, voxel), voxel_downsample(xyz, voxel)
    for w, g in zip(want, got):
        assert g.dtype == w.dtype and g.shape == w.shape
        np.testing.assert_array_equal(g, w)


def test_voxel_downsample_sorts_when_the_grid_is_sparse(monkeypatch):
    import fpcc_ros.features as features

    xyz = _clouds()["camera"]
    want = _voxel_downsample_before(xyz, 0.02)
    monkeypatch.setattr(features, "DENSE_VOXEL_CELLS_PER_POINT", 0)   # force the np.unique path
    for w, g in zip(want, features.voxel_downsample(xyz, 0.02)):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize("name", ["camera", "quantized", "duplicates", "flat"])
@pytest.mark.parametrize("workers", [1, 2, -1])
def test_knn_graph_is_bit_identical_to_before(name, workers):
    from fpcc_ros.features import knn_graph

    xyz = _clouds()[name][:3000]
    np.testing.assert_array_equal(knn_graph(xyz, 16, workers=workers), _knn_graph_before(xyz, 16))
    small = xyz[:5]   # fewer points than k: the farthest neighbour is repeated
    np.testing.assert_array_equal(knn_graph(small, 16, workers=workers), _knn_graph_before(small, 16))


@pytest.mark.parametrize("roi", [(None, None), ((-0.2, -1.0, 0.5), None), (None, (0.3, 0.3, 2.0)),
                                 ((-0.2, -0.2, 0.8), (0.3, 0.3, 1.6))])
def test_valid_points_match_the_row_mask(roi):
    from fpcc_ros.pipeline import _valid_points

    rng = np.random.default_rng(8)
    xyz = (rng.normal(0, 0.3, (5000, 3)) + [0, 0, 1.2]).astype(np.float32)
    xyz[rng.integers(0, 5000, 400), rng.integers(0, 3, 400)] = np.nan
    xyz[rng.integers(0, 5000, 50), rng.integers(0, 3, 50)] = np.inf
    xyz[rng.integers(0, 5000, 50), rng.integers(0, 3, 50)] = -np.inf
    lo, hi = roi
    mask = np.isfinite(xyz).all(axis=1)
    if lo is not None:
        mask &= (xyz >= lo).all(axis=1)
    if hi is not None:
        mask &= (xyz <= hi).all(axis=1)
    np.testing.assert_array_equal(_valid_points(xyz, lo, hi), np.flatnonzero(mask))


# ---------------------------------------------------------------------------------------------
# msg_tools: the segmented cloud's bytes are those of the structured-dtype writer
# ---------------------------------------------------------------------------------------------
def _segmented_bytes_before(xyz, labels, score, n):
    from msg_tools.palette import packed_rgb
    from msg_tools.point_cloud2 import _SEGMENTED_BUILD_DTYPE

    cloud = np.empty(n, dtype=_SEGMENTED_BUILD_DTYPE)
    flat = np.asarray(xyz).reshape(n, 3)
    cloud["x"], cloud["y"], cloud["z"] = flat[:, 0], flat[:, 1], flat[:, 2]
    lab = np.asarray(labels).reshape(n)
    cloud["rgb"] = packed_rgb(lab)
    cloud["label"] = lab
    cloud["center_score"] = 0.0 if score is None else np.asarray(score).reshape(n)
    return cloud.tobytes()


@pytest.mark.parametrize("case", ["f32_u32", "f64_i64_none", "big_labels"])
def test_segmented_cloud_bytes_match_the_structured_writer(case):
    from msg_tools.msg_types import ROSBAGS
    from msg_tools.point_cloud2 import create_segmented_cloud

    rng = np.random.default_rng(4)
    h, w = 12, 17
    xyz = rng.normal(0, 1, (h, w, 3))
    xyz[0, :3] = np.nan
    labels = rng.integers(0, 40, (h, w))
    score = rng.uniform(0, 1, (h, w)).astype(np.float32)
    if case == "f32_u32":
        xyz, labels = xyz.astype(np.float32), labels.astype(np.uint32)
    elif case == "f64_i64_none":
        score = None
    else:
        labels = labels.astype(np.uint32) * 70001   # beyond the lookup table's range
    msg = create_segmented_cloud(ROSBAGS.header("f"), xyz, labels, score, h, w, types=ROSBAGS)
    assert bytes(msg.data) == _segmented_bytes_before(xyz, labels, score, h * w)


@pytest.mark.parametrize("n,block", [(8240, 2048), (2048, 2048), (2049, 2048), (10090, 2048),
                                     (5, 2048), (0, 2048), (1000, 64)])
def test_balanced_blocks_partition_into_the_fewest_blocks(n, block):
    from fpcc_ros.features import balanced_blocks

    rng = np.random.default_rng(n)
    xyz = rng.uniform(0, [0.9, 0.7, 0.3], (n, 3))
    blocks = balanced_blocks(xyz, block)
    assert len(blocks) == -(-n // block)               # ceil(n / block) blocks
    every = np.sort(np.concatenate(blocks)) if blocks else np.array([], int)
    np.testing.assert_array_equal(every, np.arange(n))  # a partition of the points
    sizes = [len(b) for b in blocks]
    assert all(s <= block for s in sizes)
    if len(blocks) > 1:
        assert max(sizes) - min(sizes) <= 2 and min(sizes) >= block // 2
    if n == 8240:   # the first cut is along x (the longest axis) at 2/5 of the points
        first_two = np.concatenate(blocks[:2])
        assert xyz[first_two, 0].max() <= np.sort(xyz[:, 0])[len(first_two)]


def test_pipeline_block_split_is_validated():
    from fpcc_ros.pipeline import ConfigError, PipelineConfig

    cfg = PipelineConfig(part_radius=0.1)
    assert cfg.replace(block_split="balanced").block_split == "balanced"
    with pytest.raises(ConfigError, match="block_split"):
        cfg.replace(block_split="random")


def _halo_blocks(xyz, block, halo):
    from fpcc_ros.features import spatial_blocks

    exts = []
    for core in spatial_blocks(xyz, block):
        lo, hi = xyz[core].min(axis=0) - halo, xyz[core].max(axis=0) + halo
        inside = ((xyz >= lo) & (xyz <= hi)).all(axis=1)
        inside[core] = False
        exts.append(np.concatenate([core, np.flatnonzero(inside)]))
    return exts


@pytest.mark.parametrize("name", ["camera", "quantized", "flat"])
def test_block_knn_gives_knn_graphs_neighbour_sets(name):
    from fpcc_ros.features import block_knn_graphs, knn_graph

    xyz = _clouds()[name][:6000]
    exts = _halo_blocks(xyz, 700, halo=0.1)
    got = block_knn_graphs(xyz, exts, 16, workers=2)
    assert len(got) == len(exts) > 4
    for ext, g in zip(exts, got):
        want = knn_graph(xyz[ext], 16)
        assert g.shape == want.shape and g.dtype == want.dtype
        # the same neighbours (sets) at the same distances; order may differ only among ties
        np.testing.assert_array_equal(np.sort(g, axis=1), np.sort(want, axis=1))
        pts = xyz[ext]
        dist = lambda k: np.linalg.norm(pts[k] - pts[:, None], axis=2)  # noqa: E731
        np.testing.assert_array_equal(dist(g), dist(want))
        if name != "quantized":   # (duplicated points there: distance-0 ties with itself)
            assert (g[:, 0] == np.arange(len(ext))).all()   # itself first


def test_block_knn_small_blocks_fall_back_to_knn_graph():
    from fpcc_ros.features import block_knn_graphs, knn_graph

    xyz = _clouds()["camera"][:40]
    order = np.argsort(xyz[:, 0])
    exts = [order[:5], order[5:]]           # split along x
    got = block_knn_graphs(xyz, exts, 16)
    np.testing.assert_array_equal(got[0], knn_graph(xyz[exts[0]], 16))   # fewer points than k
    np.testing.assert_array_equal(np.sort(got[1], 1), np.sort(knn_graph(xyz[exts[1]], 16), 1))


def test_block_knn_on_scattered_subsets():
    """Blocks need not be boxes: every other point, or a random third, interleaved with the
    points they lack -- most rows' global neighbours fall outside and are queried again."""
    from fpcc_ros.features import block_knn_graphs, knn_graph

    xyz = _clouds()["camera"][:3000]
    rng = np.random.default_rng(5)
    blocks = [np.arange(0, 3000, 2), np.sort(rng.choice(3000, 1000, replace=False)),
              np.arange(3000)]
    for block, got in zip(blocks, block_knn_graphs(xyz, blocks, 16)):
        np.testing.assert_array_equal(np.sort(got, 1), np.sort(knn_graph(xyz[block], 16), 1))


def test_network_output_does_not_depend_on_neighbour_order():
    """Why neighbour sets suffice: every EdgeConv takes a max over the row."""
    from fpcc_ros.features import block_features, knn_graph

    sess = _session(TINY.read_bytes())
    xyz = _clouds()["quantized"][:900]
    feats = block_features(xyz, 0.05)[None]
    knn = knn_graph(xyz, 16)
    rng = np.random.default_rng(0)
    shuffled = np.take_along_axis(knn, np.argsort(rng.random(knn.shape), axis=1), axis=1)
    a = sess.run(None, {"features": feats, "knn": knn[None]})
    b = sess.run(None, {"features": feats, "knn": shuffled[None]})
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_the_shipped_model_carries_every_rewrite():
    """A re-exported default must go through optimize_file again: without the rewrites the
    node is a third (global max-pool) plus 12-17% (max-first) slower for the same outputs, and
    the node's global_stride parameter could not be applied (the card ships stride 1: the
    healthy network loses 0.02 F1 on the ring screw at stride 2-4)."""
    from fpcc_ros.graph_rewrite import (METADATA_VALUE, STRIDE_NOTE, add_global_stride,
                                        move_max_before_monotone, rewrite_global_max)
    from fpcc_ros.onnx_model import FpccModel, default_model_path

    model = FpccModel(default_model_path())
    assert model.graph_notes == f"{METADATA_VALUE},{STRIDE_NOTE}"
    assert model.supports_global_stride
    shipped = onnx.load(str(default_model_path()))
    assert rewrite_global_max(shipped)[1:] == (0, 0)          # nothing left to rewrite
    assert move_max_before_monotone(shipped)[1] == 0
    assert add_global_stride(shipped)[1] == 0
