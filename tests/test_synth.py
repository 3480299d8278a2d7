"""Synthetic sessions: determinism, truth consistency, EMG recovery through the project's EMG chain, IMU, exports."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import piqp
import pytest

from msk_core.errors import ConfigError
from msk_core.model import load_pack
from msk_core.model.pack import available_packs
from msk_core.signal.emg import EmgFilterConfig, envelope_causal, envelope_group_delay_s
from msk_core.signal.reps import REST_PHASE
from msk_core.synth import Exercise, SynthConfig, generate_exercise, generate_session, parse_effects
from msk_core.synth.files import EmgOutput, write_session

# The exercise packs are compiled from OpenSim by the model work; the smaller packs stand in until they ship.
PACKS = {
    Exercise.BENCH_PRESS: "bench_press" if "bench_press" in available_packs() else "arm26",
    Exercise.DEADLIFT: "deadlift" if "deadlift" in available_packs() else "lumbar_lift",
}
LIGHT = {Exercise.BENCH_PRESS: (20.0,), Exercise.DEADLIFT: (35.0,)}
if PACKS[Exercise.BENCH_PRESS] == "arm26":
    LIGHT[Exercise.BENCH_PRESS] = (0.0,)  # arm26's shoulder muscles cannot hold a bar at 80° elevation


def small_config(**kw) -> SynthConfig:
    return SynthConfig(n_reps=1, loads_kg=LIGHT, **kw)


@pytest.fixture(scope="module")
def deadlift():
    return generate_exercise(Exercise.DEADLIFT, small_config(), pack=PACKS[Exercise.DEADLIFT])


def _all_bytes(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_same_seed_gives_identical_files_and_other_seed_differs(tmp_path):
    from services.sessions.synth_export import write_device_streams, write_mcap

    outputs = []
    for run, seed in (("a", 7), ("b", 7), ("c", 8)):
        cfg = replace(small_config(), subject_seed=seed)
        session = generate_session([Exercise.BENCH_PRESS], cfg, packs=PACKS)
        out = tmp_path / run
        write_session(session, out)
        write_mcap(session, out / "session.mcap")
        write_device_streams(session, out)
        outputs.append(_all_bytes(out))
    a, b, c = outputs
    assert "session.mcap" in a and "truth.json" in a and any(k.endswith("trigno.npz") for k in a)
    assert a.keys() == b.keys()
    for name in a:
        assert a[name] == b[name], name
    assert a["truth.json"] != c["truth.json"]
    assert a["session.mcap"] != c["session.mcap"]


@pytest.fixture(scope="module")
def bench():
    return generate_exercise(Exercise.BENCH_PRESS, small_config(), pack=PACKS[Exercise.BENCH_PRESS])


def test_truth_torques_reproduced_by_true_activations_and_not_static_optimisation(bench, deadlift):
    # deadlift pack 1.0 puts the bar behind the feet (arms locked to the thorax): short ankle peaks exceed the
    # dorsiflexors; those frames are flagged (fallback) and must stay rare
    dl = deadlift.trials[0]
    assert dl.fallback_frames <= 0.1 * dl.time.size
    ok = np.abs(dl.residual).max(axis=1) <= 1e-4 * np.abs(dl.torque_id).max()
    assert ok.sum() >= dl.time.size - dl.fallback_frames
    trial = bench.trials[0]
    pack = load_pack(PACKS[Exercise.BENCH_PRESS])
    scale = np.abs(trial.torque_id).max()
    assert trial.fallback_frames == 0
    assert np.abs(trial.residual).max() < 1e-4 * scale
    assert np.all(trial.activation >= 0) and np.all(trial.activation <= 1)
    # re-evaluate the muscle torque from the stored truth
    for k in range(0, trial.time.size, 37):
        model = pack.moment_arms(trial.q[k]) @ (bench.f_max * trial.activation[k])
        assert np.allclose(model, trial.torque_id[k], atol=1e-4 * scale)
    # static optimisation (min sum a^2, same torques) gives different activations: the truth is not SO by construction
    diffs = []
    for k in range(0, trial.time.size, 10):
        a_mat = pack.moment_arms(trial.q[k]) * bench.f_max[None, :]
        solver = piqp.DenseSolver()
        solver.settings.verbose = False
        n = a_mat.shape[1]
        solver.setup(
            np.asfortranarray(2 * np.eye(n)),
            np.zeros(n),
            A=np.asfortranarray(a_mat),
            b=trial.torque_id[k],
            x_l=np.zeros(n),
            x_u=np.ones(n),
        )
        assert solver.solve() == piqp.PIQP_SOLVED
        diffs.append(solver.result.x - trial.activation[k])
    assert np.sqrt(np.mean(np.square(diffs))) > 0.01


def test_rep_tempo_and_variability(deadlift):
    from msk_core.synth.kinematics import plan_reps

    plan = plan_reps(np.zeros(2), np.ones(2), 3, seed=7, key=("x",))
    ecc = [m.duration for m in plan.moves if m.kind == "eccentric"]
    con = [m.duration for m in plan.moves if m.kind == "concentric"]
    assert all(1.5 <= d <= 2.5 for d in ecc) and all(1.0 <= d <= 1.5 for d in con)
    assert len(set(np.round(ecc, 6))) == 3
    bottoms = [m.q0 for m in plan.moves if m.kind == "bottom"]
    assert not np.allclose(bottoms[0], bottoms[1])
    # qd and qdd are the derivatives of q (1 kHz grid: min-jerk pieces join with a jerk step, so coarser grids blur)
    from msk_core.synth.kinematics import evaluate

    plan = plan_reps(np.zeros(2), np.radians([80.0, -65.0]), 2, seed=7, key=("y",), warp=np.array([-0.15, 0.35]))
    t = np.arange(0.0, plan.duration, 1e-3)
    q, qd, qdd, phase, rep = evaluate(plan, t)
    assert np.abs(np.gradient(q, 1e-3, axis=0) - qd).max() < 1e-3 * np.abs(qd).max()
    assert np.abs(np.gradient(qd, 1e-3, axis=0) - qdd).max() < 1e-2 * np.abs(qdd).max()
    assert np.allclose(q[0], 0.0) and np.allclose(qd[[0, -1]], 0.0)
    assert set(np.unique(rep)) == {-1, 0, 1} and phase.max() < 1.0 and np.all(phase[rep < 0] == -1.0)
    assert deadlift.trials[0].rep_starts.size == 1


def _best_lag(time, truth, envelope, skip=4000):
    """(correlation, lag s) maximising corr(truth delayed by lag, envelope)."""
    lags = np.arange(-0.2, 0.2, 0.0025)
    corr = [np.corrcoef(np.interp(time - lag, time, truth)[skip:], envelope[skip:])[0, 1] for lag in lags]
    best = int(np.argmax(corr))
    return corr[best], lags[best]


@pytest.mark.parametrize("emd", [0.0, 0.06])
def test_emg_generator_through_project_chain_recovers_activation(emd):
    """Rep-like activation bursts -> raw EMG (generator) -> causal chain (msk_core.signal.emg) -> MVC-normalised envelope."""
    from msk_core.synth.emg import mvc_drive, raw_emg
    from msk_core.synth.subject import make_subject

    rate = 2000.0
    chain = EmgFilterConfig(rate_hz=rate)
    channels = ["Gmax", "ESL"]
    subject = make_subject(7, channels, channels)
    t = np.arange(0.0, 12.0, 1 / rate)
    burst = np.clip(np.sin(2 * np.pi * t / 4.0), 0.0, None) ** 2  # one lift every 4 s
    truth = np.column_stack([0.03 + 0.6 * burst, 0.05 + 0.4 * np.roll(burst, 800)])
    drive = np.column_stack([np.interp(t + emd, t, truth[:, k]) for k in range(2)])  # EMG leads force by the EMD
    emg = raw_emg(
        t,
        drive,
        channels,
        subject.emg_gain_uv,
        subject.noise_floor_uv,
        rate_hz=rate,
        seed=7,
        key=("t",),
        artefact_times=np.array([4.0, 8.0]),
    )
    mvc_t, mvc = mvc_drive(channels, rate, seed=7)
    mvc_emg = raw_emg(
        mvc_t, mvc, channels, subject.emg_gain_uv, subject.noise_floor_uv, rate_hz=rate, seed=7, key=("mvc",)
    )
    peak = envelope_causal(mvc_emg, chain).max(axis=0)
    env = envelope_causal(emg, chain) / peak
    expected = envelope_group_delay_s(chain, modulation_hz=0.25) - emd
    for k in range(2):
        corr, lag = _best_lag(t, truth[:, k], env[:, k])
        assert corr > 0.95, (channels[k], corr)
        assert abs(lag - expected) <= 0.015, (channels[k], lag, expected)
        # amplitude: on the activation scale (MVC peak of a noisy envelope reads a little high)
        assert 0.7 < np.percentile(env[:, k], 99) / truth[:, k].max() < 1.3


def test_session_emg_tracks_true_activation(deadlift):
    trial = deadlift.trials[0]
    chain = EmgFilterConfig(rate_hz=2000.0)
    peak = envelope_causal(deadlift.mvc.emg, chain).max(axis=0)
    env = envelope_causal(trial.emg, chain) / peak
    results = []
    for j, ch in enumerate(trial.channels):
        truth = np.interp(trial.emg_time, trial.time, trial.activation[:, trial.groups.index(ch)])
        if np.ptp(truth) >= 0.15:  # sites whose activation changes enough for a correlation to mean something
            results.append(_best_lag(trial.emg_time, truth, env[:, j])[0])
        assert 0.6 < np.percentile(env[:, j], 99) / max(np.percentile(truth, 99), 0.02) < 1.6, ch
    assert results and np.median(results) > 0.75


def test_imu_streams_are_consistent(deadlift):
    from scipy.spatial.transform import Rotation

    trial = deadlift.trials[0]
    assert trial.imu
    for imu in trial.imu:
        rate = 1.0 / (imu.time[1] - imu.time[0])
        assert 60.0 <= rate <= 100.0
        assert np.allclose(np.linalg.norm(imu.orientation, axis=1), 1.0)
        # at rest (first 0.5 s) the accelerometer reads gravity only
        rest = imu.time < 0.5
        assert np.allclose(np.linalg.norm(imu.acceleration[rest], axis=1).mean(), 9.81, atol=0.1)
        # rate of turn agrees with the change of orientation (body frame): R_k^T R_{k+1} ≈ exp(ω dt)
        r = Rotation.from_quat(imu.orientation, scalar_first=True)
        rel = (r[:-1].inv() * r[1:]).as_rotvec() * rate
        moving = np.linalg.norm(imu.rate_of_turn, axis=1)[:-1] > 0.5
        if moving.any():
            err = np.linalg.norm(rel[moving] - 0.5 * (imu.rate_of_turn[:-1] + imu.rate_of_turn[1:])[moving], axis=1)
            assert np.median(err) < 0.1 * np.median(np.linalg.norm(imu.rate_of_turn[:-1][moving], axis=1)) + 0.05


def test_effects_parse_and_errors():
    e = parse_effects("emd=0.06, fv, damping=1.5,load_misreport")
    assert e.emd == 0.06 and e.fv and e.damping == 1.5 and e.load_misreport == 1.1
    assert parse_effects("") == parse_effects("none") and not parse_effects(None).active()
    for bad, field in (("speed=3", "speed=3"), ("emd=abc", "emd=abc"), ("emd=0.9", "emd=0.9"), ("fv=2", "fv=2")):
        with pytest.raises(ConfigError) as info:
            parse_effects(bad)
        assert field in str(info.value)


def test_hidden_effects_in_truth_and_trial_files(tmp_path):
    from msk_core.estimate.trial import load_trial

    cfg = small_config(effects=parse_effects("load_misreport=1.2,damping=2.0,fl_active,fl_passive,fv,crosstalk=0.2"))
    session = generate_session([Exercise.BENCH_PRESS], cfg, packs=PACKS)
    trial = session.exercises[0].trials[0]
    assert trial.reported_load_kg == pytest.approx(1.2 * trial.load_kg)
    assert not np.allclose(trial.torque_reported, trial.torque_id)  # the lab's ID uses the reported load
    assert np.allclose(trial.torque_muscle - trial.torque_id, 2.0 * trial.qd)
    assert trial.fallback_frames <= 0.1 * trial.time.size
    truth_path = write_session(session, tmp_path, emg_output=EmgOutput.RAW)
    truth = json.loads(truth_path.read_text())
    assert truth["effects_active"] == {
        "load_misreport": 1.2,
        "damping": 2.0,
        "fl_active": True,
        "fl_passive": True,
        "fv": True,
        "crosstalk": 0.2,
    }
    entry = truth["exercises"]["bench_press"]
    assert entry["f_max_n"] == {
        g: pytest.approx(f) for g, f in zip(session.exercises[0].subject.groups, session.exercises[0].f_max)
    }
    data = load_trial(tmp_path / entry["trials"][0]["trial"], load_pack(PACKS[Exercise.BENCH_PRESS]))
    assert data.load_kg == pytest.approx(trial.reported_load_kg)
    assert np.allclose(data.q, trial.q[: data.q.shape[0]])
    assert np.allclose(data.torques, trial.torque_reported[: data.q.shape[0]], atol=1e-9)
    assert set(data.emg) == set(trial.channels)
    # raw EMG in the file, made an MVC-normalised envelope by the loader: on the activation scale
    j = trial.channels[int(np.argmax(trial.activation[:, [trial.groups.index(c) for c in trial.channels]].max(0)))]
    assert 0.4 < np.nanmax(data.emg[j]) / trial.activation[:, trial.groups.index(j)].max() < 2.0


def test_mcap_export_topics_and_emg_chunks(tmp_path):
    from services.sessions.synth_export import EMG_CHUNK, write_mcap
    from services.transport import messages
    from services.transport.mcap_io import read_messages

    session = generate_session([Exercise.DEADLIFT], small_config(), packs=PACKS)
    trial = session.exercises[0].trials[0]
    path = write_mcap(session, tmp_path / "s.mcap", session_name="demo")
    by_topic: dict[str, list] = {}
    for m in read_messages(path):
        by_topic.setdefault(m.topic, []).append(m)
    assert "msk/demo/joints" in by_topic and "msk/demo/load" in by_topic
    loads = [m.decode() for m in by_topic["msk/demo/load"]]
    assert [x.barbell_mass_kg for x in loads] == [trial.reported_load_kg, 0.0] and loads[0].exercise == "deadlift"
    joints = [m.decode() for m in by_topic["msk/demo/joints"]]
    assert len(joints) == trial.time.size and list(joints[0].coordinates) == trial.coordinates
    assert np.allclose([j.q[0] for j in joints], trial.q[:, 0])
    chunks = [m.decode() for m in by_topic["msk/demo/emg/trigno-synth"]]
    assert all(c.n_samples == EMG_CHUNK and c.units == "V" for c in chunks)
    index = [c.first_sample_index for c in chunks]
    assert np.all(np.diff(index) == EMG_CHUNK)
    stacked = np.concatenate([np.asarray(c.samples).reshape(c.n_samples, c.n_channels) for c in chunks])
    assert np.allclose(stacked, trial.emg[: stacked.shape[0]].astype(np.float32))
    imu_topics = [t for t in by_topic if "/imu/" in t]
    assert len(imu_topics) == len(trial.imu)
    sample = by_topic[imu_topics[0]][0].decode()
    assert isinstance(sample, messages.ImuSample) and sample.coordinate_frame == "ENU"
    times = [m.log_time_ns for m in read_messages(path)]
    assert times == sorted(times)


def test_device_streams_replay_through_driver_sources(tmp_path):
    from drivers.trigno.source import load_source
    from drivers.xsens.source import load_imu_source
    from services.sessions.synth_export import write_device_streams

    session = generate_session([Exercise.BENCH_PRESS], small_config(), packs=PACKS)
    trial = session.exercises[0].trials[0]
    write_device_streams(session, tmp_path)
    folder = tmp_path / "raw" / trial.name
    src = load_source(folder / "trigno.npz")
    assert src.rate_hz == 2000.0 and np.allclose(src.samples[:, : len(trial.channels)], trial.emg.astype(np.float32))
    raw = np.frombuffer((folder / "trigno_emg.bin").read_bytes(), dtype="<f4").reshape(-1, 16)
    assert np.array_equal(raw[:, : len(trial.channels)], trial.emg.astype(np.float32))
    for imu in trial.imu:
        cap = load_imu_source(folder / f"xsens_{imu.segment}.bin")
        assert cap.arrays["quaternion"].shape == imu.orientation.shape
        assert np.allclose(cap.arrays["acceleration"], imu.acceleration, atol=1e-4)
        assert np.allclose(cap.arrays["quaternion"], imu.orientation, atol=1e-6)


def test_cli_writes_session_and_reports_bad_input(tmp_path, capsys):
    from services.cli import main

    out = tmp_path / "cli"
    args = [
        "synth",
        "--exercise",
        "deadlift",
        "--reps",
        "1",
        "--loads",
        "35",
        "--quiet",
        "--out",
        str(out),
        "--effects",
        "emd=0.05",
        "--pack",
        f"deadlift={PACKS[Exercise.DEADLIFT]}",
    ]
    assert main(args) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["effects_active"] == {"emd": 0.05}
    assert (out / "session.mcap").stat().st_size > 0 and (out / "deadlift" / "deadlift_35kg" / "trial.toml").is_file()
    assert main(["synth", "--exercise", "deadlift", "--effects", "bogus", "--out", str(out)]) != 0
    assert "bogus" in capsys.readouterr().err


def test_muscle_effects_and_crosstalk_change_the_truth_in_the_expected_direction():
    from msk_core.synth.effects import active_force_length, force_velocity, passive_force_length

    # curve sanity: optimum at l̃ = 1, no passive force below slack, fv = 1 isometric, < 1 shortening, > 1 lengthening
    assert active_force_length(np.array([1.0]))[0] == 1.0 and active_force_length(np.array([0.6]))[0] < 0.5
    assert passive_force_length(np.array([0.9]))[0] == 0.0 and passive_force_length(np.array([1.6]))[
        0
    ] == pytest.approx(1.0)
    fv = force_velocity(np.array([0.0, 0.2, -0.2]))
    assert fv[0] == 1.0 and fv[1] < 1.0 < fv[2] < 1.8
    base = generate_exercise(Exercise.BENCH_PRESS, small_config(), pack=PACKS[Exercise.BENCH_PRESS])
    weak = generate_exercise(
        Exercise.BENCH_PRESS, small_config(effects=parse_effects("fl_active")), pack=PACKS[Exercise.BENCH_PRESS]
    )
    a0, a1 = base.trials[0].activation, weak.trials[0].activation
    # same torques from force-length-scaled muscles need more activation overall
    assert a1.sum() > 1.02 * a0.sum()
    assert np.array_equal(base.trials[0].torque_id, weak.trials[0].torque_id)
    mixed = generate_exercise(
        Exercise.BENCH_PRESS, small_config(effects=parse_effects("crosstalk=0.3")), pack=PACKS[Exercise.BENCH_PRESS]
    )

    def neighbour_corr(ex):
        env = envelope_causal(ex.trials[0].emg, EmgFilterConfig(rate_hz=2000.0))
        return np.mean([np.corrcoef(env[:, k], env[:, k + 1])[0, 1] for k in range(env.shape[1] - 1)])

    assert neighbour_corr(mixed) > neighbour_corr(base) + 0.05


def test_mvc_blocks_are_isometric_trials_with_dynamometer_torques(bench, tmp_path):
    """Each MVC block is one site's maximal contraction in its test position; the torques are the muscles' (true
    F_max, true activations of every group) and the written isometric trial loads as such."""
    import itertools

    from msk_core.estimate.trial import load_trial

    pack = load_pack(PACKS[Exercise.BENCH_PRESS])
    mvc = bench.mvc
    assert mvc.poses.shape == (len(mvc.channels), len(pack.coordinates))
    lo, hi = pack.coordinate_ranges[:, 0], pack.coordinate_ranges[:, 1]
    for k, ch in enumerate(mvc.channels):
        sl = mvc.block(k)
        assert np.all(mvc.poses[k] >= lo) and np.all(mvc.poses[k] <= hi)
        g = pack.groups.index(ch)
        # the target group is the most active, at MVC level; the others co-contract
        peak = mvc.activation[sl].max(axis=0)
        assert peak[g] > 0.95 and np.all(np.delete(peak, g) < 0.3)
        torque = mvc.activation[sl] @ (pack.moment_arms(mvc.poses[k]) * bench.f_max[None, :]).T
        assert np.allclose(torque, mvc.torque[sl], atol=1e-9)

        # the test position: no pose of the 5-per-coordinate grid over the inner 80 % of the ranges gives the target
        # a larger share of a coordinate's reference capacity (brute force over the grid)
        def share(q: np.ndarray, g: int = g) -> float:
            return float(
                np.max(
                    np.abs(pack.moment_arms(q)[:, g])
                    * pack.f_max_ref[g]
                    / (np.abs(pack.moment_arms(q)) @ pack.f_max_ref)
                )
            )

        grid = itertools.product(*[np.linspace(a + 0.1 * (b - a), b - 0.1 * (b - a), 5) for a, b in zip(lo, hi)])
        assert share(mvc.poses[k]) >= max(share(np.array(q)) for q in grid) - 1e-12
    truth = json.loads(
        write_session(generate_session([Exercise.BENCH_PRESS], small_config(), packs=PACKS), tmp_path).read_text()
    )
    entries = truth["exercises"]["bench_press"]["isometric_trials"]
    assert [e["channel"] for e in entries] == mvc.channels
    trial = load_trial(tmp_path / entries[0]["trial"], pack)
    assert trial.isometric and np.all(trial.rep_index == -1) and np.all(trial.phase == REST_PHASE)
    assert np.allclose(trial.q, trial.q[0]) and set(trial.emg) == set(mvc.channels)
    from msk_core.signal.emg import windowed_peak

    target = trial.emg[entries[0]["channel"]]  # the block is the normalisation reference of its own channel:
    assert windowed_peak(target[:, None], 25)[0] == pytest.approx(1.0, abs=0.02)  # its highest 0.5 s mean is 1
    assert np.abs(trial.torques).max() == pytest.approx(max(entries[0]["peak_abs_torque_nm"].values()), rel=0.02)


def test_isometric_trials_with_raw_emg_load_as_the_envelope_version(tmp_path):
    """With raw EMG written (2000 Hz slices of the MVC recording), the loader's offline envelope of an isometric trial
    matches the written-envelope version: the same normalisation reference either way."""
    from msk_core.estimate.trial import load_trial

    pack = load_pack(PACKS[Exercise.BENCH_PRESS])
    session = generate_session([Exercise.BENCH_PRESS], small_config(), packs=PACKS)
    loaded = {}
    for mode in (EmgOutput.ENVELOPE, EmgOutput.RAW):
        truth = json.loads(write_session(session, tmp_path / mode.value, emg_output=mode).read_text())
        entry = truth["exercises"]["bench_press"]["isometric_trials"][0]
        loaded[mode] = load_trial(tmp_path / mode.value / entry["trial"], pack)
    env, raw = loaded[EmgOutput.ENVELOPE], loaded[EmgOutput.RAW]
    assert raw.isometric and set(raw.emg) == set(env.emg)
    for g in env.emg:  # the raw slice's envelope differs only at the slice's first samples (filter start-up)
        assert np.nanmax(np.abs(raw.emg[g][10:] - env.emg[g][10:])) < 0.01, g
