"""The live estimator node over real Zenoh on loopback: every frame in gives one frame out per method, equal to the
offline estimator, bad frames are published flagged, and a load event changes the hand load."""

from __future__ import annotations

import time

import numpy as np
import pytest

from msk_core.estimate import FrameEstimator
from services.nodes import estimator
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session, publish
from tests.node_helpers import estimator_client, estimator_node, wait_matching
from tests.profile_helpers import phased_profile

model = pytest.importorskip("msk_core.model")


def test_estimator_node_publishes_one_frame_per_input_and_method(zenoh_endpoint):
    pack = model.load_pack("arm26")
    coords = list(pack.coordinates)
    rng = np.random.default_rng(3)
    lo, hi = np.asarray(pack.coordinate_ranges)[:, 0], np.asarray(pack.coordinate_ranges)[:, 1]
    poses = [lo + (hi - lo) * (0.2 + 0.6 * rng.random(len(coords))) for _ in range(40)]
    received: dict[str, list] = {"so": [], "hybrid": []}
    node = estimator_node(zenoh_endpoint, pack="arm26", exercise="arm_curl", session="t", methods=["so", "hybrid"])
    with node as stats, open_session(ZenohOptions(connect=(zenoh_endpoint,))) as session:
        session.declare_subscriber(
            "msk/t/activations/*",
            lambda s: received[str(s.key_expr).rsplit("/", 1)[1]].append(
                messages.decode("msk.ActivationFrame", s.payload.to_bytes())
            ),
        )
        joints_pub = declare_data_publisher(session, topics.joints_key("t"), "msk.JointAngles")
        load_pub = declare_data_publisher(session, topics.load_key("t"), "msk.LoadEvent")
        wait_matching(joints_pub, load_pub)
        publish(load_pub, messages.LoadEvent(barbell_mass_kg=2.0, exercise="arm_curl"))
        # Coordinates deliberately in reverse order: the node maps them by name.
        for i, q in enumerate(poses):
            publish(
                joints_pub,
                messages.JointAngles(
                    coordinates=coords[::-1], q=q[::-1].tolist(), phase=-1.0, device_time_ns=(i + 1) * 10_000_000
                ),
            )
        publish(
            joints_pub,
            messages.JointAngles(coordinates=coords, q=[float("nan")] * len(coords), device_time_ns=999_000_000_000),
        )
        publish(joints_pub, messages.JointAngles(coordinates=["not_a_coordinate"], q=[0.0], device_time_ns=1))
        # Another exercise under way: its frames are skipped, not rejected as errors.
        publish(
            load_pub, messages.LoadEvent(barbell_mass_kg=60.0, exercise="deadlift", device_time_ns=1_000_000_000_000)
        )
        publish(
            joints_pub,
            messages.JointAngles(coordinates=["lumbar_extension"], q=[0.0], device_time_ns=1_000_000_000_001),
        )
        deadline = time.monotonic() + 30
        while min(len(v) for v in received.values()) < len(poses) + 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.2)
    assert stats.other_exercise == 1 and stats.load_events == 2
    assert stats.rejected == 1 and "lack" in stats.last_error and "not_a_coordinate" in stats.last_error
    for method in ("so", "hybrid"):
        frames = received[method]
        assert len(frames) == len(poses) + 1
        offline = FrameEstimator(pack, method=method)
        for frame, q in zip(frames, poses):
            expected = offline.step(q, np.zeros(len(q)), np.zeros(len(q)), hand_load_newton=2.0 * 9.81)
            np.testing.assert_allclose(frame.activations, expected.activations, atol=1e-6)
            assert [t.coordinate for t in frame.torques] == coords
            np.testing.assert_allclose([t.inverse_dynamics_nm for t in frame.torques], expected.torques, rtol=1e-9)
            assert frame.publish_ns >= frame.input_arrival_ns > 0
            # no uncertainty from so's or hybrid's objective: a dashboard showed their 1/sqrt(2) as +-70 % bars
            assert len(frame.activation_std) == 0
        assert [f.time_s for f in frames[:-1]] == pytest.approx([(i + 1) * 0.01 for i in range(len(poses))])
        assert frames[-1].flags == ["invalid_input"] and frames[-1].solver_status == "invalid_input"
    assert stats.flagged.get("invalid_input") == 2  # the NaN frame, once per method
    assert stats.invalid == {"q non-finite": 2}  # and why, as the summary says it


