"""Electrode quality in the estimator's EMG path: LiveQuality (one monitor per source, episodes, time in check and bad,
gaps, re-sent rows, units) and the masking of a bad electrode in LiveEmg (its group averaged without it, NaN when it
was the group's only one, ``electrode_bad`` on the envelope and on the frames that read it); the node's status."""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.live_emg import FLAG_ELECTRODE_BAD, EmgSetup, LiveEmg
from msk_core.estimate.live_quality import LiveQuality
from msk_core.signal.quality import ElectrodeState, Fault

RATE = 2000.0
CHUNK = 27


def t_ns(index: int) -> int:
    return int(round(index * 1e9 / RATE))


def emg(n: int, channels: int, rng: np.random.Generator) -> np.ndarray:
    """EMG-like noise of 50 uV RMS in 20-450 Hz (what the monitor calls good)."""
    from scipy import signal

    sos = signal.butter(4, (20.0, 450.0), btype="band", fs=RATE, output="sos")
    x = signal.sosfilt(sos, rng.standard_normal((n + 2000, channels)), axis=0)[2000:]
    return 50e-6 * x / x.std(axis=0)


def feed(quality: LiveQuality, samples: np.ndarray, start: int = 0, labels=("a", "b", "c"), units: str = "V") -> int:
    for k in range(0, len(samples), CHUNK):
        block = samples[k : k + CHUNK]
        quality.add_chunk(RawEmgChunk("s", labels, RATE, start + k, t_ns(start + k), block, units))
    return start + len(samples)


def test_episodes_times_and_reasons_of_a_flat_channel():
    rng = np.random.default_rng(1)
    x = emg(int(8 * RATE), 3, rng)
    x[int(3 * RATE) : int(5 * RATE), 1] = x[int(3 * RATE) - 1, 1]  # channel b holds still for 2 s
    quality = LiveQuality({"a": "G1", "b": "G2"})
    feed(quality, x)
    a, b, c = quality.report()
    assert (a.group, b.group, c.group) == ("G1", "G2", "")
    assert a.episodes == c.episodes == 0 and a.state is ElectrodeState.GOOD and a.detail == "good"
    assert b.episodes == 1 and b.episode_faults == {Fault.FLAT_LINE: 1} and b.state is ElectrodeState.GOOD
    episode = b.recent[0]
    assert episode.worst is ElectrodeState.BAD and episode.faults == [Fault.FLAT_LINE]
    assert 3.0 < episode.start_ns / 1e9 <= 4.0 and 5.0 < episode.end_ns / 1e9 <= 6.0
    # time in bad: the verdicts in bad times the hop, as long as the episode less the hops before it turned bad
    assert b.bad_s == pytest.approx((episode.end_ns - episode.start_ns) / 1e9, abs=0.13) and b.check_s == 0.0
    assert b.since_ns == episode.end_ns  # good again since the episode ended


def test_bad_channels_follow_the_state_and_gaps_restart_the_monitor():
    rng = np.random.default_rng(2)
    x = emg(int(3 * RATE), 3, rng)
    x[int(1 * RATE) :, 2] = 0.0  # channel c stops at 1 s
    quality = LiveQuality()
    end = feed(quality, x)
    assert quality.bad_channels("s") == {"c"} and quality.bad_channels("other") == frozenset()
    c = quality.report()[2]
    assert c.state is ElectrodeState.BAD and "flat line" in c.detail and c.recent[0].end_ns is None
    # 1 s of samples never arrive: the monitor starts again (unknown), the episode stays open through the gap
    feed(quality, emg(CHUNK, 3, rng) * [1, 1, 0], start=end + int(RATE))
    c = quality.report()[2]
    assert c.state is ElectrodeState.UNKNOWN and quality.bad_channels("s") == frozenset() and c.episodes == 1
    end = feed(quality, emg(int(2 * RATE), 3, rng), start=end + int(RATE) + CHUNK)
    c = quality.report()[2]
    assert c.state is ElectrodeState.GOOD and c.episodes == 1 and c.recent[0].end_ns is not None


