"""`/diagnostics`: the status computation from counters (no ROS graph), then the live node over
DDS: the values follow what was sent, stale drops turn the level WARN, a failing frame ERROR.

Expected values are worked out here from what each test sends (or by hand for the pure part),
never read back from the node.
"""
import json
import math
import sys
import threading

import pytest
import rclpy
from rclpy.context import Context

import cloud_factory as cf
from conftest import REPO, TEST_DATA
from diagnostics_listener import DiagnosticsListener
from fpcc_ros.node_diagnostics import (ERROR, OK, WARN, CounterWindow, ModelInfo, Reading,
                                       Thresholds, Window, evaluate, quantiles_ms)
from fpcc_ros.replay import NodeProcess
from test_node_faults import LiveNode, _set, _wait, scene

sys.path.insert(0, str(REPO / "scripts"))
from fuzz_node import Collector, parse_totals  # noqa: E402

TINY = TEST_DATA / "tiny_fpcc.onnx"
ZERO = dict(received=0, published=0, dropped_stale=0, skipped_old=0, invalid=0, failed=0)


# ----------------------------------------------------------------------------- pure status

def _counters(**kw):
    return {**ZERO, **kw}


def test_the_window_differences_the_counters_of_its_last_seconds():
    w = CounterWindow(start=0.0)
    latencies = []
    for t in range(1, 11):           # 2 clouds in and 1 frame out per second
        latencies.append(float(t))
        win = w.update(float(t), _counters(received=2 * t, published=t), latencies, window_s=3.0)
    # base = the reading at t = 7 (the last at or before 10 - 3): 20 - 14 clouds, 10 - 7 frames
    assert win.seconds == 3.0
    assert win.deltas["received"] == 6 and win.deltas["published"] == 3
    assert win.input_rate_hz == 2.0 and win.output_rate_hz == 1.0
    assert list(win.latencies_ms) == [8.0, 9.0, 10.0]     # only the window's frames
    assert win.since_input_s == 0.0
    w.update(11.0, _counters(received=20, published=10), latencies, window_s=3.0)
    win = w.update(12.5, _counters(received=20, published=10), latencies, window_s=3.0)
    assert win.since_input_s == 2.5                          # last new cloud seen at t = 10
    # base = the reading at t = 9 (the last at or before 9.5): 20 - 18 clouds, 10 - 9 frames
    assert win.deltas["received"] == 2 and list(win.latencies_ms) == [10.0]
    # not taking frames (a managed node, inactive): the input clock does not run
    win = w.update(20.0, _counters(received=20, published=10), latencies, 3.0, taking_frames=False)
    assert win.since_input_s == 0.0


def test_the_first_window_counts_from_start_up():
    win = CounterWindow(start=100.0).update(101.5, _counters(received=3, published=2),
                                            [40.0, 50.0], window_s=5.0)
    assert win.seconds == 1.5 and win.deltas["received"] == 3
    assert list(win.latencies_ms) == [40.0, 50.0]


def test_latency_median_and_p90():
    # by hand: median of 10..100 = (50 + 60) / 2; p90 at rank 0.9 * 9 = 8.1 -> 90 + 0.1 * 10
    assert quantiles_ms([float(v) for v in range(10, 101, 10)]) == (55.0, 91.0)
    assert all(math.isnan(v) for v in quantiles_ms([]))


def _reading(counters=ZERO, **kw):
    kw.setdefault("thresholds", Thresholds(window_s=5.0, stale_warn_fraction=0.5,
                                           input_timeout_s=10.0))
    return Reading(counters=counters, latencies_ms=[], last_instances=3, input_topic="/points",
                   **kw)


def _window(seconds=5.0, since_input_s=0.0, latencies=(), **deltas):
    return Window(seconds=seconds, deltas=_counters(**deltas), latencies_ms=list(latencies),
                  since_input_s=since_input_s)


def test_levels_follow_the_rules():
    def level(window, **kw):
        return evaluate(_reading(**kw), window)

    ok = level(_window(received=4, published=4))
    assert (ok.level, ok.message) == (OK, "ok: 4 frames out in the last 5 s")
    assert level(_window()).message == "ok: waiting for clouds on /points"

    s = level(_window(received=5, published=2, dropped_stale=3))           # 3/5 > 0.5
    assert s.level == WARN
    assert s.message == "falling behind the camera: 3 of 5 clouds in the last 5 s dropped as stale"
    assert level(_window(received=5, published=1, dropped_stale=2, skipped_old=2)).level == WARN
    assert level(_window(received=4, published=2, dropped_stale=2)).level == OK   # half: not most
    assert level(_window(received=10, published=9, dropped_stale=1),
                 thresholds=Thresholds(5.0, 0.0, 10.0)).level == WARN              # 0 = any

    s = level(_window(since_input_s=12.0))
    assert (s.level, s.message) == (WARN, "no input on /points for 12 s")
    assert level(_window(since_input_s=12.0), thresholds=Thresholds(5.0, 0.5, 0.0)).level == OK

    s = level(_window(received=1, invalid=1), last_invalid="no field 'y'")
    assert (s.level, s.message) == (WARN, "1 malformed cloud in the last 5 s (last: no field 'y')")

    s = level(_window(received=6, published=1, failed=1, dropped_stale=4),
              last_failure="RuntimeError: boom")
    assert s.level == ERROR
    assert s.message == ("1 frame failed in the last 5 s (last: RuntimeError: boom); falling "
                         "behind the camera: 4 of 6 clouds in the last 5 s dropped as stale")