def test_load_events_apply_by_device_time_not_arrival_order():
    timeline = estimator.LoadTimeline(initial_load_kg=0.0)
    assert timeline.at(5) == (0.0, "")
    timeline.add(100, 40.0, "bench_press")
    timeline.add(300, 0.0, "bench_press")
    timeline.add(400, 60.0, "deadlift")
    # Frames that arrive late (through the kinematics node) still get the load that was on the bar at their time.
    assert timeline.at(150) == (40.0, "bench_press")
    assert timeline.at(350) == (0.0, "bench_press")
    assert timeline.at(99) == (0.0, "")
    assert timeline.at(500) == (60.0, "deadlift")
    # An event without a device time applies from the latest frame seen; an event naming no exercise keeps the last one.
    timeline.add(0, 70.0, "")
    assert timeline.at(500) == (70.0, "deadlift") and timeline.at(450) == (60.0, "deadlift")


def _curl_reps(n_reps: int = 3, rate: float = 100.0):
    """Elbow curls: rest, flex to 1.6 rad and back (1.5 s per rep), rest; shoulder still."""
    rest, rep = int(0.8 * rate), int(1.5 * rate)
    elbow = [0.2] * rest
    for _ in range(n_reps):
        elbow += list(0.2 + 1.4 * np.sin(np.pi * np.arange(rep) / rep) ** 2) + [0.2] * rest
    elbow = np.array(elbow)
    return np.arange(elbow.size) / rate, np.column_stack([np.full(elbow.size, 0.3), elbow])


def test_node_fills_the_phase_from_the_profiles_rep_template(zenoh_endpoint, tmp_path):
    from msk_core.estimate import SubjectProfile
    from msk_core.estimate.phase import LivePhase, kinematic_phase, learn_phase_model

    pack = model.load_pack("arm26")
    coords = list(pack.coordinates)
    t, q = _curl_reps()
    phase_model = learn_phase_model("r_elbow_flex", [(t, q[:, 1])])
    profile = phased_profile(pack, phase_model=phase_model)
    path = tmp_path / "subject.json"
    profile.save(path)
    node = estimator_client(
        zenoh_endpoint, "p", pack="arm26", exercise="arm_curl", methods=["proposed"], subject_path=path
    )
    with node as client:
        for ti, qi in zip(t, q):  # no phase field: the node must track it
            publish(
                client.joints,
                messages.JointAngles(coordinates=coords, q=qi.tolist(), device_time_ns=int(round(ti * 1e9))),
            )
        # a message that carries its phase keeps it
        publish(
            client.joints,
            messages.JointAngles(
                coordinates=coords, q=q[0].tolist(), phase=0.25, device_time_ns=int(round((t[-1] + 1.0) * 1e9))
            ),
        )
        client.wait_frames(t.size + 1, 60)
    received = client.frames
    assert len(received) == t.size + 1
    expected = LivePhase(SubjectProfile.load(path).phase_model, coords).process(t, q)
    got = np.array([f.phase for f in received[:-1]])
    np.testing.assert_allclose(got, expected, atol=1e-12)
    assert received[-1].phase == 0.25
    # the tracked phase is the offline rep phase (msk_core.signal.reps) of the same signal: rest between reps, 3 reps
    offline, index = kinematic_phase(t, q[:, 1])
    inside = (index >= 0) & (got >= 0)
    assert np.mean((index >= 0) == (got >= 0)) > 0.85 and np.median(np.abs(got[inside] - offline[inside])) < 0.05
    assert np.all(got[index < 0][:10] == -1.0) and got.max() > 0.9
    # and the estimator used it: the proposed activations follow the prior at that phase, not the pooled prior
    offline_est = FrameEstimator(pack, profile, "proposed")
    for k in (50, 150, 300):
        ref = offline_est.step(q[k], np.zeros(2), np.zeros(2), phase=float(expected[k]))
        np.testing.assert_allclose(received[k].activations, ref.activations, atol=1e-6)


@pytest.mark.parametrize("load_kg", [60000.0, float("nan"), -1.0])
def test_the_estimators_own_load_is_checked_as_msk_loads(load_kg):
    """Found by review: `msk load` and the session file refused 60000 kg, the estimator's own --load-kg did not."""
    from msk_core.errors import ConfigError
    from services.nodes.estimator import EstimatorSettings

    with pytest.raises(ConfigError) as error:
        EstimatorSettings("arm26", "t", initial_load_kg=load_kg)
    assert error.value.field == "--load-kg"
