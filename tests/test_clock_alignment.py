"""The live EMG clock measured against the trackers' (msk_core.estimate.clock_alignment), and joint frames waiting
for the EMG of their instant, on synthetic streams with a known truth and no network.

A segment moves after a rest (tests/test_clock_sync.py's motion). The Trigno counts from its START 0.25 s into the
trial and delivers each 13.5 ms frame 60 ms after its last sample, a latency nobody stated; its sensor01 sits on the
moving segment, sensor02 lies still. A tracker on the segment counts from its own power-up long before and delivers
each sample 2 ms after it (stated). The arrival mapping alone puts the EMG 60 ms late; the alignment must put it
where it was measured, say what it replaced, and fall back to the arrival mapping, saying why, for a tracker no EMG
sensor moves with.
"""

from __future__ import annotations

import numpy as np
import pytest

from msk_core.errors import ConfigError
from msk_core.estimate.clock_alignment import METHOD_ACCELERATION, AccelerationAlignment
from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.live_emg import EmgSetup, LiveEmg
from msk_core.signal.clock_sync import STANDARD_GRAVITY, SyncStatus
from msk_core.signal.host_clock import METHOD_ARRIVAL, DeviceClocks
from services.nodes.node_runtime import clock_offsets
from services.transport import messages
from tests.profile_helpers import reference_profile
from tests.test_clock_sync import measured, motion

HOST0_NS = 1_790_000_000_000_000_000  # host clock (ns) at trial time 0
EMG_START_S = 0.25  # the Trigno's START, trial time
TRACKER_CLOCK_S = -1234.5678912  # trial time of the tracker's clock origin (powered up long before)
TRIGNO_LATENCY_S = 0.060  # not stated
TRACKER_LATENCY_S = 0.002  # stated
EMG_HZ, FRAME_S, AUX_PER_FRAME = 2000.0, 0.0135, 2
SECONDS = 16.0


def _ns(seconds) -> np.ndarray:
    return np.round(np.asarray(seconds) * 1e9).astype(np.int64)


def _live_emg() -> LiveEmg:
    setup = EmgSetup({"sensor01.EMG": "g1"}, {"sensor01.EMG": 1.0})
    return LiveEmg(["g1"], setup, clock="host", joints_clock="host")


def _events(trackers: dict[str, np.ndarray]) -> list[tuple[int, int, str, tuple]]:
    """(receipt ns, order, kind, data), in the order the host receives them: EMG chunks and AUX blocks per Trigno
    frame, tracker samples; ``trackers``: per tracker the world acceleration it measures (on the motion's grid)."""
    t, arm = motion(SECONDS, seed=1)
    events = []
    aux_hz = AUX_PER_FRAME / FRAME_S
    aux_t, sensor01 = measured(t, arm, aux_hz, 10, start_s=EMG_START_S)
    _, sensor02 = measured(t, np.zeros_like(arm), aux_hz, 11, start_s=EMG_START_S)
    per_frame = int(round(EMG_HZ * FRAME_S))
    for frame in range(int((SECONDS - EMG_START_S - 0.1) / FRAME_S)):
        last_s = EMG_START_S + ((frame + 1) * per_frame - 1) / EMG_HZ  # trial instant of the frame's last sample
        receipt = HOST0_NS + int(_ns(last_s + TRIGNO_LATENCY_S))
        first = frame * per_frame
        events.append((receipt, 0, "emg", (first, int(_ns(first / EMG_HZ)), np.zeros((per_frame, 1)))))
        k = slice(frame * AUX_PER_FRAME, (frame + 1) * AUX_PER_FRAME)
        acc = np.stack([sensor01[k], sensor02[k]], axis=1) / STANDARD_GRAVITY
        events.append((receipt, 1, "acc", (_ns(aux_t[k] - EMG_START_S), acc)))
    for seed, (tracker, world) in enumerate(trackers.items(), start=20):
        ts, acc = measured(t, world, 100.0, seed, start_s=EMG_START_S + 0.3)
        for time_s, a in zip(ts, acc):
            events.append(
                (
                    HOST0_NS + int(_ns(time_s + TRACKER_LATENCY_S)),
                    2,
                    "imu",
                    (tracker, int(_ns(time_s - TRACKER_CLOCK_S)), a),
                )
            )
    return sorted(events, key=lambda e: (e[0], e[1]))


