"""Phase priors N(mu, sigma^2): recovered from synthetic reps with known statistics, fitted on real lifts, JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import ConfigError, InputError
from msk_core.io import load_trial
from msk_core.signal.reps import Excursion, RepDetectionConfig, detect_reps, rep_phase
from msk_core.signal.priors import PhasePriors, average_groups, fit_priors


def _synthetic(n_reps: int, seed: int):
    """Two groups: mu_g(phase) known, a per-rep offset with sd sigma_g; reps of random length."""
    rng = np.random.default_rng(seed)
    sigma = np.array([0.05, 0.1])
    phases, index, emg = [], [], []
    for k in range(n_reps):
        n = int(rng.integers(80, 200))
        ph = np.arange(n) / n
        mu = np.column_stack([0.2 + 0.5 * np.sin(np.pi * ph), 0.1 + 0.3 * ph])
        emg.append(mu + sigma * rng.standard_normal(2))  # the whole rep sits one draw above/below the mean
        phases.append(ph)
        index.append(np.full(n, k))
        # rest between reps: outside any rep
        phases.append(np.full(30, np.nan))
        index.append(np.full(30, -1))
        emg.append(np.full((30, 2), 0.02))
    return np.concatenate(phases), np.concatenate(index), np.vstack(emg), sigma


def test_recovers_known_mean_and_rep_to_rep_std() -> None:
    phase, index, emg, sigma = _synthetic(400, seed=0)
    pr = fit_priors(phase, index, emg, ["pecs", "triceps"], n_bins=10)
    centres = (np.arange(10) + 0.5) / 10
    true_mu = np.column_stack([0.2 + 0.5 * np.sin(np.pi * centres), 0.1 + 0.3 * centres])
    # bin averages of sin differ from the centre value by < 0.01
    np.testing.assert_allclose(pr.mean, true_mu, atol=0.02)
    np.testing.assert_allclose(pr.std, np.broadcast_to(sigma, pr.std.shape), rtol=0.12)
    assert np.all(pr.n_reps == 400)
    mu, sd = pr.at(0.55)
    np.testing.assert_array_equal(mu, pr.mean[5])
    mu_any, sd_any = pr.at(float("nan"))  # no rep under way: pooled, wider prior
    assert np.all(sd_any >= pr.std.mean(axis=0))
    np.testing.assert_array_equal(pr.bin_of(np.array([0.0, 0.0999, 0.1, 0.999, np.nan])), [0, 0, 1, 9, -1])


def test_single_rep_is_floored_and_round_trips_json() -> None:
    phase, index, emg, _ = _synthetic(1, seed=1)
    pr = fit_priors(phase, index, emg, ["a", "b"], n_bins=5, min_std=0.02)
    assert np.all(pr.std == 0.02) and np.all(pr.n_reps == 1)
    back = PhasePriors.from_dict(json.loads(json.dumps(pr.to_dict())))
    assert back.groups == ("a", "b")
    np.testing.assert_array_equal(back.mean, pr.mean)
    np.testing.assert_array_equal(back.std, pr.std)


def test_fit_on_backmodel_squat(shared_dir: Path) -> None:
    groups = ["iliocost_r", "iliocost_l", "longthor_r", "rectabd_r"]
    aligned = load_trial(shared_dir / "data/backmodel-lift/squat5kg", emg_columns=groups)
    reps = detect_reps(aligned.time, aligned.coordinate("pelvis_ty"), RepDetectionConfig(excursion=Excursion.DECREASE))
    phase, index = rep_phase(aligned.time, reps)
    pr = fit_priors(phase, index, aligned.emg, groups, n_bins=10)
    assert pr.mean.shape == (10, 4) and np.all(pr.n_reps == 4)
    # back extensors work harder in mid-lift than at its start (standing)
    ilio = pr.mean[:, 0]
    assert ilio[3:7].max() > 1.3 * ilio[0]
    assert np.all(pr.mean >= 0) and np.all(pr.mean < 1.5) and np.all(pr.std >= 0.01)


def test_errors() -> None:
    with pytest.raises(InputError, match="no sample lies inside"):
        fit_priors(np.full(5, np.nan), np.full(5, -1), np.zeros((5, 1)), ["a"])
    with pytest.raises(InputError, match="2 group names for 1"):
        fit_priors(np.zeros(5), np.zeros(5, dtype=int), np.zeros((5, 1)), ["a", "b"])
    with pytest.raises(InputError, match=r"\[0, 1\)"):
        fit_priors(np.full(5, 1.0), np.zeros(5, dtype=int), np.zeros((5, 1)), ["a"])
    with pytest.raises(ConfigError, match="field 'std'"):
        PhasePriors.from_dict({"groups": ["a"], "n_bins": 1, "mean": [[0.1]], "std": [[0.0]], "n_reps": [[1]]})
    with pytest.raises(ConfigError, match="field 'mean'"):
        PhasePriors.from_dict({"groups": ["a"], "std": [[0.1]], "n_reps": [[1]]})


def test_average_groups() -> None:
    x = np.array([[1.0, 3.0, 10.0], [2.0, 4.0, 20.0]])
    g, names = average_groups(x, ["es_l", "es_r", "ra"], {"erector": ["es_l", "es_r"], "abdominal": ["ra"]})
    assert names == ["erector", "abdominal"]
    np.testing.assert_array_equal(g, [[2.0, 10.0], [3.0, 20.0]])
    with pytest.raises(InputError, match="group 'x' names unknown channels \\['nope'\\]"):
        average_groups(x, ["es_l", "es_r", "ra"], {"x": ["nope"]})
