"""`msk evaluate --leave-out` on a short real excerpt: the backmodel squat (405 frames) calibrates, the stoop is held
out, two trunk groups are left out in turn (docs/estimation.md, "Leave one electrode out"; the full tables on both
real data sets are `msk bench leave-out`'s).

What is asserted is the structure of summary.json and that the numbers are finite and sensible (RMSE within the
envelope's scale, r and agreements in range, the lag within the searched window), that each left-out run calibrated
without the left-out electrode and the paper's run with it, and that the plots and report exist; of the accuracy, only
what was measured to hold on these two groups (the full tables: docs/estimation.md).
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from msk_core.estimate.leave_out import LEAVE_OUT_METHODS, MAX_LAG_S, PAPER_METHODS
from services.cli import main
from tests.conftest import committed_trial

pytestmark = [pytest.mark.needs_shared, pytest.mark.slow]

LEFT_OUT = ["iliocost_r", "longthor_l"]
CHANNELS = [f"{m}_{side}" for m in ("rectabd", "iliocost", "longlumb", "longthor") for side in ("r", "l")]


def _trial(name: str, shared_dir: Path, tmp_path: Path) -> Path:
    return committed_trial("backmodel-lift", name, shared_dir, tmp_path)


def test_leave_out_command_writes_a_sensible_summary(shared_dir, tmp_path):
    report = tmp_path / "report"
    argv = ["evaluate", "--pack", "lumbar_lift", "--report", str(report)]
    argv += ["--train", str(_trial("squat5kg", shared_dir, tmp_path))]
    argv += ["--trial", str(_trial("stoop5kg", shared_dir, tmp_path))]
    argv += ["--leave-out", LEFT_OUT[0], "--leave-out", LEFT_OUT[1]]
    assert main(argv) == 0
    summary = json.loads((report / "summary.json").read_text())
    assert summary["groups"] == LEFT_OUT and summary["train"] == ["squat5kg"] and summary["held_out"] == ["stoop5kg"]
    for table, methods in (("leave_one_out", LEAVE_OUT_METHODS), ("paper_protocol", PAPER_METHODS)):
        assert set(summary[table]) == set(LEFT_OUT)
        for group in LEFT_OUT:
            assert list(summary[table][group]) == list(methods)
            for method, scores in summary[table][group].items():
                assert set(scores) == {"rmse", "r", "lag_ms", "on_off_agreement", "rmse_aligned", "r_aligned"}
                assert 0 < scores["rmse"] < 0.5 and 0 < scores["rmse_aligned"] < 0.5, (table, group, method, scores)
                assert 0 <= scores["on_off_agreement"] <= 1, (table, group, method, scores)
                if scores["r"] is not None:  # hybrid may sit at a constant (its r is then undefined: null)
                    assert -1 <= scores["r"] <= 1 and abs(scores["lag_ms"]) <= 1000 * MAX_LAG_S + 1
                else:
                    assert method == "hybrid", (table, group, method, scores)
        # the trunk extensors follow the lift with or without their electrode: proposed correlates
        assert all(summary[table][g]["proposed"]["r"] > 0.5 for g in LEFT_OUT), summary[table]
    # what was measured to hold (docs/estimation.md): without its electrode the right iliocostalis is estimated with
    # less than 0.8x so's RMSE (0.026 vs 0.077)
    loo = summary["leave_one_out"]
    assert loo["iliocost_r"]["proposed"]["rmse"] < 0.8 * loo["iliocost_r"]["so"]["rmse"], loo["iliocost_r"]
    runs = summary["calibrations"]
    assert [r["left_out"] for r in runs] == [None] + LEFT_OUT and all(r["converged"] for r in runs)
    assert set(runs[0]["strength"]) == set(CHANNELS)  # the paper's run calibrates every electrode's group
    for run in runs[1:]:  # a left-out run has no strength factor of its own for the left-out group
        assert set(run["strength"]) == set(CHANNELS) - {run["left_out"]}
    medians = summary["medians"]["leave_one_out"]
    assert set(medians) == set(LEAVE_OUT_METHODS) and all(
        v["rmse"] is not None and math.isfinite(v["rmse"]) for v in medians.values()
    )
    assert set(summary["targets"]["per_group"]) == set(LEFT_OUT)
    assert set(summary["targets_aligned"]["per_group"]) == set(LEFT_OUT)
    assert set(summary["medians_aligned"]["paper_protocol"]) == set(PAPER_METHODS)
    for group in LEFT_OUT:
        assert (report / f"leave_out_{group}.png").stat().st_size > 1000
    text = (report / "report.md").read_text()
    assert "## Left out" in text and "paper's protocol" in text and all(g in text for g in LEFT_OUT)
    assert "## Against the delay-aligned envelope" in text
    # the lifts' calibration with every electrode, every run's reference, finds no delay: one sentence, not the
    # scores above again under another title
    assert "The calibration with every electrode, the reference of every run, found no electromechanical delay" in text
    # what made the numbers is said and kept (found by a new user's walk: the report said "minimal-effort prior,
    # reference strength" whatever the options)
    assert summary["settings"] == {
        "no_emg_prior": "min_effort",
        "no_emg_strength": "reference",
        "prior_synergists": {},
        "live_synergists": True,
        "phase_signal": ["torque:L5_S1_Flex_Ext"],
    }, summary["settings"]
    assert "(no electrode: minimal-effort prior, reference strength; `assisted` with live synergists on)" in text
    assert "| Iliocostalis lumborum, right (iliocost_r) |" in text  # the pack's names, with the model's
    assert text.count("Medians over the left-out groups") == 1, text
    r_groups = summary["targets"]["r_groups"]
    assert f"paired over the {r_groups} groups where both have an r" in text  # the r target's comparison, said
    # a lag is said only where the curves correlate and not at the edge of the lags searched; a constant so has no r
    assert "vs so nan" not in text
    # and the table shows '–' for such a lag (found by a new user's walk: -483 to -500 ms read as if meaningful)
    table = text.split("## Left out", 1)[1].split("\n\n", 2)[1].splitlines()
    methods = [h.split(" RMSE")[0] for h in table[0].strip("| ").split(" | ")[1:]]
    for row in table[2:]:
        label, *cells = row.strip("| ").split(" | ")
        group = label.rsplit("(", 1)[1].rstrip(")")
        for method, cell in zip(methods, cells):
            scores = summary["leave_one_out"][group][method]
            delay = scores["r"] is not None and scores["r"] >= 0.3 and abs(scores["lag_ms"]) < 0.95 * 1000 * MAX_LAG_S
            assert (cell.split(" / ")[2] == "–") != delay, (group, method, cell, scores)
    for g, method, _ in re.findall(r"^- .*?\((\w+)\) \((\w+)\): not met: .*its estimate is (\d+) ms", text, re.M):
        scores = summary["leave_one_out"][g][method]
        assert scores["r"] >= 0.3 and abs(scores["lag_ms"]) < 0.95 * 1000 * MAX_LAG_S, (g, method, scores)
    assert summary["load_scale"] == {}  # both lifts at 5 kg: the prior as learned


def test_a_held_out_trial_at_another_load_says_how_the_prior_was_scaled(shared_dir, tmp_path):
    """The stoop declared at 15 kg (its torques are the 5 kg lift's): the prior is scaled by the torques, so about
    by the stoop's torque against the squat's, and the summary and report say so."""
    committed = _trial("stoop5kg", shared_dir, tmp_path)
    heavier = tmp_path / "stoop_declared_15kg.toml"
    text = committed.read_text().replace("load_kg = 5.0", "load_kg = 15.0")
    heavier.write_text(text.replace('"../../../shared', f'"{committed.parent.resolve() / "../../../shared"}'))
    report = tmp_path / "report"
    argv = ["evaluate", "--pack", "lumbar_lift", "--report", str(report), "--leave-out", "iliocost_r"]
    argv += ["--train", str(_trial("squat5kg", shared_dir, tmp_path)), "--trial", str(heavier)]
    assert main(argv) == 0
    scale = json.loads((report / "summary.json").read_text())["load_scale"]
    assert list(scale) == ["stoop5kg"], scale  # the trial's name, from its file
    assert scale["stoop5kg"]["prior_load_kg"] == pytest.approx(5.0) and scale["stoop5kg"]["load_kg"] == 15.0
    values = list(scale["stoop5kg"]["mean_scale"].values())
    assert scale["stoop5kg"]["frames"] > 100 and 0.9 < min(values) <= max(values) < 1.4, scale
    assert "stoop5kg: the prior, learned at 5 kg, was scaled to the trial's 15 kg" in (report / "report.md").read_text()


def test_leave_out_refuses_a_group_without_an_electrode(shared_dir, tmp_path, capsys):
    argv = ["evaluate", "--pack", "lumbar_lift", "--report", str(tmp_path / "r"), "--leave-out", "psoas_r"]
    argv += ["--train", str(_trial("squat5kg", shared_dir, tmp_path))]
    argv += ["--trial", str(_trial("stoop5kg", shared_dir, tmp_path))]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "psoas_r" in err and "iliocost_r" in err  # names the group and the ones that can be left out
    # the report folder, made before the work to refuse a bad one early, is not left behind empty
    assert not (tmp_path / "r").exists()


def test_leave_out_refuses_a_held_out_trial_that_is_also_a_training_trial(shared_dir, tmp_path, capsys):
    """Found by a new user's walk: the same trial as --train and --trial gave "target met" verdicts on in-sample
    data, where `msk discrepancy` refuses it; both now refuse it alike, before any calibration."""
    squat = str(_trial("squat5kg", shared_dir, tmp_path))
    argv = ["evaluate", "--pack", "lumbar_lift", "--report", str(tmp_path / "r"), "--leave-out", "all"]
    assert main([*argv, "--train", squat, "--trial", squat]) == 2
    err = capsys.readouterr().err
    assert "field '--trial'" in err and "must not also be a training trial" in err and squat in err, err
    assert not (tmp_path / "r").exists()


def test_no_emg_strength_measured_puts_unmeasured_groups_on_the_measured_scale(shared_dir, tmp_path):
    """``--no-emg-strength measured``: the groups without EMG take the geometric median of the measured groups'
    calibrated factors, and their minimal-effort prior is re-derived at those strengths (lower here: the extensors'
    factors are above 1, so each unit of activation carries more force); the NLP, hence the measured factors, is the
    same as with the default."""
    from msk_core.estimate.pipeline import calibrate_subject
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack

    pack = load_pack("lumbar_lift")
    trial = load_trial(_trial("squat5kg", shared_dir, tmp_path), pack)
    reference, result = calibrate_subject(pack, [trial])
    measured, result_m = calibrate_subject(pack, [trial], no_emg_strength="measured")
    assert np.allclose(result.scale, result_m.scale) and measured.calibration["no_emg_strength"] == "measured"
    has_emg = np.asarray(reference.prior.has_emg, dtype=bool)
    common = float(np.exp(np.median(np.log(result.scale[has_emg]))))
    f_ref = np.asarray(pack.f_max_ref, dtype=float)
    assert common > 1.0
    assert np.allclose(np.asarray(measured.f_max)[~has_emg], common * f_ref[~has_emg])
    assert np.allclose(np.asarray(measured.f_max)[has_emg], np.asarray(reference.f_max)[has_emg])
    effort = [j for j, s in enumerate(reference.prior.sources) if s == "min_effort"]
    assert effort and np.allclose(measured.prior.mean[:, has_emg], reference.prior.mean[:, has_emg])
    assert measured.prior.mean[:, effort].mean() < reference.prior.mean[:, effort].mean()


WALK = Path(__file__).resolve().parents[1] / "recordings" / "lowerlimb-walk"


def _walk_excerpt(shared_dir: Path, tmp_path: Path, name: str, start: float, end: float | None, *, grf: bool) -> Path:
    """A window of the walk's trial file (``end`` None: to the end), its reps the gait cycles from the force plate
    (``grf``) or from the kinematics (the committed files' hip-flexion reps)."""
    data = (shared_dir / "data" / "lowerlimb-walk").resolve()
    text = (WALK / "walk_train.toml").read_text().replace("../../../shared/data/lowerlimb-walk", str(data))
    text = "\n".join(line for line in text.splitlines() if not line.startswith(("end =", "name =")))
    text = f'name = "{name}"\nstart = {start}\n' + ("" if end is None else f"end = {end}\n") + text
    if grf:
        text = text.replace('phase_signal = "hip_flexion_r"', f'grf = "{data / "walk45_XLD.mot"}"')
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return path


def test_gait_cycles_from_the_force_plate(shared_dir, tmp_path):
    """``grf = ...``: the reps are the right foot's gait cycles, heel strike (vertical force rising through 20 N)
    to heel strike, its column found by name; the kinematic reps start a tenth of a cycle later and leave more
    frames between reps."""
    from msk_core.errors import ConfigError, InputError
    from msk_core.estimate.trial import load_trial, vertical_grf_column
    from msk_core.io import read_sto
    from msk_core.model import load_pack
    from msk_core.signal.gait import heel_strikes

    pack = load_pack("gait2392")
    trial = load_trial(_walk_excerpt(shared_dir, tmp_path, "w", 10.0, 16.0, grf=True), pack)
    kin = load_trial(_walk_excerpt(shared_dir, tmp_path, "k", 10.0, 16.0, grf=False), pack)
    grf = read_sto(shared_dir / "data" / "lowerlimb-walk" / "walk45_XLD.mot")
    strikes = heel_strikes(grf.time, grf.column("ground_force_vy"))
    inside = strikes[(strikes >= 10.0) & (strikes <= 16.0)]
    assert trial.phase_signal == "grf:ground_force_vy" and trial.phase_coordinate is None
    assert int(trial.rep_index.max()) + 1 == inside.size - 1 >= 4  # one rep per complete cycle
    starts = [trial.time[np.flatnonzero(trial.rep_index == k)[0]] for k in range(inside.size - 1)]
    assert np.allclose(starts, inside[:-1], atol=0.011)  # each rep starts at the first frame of its cycle
    assert np.mean(trial.rep_index >= 0) > np.mean(kin.rep_index >= 0)
    # the columns by name: the side in the name, else the unprefixed one beside the other foot's
    cols = list(grf.columns)
    assert vertical_grf_column(cols, "r") == "ground_force_vy" and vertical_grf_column(cols, "l") == "l_ground_force_vy"
    assert vertical_grf_column(["time", "r_ground_force_vy", "ground_force_vy"], "r") == "r_ground_force_vy"
    assert vertical_grf_column(["time", "ground_force_right_vy", "ground_force_left_vy"], "l") == "ground_force_left_vy"
    with pytest.raises(InputError, match="no vertical ground-reaction-force column of foot 'r'.*ground_force_vy"):
        vertical_grf_column(["time", "ground_force_vy", "1_ground_force_vy"], "r")
    with pytest.raises(ConfigError, match="grf_foot"):
        vertical_grf_column(cols, "x")
    both = _walk_excerpt(shared_dir, tmp_path, "both", 10.0, 16.0, grf=True)
    both.write_text('phase_signal = "hip_flexion_r"\n' + both.read_text())
    with pytest.raises(ConfigError, match="grf and phase_signal both define the reps"):
        load_trial(both, pack)


HALF_WALK_S = 29.268  # the right heel strike nearest the middle of the walk (the committed trial files)


def test_leave_out_on_the_walk_with_force_plate_cycles_meets_the_targets_against_the_aligned_envelope(
    shared_dir, tmp_path
):
    """The full leave-one-out on the real walk (first half calibrates, second half held out, gait cycles from the
    force plate), defaults: every calibration converges with the reduced solver and has no factor for the group it
    leaves out. Against the envelope delayed by the calibrated delay (docs/estimation.md, "Leave one electrode out";
    measured 27 Nov: assisted 0.0463 vs so 0.0593, r 0.88 vs 0.71) the three walk targets are met; against the
    envelope as recorded only the r above so's (0.55 vs 0.33; RMSE -14 %)."""
    from msk_core.estimate.leave_out import leave_one_out
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack

    pack = load_pack("gait2392")
    train = load_trial(_walk_excerpt(shared_dir, tmp_path, "train", 0.0, HALF_WALK_S, grf=True), pack)
    held = load_trial(_walk_excerpt(shared_dir, tmp_path, "held", HALF_WALK_S, None, grf=True), pack)
    result = leave_one_out(pack, [train], [held])
    assert len(result.groups) == 9
    assert all(run.converged for run in result.calibrations), [r.to_dict() for r in result.calibrations]
    for run in result.calibrations[1:]:
        assert run.left_out not in run.strength and run.left_out in result.calibrations[0].strength
    aligned = result.targets(aligned=True)
    assert aligned["rmse_met"] and aligned["r_met"] and aligned["median_r"] >= 0.6, aligned
    recorded = result.targets()
    assert recorded["r_met"], recorded
    scores = result.leave_one_out["soleus_r"]
    assert set(scores) == set(LEAVE_OUT_METHODS)
    assert all(0 < s.rmse < 0.5 for s in scores.values()), scores
    # the soleus follows the ankle's plantarflexion demand without its electrode (0.6-0.7 on the full walk), later
    # than its envelope by about the calibrated delay: against the delayed envelope it correlates better (0.94)
    assert scores["proposed"].r > 0.4, scores["proposed"]
    assert scores["proposed"].lag_ms > 0 and scores["proposed"].r_aligned > scores["proposed"].r, scores["proposed"]
    assert result.cpu_seconds > 0 and all(run.cpu_seconds > 0 for run in result.calibrations)


def test_no_emg_strength_synergist_takes_the_most_similar_measured_groups_factor(shared_dir, tmp_path):
    """``no_emg_strength="synergist"``: a group without EMG whose moment arms match a measured group's (cosine >= 0.9)
    takes that group's calibrated factor, the others the measured factors' geometric median; the NLP is unchanged."""
    from msk_core.estimate.pipeline import SYNERGIST_MIN_COSINE, calibrate_subject, pick_synergists
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack

    pack = load_pack("lumbar_lift")
    trial = load_trial(_trial("squat5kg", shared_dir, tmp_path), pack)
    measured, result = calibrate_subject(pack, [trial], no_emg_strength="measured")
    synergist, result_s = calibrate_subject(pack, [trial], no_emg_strength="synergist")
    assert np.allclose(result.scale, result_s.scale) and synergist.calibration["no_emg_strength"] == "synergist"
    groups = list(pack.groups)
    has_emg = np.asarray(synergist.prior.has_emg, dtype=bool)
    picked = pick_synergists(pack, [trial], [g for g, m in zip(groups, has_emg) if not m], sorted(trial.emg))
    assert picked and SYNERGIST_MIN_COSINE == 0.9
    f_ref = np.asarray(pack.f_max_ref, dtype=float)
    f_s, f_m = np.asarray(synergist.f_max), np.asarray(measured.f_max)
    for g, h in picked.items():
        assert f_s[groups.index(g)] == pytest.approx(result.scale[groups.index(h)] * f_ref[groups.index(g)])
    rest = [j for j, g in enumerate(groups) if not has_emg[j] and g not in picked]
    assert np.allclose(f_s[rest], f_m[rest]) and np.allclose(f_s[has_emg], f_m[has_emg])


def test_live_synergists_meet_both_targets_on_the_lifts(shared_dir, tmp_path):
    """What is met (docs/estimation.md, "Leave one electrode out"): on squat -> stoop, every trunk group left out in
    turn, with the synergist prior, the measured strength and ``assisted`` following the live envelope of the left-out
    group's measured synergist, the median RMSE of assisted is at least 20 % below so's (same profiles) and its median
    r above so's (paired: over the groups where so's r is defined). Without the live synergists assisted's r is not."""
    from msk_core.estimate.leave_out import leave_one_out
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack
    from services.bench.leave_out import lift_options

    pack = load_pack("lumbar_lift")
    train = load_trial(_trial("squat5kg", shared_dir, tmp_path), pack)
    held = load_trial(_trial("stoop5kg", shared_dir, tmp_path), pack)
    live = leave_one_out(pack, [train], [held], **lift_options()).targets()  # as msk bench leave-out runs them
    assert live["method"] == "assisted" and live["rmse_met"] and live["r_met"], live
    assert live["r_groups"] == 6  # so gives both rectus abdominis a constant (their r undefined)
    assisted = leave_one_out(pack, [train], [held], **(lift_options() | {"live_synergists": False}))
    assisted = assisted.method_targets("assisted")
    assert assisted["rmse_met"] and not assisted["r_met"], assisted


def test_aligned_scores_compare_with_the_envelope_delayed_by_the_calibrated_delay():
    """An estimate that is exactly the envelope delayed by d (a(t) = e(t - d), the calibration's model) scores RMSE 0
    and r 1 against the aligned envelope, and less against the envelope as recorded; delayed the other way, worse."""
    from msk_core.estimate.emd import shift_emg
    from msk_core.estimate.leave_out import _agreement
    from tests.test_estimate_no_emg_prior import ConstantPack, _trial

    trial = _trial()
    d = 0.08
    envelope = trial.emg["g0"]
    delayed = np.interp(trial.time - d, trial.time, envelope)
    early = np.interp(trial.time + d, trial.time, envelope)
    pack = ConstantPack()
    j = list(pack.groups).index("g0")

    def scores(signal):
        est = np.zeros((trial.n_frames, len(pack.groups)))
        est[:, j] = signal
        return _agreement([trial], [shift_emg(trial, d, hold_first=False)], [est], pack, "g0", 0.01)

    right, wrong = scores(delayed), scores(early)
    assert right.rmse_aligned < 1e-12 and right.r_aligned > 1 - 1e-12
    assert right.rmse > 0.01 and right.r < right.r_aligned and right.lag_ms > 0
    assert wrong.rmse_aligned > right.rmse and wrong.lag_ms < 0


def test_leave_out_names_a_misspelt_group_and_a_training_set_without_emg(shared_dir, tmp_path, capsys):
    """Found by a new user's walk: `--leave-out tib_ant` said what `psoas_r` (a group without an electrode) says, with
    no "did you mean"; training trials without EMG gave "cannot leave out no group" naming no file."""
    squat, stoop = _trial("squat5kg", shared_dir, tmp_path), _trial("stoop5kg", shared_dir, tmp_path)
    argv = ["evaluate", "--pack", "lumbar_lift", "--report", str(tmp_path / "r"), "--train", str(squat)]
    assert main([*argv, "--trial", str(stoop), "--leave-out", "iliocost"]) == 2
    err = capsys.readouterr().err
    assert "field '--leave-out'" in err and "not a group of pack 'lumbar_lift'; did you mean" in err, err
    assert "iliocost_r" in err.split("did you mean", 1)[1], err
    assert main([*argv, "--trial", str(stoop), "--leave-out", "psoas_r"]) == 2  # a group, but no electrode
    assert "psoas_r: no electrode in the training trials with reps nor the held-out trials" in capsys.readouterr().err
    no_emg = tmp_path / "no_emg.toml"  # its paths made absolute (the committed ones are relative to its folder)
    relative = "../../../shared/data/backmodel-lift"
    text = squat.read_text().replace(relative, str((squat.parent / relative).resolve()))
    no_emg.write_text(text.split("[emg_map]")[0].replace("emg = ", "# emg = "))
    argv[-1] = str(no_emg)
    assert main([*argv, "--trial", str(stoop), "--leave-out", "all"]) == 2
    err = capsys.readouterr().err
    assert f"{no_emg}, field 'emg': a leave-one-out needs EMG in the training trials too" in err, err
    assert not (tmp_path / "r").exists()


def test_a_group_is_found_by_its_display_name_in_any_case():
    from msk_core.model import load_pack
    from services.commands.estimate import leave_out_group

    pack = load_pack("gait2392")
    assert leave_out_group(pack, "TIB_ANT_R") == "tib_ant_r"
    assert leave_out_group(pack, pack.display_names.group("tib_ant_r").lower()) == "tib_ant_r"


def test_the_reports_figures_do_not_round_onto_their_target():
    """Found by a new user's walk: "RMSE -20 %" for a -19.97 % that misses the -20 % target, "r 0.67 vs so 0.67"."""
    from services.surfaces.reports.evaluation import _percent, _two_r

    assert _percent(-0.1997, -0.2) == "-19.97" and _percent(-0.31, -0.2) == "-31.0" and _percent(0.228, -0.2) == "+22.8"
    assert _percent(-0.19996, -0.2) == "-19.996" and _percent(-0.2, -0.2) == "-20.0"  # (found by a review)
    assert _two_r(0.6712, 0.6698) == ("0.671", "0.670") and _two_r(0.55, 0.27) == ("0.55", "0.27")
    assert _two_r(0.8844, 0.8836) == ("0.8844", "0.8836") and _two_r(0.5, float("nan")) == ("0.50", "none")
    from services.surfaces.reports.evaluation import _apart

    assert _apart(0.597, 0.6, 2) == "0.597"  # the r >= 0.6 line: 0.597 is not "0.60 ... not met"
