"""The command-line flags every node process shares: the graph's readiness (``--ready-key``, ``--ready-after``),
which :meth:`services.sessions.graph.Graph.add_process` appends and each node reads with one function."""

from __future__ import annotations

import argparse

import pytest

from msk_core.errors import ConfigError
from services.nodes import estimator, kinematics_node, recorder
from services.nodes.readiness import ReadySpec, ready_from_args, ready_key


@pytest.mark.parametrize(
    ("add_arguments", "required"),
    [
        (estimator.add_arguments, ["--pack", "p", "--session", "s"]),
        (kinematics_node.add_arguments, ["--pack", "p", "--session", "s"]),
        (recorder.add_arguments, ["--out", "x.mcap"]),
    ],
)
def test_a_node_reads_the_token_key_and_the_nodes_it_publishes_to(add_arguments, required):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    flags = ["--ready-key", ready_key("lab", "estimator"), "--ready-after", "recorder", "--ready-after", "view"]
    assert ready_from_args(parser.parse_args([*required, *flags])) == ReadySpec(
        "lab", "estimator", ("recorder", "view")
    )
    assert ready_from_args(parser.parse_args(required)) is None


def test_a_key_outside_msk_is_refused():
    args = argparse.Namespace(ready_key="other/lab/graph/estimator", ready_after=[])
    with pytest.raises(ConfigError):
        ready_from_args(args)
