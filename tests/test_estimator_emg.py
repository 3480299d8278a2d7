"""EMG in the live estimator on the demo session: the streamed envelope equals the offline `msk emg envelope` one, the
node publishes envelopes and measured_envelope beside the estimates, and `assisted` beats `proposed` held out."""

from __future__ import annotations

import subprocess
import sys
import threading
import time as time_module
from pathlib import Path

import numpy as np
import pytest

from msk_core.estimate import FrameEstimator
from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.live_emg import FLAG_GAP, FLAG_NOT_FINITE, FLAG_STALLED, EmgSetup, LiveEmg
from msk_core.estimate.profile import SubjectProfile
from msk_core.io import read_sto, write_sto
from msk_core.signal.emg import EmgFilterConfig, envelope_causal
from msk_core.units import GRAVITY
from services.nodes import estimator
from services.sessions import demo_subject, live_scoring
from services.sessions.graph import Graph, wait_for
from services.transport import messages, topics
from services.transport.mcap_io import read_messages
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"
MCAP = RECORDINGS / "demo_session.mcap"
SESSION = "emgtest"
NODE_SECONDS = 12.0  # of the session streamed through the node
STALL_S = 1.0  # generous: on a loaded 2-core machine delivery may pause for a few 100 ms (stall logic: unit test below)


@pytest.fixture(scope="module")
def profile_path() -> Path:
    return demo_subject.sim_subject("bench_press", lambda _: None)  # msk live --sim's: calibrated once, cached


def session_messages(until_s: float | None = None):
    first = None
    for recorded in read_messages(MCAP):
        first = recorded.log_time_ns if first is None else first
        if until_s is not None and recorded.log_time_ns - first > until_s * 1e9:
            return
        yield recorded


