"""``msk live --sim`` plays sets with rests (services.sessions.sim_sets): one cycle spliced per stream on the common sample
grid, a set's reps exactly the looped trial, the rest the trial's static start, and the trial instant of every
moment of the cycle (services.sessions.live_scoring.SimWorld)."""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.errors import ConfigError
from services.sessions.live import RECORDINGS, sim_sources
from services.sessions.live_scoring import SimWorld
from services.sessions.sim_sets import SimSets, grid_s, schedule, with_sets


@pytest.fixture(scope="module")
def trial():
    return sim_sources(RECORDINGS / "demo_session.mcap", "bench_press")


def test_the_trials_reps_and_static_start(trial):
    assert len(trial.rep_ends_s) == 3 and 0.9 < trial.lead_s < 1.1  # three reps after about 1 s at rest
    assert all(b - a > 3.0 for a, b in zip((trial.lead_s,) + trial.rep_ends_s, trial.rep_ends_s))


@pytest.mark.parametrize(("reps", "rest_s"), [(9, 30.0), (5, 30.0), (2, 7.3), (1, 8.0)])
def test_every_stream_plays_one_cycle_of_set_and_rest(trial, reps, rest_s):
    sets = SimSets(reps, rest_s)
    played = with_sets(trial, sets)
    cycle_s = played.emg.n_samples / played.emg.rate_hz
    durations = [source.n_samples / source.rate_hz for _, source in played.imu.values()]
    durations.append(played.emg.acc.shape[0] / played.emg.acc_rate_hz)
    assert max(abs(d - cycle_s) for d in durations) < 1e-9  # the simulators loop together
    assert sum(d for _, d in played.schedule) == pytest.approx(cycle_s)
    rest = [segment for segment in played.schedule if segment[0] == 0.0 and segment[1] <= trial.lead_s]
    assert sum(d for _, d in rest) == pytest.approx(rest_s, abs=0.05)  # the rest: the static start, repeated
    n = trial.emg.n_samples
    rounds = reps // 3
    assert np.array_equal(played.emg.samples[: rounds * n], np.tile(trial.emg.samples, (rounds, 1)))
    if reps % 3:  # the last round, cut after its rep: the trial up to there
        cut = int(round(played.schedule[rounds][1] * trial.emg.rate_hz))
        assert np.array_equal(played.emg.samples[rounds * n : rounds * n + cut], trial.emg.samples[:cut])
    # the trial instant of each moment: a moment of the rest is one of the static start
    world = SimWorld(
        "bench_press", "t", 0, n / trial.emg.rate_hz, 1.0, played.schedule, sum(d for _, d in played.schedule)
    )
    moments = np.arange(0.0, 2 * world.cycle_s, 0.01)
    instants = world.trial_s((moments * 1e9).astype(np.int64))
    starts = np.cumsum([0.0] + [d for _, d in played.schedule])
    in_rest = (np.mod(moments, world.cycle_s) >= starts[-1] - rest_s + 1e-6) & (
        np.mod(moments, world.cycle_s) < starts[-1] - 1e-6
    )
    assert np.all(instants[in_rest] < trial.lead_s + 1e-6) and np.all((instants >= 0) & (instants < world.loop_s))
    first_set = moments < rounds * world.loop_s
    assert np.allclose(instants[first_set], np.mod(moments[first_set], world.loop_s))  # the set: the looped trial


def test_no_sets_leaves_the_trial_looping_and_bad_options_are_refused(trial):
    assert with_sets(trial, SimSets(0, 30.0)) is trial
    with pytest.raises(ConfigError, match="--sim-reps"):
        SimSets(-1, 30.0)
    with pytest.raises(ConfigError, match="--sim-rest"):
        SimSets(5, float("nan"))
    assert grid_s([2000.0, 100.0, 60.0]) == pytest.approx(0.05)
    assert schedule(SimSets(3, 0.0), 15.05, trial.rep_ends_s, trial.lead_s, 0.05) == [(0.0, 15.05)]
