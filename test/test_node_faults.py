"""Faults: bad models and parameters at start-up, an exception in one frame, invalid parameter
updates, a model swap under load, SIGINT/SIGTERM, warning throttling.

Start-up and signals run the node in its own process (that is where exit codes live); frame and
parameter faults construct SegmenterNode in this process with a fresh rclpy context, talking to it
over DDS through scripts/fuzz_node.py's Collector.
"""
import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

import cloud_factory as cf
from conftest import REPO, TEST_DATA
from fpcc_ros.node_shutdown import spin_until_stopped
from fpcc_ros.replay import NodeProcess, isolated_ros_env

sys.path.insert(0, str(REPO / "scripts"))
from fuzz_node import Collector, parse_totals  # noqa: E402

pytestmark = pytest.mark.ros
TINY = TEST_DATA / "tiny_fpcc.onnx"


# ----------------------------------------------------------------------------- model files

def _card() -> dict:
    return json.loads(TINY.with_suffix(".json").read_text())


def _model(dir_: Path, stem: str, onnx: bytes | None, **card_changes) -> Path:
    path = dir_ / f"{stem}.onnx"
    if onnx is not None:
        path.write_bytes(onnx)
    if card_changes.get("_no_card"):
        return path
    card = _card()
    card.update({k: v for k, v in card_changes.items() if not k.startswith("_")})
    path.with_suffix(".json").write_text(json.dumps(card))
    return path


def _onnx_graph(nodes, inputs, outputs) -> bytes:
    from onnx import helper
    graph = helper.make_graph(nodes, "g", inputs, outputs)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)],
                             ir_version=8).SerializeToString()


def _identity_onnx() -> bytes:
    from onnx import TensorProto, helper
    return _onnx_graph([helper.make_node("Identity", ["x"], ["y"])],
                       [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3])],
                       [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 3])])


def _fpcc_named_wrong_width_onnx() -> bytes:
    """FPCC's input/output names with symbolic dims, but embedding = [features, knn] (6 + k
    wide, not 128): passes a shape-only signature check, disagrees with any card when run."""
    from onnx import TensorProto, helper
    nodes = [helper.make_node("Cast", ["knn"], ["knnf"], to=TensorProto.FLOAT),
             helper.make_node("Concat", ["features", "knnf"], ["embedding"], axis=2),
             helper.make_node("ReduceMax", ["features"], ["mx"], axes=[2], keepdims=0),
             helper.make_node("Sigmoid", ["mx"], ["center_score"])]
    return _onnx_graph(
        nodes,
        [helper.make_tensor_value_info("features", TensorProto.FLOAT, ["b", "n", 6]),
         helper.make_tensor_value_info("knn", TensorProto.INT64, ["b", "n", "k"])],
        [helper.make_tensor_value_info("embedding", TensorProto.FLOAT, ["b", "n", "e"]),
         helper.make_tensor_value_info("center_score", TensorProto.FLOAT, ["b", "n"])])


def test_bad_model_or_parameters_stop_start_up_with_a_message_that_says_what_to_fix(tmp_path):
    raw = TINY.read_bytes()
    cases = {  # name -> (ros args, phrases the message must contain)
        "missing file": (["-p", f"model:={tmp_path / 'nope.onnx'}"],
                         ["not found", "set the 'model' parameter"]),
        "truncated onnx": (["-p", f"model:={_model(tmp_path, 'trunc', raw[:len(raw) // 2])}"],
                           ["not a loadable ONNX model", "fpcc export"]),
        "not an FPCC model": (["-p", f"model:={_model(tmp_path, 'ident', _identity_onnx())}"],
                              ["not an FPCC-Net matching its card", "inputs are ['x']"]),
        "card k disagrees": (["-p", f"model:={_model(tmp_path, 'k8', raw, k=8)}"],
                             ["the card says [batch, points, 8]", "fpcc export"]),
        "card disagrees when run": (
            ["-p", f"model:={_model(tmp_path, 'wide', _fpcc_named_wrong_width_onnx())}"],
            ["does not behave as its card", "'embedding' came out [1, 64, 22]"]),
        "card missing": (["-p", f"model:={_model(tmp_path, 'nocard', raw, _no_card=True)}"],
                         ["model card", "not found"]),
        "negative part_radius": (["-p", f"model:={TINY}", "-p", "part_radius:=-0.01"],
                                 ["part_radius", "out of range"]),
        "roi_min above roi_max": (["-p", f"model:={TINY}", "-p", "roi_min:=[1.0,1.0,1.0]",
                                   "-p", "roi_max:=[0.0,2.0,2.0]"],
                                  ["roi_min=[1.0, 1.0, 1.0] must be below roi_max"]),
    }
    env = isolated_ros_env()
    env["PYTHONPATH"] = str(REPO)
    procs = {name: subprocess.Popen([sys.executable, "-m", "fpcc_ros.segmenter", "--ros-args",
                                     *args], env=env, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True)
             for name, (args, _) in cases.items()}
    for name, proc in procs.items():
        out, _ = proc.communicate(timeout=120)
        assert proc.returncode == 1, f"{name}: exit {proc.returncode}\n{out}"
        assert "cannot start:" in out and "Traceback" not in out, f"{name}:\n{out}"
        for phrase in cases[name][1]:
            assert phrase in out, f"{name}: {phrase!r} not in\n{out}"


