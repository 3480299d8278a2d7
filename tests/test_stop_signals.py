"""The one stop-on-signal context of every msk process (services.transport.stop_signals)."""

from __future__ import annotations

import os
import signal
import threading

import pytest

from services.transport.stop_signals import STOP_SIGNALS, StopOnSignals


@pytest.mark.parametrize("number", STOP_SIGNALS)
def test_each_stop_signal_sets_the_flag_and_the_previous_handlers_come_back(number):
    before = {n: signal.getsignal(n) for n in STOP_SIGNALS}
    with StopOnSignals() as stop:
        os.kill(os.getpid(), number)
        assert stop.event.wait(5.0) and stop.signal == signal.Signals(number).name
        os.kill(os.getpid(), number)  # asked again: still a stop, not an interrupt
    assert {n: signal.getsignal(n) for n in STOP_SIGNALS} == before


def test_a_second_ctrl_c_interrupts_at_once_when_asked_for():
    with pytest.raises(KeyboardInterrupt), StopOnSignals(interrupt_twice=True) as stop:
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.event.wait(5.0)
        os.kill(os.getpid(), signal.SIGINT)
        threading.Event().wait(5.0)  # the handler raises here
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_outside_the_main_thread_nothing_is_installed():
    before = {n: signal.getsignal(n) for n in STOP_SIGNALS}
    seen: list[dict] = []

    def enter() -> None:
        with StopOnSignals():
            seen.append({n: signal.getsignal(n) for n in STOP_SIGNALS})

    thread = threading.Thread(target=enter)
    thread.start()
    thread.join(5.0)
    assert seen == [before]
