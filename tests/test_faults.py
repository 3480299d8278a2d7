"""Faults with counted messages: real processes (``msk router``, ``msk recorder``, a hung app), real Zenoh on
loopback, real MCAP files. docs/deployment.md ("Faults") reports the figures these tests bound."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
import zenoh

from services import messages, topics
from services.mcap_io import ReadReport, read_messages
from services.zenoh_session import ZenohOptions, declare_data_publisher, open_session, publish
from tests.conftest import free_tcp_port

pytestmark = pytest.mark.slow

SESSION = "fault"


def _msk(*argv: str, **popen) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "services.cli", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)


def _stop(process: subprocess.Popen, sig: int = signal.SIGINT, timeout_s: float = 15) -> str:
    """Stop a process we started (signal, then kill after ``timeout_s``); returns its stderr."""
    if process.poll() is None:
        try:
            process.send_signal(sig)
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
    try:
        return process.communicate(timeout=10)[1] or ""
    except (subprocess.TimeoutExpired, ValueError):
        return ""


def _wait(predicate, timeout_s: float, what: str, have=lambda: "") -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"after {timeout_s:.0f} s still waiting for {what}; have: {have()}")
        time.sleep(0.02)


@pytest.fixture
def router():
    """``msk router`` on a free loopback port; yields its endpoint."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    process = _msk("router", "--listen", endpoint)

    def listening() -> bool:
        if process.poll() is not None:
            raise AssertionError(f"msk router exited {process.returncode}: {process.communicate()[1][-2000:]}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return True
        except OSError:
            return False

    _wait(listening, 30, f"msk router listening on {endpoint}")
    yield endpoint
    _stop(process)


def _client(endpoint: str) -> zenoh.Session:
    return open_session(ZenohOptions(mode="client", connect=(endpoint,)))


def _start_recorder(out: Path, endpoint: str, session: zenoh.Session) -> subprocess.Popen:
    """``msk recorder`` as a client of the router; returns once it is subscribed (a probe publisher matches it)."""
    process = _msk("recorder", "--out", str(out), "--mode", "client", "--connect", endpoint)
    probe = session.declare_publisher(f"msk/{SESSION}/probe-{os.getpid()}-{time.monotonic_ns()}")
    try:
        def matched() -> bool:
            if process.poll() is not None:
                raise AssertionError(f"msk recorder exited {process.returncode}: {process.communicate()[1][-2000:]}")
            return probe.matching_status.matching

        _wait(matched, 30, f"msk recorder writing {out.name} to subscribe")
    finally:
        probe.undeclare()
    return process


def _activation(index: int, n_groups: int = 60) -> messages.ActivationFrame:
    return messages.ActivationFrame(
        time_s=index * 0.01, method="so", groups=[f"muscle_{g:02d}" for g in range(n_groups)],
        activations=[0.5] * n_groups, forces_n=[100.0] * n_groups, solver_status="solved",
    )


def _emg(index: int) -> messages.EmgChunk:
    return messages.EmgChunk(
        source_id="trigno", channel_labels=[f"ch{c}" for c in range(16)], sample_rate_hz=2000.0,
        first_sample_index=27 * index, n_samples=27, n_channels=16, samples=[0.001] * (27 * 16), units="V",
    )


HUNG_APP = textwrap.dedent(
    """
    import signal, sys, threading, zenoh
    endpoint, key = sys.argv[1], sys.argv[2]
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", f'["{endpoint}"]')
    count = [0]
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    with zenoh.open(config) as session:
        session.declare_subscriber(key, lambda sample: count.__setitem__(0, count[0] + 1))
        print("ready", flush=True)
        done.wait(120)
    print(count[0], flush=True)
    """
)


def test_hung_app_stalls_no_publisher_and_the_recorder_loses_nothing(router, tmp_path):
    """A tablet app that stops reading (SIGSTOP) while the estimator publishes activation frames (newest-wins) and
    the driver EMG (lossless) at 10x real-time rates (~11 MB towards the app): no put waits for the hung app, the recorder holds every message
    of both, and the hung app itself missed frames (so its link was congested, and the frames were dropped for it
    alone)."""
    n_frames = 6000  # ~1.9 kB activation frames: about twice what the kernel's and Zenoh's buffers towards the app hold
    frame_rate_hz = 1000.0
    out = tmp_path / "hung.mcap"
    publisher_session = _client(router)
    recorder = _start_recorder(out, router, publisher_session)
    app = subprocess.Popen([sys.executable, "-c", HUNG_APP, router, f"msk/{SESSION}/activations/**"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert app.stdout.readline().strip() == "ready", app.stderr.read()[-2000:]
        activations = declare_data_publisher(publisher_session, topics.activations_key(SESSION, "so"), "msk.ActivationFrame")
        emg = declare_data_publisher(publisher_session, topics.emg_key(SESSION, "trigno"), "msk.EmgChunk")
        time.sleep(0.3)  # the app's subscription reaches the router
        os.kill(app.pid, signal.SIGSTOP)  # the app hangs: it reads nothing from now on
        longest_put = 0.0
        start = time.monotonic()
        for index in range(n_frames):
            due = start + index / frame_rate_hz
            if (delay := due - time.monotonic()) > 0:
                time.sleep(delay)
            before = time.monotonic()
            publish(activations, _activation(index))
            publish(emg, _emg(index))
            longest_put = max(longest_put, time.monotonic() - before)
        publish_time = time.monotonic() - start
        os.kill(app.pid, signal.SIGCONT)

        time.sleep(1.5)  # > the recorder's flush interval
        _stop(recorder)
        recorded = list(read_messages(out))
        app.send_signal(signal.SIGTERM)
        app_out, app_err = app.communicate(timeout=30)
        app_received = int(app_out.strip().splitlines()[-1])
    finally:
        for process in (app, recorder):
            if process.poll() is None:
                process.kill()
                process.wait(10)
        publisher_session.close()
    print(f"hung app received {app_received} of {n_frames}; longest put {longest_put * 1e3:.1f} ms; "
          f"published in {publish_time:.2f} s")
    by_key = {}
    for message in recorded:
        by_key.setdefault(message.topic, []).append(message)
    frames = by_key.get(topics.activations_key(SESSION, "so"), [])
    chunks = by_key.get(topics.emg_key(SESSION, "trigno"), [])
    assert len(chunks) == n_frames, f"recorder lost {n_frames - len(chunks)} of {n_frames} EMG chunks"
    assert len(frames) == n_frames, f"recorder lost {n_frames - len(frames)} of {n_frames} activation frames"
    assert [m.decode().first_sample_index for m in chunks] == [27 * i for i in range(n_frames)]
    assert longest_put < 0.5, f"a put waited {longest_put:.2f} s: the hung app stalled the publisher"
    assert publish_time < n_frames / frame_rate_hz + 3.0, f"publishing {n_frames} frames took {publish_time:.1f} s"
    assert app_received < n_frames, (
        f"the hung app received all {n_frames} frames: its link was never congested, so this test showed nothing"
    )
