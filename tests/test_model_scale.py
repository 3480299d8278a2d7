"""`msk model scale`: OpenSim's own scaling of the source model, then a recompiled pack."""

from __future__ import annotations

import re

import numpy as np
import pytest

from msk_core.errors import ConfigError
from msk_core.model import load_pack

pytest.importorskip("opensim")

from msk_core.model import osim_tools  # noqa: E402
from msk_core.model.scale import parse_segments, scale_pack, segment_lengths  # noqa: E402
from services import cli  # noqa: E402


def test_scale_arm26_matches_measurements(shared_dir, tmp_path):
    osim = shared_dir / "models" / "arm26.osim"
    out, summary = scale_pack(
        "arm26",
        osim,
        mass_kg=90.0,
        height_m=1.95,
        segments={"upper_arm": 0.34},
        out=tmp_path / "arm26_subject.json",
        samples=120,
    )
    scaled = load_pack(out)
    generic = load_pack("arm26")
    # the scaled OpenSim model has the measured upper-arm length and the person's mass share
    model, state = osim_tools.load_model(tmp_path / "arm26_subject.osim")
    seg = {"upper_arm": {"between": ["r_humerus", "r_ulna_radius_hand"]}}
    assert segment_lengths(model, state, seg)["upper_arm"] == pytest.approx(0.34, abs=1e-9)
    masses, generic_masses = scaled.rigid.body_masses(), generic.rigid.body_masses()
    for body, mass in masses.items():
        assert mass == pytest.approx(generic_masses[body] * 90.0 / 75.0, rel=1e-9)
    assert summary["segment_factors"]["upper_arm"] == pytest.approx(
        0.34 / summary["generic_segment_lengths_m"]["upper_arm"]
    )
    # a bigger arm: longer moment arms and fibres, larger gravity torques
    q, z = np.array([0.3, 1.0]), np.zeros(2)
    ratio = scaled.moment_arms(q)[1] / generic.moment_arms(q)[1]
    assert np.all((ratio > 1.03) & (ratio < 1.2)), ratio
    assert np.all(scaled.optimal_fiber_lengths > generic.optimal_fiber_lengths)
    tau_s, tau_g = scaled.inverse_dynamics(q, z, z, 0.0), generic.inverse_dynamics(q, z, z, 0.0)
    assert np.all(np.abs(tau_s) > 1.1 * np.abs(tau_g))
    assert scaled.raw["scaling"]["mass_kg"] == 90.0


def test_scale_cli_and_bad_input(shared_dir, tmp_path, capsys):
    osim = shared_dir / "models" / "arm26.osim"
    code = cli.main(
        [
            "model",
            "scale",
            "--pack",
            "arm26",
            "--osim",
            str(osim),
            "--mass-kg",
            "70",
            "--height-m",
            "1.7",
            "--segment",
            "upper_arm=0.28",
            "--out",
            str(tmp_path / "p.json"),
            "--samples",
            "60",
        ]
    )
    assert code == 0
    printed = re.search(r"scaled_segment_lengths_m: \{'upper_arm': ([0-9.]+)\}", capsys.readouterr().out)
    assert printed and float(printed.group(1)) == pytest.approx(0.28, abs=1e-9)
    with pytest.raises(ConfigError, match="forarm"):
        scale_pack("arm26", osim, mass_kg=70, height_m=1.7, segments={"forarm": 0.3}, out=tmp_path / "x.json")
    with pytest.raises(ConfigError, match="--segment"):
        parse_segments(["upper_arm:0.3"])
