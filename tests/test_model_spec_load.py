"""A pack spec says whether the pack carries a hand load: `load_points` (and `load_share`) for a barbell or a box, none
for a pack whose external loads come from force plates (a walk) or that has none. Invalid values are precise errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from msk_core.errors import ConfigError
from msk_core.model.spec import load_spec, parse_spec
from tests.conftest import SPECS_DIR

BASE = """name = "t"
[coordinates]
knee_angle_r = { range_deg = [-80, 0], reference_deg = 0 }
[groups]
vas_lat_r = ["vas_lat_r"]
"""


def _spec(dynamics: str):
    return parse_spec(BASE + "[dynamics]\n" + dynamics, Path("t.toml"))


def test_shipped_specs_keep_their_loads_and_the_walk_has_none():
    shares = {
        name: load_spec(SPECS_DIR / f"{name}.toml").dynamics
        for name in ("arm26", "lumbar_lift", "bench_press", "deadlift")
    }
    assert {n: (d.has_hand_load, d.load_share, len(d.load_points)) for n, d in shares.items()} == {
        "arm26": (True, 1.0, 1),
        "lumbar_lift": (True, 1.0, 2),
        "bench_press": (True, 0.5, 1),
        "deadlift": (True, 0.5, 2),
    }
    gait = load_spec(SPECS_DIR / "gait2392.toml").dynamics
    assert not gait.has_hand_load and gait.load_points == ()


def test_no_load_is_said_by_leaving_the_load_out():
    assert not _spec('root = "ground"\n').dynamics.has_hand_load
    assert not _spec('root = "ground"\nload_points = []\n').dynamics.has_hand_load
    # a shared-body pack without a hand load keeps load_share for the shared bodies' mass
    shared = _spec('shared_from = "pelvis"\nload_share = 0.5\n').dynamics
    assert not shared.has_hand_load and shared.load_share == 0.5
    loaded = _spec('load_points = [{ body = "tibia_r", point = [0, -0.4, 0] }]\n').dynamics
    assert loaded.has_hand_load and loaded.load_share == 1.0


@pytest.mark.parametrize(
    ("dynamics", "field", "message"),
    [
        (
            "load_share = 0\n",
            "dynamics.load_share",
            r"must be a number in \(0, 1\].*leaves load_points and load_share out",
        ),
        (
            'load_points = [{ body = "tibia_r", point = [0, 0, 0] }]\nload_share = 1.5\n',
            "dynamics.load_share",
            r"must be a number in \(0, 1\]",
        ),
        (
            'load_points = [{ body = "tibia_r", point = [0, 0, 0] }]\nload_share = "half"\n',
            "dynamics.load_share",
            r"must be a number",
        ),
        (
            'load_points = [{ body = "tibia_r", point = [0, 0, 0] }]\nload_share = true\n',
            "dynamics.load_share",
            r"must be a number",
        ),
        ("load_share = 0.5\n", "dynamics.load_share", "shares nothing: this pack has no hand load"),
        ('load_points = { body = "tibia_r" }\n', "dynamics.load_points", "must be a list"),
        ('load_points = [{ body = "tibia_r", point = [0, "a", 0] }]\n', "dynamics.load_points", "entries are"),
        ("load_shares = 0.5\n", "dynamics.load_shares", "unknown key.*closest: load_share"),
        ("gravity = [0, -9.8]\n", "dynamics.gravity", r"must be \[x, y, z\]"),
    ],
)
def test_invalid_load_values_name_the_field_and_line(dynamics, field, message):
    with pytest.raises(ConfigError, match=message) as err:
        _spec(dynamics)
    assert err.value.field == field and "t.toml" in str(err.value)
    assert err.value.line == len(BASE.splitlines()) + 1 + next(
        i for i, line in enumerate(dynamics.splitlines(), start=1) if field.split(".")[1] in line
    )