def test_re_sent_rows_are_judged_once_and_units_are_honoured():
    rng = np.random.default_rng(3)
    x = emg(int(2 * RATE), 3, rng)
    once, twice = LiveQuality(), LiveQuality()
    feed(once, x)
    for k in range(0, len(x), CHUNK):  # every chunk sent twice
        for _ in range(2):
            twice.add_chunk(RawEmgChunk("s", ("a", "b", "c"), RATE, k, t_ns(k), x[k : k + CHUNK]))
    assert [r.detail for r in once.report()] == [r.detail for r in twice.report()]
    assert once.sources["s"].monitor.samples_seen == twice.sources["s"].monitor.samples_seen == len(x)
    millivolts = LiveQuality()
    feed(millivolts, x * 1e3, units="mV")  # the same EMG in mV: the same verdicts
    assert [r.detail for r in millivolts.report()] == [r.detail for r in once.report()]
    normalised = LiveQuality()
    assert not normalised.add_chunk(RawEmgChunk("s", ("a", "b", "c"), RATE, 0, 0, x[:CHUNK], "normalised"))
    assert all(r.state is ElectrodeState.UNKNOWN and "not judged" in r.detail for r in normalised.report())


def test_a_bad_electrode_is_left_out_of_its_group_and_the_frames_say_so():
    setup = EmgSetup({"a": "G1", "b": "G1", "c": "G2"}, {"a": 1.0, "b": 1.0, "c": 1.0}, emd_s=0.0)
    every, masked = LiveEmg(["G1", "G2", "G3"], setup), LiveEmg(["G1", "G2", "G3"], setup)
    masked.exclude_channels("s", {"b"})  # before the source's first chunk: kept until it comes
    rng = np.random.default_rng(4)
    base = rng.normal(size=(CHUNK * 101, 1))
    x = np.hstack([base, 3 * base, rng.normal(size=(CHUNK * 101, 1))])  # b = 3 a: its envelope is 3x a's

    def both(k: int):
        index = k * CHUNK
        chunk = RawEmgChunk("s", ["a", "b", "c"], RATE, index, t_ns(index), x[index : index + CHUNK])
        return every.add_chunk(chunk, t_ns(index)), masked.add_chunk(chunk, t_ns(index))

    for k in range(50):
        full, without_b = both(k)
    assert FLAG_ELECTRODE_BAD in without_b.flags and FLAG_ELECTRODE_BAD not in full.flags
    # G1 = mean(a, b) = 2a with b; a alone without it; G2 untouched
    assert np.allclose(2 * without_b.envelope[:, 0], full.envelope[:, 0])
    assert np.array_equal(without_b.envelope[:, 1], full.envelope[:, 1])
    env, flags = masked.at(t_ns(50 * CHUNK - 60), t_ns(50 * CHUNK))
    assert FLAG_ELECTRODE_BAD in flags and np.all(np.isfinite(env[:2])) and np.isnan(env[2])
    masked.exclude_channels("s", set())  # b is good again: its filter ran all along, the envelopes are the same
    for k in range(50, 100):
        full, with_b = both(k)
    assert FLAG_ELECTRODE_BAD not in with_b.flags and np.array_equal(with_b.envelope, full.envelope)
    _, flags = masked.at(t_ns(100 * CHUNK - 60), t_ns(100 * CHUNK))
    assert FLAG_ELECTRODE_BAD not in flags
    _, flags = masked.at(t_ns(50 * CHUNK - 60), t_ns(100 * CHUNK))  # an envelope made without b still says so
    assert FLAG_ELECTRODE_BAD in flags
    masked.exclude_channels("s", {"c"})  # the only electrode of G2: G2 has no envelope while it is bad
    _, without_c = both(100)
    assert FLAG_ELECTRODE_BAD in without_c.flags and np.all(np.isnan(without_c.envelope[:, 1]))
    assert np.all(np.isfinite(without_c.envelope[:, 0]))
    env, flags = masked.at(t_ns(101 * CHUNK - 1), t_ns(101 * CHUNK))
    assert np.isnan(env[1]) and np.isfinite(env[0]) and FLAG_ELECTRODE_BAD in flags


def test_an_unmapped_bad_channel_changes_nothing():
    setup = EmgSetup({"a": "G1"}, {"a": 1.0}, emd_s=0.0)
    live = LiveEmg(["G1"], setup)
    live.exclude_channels("s", {"z"})  # not an electrode of any group (nor a label of the source)
    block = live.add_chunk(RawEmgChunk("s", ["a", "z"], RATE, 0, 0, np.ones((CHUNK, 2))), 0)
    assert FLAG_ELECTRODE_BAD not in block.flags and np.all(np.isfinite(block.envelope))
