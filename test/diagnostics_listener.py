"""A `/diagnostics` subscriber for the node tests: keeps the segmenter's statuses as they arrive
and waits for one that satisfies a condition (shared by test_node_diagnostics.py and
test_managed_node.py)."""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

STATUS_NAME = "fpcc_segmenter: segmentation"
LEVELS = {0: "OK", 1: "WARN", 2: "ERROR", 3: "STALE"}


@dataclass(frozen=True)
class Seen:
    level: str
    message: str
    values: dict[str, str]
    hardware_id: str

    def count(self, key: str) -> int:
        return int(self.values[f"frames {key}"])


class DiagnosticsListener(Node):
    def __init__(self, context: Context, name: str = STATUS_NAME):
        super().__init__(f"fpcc_diag_listener_{os.getpid()}", context=context)
        self.status_name = name
        self.seen: list[Seen] = []
        self._cond = threading.Condition()
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on, 50)
        self._executor = SingleThreadedExecutor(context=context)
        self._executor.add_node(self)
        self._thread = threading.Thread(target=self._executor.spin, daemon=True)
        self._thread.start()

    def _on(self, msg: DiagnosticArray) -> None:
        with self._cond:
            for s in msg.status:
                if s.name == self.status_name:
                    self.seen.append(Seen(LEVELS[ord(s.level)], s.message,
                                          {kv.key: kv.value for kv in s.values}, s.hardware_id))
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[Seen], bool], timeout: float = 60.0,
                 after: int = 0) -> Seen | None:
        """The first status from index ``after`` on that satisfies ``predicate``, or None."""
        deadline = time.monotonic() + timeout
        with self._cond:
            i = after
            while True:
                for s in self.seen[i:]:
                    if predicate(s):
                        return s
                i = len(self.seen)
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(timeout=min(left, 0.5))

    def last(self) -> Seen | None:
        with self._cond:
            return self.seen[-1] if self.seen else None

    def close(self) -> None:
        self._executor.shutdown()
        self.destroy_node()