def _run(trackers: dict[str, np.ndarray]) -> tuple[LiveEmg, AccelerationAlignment]:
    live = _live_emg()
    alignment = AccelerationAlignment(live, DeviceClocks("imu", default_latency_ns=int(TRACKER_LATENCY_S * 1e9)))
    for receipt, _, kind, data in _events(trackers):
        if kind == "emg":
            first, device_ns, samples = data
            live.add_chunk(RawEmgChunk("trigno", ["sensor01.EMG"], EMG_HZ, first, device_ns, samples), receipt, receipt)
        elif kind == "acc":
            alignment.add_acc("trigno", ["sensor01", "sensor02"], *data)
        else:
            tracker, device_ns, acc = data
            alignment.add_tracker_sample(tracker, device_ns, receipt, acc)
    return live, alignment


def test_the_emg_is_mapped_through_the_tracker_it_moves_with_and_the_arrival_error_is_reported():
    t, arm = motion(SECONDS, seed=1)
    _, leg = motion(SECONDS, seed=5)  # another segment: no EMG sensor moves with it
    live, alignment = _run({"arm": arm, "leg": leg})
    report = {r.source: r for r in alignment.report(live.clock_report())}["emg/trigno"]
    truth_ns = HOST0_NS + int(_ns(EMG_START_S))  # host instant of EMG device time 0
    print(
        f"\napplied {(report.offset_ns - truth_ns) / 1e6:+.3f} ms, arrival {(report.arrival_offset_ns - truth_ns) / 1e6:+.3f}"
        f" ms from the truth; {report.reason}"
    )
    assert report.method == METHOD_ACCELERATION
    assert abs(report.offset_ns - truth_ns) < 1_000_000  # within 1 ms
    # the arrival mapping would have put it the unstated latency later: reported beside it
    assert TRIGNO_LATENCY_S * 1e9 <= report.arrival_offset_ns - truth_ns < (TRIGNO_LATENCY_S + 0.001) * 1e9
    by_tracker = {a.reference: a for a in report.alignments}
    arm_alignment, leg_alignment = by_tracker["imu/arm"], by_tracker["imu/leg"]
    assert arm_alignment.offset.status is SyncStatus.LOCKED and arm_alignment.offset.sensor == "sensor01"
    tracker_minus_emg_ns = int(_ns(EMG_START_S - TRACKER_CLOCK_S))
    assert abs(arm_alignment.offset.offset_ns - tracker_minus_emg_ns) < 1_000_000
    assert leg_alignment.offset.status is SyncStatus.NOT_TOGETHER and leg_alignment.host_offset_ns is None
    assert report.reason.startswith("1 of 2 tracker(s)"), report.reason
    # as the status carries it
    status = clock_offsets([report])[0]
    assert status.method == METHOD_ACCELERATION and status.HasField("arrival_offset_ms")
    assert status.arrival_offset_ms - status.offset_ms == pytest.approx(
        (report.arrival_offset_ns - report.offset_ns) / 1e6, abs=1e-3
    )
    assert {a.reference: a.status for a in status.alignments} == {"imu/arm": "locked", "imu/leg": "not_together"}
    assert messages.decode("msk.DeviceStatus", messages.encode(messages.DeviceStatus(device_id="e", clocks=[status])))


def test_without_a_tracker_that_moves_with_an_emg_sensor_the_arrival_mapping_stays_and_says_why():
    _, leg = motion(SECONDS, seed=5)
    live, alignment = _run({"leg": leg})
    report = {r.source: r for r in alignment.report(live.clock_report())}["emg/trigno"]
    assert report.method == METHOD_ARRIVAL and report.offset_ns == live.arrival_offset_ns("trigno")
    assert report.arrival_offset_ns is None
    assert report.reason.startswith("arrival mapping: no tracker moved with an EMG sensor yet: imu/leg not_together")


