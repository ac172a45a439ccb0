"""The managed node (`segmenter_managed`, fpcc_ros.managed_segmenter) driven through its lifecycle
services over DDS, as a cell controller would: a configure with a missing model fails and the
node stays up, unconfigured, with the reason on /diagnostics and in its log; with the model set,
configure -> activate (frames answered) -> deactivate (frames not taken) -> activate -> shutdown,
after which the process exits cleanly. Plus cleanup and re-configure in this process.
"""
import os
import sys
import threading
import time

import pytest
import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

import cloud_factory as cf
from conftest import REPO, TEST_DATA
from diagnostics_listener import DiagnosticsListener
from fpcc_ros.replay import NodeProcess
from test_node_faults import _wait

sys.path.insert(0, str(REPO / "scripts"))
from fuzz_node import Collector, parse_totals  # noqa: E402

pytestmark = pytest.mark.ros
TINY = TEST_DATA / "tiny_fpcc.onnx"
TARGET = "/fpcc_segmenter"


class LifecycleClient(Node):
    """change_state / get_state / set_parameters clients of one managed node."""

    def __init__(self, context: Context, target: str = TARGET):
        super().__init__(f"fpcc_lifecycle_client_{os.getpid()}", context=context)
        self._change = self.create_client(ChangeState, f"{target}/change_state")
        self._get = self.create_client(GetState, f"{target}/get_state")
        self._params = AsyncParameterClient(self, target)
        self._executor = SingleThreadedExecutor(context=context)
        self._executor.add_node(self)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()

    def wait_ready(self, timeout: float) -> bool:
        return (self._change.wait_for_service(timeout) and self._get.wait_for_service(timeout)
                and self._params.wait_for_services(timeout))

    @staticmethod
    def _result(future, timeout: float):
        deadline = time.monotonic() + timeout
        while not future.done():
            if time.monotonic() > deadline:
                raise TimeoutError("no answer from the node")
            time.sleep(0.02)
        return future.result()

    def transition(self, transition_id: int, timeout: float = 120.0) -> bool:
        request = ChangeState.Request(transition=Transition(id=transition_id))
        return self._result(self._change.call_async(request), timeout).success

    def state(self, timeout: float = 60.0) -> str:
        return self._result(self._get.call_async(GetState.Request()), timeout).current_state.label

    def set(self, timeout: float = 60.0, **values) -> bool:
        future = self._params.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        return all(r.successful for r in self._result(future, timeout).results)

    def close(self) -> None:
        self._executor.shutdown()
        self.destroy_node()


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """Drive one managed node process through the whole walk; what was seen, by step."""
    tmp = tmp_path_factory.mktemp("managed")
    missing = tmp / "missing.onnx"
    node = NodeProcess(["-p", f"model:={missing}", "-p", "min_points:=5",
                        "-p", "input_timeout:=0.0"], log_path=tmp / "node.log")
    node.cmd[node.cmd.index("fpcc_ros.segmenter")] = "fpcc_ros.managed_segmenter"
    seen: dict = {}
    context = Context()
    rclpy.init(context=context)
    try:
        with node:
            lc, diag = LifecycleClient(context), DiagnosticsListener(context)
            client = Collector(context)
            try:
                assert lc.wait_ready(60), node.log()
                seen["start"] = lc.state()
                seen["configure_missing"] = lc.transition(Transition.TRANSITION_CONFIGURE)
                seen["after_missing"] = lc.state()
                seen["alive_after_missing"] = node.alive()
                seen["diag_missing"] = diag.wait_for(lambda s: s.level == "ERROR", 60)

                seen["set_model"] = lc.set(model=str(TINY))
                seen["configure"] = lc.transition(Transition.TRANSITION_CONFIGURE)
                seen["after_configure"] = lc.state()
                n = len(diag.seen)
                seen["diag_inactive"] = diag.wait_for(lambda s: s.values["state"] == "inactive",
                                                      60, after=n)

                seen["activate"] = lc.transition(Transition.TRANSITION_ACTIVATE)
                seen["after_activate"] = lc.state()
                assert client.wait_connected(60), node.log()
                client.pub.publish(cf.set_stamp(cf.make_cloud(cf.scene_xyz(30, 40, seed=1),
                                                              "xyz32"), 1))
                seen["frame_active"] = client.take(1, 60)

                seen["deactivate"] = lc.transition(Transition.TRANSITION_DEACTIVATE)
                seen["after_deactivate"] = lc.state()
                seen["input_gone"] = _wait(lambda: client.pub.get_subscription_count() == 0,
                                           timeout=60)
                client.pub.publish(cf.set_stamp(cf.make_cloud(cf.scene_xyz(30, 40, seed=2),
                                                              "xyz32"), 2))
                time.sleep(2.0)

                seen["reactivate"] = lc.transition(Transition.TRANSITION_ACTIVATE)
                assert _wait(lambda: client.pub.get_subscription_count() > 0,
                             timeout=60), node.log()
                client.pub.publish(cf.set_stamp(cf.make_cloud(cf.scene_xyz(30, 40, seed=3),
                                                              "xyz32"), 3))
                seen["frame_reactivated"] = client.take(3, 60)
                seen["stamps_answered"] = client.stamps_seen()

                seen["shutdown"] = lc.transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
                try:
                    seen["exit_code"] = node.proc.wait(timeout=60)
                except Exception:  # noqa: BLE001 - recorded as no exit; stop() below kills it
                    seen["exit_code"] = None
            finally:
                client.close()
                diag.close()
                lc.close()
    finally:
        rclpy.try_shutdown(context=context)
    seen["log"] = node.log()
    return seen