# ----------------------------------------------------------------------------- in-process node

class LiveNode:
    """SegmenterNode in this process (fresh context) plus a Collector talking to it over DDS."""

    def __init__(self, **params):
        from fpcc_ros.segmenter import SegmenterNode
        self.context = Context()
        rclpy.init(context=self.context)
        overrides = [Parameter(k, value=v) for k, v in {"model": str(TINY), "min_points": 5,
                                                         **params}.items()]
        self.node = SegmenterNode(context=self.context, parameter_overrides=overrides)
        self.warnings: list[str] = []
        logger = self.node._throttle._logger
        recorder = self

        class _Recorder:  # keeps what the node warns about, and still logs it
            def warning(self, text):
                recorder.warnings.append(text)
                logger.warning(text)
        self.node._throttle._logger = _Recorder()
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=spin_until_stopped, daemon=True,
                                       args=(self.executor, self._stop.is_set))
        self.thread.start()
        self.client = Collector(self.context)
        assert self.client.wait_connected(30)
        self.stamp = 0

    def send(self, msg):
        self.stamp += 1_000_000
        cf.set_stamp(msg, self.stamp)
        self.client.pub.publish(msg)
        return self.stamp

    def segment(self, msg, timeout=30.0):
        """Send and wait for the three outputs; their labels (None if nothing came)."""
        out = self.client.take(self.send(msg), timeout)
        return None if out is None else cf.check_output(msg, out, cf.Kind("x", True, None), roi=None)

    def stop_spinning(self):
        """The executor thread returns (node.shutdown()'s precondition, as in main())."""
        self._stop.set()
        self.thread.join(timeout=10)

    def close(self):
        self.client.close()
        self.stop_spinning()
        self.node.shutdown()
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture
def live():
    node = LiveNode()
    yield node
    node.close()


