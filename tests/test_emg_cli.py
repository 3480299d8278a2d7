"""``msk emg envelope`` and ``msk emg reps`` on real files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.io import read_anc, read_sto
from msk_core.signal.emg import EmgFilterConfig, envelope_causal, envelope_zero_phase_noncausal
from services.cli import main


def test_envelope_command_matches_library(shared_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    anc = shared_dir / "data/rajagopal-walk/emg_walk_raw.anc"
    out = tmp_path / "env.sto"
    assert main(["emg", "envelope", str(anc), "--channels", "SOL,TA", "-o", str(out)]) == 0
    s = read_sto(out)
    raw = read_anc(anc).select(["SOL", "TA"])
    assert s.columns == ["SOL", "TA"] and s.name == "EMG envelopes, causal"
    np.testing.assert_allclose(s.data, envelope_causal(raw.data, EmgFilterConfig(rate_hz=2000.0)), rtol=1e-12, atol=0)
    # offline zero-phase, normalised by an "MVC" trial (here the same file: peak exactly 1)
    out2 = tmp_path / "env_norm.sto"
    assert (
        main(["emg", "envelope", str(anc), "--channels", "SOL,TA", "--zero-phase", "--mvc", str(anc), "-o", str(out2)])
        == 0
    )
    s2 = read_sto(out2)
    np.testing.assert_allclose(s2.data.max(axis=0), 1.0)
    zp = envelope_zero_phase_noncausal(raw.data, EmgFilterConfig(rate_hz=2000.0))
    np.testing.assert_allclose(s2.data, zp / zp.max(axis=0), rtol=1e-12)
    assert "normalised peak per channel" in capsys.readouterr().out


def test_reps_command(shared_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ik = shared_dir / "data/backmodel-lift/stoop5kg/ik.sto"
    phase_file = tmp_path / "phase.sto"
    assert (
        main(
            [
                "emg",
                "reps",
                str(ik),
                "--coordinate",
                "pelvis_ty",
                "--excursion",
                "decrease",
                "--phase-out",
                str(phase_file),
            ]
        )
        == 0
    )
    assert "4 repetitions" in capsys.readouterr().out
    ph = read_sto(phase_file)
    assert ph.columns == ["phase", "rep"] and set(np.unique(ph.column("rep"))) == {-1.0, 0.0, 1.0, 2.0, 3.0}


def test_errors_exit_2(shared_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    anc = shared_dir / "data/rajagopal-walk/emg_walk_raw.anc"
    assert main(["emg", "envelope", str(anc), "--channels", "SOL,NOPE", "-o", str(tmp_path / "x.sto")]) == 2
    assert "no channel 'NOPE'" in capsys.readouterr().err
    assert main(["emg", "envelope", str(tmp_path / "x.txt"), "-o", str(tmp_path / "x.sto")]) == 2
    assert "unknown EMG file type" in capsys.readouterr().err
    assert main(["emg", "envelope", str(anc), "--lowpass-hz", "5000", "-o", str(tmp_path / "x.sto")]) == 2
    assert "lowpass_hz" in capsys.readouterr().err
