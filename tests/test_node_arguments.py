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


def _kinematics(argv: list[str]) -> kinematics_node.KinematicsSettings:
    parser = argparse.ArgumentParser()
    kinematics_node.add_arguments(parser)
    return kinematics_node.KinematicsSettings.from_args(parser.parse_args(argv))


def test_kinematics_settings_of_the_command_line_and_of_msk_live_read_back(tmp_path):
    from services.sessions import live
    from services.sessions.live_session import LiveSession

    assert _kinematics(["--pack", "bench_press", "--session", "lab"]) == kinematics_node.KinematicsSettings(
        "bench_press", "lab", latency_ns={}
    )
    session = LiveSession(tmp_path / "lab.toml", name="lab", pack="deadlift")
    plan = live.LivePlan(session, ("so",), tmp_path / "subject.json", tracker_latency_ms={"00B4EB80": 5.0, "t2": 0.3})
    settings = live.kinematics_settings(plan)
    assert settings.clock == "host" and settings.latency_ns == {"00B4EB80": 5_000_000, "t2": 300_000}
    argv = live.node_argv(plan, "kinematics", tmp_path / "x.mcap")
    assert _kinematics(argv[argv.index("--pack") :]) == settings
    full = kinematics_node.KinematicsSettings(
        "bench_press",
        "lab",
        output_session="kin",
        facing_deg=90.0,
        static_pose_deg={"elbow_flex_r": 15.5},
        static_s=0.25,
        gap_s=2.0,
        sync_tolerance_s=0.012,
        imu_rate_hz=100.0,
        jerk_std=40.0,
        angle_std_deg=0.5,
        phase_template=tmp_path / "profile.json",
        phase_coordinate="elbow_flex_r",
        clock="host",
        latency_ns={"00B4EB80": 1_234_567},
        default_latency_ns=2_000_000,
    )
    assert _kinematics(full.argv()) == full


@pytest.mark.parametrize(
    ("given", "field"),
    [
        (dict(static_s=0.0), "--static-s"),
        (dict(gap_s=float("nan")), "--gap"),
        (dict(imu_rate_hz=-60.0), "--imu-rate"),
        (dict(clock="gps"), "--imu-clock"),
        (dict(phase_coordinate="elbow_flex_r"), "--phase-coordinate"),
    ],
)
def test_refused_kinematics_settings_name_their_option(given, field):
    with pytest.raises(ConfigError) as err:
        kinematics_node.KinematicsSettings("bench_press", "lab", **given)
    assert err.value.field == field
