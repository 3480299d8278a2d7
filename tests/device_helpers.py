"""Shared by the tests that read the device simulators through the real drivers in threads of the test process: a
reader thread's body that keeps its exception, and a Trigno client streaming from a simulator from a given instant."""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from typing import Any

from drivers.trigno.client import TrignoClient, TrignoConfig
from drivers.trigno.simulator import TrignoSimulator


def keeping_errors(target: Callable[..., None], errors: list[BaseException]) -> Callable[..., None]:
    """A reader thread's body: ``target(*args)``, its exception kept in ``errors`` (the test raises it after the
    join)."""

    def run(*args: Any) -> None:
        try:
            target(*args)
        except BaseException as error:
            errors.append(error)

    return run


@contextlib.contextmanager
def trigno_streaming(sim: TrignoSimulator, start_at: float, *, aux: bool = False) -> Iterator[TrignoClient]:
    """A Trigno client of ``sim`` (EMG port, and the AUX port with ``aux``) connected now and started at the
    ``time.monotonic()`` instant ``start_at``; stopped and closed after the block."""
    ports = {"aux_port": sim.ports["aux"]} if aux else {}
    client = TrignoClient(TrignoConfig(command_port=sim.ports["command"], emg_port=sim.ports["emg"], **ports))
    client.connect()
    time.sleep(max(0.0, start_at - time.monotonic()))
    client.start()
    try:
        yield client
    finally:
        client.stop()
        client.close()