def test_node_streams_envelopes_equal_to_the_offline_chain_and_assisted_frames(zenoh_endpoint, profile_path, tmp_path):
    profile = SubjectProfile.load(profile_path)
    setup = EmgSetup.from_profile(profile)
    inputs = [
        r for r in session_messages(NODE_SECONDS) if r.type_name in ("msk.EmgChunk", "msk.JointAngles", "msk.LoadEvent")
    ]
    chunks = [r.decode() for r in inputs if r.type_name == "msk.EmgChunk"]
    # then the EMG source goes silent while the kinematics go on for STALL_S + 1 s: those frames must say so
    inputs += [
        r
        for r in session_messages(NODE_SECONDS + STALL_S + 1.0)
        if r.type_name == "msk.JointAngles" and r.log_time_ns > inputs[-1].log_time_ns
    ]
    n_joints = sum(r.type_name == "msk.JointAngles" for r in inputs)
    assert len(chunks) > 500 and n_joints > 300
    indices = [(c.first_sample_index, c.n_samples) for c in chunks]
    assert all(a + n == b for (a, n), (b, _) in zip(indices, indices[1:])), "the slice is one contiguous EMG block"

    envelopes, frames = [], {m: [] for m in ("assisted", "proposed")}
    stats = estimator.EstimatorStats()
    with Graph(SESSION, zenoh_endpoint) as graph:
        settings = estimator.EstimatorSettings(
            "bench_press", SESSION, tuple(frames), profile_path, emg=True, emg_stall_s=STALL_S
        )
        graph.add_thread("estimator", estimator.main, settings, stats=stats)
        graph.wait_ready(60)
        with open_session(ZenohOptions(connect=(zenoh_endpoint,))) as zsession:
            lock = threading.Lock()

            def on_envelope(sample):
                with lock:
                    envelopes.append(messages.decode("msk.EmgEnvelope", sample.payload.to_bytes()))

            def on_frame(sample):
                frame = messages.decode("msk.ActivationFrame", sample.payload.to_bytes())
                with lock:
                    frames[frame.method].append(frame)

            subs = [
                zsession.declare_subscriber(topics.envelopes_key(SESSION), on_envelope),
                zsession.declare_subscriber(f"{topics.session_prefix(SESSION)}/activations/*", on_frame),
            ]
            from services.nodes.readiness import wait_for_nodes

            wait_for_nodes(zsession, SESSION, graph.nodes, 30)
            publishers = {}
            for recorded in inputs:
                key = topics.rename_session(recorded.topic, SESSION)
                if key not in publishers:
                    publishers[key] = declare_data_publisher(zsession, key, recorded.type_name)
            # the EMG is on before the first joint frame, as on a rig whose base streams before the trackers: the
            # frames after it must all carry it (a frame before any EMG is flagged stalled, by design)
            first_emg = next(r for r in inputs if r.type_name == "msk.EmgChunk")
            publishers[topics.rename_session(first_emg.topic, SESSION)].put(first_emg.data)
            wait_for("the first EMG chunk", lambda: stats.emg_chunks == 1, lambda: f"{stats.emg_chunks} chunks", 30)
            start_wall, start_log = time_module.monotonic(), inputs[0].log_time_ns
            for recorded in inputs:  # paced at 4x real time: EMG and joints interleave as on a rig, not in a burst
                if recorded is first_emg:
                    continue
                delay = start_wall + (recorded.log_time_ns - start_log) / 4e9 - time_module.monotonic()
                if delay > 0:
                    time_module.sleep(delay)
                publishers[topics.rename_session(recorded.topic, SESSION)].put(recorded.data)
            wait_for(
                "every envelope and frame",
                lambda: len(envelopes) == len(chunks) and all(len(f) == n_joints for f in frames.values()),
                lambda: (
                    f"{len(envelopes)}/{len(chunks)} envelopes, "
                    + ", ".join(f"{m} {len(f)}/{n_joints}" for m, f in frames.items())
                ),
                120,
            )
            for sub in subs:
                sub.undeclare()
    assert stats.emg.gaps == 0 and stats.emg.samples_lost == 0 and stats.emg_chunks == len(chunks)

    # offline: the raw EMG of the same chunks, one .sto, through `msk emg envelope` (causal chain, default band-pass)
    labels = list(chunks[0].channel_labels)
    raw = np.concatenate([np.asarray(c.samples, dtype=float).reshape(c.n_samples, c.n_channels) for c in chunks])
    rate = chunks[0].sample_rate_hz
    time = chunks[0].device_time_ns / 1e9 + np.arange(raw.shape[0]) / rate
    write_sto(tmp_path / "raw.sto", time, labels, raw, name="raw EMG")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "services.cli",
            "emg",
            "envelope",
            str(tmp_path / "raw.sto"),
            "-o",
            str(tmp_path / "env.sto"),
        ],
        check=True,
        capture_output=True,
    )
    offline = read_sto(tmp_path / "env.sto")
    ends = np.cumsum([c.n_samples for c in chunks]) - 1  # each message carries the envelope at its chunk's last row
    groups = list(envelopes[0].groups)
    expected = np.column_stack(
        [
            np.mean(
                [offline.column(ch)[ends] / setup.mvc[ch] for ch, g in setup.channel_group.items() if g == group],
                axis=0,
            )
            for group in groups
        ]
    )
    live = np.array([e.envelope for e in envelopes])
    assert live.shape == expected.shape
    # the .sto text keeps ~8 significant digits of the raw input and the envelope: equal to that precision
    np.testing.assert_allclose(live, expected, rtol=1e-6, atol=1e-12)
    # and to float precision against the same offline chain in memory (the CLI's function, no text round trip)
    in_memory = envelope_causal(raw, EmgFilterConfig(rate_hz=rate))[ends]
    expected = np.column_stack(
        [
            np.mean(
                [in_memory[:, labels.index(ch)] / setup.mvc[ch] for ch, g in setup.channel_group.items() if g == group],
                axis=0,
            )
            for group in groups
        ]
    )
    np.testing.assert_allclose(live, expected, rtol=1e-10, atol=1e-15)
    assert np.allclose([e.time_s for e in envelopes], time[ends])

    # every frame carries the measured envelope beside the estimate: NaN exactly where no electrode
    pack_groups = list(frames["assisted"][0].groups)
    no_electrode = [g for g in pack_groups if g not in set(setup.channel_group.values())]
    assert sorted(no_electrode) == ["BRA", "BicSho", "PMCos"]
    emg_end_s = time[-1]
    covered = [f for f in frames["assisted"] if time[0] + 0.05 <= f.time_s <= emg_end_s]  # before: no EMG yet
    assert len(covered) > 300
    for frame in covered:
        env = np.array(frame.measured_envelope)
        assert env.shape == (len(pack_groups),)
        assert all(np.isnan(env[pack_groups.index(g)]) for g in no_electrode)
        assert np.all(np.isfinite(np.delete(env, [pack_groups.index(g) for g in no_electrode]))), (
            frame.flags,
            frame.time_s,
            time[0],
            emg_end_s,
            covered.index(frame),
        )
        assert not frame.flags and len(frame.activation_std) == len(pack_groups)
    # after the EMG's end the frames say so (stalled), and carry no stale envelope
    after = [f for f in frames["assisted"] if f.time_s > emg_end_s + STALL_S + 0.01]
    assert len(after) > 10 and all("emg_stalled" in f.flags and np.all(np.isnan(f.measured_envelope)) for f in after)
    assert stats.emg_flags.get("emg_stalled", 0) >= len(after)


