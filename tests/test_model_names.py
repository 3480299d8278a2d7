"""Display names: every shipped pack names every group and coordinate (with its unit) in its spec, and carries that
spec; a pack without names falls back to the model names; bad [names] tables are refused naming file, line, field and
value; a session's names override the pack's."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from msk_core.errors import ConfigError, ModelError
from msk_core.model import available_packs, load_pack
from msk_core.model.names import MAX_NAME_CHARS, fallback_names, parse_names
from msk_core.model.pack import names_of, pack_display_names, with_names
from msk_core.model.spec import load_spec, parse_spec
from tests.conftest import KNEE_SPEC, SPECS_DIR

SPEC = KNEE_SPEC + 'RF = ["recfem_r"]\n'


@pytest.mark.parametrize("name", available_packs())
def test_every_shipped_pack_names_every_group_and_coordinate(name):
    names = pack_display_names(name)
    pack = load_pack(name)
    assert names.missing == (), (
        f"{name}: no display name for {', '.join(names.missing)} (add them to [names] of "
        f"msk_core/model/specs/{name}.toml and refresh the pack with with_names)"
    )
    assert list(names.groups) == pack.groups and list(names.coordinates) == pack.coordinates
    assert pack.display_names == names
    for model_name, display in (names.groups | names.coordinates).items():
        assert display != model_name and display[0].isupper(), (name, model_name, display)
    assert {names.unit(c) for c in pack.coordinates} == {"deg"}  # every pack coordinate is a rotation
    assert {names.torque_unit(c) for c in pack.coordinates} == {"N·m"}
    # the pack carries the spec it names them from: changing the spec file without refreshing the pack fails here
    assert pack.raw["spec"] == (SPECS_DIR / f"{name}.toml").read_text()
    assert len(set(names.groups.values())) == len(names.groups), f"{name}: two groups share a display name"


def test_a_few_names_people_use():
    bench, deadlift = pack_display_names("bench_press"), pack_display_names("deadlift")
    assert bench.group("TriLat") == "Triceps brachii, lateral and medial heads"
    assert bench.group("PMCla") == "Pectoralis major, clavicular part"
    assert bench.coordinate("elv_angle_r") == "Shoulder flexion" and bench.unit("elv_angle_r") == "deg"
    assert deadlift.group("VL") == "Vastus lateralis" and deadlift.coordinate("knee_angle_r") == "Knee flexion"
    assert bench.as_dict()["coordinates"]["elbow_flex_r"] == {
        "name": "Elbow flexion",
        "unit": "deg",
        "torque_unit": "N·m",
    }


def test_a_pack_without_names_shows_its_model_names():
    spec = parse_spec(SPEC, Path("t.toml"))
    names = spec.display_names()
    assert names.groups == {"VL": "VL", "RF": "RF"} and names.coordinate("knee_angle_r") == "knee_angle_r"
    assert names.missing == ("VL", "RF", "knee_angle_r")
    data = json.loads(json.dumps(load_pack("arm26").raw))
    data.pop("spec")  # a pack compiled before specs were embedded
    assert names_of(data).missing == (*data["groups"], *data["coordinates"])
    assert names_of(data) == fallback_names(data["groups"], data["coordinates"])
    assert names.group("not_in_this_pack") == "not_in_this_pack" and names.unit("not_in_this_pack") == ""


def test_partial_names_and_the_legend_of_abbreviations():
    spec = parse_spec(SPEC + '[names]\nVL = "Vastus lateralis"\n', Path("t.toml"))
    names = spec.display_names()
    assert names.groups == {"VL": "Vastus lateralis", "RF": "RF"} and names.missing == ("RF", "knee_angle_r")
    assert names.legend(["VL", "RF"]) == "VL: Vastus lateralis"  # RF has no other name to explain


@pytest.mark.parametrize(
    ("table", "field", "message", "line"),
    [
        (
            'VLL = "Vastus lateralis"',
            "names.VLL",
            # the table may be right and the group misspelt where the pack defines it
            "not a muscle group or coordinate of the pack (closest: VL; or is 'VL' the misspelt one, where the pack",
            8,
        ),
        ("VL = 3", "names.VL", "must be a display name", 8),
        ('VL = ""', "names.VL", "must be a display name", 8),
        ('VL = "Vastus\\nlateralis"', "names.VL", "one line of printable text", 8),
        ('VL = " Vastus lateralis"', "names.VL", "without surrounding spaces", 8),
        (f'VL = "{"V" * (MAX_NAME_CHARS + 1)}"', "names.VL", f"at most {MAX_NAME_CHARS} characters", 8),
    ],
)
def test_bad_names_are_refused_naming_file_line_field_and_value(table, field, message, line):
    with pytest.raises(ConfigError, match="t.toml") as error:
        parse_spec(SPEC + "[names]\n" + table + "\n", Path("t.toml"))
    assert error.value.field == field and error.value.line == line and message in str(error.value)
    assert error.value.value is not None


def test_names_must_be_a_table():
    with pytest.raises(ConfigError, match="must be a table") as error:
        parse_spec('names = "Vastus"\n' + SPEC, Path("t.toml"))
    assert error.value.field == "names" and error.value.value == "Vastus"


def test_a_sessions_names_override_the_packs():
    bench = pack_display_names("bench_press")
    overrides = parse_names(
        {"PMCla": "Upper chest", "elbow_flex_r": "Elbow"}, [*bench.groups, *bench.coordinates], path=Path("monday.toml")
    )
    named = bench.with_overrides(overrides | {"VL": "a group of another pack"})
    assert named.group("PMCla") == "Upper chest" and named.coordinate("elbow_flex_r") == "Elbow"
    assert named.group("BRA") == "Brachialis" and named.overridden == ("PMCla", "elbow_flex_r")
    assert "VL" not in named.groups and bench.group("PMCla") == "Pectoralis major, clavicular part"  # pack unchanged
    with pytest.raises(ConfigError, match="monday.toml.*names.PMCl.*closest: PMCla"):
        parse_names({"PMCl": "Upper chest"}, list(bench.groups), path=Path("monday.toml"))


def test_with_names_refreshes_only_the_names():
    data = json.loads(json.dumps(load_pack("arm26").raw))
    spec = load_spec(SPECS_DIR / "arm26.toml")
    renamed = parse_spec(spec.text.replace('BRA = "Brachialis"', 'BRA = "Brachialis muscle"'), Path("arm26.toml"))
    assert names_of(with_names(data, renamed)).group("BRA") == "Brachialis muscle"
    assert names_of(data).group("BRA") == "Brachialis"  # the input is not changed
    refit = parse_spec(spec.text.replace("samples = 400", "samples = 500"), Path("arm26.toml"))
    with pytest.raises(ModelError, match=r"arm26.toml: differs .* in \[fit\], not only in \[names\]: recompile"):
        with_names(data, refit)


def test_the_names_a_surface_shows_for_frames():
    from msk_core.model.pack import names_for

    assert names_for("bench_press", ["TriLat", "BRA"]).group("BRA") == "Brachialis"
    assert names_for("bench_press", ["TriLat"], {"TriLat": "Triceps"}).group("TriLat") == "Triceps"
    # frames of another pack, or of a pack that is not shipped: their model names
    assert names_for("deadlift", ["TriLat"]).group("TriLat") == "TriLat"
    assert names_for("my_pack", ["A"]).groups == {"A": "A"} and names_for("", ["A"]).missing == ("A",)
