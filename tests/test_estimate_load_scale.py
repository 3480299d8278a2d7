"""The prior at another load than its training's (``msk_core.estimate.prior.LoadScale``): kept in the profile, used
only at another load, equal between the hot start and PIQP, and closer to the truth of a heavier synthetic lift."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import EstimationError, FileFormatError
from msk_core.estimate import FrameEstimator, PhasePrior, SubjectProfile
from msk_core.estimate.pipeline import build_prior, calibrate_subject, training_torque
from msk_core.estimate.prior import LOAD_SCALE_RANGE, LOAD_SCALE_REPS, MIN_STD, SAME_LOAD_N, LoadScale
from msk_core.estimate.trial import load_trial
from msk_core.io import read_sto
from msk_core.model import load_pack
from tests.profile_helpers import phased_profile

DEMO = Path(__file__).resolve().parents[1] / "recordings" / "demo" / "bench_press"


def _prior(n_bins: int = 4, torque: float = 100.0, load: float | None = 400.0) -> PhasePrior:
    return PhasePrior(
        ("a", "b"),
        np.full((n_bins, 2), 0.2),
        np.full((n_bins, 2), 0.05),
        np.ones(2, dtype=bool),
        torque=None if load is None else np.full((n_bins, 1), torque),
        load_newton=load,
    )


def test_the_training_torque_and_load_go_through_the_profile_and_are_checked(tmp_path):
    prior = _prior()
    back = PhasePrior.from_dict(json.loads(json.dumps(prior.to_dict())))
    np.testing.assert_array_equal(back.torque, prior.torque)
    assert back.load_newton == 400.0
    old = prior.to_dict()
    del old["torque"], old["load_newton"]  # a profile written before: the prior as learned at every load
    assert PhasePrior.from_dict(old).torque is None and PhasePrior.from_dict(old).load_newton is None
    with pytest.raises(EstimationError, match="both or neither"):
        replace(prior, load_newton=None)
    with pytest.raises(EstimationError, match=r"n_bins=4"):
        replace(prior, torque=np.ones((3, 1)))
    with pytest.raises(EstimationError, match="load_newton must be finite"):
        replace(prior, load_newton=float("nan"))
    pack = load_pack("bench_press")
    profile = phased_profile(pack)
    data = profile.to_dict()
    data["prior"]["torque"] = [[1.0]] * profile.prior.n_bins  # bench_press has 2 coordinates
    data["prior"]["load_newton"] = 400.0
    path = tmp_path / "subject.json"
    path.write_text(json.dumps(data))
    loaded = SubjectProfile.load(path)  # a profile file is read as written; the estimator checks it against the pack
    with pytest.raises(EstimationError, match="training torque has 1 coordinates, the pack 2"):
        FrameEstimator(pack, loaded, "proposed")
    data["prior"]["load_newton"] = None
    path.write_text(json.dumps(data))
    with pytest.raises(FileFormatError, match="both or neither"):
        SubjectProfile.load(path)


def test_load_scale_is_the_torque_ratio_at_another_load_only_inside_reps_averaged_over_reps():
    arms = np.array([[0.05, -0.02]])
    scale = LoadScale(_prior(torque=100.0, load=400.0))
    assert scale.update(arms, np.array([150.0]), 0.3) is None  # no load known
    scale.set_load(400.0 + SAME_LOAD_N / 2)
    assert scale.update(arms, np.array([150.0]), 0.3) is None  # the prior's own load
    scale.set_load(600.0)
    assert scale.update(arms, np.array([150.0]), -1.0) is None  # between reps: the rest prior stands
    assert scale.update(arms, np.array([150.0]), None) is None
    assert scale.update(arms, np.array([150.0]), 0.3) is None  # no progress yet: nothing to average
    np.testing.assert_allclose(scale.update(arms, np.array([150.0]), 0.35), [1.5, 1.5])  # one coordinate: one ratio
    # a lift that needs twice the training's torque: the average forgets the 1.5 over LOAD_SCALE_REPS reps of frames
    k = 0.05 / LOAD_SCALE_REPS  # 20 frames per rep
    s = None
    for i in range(1, 11):
        s = scale.update(arms, np.array([200.0]), 0.35 + 0.05 * i)
    old = (1.0 - k) ** 10
    expected = (k * 150.0 * old + 200.0 * (1.0 - old)) / (k * 100.0 * old + 100.0 * (1.0 - old))
    assert s is not None
    np.testing.assert_allclose(s, [expected, expected])
    # each frame weighs the same, however far the phase moved in it (a tracker holding, then jumping)
    held = LoadScale(_prior(torque=100.0, load=400.0), load_newton=600.0)
    for i in range(21):
        held.update(arms, np.array([100.0]), 0.05 * i)
    jumped = held.update(arms, np.array([300.0]), 1.0)  # one frame that jumped 0.45 of a rep, at 3x the torque
    # weighted by its phase progress it would count 9 normal frames (ratio 1.77); as one frame, about 1.2
    assert jumped is not None and 1.1 < jumped[0] < 1.3, jumped
    # the next rep starts (phase wraps): it goes on; a new load restarts the average
    wrapped = scale.update(arms, np.array([200.0]), 0.02)
    assert wrapped is not None and wrapped[0] > s[0]
    scale.set_load(700.0)
    assert scale.update(arms, np.array([1000.0]), 0.5) is None
    np.testing.assert_allclose(scale.update(arms, np.array([1000.0]), 0.55), [LOAD_SCALE_RANGE[1]] * 2)  # bounded


def test_the_estimator_scales_the_prior_at_another_load_and_the_hot_start_equals_piqp():
    pack = load_pack("bench_press")
    profile = phased_profile(pack)
    n_bins, n_c = profile.prior.n_bins, len(pack.coordinates)
    rng = np.random.default_rng(3)
    lo, hi = pack.coordinate_ranges[:, 0], pack.coordinate_ranges[:, 1]
    frames = [(lo + (hi - lo) * rng.uniform(0.3, 0.7, n_c), (k % 20) / 20) for k in range(60)]
    torque = np.abs(np.stack([pack.inverse_dynamics(q, np.zeros(n_c), np.zeros(n_c), 400.0) for q, _ in frames]))
    profile.prior = replace(profile.prior, torque=np.full((n_bins, n_c), float(torque.mean())), load_newton=400.0)
    plain = replace(profile.prior, torque=None, load_newton=None)

    def run(method: str, load: float, prior: PhasePrior | None = None, hot: bool = True) -> np.ndarray:
        est = FrameEstimator(pack, profile, method, prior=prior, hot_start=hot)
        zero = np.zeros(n_c)
        return np.array([est.step(q, zero, zero, load, phase=p).activations for q, p in frames])

    # at the prior's load the profile's torque changes nothing
    np.testing.assert_array_equal(run("proposed", 400.0), run("proposed", 400.0, plain))
    # at twice the load: the prior alone is the prior scaled by its group's torque ratio above the rest level
    replica, expected = LoadScale(profile.prior, load_newton=800.0), []
    for q, p in frames:
        tau = np.asarray(pack.inverse_dynamics(q, np.zeros(n_c), np.zeros(n_c), 800.0))
        s = replica.update(np.asarray(pack.moment_arms(q)), tau, p)
        mu = profile.prior.mean_precision(p)[0]
        base = np.minimum(mu, profile.prior.rest_mean)
        expected.append(np.clip(mu if s is None else base + s * (mu - base), 0.0, 1.0))
    scaled, unscaled = run("prior", 800.0), run("prior", 800.0, plain)
    np.testing.assert_allclose(scaled, expected, atol=1e-12)
    assert np.abs(scaled - unscaled).max() > 0.05
    # another recording (offline: the next trial) starts its own average: its first frame has no progress yet
    est, zero = FrameEstimator(pack, profile, "prior"), np.zeros(n_c)
    for q, p in frames:
        est.step(q, zero, zero, 800.0, phase=p)
    q, p = frames[5]
    assert not np.allclose(est.step(q, zero, zero, 800.0, phase=p).activations, unscaled[5])
    est.new_recording()
    np.testing.assert_array_equal(est.step(q, zero, zero, 800.0, phase=p).activations, unscaled[5])
    assert est.load_scale is not None and est.load_scale["frames"] > 0  # the summary counts the whole run
    # a quarter of the load: the spread shrinks with the scale, but not below the prior's floor
    light, zero = FrameEstimator(pack, profile, "prior"), np.zeros(n_c)
    stds = np.array([light.step(q, zero, zero, 100.0, phase=p).activation_std for q, p in frames])
    assert stds.min() >= MIN_STD - 1e-12 and stds.min() < 0.05, stds.min()  # the profile's sigma is 0.05
    hot, cold = run("proposed", 800.0), run("proposed", 800.0, hot=False)
    np.testing.assert_allclose(hot, cold, atol=2e-4)
    assert hot.mean() > run("proposed", 800.0, plain).mean()


def test_a_heavier_synthetic_lift_is_estimated_closer_to_the_truth_with_the_load_scaled_prior():
    """Calibrated on the 40 kg bench press alone, estimated on the 50 kg one (the generator's truth): the prior at
    the new load lowers the error of `proposed` and of the prior alone."""
    pack = load_pack("bench_press")
    light = load_trial(DEMO / "bench_press_40kg" / "trial.toml", pack)
    heavy = load_trial(DEMO / "bench_press_50kg" / "trial.toml", pack)
    profile, _ = calibrate_subject(pack, [light])
    torque, load = training_torque([light], profile.prior.n_bins)
    assert load == pytest.approx(light.hand_load_newton) and profile.prior.load_newton == pytest.approx(load)
    np.testing.assert_allclose(profile.prior.torque, torque)
    assert build_prior(pack, [light]).load_newton == pytest.approx(load)
    truth = read_sto(DEMO / "bench_press_50kg" / "truth_activations.sto")
    a_true = np.column_stack([np.interp(heavy.time, truth.time, truth.column(g)) for g in pack.groups])
    plain = replace(profile.prior, torque=None, load_newton=None)

    def rmse(method: str, prior: PhasePrior | None = None) -> float:
        est = FrameEstimator(pack, profile, method, prior=prior)
        a = np.array(
            [
                est.step(
                    heavy.q[i],
                    heavy.qd[i],
                    heavy.qdd[i],
                    heavy.hand_load_newton,
                    torques=heavy.torques[i],
                    phase=float(heavy.phase[i]),
                ).activations
                for i in range(heavy.n_frames)
            ]
        )
        return float(np.sqrt(np.mean((a - a_true) ** 2)))

    proposed, proposed_plain = rmse("proposed"), rmse("proposed", plain)
    prior, prior_plain = rmse("prior"), rmse("prior", plain)
    assert proposed < 0.95 * proposed_plain, (proposed, proposed_plain)
    assert prior < 0.9 * prior_plain, (prior, prior_plain)