def test_live_emg_flags_gaps_and_stalls_and_counts_lost_samples():
    setup = EmgSetup({"a": "G1", "b": "G2", "c": "G2"}, {"a": 1.0, "b": 2.0}, emd_s=0.0)
    live = LiveEmg(["G1", "G2", "G3"], setup)
    rng = np.random.default_rng(0)
    rate, n = 2000.0, 27
    t_ns = lambda i: int(round(i * 1e9 / rate))  # noqa: E731
    env, flags = live.at(0, 0)
    assert FLAG_STALLED in flags and np.all(np.isnan(env))  # configured electrodes, no EMG yet
    index = 0
    for _ in range(200):
        block = live.add_chunk(
            RawEmgChunk("s", ["a", "b", "c"], rate, index, t_ns(index), rng.normal(size=(n, 3))), t_ns(index)
        )
        index += n
    assert block.groups == ["G1", "G2"] and "no_mvc" in block.flags  # channel c has no MVC: left out, said so
    assert live.counters.no_mvc_channels == ["c"]
    env, flags = live.at(t_ns(index - 100), t_ns(index))
    assert np.all(np.isfinite(env[:2])) and np.isnan(env[2]) and FLAG_GAP not in flags and FLAG_STALLED not in flags
    # 1000 samples never arrive: counted, the chunk flagged, and frames just after it flagged (filter restarting)
    index += 1000
    block = live.add_chunk(
        RawEmgChunk("s", ["a", "b", "c"], rate, index, t_ns(index), rng.normal(size=(n, 3))), t_ns(index)
    )
    assert FLAG_GAP in block.flags and live.counters.gaps == 1 and live.counters.samples_lost == 1000
    env, flags = live.at(t_ns(index + 10), t_ns(index + 27))
    assert FLAG_GAP in flags and np.all(np.isnan(env))
    # a re-sent chunk: its rows are dropped as duplicates, not filtered twice
    assert (
        live.add_chunk(
            RawEmgChunk("s", ["a", "b", "c"], rate, index, t_ns(index), rng.normal(size=(n, 3))), t_ns(index)
        )
        is None
    )
    assert live.counters.duplicates == n
    # the source stops: frames 0.3 s later on the host clock are flagged stalled, never given stale EMG
    env, flags = live.at(t_ns(index + 27) + int(0.3e9), t_ns(index + 27) + int(0.3e9))
    assert FLAG_STALLED in flags and np.all(np.isnan(env))