def test_a_managed_node_that_is_not_active_reports_its_state_not_its_frames():
    model = ModelInfo("/m/tiny.onnx", "tiny", "/m/tiny.json", ("CPUExecutionProvider",))
    s = evaluate(_reading(state="inactive", model=model), _window(since_input_s=99.0, failed=1))
    assert (s.level, s.message) == (OK, "inactive: model loaded, not taking frames")
    s = evaluate(_reading(state="unconfigured", state_error="configure failed: x not found"),
                 _window())
    assert (s.level, s.message) == (ERROR, "configure failed: x not found")


def test_key_values_name_totals_window_and_model():
    model = ModelInfo("/m/tiny.onnx", "tiny", "/m/tiny.json", ("CUDAExecutionProvider",
                                                                 "CPUExecutionProvider"))
    reading = _reading(_counters(received=9, published=5, dropped_stale=1, skipped_old=0,
                                 invalid=2, failed=1),
                       model=model, view_axes={"world": "-z", "cam": "+z"},
                       last_invalid="x" * 1000)
    values = dict(evaluate(reading, _window(seconds=4.0, received=8, published=4,
                                            latencies=[10.0, 20.0, 30.0, 40.0])).values)
    assert {k: values[f"frames {k}"] for k in ("received", "published", "dropped stale",
                                              "invalid", "failed")} == \
        {"received": "9", "published": "5", "dropped stale": "1", "invalid": "2", "failed": "1"}
    # median of 10..40 = 25; p90 at rank 2.7 -> 30 + 0.7 * 10
    assert (values["latency median (ms)"], values["latency p90 (ms)"]) == ("25.0", "37.0")
    assert (values["input rate (Hz)"], values["output rate (Hz)"]) == ("2.00", "1.00")
    assert values["instances in last frame"] == "3"
    assert (values["model name"], values["model card"]) == ("tiny", "/m/tiny.json")
    assert values["execution providers"] == "CUDAExecutionProvider, CPUExecutionProvider"
    assert values["view axis"] == "+z (frame 'cam'), -z (frame 'world'); setting auto"
    assert len(values["last malformed input"]) < 400       # a hostile header stays short


# ----------------------------------------------------------------------------- live node

@pytest.mark.ros
def test_diagnostics_count_the_clouds_sent_to_the_node_process(tmp_path):
    """5 valid and 2 malformed clouds: published 5, invalid 2, the model and view named; then
    the input stops and the level turns WARN."""
    card_name = json.loads(TINY.with_suffix(".json").read_text())["name"]
    base = scene()
    truncated = cf.clone(base, data=bytes(base.data)[:100])
    no_y = cf.clone(base, fields=[f for f in cf.fields_of(base) if f[0] != "y"])
    context = Context()
    rclpy.init(context=context)
    try:
        with NodeProcess(["-p", f"model:={TINY}", "-p", "min_points:=5",
                          "-p", "diagnostics_window:=600.0", "-p", "input_timeout:=4.0"],
                         log_path=tmp_path / "node.log") as node:
            client, diag = Collector(context), DiagnosticsListener(context)
            try:
                assert client.wait_connected(60), node.log()
                assert diag.wait_for(lambda s: True, 60), node.log()
                stamp, invalid_sent, last_poses = 0, 0, None
                for kind in ("valid", "valid", "truncated", "valid", "no_y", "valid", "valid"):
                    stamp += 1
                    if kind == "valid":
                        client.pub.publish(cf.set_stamp(scene(stamp), stamp))
                        out = client.take(stamp, 60)
                        assert out is not None, node.log()
                        last_poses = len(out["instances"].poses)
                    else:   # wait until it was examined, so the next cloud cannot replace it
                        client.pub.publish(cf.set_stamp(truncated if kind == "truncated"
                                                        else no_y, stamp))
                        invalid_sent += 1
                        assert diag.wait_for(lambda s: s.count("invalid") == invalid_sent,
                                             60), (diag.last(), node.log())
                seen = diag.wait_for(lambda s: s.count("published") == 5, 60)
                assert seen is not None, (diag.last(), node.log())
                after = len(diag.seen)
                stopped = diag.wait_for(lambda s: "no input" in s.message, 60, after=after)
            finally:
                diag.close()
                client.close()
            code = node.stop()
    finally:
        rclpy.try_shutdown(context=context)
    assert {k: seen.count(k) for k in ("received", "published", "invalid", "failed",
                                       "dropped stale", "skipped old")} == \
        {"received": 7, "published": 5, "invalid": 2, "failed": 0, "dropped stale": 0,
         "skipped old": 0}
    v = seen.values
    assert seen.level == "WARN" and "2 malformed clouds" in seen.message   # in the window
    assert "no field 'y'" in v["last malformed input"]
    assert v["last failure"] == ""
    assert int(v["instances in last frame"]) == last_poses
    assert (v["model"], v["model name"]) == (str(TINY), card_name)
    assert v["model card"] == str(TINY.with_suffix(".json"))
    assert v["execution providers"] == "CPUExecutionProvider"
    assert v["view axis"] == "+z (frame 'camera'); setting auto"     # a camera-frame scene
    median, p90 = float(v["latency median (ms)"]), float(v["latency p90 (ms)"])
    assert 0 < median <= p90
    assert float(v["input rate (Hz)"]) > 0
    assert seen.hardware_id == "fpcc_segmenter"
    assert stopped is not None and stopped.level == "WARN", diag.last()
    assert stopped.message.startswith("no input on /points for ")
    assert code == 0
    assert parse_totals(node.log())["received"] == 7


