"""Heel strikes from the vertical ground reaction force and the gait-cycle phase; on synthetic forces and on the real
walk (whose trial files split it at the right heel strike nearest its middle)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import InputError
from msk_core.estimate.trial import load_trial
from msk_core.io import read_sto, write_sto
from msk_core.model import load_pack
from msk_core.signal.gait import gait_cycle_phase, heel_strikes
from msk_core.signal.reps import REST_PHASE

WALK_TRIALS = Path(__file__).resolve().parents[1] / "recordings" / "lowerlimb-walk"


def _stance_forces(strikes: list[float], stance_s: float = 0.62, rate: float = 100.0, seconds: float = 6.0):
    t = np.arange(int(seconds * rate)) / rate
    f = np.zeros_like(t)
    for s in strikes:
        inside = (t >= s) & (t < s + stance_s)
        f[inside] = 700.0 * np.sin(np.pi * (t[inside] - s) / stance_s) + 5.0
    return t, f


def test_heel_strikes_are_the_threshold_crossings_after_a_swing():
    truth = [0.503, 1.552, 2.611, 3.655, 4.702]
    t, f = _stance_forces(truth)
    f[(t > 1.9) & (t < 1.93)] = 25.0  # a flicker above the threshold inside the swing: 0.03 s, then off again
    found = heel_strikes(t, f)
    assert found.size == len(truth)
    # the crossing of 20 N is interpolated between samples: within a sample of the true contact
    assert np.abs(found - np.array(truth)).max() < 0.01


def test_gait_cycle_phase_runs_from_heel_strike_to_heel_strike():
    t = np.arange(0, 4.0, 0.01)
    phase, index = gait_cycle_phase(t, np.array([0.5, 1.5, 2.5]))
    assert np.all(phase[t < 0.5] == REST_PHASE) and np.all(index[t >= 2.5] == -1)
    assert phase[100] == pytest.approx(0.5) and index[100] == 0  # t = 1.0
    assert phase[150] == pytest.approx(0.0) and index[150] == 1  # a heel strike starts the next cycle
    with pytest.raises(InputError, match="at least 2 increasing heel-strike times"):
        gait_cycle_phase(t, np.array([1.0]))
    with pytest.raises(InputError, match="not finite at t = 0.02"):
        heel_strikes(t[:5], np.array([0.0, 0.0, np.nan, 0.0, 0.0]))


def test_the_walk_trials_split_at_a_heel_strike_and_its_reps_are_gait_cycles(shared_dir):
    from msk_core.estimate.trial import load_trial  # noqa: PLC0415
    from msk_core.model import load_pack  # noqa: PLC0415

    walk = shared_dir / "data" / "lowerlimb-walk"
    grf = read_sto(walk / "walk45_XLD.mot")
    strikes = heel_strikes(grf.time, grf.column("ground_force_vy"))  # right foot (left: l_ground_force_vy)
    assert 50 <= strikes.size <= 60
    train = tomllib.loads((WALK_TRIALS / "walk_train.toml").read_text())
    held = tomllib.loads((WALK_TRIALS / "walk_holdout.toml").read_text())
    split = train["end"]
    assert held["start"] == split
    middle = strikes[np.argmin(np.abs(strikes - grf.time[-1] / 2))]
    assert split == pytest.approx(middle, abs=0.001)
    before, after = np.sum(strikes < split + 0.001) - 1, np.sum(strikes > split - 0.001) - 1  # complete cycles
    assert abs(before - after) <= 2, (before, after)
    if (WALK_TRIALS / train["kinematics"]).resolve() != (walk / "walk45_ik.sto").resolve():
        pytest.skip(f"the trial files point at ../shared beside the repository, the data are at {shared_dir}")
    pack = load_pack("gait2392")
    for name in ("walk_train", "walk_holdout"):
        trial = load_trial(WALK_TRIALS / f"{name}.toml", pack)
        n_reps = int(trial.rep_index.max()) + 1
        starts = np.array([trial.time[np.flatnonzero(trial.rep_index == k)[0]] for k in range(n_reps)])
        # heel strikes that close a cycle inside the window (the split strike closes the first half's last one)
        inside = strikes[(strikes >= trial.time[0] - 0.02) & (strikes <= trial.time[-1] + 0.02)]
        timed = starts[starts > strikes[0] - 0.2]  # the walk's first cycle starts before the first detected strike
        lag = np.array([s - strikes[np.argmin(np.abs(strikes - s))] for s in timed])
        print(
            f"{name}: {n_reps} reps, {inside.size} heel strikes; rep start - heel strike median "
            f"{np.median(lag):+.3f} s, 90th percentile |lag| {np.percentile(np.abs(lag), 90):.3f} s, "
            f"max {np.abs(lag).max():.3f} s; {np.mean(trial.rep_index >= 0):.0%} of frames in a rep"
        )
        assert inside.size - 1 <= n_reps <= inside.size + 1  # one rep per gait cycle
        # a hip-flexion rep starts when the hip leaves its flexed heel-strike level: a tenth of a cycle after the
        # strike, never before it (docs/estimation.md, "The walk")
        assert 0.0 < np.median(lag) < 0.15 and np.percentile(np.abs(lag), 90) < 0.2


def test_a_grf_file_on_another_clock_than_the_trial_names_both_spans(shared_dir, tmp_path):
    walk = shared_dir / "data" / "lowerlimb-walk"
    grf = read_sto(walk / "walk45_XLD.mot")
    shifted = tmp_path / "grf_epoch.mot"
    write_sto(shifted, grf.time + 1.7e9, list(grf.columns), grf.data, name="grf on epoch seconds")
    text = (WALK_TRIALS / "walk_train.toml").read_text().replace("../../../shared", str(shared_dir))
    text = text.replace('phase_signal = "hip_flexion_r"', f'grf = "{shifted}"')
    (tmp_path / "walk.toml").write_text(text)
    trial = load_trial(tmp_path / "walk.toml", load_pack("gait2392"))
    said = trial.extra["no_reps"]
    assert (
        said.startswith("0 heel strike(s) of ground_force_vy")
        and "(0 .. 29.26 s; grf_epoch.mot spans 1700000000 .. 1700000059.03 s)" in said
    ), said
