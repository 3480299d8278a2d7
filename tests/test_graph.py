"""services.sessions.graph and services.nodes.readiness: readiness over Zenoh liveliness, late subscribers, bounded waits that say what is missing."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from services.nodes.readiness import GraphTimeout, declare_ready, wait_for_nodes
from services.sessions.graph import Graph, kill_live, pids_path, wait_for
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session, publish

SESSION = "graphtest"
N_MESSAGES = 300


def counting_node(
    options: ZenohOptions, *, counts: dict, label: str, delay_s: float, stop_event, ready_event, ready_key
):
    """Joins the network at once but declares its subscriber only after ``delay_s`` (a slow-starting node)."""
    with open_session(options) as zsession:
        time.sleep(delay_s)
        counts[label] = 0

        def on_sample(_sample) -> None:
            counts[label] += 1

        subscriber = zsession.declare_subscriber(f"{topics.session_prefix(SESSION)}/load", on_sample)
        token = declare_ready(zsession, ready_key)  # noqa: F841
        ready_event.set()
        stop_event.wait(30)
        subscriber.undeclare()


def test_publisher_waits_for_every_node_even_one_that_subscribes_late(zenoh_endpoint):
    counts: dict[str, int] = {}
    with Graph(SESSION, zenoh_endpoint) as graph:
        graph.add_thread("early", counting_node, counts=counts, label="early", delay_s=0.0)
        graph.add_thread("late", counting_node, counts=counts, label="late", delay_s=1.5)
        with open_session(ZenohOptions(connect=(zenoh_endpoint,))) as zsession:
            publisher = declare_data_publisher(zsession, topics.load_key(SESSION), "msk.LoadEvent")
            # Zenoh's matching status turns true with the first subscriber: publishing then would lose the late one's
            deadline = time.monotonic() + 10
            while not publisher.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.01)
            assert publisher.matching_status.matching and "late" not in counts
            waited = wait_for_nodes(zsession, SESSION, graph.nodes, timeout_s=20)
            assert waited > 0.5  # it did wait for the late node
            for i in range(N_MESSAGES):
                publish(publisher, messages.LoadEvent(barbell_mass_kg=float(i)))
            wait_for(
                "both nodes to count every message",
                lambda: all(counts.get(n) == N_MESSAGES for n in ("early", "late")),
                lambda: str(counts),
                timeout_s=20,
            )
    assert counts == {"early": N_MESSAGES, "late": N_MESSAGES}


def test_wait_for_nodes_names_what_is_missing_when_it_expires(zenoh_endpoint):
    with Graph(SESSION, zenoh_endpoint) as graph:
        graph.add_thread("present", counting_node, counts={}, label="present", delay_s=0.0)
        graph.wait_ready(20)
        with open_session(ZenohOptions(connect=(zenoh_endpoint,))) as zsession:
            with pytest.raises(GraphTimeout, match=r"2 nodes .*1 ready, missing \['absent'\]"):
                wait_for_nodes(zsession, SESSION, ["present", "absent"], timeout_s=1.0)
    with pytest.raises(GraphTimeout, match=r"waited 0.2 s for the answer; arrived: 41 of 42"):
        wait_for("the answer", lambda: False, lambda: "41 of 42", timeout_s=0.2)


def test_a_thread_node_never_ready_is_named_with_the_whole_wait(zenoh_endpoint):
    """A thread node (msk live's monitor, the demo's recorder) that never became ready made the graph say "waited 0.1 s
    for N nodes" after the whole wait: the thread phase broke out and left the observer 0.1 s."""
    with Graph(SESSION, zenoh_endpoint) as graph:
        graph.add_thread("present", counting_node, counts={}, label="present", delay_s=0.0)
        graph.add_thread("stuck", counting_node, counts={}, label="stuck", delay_s=3.0)
        started = time.monotonic()
        with pytest.raises(
            GraphTimeout,
            match=r"waited 1.5 s for node stuck \(a thread of this process\).*1 of its 2 thread nodes ready",
        ):
            graph.wait_ready(1.5)
        assert 1.4 < time.monotonic() - started < 5