def test_an_emg_stream_without_accelerations_says_so():
    live = _live_emg()
    alignment = AccelerationAlignment(live, DeviceClocks("imu"))
    live.add_chunk(RawEmgChunk("trigno", ["sensor01.EMG"], EMG_HZ, 0, 0, np.zeros((27, 1))), HOST0_NS, HOST0_NS)
    (report,) = [r for r in alignment.report(live.clock_report()) if r.source == "emg/trigno"]
    assert report.method == METHOD_ARRIVAL and "no accelerations on this EMG clock (acc/trigno)" in report.reason


def test_a_restarted_tracker_clock_starts_its_estimate_over():
    live, alignment = _run({"arm": motion(SECONDS, seed=1)[1]})
    assert alignment.alignments("trigno")[0].offset.locked
    alignment.add_tracker_sample("arm", 5_000_000, HOST0_NS + int(_ns(SECONDS)), (0.0, 0.0, STANDARD_GRAVITY))
    alignment.add_acc("trigno", ["sensor01", "sensor02"], _ns([SECONDS]), np.array([[[0, 0, 1.0], [0, 0, 1.0]]]))
    (again,) = alignment.alignments("trigno")
    assert alignment.counters.restarts == 1 and again.offset.status is SyncStatus.WAITING
    assert {r.source: r for r in live.clock_report()}["emg/trigno"].method == METHOD_ARRIVAL  # back to arrival


def test_only_with_device_clocks_mapped_onto_the_host_clock():
    setup = EmgSetup({"sensor01.EMG": "g1"}, {"sensor01.EMG": 1.0})
    with pytest.raises(ConfigError, match="clock 'host'"):
        AccelerationAlignment(LiveEmg(["g1"], setup, clock="device"), DeviceClocks("imu"))


def test_a_frame_awaits_the_emg_of_its_instant_while_the_source_delivers():
    live = _live_emg()
    # a chunk of 27 samples measured from host instant 0 (device time 0), received 60 ms after its last sample
    received = 13_000_000 + 60_000_000
    live.add_chunk(RawEmgChunk("trigno", ["sensor01.EMG"], EMG_HZ, 0, 0, np.ones((27, 1))), received, received)
    offset = live.arrival_offset_ns("trigno")  # host instant of device time 0: 60 ms late (unstated latency)
    live.set_offset("trigno", offset - 60_000_000, 0, METHOD_ACCELERATION)  # the true mapping
    assert not live.awaits(10_000_000, received)  # the EMG of instant 10 ms is here
    assert live.awaits(40_000_000, received)  # that of 40 ms is on its way
    assert not live.awaits(40_000_000, received + 300_000_000)  # unless the source stalled (nothing to wait for)


