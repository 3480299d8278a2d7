"""Balance pairs a pack declares (``[balance]`` of its spec): every shipped pack carries them in its embedded spec,
the declared agonists pull the coordinate its positive way in the model (and the antagonists the other way), and a
bad table is refused naming the file, line, field and value."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import ConfigError
from msk_core.model import available_packs, load_pack
from msk_core.model.pack import balance_of, with_names
from msk_core.model.spec import load_spec, parse_spec
from tests.conftest import KNEE_SPEC, SPECS_DIR

SPEC = KNEE_SPEC + 'ST = ["semiten_r"]\nVL_l = ["vaslat140_l"]\n[balance]\n'


@pytest.mark.parametrize("name", available_packs())
def test_every_shipped_pack_declares_pairs_the_model_agrees_with(name):
    pack = load_pack(name)
    spec = load_spec(SPECS_DIR / f"{name}.toml")
    assert pack.balance == spec.balance == balance_of(pack.raw)
    assert pack.balance.agonist_antagonist, f"{name}: no agonist/antagonist pair declared"
    # over poses spread through the pack's ranges, each agonist's moment arm is positive in most of them and each
    # antagonist's negative: the declaration reads the model's sign convention (the coordinate's display name)
    rng = np.random.default_rng(3)
    lo, hi = pack.coordinate_ranges[:, 0], pack.coordinate_ranges[:, 1]
    arms = np.array([pack.moment_arms(q) for q in lo + (hi - lo) * rng.random((60, len(lo)))])
    for joint in pack.balance.agonist_antagonist:
        c = pack.coordinates.index(joint.coordinate)
        for groups, sign in ((joint.agonists, 1), (joint.antagonists, -1)):
            for g in groups:
                share = float(np.mean(sign * arms[:, c, pack.groups.index(g)] > 0))
                assert share > 0.5, f"{name}: {g} pulls {joint.coordinate} {'+' if sign > 0 else '-'} in {share:.0%}"


def test_left_right_pairs_only_where_the_pack_has_both_sides():
    assert load_pack("lumbar_lift").balance.left_right[0] == ("rectabd_l", "rectabd_r")
    for name in ("arm26", "bench_press", "deadlift", "gait2392"):
        assert load_pack(name).balance.left_right == (), name


def test_a_spec_without_balance_declares_nothing():
    spec = parse_spec(SPEC.replace("[balance]\n", ""))
    assert spec.balance.empty


@pytest.mark.parametrize(
    ("table", "field", "value", "message"),
    [
        ('left_right = [["VL_l", "VX"]]', "balance.left_right[0]", "VX", "not a muscle group of the pack"),
        ('left_right = [["VL", "VL"]]', "balance.left_right[0]", "VL", "a group on both sides of the pair"),
        ('left_right = [["VL_l", "VL"], ["VL", "ST"]]', "balance.left_right[1]", "VL", "another left/right pair"),
        ('left_right = ["VL_l"]', "balance.left_right[0]", "VL_l", "must be [left group, right group]"),
        (
            'agonist_antagonist = [{ coordinate = "knee_flex", agonists = ["ST"], antagonists = ["VL"], label = "K" }]',
            "balance.agonist_antagonist[0].coordinate",
            "knee_flex",
            "not a coordinate of the pack",
        ),
        (
            'agonist_antagonist = [{ coordinate = "knee_angle_r", agonists = ["ST"], antagonists = ["VLX"], '
            'label = "K" }]',
            "balance.agonist_antagonist[0].antagonists",
            "VLX",
            "not a muscle group of the pack (closest: VL",
        ),
        (
            'agonist_antagonist = [{ coordinate = "knee_angle_r", agonists = ["ST", "VL"], antagonists = ["VL"], '
            'label = "K" }]',
            "balance.agonist_antagonist[0].antagonists",
            "VL",
            "a group on both sides",
        ),
        (
            'agonist_antagonist = [{ coordinate = "knee_angle_r", agonists = [], antagonists = ["VL"], label = "K" }]',
            "balance.agonist_antagonist[0].agonists",
            [],
            "non-empty list",
        ),
        (
            'agonist_antagonist = [{ coordinate = "knee_angle_r", agonists = ["ST"], antagonists = ["VL"] }]',
            "balance.agonist_antagonist[0].label",
            None,
            "missing required key",
        ),
        ('left_rigth = [["VL_l", "VL"]]', "balance.left_rigth", "left_rigth", "closest: left_right"),
    ],
)
def test_bad_balance_tables_are_refused_naming_file_line_field_and_value(table, field, value, message):
    path = Path("specs/t.toml")
    with pytest.raises(ConfigError) as caught:
        parse_spec(SPEC + table + "\n", path)
    error = caught.value
    assert error.field == field and error.value == value and error.path == path, error
    assert message in str(error) and "specs/t.toml" in str(error)
    assert error.line == 9, error  # the [balance] line or the one below it holding the value


def test_a_change_of_balance_alone_needs_no_recompile(tmp_path):
    name = "arm26"
    data = json.loads(Path(str(load_pack(name).path)).read_text())
    text = (SPECS_DIR / f"{name}.toml").read_text().replace('label = "Elbow flexors / extensors"', 'label = "Elbow"')
    changed = tmp_path / f"{name}.toml"
    changed.write_text(text)
    refreshed = with_names(data, load_spec(changed))
    assert balance_of(refreshed).agonist_antagonist[0].label == "Elbow"
    broken = tmp_path / "broken.toml"
    broken.write_text(text.replace('antagonists = ["TRIlong"]', 'antagonists = ["TRIlongus"]'))
    with pytest.raises(ConfigError, match="not a muscle group of the pack"):
        load_spec(broken)
