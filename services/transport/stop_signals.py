"""Stopping a process cleanly on a signal: the one place every msk process (node, page, ``msk live``, ``msk capture``)
turns SIGINT (Ctrl-C), SIGTERM and SIGHUP (its terminal closed, an SSH link dropped) into a stop flag, so its loops end,
devices get their STOP, files are closed and a summary is written, rather than the process being torn down.

SIGHUP matters for ``msk live``: it starts its nodes in their own process groups (a Ctrl-C reaches it alone and it
stops them in order), so a closed terminal killed it by SIGHUP's default action and left every node running, the
recorder still writing and the view spinning on a terminal that was gone.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable
from types import FrameType

#: The signals that ask a process to stop.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: Set by a process in the environment of the children it stops itself (``msk live``'s nodes, in their own process
#: groups): its pid. Such a child stops as on a signal when that parent is gone (killed, crashed) rather than running
#: on unattended.
PARENT_ENV = "MSK_STOP_WITH_PARENT"
#: How often a child of :data:`PARENT_ENV` looks for its parent (s).
PARENT_CHECK_S = 0.5


def stop_with_parent_env() -> dict[str, str]:
    """The environment entry that makes a child started now stop with this process (:data:`PARENT_ENV`)."""
    return {PARENT_ENV: str(os.getpid())}


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
                if number == signal.SIGHUP and signal.getsignal(number) == signal.SIG_IGN:
                    continue  # started with nohup: meant to outlive its terminal
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
    called from the main thread), and the end of the parent that started it with :func:`stop_with_parent_env`."""
    stop = StopOnSignals().__enter__()
    parent = os.environ.pop(PARENT_ENV, "")  # not passed on: a grandchild's parent is another process
    if parent.isdigit():
        threading.Thread(target=_watch_parent, args=(stop, int(parent)), name="parent-watch", daemon=True).start()
    return stop.event


def _watch_parent(stop: StopOnSignals, parent: int) -> None:
    while not stop.event.wait(PARENT_CHECK_S):
        if os.getppid() != parent:  # re-parented: the process that would have stopped this one is gone
            stop.signal = stop.signal or "parent gone"
            stop.event.set()


def exit_text(code: int) -> str:
    """How a process ended, from its return code: "exited with code 1", "was killed by signal 9 (SIGKILL)"."""
    if code >= 0:
        return f"exited with code {code}"
    name = f" ({signal.Signals(-code).name})" if -code in signal.valid_signals() else ""
    return f"was killed by signal {-code}{name}"
