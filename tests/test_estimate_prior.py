"""Offline rep phase of a torque, the phase prior fitted from reps, and the subject profile round trip."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msk_core.errors import EstimationError, FileFormatError
from msk_core.estimate import PhasePrior, SubjectProfile, fit_phase_prior
from msk_core.estimate.phase import torque_phase
from msk_core.estimate.prior import MIN_STD
from msk_core.io import read_sto
from msk_core.signal.reps import REST_PHASE


def test_torque_phase_on_a_synthetic_signal_gives_phase_through_each_rep():
    t = np.linspace(0, 12, 1201)
    x = np.where((t % 4) < 2.5, np.sin(np.pi * (t % 4) / 2.5) ** 2, 0.0)  # 3 reps of 2.5 s with 1.5 s rest
    phase, rep = torque_phase(t, x)
    assert rep.max() == 2 and np.all(phase[rep < 0] == REST_PHASE)
    for k in range(3):
        ph = phase[rep == k]
        assert ph[0] == 0.0 and ph[-1] < 1.0 and np.all(np.diff(ph) > 0)
        span = t[rep == k] - 4 * k
        # a complete rep: from where the excursion leaves rest to where it is back (within 3 % of its range)
        edge = 2.5 / np.pi * np.arcsin(np.sqrt(0.03))
        assert span[0] <= edge and span[-1] >= 2.5 - edge - 0.01
        assert phase[rep == k][np.argmin(np.abs(span - 1.25))] == pytest.approx(0.5, abs=0.01)  # turning point
    with pytest.raises(EstimationError, match="does not move"):
        torque_phase(t, np.zeros_like(t))


def test_torque_phase_finds_the_five_lifts_of_each_backmodel_trial(shared_dir):
    for trial in ("squat5kg", "stoop5kg"):
        tau = read_sto(shared_dir / "data" / "backmodel-lift" / trial / "id.sto")
        _, rep = torque_phase(tau.time, tau.column("L5_S1_Flex_Ext"))
        assert rep.max() + 1 == 5, trial


def test_phase_prior_mean_and_spread_across_reps():
    n_bins, reps = 4, 3
    phase = np.tile(np.linspace(0, 0.999, 40), reps)
    rep_index = np.repeat(np.arange(reps), 40)
    level = np.array([0.2, 0.3, 0.4])[rep_index]  # each rep a constant level
    prior = fit_phase_prior(["a", "b"], {"a": level}, phase, rep_index, n_bins=n_bins)
    np.testing.assert_allclose(prior.mean[:, 0], 0.3)
    np.testing.assert_allclose(prior.std[:, 0], 0.1)  # sample std across reps (ddof 1)
    assert prior.has_emg.tolist() == [True, False] and np.all(prior.std[:, 1] == 0.5)
    mu, sd = prior.at(0.5)
    np.testing.assert_allclose(mu, [0.3, 0.0])
    mu_p, sd_p = prior.at(None)
    np.testing.assert_allclose(sd_p[0], 0.1)


def test_rest_prior_from_samples_outside_reps_selected_by_negative_phase():
    phase = np.r_[np.full(10, REST_PHASE), np.linspace(0, 0.99, 30), np.full(10, REST_PHASE)]
    rep_index = np.r_[np.full(10, -1), np.zeros(30, dtype=int), np.full(10, -1)]
    emg = np.r_[np.full(10, 0.02), np.full(30, 0.3), np.full(10, 0.04)]
    prior = fit_phase_prior(["a"], {"a": emg}, phase, rep_index, n_bins=3)
    mu, sd = prior.at(REST_PHASE)
    np.testing.assert_allclose(mu, [0.03])
    np.testing.assert_allclose(sd, [0.02])  # spread 0.01, floored at MIN_STD
    np.testing.assert_allclose(prior.at(0.5)[0], [0.3])
    back = PhasePrior.from_dict(json.loads(json.dumps(prior.to_dict())))
    np.testing.assert_allclose(back.at(REST_PHASE)[0], mu)


def _synthetic_reps(n_reps: int, seed: int):
    """Two groups: mu_g(phase) known, a per-rep offset with sd sigma_g; reps of random length with rest between."""
    rng = np.random.default_rng(seed)
    sigma = np.array([0.05, 0.1])
    phases, index, emg = [], [], []
    for k in range(n_reps):
        n = int(rng.integers(80, 200))
        ph = np.arange(n) / n
        mu = np.column_stack([0.2 + 0.5 * np.sin(np.pi * ph), 0.1 + 0.3 * ph])
        emg.append(mu + sigma * rng.standard_normal(2))  # the whole rep sits one draw above/below the mean
        phases += [ph, np.full(30, REST_PHASE)]
        index += [np.full(n, k), np.full(30, -1)]
        emg.append(np.full((30, 2), 0.02))
    return np.concatenate(phases), np.concatenate(index), np.vstack(emg), sigma


def test_phase_prior_recovers_known_mean_and_rep_to_rep_spread_and_rest_is_its_own_state():
    phase, index, emg, sigma = _synthetic_reps(400, seed=0)
    prior = fit_phase_prior(["pecs", "triceps"], {"pecs": emg[:, 0], "triceps": emg[:, 1]}, phase, index, n_bins=10)
    centres = (np.arange(10) + 0.5) / 10
    true_mu = np.column_stack([0.2 + 0.5 * np.sin(np.pi * centres), 0.1 + 0.3 * centres])
    np.testing.assert_allclose(prior.mean, true_mu, atol=0.02)  # bin averages of sin: within 0.01 of the centre's
    np.testing.assert_allclose(prior.std, np.broadcast_to(sigma, prior.std.shape), rtol=0.12)
    np.testing.assert_array_equal(prior.at(0.55)[0], prior.mean[5])  # a bin centre
    # between reps: the rest state, not the first phase bin
    np.testing.assert_allclose(prior.at(REST_PHASE)[0], [0.02, 0.02])
    assert np.all(np.abs(prior.at(REST_PHASE)[0] - prior.mean[0]) > 0.05)
    _, sd_any = prior.at(float("nan"))  # phase unknown: pooled, wider
    assert np.all(sd_any >= prior.std.mean(axis=0))


def test_phase_prior_of_one_rep_uses_the_spread_within_its_bins_floored(tmp_path):
    phase, index, emg, _ = _synthetic_reps(1, seed=1)
    prior = fit_phase_prior(["a", "b"], {"a": emg[:, 0], "b": emg[:, 1]}, phase, index, n_bins=5)
    assert np.all(prior.std >= MIN_STD) and np.all(prior.std[:, 0] < 0.1)
    with pytest.raises(EstimationError, match="no repetition"):
        fit_phase_prior(["a"], {"a": emg[:, 0]}, phase, np.full(index.shape, -1), n_bins=5)


def test_phase_prior_of_a_real_lift_has_the_back_extensors_working_mid_lift(shared_dir, tmp_path):
    import os

    from msk_core.estimate.pipeline import PriorSettings, build_prior
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack

    data = shared_dir / "data/backmodel-lift/squat5kg"
    groups = ["iliocost_r", "iliocost_l", "longthor_r", "rectabd_r"]
    toml = tmp_path / "squat.toml"
    rel = lambda f: os.path.relpath(data / f, tmp_path)  # noqa: E731
    toml.write_text(
        f'kinematics = "{rel("ik.sto")}"\ntorques = "{rel("id.sto")}"\nemg = "{rel("emgFilt.sto")}"\n'
        'phase_signal = "pelvis_ty"\nload_kg = 5.0\n[emg_map]\n' + "".join(f'{g} = "{g}"\n' for g in groups)
    )
    trial = load_trial(toml, load_pack("lumbar_lift"))
    assert trial.rep_index.max() + 1 == 4  # the pelvis drops in each of the four lifts, squat or stoop
    prior = build_prior(load_pack("lumbar_lift"), [trial], PriorSettings(n_bins=10, no_emg="wide"))
    ilio = prior.mean[:, list(prior.groups).index("iliocost_r")]
    assert ilio[3:7].max() > 1.3 * ilio[0]  # back extensors work harder mid-lift than at its start (standing)
    measured = [list(prior.groups).index(g) for g in groups]
    assert np.all(prior.mean[:, measured] >= 0) and np.all(prior.mean[:, measured] < 1.5)


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
    prof = SubjectProfile(
        "toy",
        "2",
        ["g1", "g2"],
        np.array([600.0, 900.0]),
        np.array([500.0, 1000.0]),
        prior,
        {"ch1": {"group": "g1", "divisor": 1.0}},
        {"converged": True},
        {"trials": ["a.toml"]},
    )
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
