"""SIGINT and SIGTERM as one exception for commands that write outputs (`fpcc segment`, `demo`).

Python turns SIGINT into KeyboardInterrupt, so ``with`` blocks unwind and msg_tools.bag's
BagWriter removes its temporary ``.NAME.partial-*`` folder; SIGTERM (what a supervisor or
``timeout`` sends) kills the process outright, leaving that folder behind and, for `fpcc demo`,
the node process orphaned. Inside :func:`interruptible` both raise :class:`Interrupted`, which
unwinds the same way; the command then returns :func:`exit_code` (128 + the signal number, the
shell's convention).

A handler's exception is lost when the signal lands while Python runs a finaliser or a weakref
callback (``__del__``, importlib's module-lock callbacks): Python prints "Exception ignored in"
and carries on, and the command would then finish and commit its output. So the handler also
records the signal, :meth:`StopSignal.check` raises it again at the points a command commits,
and the ignored copy is not printed.
"""
from __future__ import annotations

import signal
import sys
from contextlib import contextmanager
from types import FrameType
from typing import Iterator


class Interrupted(KeyboardInterrupt):
    """A stop signal arrived. A KeyboardInterrupt, so no ``except Exception`` swallows it."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class StopSignal:
    """The first stop signal received inside :func:`interruptible`, if any."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def check(self) -> None:
        """Raise Interrupted if a stop signal arrived, even one whose exception was lost."""
        if self.signum is not None:
            raise Interrupted(self.signum)


@contextmanager
def interruptible(signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[StopSignal]:
    """Raise Interrupted in the main thread on the first of ``signals`` while the block runs;
    later ones are ignored, so a second Ctrl-C cannot cut the clean-up short. Call the yielded
    StopSignal's ``check()`` before committing an output."""
    stop = StopSignal()

    def _raise(signum: int, frame: FrameType | None) -> None:
        if stop.signum is None:
            stop.signum = signum
            raise Interrupted(signum)

    def _unraisable(info: "sys.UnraisableHookArgs") -> None:
        if not isinstance(info.exc_value, Interrupted):   # ours is recorded in stop
            previous_hook(info)

    previous = {sig: signal.signal(sig, _raise) for sig in signals}
    previous_hook, sys.unraisablehook = sys.unraisablehook, _unraisable
    try:
        yield stop
    finally:
        sys.unraisablehook = previous_hook
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def exit_code(exc: KeyboardInterrupt) -> int:
    """128 + signal number: 130 for SIGINT (a plain KeyboardInterrupt too), 143 for SIGTERM."""
    return 128 + getattr(exc, "signum", signal.SIGINT)
