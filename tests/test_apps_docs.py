"""docs/apps.md: the Python subscriber block runs against a replay of the demo session through an estimator node, and
`msk subscribe` prints decoded frames (text and JSON)."""

from __future__ import annotations

import json
import re
import subprocess
import sys

from services.nodes import estimator
from services.sessions.graph import Graph, wait_for
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session
from tests.dashboard_helpers import replay_demo_without_raw
from tests.live_helpers import start_subscribe

SESSION = "appsdoc"


def doc_block(repo_root) -> str:
    blocks = re.findall(r"```python\n(.*?)```", (repo_root / "docs" / "apps.md").read_text(), flags=re.S)
    assert len(blocks) == 1
    return blocks[0]


def test_docs_subscriber_and_msk_subscribe_print_frames_of_a_replay(repo_root, zenoh_endpoint, tmp_path):
    code = doc_block(repo_root).replace('"tcp/127.0.0.1:7447", "sim"', f'"{zenoh_endpoint}", "{SESSION}"')
    assert zenoh_endpoint in code  # the block's constants are where the test expects them
    script = tmp_path / "subscriber.py"
    script.write_text(code)
    with Graph(SESSION, zenoh_endpoint) as graph:
        graph.add_thread("estimator", estimator.main, estimator.EstimatorSettings("bench_press", SESSION, ("so",)))
        graph.wait_ready(60)
        doc = subprocess.Popen(
            [sys.executable, str(script)], cwd=repo_root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        cli = None
        try:
            with open_session(ZenohOptions(connect=(zenoh_endpoint,))) as zsession:
                # the doc subscriber is the only one on activations: a publisher there matches once it is declared
                probe = declare_data_publisher(zsession, f"msk/{SESSION}/activations/probe", "msk.ActivationFrame")
                wait_for(
                    "the doc subscriber to subscribe",
                    lambda: probe.matching_status.matching,
                    lambda: "no subscriber on activations yet",
                    60,
                )
                probe.undeclare()
            cli = start_subscribe(f"msk/{SESSION}/activations/*", "--count", "5", "--connect", zenoh_endpoint)
            stats = replay_demo_without_raw(zenoh_endpoint, SESSION)
            assert stats.published > 5000
            out, err = doc.communicate(timeout=120)
            cli_out, cli_err = cli.communicate(timeout=60)
        finally:
            for p in (doc, cli):
                if p is not None and p.poll() is None:
                    p.kill()
    assert doc.returncode == 0, err
    lines = out.splitlines()
    # callbacks already under way when it stops may print a few more
    assert len(lines) >= 100 and all(line.startswith("so ") for line in lines)
    assert "'TriLong':" in lines[-1]
    assert cli.returncode == 0, cli_err
    decoded = [json.loads(line) for line in cli_out.splitlines()]
    assert len(decoded) == 5 and all(
        d["type"] == "msk.ActivationFrame" and d["message"]["method"] == "so" for d in decoded
    )
    assert len(decoded[0]["message"]["activations"]) == 13 and "5 messages" in cli_err
    assert graph.failed() == []