def test_assisted_beats_proposed_on_groups_without_an_electrode_held_out(profile_path):
    """Streaming over the held-out trial (recorded joints, live causal EMG), scored against the generator's truth."""
    profile = SubjectProfile.load(profile_path)
    estimators = {m: FrameEstimator("bench_press", subject=profile, method=m) for m in ("proposed", "assisted")}
    groups = estimators["proposed"].groups
    live = LiveEmg(groups, EmgSetup.from_profile(profile))
    loads = estimator.LoadTimeline()
    window = next(
        w
        for w in live_scoring.trial_windows([r.decode() for r in read_messages(MCAP) if r.type_name == "msk.LoadEvent"])
        if w.name == "bench_press_50kg"
    )
    mapper = estimator.CoordinateMapper(estimators["proposed"].coordinates)
    times, estimates = [], {m: [] for m in estimators}
    for recorded in read_messages(MCAP):
        if recorded.type_name == "msk.LoadEvent":
            event = recorded.decode()
            loads.add(event.device_time_ns, event.barbell_mass_kg, event.exercise)
        elif recorded.type_name == "msk.EmgChunk":
            c = recorded.decode()
            live.add_chunk(
                RawEmgChunk(
                    c.source_id,
                    c.channel_labels,
                    c.sample_rate_hz,
                    c.first_sample_index,
                    c.device_time_ns,
                    np.asarray(c.samples).reshape(c.n_samples, c.n_channels),
                ),
                recorded.log_time_ns,
            )
        elif recorded.type_name == "msk.JointAngles":
            joints = recorded.decode()
            t = joints.device_time_ns / 1e9
            if not window.start_s <= t <= window.end_s:
                continue
            envelope, _ = live.at(joints.device_time_ns, recorded.log_time_ns)
            load_kg, _ = loads.at(joints.device_time_ns)
            q, qd, qdd = (mapper.take(joints, f) for f in ("q", "qd", "qdd"))
            phase = float(joints.phase) if joints.HasField("phase") else None
            for m, est in estimators.items():
                estimates[m].append(
                    est.step(q, qd, qdd, hand_load_newton=load_kg * GRAVITY, phase=phase, emg=envelope).activations
                )
            times.append(t - window.start_s)
    truth = read_sto(RECORDINGS / "demo" / "bench_press" / "bench_press_50kg" / "truth_activations.sto")
    true = np.column_stack([np.interp(times, truth.time, truth.column(g)) for g in groups])
    no_electrode = [groups.index(g) for g in ("BRA", "BicSho", "PMCos")]
    rmse = {}
    for m, a in estimates.items():
        a = np.array(a)
        ok = np.all(np.isfinite(a), axis=1)
        rmse[m] = {
            "no_electrode": float(np.sqrt(np.mean((a[ok][:, no_electrode] - true[ok][:, no_electrode]) ** 2))),
            "all": float(np.sqrt(np.mean((a[ok] - true[ok]) ** 2))),
        }
    print(f"held-out bench_press_50kg, {len(times)} frames, activation RMSE: {rmse}")
    assert len(times) > 500
    assert rmse["assisted"]["no_electrode"] < rmse["proposed"]["no_electrode"], rmse


