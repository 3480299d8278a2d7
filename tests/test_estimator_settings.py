"""The estimator node's settings (``EstimatorSettings``): built once from its command line, or by ``msk live`` from the
session file and handed to the node process as its command line, which reads back the same settings."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from msk_core.errors import ConfigError
from msk_core.estimate.live_emg import ClockMode, JointsClock
from services.nodes.estimator import ALIGN_ARRIVAL, EmgTiming, EstimatorSettings, add_arguments
from services.sessions import live
from services.sessions.live_session import LiveSession


def _parse(argv: list[str]) -> EstimatorSettings:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return EstimatorSettings.from_args(parser.parse_args(argv))


def test_the_command_line_defaults():
    settings = _parse(["--pack", "bench_press", "--session", "lab"])
    timing = EmgTiming(emg_latency_ns={}, emg_align=ALIGN_ARRIVAL, imu_latency_ns={})  # aligned only on host clocks
    assert settings == EstimatorSettings("bench_press", "lab", ("so",), emg=None, timing=timing)
    assert _parse(["--pack", "p", "--session", "s", "--subject", "x.json"]).methods == ("proposed",)


@pytest.mark.parametrize("trigno", [("127.0.0.1", 50043), None])
def test_msk_live_settings_read_back_from_the_node_command_line(trigno):
    session = LiveSession(
        Path("lab.toml"), name="lab", pack="deadlift", load_kg=62.5, solver="piqp", live_synergists=False
    )
    plan = live.LivePlan(
        session,
        ("so", "proposed"),
        Path("subject.json"),
        trigno=trigno,
        trigno_latency_ms=13.5,
        tracker_latency_ms={"t1": 5.0, "t2": 0.25},
    )
    settings = live.estimator_settings(plan)
    assert not settings.live_synergists  # `msk live --live-synergists off` reaches the node
    assert settings.emg_clock is ClockMode.HOST and settings.timing.joints_clock is JointsClock.HOST
    assert settings.timing.emg_latency_ns == {session.trigno_id: 13_500_000}
    assert (settings.timing.emg_wait_s > 0) == (trigno is not None)
    argv = live.node_argv(plan, "estimator", Path("x.mcap"))
    assert _parse(argv[argv.index("--pack") :]) == settings


def test_settings_given_in_full_read_back():
    settings = EstimatorSettings(
        "bench_press",
        "s",
        ("hybrid", "assisted"),
        Path("p.json"),
        emg=False,
        electrode_map={"sensor01.EMG": "pec", "sensor02.EMG": "tri"},
        emg_clock=ClockMode.HOST,
        timing=EmgTiming(
            joints_clock=JointsClock.ARRIVAL,
            emg_latency_ns={"trigno": 1_234_567},
            default_emg_latency_ns=2_000_000,
            emg_align=ALIGN_ARRIVAL,
            imu_latency_ns={"t1": 3_000_000},
            default_imu_latency_ns=1,
            emg_wait_s=0.123,
        ),
        initial_load_kg=41.25,
        exercise="bench_press",
        live_synergists=False,
    )
    assert _parse(settings.argv()) == settings


@pytest.mark.parametrize(
    ("given", "field"),
    [
        (dict(methods=("proposed",)), "--method"),
        (dict(methods=("so", "assisted")), "--method"),
    ],
)
def test_refused_settings_name_their_option(given, field):
    with pytest.raises(ConfigError) as err:
        EstimatorSettings("bench_press", "s", **given)
    assert err.value.field == field


def test_a_malformed_electrode_map_is_named():
    with pytest.raises(ConfigError) as err:
        _parse(["--pack", "p", "--session", "s", "--emg-map", "sensor01"])
    assert (err.value.field, err.value.value) == ("--emg-map", "sensor01")
