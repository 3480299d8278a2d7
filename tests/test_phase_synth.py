"""Reps, phase and priors on the project's synthetic sessions (msk_core.synth): known rep boundaries and truth."""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.estimate.prior import fit_phase_prior
from msk_core.io import resample_linear
from msk_core.signal.emg import EmgFilterConfig, envelope_zero_phase_noncausal, normalisation_reference
from msk_core.signal.reps import (
    Excursion,
    PhaseTracker,
    RepDetectionConfig,
    detect_reps,
    in_rep,
    learn_template,
    rep_phase,
)
from msk_core.synth import Exercise, SynthConfig, generate_exercise

CASES = {Exercise.DEADLIFT: "hip_flexion_r", Exercise.BENCH_PRESS: "elbow_flex_r"}


@pytest.fixture(scope="module", params=list(CASES))
def session(request):
    exercise = request.param
    es = generate_exercise(exercise, SynthConfig(n_reps=4, loads_kg={exercise: (60.0,)}))
    return exercise, es


def test_reps_match_the_generator(session) -> None:
    exercise, es = session
    trial = es.trials[0]
    signal = trial.q[:, trial.coordinates.index(CASES[exercise])]
    reps = detect_reps(trial.time, signal, RepDetectionConfig(excursion=Excursion.INCREASE))
    assert len(reps) == len(trial.rep_starts) == 4
    for rep, t0, t1 in zip(reps, trial.rep_starts, trial.rep_ends):
        # the generator's rep windows include the pauses; the detected movement lies inside them
        assert t0 - 0.05 <= rep.t_start < rep.t_turn < rep.t_end <= t1 + 0.05
        assert rep.duration > 0.5 * (t1 - t0)
    # causal phase from a template learned on the same set follows the offline phase
    offline, _ = rep_phase(trial.time, reps)
    live = PhaseTracker(learn_template(trial.time, signal, RepDetectionConfig(excursion=Excursion.INCREASE)))
    phase_live = live.process(trial.time, signal)
    both = in_rep(offline) & in_rep(phase_live)
    assert both.sum() > 0.8 * in_rep(offline).sum()
    assert np.median(np.abs(offline - phase_live)[both]) < 0.05


def test_priors_from_raw_synthetic_emg_follow_true_activation(session) -> None:
    exercise, es = session
    trial = es.trials[0]
    cfg = EmgFilterConfig(rate_hz=1.0 / (trial.emg_time[1] - trial.emg_time[0]))
    env = envelope_zero_phase_noncausal(trial.emg, cfg)  # calibration data: offline chain
    ref = normalisation_reference([envelope_zero_phase_noncausal(es.mvc.emg, cfg)], channels=tuple(trial.channels))
    normalised = resample_linear(trial.emg_time, ref.normalise(env), trial.time)
    signal = trial.q[:, trial.coordinates.index(CASES[exercise])]
    reps = detect_reps(trial.time, signal, RepDetectionConfig(excursion=Excursion.INCREASE))
    phase, index = rep_phase(trial.time, reps)
    ok = np.all(np.isfinite(normalised), axis=1)
    columns = lambda x: {c: x[:, j] for j, c in enumerate(trial.channels)}  # noqa: E731
    priors = fit_phase_prior(trial.channels, columns(normalised[ok]), phase[ok], index[ok], n_bins=10)
    truth = fit_phase_prior(
        trial.channels,
        columns(trial.activation[:, [trial.groups.index(c) for c in trial.channels]]),
        phase,
        index,
        n_bins=10,
    )
    # the most active muscles: the prior's phase profile follows the true activation's
    main = np.argsort(truth.mean.mean(axis=0))[-3:]
    for g in main:
        r = np.corrcoef(priors.mean[:, g], truth.mean[:, g])[0, 1]
        assert r > 0.8, (trial.channels[g], r)