def test_a_live_channel_mapped_to_a_profile_electrode_takes_its_group_and_mvc():
    """A hand-started estimator (`--emg-map sensor01.EMG=PMCla`) with a profile calibrated on trial columns: the
    channel takes that electrode's group and MVC (it used to be a bare group without MVC, every frame `no_mvc`); a
    channel mapped to a group the profile has no electrode for has none; the profile's own map is unchanged."""
    import numpy as np

    profile = SubjectProfile(
        "bench_press",
        "1",
        ["PMCla", "DelAnt"],
        np.ones(2),
        np.ones(2),
        emg_normalisation={"PMCla": {"group": "PMCla", "divisor": 0.21}, "delt_a": {"group": "DelAnt", "divisor": 0.3}},
    )
    setup = EmgSetup.from_profile(profile, {"sensor01.EMG": "PMCla", "sensor03.EMG": "delt_a", "sensor09.EMG": "LD"})
    assert setup.channel_group == {"sensor01.EMG": "PMCla", "sensor03.EMG": "DelAnt", "sensor09.EMG": "LD"}
    assert setup.mvc["sensor01.EMG"] == 0.21 and setup.mvc["sensor03.EMG"] == 0.3 and "sensor09.EMG" not in setup.mvc
    assert EmgSetup.from_profile(profile).channel_group == {"PMCla": "PMCla", "delt_a": "DelAnt"}


def test_mapped_channels_no_source_streams_are_counted_and_named_in_the_session_summary():
    """The electrode map names sensor07.EMG, the base streams sensors 1-4: it was estimated without EMG without a
    word. Now the counters the estimator logs and prints at its stop, and msk live's summary, name it."""
    from services.sessions.live import summary_text

    setup = EmgSetup(
        {"sensor01.EMG": "G1", "sensor07.EMG": "G2"}, {"sensor01.EMG": 1.0, "sensor07.EMG": 1.0}, emd_s=0.0
    )
    live_emg = LiveEmg(["G1", "G2"], setup)
    labels = [f"sensor{k:02d}.EMG" for k in range(1, 5)]
    live_emg.add_chunk(RawEmgChunk("trigno", labels, 2000.0, 0, 0, np.zeros((27, 4))), 0)
    assert live_emg.counters.missing_channels == ["sensor07.EMG"]
    live_emg.add_chunk(RawEmgChunk("other", ["sensor07.EMG"], 2000.0, 0, 0, np.zeros((27, 1))), 0)
    assert live_emg.counters.missing_channels == []  # a second source streams it
    summary = {
        "duration_s": 20.0,
        "samples": {},
        "samples_lost": {},
        "joint_frames": 0,
        "envelopes": 0,
        "frames_estimated": {},
        "flags": {},
        "electrodes_never_streamed": {"sensor07.EMG": "TriLong"},
    }
    said = summary_text({**summary, "samples": {"emg/trigno": 40_000}})
    assert (
        "electrodes never streamed (their sensors not paired or not on, or a wrong channel in [electrodes]; their"
        in said
    )
    assert "estimated without EMG): sensor07.EMG (TriLong)" in said
    # no EMG at all (a silent EMG port, found by an independent base imitation): not blamed on pairing
    assert "electrodes never streamed (no EMG arrived from the Trigno at all: see its line" in summary_text(summary)


def test_a_sample_that_is_not_a_number_is_counted_and_does_not_hold_the_envelope_at_nan():
    """A base that sent one NaN (or inf): the filter carried it on, so that channel's envelope stayed NaN for the rest
    of the session (still NaN 27 s later in the QA run)."""
    setup = EmgSetup({"a": "G1", "b": "G2"}, {"a": 1.0, "b": 1.0}, emd_s=0.0)
    live = LiveEmg(["G1", "G2"], setup)
    rng = np.random.default_rng(1)
    rate, n = 2000.0, 27
    t_ns = lambda i: int(round(i * 1e9 / rate))  # noqa: E731
    index = 0
    for k in range(100):
        samples = rng.normal(size=(n, 2))
        if k == 20:
            samples[3, 0], samples[4, 1] = np.nan, np.inf
        block = live.add_chunk(RawEmgChunk("s", ["a", "b"], rate, index, t_ns(index), samples), t_ns(index))
        if k == 20:
            assert FLAG_NOT_FINITE in block.flags
        index += n
    assert live.counters.not_finite_samples == 2
    env, _ = live.at(t_ns(index - 10), t_ns(index))
    assert np.all(np.isfinite(env)) and np.all(env > 0)