def _wait(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def scene(seed=1):
    return cf.make_cloud(cf.scene_xyz(30, 40, seed=seed, spheres=5), "xyz32")


def test_an_exception_in_one_frame_is_logged_and_the_next_frame_is_processed(live):
    reference = live.segment(scene())
    assert reference is not None
    pipeline = live.node._pipeline
    real = pipeline.segment
    calls = []

    def segment_failing_once(xyz, image_shape=None):
        calls.append(len(xyz))
        if len(calls) == 1:
            raise RuntimeError("injected fault in frame 1")
        return real(xyz, image_shape)

    pipeline.segment = segment_failing_once
    assert live.segment(scene(), timeout=3.0) is None          # the failing frame: no output
    assert live.node.stats.failed == 1
    assert any("frame failed (RuntimeError: injected fault in frame 1)" in w
               for w in live.warnings)
    np.testing.assert_array_equal(live.segment(scene()), reference)   # the next one: correct
    assert len(calls) == 2


def test_an_exception_while_publishing_does_not_stop_the_worker(live):
    reference = live.segment(scene())
    pub = live.node._pub_instances
    real, calls = pub.publish, []

    def publish_failing_once(msg):
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError("injected publish fault")
        real(msg)

    pub.publish = publish_failing_once
    live.send(scene())
    assert _wait(lambda: live.node.stats.failed == 1)
    assert any("injected publish fault" in w for w in live.warnings)
    np.testing.assert_array_equal(live.segment(scene()), reference)
    assert live.node._worker.is_alive()


def _set(node, **values):
    return node.set_parameters([Parameter(k, value=v) for k, v in values.items()])[0]


def test_invalid_parameter_updates_are_rejected_with_a_reason_and_the_old_value_stays(live, tmp_path):
    node = live.node
    before = live.segment(scene(2))
    model_before = node._pipeline.model

    result = _set(node, part_radius=-0.01)
    assert not result.successful and "part_radius" in result.reason and "range" in result.reason
    assert node.get_parameter("part_radius").value == pytest.approx(node._pipeline.config.part_radius)
    assert node.get_parameter("part_radius").value > 0

    result = _set(node, voxel_size=-0.5)
    assert not result.successful and "voxel_size=-0.5 is invalid" in result.reason
    assert node.get_parameter("voxel_size").value == -1.0

    result = node.set_parameters_atomically([Parameter("roi_min", value=[-5.0, -5.0, -5.0]),
                                             Parameter("roi_max", value=[5.0, 5.0, 5.0])])
    assert result.successful, result.reason
    result = _set(node, roi_min=[6.0, 0.0, 0.0])
    assert not result.successful and "must be below roi_max" in result.reason
    assert list(node.get_parameter("roi_min").value) == [-5.0, -5.0, -5.0]
    assert node._pipeline.config.roi_min == (-5.0, -5.0, -5.0)

    for bad_model, phrase in [(tmp_path / "missing.onnx", "not found"),
                              (_model(tmp_path, "half", TINY.read_bytes()[:5000]),
                               "not a loadable ONNX model")]:
        result = _set(node, model=str(bad_model))
        assert not result.successful and phrase in result.reason
        assert node.get_parameter("model").value == str(TINY)
        assert node._pipeline.model is model_before

    prototype_before = node._pipeline.config.center_prototype
    result = _set(node, center_prototype=5.0)
    assert not result.successful and "center_prototype" in result.reason
    assert node._pipeline.config.center_prototype == prototype_before

    # the node still runs with the old settings (the accepted ROI holds the whole scene)
    np.testing.assert_array_equal(live.segment(scene(2)), before)
    assert node.stats.failed == 0

    # the new clustering settings apply at runtime
    result = _set(node, center_prototype=0.5, center_merge=0.7)
    assert result.successful, result.reason
    assert (node._pipeline.config.center_prototype, node._pipeline.config.center_merge) == \
        (0.5, 0.7)


def test_a_valid_model_change_swaps_models_between_frames(live, tmp_path):
    """Clouds stream in while the model changes: every output is entirely the old model's or
    entirely the new one's, old ones first. The new model is the tiny network with a card
    asking for a coarser voxel grid, so its labels differ."""
    other = _model(tmp_path, "tiny_coarse", TINY.read_bytes(), name="tiny_coarse",
                   voxel_factor=0.3)
    cloud = cf.make_cloud(cf.scene_xyz(60, 80, seed=0, spheres=8), "xyz32")
    old = live.segment(cloud)
    assert old.any(), "precondition: the old model finds instances in this cloud"
    stamps, stop = [], threading.Event()

    def stream():
        while not stop.is_set():
            stamps.append(live.send(cloud))
            time.sleep(0.03)

    sender = threading.Thread(target=stream)
    sender.start()
    time.sleep(1.0)
    result = _set(live.node, model=str(other))
    time.sleep(1.0)
    stop.set()
    sender.join()
    assert result.successful, result.reason
    assert live.node._pipeline.model.card.name == "tiny_coarse"
    new = live.segment(cloud)
    assert not np.array_equal(old, new), "precondition: the two models must disagree"
    time.sleep(0.5)
    seen = []
    for stamp in stamps:
        out = live.client.take(stamp, timeout=0.0)
        if out:
            labels = cf.decode_segmented(out["segmented_points"])["label"]
            seen.append("old" if np.array_equal(labels, old) else
                        "new" if np.array_equal(labels, new) else "mixed")
    assert "mixed" not in seen
    assert seen.count("old") >= 1 and seen.count("new") >= 1, seen  # both models answered
    assert seen == sorted(seen, key=lambda s: s == "new"), seen   # no old after the first new


def test_warnings_are_throttled_per_problem_and_name_it(live):
    base = scene()
    for i in range(30):   # 30 truncated clouds of 30 different lengths
        live.node._process(cf.clone(base, data=bytes(base.data)[:100 + i]), time.perf_counter())
    live.node._process(cf.clone(base, fields=[f for f in cf.fields_of(base) if f[0] != "y"]),
                       time.perf_counter())
    fields = [(f"f{i}_" + "n" * 40, 0, 7, 1) for i in range(2000)]     # a hostile header
    live.node._process(cf.clone(base, fields=fields), time.perf_counter())
    assert live.node.stats.invalid == 32
    assert len(live.warnings) == 3, live.warnings
    assert "the message is truncated" in live.warnings[0]
    assert "no field 'y'" in live.warnings[1]
    assert "no field 'x'" in live.warnings[2] and len(live.warnings[2]) < 800


# ----------------------------------------------------------------------------- signals

@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signals_shut_down_cleanly_even_with_a_frame_in_flight(tmp_path, sig):
    context = Context()
    rclpy.init(context=context)
    try:
        with NodeProcess(["-p", f"model:={TINY}"], log_path=tmp_path / "node.log") as node:
            client = Collector(context, keep_outputs=False)
            try:
                assert client.wait_connected(60), node.log()
                client.pub.publish(cf.set_stamp(scene(), 1))
                assert client.take(1, 60) is not None, node.log()
                big = cf.two_million_points()
                for stamp in (2, 3, 4):   # keeps the worker busy: the signal lands mid-frame
                    client.pub.publish(cf.set_stamp(big, stamp))
                    time.sleep(0.5)
                started = time.monotonic()
                code = node.stop(sig, timeout=20)
                took = time.monotonic() - started
            finally:
                client.close()
    finally:
        rclpy.try_shutdown(context=context)
    log = node.log()
    assert code == 0, log
    assert took < 15.0  # the worker gets 5 s to finish its frame; margin for a loaded machine
    for bad in ("Traceback", "Exception in thread", "terminate called", "Failed to publish"):
        assert bad not in log, log
    totals = parse_totals(log)
    assert totals["received"] >= 1 and totals["published"] >= 1, log
    in_flight = 1 if "still being processed" in log else 0   # not counted in the totals
    assert totals["received"] == in_flight + sum(totals[k] for k in (
        "published", "invalid", "failed", "dropped_stale", "skipped_old",
        "dropped_at_shutdown")), log


def test_a_model_given_at_start_up_brings_its_own_cards_settings(tmp_path):
    """A per-part model's calibration (θ, γ, gate, merge, part_radius) applies without repeating
    it as parameters; a parameter given explicitly still wins."""
    from fpcc_ros.segmenter import SegmenterNode

    custom = _model(tmp_path, "my_part", TINY.read_bytes(), part_radius=0.0421,
                    score_threshold=0.37, screening_factor=0.45, feature_gate=1.7,
                    center_merge=0.6, center_prototype=0.7)
    context = Context()
    rclpy.init(context=context)
    try:
        node = SegmenterNode(context=context, parameter_overrides=[
            Parameter("model", value=str(custom)), Parameter("feature_gate", value=2.5)])
        try:
            values = {name: node.get_parameter(name).value for name in
                      ("part_radius", "score_threshold", "screening_factor", "feature_gate",
                       "center_merge", "center_prototype")}
            cfg = node._pipeline.config
        finally:
            node.stop_worker()
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    assert values == {"part_radius": 0.0421, "score_threshold": 0.37, "screening_factor": 0.45,
                      "feature_gate": 2.5, "center_merge": 0.6, "center_prototype": 0.7}
    assert (cfg.part_radius, cfg.screening_factor, cfg.feature_gate, cfg.center_merge,
            cfg.center_prototype) == (0.0421, 0.45, 2.5, 0.6, 0.7)


def test_view_axis_is_a_checked_parameter_and_each_frames_view_is_noted(live):
    node = live.node
    result = _set(node, view_axis="down")
    assert not result.successful and "view_axis='down' is invalid" in result.reason
    assert "-z for a z-up world frame" in result.reason
    assert node.get_parameter("view_axis").value == "auto"

    # auto: a camera's cloud is shown as it is, a z-up world frame's turned over
    xyz = cf.scene_xyz(30, 40, seed=3, spheres=5)
    world = np.stack([xyz[..., 0], -xyz[..., 1], 0.8 - xyz[..., 2]], axis=-1)  # floor at z = 0
    assert live.segment(cf.make_cloud(xyz, "xyz32", frame_id="cam_optical")) is not None
    assert live.segment(cf.make_cloud(world.astype(np.float32), "xyz32",
                                      frame_id="world")) is not None
    assert node._view_axes == {"cam_optical": "+z", "world": "-z"}

    assert _set(node, view_axis="+z").successful
    assert node._pipeline.config.view_axis == "+z"
    assert live.segment(cf.make_cloud(world.astype(np.float32), "xyz32",
                                      frame_id="world")) is not None
    assert node._view_axes["world"] == "+z"


def test_global_stride_is_a_ranged_parameter_that_needs_a_model_taking_it(live, tmp_path):
    """The tiny model's graph has no global_stride input: a stride is refused with the fix
    named and the old value stays; the same net through scripts/optimize_onnx.py takes it at
    run time (and its card's value is the start-up default)."""
    from fpcc_ros.graph_rewrite import optimize_file
    from fpcc_ros.model_card import MAX_GLOBAL_STRIDE

    node = live.node
    desc = node.describe_parameter("global_stride")
    assert (desc.integer_range[0].from_value, desc.integer_range[0].to_value) == \
        (1, MAX_GLOBAL_STRIDE)
    assert node.get_parameter("global_stride").value == 1
    result = _set(node, global_stride=2)
    assert not result.successful and "optimize_onnx" in result.reason
    assert node.get_parameter("global_stride").value == 1
    fast = _model(tmp_path, "fast", None, global_stride=3)
    optimize_file(TINY, fast)
    assert _set(node, model=str(fast), global_stride=3).successful
    assert node._pipeline.config.global_stride == 3
    assert live.segment(scene(4)) is not None
