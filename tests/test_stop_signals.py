"""The one stop-on-signal context of every msk process (services.transport.stop_signals)."""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path

import pytest

from services.transport.stop_signals import STOP_SIGNALS, StopOnSignals


@pytest.fixture
def handled():
    """Every stop signal with a handler of its own (a job started with nohup or in the background ignores some)."""
    found = {n: signal.getsignal(n) for n in STOP_SIGNALS}
    for number in STOP_SIGNALS:
        signal.signal(number, signal.default_int_handler)
    yield
    for number, handler in found.items():
        signal.signal(number, handler)


@pytest.mark.parametrize("number", STOP_SIGNALS)
def test_each_stop_signal_sets_the_flag_and_the_previous_handlers_come_back(number, handled):
    before = {n: signal.getsignal(n) for n in STOP_SIGNALS}
    with StopOnSignals() as stop:
        os.kill(os.getpid(), number)
        assert stop.event.wait(5.0) and stop.signal == signal.Signals(number).name
        os.kill(os.getpid(), number)  # asked again: still a stop, not an interrupt
    assert {n: signal.getsignal(n) for n in STOP_SIGNALS} == before


def test_a_second_ctrl_c_interrupts_at_once_when_asked_for():
    before = signal.getsignal(signal.SIGINT)  # SIG_IGN in a job started in the background (CI)
    with pytest.raises(KeyboardInterrupt), StopOnSignals(interrupt_twice=True) as stop:
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.event.wait(5.0)
        os.kill(os.getpid(), signal.SIGINT)
        threading.Event().wait(5.0)  # the handler raises here
    assert signal.getsignal(signal.SIGINT) == before


def test_a_process_started_with_nohup_outlives_its_terminal(handled):
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    with StopOnSignals() as stop:
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
        os.kill(os.getpid(), signal.SIGHUP)
        assert not stop.event.wait(0.3)
    assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN


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


def test_a_child_started_to_stop_with_its_parent_stops_when_the_parent_is_killed(tmp_path):
    """msk live's nodes run in their own process groups; killed (SIGKILL, a crash), it left them all running."""
    import subprocess
    import sys
    import time

    child = (
        "import sys; from services.transport.stop_signals import stop_on_signals\n"
        "stop = stop_on_signals(); print('ready', flush=True)\n"
        "sys.exit(0 if stop.wait(30) else 1)\n"
    )
    parent = (
        "import os, subprocess, sys, time\n"
        "from services.transport.stop_signals import stop_with_parent_env\n"
        f"p = subprocess.Popen([sys.executable, '-c', {child!r}], start_new_session=True,\n"
        "    env={**os.environ, **stop_with_parent_env()})\n"
        "print(p.pid, flush=True); time.sleep(60)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    process = subprocess.Popen([sys.executable, "-c", parent], stdout=subprocess.PIPE, text=True, env=env)
    try:
        pid = int(process.stdout.readline())
        time.sleep(1.0)
        os.kill(process.pid, signal.SIGKILL)
        process.wait(10)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and _alive(pid):
            time.sleep(0.1)
        assert not _alive(pid), f"the child {pid} still runs 10 s after its parent was killed"
    finally:
        process.kill()
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by init) has ended
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False
