"""``KEY=VALUE`` command-line items, parsed in one place (msk_core.errors.parse_pairs) for the estimator's
``--emg-map``, the drivers' ``--segment`` and ``msk synth --pack``."""

from __future__ import annotations

import pytest

from msk_core.errors import ConfigError, parse_pairs
from services.nodes.driver_nodes import parse_segments


def test_pairs_split_at_the_first_equals_sign():
    assert parse_pairs(["a=b", "c=d=e"], field="--x", form="K=V") == {"a": "b", "c": "d=e"}
    assert parse_segments(["00b4eb80=upper_arm"]) == {"00B4EB80": "upper_arm"}


@pytest.mark.parametrize("item", ["a", "=b", "a="])
def test_an_item_without_key_or_value_names_the_option_and_the_item(item):
    with pytest.raises(ConfigError) as err:
        parse_segments([item])
    assert (err.value.field, err.value.value) == ("--segment", item)
    assert "TRACKER=SEGMENT" in str(err.value)


def test_msk_synth_refuses_a_pack_without_its_exercise(tmp_path):
    from services.cli import main

    assert main(["synth", "--exercise", "bench_press", "--pack", "arm26", "--out", str(tmp_path)]) == 2