def test_the_estimator_holds_a_joint_frame_until_its_emg_arrives_or_it_has_waited_long_enough():
    from msk_core.model import load_pack
    from services.nodes.estimator import EmgTiming, EstimatorNode, EstimatorSettings, EstimatorStats

    pack = load_pack("bench_press")
    profile = reference_profile(pack, {"sensor01.EMG": pack.groups[0]})
    stats = EstimatorStats()
    timing = EmgTiming(joints_clock="host", emg_wait_s=0.1)
    settings = EstimatorSettings("bench_press", "t", ("so",), emg=True, emg_clock="host", timing=timing)
    node = EstimatorNode(settings, profile, stats)
    per_frame = 27

    def chunk(frame: int) -> messages.EmgChunk:  # device time = host time: measured at t, received at its last sample
        first = frame * per_frame
        received = HOST0_NS + int(_ns((first + per_frame - 1) / EMG_HZ))
        return messages.EmgChunk(
            source_id="trigno",
            channel_labels=["sensor01.EMG"],
            sample_rate_hz=EMG_HZ,
            first_sample_index=first,
            device_time_ns=int(_ns(first / EMG_HZ)),
            host_time_ns=received,
            n_samples=per_frame,
            n_channels=1,
            samples=[0.001] * per_frame,
            units="V",
        )

    def joints(host_ns: int) -> messages.JointAngles:
        return messages.JointAngles(
            coordinates=list(pack.coordinates),
            q=list(pack.reference_pose),
            device_time_ns=host_ns,
            host_time_ns=host_ns,
        )

    first = chunk(0)
    node.handle_emg(first, first.host_time_ns)
    node.live_emg.set_offset("trigno", HOST0_NS, 0, METHOD_ACCELERATION)  # the EMG clock is the host's, from HOST0
    arrival = first.host_time_ns
    node.offer_joints(joints(HOST0_NS + 5_000_000), arrival)  # its EMG is here
    node.offer_joints(joints(HOST0_NS + 20_000_000), arrival)  # its EMG is in the next chunk
    assert [j.device_time_ns - HOST0_NS for j, _ in node.release(arrival)] == [5_000_000]
    assert node.release(arrival + 5_000_000) == [] and stats.frames_waited == 0
    second = chunk(1)
    node.handle_emg(second, second.host_time_ns)
    assert [j.device_time_ns - HOST0_NS for j, _ in node.release(second.host_time_ns)] == [20_000_000]
    assert stats.frames_waited == 1
    node.offer_joints(joints(HOST0_NS + 60_000_000), second.host_time_ns)  # the next chunk never comes
    assert node.release(second.host_time_ns + 99_000_000) == []
    assert len(node.release(second.host_time_ns + 100_000_000)) == 1  # it waited emg_wait_s: estimated anyway
    node.offer_joints(joints(HOST0_NS + 80_000_000), second.host_time_ns)
    assert len(node.release(second.host_time_ns, flush=True)) == 1  # the node stops: every held frame out


def test_a_second_emg_source_starting_a_moment_later_is_not_said_missing(caplog):
    """Two bases: the electrode map names sensor01 of the first and sensor01 of the second. The estimator warned
    "no EMG source streams" the second's channel at the first chunk of the first base; it says so only once EMG
    has streamed for MISSING_CHANNEL_GRACE_S without it."""
    import logging

    from msk_core.model import load_pack
    from services.nodes.estimator import (
        MISSING_CHANNEL_GRACE_S,
        EstimatorNode,
        EstimatorSettings,
        EstimatorStats,
    )

    pack = load_pack("bench_press")
    profile = reference_profile(pack, {"a.EMG": pack.groups[0], "b.EMG": pack.groups[1]})

    def chunk(source: str, label: str, k: int) -> messages.EmgChunk:
        return messages.EmgChunk(
            source_id=source,
            channel_labels=[label],
            sample_rate_hz=EMG_HZ,
            first_sample_index=27 * k,
            device_time_ns=int(_ns(27 * k / EMG_HZ)),
            host_time_ns=HOST0_NS + int(_ns(27 * k / EMG_HZ)),
            n_samples=27,
            n_channels=1,
            samples=[0.001] * 27,
            units="V",
        )

    def missing_said() -> list[str]:
        return [r.getMessage() for r in caplog.records if "no EMG source streams" in r.getMessage()]

    caplog.set_level(logging.WARNING, logger="services.nodes.estimator")
    frames_per_s = round(EMG_HZ / 27)
    late = EstimatorNode(
        EstimatorSettings("bench_press", "t", ("so",), emg=True, emg_clock="host"), profile, EstimatorStats()
    )
    for k in range(frames_per_s):  # base a for 1 s, then base b joins
        late.handle_emg(chunk("base-a", "a.EMG", k), HOST0_NS + int(k * 1e9 / frames_per_s))
    late.handle_emg(chunk("base-b", "b.EMG", 0), HOST0_NS + int(1e9))
    assert missing_said() == [] and late.live_emg.counters.missing_channels == []
    never = EstimatorNode(
        EstimatorSettings("bench_press", "t", ("so",), emg=True, emg_clock="host"), profile, EstimatorStats()
    )
    for k in range(int((MISSING_CHANNEL_GRACE_S + 0.5) * frames_per_s)):  # base b never comes
        never.handle_emg(chunk("base-a", "a.EMG", k), HOST0_NS + int(k * 1e9 / frames_per_s))
    (said,) = missing_said()
    assert "the electrode map names b.EMG, which no EMG source streams" in said
