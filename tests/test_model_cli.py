"""`msk model compile|check|show` end to end on arm26 (small and fast)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from services import cli

pytest.importorskip("opensim")


def test_model_show_and_unknown_pack(capsys):
    assert cli.main(["model", "show", "deadlift"]) == 0
    out = capsys.readouterr().out
    assert "group VM" in out and "vasmed_r, vasint_r" in out and "knee_angle_r" in out
    assert cli.main(["model", "show", "squat_pack"]) == 2
    assert "no shipped model pack 'squat_pack'" in capsys.readouterr().err


def test_model_list_names_every_shipped_pack_and_which_msk_live_drives(capsys):
    """A new user found the packs' names only in error messages."""
    from msk_core.model.pack import available_packs

    assert cli.main(["model", "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in lines[:-1]] == available_packs()
    assert any(line.startswith("bench_press") and "msk live: yes" in line for line in lines)
    assert any(line.startswith("lumbar_lift") and "1 coordinate, " in line and "offline only" in line for line in lines)


def test_model_compile_and_check_cli(shared_dir, tmp_path, capsys, repo_root):
    spec = (repo_root / "msk_core" / "model" / "specs" / "arm26.toml").read_text()
    spec = spec.replace("samples = 400", "samples = 100")
    (tmp_path / "a.toml").write_text(spec)
    osim = shared_dir / "models" / "arm26.osim"

    def compile_arm26(spec_path: Path, out: Path) -> int:  # msk model compile of arm26.osim with the spec
        return cli.main(["model", "compile", "--osim", str(osim), "--spec", str(spec_path), "--out", str(out)])

    assert compile_arm26(tmp_path / "a.toml", tmp_path / "a.json") == 0
    assert (
        cli.main(
            [
                "model",
                "check",
                str(tmp_path / "a.json"),
                "--osim",
                str(osim),
                "--poses",
                "6",
                "--json",
                str(tmp_path / "r.json"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "moment arms over 6 fresh poses" in out and "% of peak" in out
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["pack"] == "arm26"
    assert set(report["muscles"]["groups"]) == {"TRIlong", "TRIlat", "TRImed", "BIClong", "BICshort", "BRA"}
    assert max(report["dynamics"]["max_error_percent_of_peak"].values()) < 1e-3
    # bad spec -> exit code 2 and a message naming the file and field
    (tmp_path / "bad.toml").write_text(spec.replace('name = "arm26"', "name = 5"))
    assert compile_arm26(tmp_path / "bad.toml", tmp_path / "b.json") == 2
    assert "bad.toml" in capsys.readouterr().err


def test_model_check_with_recorded_lift(shared_dir, tmp_path, capsys):
    lift = shared_dir / "data" / "backmodel-lift" / "stoop5kg"
    code = cli.main(
        [
            "model",
            "check",
            "lumbar_lift",
            "--osim",
            str(shared_dir / "models" / "lumbar_scaled.osim"),
            "--poses",
            "4",
            "--recorded",
            str(lift / "ik.sto"),
            str(lift / "id.sto"),
            "--recorded-load",
            "49.03",
            "--json",
            str(tmp_path / "r.json"),
        ]
    )
    assert code == 0
    assert "correlation" in capsys.readouterr().out
    recorded = json.loads((tmp_path / "r.json").read_text())["recorded"][0]
    assert recorded["frames"] > 300 and recorded["correlation"]["L5_S1_Flex_Ext"] > 0.75


def test_model_check_defaults_to_the_shared_source_model(shared_dir, capsys):
    assert cli.main(["model", "check", "arm26", "--poses", "2"]) == 0
    assert "moment arms over 2 fresh poses" in capsys.readouterr().out
