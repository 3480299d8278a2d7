"""Shared by the tests that run a node in a thread of the test process over real Zenoh on loopback: the estimator node
started and stopped, a client that feeds it joint angles and collects its frames, and the wait for a publisher's
subscribers."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from services.nodes import estimator
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session


def start_estimator_thread(
    options: ZenohOptions, stop: threading.Event, *, ready_s: float = 60.0, **node: Any
) -> tuple[threading.Thread, estimator.EstimatorStats]:
    """``estimator.main`` in a daemon thread until ``stop`` is set (``node``: the fields of its
    ``estimator.EstimatorSettings``); returns once the node is ready (at most ``ready_s``)."""
    ready, stats = threading.Event(), estimator.EstimatorStats()
    thread = threading.Thread(
        target=estimator.main,
        args=(options, estimator.EstimatorSettings(**node)),
        kwargs=dict(stop_event=stop, ready_event=ready, stats=stats),
        daemon=True,
    )
    thread.start()
    assert ready.wait(ready_s), f"estimator node did not start within {ready_s:g} s"
    return thread, stats


@contextlib.contextmanager
def estimator_node(endpoint: str, **node: Any) -> Iterator[estimator.EstimatorStats]:
    """An estimator node listening on ``endpoint`` (``node``: its settings' fields), ready inside the
    block, stopped and joined after it; yields its live stats."""
    stop = threading.Event()
    thread, stats = start_estimator_thread(ZenohOptions(listen=(endpoint,)), stop, ready_s=20.0, **node)
    try:
        yield stats
    finally:
        stop.set()
        thread.join(10)


def wait_matching(*publishers: Any, timeout_s: float = 10.0) -> None:
    """Until every publisher has a matching subscriber, or ``timeout_s`` (then the test goes on: what it counts after
    says what arrived)."""
    deadline = time.monotonic() + timeout_s
    while not all(p.matching_status.matching for p in publishers) and time.monotonic() < deadline:
        time.sleep(0.01)


@dataclass
class EstimatorClient:
    """What a test holds of a running estimator node: its own Zenoh session, a joints publisher the node already
    subscribes to, every activation frame the node published (in arrival order) and the node's stats."""

    session: Any
    joints: Any
    frames: list[messages.ActivationFrame]
    stats: estimator.EstimatorStats

    def wait_frames(self, n: int, timeout_s: float) -> None:
        """Until ``n`` frames have come, or ``timeout_s`` (the test then says how many came)."""
        deadline = time.monotonic() + timeout_s
        while len(self.frames) < n and time.monotonic() < deadline:
            time.sleep(0.05)


@contextlib.contextmanager
def estimator_client(endpoint: str, session: str, **node: Any) -> Iterator[EstimatorClient]:
    """An estimator node of the Zenoh session name ``session`` (see :func:`estimator_node`) and a client of it that
    collects its activation frames and publishes joint angles to it."""
    frames: list[messages.ActivationFrame] = []
    with (
        estimator_node(endpoint, session=session, **node) as stats,
        open_session(ZenohOptions(connect=(endpoint,))) as zsession,
    ):
        zsession.declare_subscriber(
            f"msk/{session}/activations/*",
            lambda s: frames.append(messages.decode("msk.ActivationFrame", s.payload.to_bytes())),
        )
        joints = declare_data_publisher(zsession, topics.joints_key(session), "msk.JointAngles")
        wait_matching(joints)
        yield EstimatorClient(zsession, joints, frames, stats)
