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

A max also commutes with elementwise steps that never decrease and are the same along the
axis it reduces: max_k LeakyReLU(z_k + b) = LeakyReLU(max_k z_k + b). So every max-pool
(ReduceMax over a point's k neighbours, the global GlobalMaxPool above) is moved ahead of such
a tail of bias Adds and LeakyRelu/Relu (:func:`move_max_before_monotone`): the tail then runs on
the pooled tensor, k = 16 times smaller for the EdgeConv layers (three of their (N, k, 64)
bias adds and activations), N times for the global feature. Bit-identical: rounding to float32
is monotone too, so the largest input still gives the largest output.

Inputs, outputs and the model card are unchanged. The rewritten model records
``fpcc_graph = global-max-pool,max-first`` in its metadata (onnxruntime shows it; the benchmark
reports it).

One more step is not exact, and is off unless asked for at run time
(:func:`add_global_stride`): the global feature's max may be taken over every s-th point of a
block instead of all of them, a stride the graph takes as an optional input ``global_stride``
(an overridable initializer, default 1: the graph above, bit for bit). A max over a quarter of
a block's 2-4k points barely moves it; the 1024-wide GEMM before it, a fifth of the network,
shrinks with the points it sees (see the model card's ``global_stride`` and the README). Such a
model records ``global-stride`` in ``fpcc_graph`` as well.

Needs the ``onnx`` package (training/export dependency), never at runtime:
``scripts/optimize_onnx.py`` applies the rewrites to a file and checks the result against the
original.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from fpcc_ros.features import takes_normals
from fpcc_ros.onnx_model import STRIDE_INPUT
from fpcc_ros.weight_flush import flush_tiny_weights

METADATA_KEY = "fpcc_graph"
METADATA_VALUE = "global-max-pool,max-first"
STRIDE_NOTE = "global-stride"           # what it adds to the metadata value


def _attr(node: Any, name: str, default: Any = None) -> Any:
    return _attributes(node).get(name, default)


def _attributes(node: Any) -> dict[str, Any]:
    """A node's attributes as make_node keyword arguments (to rebuild it elsewhere)."""
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


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
    producer, only_used_by = _graph_index(graph)

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
    _splice(model, new_nodes, remove, new_inits)
    return model, fused, generic


def _splice(model: Any, replacements: dict[int, list[Any]], removed: list[Any],
            new_inits: list[Any]) -> None:
    """Put each replaced node's new nodes where it stood (``replacements``: id(node) -> nodes),
    drop ``removed``, add ``new_inits``, then whatever no longer feeds an output, and mark the
    model rewritten."""
    graph = model.graph
    dropped = {id(n) for n in removed}
    rebuilt = []
    for n in graph.node:
        if id(n) not in dropped:
            rebuilt.extend(replacements.get(id(n), [n]))
    del graph.node[:]
    graph.node.extend(rebuilt)
    graph.initializer.extend(new_inits)
    _drop_dead_nodes(graph)
    _drop_unused_initializers(graph)
    _mark_rewritten(model)


def _mark_rewritten(model: Any, value: str = METADATA_VALUE) -> None:
    """Add ``value``'s comma-separated steps to the model's ``fpcc_graph`` note, keeping the
    steps already there (in order, without repeats)."""
    meta = {p.key: p for p in model.metadata_props}
    steps = meta[METADATA_KEY].value.split(",") if METADATA_KEY in meta else []
    steps += [step for step in value.split(",") if step not in steps]
    joined = ",".join(step for step in steps if step)
    if METADATA_KEY in meta:
        meta[METADATA_KEY].value = joined
    else:
        model.metadata_props.add(key=METADATA_KEY, value=joined)


def add_global_stride(model: Any) -> tuple[Any, int]:
    """Give every global max-pool of ``model`` (changed in place) a Slice of every s-th point
    ahead of it, s the new optional input :data:`STRIDE_INPUT` (int64 [1], default 1, which
    is the unsliced graph bit for bit); returns ``(model, sliced)``.

    Runs on a graph after :func:`rewrite_global_max`: from each GlobalMaxPool back through its
    monotone tail and the transposed GEMM (the constant operand aside) to the Transpose that
    turns (B, N, C) points into (B, C, N); the Slice goes ahead of that Transpose, on the point
    axis, so the GEMM runs on the sliced points only. A model that already takes the input is
    left alone.
    """
    from onnx import TensorProto, helper, numpy_helper

    graph = model.graph
    if any(i.name == STRIDE_INPUT for i in graph.input):
        return model, 0
    consts = _constants(graph)
    producer, _ = _graph_index(graph)
    transposes = []
    for pool in graph.node:
        if pool.op_type != "GlobalMaxPool":
            continue
        node = producer.get(pool.input[0])
        while node is not None and node.op_type in ("Add", "MatMul", *_MONOTONE_UNARY):
            varying = [t for t in node.input if t not in consts]
            node = producer.get(varying[0]) if len(varying) == 1 else None
        if node is not None and node.op_type == "Transpose" and \
                list(_attr(node, "perm", [])) == [0, 2, 1]:
            transposes.append(node)
    if not transposes:
        return model, 0
    tag = "fpcc_stride"
    graph.initializer.extend([
        numpy_helper.from_array(np.array([0], np.int64), f"{tag}_starts"),
        numpy_helper.from_array(np.array([np.iinfo(np.int64).max], np.int64), f"{tag}_ends"),
        numpy_helper.from_array(np.array([1], np.int64), f"{tag}_axes"),
        numpy_helper.from_array(np.array([1], np.int64), STRIDE_INPUT)])
    graph.input.append(helper.make_tensor_value_info(STRIDE_INPUT, TensorProto.INT64, [1]))
    replacements = {}
    for k, node in enumerate(transposes):
        sliced = f"{tag}{k}_points"
        replacements[id(node)] = [
            helper.make_node("Slice", [node.input[0], f"{tag}_starts", f"{tag}_ends",
                                       f"{tag}_axes", STRIDE_INPUT], [sliced],
                             name=f"{tag}{k}/slice"),
            helper.make_node("Transpose", [sliced], list(node.output), name=node.name,
                             **_attributes(node))]
    rebuilt = [n for old in graph.node for n in replacements.get(id(old), [old])]
    del graph.node[:]
    graph.node.extend(rebuilt)
    _mark_rewritten(model, STRIDE_NOTE)
    return model, len(transposes)


# elementwise steps that never decrease in their input: a max commutes with them
_MONOTONE_UNARY = ("Relu", "LeakyRelu")


def move_max_before_monotone(model: Any) -> tuple[Any, int]:
    """Move every ReduceMax / GlobalMaxPool of ``model`` (changed in place) ahead of the bias
    Adds and LeakyRelu/Relu that feed it alone; returns ``(model, moved)``, the number of
    max-pools moved.

    An Add qualifies when its other operand is the same along the reduced axes: a constant of
    size 1 there, or an Unsqueeze on exactly those axes (EdgeConv's per-point term; when the max
    drops the axes, the moved Add takes the tensor before the Unsqueeze). Tails whose tensors
    are used elsewhere, or are graph outputs, stay.
    """
    from onnx import helper, numpy_helper

    graph = model.graph
    consts = _constants(graph)
    ranks = _ranks(model)
    producer, only_used_by = _graph_index(graph)

    def same_along(name: str, axes: list[int], rank: int, keepdims: int) -> Any:
        """What the moved Add takes for operand ``name`` (a tensor name or a new constant), or
        None when ``name`` varies along ``axes``."""
        if name in consts:
            value = consts[name]
            if value.ndim > rank:
                return None
            shape = (1,) * (rank - value.ndim) + value.shape
            if any(shape[a] != 1 for a in axes):
                return None
            if keepdims or value.ndim <= rank - 1 - max(axes):
                return name                   # broadcasts the same against the pooled tensor
            return value.reshape([d for i, d in enumerate(shape) if i not in axes])
        unsqueeze = producer.get(name)
        if unsqueeze is None or unsqueeze.op_type != "Unsqueeze":
            return None
        added = _reduce_axes(unsqueeze, consts)   # the same attribute / opset-18 input
        if added is None or sorted(a % rank for a in added) != axes:
            return None
        return name if keepdims else unsqueeze.input[0]

    replaced: dict[int, list[Any]] = {}
    removed: list[Any] = []
    new_inits = []
    for k, pool in enumerate(graph.node):
        rank = ranks.get(pool.input[0]) if pool.input else None
        if rank is None:
            continue
        if pool.op_type == "ReduceMax":
            axes = _reduce_axes(pool, consts)
            if not axes:
                continue
            axes, keepdims = sorted(a % rank for a in axes), int(_attr(pool, "keepdims", 1))
        elif pool.op_type == "GlobalMaxPool":
            axes, keepdims = list(range(2, rank)), 1
        else:
            continue
        # (node, its other operand after the move); float addition commutes exactly, so the
        # moved Add takes the pooled tensor first whichever side the chain came in on
        tail: list[tuple[Any, Any]] = []
        x, user = pool.input[0], pool
        while only_used_by(x, user) and x in producer:
            node = producer[x]
            if node.op_type in _MONOTONE_UNARY and float(_attr(node, "alpha", 0.0)) >= 0:
                chain, other = node.input[0], None
            elif node.op_type == "Add":
                chain, b = node.input
                other = same_along(b, axes, rank, keepdims)
                if other is None:
                    b, chain = chain, b
                    other = same_along(b, axes, rank, keepdims)
                if other is None or ranks.get(chain) != rank:  # the chain's tensor not broadcast
                    break
            else:
                break
            tail.append((node, other))
            x, user = chain, node
        if not tail:
            continue
        tag = f"fpcc_maxfirst{k}"
        nodes = [helper.make_node(pool.op_type, [x] + list(pool.input[1:]), [f"{tag}_pooled"],
                                  name=f"{tag}/pool", **_attributes(pool))]
        current = f"{tag}_pooled"
        for step, (node, other) in enumerate(reversed(tail)):
            out = pool.output[0] if step == len(tail) - 1 else f"{tag}_{step}"
            if other is None:
                nodes.append(helper.make_node(
                    node.op_type, [current], [out], name=f"{tag}/{node.op_type}{step}",
                    **_attributes(node)))
            else:
                if not isinstance(other, str):
                    new_inits.append(numpy_helper.from_array(other, f"{tag}_c{step}"))
                    other = f"{tag}_c{step}"
                nodes.append(helper.make_node("Add", [current, other], [out],
                                              name=f"{tag}/Add{step}"))
            current = out
        replaced[id(pool)] = nodes
        removed += [node for node, _ in tail]
    if not replaced:
        return model, 0
    _splice(model, replaced, removed, new_inits)
    return model, len(replaced)


def _graph_index(graph: Any) -> tuple[dict[str, Any], Callable[[str, Any], bool]]:
    """The node producing each tensor, and ``only_used_by(tensor, node)``: ``node`` is the
    tensor's one consumer and it is not a graph output (so a rewrite may drop it)."""
    producer = {o: n for n in graph.node for o in n.output}
    consumers: dict[str, list[Any]] = {}
    for n in graph.node:
        for i in n.input:
            consumers.setdefault(i, []).append(n)
    outputs = {o.name for o in graph.output}

    def only_used_by(tensor: str, node: Any) -> bool:
        return tensor not in outputs and [id(c) for c in consumers.get(tensor, [])] == [id(node)]

    return producer, only_used_by


def _constants(graph: Any) -> dict[str, np.ndarray]:
    """Initializers and Constant nodes' values, by tensor name."""
    from onnx import numpy_helper

    values = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    for n in graph.node:
        if n.op_type == "Constant" and n.attribute and n.attribute[0].name == "value":
            values[n.output[0]] = numpy_helper.to_array(n.attribute[0].t)
    return values


def _ranks(model: Any) -> dict[str, int]:
    """Rank of every tensor shape inference can tell (dimensions may stay symbolic)."""
    from onnx import shape_inference

    inferred = shape_inference.infer_shapes(model).graph
    ranks = {}
    for info in list(inferred.input) + list(inferred.value_info) + list(inferred.output):
        t = info.type.tensor_type
        if t.HasField("shape"):
            ranks[info.name] = len(t.shape.dim)
    for init in model.graph.initializer:
        ranks[init.name] = len(init.dims)
    return ranks


def _drop_dead_nodes(graph: Any) -> None:
    """Remove nodes none of whose outputs is used (last to first, so chains go too)."""
    needed = {o.name for o in graph.output}
    keep = []
    for n in reversed(graph.node):
        if any(o in needed for o in n.output):
            keep.append(n)
            needed.update(n.input)
    del graph.node[:]
    graph.node.extend(reversed(keep))


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
    """Rewrite ``src`` into ``dst`` (may be the same path): the global max-pool on a transposed
    GEMM, then every max-pool ahead of its monotone tail (``moved``); float weights under 1e-20
    set to 0 (``flushed``, of which ``denormal``: see fpcc_ros.weight_flush). With ``check``, run both on sample
    blocks and refuse (ValueError, nothing written) if any output differs by more than
    ``tolerance``. Returns what was done and the largest difference seen."""
    import onnx

    src, dst = Path(src), Path(dst)
    model = onnx.load(str(src))
    model, fused, generic = rewrite_global_max(model)
    model, moved = move_max_before_monotone(model)
    model, sliced = add_global_stride(model)
    onnx.checker.check_model(model)
    data, flush = flush_tiny_weights(model.SerializeToString())
    worst = 0.0
    if check and (fused or generic or moved or sliced or flush.flushed):
        worst = compare_models(src.read_bytes(), data, card_path=src.with_suffix(".json"))
        if not worst <= tolerance:
            raise ValueError(f"{src}: the rewritten graph differs from the original by {worst:.2e} "
                             f"(> {tolerance:.0e}); not written")
    tmp = dst.with_name(dst.name + ".tmp")
    tmp.write_bytes(data)
    tmp.replace(dst)
    return {"fused": fused, "generic": generic, "moved": moved, "strided": sliced,
            "flushed": flush.flushed, "denormal": flush.denormal, "max_abs_diff": worst}


def sample_blocks(k: int, part_radius: float, sizes=(300, 2500), batch: int = 2,
                  seed: int = 0, normals: bool = False) -> list[dict[str, np.ndarray]]:
    """Network inputs from random points on a few part-sized spheres (real features and kNN;
    with ``normals`` the surface-normal columns too)."""
    from fpcc_ros.features import block_inputs

    rng = np.random.default_rng(seed)
    feeds = []
    for n in sizes:
        feats, knns = [], []
        for _ in range(batch):
            centers = rng.uniform(0, 4 * part_radius, size=(6, 3))
            dirs = rng.normal(size=(n, 3))
            xyz = centers[rng.integers(0, 6, n)] + part_radius * dirs / np.linalg.norm(
                dirs, axis=1, keepdims=True)
            features, knn = block_inputs(xyz, part_radius, k, normals)
            feats.append(features)
            knns.append(knn)
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
    options.log_severity_level = 3   # not the warning that global_stride is not a constant
    a = ort.InferenceSession(original, options, providers=["CPUExecutionProvider"])
    b = ort.InferenceSession(rewritten, options, providers=["CPUExecutionProvider"])
    shapes = {i.name: i.shape for i in a.get_inputs()}
    knn_width = shapes.get("knn", [None])[-1]
    if isinstance(knn_width, int):  # the graph itself says k (no card yet at export time)
        k = knn_width
    normals = takes_normals(shapes.get("features", [None])[-1])
    worst = 0.0
    for feed in sample_blocks(k, radius, normals=normals):
        for x, y in zip(a.run(None, feed), b.run(None, feed)):
            worst = max(worst, float(np.abs(x - y).max()))
    return worst
