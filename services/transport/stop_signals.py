"""Stopping a process cleanly on a signal: the one place every msk process (node, page, ``msk live``, ``msk capture``)
turns SIGINT (Ctrl-C), SIGTERM and SIGHUP (its terminal closed, an SSH link dropped) into a stop flag, so its loops end,
devices get their STOP, files are closed and a summary is written, rather than the process being torn down.

SIGHUP matters for ``msk live``: it starts its nodes in their own process groups (a Ctrl-C reaches it alone and it
stops them in order), so a closed terminal killed it by SIGHUP's default action and left every node running, the
recorder still writing and the view spinning on a terminal that was gone.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from types import FrameType

#: The signals that ask a process to stop.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

# what signal.signal takes and returns: a function, SIG_DFL or SIG_IGN, or None (a handler not set from Python)
_Handler = Callable[[int, FrameType | None], object] | int | signal.Handlers | None


class StopOnSignals:
    """While entered, :data:`STOP_SIGNALS` set :attr:`event` (:attr:`signal` names the first) instead of ending the
    process; the previous handlers are back on exit. ``interrupt_twice``: a second Ctrl-C raises
    :class:`KeyboardInterrupt` at once (an operator who will not wait for the devices). Signals reach the main thread
    only: entered from another thread (a command run from a test's thread) it installs nothing."""

    def __init__(self, *, interrupt_twice: bool = False, event: threading.Event | None = None) -> None:
        self.event = event if event is not None else threading.Event()
        self.signal: str | None = None
        self.interrupt_twice = interrupt_twice
        self._previous: dict[int, _Handler] = {}

    def __enter__(self) -> StopOnSignals:
        if threading.current_thread() is threading.main_thread():
            for number in STOP_SIGNALS:
                self._previous[number] = signal.signal(number, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)
        self._previous.clear()

    def _handle(self, number: int, _frame: FrameType | None) -> None:
        if self.event.is_set() and self.interrupt_twice and number == signal.SIGINT:
            signal.signal(number, self._previous.get(number, signal.default_int_handler))
            raise KeyboardInterrupt
        self.signal = self.signal or signal.Signals(number).name
        self.event.set()


def stop_on_signals() -> threading.Event:
    """A stop flag that :data:`STOP_SIGNALS` set for the rest of the process's life (a node's or a page's main,
    called from the main thread)."""
    return StopOnSignals().__enter__().event