def _before_segment(live, before):
    """The node's pipeline calls ``before()`` ahead of every segment() (which may raise)."""
    real = live.node._pipeline.segment

    def wrapped(xyz, image_shape=None):
        before()
        return real(xyz, image_shape)

    live.node._pipeline.segment = wrapped


@pytest.mark.ros
def test_stale_drops_turn_the_level_warn_and_the_threshold_is_a_runtime_parameter():
    """The worker is held on cloud 1 while clouds 2..6 arrive: each replaces the one waiting,
    so 4 are dropped as stale (2..5), 6 waits; released, 1 and 6 come out."""
    live = LiveNode(diagnostics_window=600.0, input_timeout=0.0)
    diag = DiagnosticsListener(live.context)
    try:
        gate = threading.Event()
        _before_segment(live, lambda: gate.wait(120))   # the worker waits inside cloud 1
        for i in range(6):
            live.send(scene(i))   # one at a time: each must reach the node before the next
            assert _wait(lambda: live.node.stats.received == i + 1, timeout=60)
        seen = diag.wait_for(lambda s: s.count("received") == 6, 60)
        assert seen is not None, diag.last()
        assert (seen.count("dropped stale"), seen.count("published")) == (4, 0)
        assert seen.level == "WARN"
        assert seen.message.startswith("falling behind the camera: 4 of 6 clouds in the last ")
        gate.set()
        seen = diag.wait_for(lambda s: s.count("published") == 2, 60)
        assert seen is not None, diag.last()
        assert (seen.count("dropped stale"), seen.level) == (4, "WARN")   # 4/6 still > 0.5

        assert not _set(live.node, stale_warn_fraction=1.5).successful   # out of its range
        assert not _set(live.node, diagnostics_window=0.0).successful
        assert _set(live.node, stale_warn_fraction=0.7).successful        # 4/6 < 0.7
        after = len(diag.seen)
        seen = diag.wait_for(lambda s: True, 30, after=after + 1)  # one tick after the change
        assert seen is not None and seen.level == "OK", seen
    finally:
        diag.close()
        live.close()


@pytest.mark.ros
def test_a_failing_frame_turns_the_level_error_until_it_leaves_the_window():
    live = LiveNode(diagnostics_window=2.0, input_timeout=0.0)
    diag = DiagnosticsListener(live.context)
    try:
        faults = [RuntimeError("injected fault in frame 1")]

        def fail_once():
            if faults:
                raise faults.pop()

        _before_segment(live, fail_once)
        live.send(scene())
        seen = diag.wait_for(lambda s: s.count("failed") == 1, 60)
        assert seen is not None, diag.last()
        assert seen.level == "ERROR"
        assert "1 frame failed" in seen.message
        assert "RuntimeError: injected fault in frame 1" in seen.message
        assert seen.values["last failure"] == "RuntimeError: injected fault in frame 1"
        assert live.segment(scene()) is not None      # the next frame is fine ...
        seen = diag.wait_for(lambda s: s.level == "OK", 60, after=len(diag.seen))
        assert seen is not None, diag.last()           # ... and the error ages out
        assert (seen.count("failed"), seen.count("published")) == (1, 1)
    finally:
        diag.close()
        live.close()
