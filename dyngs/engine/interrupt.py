"""Ctrl-C during training stops it between two steps, never inside one."""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from types import FrameType


@contextmanager
def deferred_interrupt() -> Iterator[Callable[[], bool]]:
    """While active, a first SIGINT only sets a flag, read with the yielded function, so
    the training loop can stop at the end of a step: model, optimizer and densification
    statistics then all describe the same step when the checkpoint is written. A second
    SIGINT raises KeyboardInterrupt at once, for a step that hangs.

    Python raises KeyboardInterrupt wherever the main thread happens to be: half-way
    through an optimizer step, or through a densification that has replaced some
    parameters and not yet their optimizer state, and the checkpoint written on the way
    out would hold that half-done step. (Raised inside a finalizer, it would even be
    printed and dropped.)

    A SIGINT that was ignored (a job started in the background by a non-interactive
    shell) stays ignored. Outside the main thread no handler can be set, and nothing
    changes.
    """
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous == signal.SIG_IGN:
        yield lambda: False
        return
    pressed = False

    def on_interrupt(signum: int, frame: FrameType | None) -> None:
        nonlocal pressed
        if pressed:
            raise KeyboardInterrupt
        pressed = True

    signal.signal(signal.SIGINT, on_interrupt)
    try:
        yield lambda: pressed
    finally:
        signal.signal(signal.SIGINT, previous)
