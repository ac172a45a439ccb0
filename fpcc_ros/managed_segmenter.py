"""The `segmenter_managed` node: the same `fpcc_segmenter`, as a ROS 2 managed (lifecycle) node.

A cell controller brings it up as Nav2 and most driver stacks do, through the lifecycle services
`<node>/change_state` and `<node>/get_state`:

* configure: load and check the model (a bad one fails the transition; the reason is logged and
  shown on /diagnostics; the node stays up, unconfigured) and create the output publishers;
* activate: subscribe to `points`, start the worker, enable the outputs;
* deactivate: unsubscribe, finish the frame in flight, disable the outputs; the model stays;
* cleanup: release the model and the publishers; shutdown: all of that, then the process exits.

Parameters, frame processing and /diagnostics are SegmenterNode's (fpcc_ros.segmenter): only
when things start and stop differs. Parameters set while unconfigured are checked at configure.
"""
from __future__ import annotations

import sys
from typing import Any

from rclpy.lifecycle import LifecycleNodeMixin, LifecycleState, TransitionCallbackReturn
from rclpy.node import Node

from fpcc_ros.node_diagnostics import Reading
from fpcc_ros.onnx_model import ModelLoadError
from fpcc_ros.pipeline import ConfigError
from fpcc_ros.segmenter import NODE_NAME, SegmenterNode, run_node

SUCCESS, FAILURE = TransitionCallbackReturn.SUCCESS, TransitionCallbackReturn.FAILURE
WORKER_STOP_S = 60.0   # deactivate waits this long for the frame in flight (a huge cloud)


class ManagedSegmenterNode(LifecycleNodeMixin, SegmenterNode):
    """SegmenterNode whose model, outputs, input and worker follow the lifecycle transitions."""

    def __init__(self, **kwargs: Any):
        Node.__init__(self, NODE_NAME, **kwargs)    # not SegmenterNode's: nothing starts yet
        LifecycleNodeMixin.__init__(self)
        self._setup()
        self._state_error = ""
        self.finalized = False

    # ---- transitions ------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            pipeline = self._build_pipeline(self._param_values())
        except (ModelLoadError, ConfigError, TypeError, ValueError) as exc:
            self._state_error = f"configure failed: {exc}"
            self.get_logger().error(self._state_error)
            return FAILURE
        self._state_error = ""
        self._pipeline = pipeline
        self._log_model(pipeline)
        self._create_outputs(self.create_lifecycle_publisher)
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self._worker is not None:
            self._worker.join()   # one that outlived a deactivate's wait: never two workers
        self._create_input()
        self._start_worker()
        return super().on_activate(state)   # enables the lifecycle publishers

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_taking_frames()
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_taking_frames()
        self._release()
        self.finalized = True   # main() stops spinning once the service has answered
        return SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._state_error = f"a transition from {state.label} raised; back to unconfigured"
        self.get_logger().error(self._state_error)
        self._stop_taking_frames()
        self._release()
        return SUCCESS

    def _stop_taking_frames(self) -> None:
        if self._sub is not None:
            self.destroy_subscription(self._sub)
            self._sub = None
        if self._worker is not None and not self.stop_worker(timeout_s=WORKER_STOP_S):
            self.get_logger().warning(f"a frame was still being processed {WORKER_STOP_S:.0f} s "
                                      "after deactivate; its outputs will not be published")

    def _release(self) -> None:
        for name in ("_pub_cloud", "_pub_instances", "_pub_markers"):
            pub = self.__dict__.pop(name, None)
            if pub is not None:
                self.destroy_lifecycle_publisher(pub)
        self._pipeline = None   # the onnxruntime session goes with its last reference

    # ---- SegmenterNode hooks ----------------------------------------------------------------
    def _diagnostic_reading(self, state: str = "", state_error: str = "") -> Reading:
        return super()._diagnostic_reading(self._state_machine.current_state[1], self._state_error)


def main(args: list[str] | None = None) -> int:
    """As fpcc_ros.segmenter.main (signals only set a flag), and the process also ends once a
    shutdown transition has finalized the node. No model yet at start: that is configure's."""
    return run_node(ManagedSegmenterNode, args, finished=lambda node: node.finalized)


if __name__ == "__main__":
    sys.exit(main())
