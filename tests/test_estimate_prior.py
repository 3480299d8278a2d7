"""Offline rep phase, the phase prior built from reps, and the subject profile round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msk_core.errors import EstimationError, FileFormatError
from msk_core.estimate import PhasePrior, SubjectProfile, prior_from_reps
from msk_core.estimate.phase import detect_reps
from msk_core.estimate.prior import REST_PHASE
from msk_core.io import read_sto


def test_detect_reps_on_a_synthetic_signal_gives_phase_through_each_rep():
    t = np.linspace(0, 12, 1201)
    x = np.where((t % 4) < 2.5, np.sin(np.pi * (t % 4) / 2.5) ** 2, 0.0)  # 3 reps of 2.5 s with 1.5 s rest
    phase, rep = detect_reps(t, x)
    assert rep.max() == 2
    for k in range(3):
        ph = phase[rep == k]
        assert ph[0] == 0.0 and ph[-1] == 1.0 and np.all(np.diff(ph) > 0)
        span = t[rep == k] - 4 * k
        # boundaries where the excursion crosses 15 % of its peak: sin^2(pi t / 2.5) = 0.15
        edge = 2.5 / np.pi * np.arcsin(np.sqrt(0.15))
        assert abs(span[0] - edge) < 0.015 and abs(span[-1] - (2.5 - edge)) < 0.015
    assert np.all(np.isnan(phase[rep < 0]))
    with pytest.raises(EstimationError):
        detect_reps(t, np.zeros_like(t))


def test_detect_reps_finds_the_five_lifts_of_each_backmodel_trial(shared_dir):
    for trial in ("squat5kg", "stoop5kg"):
        tau = read_sto(shared_dir / "data" / "backmodel-lift" / trial / "id.sto")
        _, rep = detect_reps(tau.time, tau.column("L5_S1_Flex_Ext"))
        assert rep.max() + 1 == 5, trial


def test_prior_from_reps_mean_and_spread_across_reps():
    n_bins, reps = 4, 3
    phase = np.tile(np.linspace(0, 0.999, 40), reps)
    rep_index = np.repeat(np.arange(reps), 40)
    level = np.array([0.2, 0.3, 0.4])[rep_index]  # each rep a constant level
    prior = prior_from_reps(["a", "b"], {"a": level}, phase, rep_index, n_bins=n_bins)
    np.testing.assert_allclose(prior.mean[:, 0], 0.3)
    np.testing.assert_allclose(prior.std[:, 0], 0.1)  # sample std across reps (ddof 1)
    assert prior.has_emg.tolist() == [True, False] and np.all(prior.std[:, 1] == 0.5)
    mu, sd = prior.at(0.5)
    np.testing.assert_allclose(mu, [0.3, 0.0])
    mu_p, sd_p = prior.at(None)
    np.testing.assert_allclose(sd_p[0], 0.1)


def test_rest_prior_from_samples_outside_reps_selected_by_negative_phase():
    phase = np.r_[np.full(10, np.nan), np.linspace(0, 0.99, 30), np.full(10, np.nan)]
    rep_index = np.r_[np.full(10, -1), np.zeros(30, dtype=int), np.full(10, -1)]
    emg = np.r_[np.full(10, 0.02), np.full(30, 0.3), np.full(10, 0.04)]
    prior = prior_from_reps(["a"], {"a": emg}, phase, rep_index, n_bins=3)
    mu, sd = prior.at(REST_PHASE)
    np.testing.assert_allclose(mu, [0.03])
    np.testing.assert_allclose(sd, [0.02])  # spread 0.01, floored at MIN_STD
    np.testing.assert_allclose(prior.at(0.5)[0], [0.3])
    back = PhasePrior.from_dict(json.loads(json.dumps(prior.to_dict())))
    np.testing.assert_allclose(back.at(REST_PHASE)[0], mu)


def test_phase_prior_interpolates_between_bin_centres_and_clamps():
    prior = PhasePrior(("g",), np.array([[0.0], [1.0]]), np.array([[0.1], [0.2]]), np.array([True]))
    assert prior.at(0.25)[0][0] == 0.0 and prior.at(0.75)[0][0] == 1.0  # bin centres
    np.testing.assert_allclose(prior.at(0.5)[0], [0.5])
    np.testing.assert_allclose(prior.at(3.0)[0], [1.0])  # clamped at the last bin
    np.testing.assert_allclose(prior.at(-1.0)[0], prior.pooled()[0])  # between reps, no rest state: pooled
    prec = 0.5 * (1 / 0.01 + 1 / 0.04)
    np.testing.assert_allclose(prior.at(0.5)[1], [1 / np.sqrt(prec)])


def test_subject_profile_round_trip_and_errors(tmp_path):
    prior = PhasePrior(("g1", "g2"), np.full((3, 2), 0.2), np.full((3, 2), 0.1), np.array([True, False]))
    prof = SubjectProfile("toy", "2", ["g1", "g2"], np.array([600.0, 900.0]), np.array([500.0, 1000.0]), prior,
                          {"ch1": {"group": "g1", "divisor": 1.0}}, {"converged": True}, {"trials": ["a.toml"]})
    path = tmp_path / "s.json"
    prof.save(path)
    back = SubjectProfile.load(path)
    np.testing.assert_allclose(back.f_max, prof.f_max)
    np.testing.assert_allclose(back.scale_factors, [1.2, 0.9])
    np.testing.assert_allclose(back.prior.mean, prior.mean)
    assert back.emg_normalisation == prof.emg_normalisation

    class Pack:
        name, version, groups = "toy", "3", ["g1", "g2"]

    with pytest.raises(EstimationError, match="version '3'"):
        back.check_pack(Pack())
    path.write_text("{ not json")
    with pytest.raises(FileFormatError, match="s.json, line 1"):
        SubjectProfile.load(path)
    data = prof.to_dict()
    del data["groups"]["g2"]["f_max_n"]
    path.write_text(json.dumps(data))
    with pytest.raises(FileFormatError, match="field 'f_max_n'"):
        SubjectProfile.load(path)
