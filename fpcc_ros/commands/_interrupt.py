"""SIGINT and SIGTERM as one exception for commands that write outputs (`fpcc segment`, `demo`).

Python turns SIGINT into KeyboardInterrupt, so ``with`` blocks unwind and msg_tools.bag's
BagWriter removes its temporary ``.NAME.partial-*`` folder; SIGTERM (what a supervisor or
``timeout`` sends) kills the process outright, leaving that folder behind and, for `fpcc demo`,
the node process orphaned. Inside :func:`interruptible` both raise :class:`Interrupted`, which
unwinds the same way; the command then returns :func:`exit_code` (128 + the signal number, the
shell's convention).
"""
from __future__ import annotations

import signal
from contextlib import contextmanager
from types import FrameType
from typing import Iterator


class Interrupted(KeyboardInterrupt):
    """A stop signal arrived. A KeyboardInterrupt, so no ``except Exception`` swallows it."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@contextmanager
def interruptible(signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Raise Interrupted in the main thread on the first of ``signals`` while the block runs;
    later ones are ignored, so a second Ctrl-C cannot cut the clean-up short."""
    raised = []

    def _raise(signum: int, frame: FrameType | None) -> None:
        if not raised:
            raised.append(signum)
            raise Interrupted(signum)

    previous = {sig: signal.signal(sig, _raise) for sig in signals}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def exit_code(exc: KeyboardInterrupt) -> int:
    """128 + signal number: 130 for SIGINT (a plain KeyboardInterrupt too), 143 for SIGTERM."""
    return 128 + getattr(exc, "signum", signal.SIGINT)
