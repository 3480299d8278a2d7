"""Calibration on the embedded synthetic demo session (recordings/demo, known truth): strength identifiability and
the honesty of the minimal-effort prior of unmeasured groups."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msk_core.estimate.pipeline import build_prior, calibrate_subject, calibration_frames, min_effort_error
from msk_core.estimate.trial import load_trial
from msk_core.io import read_sto
from msk_core.model import load_pack

DEMO = Path(__file__).resolve().parents[1] / "recordings" / "demo"
TRIAL = DEMO / "bench_press" / "bench_press_40kg"


@pytest.fixture(scope="module")
def bench():
    pack = load_pack("bench_press")
    trial = load_trial(TRIAL / "trial.toml", pack)
    truth = read_sto(TRIAL / "truth_activations.sto")
    a_true = np.column_stack([np.interp(trial.time, truth.time, truth.column(g)) for g in pack.groups])
    f_true = json.loads((DEMO / "truth.json").read_text())["exercises"]["bench_press"]["f_max_n"]
    return pack, trial, a_true, np.array([f_true[g] for g in pack.groups])


def test_min_effort_prior_widened_by_its_error_on_measured_groups_is_honest(bench):
    pack, trial, a_true, _ = bench
    prior = build_prior(pack, [trial])
    error = min_effort_error(pack, [trial])
    assert 0.02 < error < 0.2
    unmeasured = [j for j, s in enumerate(prior.sources) if s == "min_effort"]
    assert unmeasured
    inside = trial.rep_index >= 0  # every frame of this trial is inside the pack's range

    def z_rms(frames):
        mu, sd = frames.prior_mean[inside][:, unmeasured], frames.prior_std[inside][:, unmeasured]
        return float(np.sqrt(np.mean(((a_true[inside][:, unmeasured] - mu) / sd) ** 2)))

    narrow = z_rms(calibration_frames(pack, [trial], prior))
    wide = z_rms(calibration_frames(pack, [trial], prior, min_effort_std=error))
    assert narrow > 1.5  # the across-rep spread of a deterministic SO solution is overconfident
    assert 0.5 < wide < 1.3, (narrow, wide)


def test_calibration_reports_which_strengths_the_data_determine(bench):
    pack, trial, _, f_true = bench
    profile, result = calibrate_subject(pack, [trial])
    strength = profile.calibration["strength"]
    assert set(strength) == set(pack.groups)
    assert profile.calibration["min_effort_error_rms"] > 0
    status = {g: v["status"] for g, v in strength.items()}
    assert {status[g] for g in pack.groups if g not in trial.emg} == {"not_calibrated"}
    identified = [g for g, s in status.items() if s == "identified"]
    assert identified and len(identified) < len(trial.emg)  # a few groups are determined, most are not
    for g in identified:  # identified = small data-only std, and then close to the truth
        j = pack.groups.index(g)
        assert strength[g]["std_data"] / strength[g]["scale"] <= 0.15
        assert abs(profile.f_max[j] / f_true[j] - 1.0) <= 0.10, (g, profile.f_max[j], f_true[j])
    for g in ("BRD", "PMSte", "DelPos"):  # EMG near rest all trial: their strength is invisible
        assert status[g] in ("unidentified", "at_bound") and strength[g]["std_data"] > 0.5
