"""The mistakes a biomechanist makes in a spec for their own OpenSim model (found by exploratory QA with the shared
MOBL arm, Rajagopal leg and full-body models): each used to compile a wrong pack without a word, or to end in a
traceback. Now each is refused naming the file, line, field and value, or said when the pack is written."""

from __future__ import annotations

from pathlib import Path

import pytest

from msk_core.errors import ConfigError
from msk_core.model.spec import parse_spec

BASE = """name = "t"
[coordinates]
knee_angle_r = { range_deg = [0, 120], reference_deg = 0 }
[groups]
vas_lat_r = ["vas_lat_r"]
"""


def _refused(text: str) -> ConfigError:
    with pytest.raises(ConfigError) as error:
        parse_spec(text, Path("t.toml"))
    return error.value


@pytest.mark.parametrize(
    ("text", "field", "said"),
    [
        (BASE + "[lock]\nankle_angle_r = { deg = 10 }\n", "lock", "closest: locked"),  # all locks were dropped
        (BASE.replace("reference_deg", "refrence_deg"), "coordinates.knee_angle_r.refrence_deg", "closest: reference"),
        (BASE + "[fit]\nsample = 50\n", "fit.sample", "closest: samples"),
        (BASE + "[fit]\nmax_degree = 0\n", "fit.max_degree", "a whole number >= 1"),  # was a TypeError
        (BASE + "[fit]\nsamples = 2\n", "fit.samples", "a whole number >= 10"),
        (BASE + "[fit]\nholdout = 1.0\n", "fit.holdout", "a share in [0, 1)"),
        (BASE.replace("[0, 120]", "[0, inf]"), "coordinates.knee_angle_r.range_deg", "lower < upper"),  # Overflow
        (BASE + '[locked]\nankle_angle_r = { deg = "zero" }\n', "locked.ankle_angle_r", "{ deg = .. }"),
        (BASE + "[locked]\nknee_angle_r = { deg = 10 }\n", "locked.knee_angle_r", "pack coordinate and locked"),
        (
            BASE.replace("reference_deg = 0 }", "reference_deg = 0, coupled = { knee_angle_r = 0.5 } }"),
            "coordinates.knee_angle_r.coupled",
            "already sets",
        ),
    ],
)
def test_spec_mistakes_are_refused_naming_the_field(text, field, said):
    error = _refused(text)
    assert error.field == field and said in str(error), error
    assert error.line is not None and "t.toml" in str(error)


def test_a_default_reference_outside_the_range_says_it_was_the_default():
    error = _refused(BASE.replace("[0, 120], reference_deg = 0", "[10, 120]"))
    assert "reference_deg 0 (the default) outside range_deg [10, 120]" in str(error), error


@pytest.fixture(scope="module")
def rajagopal(shared_dir):
    from msk_core.model.osim_tools import load_model

    return load_model(shared_dir / "models" / "Rajagopal2016.osim")


@pytest.mark.parametrize(
    ("extra", "field", "said"),
    [
        ("subtalar_angle_r = { range_deg = [-20, 20] }", "coordinates", "is locked in the model at 0"),
        ("knee_angle_r_beta = { range_deg = [0, 100] }", "coordinates", "driven by a coupler constraint"),
    ],
)
def test_a_coordinate_the_model_locks_or_drives_is_refused(rajagopal, extra, field, said):
    """A pack coordinate the model locks, or a coupler constraint drives: zero moment arms and torques throughout."""
    pytest.importorskip("opensim")
    from msk_core.model.osim_tools import OsimPoser

    spec = parse_spec(BASE.replace("[groups]", extra + "\n[groups]"), Path("t.toml"))
    with pytest.raises(ConfigError) as error:
        OsimPoser(*rajagopal, spec)
    assert error.value.field == field and said in str(error.value), error.value
    locked = parse_spec(BASE + "[locked]\nmtp_angle_r = { deg = 20 }\n", Path("t.toml"))  # ignored before
    with pytest.raises(ConfigError, match="'mtp_angle_r' is locked in the model at 0"):
        OsimPoser(*rajagopal, locked)
    OsimPoser(*rajagopal, parse_spec(BASE + "[locked]\nmtp_angle_r = { deg = 0 }\n", Path("t.toml")))  # held there


