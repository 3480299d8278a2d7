"""``msk live --sim`` with four electrode faults injected by the Trigno simulator on four sensors at stated times
(lift-off, 50 Hz hum, saturation, a flat line): through the real drivers and the real estimator, each is flagged on
its electrode within 1 s of its start and cleared within 1 s of its end, with its reason; no clean electrode is
flagged (false alarms counted over the run); the estimator's status says each change as it happens; and the
``assisted`` frames whose EMG instant falls in an electrode's bad stretch carry ``electrode_bad`` and have no measured
envelope for that electrode's muscle (each sensor of the bundled session is its muscle's only electrode), while the
frames outside every bad stretch have all of them.
"""

from __future__ import annotations

import bisect
import json
import math

import pytest

from drivers.trigno.simulator import FaultKind, SensorFault
from msk_core.estimate.live_emg import FLAG_ELECTRODE_BAD, EmgSetup
from msk_core.estimate.profile import SubjectProfile
from services.sessions import live
from services.sessions.live_session import load_session_file
from services.transport.mcap_io import read_messages

FAULTS = (
    SensorFault(2, FaultKind.LIFT_OFF, 2.0, 4.5),
    SensorFault(5, FaultKind.HUM, 3.0, 5.5),
    SensorFault(9, FaultKind.SATURATION, 4.0, 6.5),
    SensorFault(4, FaultKind.FLAT, 5.0, 7.5),
)
RUN_S = 11.0  # the EMG streams from ~0.3 s after the start: every fault has ended and cleared before the stop
REASONS = {
    FaultKind.LIFT_OFF: {"contact: low-frequency artefact", "contact: no signal above the noise floor"},
    FaultKind.HUM: {"mains interference"},
    FaultKind.SATURATION: {"saturation"},
    FaultKind.FLAT: {"flat line"},
}
WITHIN_S = 1.0
MARGIN_S = 0.1  # a frame's EMG instant this far inside (outside) a bad stretch: chunks, the clock mapping, the wait


def channel(fault: SensorFault) -> str:
    return f"trigno/sensor{fault.sensor:02d}.EMG"


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """(summary, the recording's estimator statuses and assisted frames, the subject's EMD)."""
    from services.transport.zenoh_session import free_loopback_endpoint

    tmp = tmp_path_factory.mktemp("quality")
    path = tmp / "quality.toml"
    path.write_text('[session]\nname = "quality"\nout = "out"\nmethods = ["assisted"]\n[trigno]\n[xsens]\n')
    session = load_session_file(path, require_devices=False)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MSK_SESSIONS_DIR", str(tmp / "sessions"))
        summary = live.main(
            session, sim=True, duration_s=RUN_S, view=False, listen=free_loopback_endpoint(), sim_faults=FAULTS
        )
    assert json.loads((session.out / "summary.json").read_text())["electrodes"] == summary["electrodes"]
    statuses, frames = [], []
    for part in summary["recordings"]:
        for m in read_messages(part):
            if m.type_name == "msk.DeviceStatus" and m.topic.endswith("/status/estimator"):
                statuses.append((m.log_time_ns, m.decode()))
            elif m.type_name == "msk.ActivationFrame" and m.topic.endswith("/assisted"):
                frames.append(m.decode())
    emd_s = EmgSetup.from_profile(SubjectProfile.load(session.out / "subject_session.json")).emd_s
    return summary, statuses, frames, emd_s


def test_each_fault_is_flagged_on_its_electrode_and_no_clean_one_is(live_run):
    summary, _, _, _ = live_run
    electrodes = summary["electrodes"]
    assert len(electrodes) == 10, list(electrodes)
    assert summary["simulators_sent"]["trigno"]["faults"] == [f.describe() for f in FAULTS]
    faulty = {channel(f): f for f in FAULTS}
    false_alarms = {
        name: e["recent_episodes"] for name, e in electrodes.items() if name not in faulty and e["episodes"]
    }
    assert not false_alarms, f"{len(false_alarms)} clean electrodes flagged: {false_alarms}"
    for name, fault in faulty.items():
        e = electrodes[name]
        assert e["episodes"] == 1, (name, e["recent_episodes"])
        episode = e["recent_episodes"][0]
        assert fault.start_s < episode["start_s"] <= fault.start_s + WITHIN_S, (name, episode)
        assert episode["end_s"] is not None and fault.end_s < episode["end_s"] <= fault.end_s + WITHIN_S, (
            name,
            episode,
        )
        assert episode["worst"] == "bad" and set(episode["reasons"]) <= REASONS[fault.kind], (name, episode)
        assert e["state"] == "good" and e["bad_s"] > 0.5 * (fault.end_s - fault.start_s), (name, e)
    text = live.summary_text(summary)
    assert "10 judged, 4 with fault episodes" in text and "mains interference 1" in text


