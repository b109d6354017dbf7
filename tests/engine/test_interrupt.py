"""deferred_interrupt: the first Ctrl-C is a flag, the second an exception."""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator

import pytest

from dyngs.engine.interrupt import deferred_interrupt


@pytest.fixture(autouse=True)
def python_handles_sigint() -> Iterator[None]:
    """Python's own handler, whatever this process inherited: started in the background
    by a non-interactive shell, a test run has SIGINT ignored."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def _press_ctrl_c() -> None:
    os.kill(os.getpid(), signal.SIGINT)  # handled in the main thread before kill returns


def test_first_sigint_sets_the_flag_and_the_second_raises() -> None:
    before = signal.getsignal(signal.SIGINT)
    with deferred_interrupt() as interrupted:
        assert not interrupted()
        _press_ctrl_c()
        assert interrupted()
        with pytest.raises(KeyboardInterrupt):
            _press_ctrl_c()
    assert signal.getsignal(signal.SIGINT) is before


def test_the_handler_is_restored_when_the_body_raises() -> None:
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(RuntimeError), deferred_interrupt():
        raise RuntimeError("boom")
    assert signal.getsignal(signal.SIGINT) is before


def test_an_ignored_sigint_stays_ignored() -> None:
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with deferred_interrupt() as interrupted:
            _press_ctrl_c()
            assert not interrupted()
            assert signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)


def test_outside_the_main_thread_nothing_changes() -> None:
    seen: list[bool] = []

    def body() -> None:
        with deferred_interrupt() as interrupted:
            seen.append(interrupted())

    worker = threading.Thread(target=body)
    worker.start()
    worker.join()
    assert seen == [False]
