"""Exact rewrites of an exported FPCC-Net ONNX graph that onnxruntime's CPU kernels run faster.

The global feature of FPCC-Net is ``max over points of LeakyReLU(local @ W + b)``: a (B, N, 1024)
tensor reduced over the point axis. onnxruntime 1.23's ReduceMax over a long axis is slow (about
a third of the whole network on a 5k-point block, measured with its profiler), while its
GlobalMaxPool over the last axis of a (B, C, N) tensor runs at memory speed. So the chain

    MatMul(X, W) -> Add(b) -> LeakyRelu -> ReduceMax(axes=[1], keepdims=1)        (B, 1, C)

becomes, with the same weights transposed,

    Transpose(X) -> MatMul(W^T, .) -> Add(b^T) -> LeakyRelu -> GlobalMaxPool -> Transpose

Same arithmetic per output element (one dot product per point and channel, then a max), so
the outputs agree to float32 rounding (the GEMM may sum in another order). Any other ReduceMax
over axis 1 becomes Transpose -> GlobalMaxPool -> Transpose (bit-identical).

Inputs, outputs and the model card are unchanged. The rewritten model records
``fpcc_graph = global-max-pool`` in its metadata (onnxruntime shows it; the benchmark reports
it). Needs the ``onnx`` package (training/export dependency), never at runtime:
``scripts/optimize_onnx.py`` applies it to a file and checks the result against the original.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

METADATA_KEY = "fpcc_graph"
METADATA_VALUE = "global-max-pool"


def _attr(node: Any, name: str, default: Any = None) -> Any:
    from onnx import helper

    for a in node.attribute:
        if a.name == name:
            return helper.get_attribute_value(a)
    return default


def _reduce_axes(node: Any, inits: dict[str, np.ndarray]) -> list[int] | None:
    axes = _attr(node, "axes")
    if axes is None and len(node.input) > 1 and node.input[1] in inits:  # opset >= 18
        axes = inits[node.input[1]].reshape(-1).tolist()
    return None if axes is None else [int(a) for a in axes]


def rewrite_global_max(model: Any) -> tuple[Any, int, int]:
    """Rewrite every ReduceMax over axis 1 in ``model`` (an onnx ModelProto, changed in place).

    Returns ``(model, fused, generic)``: chains rewritten with the transposed GEMM, and other
    ReduceMax nodes rewritten as Transpose -> GlobalMaxPool -> Transpose.
    """
    from onnx import helper, numpy_helper

    graph = model.graph
    inits = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    producer = {o: n for n in graph.node for o in n.output}
    consumers: dict[str, list[Any]] = {}
    for n in graph.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    outputs = {o.name for o in graph.output}

    def only_used_by(tensor: str, node: Any) -> bool:
        return tensor not in outputs and [id(c) for c in consumers.get(tensor, [])] == [id(node)]

    remove: list[Any] = []
    fused = generic = 0
    new_nodes: dict[int, list[Any]] = {}   # id(ReduceMax node) -> replacement nodes
    new_inits = []
    for k, node in enumerate(graph.node):
        if node.op_type != "ReduceMax" or _reduce_axes(node, inits) != [1]:
            continue
        keepdims = int(_attr(node, "keepdims", 1))
        out = node.output[0]
        tag = f"fpcc_gmp{k}"
        x = node.input[0]
        pooled = f"{tag}_pooled"
        tail = [helper.make_node("Transpose", [pooled], [out] if keepdims else [f"{tag}_t"],
                                 perm=[0, 2, 1], name=f"{tag}/back")]
        if not keepdims:
            new_inits.append(numpy_helper.from_array(np.array([1], np.int64), f"{tag}_axis"))
            tail.append(helper.make_node("Squeeze", [f"{tag}_t", f"{tag}_axis"], [out],
                                         name=f"{tag}/squeeze"))
        chain = _linear_chain(x, node, producer, inits, only_used_by)
        if chain is not None:
            act, add, matmul, w, b, inp = chain
            new_inits += [numpy_helper.from_array(np.ascontiguousarray(w.T), f"{tag}_wT"),
                          numpy_helper.from_array(b.reshape(-1, 1).copy(), f"{tag}_bT")]
            nodes = [
                helper.make_node("Transpose", [inp], [f"{tag}_xT"], perm=[0, 2, 1], name=f"{tag}/xT"),
                helper.make_node("MatMul", [f"{tag}_wT", f"{tag}_xT"], [f"{tag}_mT"], name=f"{tag}/mm"),
                helper.make_node("Add", [f"{tag}_mT", f"{tag}_bT"], [f"{tag}_aT"], name=f"{tag}/add"),
                helper.make_node(act.op_type, [f"{tag}_aT"], [f"{tag}_lT"], name=f"{tag}/act",
                                 **({"alpha": float(_attr(act, "alpha", 0.01))}
                                    if act.op_type == "LeakyRelu" else {})),
                helper.make_node("GlobalMaxPool", [f"{tag}_lT"], [pooled], name=f"{tag}/pool"),
            ]
            remove += [act, add, matmul]
            fused += 1
        else:
            nodes = [helper.make_node("Transpose", [x], [f"{tag}_xT"], perm=[0, 2, 1], name=f"{tag}/xT"),
                     helper.make_node("GlobalMaxPool", [f"{tag}_xT"], [pooled], name=f"{tag}/pool")]
            generic += 1
        new_nodes[id(node)] = nodes + tail
    if not new_nodes:
        return model, 0, 0
    dropped = {id(n) for n in remove}
    rebuilt = []
    for n in graph.node:
        if id(n) in dropped:
            continue
        rebuilt.extend(new_nodes.get(id(n), [n]))
    del graph.node[:]
    graph.node.extend(rebuilt)
    graph.initializer.extend(new_inits)
    _drop_unused_initializers(graph)
    meta = {p.key: p for p in model.metadata_props}
    if METADATA_KEY in meta:
        meta[METADATA_KEY].value = METADATA_VALUE
    else:
        model.metadata_props.add(key=METADATA_KEY, value=METADATA_VALUE)
    return model, fused, generic


def _linear_chain(x: str, reduce: Any, producer: dict, inits: dict, only_used_by) -> tuple | None:
    """(act, add, matmul, W, b, input) when ``x`` = act(MatMul(input, W) + b) feeds only the
    ReduceMax, with W (Cin, Cout) and b (Cout,) constant; else None."""
    act = producer.get(x)
    if act is None or act.op_type not in ("LeakyRelu", "Relu") or not only_used_by(x, reduce):
        return None
    add = producer.get(act.input[0])
    if add is None or add.op_type != "Add" or not only_used_by(act.input[0], act):
        return None
    pair = list(add.input)
    bias_name = next((t for t in pair if t in inits), None)
    mm_name = next((t for t in pair if t != bias_name), None)
    matmul = producer.get(mm_name)
    if bias_name is None or matmul is None or matmul.op_type != "MatMul" or \
            not only_used_by(mm_name, add):
        return None
    w_name = matmul.input[1]
    if w_name not in inits:
        return None
    w, b = inits[w_name], inits[bias_name]
    if w.ndim != 2 or b.reshape(-1).shape != (w.shape[1],):
        return None
    return act, add, matmul, w.astype(np.float32), b.reshape(-1).astype(np.float32), matmul.input[0]


def _drop_unused_initializers(graph: Any) -> None:
    used = {i for n in graph.node for i in n.input} | {o.name for o in graph.output}
    keep = [i for i in graph.initializer if i.name in used]
    del graph.initializer[:]
    graph.initializer.extend(keep)


def optimize_file(src: Path | str, dst: Path | str, check: bool = True,
                  tolerance: float = 1e-4) -> dict[str, Any]:
    """Rewrite ``src`` into ``dst`` (may be the same path); with ``check``, run both on sample
    blocks and refuse (ValueError, nothing written) if any output differs by more than
    ``tolerance``. Returns what was done and the largest difference seen."""
    import onnx

    src, dst = Path(src), Path(dst)
    model = onnx.load(str(src))
    model, fused, generic = rewrite_global_max(model)
    onnx.checker.check_model(model)
    data = model.SerializeToString()
    worst = 0.0
    if check and (fused or generic):
        worst = compare_models(src.read_bytes(), data, card_path=src.with_suffix(".json"))
        if not worst <= tolerance:
            raise ValueError(f"{src}: the rewritten graph differs from the original by {worst:.2e} "
                             f"(> {tolerance:.0e}); not written")
    tmp = dst.with_name(dst.name + ".tmp")
    tmp.write_bytes(data)
    tmp.replace(dst)
    return {"fused": fused, "generic": generic, "max_abs_diff": worst}


def sample_blocks(k: int, part_radius: float, sizes=(300, 2500), batch: int = 2,
                  seed: int = 0) -> list[dict[str, np.ndarray]]:
    """Network inputs from random points on a few part-sized spheres (real features and kNN)."""
    from fpcc_ros.features import block_features, knn_graph

    rng = np.random.default_rng(seed)
    feeds = []
    for n in sizes:
        feats, knns = [], []
        for _ in range(batch):
            centers = rng.uniform(0, 4 * part_radius, size=(6, 3))
            dirs = rng.normal(size=(n, 3))
            xyz = centers[rng.integers(0, 6, n)] + part_radius * dirs / np.linalg.norm(
                dirs, axis=1, keepdims=True)
            feats.append(block_features(xyz, part_radius))
            knns.append(knn_graph(xyz, k))
        feeds.append({"features": np.stack(feats), "knn": np.stack(knns)})
    return feeds


def compare_models(original: bytes, rewritten: bytes, card_path: Path | None = None) -> float:
    """Largest |difference| of both outputs over :func:`sample_blocks`."""
    import onnxruntime as ort

    k, radius = 16, 0.05
    if card_path is not None and Path(card_path).is_file():
        from fpcc_ros.model_card import load_card
        card = load_card(card_path)
        k, radius = card.k, card.part_radius
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    a = ort.InferenceSession(original, options, providers=["CPUExecutionProvider"])
    b = ort.InferenceSession(rewritten, options, providers=["CPUExecutionProvider"])
    knn_width = {i.name: i.shape for i in a.get_inputs()}.get("knn", [None])[-1]
    if isinstance(knn_width, int):  # the graph itself says k (no card yet at export time)
        k = knn_width
    worst = 0.0
    for feed in sample_blocks(k, radius):
        for x, y in zip(a.run(None, feed), b.run(None, feed)):
            worst = max(worst, float(np.abs(x - y).max()))
    return worst