def test_a_group_that_crosses_no_pack_coordinate_and_a_file_that_is_no_model_are_refused(shared_dir, tmp_path):
    """The brachialis crosses only the elbow: in a shoulder-only pack its moment arms were zero throughout."""
    pytest.importorskip("opensim")
    from msk_core.model.compile import compile_pack

    text = """name = "arm"
[coordinates]
r_shoulder_elev = { range_deg = [0, 90], reference_deg = 0 }
[groups]
BIClong = ["BIClong"]
BRA = ["BRA"]
[fit]
samples = 30
"""
    with pytest.raises(ConfigError, match=r"no muscle of this group \(BRA\) crosses a pack coordinate") as error:
        compile_pack(shared_dir / "models" / "arm26.osim", parse_spec(text, Path("arm.toml")))
    assert error.value.field == "groups.BRA" and error.value.line == 6
    not_a_model = tmp_path / "spec.osim"
    not_a_model.write_text(text)
    with pytest.raises(ConfigError, match="not an OpenSim model OpenSim can read"):
        compile_pack(not_a_model, parse_spec(text, Path("arm.toml")))


def test_ranges_beyond_the_model_or_in_radians_are_said_when_the_pack_is_written(shared_dir):
    pytest.importorskip("opensim")
    from msk_core.model.compile import compile_pack

    text = """name = "arm"
[coordinates]
r_shoulder_elev = { range_deg = [0.1, 2.0], reference_deg = 1 }
r_elbow_flex = { range_deg = [-30, 170], reference_deg = 0 }
[groups]
BIClong = ["BIClong"]
BRA = ["BRA"]
[fit]
samples = 30
"""
    notes = compile_pack(shared_dir / "models" / "arm26.osim", parse_spec(text, Path("arm.toml")))["fit_report"][
        "notes"
    ]
    assert any(
        n.startswith("coordinates.r_elbow_flex: range [-30, 170] deg goes beyond the model's [0, ") for n in notes
    )
    assert "coordinates.r_shoulder_elev: range [0.1, 2] deg is under 5 deg wide: radians typed as degrees?" in notes


def test_a_steep_smooth_path_keeps_its_slope_and_a_kink_does_not():
    """The rectus abdominis of a full-body trunk, its 6 lumbar levels coupled to one pack coordinate, curves at tens of
    m/rad²: every slope sample there was dropped as a path jump, and the pack was 73 mm off OpenSim there."""
    import numpy as np

    from msk_core.model.osim_tools import sample_lengths

    class Path_:
        def __init__(self, length):
            self.length, self.q = length, 0.0

        def getLength(self, _state):  # noqa: N802 - OpenSim's name
            return self.length(self.q)

    paths = {"smooth": Path_(lambda q: 20.0 * q**2), "kink": Path_(lambda q: 0.05 * abs(q - 0.01))}

    class Poser:
        state = None
        model = type("M", (), {"getMuscles": lambda self: type("S", (), {"get": lambda self, n: paths[n]})()})()

        def set(self, q):
            for path in paths.values():
                path.q = float(q[0])

    poses = np.array([[-0.2], [0.01], [0.15]])
    _, derivs = sample_lengths(Poser(), ["smooth", "kink"], poses)
    np.testing.assert_allclose(derivs[:, 0, 0], 40.0 * poses[:, 0], rtol=1e-6)  # slope 40 q at every pose
    assert np.isnan(derivs[1, 1, 0]) and not np.isnan(derivs[[0, 2], 1, 0]).any()  # only the kink's pose has none


def test_a_muscle_in_two_groups_names_both(shared_dir):
    pytest.importorskip("opensim")
    from msk_core.model.compile import compile_pack

    text = """name = "arm"
[coordinates]
r_elbow_flex = { range_deg = [0, 120], reference_deg = 0 }
[groups]
Flexors = ["BIClong", "BRA"]
Brachialis = ["BRA"]
"""
    with pytest.raises(ConfigError, match="a muscle belongs to more than one group: BRA is in Flexors and Brachialis"):
        compile_pack(shared_dir / "models" / "arm26.osim", parse_spec(text, Path("arm.toml")))
