"""The seed method on real lifts (backmodel-lift, pack lumbar_lift): calibrate on one technique, evaluate on the other.

Defaults only (nothing here is tuned to these trials). Body mass for N·m/kg: total mass of lumbar_scaled.osim
(81.5 kg), the subject's scaled model.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from services.cli import main

CHANNELS = [f"{m}_{side}" for m in ("rectabd", "iliocost", "longlumb", "longthor") for side in ("r", "l")]


def _toml(tmp_path, shared_dir, name):
    data = shared_dir / "data" / "backmodel-lift" / name
    path = tmp_path / f"{name}.toml"
    rel = lambda f: os.path.relpath(data / f, tmp_path)  # noqa: E731 - paths relative to the TOML file
    path.write_text(
        f'kinematics = "{rel("ik.sto")}"\ntorques = "{rel("id.sto")}"\nemg = "{rel("emgFilt.sto")}"\n'
        "emg_is_envelope = true\nload_kg = 5.0\nbody_mass_kg = 81.5\n[emg_map]\n"
        + "".join(f'{c} = "{c}"\n' for c in CHANNELS)
    )
    return path


@pytest.mark.parametrize("train,test", [("squat5kg", "stoop5kg"), ("stoop5kg", "squat5kg")])
def test_proposed_beats_so_and_prior_alone_on_held_out_technique(shared_dir, tmp_path, train, test, capsys):
    subject = tmp_path / "subject.json"
    assert (
        main(
            [
                "calibrate",
                "--pack",
                "lumbar_lift",
                "--trial",
                str(_toml(tmp_path, shared_dir, train)),
                "--out",
                str(subject),
            ]
        )
        == 0
    )
    profile = json.loads(subject.read_text())
    assert profile["calibration"]["converged"] and profile["calibration"]["projected_gradient_inf_norm"] < 1e-3
    report = tmp_path / "report"
    assert (
        main(
            [
                "evaluate",
                "--pack",
                "lumbar_lift",
                "--subject",
                str(subject),
                "--trial",
                str(_toml(tmp_path, shared_dir, test)),
                "--report",
                str(report),
            ]
        )
        == 0
    )
    scores = {s["method"]: s for s in json.loads((report / "metrics.json").read_text())["scores"]}
    rmse = {m: s["activation_rmse"]["mean"] for m, s in scores.items()}
    torque = scores["proposed"]["torque"]["L5_S1_Flex_Ext"]
    print(
        f"{train}->{test}: activation RMSE {rmse}; proposed L5/S1 R {torque['r']:.3f}, "
        f"RMSE {torque['rmse_nm_per_kg']:.3f} N·m/kg"
    )
    assert rmse["proposed"] < rmse["so"]
    assert rmse["proposed"] < rmse["prior"]
    # docs/estimation.md's table (0.0226 / 0.0224): a change that moves it past this is said there (26 Nov's moved
    # it from 0.0204 / 0.0213 and the table did not follow)
    assert rmse["proposed"] < 0.0235, rmse
    assert torque["r"] >= 0.95
    assert np.isfinite(torque["rmse_nm_per_kg"])
    assert all(not s["flag_counts"].get("solver_failed") for s in scores.values())
    for channel in CHANNELS:
        assert (report / f"{test}_{channel}.png").is_file()
