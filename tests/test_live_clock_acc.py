"""``msk live --sim`` with a Trigno that delivers 60 ms late without the session file saying so, and trackers switched
on 300 ms after the Trigno: the estimator measures the EMG clock against each tracker's from the accelerations both
sense (the Trigno sensors' accelerometers on the AUX port, ``msk/<s>/acc/trigno``; the trackers' ``ImuSample``), maps
the EMG through them and says so in its status and in ``summary.json``: method ``acceleration``, each tracker's
offset within ±10 ms of the truth the simulators' trial clock gives, and beside it the arrival mapping's error (the
unstated 60 ms). The live measured envelope then lines up with the motion within one joint frame (the lags measured
as tests/test_sim_clock.py measures them, from the recording's content), and the recording, replayed through an
estimator, gives the same alignment.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.estimate.live_emg import FLAG_GAP, FLAG_STALLED, EmgSetup
from msk_core.estimate.profile import SubjectProfile
from services.nodes.estimator import EmgTiming, EstimatorNode, EstimatorSettings, EstimatorStats
from services.sessions import live
from services.sessions.live_session import load_session_file
from services.transport import messages
from services.transport.mcap_io import read_messages
from tests.live_helpers import run_sim_graph
from tests.test_sim_clock import (
    FRAME_S,
    MAX_LAG_S,
    emg_stream,
    frame_trial_instants,
    group_envelopes,
    imu_streams,
    peak_lag,
    unwrap_to,
)

TRIGNO_LATENCY_S = 0.060  # the simulated base holds each frame this long; the session file states nothing
TRACKERS_AFTER_S = 0.300  # the trackers measure from this long after the Trigno's first sample
RUN_S = 16.0  # the first 6 s windows with movement on both sides lock (10-11 s in), the lags are measured after
AFTER_LOCK_S = 1.0  # frames are compared from this long after the status first says "acceleration"
TOLERANCE_MS = 10.0


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """One ``msk live --sim`` session on simulators whose trial clock this test reads: (summary, plan, truth), the
    truth in ns: per stream the host instant (CLOCK_REALTIME) of its device time 0, per tracker its offset to the
    EMG clock (tracker device time - EMG device time of one instant)."""
    tmp = tmp_path_factory.mktemp("acc")
    path = tmp / "acc.toml"
    path.write_text('[session]\nname = "acc"\nout = "out"\nmethods = ["so"]\n[trigno]\n[xsens]\n')
    session = load_session_file(path, require_devices=False)
    start_simulators = live.start_simulators

    def late_trigno(sources, **options):  # what the session file says is 0 ms; the base takes 60
        options["trigno_latency_s"] = TRIGNO_LATENCY_S
        return start_simulators(sources, trackers_after_trigno_s=TRACKERS_AFTER_S, **options)

    summary, plan, simulators, real_minus_monotonic_ns = run_sim_graph(
        session, tmp, RUN_S, start_simulators=late_trigno
    )
    assert plan.trigno_latency_ms == 0.0 and simulators.trigno.stats.latency_s == TRIGNO_LATENCY_S
    trigno = simulators.trigno
    emg_origin_s = simulators.clock.start + trigno.stats.start_index / trigno.rate_hz
    truth = {"emg/trigno": emg_origin_s * 1e9 + real_minus_monotonic_ns}
    for tracker, sim in simulators.xsens.items():
        truth[f"imu/{tracker}"] = sim._powered_at * 1e9 + real_minus_monotonic_ns
        truth[f"offset/{tracker}"] = (emg_origin_s - sim._powered_at) * 1e9
        started_s = sim.stats.start_index / sim.source.rate_hz - trigno.stats.start_index / trigno.rate_hz
        # the scenario: each tracker streams at least TRACKERS_AFTER_S after the Trigno (on busy cores its driver's
        # start can add a few hundred ms: 0.55 s seen in a clean-clone suite); the truth above uses the real start
        assert TRACKERS_AFTER_S - 0.02 < started_s < TRACKERS_AFTER_S + 2.0, (tracker, started_s)
    return summary, plan, truth


def test_the_estimator_maps_the_emg_by_the_accelerations_and_reports_the_arrival_mappings_error(live_run):
    summary, plan, truth = live_run
    emg = summary["clocks"]["emg/trigno"]
    print(f"\nEMG clock: {emg}")
    assert emg["method"] == "acceleration" and emg["node"] == "estimator", emg
    assert set(emg["alignments"]) == {f"imu/{t}" for t in plan.trackers}, emg
    for tracker in plan.trackers:
        alignment = emg["alignments"][f"imu/{tracker}"]
        error_ms = alignment["device_offset_ms"] - truth[f"offset/{tracker}"] / 1e6
        print(
            f"imu/{tracker}: {alignment['status']}, EMG-vs-tracker offset {error_ms:+.3f} ms from the truth, r "
            f"{alignment['peak_correlation']}, sensor {alignment['sensor']}, {alignment['windows']} window(s)"
        )
        assert alignment["status"] == "locked" and abs(error_ms) <= TOLERANCE_MS, alignment
    # the applied mapping puts an EMG sample where it was measured; the arrival mapping it replaced would have put
    # it the unstated latency later (plus up to the fastest delivery's excess), and the summary says by how much
    applied_error_ms = emg["offset_ms"] - truth["emg/trigno"] / 1e6
    arrival_error_ms = emg["arrival_offset_ms"] - truth["emg/trigno"] / 1e6
    print(
        f"EMG mapping error: applied {applied_error_ms:+.2f} ms, arrival {arrival_error_ms:+.2f} ms (reported "
        f"{emg['arrival_error_ms']:+.2f} ms beside it)"
    )
    assert abs(applied_error_ms) <= TOLERANCE_MS, applied_error_ms
    assert TRIGNO_LATENCY_S * 1e3 - 2 < arrival_error_ms < TRIGNO_LATENCY_S * 1e3 + 15, arrival_error_ms
    assert emg["arrival_error_ms"] == pytest.approx(arrival_error_ms - applied_error_ms, abs=0.01)
    # the status says so while the session runs: arrival (and why) first, acceleration once locked
    methods = [(c.method, c.reason) for s in _statuses(summary) for c in s.clocks if c.source == "emg/trigno"]
    assert methods[0][0] == "arrival" and methods[0][1].startswith("arrival mapping"), methods[0]
    assert methods[-1][0] == "acceleration", methods[-1]


def test_the_live_measured_envelope_lines_up_with_the_motion_once_aligned(live_run):
    summary, plan, _ = live_run
    recordings = [Path(p) for p in summary["recordings"]]
    statuses = _statuses(summary)
    locked_ns = min(
        s.host_time_ns for s in statuses for c in s.clocks if c.source == "emg/trigno" and c.method == "acceleration"
    )
    sources = live.sim_sources(live.RECORDINGS / "demo_session.mcap", plan.exercise)
    rate = sources.emg.rate_hz
    emg, raw, labels = emg_stream(recordings, sources.emg.samples, rate)
    loop_s = sources.emg.n_samples / rate
    trackers = {t: unwrap_to(s, emg, loop_s) for t, s in imu_streams(recordings, sources.imu, loop_s).items()}
    frames = [
        f
        for part in recordings
        for m in read_messages(part)
        if m.type_name == "msk.ActivationFrame" and (f := m.decode()).input_arrival_ns > locked_ns + AFTER_LOCK_S * 1e9
    ]
    frames_ns = np.array([round(f.time_s * 1e9) for f in frames], np.int64)
    frame_trial_s, _ = frame_trial_instants(frames_ns, trackers)
    inside = (frame_trial_s - MAX_LAG_S > emg.trial_s[0]) & (frame_trial_s + MAX_LAG_S < emg.trial_s[-1])
    assert inside.sum() >= 180, f"only {inside.sum()} frames after the lock within the recorded EMG"  # 3 s: a rep
    setup = EmgSetup.from_profile(SubjectProfile.load(plan.subject))
    offline = group_envelopes(raw, labels, rate, setup)
    groups = list(frames[0].groups)
    results = {}
    for group, envelope in offline.items():
        measured = np.array([f.measured_envelope[groups.index(group)] for f in frames])
        usable = (
            inside & np.isfinite(measured) & np.array([not {FLAG_GAP, FLAG_STALLED} & set(f.flags) for f in frames])
        )
        assert usable.sum() > 0.9 * inside.sum(), (group, usable.sum(), inside.sum())
        lag_s, correlation = peak_lag(measured[usable], frame_trial_s[usable], emg.trial_s, envelope)
        results[group] = (lag_s + setup.emd_s, correlation)
    report = "; ".join(f"{g} {lag * 1e3:+.1f} ms (r {r:.4f})" for g, (lag, r) in results.items())
    print(
        f"\nlocked {(locked_ns - statuses[0].host_time_ns) / 1e9:.1f} s after the estimator's first status; "
        f"{inside.sum()} frames after the lock; EMG read minus the frame's instant, per group: {report}"
    )
    assert results and all(abs(lag) <= FRAME_S for lag, _ in results.values()), report
    # the peak is the same signal (r 0.95-1.00 seen in clean-clone runs on 2 busy cores): a wrong alignment gives a
    # lag beyond a frame, which the assertion above catches
    assert all(r > 0.9 for _, r in results.values()), report


def test_the_recording_replayed_through_an_estimator_gives_the_live_alignment(live_run):
    """The accelerations, the trackers' samples and the EMG are recorded with their receipt times: an estimator fed
    the recording in its order measures the offsets the live one reported last."""
    summary, plan, _ = live_run
    timing = EmgTiming(joints_clock="host", emg_latency_ns={"trigno": 0}, emg_align="acceleration")
    settings = EstimatorSettings(
        plan.session.pack, "replay", ("so",), emg=True, emg_clock="host", emg_stall_s=3600.0, timing=timing
    )
    node = EstimatorNode(settings, SubjectProfile.load(plan.subject), EstimatorStats())
    for part in summary["recordings"]:
        for m in read_messages(Path(part)):
            if m.type_name == "msk.EmgChunk":
                node.handle_emg(m.decode(), messages.now_ns())
            elif m.type_name == "msk.AccChunk":
                node.handle_acc(m.decode())
            elif m.type_name == "msk.ImuSample":
                node.handle_imu(m.topic, m.decode())
    replayed = {r.source: r for r in node.clock_report()}["emg/trigno"]
    live_emg = summary["clocks"]["emg/trigno"]
    assert replayed.method == "acceleration"
    print(f"\nreplayed minus live: applied offset {replayed.offset_ns / 1e6 - live_emg['offset_ms']:+.4f} ms")
    assert replayed.offset_ns / 1e6 == pytest.approx(live_emg["offset_ms"], abs=0.5)
    for alignment in replayed.alignments:
        live_alignment = live_emg["alignments"][alignment.reference]
        assert alignment.offset.offset_ns / 1e6 == pytest.approx(live_alignment["device_offset_ms"], abs=0.5)


def _statuses(summary) -> list:
    """The estimator's status messages of the session, in order."""
    return [
        s
        for part in summary["recordings"]
        for m in read_messages(Path(part))
        if m.type_name == "msk.DeviceStatus" and (s := m.decode()).kind == "node" and s.device_id == "estimator"
    ]
