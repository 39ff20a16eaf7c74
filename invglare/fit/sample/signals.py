"""Ctrl-C and SIGTERM during a run: held while a step is written, then delivered."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from typing import Any


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """Hold Ctrl-C (and SIGTERM) while a step is written; deliver it afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []

    def hold(signum, frame):
        received.append(signum)

    old = {s: signal.signal(s, hold) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        if received:
            handler = old[received[0]]
            if callable(handler):  # the run's own handler (records the request) or Python's
                handler(received[0], None)
            # Both become KeyboardInterrupt: the caller's clean-up and messages are the same.
            raise KeyboardInterrupt


class StopRequests:
    """Ctrl-C and a plain ``kill`` (SIGTERM) during a run, as KeyboardInterrupt.

    The handler raises KeyboardInterrupt at once (to stop a long evaluation), and
    also records the request: Python swallows an exception raised while a weakref
    callback or ``__del__`` runs, so the run loop re-raises after the step in
    progress if the first one got lost.
    """

    def __init__(self):
        self.received = False
        self._old: dict[int, Any] = {}

    def _stop(self, signum, frame):
        self.received = True
        raise KeyboardInterrupt

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._old = {s: signal.signal(s, self._stop) for s in (signal.SIGINT, signal.SIGTERM)}
        return self

    def __exit__(self, *exc):
        for s, h in self._old.items():
            signal.signal(s, h)
        return False

    def check(self) -> None:
        if self.received:
            raise KeyboardInterrupt
