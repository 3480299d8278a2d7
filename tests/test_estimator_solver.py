"""The estimator node's per-input logic without Zenoh (``EstimatorNode``), and its ``--solver piqp``: the warm PIQP on
every frame gives the live activations of the hot start to PIQP's tolerance, and is the one answering."""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.errors import ConfigError
from msk_core.estimate.trial import load_trial
from msk_core.model import load_pack
from services.nodes.estimator import EstimatorNode, EstimatorSettings, EstimatorStats
from services.transport import messages


def _node(solver: str) -> EstimatorNode:
    settings = EstimatorSettings("bench_press", "t", ("hybrid", "so"), initial_load_kg=50.0, solver=solver)
    return EstimatorNode(settings, None, EstimatorStats())


def test_piqp_every_frame_equals_the_hot_start_in_the_node(repo_root):
    pack = load_pack("bench_press")
    trial = load_trial(repo_root / "recordings/demo/bench_press/bench_press_50kg/trial.toml", pack)
    hot, piqp = _node("active-set"), _node("piqp")
    for i in range(0, trial.n_frames, 5):
        payload = messages.JointAngles(
            coordinates=list(pack.coordinates),
            q=trial.q[i].tolist(),
            qd=trial.qd[i].tolist(),
            qdd=trial.qdd[i].tolist(),
            device_time_ns=int(trial.time[i] * 1e9),
        ).SerializeToString()
        a, b = hot.handle_joints(payload, 0), piqp.handle_joints(payload, 0)
        assert [m for m, _ in a] == [m for m, _ in b] == ["hybrid", "so"]
        for (_, fa), (_, fb) in zip(a, b):
            assert np.abs(np.array(fa.activations) - np.array(fb.activations)).max() <= 1e-3
    assert hot.stats.frames_out == piqp.stats.frames_out > 250
    assert piqp.estimators["hybrid"].solver_counts["active_set"] == 0
    assert hot.estimators["hybrid"].solver_counts["active_set"] > 0.9 * hot.stats.frames_out


def test_unknown_solver_is_named():
    with pytest.raises(ConfigError) as err:
        EstimatorSettings("bench_press", "s", ("so",), solver="fast")
    assert err.value.field == "--solver"


def test_msk_live_solver_reaches_the_estimator_node():
    """``msk live --solver piqp`` (the session's typed setting) gives the estimator node its ``--solver piqp``; the
    default keeps the hot start."""
    import argparse
    from pathlib import Path

    from services.commands import live as live_command
    from services.sessions import live

    parser = argparse.ArgumentParser()
    live_command.register(parser.add_subparsers())
    for given, expected in ((["--solver", "piqp"], "piqp"), ([], "active-set")):
        session = live_command.session_from_args(parser.parse_args(["live", "--sim", *given]))
        assert session.solver == expected
        argv = live.node_argv(live.LivePlan(session, ("so",), Path("subject.json")), "estimator", Path("x.mcap"))
        assert argv[argv.index("--solver") + 1] == expected
    with pytest.raises(SystemExit):
        parser.parse_args(["live", "--sim", "--solver", "fast"])
