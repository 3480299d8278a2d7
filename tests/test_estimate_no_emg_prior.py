"""Priors of groups without EMG: minimal effort (static optimisation over the reps), measured synergist, wide."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import EstimationError
from msk_core.estimate import PhasePrior, SubjectProfile
from msk_core.estimate.pipeline import NoEmgPrior, PriorSettings, build_prior, pick_synergists
from msk_core.estimate.prior import NO_EMG_STD
from msk_core.estimate.trial import TrialData
from msk_core.signal.reps import REST_PHASE

# one coordinate; g0, g1 extensors (g1 unmeasured, like g0), g2 flexor (measured), g3 flexor unmeasured
ARMS = np.array([[0.05, 0.03, -0.04, -0.02]])
F_REF = np.array([800.0, 500.0, 600.0, 400.0])


class ConstantPack:
    name, version = "toy", "1"
    coordinates = ["c0"]
    groups = ["g0", "g1", "g2", "g3"]
    f_max_ref = F_REF

    def moment_arms(self, q):
        return ARMS.copy()

    def inverse_dynamics(self, q, qd, qdd, hand_load_newton):
        return np.zeros(1)


def _trial(n_reps: int = 4) -> TrialData:
    rate, rest, rep = 50.0, 25, 100
    tau, phase, index = [], [], []
    for k in range(n_reps):
        tau += [0.0] * rest
        phase += [REST_PHASE] * rest
        index += [-1] * rest
        ph = np.arange(rep) / rep
        tau += list((10.0 + 2.0 * k) * np.sin(np.pi * ph))  # extension torque, a bit larger each rep
        phase += list(ph)
        index += [k] * rep
    tau += [0.0] * rest
    phase += [REST_PHASE] * rest
    index += [-1] * rest
    n = len(tau)
    tau = np.array(tau)[:, None]
    a = np.clip(tau[:, 0] / 60.0, 0.0, 1.0)
    return TrialData(
        name="toy",
        path=Path("toy.toml"),
        time=np.arange(n) / rate,
        q=np.zeros((n, 1)),
        qd=np.zeros((n, 1)),
        qdd=np.zeros((n, 1)),
        torques=tau,
        torque_source="file",
        emg={"g0": a, "g2": 0.02 + 0 * a},
        emg_channels={"g0": "g0", "g2": "g2"},
        emg_normalisation={},
        load_kg=0.0,
        body_mass_kg=None,
        phase=np.array(phase),
        rep_index=np.array(index),
        phase_signal="torque:c0",
    )


def test_min_effort_prior_is_static_optimisation_binned_over_reps():
    trial = _trial()
    prior = build_prior(ConstantPack(), [trial], PriorSettings(n_bins=10))
    assert prior.sources == ("emg", "min_effort", "emg", "min_effort")
    assert list(prior.has_emg) == [True, False, True, False]
    # independent so for one coordinate: a_g = max(A_g, 0) tau / sum max(A_h, 0)^2 while no group saturates
    a_cols = np.clip(ARMS[0] * F_REF, 0.0, None)
    so = trial.torques[:, 0:1] * a_cols / (a_cols @ a_cols)
    bins = np.minimum((trial.phase * 10).astype(int), 9)  # used inside reps only
    for b in (2, 5, 8):
        per_rep = [so[(trial.rep_index == k) & (bins == b), 1].mean() for k in range(4)]
        np.testing.assert_allclose(prior.mean[b, 1], np.mean(per_rep), rtol=1e-4)
        np.testing.assert_allclose(prior.std[b, 1], max(np.std(per_rep, ddof=1), 0.02), rtol=1e-3)
    np.testing.assert_allclose(prior.mean[:, 3], 0.0, atol=1e-4)  # the flexor does nothing against extension
    mu_rest, _ = prior.at(REST_PHASE)
    assert abs(mu_rest[1]) < 1e-4  # no torque between reps: minimal effort is rest


def test_synergist_prior_copies_the_most_similar_measured_group_and_explicit_mapping_wins():
    pack, trial = ConstantPack(), _trial()
    assert pick_synergists(pack, [trial], ["g1", "g3"], ["g0", "g2"]) == {"g1": "g0", "g3": "g2"}
    prior = build_prior(pack, [trial], PriorSettings(n_bins=10, no_emg=NoEmgPrior.SYNERGIST))
    assert prior.sources == ("emg", "synergist:g0", "emg", "synergist:g2")
    np.testing.assert_allclose(prior.mean[:, 1], prior.mean[:, 0])
    np.testing.assert_allclose(prior.std[:, 3], prior.std[:, 2])
    np.testing.assert_allclose(prior.rest_mean[1], prior.rest_mean[0])
    explicit = build_prior(pack, [trial], PriorSettings(n_bins=10, synergists={"g3": "g0"}))  # the rest: minimal effort
    assert explicit.sources == ("emg", "min_effort", "emg", "synergist:g0")
    with pytest.raises(EstimationError, match="group with EMG"):
        build_prior(pack, [trial], PriorSettings(synergists={"g3": "g1"}))


def test_wide_prior_is_the_old_default_and_sources_survive_the_profile(tmp_path):
    prior = build_prior(ConstantPack(), [_trial()], PriorSettings(n_bins=10, no_emg="wide"))
    assert prior.sources == ("emg", "default", "emg", "default")
    np.testing.assert_allclose(prior.std[:, 1], NO_EMG_STD)
    prof = SubjectProfile(
        "toy",
        "1",
        list(ConstantPack.groups),
        F_REF.copy(),
        F_REF.copy(),
        build_prior(ConstantPack(), [_trial()], PriorSettings(n_bins=10)),
    )
    prof.save(tmp_path / "s.json")
    back = SubjectProfile.load(tmp_path / "s.json")
    assert back.prior.sources == ("emg", "min_effort", "emg", "min_effort")
    with pytest.raises(EstimationError, match="sources"):
        PhasePrior(("a", "b"), np.zeros((2, 2)), np.ones((2, 2)), np.ones(2, dtype=bool), sources=("emg",))


def test_prior_settings_are_checked_copied_and_named():
    import copy
    import pickle

    from msk_core.errors import EstimationError

    given = {"g3": "g0"}
    settings = PriorSettings(n_bins=10, no_emg="synergist", synergists=given)
    given["g4"] = "g0"  # the caller's mapping changes: the settings do not
    assert settings.no_emg is NoEmgPrior.SYNERGIST and dict(settings.synergists) == {"g3": "g0"}
    assert pickle.loads(pickle.dumps(settings)) == settings == copy.deepcopy(settings)  # e.g. to a process pool
    assert hash(settings) == hash(PriorSettings(n_bins=10, no_emg=NoEmgPrior.SYNERGIST, synergists={"g3": "g0"}))
    assert str(settings) == "prior synergist, 10 bins, synergists g3=g0" and str(PriorSettings()) == "prior min_effort"
    for bins in (1, 2.5, True):
        with pytest.raises(EstimationError, match="at least 2 phase bins"):
            PriorSettings(n_bins=bins)
    with pytest.raises(EstimationError, match="no_emg must be one of min_effort, synergist, wide, got 'nearby'"):
        PriorSettings(no_emg="nearby")
