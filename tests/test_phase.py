"""Repetitions and phase: offline on real backmodel lifts and synthetic lifts; causal tracker against offline."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import ConfigError, InputError
from msk_core.io import align_to_kinematics, read_sto
from msk_core.signal.reps import (
    REST_PHASE,
    Excursion,
    PhaseMode,
    PhaseRepCounter,
    PhaseTracker,
    RepDetectionConfig,
    RepTemplate,
    detect_reps,
    in_rep,
    learn_template,
    phase_rep_spans,
    rep_phase,
)


def synthetic_lift(seed: int, n_reps: int = 6, fs: float = 100.0, pause_s: tuple[float, float] = (0.8, 2.0)):
    """Hip flexion (deg) of a deadlift set: rest, then reps with random tempo and pauses, noise and drift.
    Returns time, angle and the true (start, turn, end) times."""
    rng = np.random.default_rng(seed)
    pieces, truth, t0 = [np.full(int(1.5 * fs), 0.0)], [], 1.5
    for _ in range(n_reps):
        down, up = rng.uniform(0.8, 1.5), rng.uniform(0.8, 1.6)
        depth = rng.uniform(80.0, 100.0)
        u1 = np.arange(int(down * fs)) / (down * fs)
        u2 = np.arange(int(up * fs)) / (up * fs)
        rep = np.concatenate([depth * (1 - np.cos(np.pi * u1)) / 2, depth * (1 + np.cos(np.pi * u2)) / 2])
        pause = rng.uniform(*pause_s)
        pieces += [rep, np.zeros(int(pause * fs))]
        truth.append((t0, t0 + len(u1) / fs, t0 + len(rep) / fs))
        t0 += len(rep) / fs + int(pause * fs) / fs
    angle = np.concatenate(pieces)
    t = np.arange(angle.shape[0]) / fs
    angle = angle + 10.0 + 0.5 * rng.standard_normal(t.shape) + 2.0 * np.sin(2 * np.pi * t / 30.0)
    return t, angle, truth


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_offline_reps_on_synthetic_lifts(seed: int) -> None:
    t, angle, truth = synthetic_lift(seed)
    reps = detect_reps(t, angle, RepDetectionConfig(excursion=Excursion.INCREASE))
    assert len(reps) == len(truth)
    for rep, (ts, tt, te) in zip(reps, truth):
        assert abs(rep.t_start - ts) < 0.2 and abs(rep.t_turn - tt) < 0.1 and abs(rep.t_end - te) < 0.2
    for mode in PhaseMode:
        phase, index = rep_phase(t, reps, mode)
        inside = index >= 0
        assert np.all((phase[inside] >= 0) & (phase[inside] < 1)) and np.all(phase[~inside] == REST_PHASE)
        for k in range(len(reps)):
            assert np.all(np.diff(phase[index == k]) > 0)  # monotonic inside each rep
        if mode is PhaseMode.TURNING_POINT:
            assert all(phase[r.turn] == pytest.approx(0.5) for r in reps)


@pytest.mark.parametrize("seed", [3, 4])
def test_causal_tracker_follows_offline_phase_on_new_synthetic_set(seed: int) -> None:
    cfg = RepDetectionConfig(excursion=Excursion.INCREASE)
    t_cal, a_cal, _ = synthetic_lift(seed)
    template = RepTemplate.from_dict(json.loads(json.dumps(learn_template(t_cal, a_cal, cfg).to_dict())))
    assert template.n_reps == 6 and template.turn_phase == pytest.approx(0.5, abs=0.02)
    t, angle, truth = synthetic_lift(seed + 100)  # a different set: other tempo, depth, pauses
    offline, _ = rep_phase(t, detect_reps(t, angle, cfg))
    tracker = PhaseTracker(template)
    live = np.array([tracker.update(a, b) for a, b in zip(t, angle)])
    assert tracker.rep_count == len(truth)
    assert np.all(live[~in_rep(live)] == REST_PHASE)  # between reps, never unknown
    both = in_rep(offline) & in_rep(live)
    assert both.sum() > 0.85 * in_rep(offline).sum()
    err = np.abs(offline - live)[both]
    assert np.median(err) < 0.03 and np.percentile(err, 95) < 0.15


def test_touch_and_go_reps() -> None:
    """No rest between reps: the offline split is at the top, the tracker starts the next rep as progress rises."""
    cfg = RepDetectionConfig(excursion=Excursion.INCREASE)
    t_cal, a_cal, _ = synthetic_lift(3)
    t, angle, truth = synthetic_lift(11, pause_s=(0.0, 0.05))
    reps = detect_reps(t, angle, cfg)
    assert len(reps) == len(truth) == 6
    tracker = PhaseTracker(learn_template(t_cal, a_cal, cfg))
    live = tracker.process(t, angle)
    assert tracker.rep_count == 6
    offline, _ = rep_phase(t, reps)
    both = in_rep(offline) & in_rep(live)
    assert np.median(np.abs(offline - live)[both]) < 0.03


@pytest.mark.parametrize("trial", ["squat5kg", "stoop5kg"])
def test_reps_and_phase_on_backmodel_lifts(shared_dir: Path, trial: str) -> None:
    folder = shared_dir / "data/backmodel-lift" / trial
    aligned = align_to_kinematics(*(read_sto(folder / f) for f in ("emgFilt.sto", "ik.sto", "id.sto")))
    height = aligned.coordinate("pelvis_ty")  # the pelvis drops in every lift, squat or stoop
    cfg = RepDetectionConfig(excursion=Excursion.DECREASE)
    reps = detect_reps(aligned.time, height, cfg)
    assert len(reps) == 4  # two box pick-ups and two put-downs per trial
    assert all(3.0 < r.duration < 4.5 for r in reps)
    # the lumbar moment peaks inside the reps, not between them
    l5 = aligned.id.column("L5_S1_Flex_Ext")
    phase, index = rep_phase(aligned.time, reps)
    assert l5[index >= 0].mean() > 2.0 * l5[index < 0].mean()
    tracker = PhaseTracker(learn_template(aligned.time, height, cfg))
    live = tracker.process(aligned.time, height)
    both = in_rep(phase) & in_rep(live)
    assert both.sum() > 0.8 * in_rep(phase).sum()
    assert np.median(np.abs(phase - live)[both]) < 0.05


def test_reps_of_a_phase_stream_split_on_wrap_rest_and_gaps() -> None:
    t = [0.1 * i for i in range(40)]
    phase = (
        [-1.0] * 5
        + [i / 10 for i in range(10)]
        + [i / 10 for i in range(10)]
        + [-1.0] * 5
        + [i / 10 for i in range(10)]
    )
    assert [(round(a, 1), round(b, 1)) for a, b in phase_rep_spans(t, phase)] == [(0.5, 1.4), (1.5, 2.4), (3.0, 3.9)]
    assert phase_rep_spans(t, [math.nan] * 40) == []
    gap = [0.0, 0.1, 0.2, 0.3, 1.0, 1.1, 1.2, 1.3]  # the stream paused 0.7 s inside what looked like one rep
    gap_phase = [0.0, 0.1, 0.2, 0.3, 0.7, 0.8, 0.9, 0.95]  # the second part is through its cycle when the data end
    assert phase_rep_spans(gap, gap_phase) == [(0.0, 0.3), (1.0, 1.3)]
    # a rep the end of the data cuts before its phase got through (0.7 < MIN_FINISHED_PHASE) was not done
    assert phase_rep_spans(gap, [0.1 * i for i in range(8)]) == [(0.0, 0.3)]
    short = [0.0, 0.1, 0.2]  # shorter than MIN_REP_S: a flicker, no rep
    assert phase_rep_spans(short + [0.3], [0.2, 0.4, 0.6, REST_PHASE]) == []
    counter = PhaseRepCounter()  # live: a rep is counted at the sample that ends it
    done = [counter.update(0.2 * k, p) for k, p in enumerate([REST_PHASE, 0.1, 0.5, 0.9, REST_PHASE])]
    assert done[:4] == [None] * 4 and done[4] == pytest.approx((0.2, 0.6)) and counter.count == 1


def test_errors() -> None:
    with pytest.raises(ConfigError, match="start_fraction"):
        RepDetectionConfig(start_fraction=0.6, min_depth_fraction=0.5)
    t = np.arange(10.0)
    with pytest.raises(InputError, match="does not move"):
        detect_reps(t, np.ones(10), RepDetectionConfig())
    with pytest.raises(InputError, match="strictly increasing"):
        detect_reps(np.zeros(10), t, RepDetectionConfig())
    with pytest.raises(InputError, match="no complete repetition"):
        learn_template(t, t, RepDetectionConfig())  # a ramp never comes back
    with pytest.raises(ConfigError, match="depth"):
        RepTemplate.from_dict({"excursion": "increase", "mode": "time", "rest": 0.0})