def bad_stretches(statuses) -> dict[str, list[tuple[float, float]]]:
    """Per electrode, its bad stretches on the EMG device clock, from the states the estimator published in turn
    (each with ``since_s``, the verdict that gave it)."""
    stretches: dict[str, list[tuple[float, float]]] = {}
    state: dict[str, tuple[str, float]] = {}
    for _, status in statuses:
        for e in status.electrodes:
            name = f"{e.source}/{e.channel}"
            before = state.get(name)
            if before is not None and before[0] == "bad" and e.state != "bad":
                stretches.setdefault(name, []).append((before[1], e.since_s))
            if before is None or before[0] != e.state:
                state[name] = (e.state, e.since_s)
    return stretches


def test_the_status_says_each_change_as_it_happens(live_run):
    summary, statuses, _, _ = live_run
    stretches = bad_stretches(statuses)
    assert set(stretches) == {channel(f) for f in FAULTS}, stretches
    offset_s = summary["clocks"]["emg/trigno"]["offset_ms"] / 1e3  # EMG device time + offset = host instant
    for fault in FAULTS:
        ((start, end),) = stretches[channel(fault)]
        assert fault.start_s < start <= fault.start_s + WITHIN_S and fault.end_s < end <= fault.end_s + WITHIN_S
        # the first status that names the fault is recorded soon after the verdict (published at once, not with
        # the next periodic status, 1 s apart)
        first = min(
            t
            for t, status in statuses
            for e in status.electrodes
            if f"{e.source}/{e.channel}" == channel(fault) and e.reasons
        )
        episode_start = summary["electrodes"][channel(fault)]["recent_episodes"][0]["start_s"]
        delay = first / 1e9 - (episode_start + offset_s)
        assert -0.05 < delay < 0.5, (channel(fault), delay)


def emg_offsets(statuses) -> tuple[list[int], list[float]]:
    """(host times, EMG host offsets in s) of the estimator's statuses: the mapping it applied from each on."""
    times, offsets = [], []
    for _, status in statuses:
        clock = next((c for c in status.clocks if c.source == "emg/trigno"), None)
        if clock is not None:
            times.append(status.host_time_ns)
            offsets.append(clock.offset_ms / 1e3)
    return times, offsets


def test_assisted_frames_leave_a_bad_electrode_out_and_say_so(live_run):
    summary, statuses, frames, emd_s = live_run
    stretches = bad_stretches(statuses)
    times, offsets = emg_offsets(statuses)
    groups = list(frames[0].groups)
    measured = {e["group"] for e in summary["electrodes"].values()}  # the muscles with an electrode
    inside = {name: 0 for name in stretches}
    outside = flagged = 0
    not_left_out, left_out_outside = [], []
    for frame in frames:
        k = bisect.bisect_right(times, frame.publish_ns) - 1  # the EMG mapping the estimator said last
        if k < 0:
            continue
        emg_s = frame.time_s - emd_s - offsets[k]  # the EMG instant the frame read, on the EMG device clock
        envelope = dict(zip(groups, frame.measured_envelope))
        bad_now = [
            name for name, spans in stretches.items() if any(a + MARGIN_S <= emg_s <= b - MARGIN_S for a, b in spans)
        ]
        near_bad = any(a - MARGIN_S <= emg_s <= b + MARGIN_S for spans in stretches.values() for a, b in spans)
        # a frame whose EMG stalled (CPU starved, e.g. beside another test run) read none: nothing to leave out, so
        # no electrode_bad, but no envelope either
        stalled = "emg_gap" in frame.flags or "emg_stalled" in frame.flags
        for name in bad_now:
            group = summary["electrodes"][name]["group"]
            if not math.isnan(envelope[group]) or not (stalled or FLAG_ELECTRODE_BAD in frame.flags):
                not_left_out.append((name, round(emg_s, 3), list(frame.flags), envelope[group]))
            inside[name] += 1
        flagged += bool(bad_now)
        if not near_bad and "emg_gap" not in frame.flags and "emg_stalled" not in frame.flags and emg_s > 1.0:
            if FLAG_ELECTRODE_BAD in frame.flags or not all(math.isfinite(envelope[g]) for g in measured):
                left_out_outside.append((round(emg_s, 3), list(frame.flags), envelope))
            outside += 1
    assert not not_left_out, f"{len(not_left_out)} frames in a bad stretch used the electrode: {not_left_out[:5]}"
    assert not left_out_outside, f"{len(left_out_outside)} frames outside left one out: {left_out_outside[:5]}"
    # every bad stretch (>= 1.5 s each) is covered by frames at ~60 Hz, and so is the time without one
    assert all(n > 60 for n in inside.values()), inside
    assert outside > 100, outside
    assert summary["flags"]["assisted"][FLAG_ELECTRODE_BAD] >= flagged
