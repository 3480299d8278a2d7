"""msk estimate / calibrate / evaluate end to end on the real arm26 tutorial files with the arm26 pack.

The arm26 data have no EMG, so the calibration test synthesises it from a known truth. The tutorial motion is nearly
unloaded (activations ~0.01-0.05, below any EMG noise floor), so the synthetic trial is one repetition of the motion
(forward, then backward) with the inverse-dynamics torques of a 5x heavier arm; activations `so` finds for them with strength F_ref reproduce the
torques, so with true strength k_true x F_ref the muscles' EMG is a_so / k_true (three muscles), and calibration must
find k_true.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import ConfigError, InputError
from msk_core.estimate import SubjectProfile
from msk_core.estimate.pipeline import estimate_trial
from msk_core.estimate.trial import load_trial
from msk_core.io import read_sto, write_sto
from services.cli import main
from tests.cli_helpers import discrepancy_argv

# every muscle `so` activates in this motion has EMG (a synergist without EMG would absorb strength); TRIlat and
# TRImed share their moment arms, so only their common factor is identifiable
K_TRUE = {"BIClong": 1.5, "BICshort": 1.3, "TRIlat": 0.8, "TRImed": 0.8}


def _rel(path: Path, start: Path) -> str:
    return os.path.relpath(path, start)  # trial paths are relative to the TOML file


@pytest.fixture()
def arm26_trials(shared_dir, tmp_path):
    from msk_core.model import load_pack

    data = shared_dir / "data" / "opensim-arm26"
    base = tmp_path / "trials"
    base.mkdir()
    plain = base / "arm26.toml"
    plain.write_text(
        f'kinematics = "{_rel(data / "arm26_InverseKinematics.mot", base)}"\n'
        f'torques = "{_rel(data / "arm26_InverseDynamics.sto", base)}"\n'
        'phase_signal = "r_elbow_flex"\nbody_mass_kg = 70.0\n'
    )
    pack = load_pack("arm26")
    trial = load_trial(plain, pack)
    # One repetition: the tutorial motion, then the same motion backwards (time-reversed rigid-body dynamics without
    # damping has the same torques at the mirrored instants), with 5x the torques.
    ik = read_sto(data / "arm26_InverseKinematics.mot")
    tau = read_sto(data / "arm26_InverseDynamics.sto")
    t_rep = np.r_[ik.time, 2 * ik.time[-1] - ik.time[::-1][1:]]
    write_sto(tmp_path / "ik_rep.mot", t_rep, ik.columns, np.vstack([ik.data, ik.data[::-1][1:]]), in_degrees=True)
    write_sto(tmp_path / "id_rep.sto", t_rep, tau.columns, 5.0 * np.vstack([tau.data, tau.data[::-1][1:]]))
    heavy_toml = base / "heavy.toml"
    heavy_toml.write_text(
        f'kinematics = "{_rel(tmp_path / "ik_rep.mot", base)}"\ntorques = "{_rel(tmp_path / "id_rep.sto", base)}"\n'
        'phase_signal = "r_elbow_flex"\nbody_mass_kg = 70.0\n'
    )
    heavy_trial = load_trial(heavy_toml, pack)
    so = estimate_trial(pack, heavy_trial, "so")
    emg = np.column_stack([so.activations[:, so.groups.index(g)] / k for g, k in K_TRUE.items()])
    write_sto(tmp_path / "emg.sto", heavy_trial.time, [f"ch_{g}" for g in K_TRUE], emg)
    with_emg = base / "arm26_emg.toml"
    with_emg.write_text(
        heavy_toml.read_text()
        + f'emg = "{_rel(tmp_path / "emg.sto", base)}"\nemg_is_envelope = true\n[emg_map]\n'
        + "".join(f'ch_{g} = "{g}"\n' for g in K_TRUE)
    )
    return {"plain": plain, "emg": with_emg, "pack": pack, "trial": trial}


def _msk_arm26(command: str, trial: Path | str, *options: str) -> int:
    """``msk COMMAND --pack arm26 --trial TRIAL [OPTIONS]``, in this process: its exit code."""
    return main([command, "--pack", "arm26", "--trial", str(trial), *options])


def test_msk_estimate_so_writes_activations_and_torques(arm26_trials, tmp_path, capsys):
    out = tmp_path / "out" / "act.sto"
    trial = str(arm26_trials["plain"])
    rc = _msk_arm26("estimate", trial, "--method", "so", "--out", str(out))
    assert rc == 0
    act = read_sto(out)
    assert act.columns == list(arm26_trials["pack"].groups) and act.n_rows == arm26_trials["trial"].n_frames
    tq = read_sto(out.with_name("act_torques.sto"))
    assert tq.columns[:3] == ["r_shoulder_elev_id", "r_shoulder_elev_model", "r_shoulder_elev_residual"]
    assert np.abs(tq.column("r_elbow_flex_residual")).max() < 1e-3  # so matches the torques
    std = read_sto(out.with_name("act_std.sto"))
    assert std.columns == act.columns and np.all(std.data >= 0) and np.any(std.data > 0)
    np.testing.assert_allclose(
        tq.column("r_elbow_flex_id"),
        read_sto(arm26_trials["trial"].path.parent / _rel_path(arm26_trials["plain"], "torques")).column(
            "r_elbow_flex_moment"
        ),
        atol=1e-4,
    )  # the ID time stamps sit 2e-7 s before the kinematics ones: values are interpolated


def _rel_path(toml: Path, key: str) -> str:
    import tomllib

    return tomllib.loads(toml.read_text())[key]


def test_msk_calibrate_recovers_strength_then_estimate_and_evaluate(arm26_trials, tmp_path, capsys):
    profile_path = tmp_path / "subject.json"
    # TRIlat and TRImed have the same moment arms: each alone is unidentified, their common factor is identified
    rc = _msk_arm26("calibrate", arm26_trials["emg"], "--out", str(profile_path))
    printed = capsys.readouterr().out
    assert rc == 0, printed
    strength = json.loads(profile_path.read_text())["calibration"]["strength"]
    assert strength["TRIlat"]["status"] == strength["TRImed"]["status"] == "combination", strength
    assert strength["TRIlat"]["std_data"] > 10.0 and abs(strength["TRIlat"]["identified_share"] - 0.5) < 0.01
    assert abs(strength["TRIlat"]["scale"] / 0.8 - 1) <= 0.10
    assert strength["BIClong"]["status"] == "identified" and abs(strength["BIClong"]["scale"] / 1.5 - 1) <= 0.10
    assert strength["BRA"]["status"] == "not_calibrated"
    assert "TRIlat" in printed and "combination" in printed and "std (data)" in printed
    hint = [line for line in printed.splitlines() if line.startswith("hint:")]  # no isometric trial given
    assert len(hint) == 1 and "TRIlat" in hint[0] and "TRImed" in hint[0] and "isometric = true" in hint[0], hint
    # without the identifiability pass every factor stays free (same common factor here)
    off = tmp_path / "subject_free.json"
    rc = _msk_arm26("calibrate", arm26_trials["emg"], "--out", str(off), "--identify-max-std", "0")
    assert rc == 0, capsys.readouterr().out
    assert json.loads(off.read_text())["calibration"]["settings"]["identify_max_std"] is None
    doc = json.loads(profile_path.read_text())
    assert doc["pack"] == {"name": "arm26", "version": str(arm26_trials["pack"].version)}
    assert doc["calibration"]["converged"] is True
    assert doc["prior"]["has_emg"] == [g in K_TRUE for g in arm26_trials["pack"].groups]
    assert set(doc["emg_normalisation"]) == {f"ch_{g}" for g in K_TRUE}
    profile = SubjectProfile.load(profile_path)
    scale = dict(zip(profile.groups, profile.scale_factors))
    errors = [abs(scale[g] - k) / k for g, k in K_TRUE.items()]
    assert np.median(errors) <= 0.10, scale
    assert scale["BRA"] == 1.0  # no EMG -> reference strength

    out = tmp_path / "prop.sto"
    rc = _msk_arm26(
        "estimate", arm26_trials["emg"], "--subject", str(profile_path), "--method", "proposed", "--out", str(out)
    )
    assert rc == 0
    assert read_sto(out).n_rows == load_trial(arm26_trials["emg"], arm26_trials["pack"]).n_frames
    assert "the prior, learned at" not in capsys.readouterr().out  # the calibration's own load: the prior as learned
    # the same lift declared at another load: the prior is scaled by the torques, which are the calibration's here
    declared = arm26_trials["emg"].with_name("declared_10kg.toml")
    declared.write_text(
        arm26_trials["emg"].read_text().replace("body_mass_kg = 70.0\n", "body_mass_kg = 70.0\nload_kg = 10.0\n")
    )
    assert _msk_arm26("estimate", declared, "--subject", str(profile_path), "--out", str(tmp_path / "d.sto")) == 0
    printed = capsys.readouterr().out
    assert "declared_10kg: the prior, learned at 0 kg, was scaled to the trial's 10 kg on" in printed, printed
    low, high = map(float, re.search(r"mean scale per group ([\d.]+)-([\d.]+)", printed).groups())
    assert 0.97 <= low <= high <= 1.03, printed  # the same torques as the calibration's: about 1
    declared_report = tmp_path / "declared_report"
    assert _msk_arm26("evaluate", declared, "--subject", str(profile_path), "--report", str(declared_report)) == 0
    scaled = json.loads((declared_report / "metrics.json").read_text())["load_scale"]
    assert list(scaled) == ["declared_10kg"] and scaled["declared_10kg"]["load_kg"] == pytest.approx(10.0)
    assert (
        "declared_10kg: the prior, learned at 0 kg, was scaled to the trial's 10 kg"
        in (declared_report / "report.md").read_text()
    )

    report = tmp_path / "report"
    rc = _msk_arm26("evaluate", arm26_trials["emg"], "--subject", str(profile_path), "--report", str(report))
    assert rc == 0
    md = (report / "report.md").read_text()
    for method in ("proposed", "so", "hybrid", "prior"):
        assert f"| arm26_emg | {method} |" in md
    # the trial also calibrated the subject: said, where the declared-load copy (another file) was not
    assert f"subject calibrated on {arm26_trials['emg'].name}" in md
    assert "**In sample:** arm26_emg also calibrated the subject" in md
    assert "In sample" not in (declared_report / "report.md").read_text()
    assert (report / "arm26_emg_TRIlat.png").stat().st_size > 1000
    assert (report / "arm26_emg_torque.png").is_file()
    metrics = json.loads((report / "metrics.json").read_text())
    assert metrics["load_scale"] == {}  # the calibration's own load
    by_method = {s["method"]: s for s in metrics["scores"]}
    assert by_method["so"]["torque"]["r_elbow_flex"]["r"] > 0.999
    assert by_method["proposed"]["torque"]["r_elbow_flex"]["r"] > 0.95
    # the prior alone ignores the torque: it tracks it clearly worse than the proposed method
    elbow = {m: s["torque"]["r_elbow_flex"]["rmse_nm"] for m, s in by_method.items()}
    assert elbow["prior"] > 3 * elbow["proposed"]


def test_trial_errors_name_file_line_field_and_value(arm26_trials, tmp_path):
    pack = arm26_trials["pack"]
    bad = tmp_path / "trials" / "bad.toml"
    bad.write_text(arm26_trials["plain"].read_text() + "laod_kg = 3\n")
    with pytest.raises(ConfigError, match=r"bad.toml, line 5, field 'laod_kg'.*did you mean load_kg"):
        load_trial(bad, pack)
    bad.write_text(arm26_trials["plain"].read_text().replace("70.0", '"heavy"'))
    with pytest.raises(ConfigError, match=r"line 4, field 'body_mass_kg': must be a number \(got 'heavy'\)"):
        load_trial(bad, pack)
    bad.write_text('kinematics = "missing.sto"\n')
    with pytest.raises(ConfigError, match="file not found"):
        load_trial(bad, pack)
    bad.write_text(arm26_trials["emg"].read_text().replace('= "BIClong"', '= "BIClongg"'))
    with pytest.raises(ConfigError, match=r"emg_map.ch_BIClong.*did you mean BIClong"):
        load_trial(bad, pack)
    ik = read_sto(Path(str(arm26_trials["trial"].path.parent / _rel_path(arm26_trials["plain"], "kinematics"))))
    write_sto(tmp_path / "renamed.sto", ik.time, ["r_shoulder_elev", "elbow"], ik.data, in_degrees=True)
    bad.write_text(f'kinematics = "{_rel(tmp_path / "renamed.sto", bad.parent)}"\n')
    with pytest.raises(InputError, match="no column for pack coordinate 'r_elbow_flex'"):
        load_trial(bad, pack)


def test_trial_without_torques_uses_pack_inverse_dynamics_and_start_end(arm26_trials, shared_dir):
    data = shared_dir / "data" / "opensim-arm26"
    base = arm26_trials["plain"].parent
    toml = base / "no_id.toml"
    toml.write_text(
        f'kinematics = "{_rel(data / "arm26_InverseKinematics.mot", base)}"\n'
        'phase_signal = "r_elbow_flex"\nstart = 0.1\nend = 0.9\nload_kg = 0.0\n'
    )
    trial = load_trial(toml, arm26_trials["pack"])
    assert trial.torque_source == "inverse_dynamics"
    assert trial.time[0] >= 0.1 and trial.time[-1] <= 0.9 and trial.n_frames == 97
    ref = read_sto(data / "arm26_InverseDynamics.sto")
    elbow = np.interp(trial.time, ref.time, ref.column("r_elbow_flex_moment"))
    # finite differences of unfiltered IK vs OpenSim's ID of the 6 Hz-filtered motion: same shape, gravity-dominated
    assert np.corrcoef(trial.torques[:, 1], elbow)[0, 1] > 0.95


def test_msk_calibrate_prior_options_for_groups_without_emg(arm26_trials, tmp_path, capsys):
    pack = arm26_trials["pack"]
    out = tmp_path / "syn.json"
    rc = _msk_arm26(
        "calibrate", arm26_trials["emg"], "--out", str(out), "--synergist", "BRA=BIClong", "--strength-prior-std", "0.3"
    )
    assert rc == 0, capsys.readouterr().out
    doc = json.loads(out.read_text())
    sources = dict(zip(pack.groups, doc["prior"]["sources"]))
    assert sources["BRA"] == "synergist:BIClong" and sources["TRIlong"] == "min_effort" and sources["BIClong"] == "emg"
    assert doc["calibration"]["settings"]["strength_prior_std"] == 0.3
    prior = SubjectProfile.load(out).prior
    j, k = list(pack.groups).index("BRA"), list(pack.groups).index("BIClong")
    np.testing.assert_allclose(prior.mean[:, j], prior.mean[:, k])
    capsys.readouterr()
    for synergist, refusal in (("BRA=TRIlong", "a group with EMG"), ("BRA", "GROUP=MEASURED")):
        assert _msk_arm26("calibrate", arm26_trials["emg"], "--out", str(out), "--synergist", synergist) != 0
        assert refusal in capsys.readouterr().err


def test_msk_discrepancy_on_arm26_with_inverse_dynamics_torques_names_a_hidden_delay(shared_dir, tmp_path, capsys):
    """The discrepancy workflow through the CLI on the arm26 pack, torques from the inverse-dynamics file: two loads
    (5x and 7x the tutorial's torques), EMG from the static-optimisation activations of each, leading them by 60 ms
    (`msk bench discrepancy`'s arm26 sessions, one rep, no noise). Calibrated without a delay, the workflow names the
    delay; with EMG that does not lead, "none". (Static optimisation leaves TRIlong off in one phase of the lighter
    trial only: the training and held-out designs must still share their columns.)"""
    from services.bench.discrepancy import ARM26_EMD_S, arm26_session

    for effect, expected in (("emd", "emd"), (None, "none")):
        folder = tmp_path / str(effect)
        folder.mkdir()
        pack, _, _, _ = arm26_session(folder, 0.0, 1, reps=1, effect=effect, calibrate=False)
        train, held = folder / "train.toml", folder / "held.toml"
        subject, report = folder / "subject.json", folder / "report"
        assert _msk_arm26("calibrate", train, "--out", str(subject), "--emd", "0") == 0
        assert main(discrepancy_argv("arm26", subject, train, held, "--report", str(report))) == 0
        assert load_trial(held, pack).torque_source == "file"
        summary = json.loads((report / "summary.json").read_text())
        assert summary["effect"] == expected, summary["candidates"][:3]
        assert list(summary["gap_per_coordinate"]) == list(pack.coordinates)
        if expected == "emd":
            assert abs(summary["parameters"]["delay_s"] - ARM26_EMD_S) <= 0.02, summary["parameters"]
            assert summary["gap_after"] < 0.7 * summary["gap_before"], summary
        assert "note: the torques of training trial" not in capsys.readouterr().err  # both from the ID file
    # a training trial without its torques file: the pack's inverse dynamics against the held-out file's, said
    computed = folder / "train_computed.toml"
    computed.write_text("\n".join(line for line in train.read_text().splitlines() if not line.startswith("torques")))
    assert main(discrepancy_argv("arm26", subject, computed, held, "--report", str(folder / "mixed"))) == 0
    assert "note: the torques of training trial(s) train_computed are the pack's inverse dynamics" in (
        capsys.readouterr().err
    )


def test_calibrating_trials_without_emg_says_so_before_the_delay_and_points_to_so(arm26_trials, tmp_path, capsys):
    """The OpenSim tutorial's trial (no EMG, no repetition): it said "EMD estimation needs EMG", and with --emd 0 that
    "the trials with reps" had none, of a trial without reps."""
    for options in ((), ("--emd", "0")):
        rc = _msk_arm26("calibrate", arm26_trials["plain"], "--out", str(tmp_path / "p.json"), *options)
        said = capsys.readouterr().err
        assert rc != 0 and "calibration needs EMG, and no trial has any (arm26)" in said, said
        assert "msk estimate --method so" in said and "EMD" not in said


@pytest.mark.parametrize("command", ["calibrate", "estimate"])
def test_an_out_that_is_a_folder_is_refused_before_the_work(command, arm26_trials, tmp_path, capsys):
    """Found by a new user's walk: `msk calibrate --out FOLDER` ran the whole calibration, then failed on a hidden
    temporary file. Both commands now refuse it first, naming --out and a file name to give."""
    folder = tmp_path / "profiles"
    folder.mkdir()
    extra = ["--method", "so"] if command == "estimate" else []
    rc = _msk_arm26(command, str(arm26_trials["plain"]), *extra, "--out", str(folder))
    err = capsys.readouterr()
    assert rc == 2 and "field '--out': is a folder" in err.err and str(folder) in err.err, err
    assert err.out == "" and list(folder.iterdir()) == []  # nothing was computed, nothing written
    if command == "estimate":  # .sto content under another name: refused too
        assert _msk_arm26(command, str(arm26_trials["plain"]), *extra, "--out", str(folder / "a.csv")) == 2
        assert "field '--out': msk estimate writes OpenSim .sto tables" in capsys.readouterr().err
