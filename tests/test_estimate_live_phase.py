"""Kinematic rep phase shared by calibration and the live node: per-pack phase coordinate, rep template in the
subject profile, and the causal LivePhase agreeing with the offline phase on the demo recordings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import ConfigError, EstimationError
from msk_core.estimate import SubjectProfile
from msk_core.estimate.phase import LivePhase, PhaseModel, kinematic_phase, learn_phase_model
from msk_core.estimate.pipeline import learn_trials_phase_model
from msk_core.estimate.trial import load_trial
from msk_core.signal.reps import REST_PHASE, PhaseMode, RepDetectionConfig, detect_reps, rep_phase

model = pytest.importorskip("msk_core.model")
DEMO = Path(__file__).resolve().parents[1] / "recordings" / "demo"


def _reps(rate=100.0, depths=(1.0, 1.2, 0.9, 1.1), sign=1.0):
    rest, rep = int(0.7 * rate), int(2.0 * rate)
    x = [0.0] * rest
    for d in depths:
        x += list(d * np.sin(np.pi * np.arange(rep) / rep) ** 2) + [0.0] * rest
    x = 0.3 + sign * np.array(x)
    return np.arange(x.size) / rate, x


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_offline_phase_is_msk_core_phase_and_live_phase_tracks_it(sign):
    t, x = _reps(sign=sign)
    phase, index = kinematic_phase(t, x)
    cfg = RepDetectionConfig()
    expected, _ = rep_phase(t, detect_reps(t, sign * x if sign < 0 else x, cfg), PhaseMode.TURNING_POINT)
    np.testing.assert_array_equal(np.isnan(phase), np.isnan(expected))
    np.testing.assert_allclose(phase[index >= 0], expected[index >= 0])
    assert index.max() == 3
    pm = learn_phase_model("c1", [(t[: t.size // 2], x[: t.size // 2]), (t[t.size // 2 :], x[t.size // 2 :])])
    assert pm.template.n_reps >= 3  # learnt over the two halves laid end to end
    live = LivePhase(pm, ["c0", "c1"]).process(t, np.column_stack([np.zeros_like(x), x]))
    assert set(np.unique(live[live < 0])) == {REST_PHASE}
    both = (index >= 0) & (live >= 0)
    assert np.mean((index >= 0) == (live >= 0)) > 0.85
    assert np.median(np.abs(live[both] - phase[both])) < 0.03
    with pytest.raises(EstimationError, match="not among"):
        LivePhase(pm, ["c0"])


def test_phase_model_round_trips_through_the_subject_profile(tmp_path):
    t, x = _reps()
    pm = learn_phase_model("elbow", [(t, x)])
    prof = SubjectProfile("toy", "1", ["g"], np.array([1.0]), np.array([1.0]), phase_model=pm)
    prof.save(tmp_path / "s.json")
    back = SubjectProfile.load(tmp_path / "s.json")
    assert back.phase_model.coordinate == "elbow"
    np.testing.assert_allclose(back.phase_model.template.progress, pm.template.progress)
    assert PhaseModel.from_dict(pm.to_dict()).template.n_reps == pm.template.n_reps
    assert LivePhase.from_profile(SubjectProfile("toy", "1", ["g"], np.ones(1), np.ones(1)), ["elbow"]) is None


@pytest.mark.parametrize("exercise,coordinate", [("bench_press", "elbow_flex_r"), ("deadlift", "hip_flexion_r")])
def test_demo_trials_phase_on_the_packs_coordinate_and_live_agrees_with_offline(exercise, coordinate):
    pack = model.load_pack(exercise)
    folders = sorted(p for p in (DEMO / exercise).iterdir() if (p / "trial.toml").is_file())
    folders.sort(key=lambda p: float(p.name.rsplit("_", 1)[1].removesuffix("kg")))
    trials = [load_trial(f / "trial.toml", pack) for f in folders]
    assert all(t.phase_signal == coordinate and t.phase_coordinate == coordinate for t in trials)
    pm = learn_trials_phase_model(pack, trials[:1])  # calibration: the light trial
    for trial in trials:  # calibration trial and held-out trial
        live = LivePhase(pm, pack.coordinates).process(trial.time, trial.q)
        off_in, live_in = trial.rep_index >= 0, live >= 0
        assert live_in.any() and np.mean(off_in == live_in) > 0.88  # live enters a rep once it is under way
        d = np.abs(live[off_in & live_in] - trial.phase[off_in & live_in])
        assert d.mean() < 0.07, (trial.name, d.mean())


def test_trial_phase_signal_errors_and_conflicting_coordinates(tmp_path):
    pack = model.load_pack("bench_press")
    src = DEMO / "bench_press"
    folder = next(p for p in src.iterdir() if (p / "trial.toml").is_file())
    text = (folder / "trial.toml").read_text().replace('kinematics = "', f'kinematics = "{folder}/')
    text = text.replace('torques = "', f'torques = "{folder}/').replace('emg = "', f'emg = "{folder}/')
    (tmp_path / "a.toml").write_text('phase_signal = "elv_angle_r"\n' + text)
    (tmp_path / "b.toml").write_text('phase_signal = "elbow_flex_x"\n' + text)
    a = load_trial(tmp_path / "a.toml", pack)
    b = load_trial(folder / "trial.toml", pack)
    with pytest.raises(EstimationError, match="different coordinates"):
        learn_trials_phase_model(pack, [a, b])
    with pytest.raises(ConfigError, match="phase_signal.*elbow_flex_x"):
        load_trial(tmp_path / "b.toml", pack)