def test_a_configure_with_a_missing_model_fails_with_the_reason_and_the_node_stays_up(walk):
    assert walk["start"] == "unconfigured"
    assert walk["configure_missing"] is False
    assert walk["after_missing"] == "unconfigured"
    assert walk["alive_after_missing"]
    status = walk["diag_missing"]
    assert status is not None, walk["log"]
    assert status.message.startswith("configure failed: model file ")
    assert "missing.onnx not found" in status.message
    assert status.values["state"] == "unconfigured" and status.values["model"] == ""
    assert "configure failed" in walk["log"] and "missing.onnx not found" in walk["log"]


def test_configure_loads_the_model_and_activate_takes_frames(walk):
    assert walk["set_model"] is True
    assert (walk["configure"], walk["after_configure"]) == (True, "inactive")
    status = walk["diag_inactive"]
    assert status is not None and status.level == "OK", walk["log"]
    assert status.message == "inactive: model loaded, not taking frames"
    assert status.values["model"] == str(TINY)
    assert (walk["activate"], walk["after_activate"]) == (True, "active")
    out = walk["frame_active"]
    assert out is not None and set(out) == {"segmented_points", "instances",
                                            "instance_markers"}, walk["log"]


def test_deactivate_stops_taking_frames_and_activate_resumes(walk):
    assert (walk["deactivate"], walk["after_deactivate"]) == (True, "inactive")
    assert walk["input_gone"], "the node still subscribes to points after deactivate"
    assert walk["reactivate"] is True
    assert walk["frame_reactivated"] is not None, walk["log"]
    assert walk["stamps_answered"] == {1, 3}      # 2 came while inactive: never answered


def test_shutdown_ends_the_process_cleanly_with_every_frame_accounted(walk):
    assert walk["shutdown"] is True
    assert walk["exit_code"] == 0, walk["log"]
    for bad in ("Traceback", "terminate called", "Exception in thread"):
        assert bad not in walk["log"], walk["log"]
    totals = parse_totals(walk["log"])
    assert (totals["received"], totals["published"]) == (2, 2), walk["log"]


def test_cleanup_releases_the_model_and_a_new_configure_loads_it_again():
    """In this process (no DDS peer needed): the transitions' effects on the node itself."""
    from fpcc_ros.managed_segmenter import ManagedSegmenterNode

    context = Context()
    rclpy.init(context=context)
    try:
        node = ManagedSegmenterNode(context=context,
                                    parameter_overrides=[Parameter("model", value=str(TINY))])
        try:
            ok = TransitionCallbackReturn.SUCCESS
            assert node._pipeline is None            # nothing loaded before configure
            assert node.trigger_configure() == ok
            assert node._pipeline.model.path == TINY
            assert node.count_publishers("/segmented_points") == 1
            assert node.trigger_cleanup() == ok
            assert node._pipeline is None
            assert node.count_publishers("/segmented_points") == 0
            assert node.trigger_configure() == ok   # again: the same outputs come back
            assert node.count_publishers("/segmented_points") == 1
            assert node.trigger_activate() == ok
            assert node.count_subscribers("/points") == 1
            assert node.trigger_shutdown() == ok
            assert node._pipeline is None and node.finalized
            assert node.count_subscribers("/points") == 0
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
