"""`msk subscribe` takes its inputs through services.nodes.node_runtime.NodeInputs: unusable payloads on any topic are
dropped and counted (the counts printed at the end), the valid messages after them are printed; a key expression of
one topic type expects that type, a broader one each key's type from the topic table."""

from __future__ import annotations

import json

import pytest

from msk_core.errors import ConfigError
from services.commands.subscribe import expected_type
from services.transport import messages
from services.transport.zenoh_session import ZenohOptions, open_session
from tests.dashboard_helpers import BAD_INPUT_TOPICS, BadInputs
from tests.live_helpers import start_subscribe


def test_expected_type_of_a_key_expression():
    assert expected_type("msk/lab/activations/*") == "msk.ActivationFrame"
    assert expected_type("msk/*/imu/00B4EB80") == "msk.ImuSample"
    assert expected_type("msk/lab/status/**") == "msk.DeviceStatus"
    assert expected_type("msk/lab/**") is None and expected_type("msk/lab/*") is None  # several types: per key
    with pytest.raises(ConfigError, match="matches no msk topic"):
        expected_type("other/**")
    with pytest.raises(ConfigError, match="not a valid key expression"):
        expected_type("msk//a")


def test_msk_subscribe_prints_valid_messages_and_counts_the_unusable_ones(repo_root, zenoh_endpoint):
    process = start_subscribe("msk/bad/**", "--count", "2", "--duration", "60", "--listen", zenoh_endpoint)
    try:
        with open_session(ZenohOptions(connect=(zenoh_endpoint,))) as zsession:
            inputs = BadInputs(zsession, "bad")
            inputs.wait_matched(BAD_INPUT_TOPICS)
            inputs.publish_every_kind()
            inputs.good("activations/so", messages.ActivationFrame(method="so", groups=["BicLong"], activations=[0.4]))
            inputs.good("load", messages.LoadEvent(barbell_mass_kg=80, exercise="deadlift", set_number=1))
            out, err = process.communicate(timeout=60)
            inputs.close()
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, err
    printed = {line["key"]: line for line in map(json.loads, out.splitlines())}
    assert sorted(printed) == ["msk/bad/activations/so", "msk/bad/load"]
    assert printed["msk/bad/load"]["message"]["barbell_mass_kg"] == 80
    assert printed["msk/bad/activations/so"]["type"] == "msk.ActivationFrame"
    summary = err.strip().splitlines()[-1]
    assert summary.startswith("msk subscribe: 2 messages on msk/bad/**; dropped 5 ("), summary
    for (key, reason), n in inputs.expected.items():
        assert f"{key}: {reason} {n}" in summary
