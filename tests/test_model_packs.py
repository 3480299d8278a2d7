"""Shipped fullbody / lumbar packs vs OpenSim on fresh random poses (kept small: OpenSim is slow on fullbody)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from msk_core.model import load_pack

pytest.importorskip("opensim")

from msk_core.model.check import check_dynamics, check_hanging_static, check_muscles  # noqa: E402
from msk_core.model.reference_id import compare_with_recorded_id  # noqa: E402

DEADLIFT_GROUPS = [
    "ESL",
    "ESI",
    "MUL",
    "RA",
    "IO",
    "EO",
    "TFL",
    "AddLong",
    "Gmax",
    "PM",
    "RF",
    "ST",
    "BF",
    "Gmed",
    "TA",
    "GL",
    "GM",
    "VL",
    "VM",
]
BENCH_GROUPS = [
    "BRA",
    "BRD",
    "TriLat",
    "BicLong",
    "BicSho",
    "TriLong",
    "DelAnt",
    "DelMed",
    "DelPos",
    "PMCla",
    "PMSte",
    "PMCos",
    "LD",
]
# groups whose OpenSim path switches wrap objects inside the range (moment arm jumps): documented in docs/models.md
WRAP_JUMP_GROUPS = {"RA", "EO", "GL", "GM", "BRA", "TriLat", "TriLong"}


def test_pack_group_names():
    assert load_pack("deadlift").groups == DEADLIFT_GROUPS
    assert load_pack("bench_press").groups == BENCH_GROUPS
    lumbar = load_pack("lumbar_lift")
    assert lumbar.coordinates == ["L5_S1_Flex_Ext"]
    assert lumbar.groups[:8] == [
        "rectabd_r",
        "rectabd_l",
        "iliocost_r",
        "iliocost_l",
        "longlumb_r",
        "longlumb_l",
        "longthor_r",
        "longthor_l",
    ]


def test_every_shipped_pack_is_every_pack_protocol_the_estimator_reads(repo_root):
    """msk_core.estimate.pack lists what the estimator and the discrepancy workflow read of a pack (PackLike, and
    RangedPackLike, PosedPackLike, MusclePackLike read after an isinstance check, so mypy checks the reads): every
    shipped pack is all of them, and nothing outside msk_core/model reads a pack's member by name (getattr), which
    mypy cannot check."""
    from msk_core.estimate.pack import MusclePackLike, PackLike, PosedPackLike, RangedPackLike, fitted_ranges
    from msk_core.model.pack import available_packs

    for name in available_packs():
        pack = load_pack(name)
        for protocol in (PackLike, RangedPackLike, PosedPackLike, MusclePackLike):
            assert isinstance(pack, protocol), (name, protocol.__name__)
        ranges = fitted_ranges(pack)
        assert ranges is not None and np.array_equal(np.column_stack(ranges), pack.coordinate_ranges), name
    by_name = re.compile(r"getattr\(\s*(self\.)?_?\w*pack\b")
    readers = [
        f"{path.relative_to(repo_root)}:{number}"
        for folder in ("msk_core", "services", "drivers")
        for path in sorted((repo_root / folder).rglob("*.py"))
        if path.relative_to(repo_root).parts[:2] != ("msk_core", "model")
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if by_name.search(line)
    ]
    assert readers == [], readers


def test_lumbar_groups_are_the_ceinms_channels(shared_dir):
    text = (shared_dir / "data" / "backmodel-lift" / "ceinms_uncalibrated.xml").read_text()
    channels = re.findall(r"<Channel>\s*<name>(\w+)</name>\s*<muscleSequence>([^<]+)</muscleSequence>", text)
    pack = load_pack("lumbar_lift")
    assert len(channels) == 8
    for name, members in channels:
        assert pack.members[name] == members.split()
    assert sum(len(v) for v in pack.members.values()) == 166  # every muscle of the model, once


@pytest.mark.parametrize(
    ("name", "model", "poses"),
    [("lumbar_lift", "lumbar_scaled.osim", 20), ("bench_press", "fullbody.osim", 10), ("deadlift", "fullbody.osim", 5)],
)
def test_moment_arms_vs_opensim(shared_dir, name, model, poses):
    pack = load_pack(name)
    report = check_muscles(pack, shared_dir / "models" / model, n_poses=poses, seed=99)
    for group, stats in report["groups"].items():
        worst = max(stats["moment_arm_max_mm"].values())
        rms = max(stats["moment_arm_rms_mm"].values())
        if group in WRAP_JUMP_GROUPS:
            assert worst < 40.0, (group, stats)
        else:
            assert worst < 2.0 and rms < 1.0, (group, stats)
        # against the derivative of OpenSim's own path length the groups without path switches meet the issue's
        # 2 mm max; RA/EO (deadlift: sums over six lumbar levels of ~400-950 mm) stay within ~1 % of their size
        assert max(stats["path_derivative_max_mm"].values()) < (10.0 if group in WRAP_JUMP_GROUPS else 2.0), (
            group,
            stats,
        )


@pytest.mark.parametrize(
    ("name", "model"),
    [("lumbar_lift", "lumbar_scaled.osim"), ("bench_press", "fullbody.osim"), ("deadlift", "fullbody.osim")],
)
def test_inverse_dynamics_vs_opensim(shared_dir, name, model):
    pack = load_pack(name)
    report = check_dynamics(pack, shared_dir / "models" / model, n_poses=12, seed=3, hand_load=300.0)
    # exact joints are exact; the rolling knee and the patella are 6-DoF polynomial chains (fit error ~1e-6 m)
    for coord, pct in report["max_error_percent_of_peak"].items():
        assert pct < (0.1 if coord in ("hip_flexion_r", "knee_angle_r", "ankle_angle_r") else 1e-4), (coord, report)


def test_deadlift_foot_rooted_dynamics():
    pack = load_pack("deadlift")
    q = np.radians([5.0, 60.0, 50.0, 15.0])
    zeros = np.zeros(4)
    loaded = pack.inverse_dynamics(q, zeros, zeros, 1000.0)
    free = pack.inverse_dynamics(q, zeros, zeros, 0.0)
    # with the legs at the reference pose both trees put the trunk in the same place: the lumbar torque (whole
    # trunk, whole bar) equals the pelvis-rooted model's -- the halving and doubling cancel exactly
    upright = np.radians([5.0, 0.0, 0.0, 0.0])
    for load in (0.0, 1000.0):
        foot = pack.inverse_dynamics(upright, zeros, zeros, load)
        pelvis = pack.validation_rigid.inverse_dynamics(upright - pack.reference_pose, zeros, zeros, load, None)
        assert foot[0] == pytest.approx(pelvis[0], rel=1e-7)
    val = pack.validation_rigid.inverse_dynamics(q - pack.reference_pose, zeros, zeros, 1000.0, None)
    # the bar loads every joint of the leg (half of it per leg), unlike a pelvis-rooted model
    assert np.all(np.abs(loaded[1:] - free[1:]) > 5.0)
    assert np.all(
        np.abs(val[1:] - pack.validation_rigid.inverse_dynamics(q - pack.reference_pose, zeros, zeros, 0.0, None)[1:])
        < 1e-9
    )
    # the modelled side carries the right leg plus half of everything from the pelvis up
    masses, full = pack.rigid.body_masses(), pack.validation_rigid.body_masses()
    assert masses["femur_r"] == pytest.approx(full["femur_r"])
    assert masses["head_neck"] == pytest.approx(0.5 * full["head_neck"])
    assert "pelvis" in masses and "pelvis" not in full  # the pelvis moves when rooted at the foot
    assert "femur_l" not in masses  # the left leg stands on its own foot


def test_deadlift_arms_hang_plumb(shared_dir):
    """Pack 1.1: the bar hangs below the shoulders whatever the trunk angle (arms as pendulums), checked twice."""
    pack = load_pack("deadlift")
    zeros = np.zeros(4)
    # (1) the bar's lever about the hip changes with the trunk angle exactly as the shoulder's horizontal position
    #     does: leaning the trunk forward moves the bar forward (with arms locked to the thorax it moved backward)
    upright, leaning = np.radians([0.0, 75.0, 60.0, 15.0]), np.radians([-3.5, 75.0, 60.0, 15.0])
    bar = [
        pack.inverse_dynamics(q, zeros, zeros, 1000.0) - pack.inverse_dynamics(q, zeros, zeros, 0.0)
        for q in (upright, leaning)
    ]
    assert bar[1][1] < bar[0][1] < 0.0  # more hip extension moment from the bar when leaning further forward
    # (2) OpenSim with the real arm bodies, the shoulder flexion solved so the hand hangs plumb (static poses)
    report = check_hanging_static(
        pack,
        shared_dir / "models" / "fullbody.osim",
        swing={"humerus_r": "elv_angle_r", "humerus_l": "elv_angle_l"},
        n_poses=8,
        hand_load=735.0,
    )
    for coord, pct in report["max_error_percent_of_peak"].items():
        assert pct < 0.5, (coord, report)


def test_lumbar_lift_vs_recorded_id(shared_dir):
    """Pack torque vs the recorded OpenSim ID of the real lifts (arms and upper lumbar levels locked in the pack)."""
    pack = load_pack("lumbar_lift")
    lift = shared_dir / "data" / "backmodel-lift"
    for trial in ("squat5kg", "stoop5kg"):
        report = compare_with_recorded_id(
            pack,
            shared_dir / "models" / "lumbar_scaled.osim",
            lift / trial / "ik.sto",
            lift / trial / "id.sto",
            hand_load_newton=5 * 9.80665,
        )
        assert report["correlation"]["L5_S1_Flex_Ext"] > 0.75, report["correlation"]
        assert report["rms_error_percent_of_peak"]["L5_S1_Flex_Ext"] < 30.0, report["rms_error_percent_of_peak"]


def test_recompile_dynamics_reproduces_the_shipped_deadlift(shared_dir):
    import json  # noqa: PLC0415

    from msk_core.errors import ConfigError  # noqa: PLC0415
    from msk_core.model.compile import recompile_dynamics  # noqa: PLC0415
    from msk_core.model.spec import load_spec, parse_spec  # noqa: PLC0415

    pack = load_pack("deadlift")
    spec_path = Path(__file__).resolve().parents[1] / "msk_core" / "model" / "specs" / "deadlift.toml"
    spec = load_spec(spec_path)
    raw = json.loads(json.dumps(pack.raw))
    out = recompile_dynamics(raw, shared_dir / "models" / "fullbody.osim", spec)
    for key in ("dynamics", "validation_dynamics"):
        np.testing.assert_allclose(np.array(out[key]["gains"]), np.array(pack.raw[key]["gains"]), atol=1e-12)
        for a, b in zip(out[key]["bodies"], pack.raw[key]["bodies"]):
            assert a["name"] == b["name"] and a.get("hanging_from") == b.get("hanging_from")
            np.testing.assert_allclose(a["com"], b["com"], atol=1e-12)
    assert out["length_coefficients"] == pack.raw["length_coefficients"]
    changed = parse_spec(spec.text.replace('TA = ["tibant_r"]', 'TA = ["tibant_r", "perlong_r"]'))
    with pytest.raises(ConfigError, match="groups"):
        recompile_dynamics(raw, shared_dir / "models" / "fullbody.osim", changed)
