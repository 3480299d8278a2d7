"""The host clock mapping of a device stream (msk_core/signal/host_clock.py) and its use by the live EMG path
(msk_core/estimate/live_emg.py): sliding window, stated latency, spread, offsets set from outside, the report."""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.errors import ConfigError
from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.live_emg import ClockMode, EmgSetup, LiveEmg
from msk_core.signal.host_clock import HostClock, parse_latencies, windowed_offsets

RATE = 2000.0
BLOCK = 27  # a Trigno frame


def delivered_blocks(
    seconds: float,
    *,
    clock_ns: int,
    latency_ns: int,
    seed: int,
    drift_ppm: float = 0.0,
    restart_at_s: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(device time of each block's last sample, host receipt) of a device sending 27-sample blocks: measured at
    host instant T (device time T - clock, the device clock running ``drift_ppm`` fast; from ``restart_at_s`` on,
    counting again from 0 as after a power cycle), received at T + latency + a random delay (exponential, mean 2 ms;
    now and then one at once)."""
    rng = np.random.default_rng(seed)
    last = np.arange(BLOCK - 1, int(seconds * RATE), BLOCK)
    host_instant = np.round(last * 1e9 / RATE).astype(np.int64)
    device = np.round(host_instant * (1 + drift_ppm * 1e-6)).astype(np.int64) - clock_ns
    extra = rng.exponential(2e6, len(last)).astype(np.int64)
    extra[rng.random(len(last)) < 0.05] = 0
    if restart_at_s is not None:
        device[host_instant >= restart_at_s * 1e9] -= int(restart_at_s * 1e9) - clock_ns
    receipt = np.maximum.accumulate(host_instant + latency_ns + extra)  # one connection delivers in order
    return device, receipt


def test_streaming_mapping_equals_the_batch_one_sample_after_sample():
    device, receipt = delivered_blocks(
        20.0, clock_ns=-7_000_000_000, latency_ns=30_000_000, seed=1, drift_ppm=80.0, restart_at_s=9.0
    )
    clock = HostClock("emg/x", latency_ns=30_000_000, window_s=5.0)
    streamed = []
    for d, r in zip(device, receipt):
        clock.add(int(d), int(r))
        streamed.append(clock.offset_ns)
    batch = windowed_offsets(device, receipt, latency_ns=30_000_000, window_s=5.0)
    np.testing.assert_array_equal(np.array(streamed), batch)
    # the batch one is a plain minimum over the samples received within the window before each one
    for i in (0, 1, 100, 500, len(device) - 1):
        inside = receipt[: i + 1] >= receipt[i] - 5_000_000_000
        assert batch[i] == (receipt[: i + 1] - device[: i + 1])[inside].min() - 30_000_000


def test_the_stated_latency_makes_the_mapping_the_instant_measured():
    """Device time + offset = host instant measured, up to the fastest delivery beyond the stated latency (the
    blocks delivered at once: 0 here)."""
    clock_ns, latency_ns = 123_456_789_000, 60_000_000
    device, receipt = delivered_blocks(6.0, clock_ns=clock_ns, latency_ns=latency_ns, seed=2)
    stated, unstated = HostClock("emg/x", latency_ns=latency_ns), HostClock("emg/x")
    for d, r in zip(device, receipt):
        stated.add(int(d), int(r))
        unstated.add(int(d), int(r))
    assert stated.offset_ns == clock_ns  # host instant T = device time + clock
    assert unstated.offset_ns == clock_ns + latency_ns  # without it, every EMG sample is placed 60 ms late


def test_the_window_follows_a_drifting_clock_and_a_clock_that_restarted():
    """A device clock 100 ppm slow (6 ms a minute) that restarts from 0 after 30 s (a power cycle): the windowed
    mapping is within a ms of the truth throughout, and from the restart's first sample on within its delivery delay
    (not 30 s off for a window's length, as while the old clock's samples held the minimum: an MVN stream started
    again gave no joint frame for 5-7 s, then a calibration mid-rep); the smallest delay over all time (the former
    rule) falls behind the drift and never recovers from the restart."""
    device, receipt = delivered_blocks(60.0, clock_ns=0, latency_ns=0, seed=3, drift_ppm=-100.0, restart_at_s=30.0)
    host_instant = np.round(np.arange(BLOCK - 1, int(60 * RATE), BLOCK) * 1e9 / RATE).astype(np.int64)
    truth = host_instant - device  # the offset that maps each sample to its instant
    windowed_error_ms = np.abs(windowed_offsets(device, receipt) - truth) / 1e6
    all_time_error_ms = np.abs(np.minimum.accumulate(receipt - device) - truth) / 1e6
    settled = (host_instant < 30e9) | (host_instant > 30.5e9)
    assert windowed_error_ms[settled].max() < 1.0, windowed_error_ms[settled].max()
    restarted = (host_instant >= 30e9) & (host_instant <= 30.5e9)
    assert windowed_error_ms[restarted].max() < 20.0  # the first blocks' own delays, until a fast one comes
    assert all_time_error_ms[(host_instant > 25e9) & (host_instant < 30e9)].min() > 2.0  # 2.5-3 ms of drift
    assert all_time_error_ms[host_instant > 30e9].min() > 1e3
    clock = HostClock("imu/t")
    for d, r in zip(device, receipt):
        clock.add(int(d), int(r))
    assert clock.restarts == 1


def test_a_device_time_a_little_behind_is_no_restart():
    """A sample some ms behind the newest (a datagram reordered on its way) is no clock restart: the window keeps
    its samples."""
    clock = HostClock("imu/t")
    for k in range(100):
        clock.add(k * 10_000_000, k * 10_000_000 + 1_000_000)
    clock.add(950_000_000, 1_001_000_000)  # 40 ms behind the newest
    assert clock.restarts == 0 and clock.report().samples == 101 and clock.offset_ns == 1_000_000


def test_the_spread_is_the_95th_percentile_minus_the_minimum_over_the_window():
    clock = HostClock("imu/t", window_s=1.0)
    delays_ms = np.concatenate([np.full(50, 40.0), np.arange(100) * 0.1 + 1.0])  # most of the first 50 leave it
    receipts = np.arange(len(delays_ms)) * 10_000_000 + np.round(delays_ms * 1e6).astype(np.int64)
    for k, receipt in enumerate(receipts):
        clock.add(k * 10_000_000, int(receipt))  # a sample every 10 ms
    kept = delays_ms[receipts >= receipts[-1] - 1_000_000_000]  # received within 1 s of the newest
    assert 100 < len(kept) < 150
    report = clock.report()
    assert report.samples == len(kept) and report.method == "arrival" and report.source == "imu/t"
    assert report.spread_ns == round((np.percentile(kept, 95) - kept.min()) * 1e6)
    assert report.offset_ns == int(1.0e6)


def test_bad_latencies_and_windows_are_refused_with_the_field_named():
    with pytest.raises(ConfigError, match="latency of emg/x"):
        HostClock("emg/x", latency_ns=-1)
    with pytest.raises(ConfigError, match="window_s"):
        HostClock("emg/x", window_s=0.0)
    assert parse_latencies(["trigno=60", "12.5"], "--emg-latency-ms") == ({"trigno": 60_000_000}, 12_500_000)
    for item in ("trigno=fast", "=5", "trigno=-1", "2000", "nan"):
        with pytest.raises(ConfigError, match="--emg-latency-ms"):
            parse_latencies([item], "--emg-latency-ms")
    with pytest.raises(ConfigError, match="receipt_ns"):
        windowed_offsets([0, 1], [5, 4])


def _live(**kwargs) -> LiveEmg:
    return LiveEmg(["g"], EmgSetup({"c": "g"}, {"c": 1.0}), clock=ClockMode.HOST, **kwargs)


def _feed(live: LiveEmg, device, receipt, arrival_ns=None) -> None:
    rng = np.random.default_rng(0)
    for k, (d, r) in enumerate(zip(device, receipt)):
        first = k * BLOCK
        live.add_chunk(
            RawEmgChunk(
                "trigno", ("c",), RATE, first, int(d) - round((BLOCK - 1) * 1e9 / RATE), rng.standard_normal((BLOCK, 1))
            ),
            int(r) if arrival_ns is None else arrival_ns,
            int(r),
        )


def test_live_emg_maps_each_source_by_its_receipts_less_its_latency_and_reports_it():
    device, receipt = delivered_blocks(4.0, clock_ns=5_000_000_000, latency_ns=60_000_000, seed=4)
    live = _live(latency_ns={"trigno": 60_000_000}, joints_clock="host")
    _feed(live, device, receipt, arrival_ns=1)  # this node's own arrival times play no part in the mapping
    assert live.sources["trigno"].offset_ns == 5_000_000_000
    reports = {r.source: r for r in live.clock_report()}
    assert set(reports) == {"emg/trigno", "joints"}
    assert reports["emg/trigno"].latency_ns == 60_000_000 and reports["emg/trigno"].method == "arrival"
    assert reports["joints"].method == "host" and reports["joints"].offset_ns == 0
    # joints on a device clock: mapped by their own receipt times, and reported so
    arrival = _live(joints_clock="arrival")
    arrival.at(1_000_000, 9_000_000, 8_000_000)
    joints = {r.source: r for r in arrival.clock_report()}["joints"]
    assert joints.method == "arrival" and joints.offset_ns == 7_000_000


def test_a_frame_reads_the_emg_of_its_own_instant_once_the_latency_is_stated():
    """A frame at host instant 3 s (joints on the host clock) reads the EMG sample measured at 3 s once the base's
    60 ms latency is stated; without it, every EMG sample is placed 60 ms late, so the frame reads the one measured
    60 ms before its instant."""
    clock_ns, latency_ns = 5_000_000_000, 60_000_000
    device, receipt = delivered_blocks(4.0, clock_ns=clock_ns, latency_ns=latency_ns, seed=5)

    def instant_read(live: LiveEmg) -> float:
        """The host instant of the EMG sample a frame at 3 s reads (from the chunk times the source kept)."""
        state = live.sources["trigno"]
        t = 3_000_000_000 - state.offset_ns
        times = np.concatenate(state.times)
        return (times[times <= t][-1] + clock_ns) / 1e9

    stated, unstated = _live(latency_ns={"trigno": latency_ns}, joints_clock="host"), _live(joints_clock="host")
    for live in (stated, unstated):
        _feed(live, device, receipt)
        envelope, flags = live.at(3_000_000_000, int(receipt[-1]))
        assert np.isfinite(envelope[0]) and not flags
    assert abs(instant_read(stated) - 3.0) <= 0.5 / RATE
    assert abs(instant_read(unstated) - (3.0 - 0.060)) <= 0.5 / RATE


def test_an_offset_measured_another_way_replaces_the_arrival_mapping_until_cleared():
    device, receipt = delivered_blocks(2.0, clock_ns=0, latency_ns=0, seed=6)
    live = _live(joints_clock="host")
    live.set_offset("trigno", 42_000_000, 1_500_000, "acceleration")  # before the source is seen: kept for it
    _feed(live, device, receipt)
    report = {r.source: r for r in live.clock_report()}["emg/trigno"]
    assert (report.offset_ns, report.spread_ns, report.method, report.samples) == (
        42_000_000,
        1_500_000,
        "acceleration",
        0,
    )
    assert live.sources["trigno"].offset_ns == 42_000_000
    live.set_offset("trigno", None)
    assert {r.source: r for r in live.clock_report()}["emg/trigno"].method == "arrival"
    assert live.sources["trigno"].offset_ns == live.sources["trigno"].clock.offset_ns
    with pytest.raises(ConfigError, match="method"):
        live.set_offset("trigno", 0, 0, "arrival")
    with pytest.raises(ConfigError, match="spread_ns"):
        live.set_offset("trigno", 0, -1, "acceleration")


def test_one_clock_maps_nothing_and_refuses_latencies_and_offsets():
    live = LiveEmg(["g"], EmgSetup({"c": "g"}, {"c": 1.0}))
    live.add_chunk(RawEmgChunk("trigno", ("c",), RATE, 0, 0, np.zeros((BLOCK, 1))), 10**9)
    assert [(r.source, r.method, r.offset_ns) for r in live.clock_report()] == [
        ("emg/trigno", "device", 0),
        ("joints", "device", 0),
    ]
    with pytest.raises(ConfigError, match="clock"):
        live.set_offset("trigno", 0, 0, "acceleration")
    with pytest.raises(ConfigError, match="latency"):
        LiveEmg(["g"], EmgSetup({"c": "g"}, {"c": 1.0}), latency_ns={"trigno": 1})
