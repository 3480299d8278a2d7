"""Calibration computes each trial's moment arms and static optimisation once (issue 28), shared by the delay
estimate, the prior, the minimal-effort error, the training frames and the discrepancy data, and calibrates the same
strengths as when each of them is computed frame by frame through the estimator, as they were before."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest

import msk_core.estimate.mechanics as mechanics
from msk_core.estimate.frame import FrameEstimator, FrameStatus, Method
from msk_core.estimate.mechanics import TrialMechanics
from msk_core.estimate.pack import CLAMP_TOLERANCE
from msk_core.estimate.pipeline import calibrate_subject
from msk_core.estimate.trial import TrialData, load_trial
from msk_core.model import load_pack

DEMO = Path(__file__).resolve().parents[1] / "recordings" / "demo" / "bench_press"


class CountingPack:
    """The bench press pack, counting the poses at which its muscle geometry is evaluated."""

    def __init__(self, pack) -> None:
        self._pack = pack
        self.poses = 0

    def __getattr__(self, name: str):
        return getattr(self._pack, name)

    def moment_arms(self, q, **kwargs):
        self.poses += 1
        return self._pack.moment_arms(q, **kwargs)

    def lengths_and_moment_arms(self, q, **kwargs):
        self.poses += 1
        return self._pack.lengths_and_moment_arms(q, **kwargs)

    def lengths_and_moment_arms_many(self, q, **kwargs):
        self.poses += len(q)
        return self._pack.lengths_and_moment_arms_many(q, **kwargs)


def _trials(pack) -> list[TrialData]:
    """The light lift and two isometric MVC blocks of the demo subject (a lift's frames and held poses)."""
    mvc = sorted((DEMO / "mvc").glob("*/trial.toml"))[:2]
    return [load_trial(DEMO / "bench_press_40kg" / "trial.toml", pack)] + [load_trial(p, pack) for p in mvc]


def _frame_by_frame(pack, trial: TrialData) -> TrialMechanics:
    """The moment arms and static optimisation as calibration computed them before they were computed once: each
    frame's moment arms from the pack at the pose clamped into its ranges (NaN beyond the tolerance), and static
    optimisation through the estimator's ``step``, which evaluates the pack itself."""
    lo, hi = np.asarray(pack.coordinate_ranges, dtype=float).T
    q_clamped = np.minimum(np.maximum(trial.q, lo), hi)
    usable = np.all(np.abs(q_clamped - trial.q) <= CLAMP_TOLERANCE, axis=1)
    arms = np.array(
        [
            pack.moment_arms(q) if ok else np.full((len(pack.coordinates), len(pack.groups)), np.nan)
            for q, ok in zip(q_clamped, usable)
        ]
    )
    est = FrameEstimator(pack, None, Method.SO)
    so = np.full((trial.n_frames, len(pack.groups)), np.nan)
    for i in range(trial.n_frames):
        res = est.step(trial.q[i], torques=trial.torques[i])
        if res.status is FrameStatus.SOLVED:
            so[i] = res.activations
    return TrialMechanics(pack, trial.q, trial.torques, q_clamped, usable, arms, None, [so])


@pytest.fixture(scope="module")
def calibrated():
    pack = CountingPack(load_pack("bench_press"))
    solves: Counter[int] = Counter()
    solve = mechanics.min_effort_of

    def counted(pack_, arms, torques):
        solves[id(torques)] += 1
        return solve(pack_, arms, torques)

    mechanics.min_effort_of = counted
    try:
        trials = _trials(pack)
        profile, _ = calibrate_subject(pack, trials)  # delay "auto", minimal-effort prior: every consumer runs
        poses_calibration = pack.poses
        from msk_core.discrepancy.data import session_arrays

        lift = [t for t in trials if not t.isometric]
        data = session_arrays(pack, profile, lift)
    finally:
        mechanics.min_effort_of = solve
    return pack, trials, profile, data, poses_calibration, solves


def test_each_trials_moment_arms_and_static_optimisation_are_computed_once(calibrated):
    pack, trials, profile, data, poses_calibration, solves = calibrated
    assert profile.calibration["emd"]["source"] == "estimated"
    assert "min_effort" in profile.prior.sources and profile.calibration["min_effort_error_rms"] > 0
    # one evaluation per frame of every trial (every demo pose is inside the pack's ranges), and none more for the
    # discrepancy data of the same trials
    assert poses_calibration == sum(t.n_frames for t in trials)
    assert pack.poses == poses_calibration
    lift = [t for t in trials if not t.isometric]
    # static optimisation once per trial with reps (the prior and the minimal-effort error), none for held poses
    assert sorted(solves.values()) == [1] * len(lift) and set(solves) == {id(t.torques) for t in lift}
    kept = np.searchsorted(lift[0].time, data.trials[0].time)  # the frames the discrepancy analysis keeps
    np.testing.assert_array_equal(data.trials[0].arms, lift[0].mechanics(pack).moment_arms[kept])


def test_strengths_equal_those_from_frame_by_frame_moment_arms_and_static_optimisation(calibrated):
    pack, trials, profile, _, _, _ = calibrated
    plain = load_pack("bench_press")
    reference = _trials(plain)
    for t in reference:
        t.mechanics_cache = _frame_by_frame(plain, t)
        assert t.mechanics(plain) is t.mechanics_cache  # served as given: nothing recomputes it
    for ours, theirs in zip(trials, reference):
        np.testing.assert_array_equal(ours.mechanics(pack).moment_arms, theirs.mechanics_cache.moment_arms)
    before, _ = calibrate_subject(plain, reference)
    np.testing.assert_allclose(profile.f_max, before.f_max, rtol=1e-9, atol=0)
    assert profile.calibration["emd"]["delay_s"] == before.calibration["emd"]["delay_s"]
    assert profile.calibration["min_effort_error_rms"] == pytest.approx(
        before.calibration["min_effort_error_rms"], rel=1e-12
    )
