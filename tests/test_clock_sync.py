"""The clock offset from accelerations (msk_core.signal.clock_sync) on synthetic arrays with a known offset.

A segment moves (smooth random acceleration after a rest); an EMG sensor (g, 148.1 Hz, EMG clock) and a tracker
(m/s², 100 Hz, its own clock) strapped on it in different orientations measure its specific force with noise. The
estimator must find the clock offset to well within a grid step, say "no movement" while everything rests, say
"not together" when the only EMG sensor that moves moves otherwise, follow a drifting clock, and refuse bad input.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal
from scipy.spatial.transform import Rotation

from msk_core.errors import ConfigError, InputError
from msk_core.signal.clock_sync import (
    STANDARD_GRAVITY,
    AccUnit,
    ClockOffset,
    ClockSync,
    ClockSyncConfig,
    SyncStatus,
)

AUX_HZ = 2 / 0.0135  # Trigno Avanti ACC
TRACKER_HZ = 100.0
UP = np.array([0.0, 0.0, STANDARD_GRAVITY])


def motion(seconds: float, seed: int, *, rest_s: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(time at 1 kHz, world acceleration (n, 3) m/s²): rest, then smooth random movement of ~1 m/s² (< 3 Hz)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1e-3)
    sos = signal.butter(2, [0.3, 3.0], btype="band", fs=1000.0, output="sos")
    a = signal.sosfiltfilt(sos, rng.standard_normal((t.size, 3)), axis=0)
    a *= 1.0 / a[t >= rest_s].std()
    a[t < rest_s] = 0.0
    return t, a


def measured(
    t: np.ndarray, a: np.ndarray, rate: float, seed: int, *, start_s: float = 0.0, noise: float = 0.02
) -> tuple[np.ndarray, np.ndarray]:
    """What an accelerometer fixed on the segment in a random orientation reads at ``rate`` from ``start_s``: the
    specific force (a + up) in its axes, with white noise (m/s²). Returns (trial times, readings)."""
    rng = np.random.default_rng(seed)
    mount = Rotation.random(random_state=rng).as_matrix()
    ts = np.arange(start_s, t[-1], 1.0 / rate)
    world = np.column_stack([np.interp(ts, t, a[:, k]) for k in range(3)]) + UP
    return ts, world @ mount + rng.normal(0.0, noise, (ts.size, 3))


def feed(
    sync: ClockSync,
    emg: dict[str, tuple[np.ndarray, np.ndarray]],
    tracker: tuple[np.ndarray, np.ndarray],
    *,
    emg_clock_s: float,
    tracker_clock_s,
    block_s: float = 0.0135,
):
    """Feed in arrival order, one block per ``block_s`` of trial time, calling update after each; the device times
    are trial time minus the clock's start (``tracker_clock_s``: a function of trial time for a drifting clock).
    Returns the answers."""
    answers = []
    end = max(ts[-1] for ts, _ in emg.values())
    edges = np.arange(0.0, end + block_s, block_s)
    for lo, hi in zip(edges[:-1], edges[1:]):
        for name, (ts, acc) in emg.items():
            sel = (ts >= lo) & (ts < hi)
            if sel.any():
                sync.add_emg_sensor(
                    name,
                    np.round((ts[sel] - emg_clock_s) * 1e9).astype(np.int64),
                    acc[sel] / STANDARD_GRAVITY,
                    AccUnit.G,
                )
        ts, acc = tracker
        sel = (ts >= lo) & (ts < hi)
        if sel.any():
            sync.add_tracker(np.round(tracker_clock_s(ts[sel]) * 1e9).astype(np.int64), acc[sel])
        answers.append(sync.update())
    return answers


def final_on_trial_time(prior_ns: int, t: np.ndarray, emg: tuple[str, np.ndarray], tracker: np.ndarray) -> ClockOffset:
    """The last answer of ``ClockSync(prior_ns)`` fed one EMG sensor (name, its segment's acceleration) and the
    tracker (its segment's acceleration), measured from ``t`` with both device clocks at trial time."""
    name, segment = emg
    return feed(
        ClockSync(prior_ns),
        {name: measured(t, segment, AUX_HZ, 1)},
        measured(t, tracker, TRACKER_HZ, 2),
        emg_clock_s=0.0,
        tracker_clock_s=lambda ts: ts,
    )[-1]


def test_known_offset_found_to_a_millisecond_from_the_sensor_on_the_trackers_segment():
    t, arm = motion(40.0, seed=1)
    _, other = motion(40.0, seed=2)  # another segment moving its own way
    emg = {"arm": measured(t, arm, AUX_HZ, 10), "other": measured(t, other, AUX_HZ, 11)}
    tracker = measured(t, arm, TRACKER_HZ, 12, start_s=0.3)
    emg_clock_s, tracker_clock_s = 0.25, -1234.5678912  # tracker powered up long before, EMG started at 0.25 s
    truth_ns = round((emg_clock_s - tracker_clock_s) * 1e9)  # tracker device time - EMG device time, one instant
    sync = ClockSync(truth_ns + 180_000_000)  # an arrival-time prior 180 ms off
    answers = feed(sync, emg, tracker, emg_clock_s=emg_clock_s, tracker_clock_s=lambda ts: ts - tracker_clock_s)
    statuses = [a.status for a in answers]
    assert statuses[0] is SyncStatus.WAITING and statuses[-1] is SyncStatus.LOCKED
    final = answers[-1]
    errors_ms = [(w.offset_ns - truth_ns) / 1e6 for w in sync.windows if w.status is SyncStatus.LOCKED]
    print(
        f"offset error {(final.offset_ns - truth_ns) / 1e6:+.3f} ms over {final.windows} windows "
        f"(each {min(errors_ms):+.2f}..{max(errors_ms):+.2f} ms), spread {final.spread_ns / 1e6:.3f} ms, "
        f"r {final.peak_correlation:.3f}, width {final.peak_width_ms:.0f} ms"
    )
    assert abs(final.offset_ns - truth_ns) < 1_000_000
    assert max(abs(e) for e in errors_ms) < 2.0
    assert final.sensor == "arm" and all(w.sensor == "arm" for w in sync.windows if w.status is SyncStatus.LOCKED)
    assert final.windows >= 10 and final.spread_ns < 1_000_000 and final.peak_correlation > 0.95
    assert final.emg_host_offset_ns(5_000_000_000) == 5_000_000_000 + final.offset_ns


def test_rest_only_cannot_and_says_so():
    t = np.arange(0.0, 20.0, 1e-3)
    still = np.zeros((t.size, 3))
    final = final_on_trial_time(0, t, ("s1", still), still)
    assert final.status is SyncStatus.NO_MOVEMENT and not final.locked and final.offset_ns is None
    assert final.windows_seen >= 3 and "rest" in final.reason and "did not move" in final.reason, final.reason
    with pytest.raises(InputError, match="arrival-time"):
        final.emg_host_offset_ns(0)


def test_movement_that_is_not_the_trackers_is_not_taken_for_it():
    t, arm = motion(30.0, seed=3)
    _, other = motion(30.0, seed=4)
    final = final_on_trial_time(0, t, ("other", other), arm)
    assert final.status is SyncStatus.NOT_TOGETHER and final.offset_ns is None, final
    assert final.peak_correlation < 0.8 and "below 0.8" in final.reason, final.reason


def test_an_offset_beyond_the_search_range_is_refused_not_guessed():
    t, arm = motion(30.0, seed=5)
    final = final_on_trial_time(-900_000_000, t, ("arm", arm), arm)  # the prior is 0.9 s off, the search spans ±0.5 s
    assert final.status is SyncStatus.NOT_TOGETHER and final.offset_ns is None, final
    assert "edge of the search range" in final.reason or "below" in final.reason, final.reason


def test_a_drifting_tracker_clock_is_followed():
    t, arm = motion(150.0, seed=6)
    drift = 80e-6  # the tracker's crystal runs 80 ppm fast
    sync = ClockSync(40_000_000)
    answers = feed(
        sync,
        {"arm": measured(t, arm, AUX_HZ, 1)},
        measured(t, arm, TRACKER_HZ, 2, start_s=0.5),
        emg_clock_s=0.0,
        tracker_clock_s=lambda ts: ts * (1 + drift),
        block_s=0.1,
    )
    final = answers[-1]
    newest = sync.windows[-1]
    centre_s = (newest.start_ns + newest.end_ns) / 2e9  # EMG device time = trial time here
    truth_ns = centre_s * drift * 1e9
    print(
        f"drift {final.drift_ppm:.1f} ppm (truth 80), offset at {centre_s:.0f} s {final.offset_ns / 1e6:.3f} ms "
        f"(truth {truth_ns / 1e6:.3f} ms), spread {final.spread_ns / 1e6:.3f} ms"
    )
    assert final.locked and final.drift_ppm == pytest.approx(80.0, abs=10.0)
    assert abs(final.offset_ns - truth_ns) < 1_000_000
    assert final.windows <= round(ClockSyncConfig().history_s / ClockSyncConfig().step_s) + 1  # old windows forgotten


def test_waiting_until_a_window_is_covered_and_bad_input_refused():
    sync = ClockSync(0)
    assert sync.update().status is SyncStatus.WAITING and "EMG-clock" in sync.update().reason
    sync.add_emg_sensor("s1", np.arange(10) * 6_750_000, np.tile([0.0, 0.0, 1.0], (10, 1)))
    assert sync.update().status is SyncStatus.WAITING and "tracker" in sync.update().reason
    sync.add_tracker(np.arange(5) * 10_000_000, np.tile(UP, (5, 1)))
    answer = sync.update()
    assert answer.status is SyncStatus.WAITING and "window" in answer.reason and answer.windows_seen == 0
    with pytest.raises(InputError, match="increase"):
        sync.add_tracker([40_000_000], [UP])  # before the tracker's last sample
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        sync.add_emg_sensor("s1", [100_000_000], [[0.0, 1.0]])
    with pytest.raises(InputError, match="one device time per"):
        sync.add_emg_sensor("s1", [100_000_000, 110_000_000], [[0.0, 0.0, 1.0]])
    with pytest.raises(InputError, match="NaN"):
        sync.add_tracker([900_000_000], [[np.nan, 0.0, 9.8]])
    for field, value in (("min_correlation", 1.5), ("window_s", 0.0), ("lowpass_hz", 150.0)):
        with pytest.raises(ConfigError, match=field):
            ClockSyncConfig(**{field: value})
