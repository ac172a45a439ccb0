"""Stopping the node (issue 26): SIGINT/SIGTERM only set a flag, the teardown runs in order.

The short soak is scripts/soak_shutdown.py's: fresh node processes stopped at the moments that
tore frames or crashed before (mid-frame, mid-publish, right after start), both signals; the
full run (200 cycles, idle and streaming too) is the script's. The in-process tests pin the
worker's side of node.shutdown(): once it gives up on a frame, that frame is neither published
nor logged through the node being destroyed.
"""
import os
import signal
import sys
import threading
import time

import pytest
from rclpy.exceptions import InvalidHandle

from conftest import REPO, TEST_DATA
from fpcc_ros.node_shutdown import StopRequest
from fpcc_ros.replay import NodeProcess

sys.path.insert(0, str(REPO / "scripts"))
from fuzz_node import parse_totals  # noqa: E402
from soak_shutdown import run_soak  # noqa: E402
from test_node_faults import LiveNode, scene  # noqa: E402

pytestmark = pytest.mark.ros


def test_a_stop_signal_only_sets_the_flag_and_a_second_one_is_counted():
    before = signal.getsignal(signal.SIGTERM)
    stop = StopRequest().install()
    try:
        assert not stop.requested
        os.kill(os.getpid(), signal.SIGTERM)   # the default action would end this process
        deadline = time.monotonic() + 5
        while not stop.requested and time.monotonic() < deadline:
            time.sleep(0.01)
        assert stop.requested and stop.name == "SIGTERM"
        os.kill(os.getpid(), signal.SIGINT)    # no KeyboardInterrupt either
        time.sleep(0.05)
        assert stop.signum == signal.SIGTERM and stop.repeats == 1
    finally:
        stop.restore()
    assert signal.getsignal(signal.SIGTERM) is before


def test_short_soak_both_signals_mid_frame_mid_publish_and_right_after_start():
    report = run_soak(cycles=6, seed=1, moments=("start", "mid_frame", "mid_publish"),
                      core_dumps=False)
    assert len(report.cycles) == 6
    assert report.ok, report.table()
    assert all(c.exit_code == 0 and c.totals for c in report.cycles)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_while_the_node_is_being_built_still_ends_in_a_clean_exit(tmp_path, sig):
    """Sent as soon as the model is loaded (the node is still creating its endpoints): before,
    rclpy's handler shut the context down under the constructor (RCLError, exit 1)."""
    log = tmp_path / "node.log"
    with NodeProcess(["-p", f"model:={TEST_DATA / 'tiny_fpcc.onnx'}"], log_path=log) as node:
        deadline = time.monotonic() + 120
        while "providers" not in node.log() and node.alive() and time.monotonic() < deadline:
            time.sleep(0.002)
        node.proc.send_signal(sig)
        code = node.stop(timeout=30)
    text = node.log()
    assert code == 0, text
    assert "Traceback" not in text, text
    totals = parse_totals(text)
    assert totals.get("received") == 0, text


def test_a_frame_given_up_at_shutdown_is_neither_published_nor_logged():
    live = LiveNode()
    try:
        assert live.segment(scene()) is not None          # warm: the pipeline works
        node = live.node
        entered, release = threading.Event(), threading.Event()
        real = node._pipeline.segment

        def stuck(xyz, image_shape=None):                                    # a frame that outlasts the timeout
            entered.set()
            release.wait(20)
            return real(xyz, image_shape)

        node._pipeline.segment = stuck
        stamp = live.send(scene())
        assert entered.wait(20)
        live.stop_spinning()
        published = node.stats.published
        live.warnings.clear()
        assert node.shutdown(timeout_s=0.2, flush_s=0.5) is False
        release.set()
        node._worker.join(20)
        assert not node._worker.is_alive()
        assert node.stats.published == published
        assert node.stats.dropped_at_shutdown == 1
        assert live.warnings == []
        assert live.client.take(stamp, timeout=1.0) is None
        for pub in (node._pub_cloud, node._pub_instances, node._pub_markers):
            with pytest.raises(InvalidHandle):   # destroyed by shutdown()
                pub.topic_name
    finally:
        live.close()