def failing_node(options, *, stop_event, ready_event, ready_key):
    raise RuntimeError("device not found")


def test_a_node_that_fails_at_start_is_reported_and_the_graph_stops(zenoh_endpoint):
    graph = Graph(SESSION, zenoh_endpoint)
    graph.add_thread("broken", failing_node)
    with pytest.raises(RuntimeError, match="device not found"):
        graph.wait_ready(10)
    assert graph.failed() == ["broken: RuntimeError('device not found')"]
    started = time.monotonic()
    graph.stop(5)
    assert time.monotonic() - started < 5
    assert not any(t.name == "node-broken" for t in threading.enumerate())


def test_msk_replay_waits_for_named_graph_nodes(zenoh_endpoint):
    from tests.dashboard_helpers import DEMO_MCAP
    from tests.live_helpers import run_msk

    def replay_waiting_for(*options: str) -> subprocess.CompletedProcess[str]:
        """msk replay of the demo session into this graph, waiting for the node "late", then ``options``."""
        demo = ("replay", str(DEMO_MCAP), "--session", SESSION, "--connect", zenoh_endpoint, "--wait-node", "late")
        return run_msk(*demo, *options, timeout=120)

    counts: dict[str, int] = {}
    with Graph(SESSION, zenoh_endpoint) as graph:
        graph.add_thread("late", counting_node, counts=counts, label="late", delay_s=1.5)
        raw = ("--exclude", f"msk/{SESSION}/imu/*", "--exclude", f"msk/{SESSION}/emg/*")
        replay = replay_waiting_for("--rate", "max", *raw, "--exclude", f"msk/{SESSION}/joints")
        assert replay.returncode == 0, replay.stderr
        assert "published 8 messages" in replay.stderr
        wait_for("the late node to count the 8 load events", lambda: counts.get("late") == 8, lambda: str(counts), 20)
        missing = replay_waiting_for("--wait-node", "ghost", "--wait-nodes-timeout", "1")
    assert missing.returncode == 2 and "1 ready, missing ['ghost']" in missing.stderr, missing.stderr


def test_kill_live_kills_msk_live_and_the_nodes_it_listed(tmp_path: Path) -> None:
    """kill_live: the process group of msk live and those of the nodes in its pids.json (each a group of its own)."""
    live = subprocess.Popen(["sleep", "60"], start_new_session=True)
    node = subprocess.Popen(["sleep", "60"], start_new_session=True)
    try:
        pids_path(tmp_path).parent.mkdir(parents=True)
        pids_path(tmp_path).write_text(json.dumps({"estimator": node.pid, "gone": 2**22 + 7}) + "\n")
        kill_live(live, tmp_path)
        assert live.wait(10) == -9 and node.wait(10) == -9, (live.returncode, node.returncode)
    finally:
        for p in (live, node):
            if p.poll() is None:
                p.kill()
                p.wait(10)


def test_a_node_process_that_exits_while_the_graph_waits_is_reported_at_once_with_its_log(zenoh_endpoint, tmp_path):
    graph = Graph(SESSION, zenoh_endpoint)
    # exits after the graph has begun waiting on Zenoh (past the check made before it), never declaring its token
    script = "import sys, time; time.sleep(1.5); print('no device on /dev/ttyUSB0'); sys.exit(2)"
    graph.add_process("late-fail", [sys.executable, "-c", script], log_path=tmp_path / "late-fail.log")
    started = time.monotonic()
    with pytest.raises(GraphTimeout, match=r"late-fail \(exit 2\)[\s\S]*no device on /dev/ttyUSB0") as raised:
        graph.wait_ready(60)
    assert time.monotonic() - started < 15, "waited for a node that had exited"
    assert "missing ['late-fail']" in str(raised.value)
    graph.stop(5)
