"""Stopping a node process on SIGINT/SIGTERM without racing rclpy (issue 26).

rclpy's own signal handlers wake the executor and then call ``rcl_shutdown`` on every context
from a C++ thread of their own, at a moment of its choosing. The node's main thread meanwhile
leaves ``spin()`` and tears down, and the worker may be publishing: the context vanishes under
whichever of them is inside rcl at that moment -- a wait set built on a dead context (RCLError,
exit 1), a frame published half (the other outputs raise), and now and then a SIGSEGV inside
``destroy_node``. So a node's ``main`` here asks rclpy for no signal handlers and installs
:class:`StopRequest` instead: the handler only records the signal, the main thread sees it
within ``poll_s`` and then shuts down in order, with the context valid until the very end (see
``fpcc_ros.segmenter.teardown``).
"""
from __future__ import annotations

import signal
from types import FrameType
from typing import Any, Callable

from rclpy.executors import ExternalShutdownException

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopRequest:
    """SIGINT/SIGTERM set a flag and nothing else (a Python handler runs on the main thread
    between bytecodes, so no exception is thrown into rclpy's executor code either).

    Install it from the main thread before ``rclpy.init(...,
    signal_handler_options=SignalHandlerOptions.NO)`` so a signal during start-up (model
    loading) is kept too. A second signal while stopping is counted, not acted on: the
    teardown is bounded (the worker gets a few seconds), and a supervisor that escalates still
    has SIGKILL.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self.repeats = 0
        self._previous: dict[int, Any] = {}

    def install(self, signals: tuple[int, ...] = STOP_SIGNALS) -> "StopRequest":
        for sig in signals:
            self._previous[sig] = signal.signal(sig, self._on_signal)
        return self

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        if self.signum is None:
            self.signum = signum
        else:
            self.repeats += 1

    @property
    def requested(self) -> bool:
        return self.signum is not None

    @property
    def name(self) -> str:
        return signal.Signals(self.signum).name if self.signum is not None else "none"


def spin_until_stopped(executor: Any, should_stop: Callable[[], bool],
                       poll_s: float = 0.1) -> None:
    """Run the executor's callbacks on this thread until ``should_stop()`` or the context is
    shut down elsewhere. rcl's wait returns neither for a Python signal handler nor for a flag,
    so it waits at most ``poll_s`` at a time: the longest a stop goes unseen.

    Whoever stops it then waits for this thread to return before shutting the executor down or
    destroying the node: ``Executor.shutdown()`` destroys its guard conditions without waiting
    for a spinning thread, and one that misses the wake-up blocks in rcl_wait (ros2/rclpy#663).
    """
    try:
        while not should_stop() and executor.context.ok():
            executor.spin_once(timeout_sec=poll_s)
    except ExternalShutdownException:
        pass
