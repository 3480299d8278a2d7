"""The one node runtime (services/nodes/node_runtime.py): what it refuses and why, over real Zenoh sessions; order, drain at
stop, status counts; and a subscription the node's role may not make is said at once."""

from __future__ import annotations

import time

import pytest
import zenoh

from services.nodes.node_runtime import DropReason, NodeInputs, Rejected, StatusReporter, check_payload
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, encoding_for, open_session

KEY = topics.joints_key("rt")


def _joints(q: float) -> messages.JointAngles:
    return messages.JointAngles(coordinates=["elbow"], q=[q], device_time_ns=int(q * 1e9) + 1)


@pytest.mark.parametrize(
    "payload, encoding, reason",
    [
        (bytes(range(256)) * 8, None, DropReason.UNDECODABLE),
        (b"", None, DropReason.INVALID),
        (messages.encode(messages.JointAngles(coordinates=["a", "b"], q=[1.0])), None, DropReason.INVALID),
        (
            messages.encode(messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press")),
            "msk.LoadEvent",
            DropReason.WRONG_TYPE,
        ),
        (b"\x00" * 100, None, DropReason.OVERSIZED),
    ],
)
def test_check_payload_says_why_it_refuses(payload, encoding, reason):
    with pytest.raises(Rejected) as refused:
        check_payload(KEY, payload, encoding_type=encoding, max_bytes=99 if reason is DropReason.OVERSIZED else 1 << 20)
    assert refused.value.reason is reason and KEY in str(refused.value)


def test_check_payload_refuses_other_types_bytes_and_unknown_keys():
    frame = messages.encode(messages.EmgEnvelope(time_s=1.0, groups=["a"], envelope=[0.5], device_time_ns=1))
    with pytest.raises(Rejected) as refused:
        check_payload(topics.load_key("rt"), frame)  # decodes field by field into a LoadEvent, with foreign fields
    assert refused.value.reason in (DropReason.WRONG_TYPE, DropReason.UNDECODABLE)
    with pytest.raises(Rejected) as refused:
        check_payload("msk/rt/nowhere", messages.encode(_joints(1.0)))
    assert refused.value.reason is DropReason.UNKNOWN_KEY
    assert check_payload(KEY, messages.encode(_joints(1.0))).q == [1.0]


def test_inputs_drop_and_count_bad_messages_keep_order_and_drain_at_close(zenoh_endpoint):
    with (
        open_session(ZenohOptions(listen=(zenoh_endpoint,))) as node_session,
        open_session(ZenohOptions(connect=(zenoh_endpoint,))) as sender,
    ):
        inputs = NodeInputs(node_session, "probe", max_payload_bytes=1 << 20)
        inputs.subscribe(KEY)
        reporter = StatusReporter(node_session, "rt", "probe", inputs)
        status: list[messages.DeviceStatus] = []
        watcher = sender.declare_subscriber(
            topics.status_key("rt", "probe"),
            lambda s: status.append(messages.decode("msk.DeviceStatus", s.payload.to_bytes())),
        )
        publisher = sender.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 10
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        bad = [b"", bytes(range(256)) * 8, b"\x01" * (2 << 20)]
        for k in range(5):
            publisher.put(messages.encode(_joints(float(k))), encoding=encoding_for("msk.JointAngles"))
            publisher.put(bad[k % len(bad)])
        publisher.put(
            messages.encode(messages.LoadEvent(barbell_mass_kg=1.0, exercise="bench_press")),
            encoding=encoding_for("msk.LoadEvent"),
        )
        time.sleep(1.0)
        first = inputs.get(2.0)
        inputs.close()
        rest = list(inputs.drain())  # what arrived before close is still handed out, in order
        reporter.tick(force=True)
        reporter.final()
        time.sleep(0.5)
        watcher.undeclare()
    assert [m.message.q[0] for m in [first, *rest]] == [0.0, 1.0, 2.0, 3.0, 4.0]
    dropped = inputs.counts.as_dict()["dropped"][KEY]
    assert dropped == {"invalid": 2, "undecodable": 2, "oversized": 1, "wrong_type": 1}, dropped
    assert status and status[-1].connected is False and status[-1].samples_lost == 6
    assert {(d.reason, d.count) for d in status[-1].dropped} == {
        ("invalid", 2),
        ("undecodable", 2),
        ("oversized", 1),
        ("wrong_type", 1),
    }


def test_a_subscription_the_role_may_not_make_is_said_and_counted(zenoh_endpoint, caplog):
    with open_session(ZenohOptions(listen=(zenoh_endpoint,))) as session:
        inputs = NodeInputs(session, "tablet-probe", role="tablet")
        inputs.subscribe("msk/rt/activations/*")  # allowed to a tablet
        assert inputs.refusals == []
        inputs.subscribe("msk/rt/emg/*")
        reporter = StatusReporter(session, "rt", "tablet-probe", inputs)
        inputs.close()
    assert len(inputs.refusals) == 1 and "role 'tablet'" in inputs.refusals[0] and "msk/rt/emg/*" in inputs.refusals[0]
    assert "refused by the router's access control" in caplog.text
    assert reporter.message().errors == 1 and "msk/rt/emg/*" in reporter.message().last_error


def test_load_event_gate_takes_load_events_as_the_estimator_does():
    """Known packs pass; an unknown exercise waits for the frames before any, and is refused once frames name
    others; a frame naming it releases its held events in order; refusals are counted once in a page's inputs."""
    from services.nodes.node_runtime import HELD_LOAD_EVENTS, InputCounts, LoadEventGate

    def event(exercise: str, kg: float = 60.0) -> messages.LoadEvent:
        return messages.LoadEvent(barbell_mass_kg=kg, exercise=exercise)

    gate = LoadEventGate()
    assert gate.offer(event("bench_press")) == [event("bench_press")]
    assert gate.offer(event("")) == [event("")]  # no exercise: the facts of whatever is under way
    # a subject's own pack before its frames: held, in order, until a frame names it
    assert gate.offer(event("ana_bench", 40)) == [] and gate.offer(event("ana_bench", 45)) == []
    assert gate.offer(event("squat")) == []
    # what comes after a held event waits behind it, known or not: the facts keep the estimator's order
    assert gate.offer(event("", 50)) == [] and gate.offer(event("bench_press", 55)) == []
    assert gate.pending == event("bench_press", 55)  # the newest facts, for an operator's mark meanwhile
    assert gate.on_frame("ana_bench") == [
        event("ana_bench", 40),
        event("ana_bench", 45),
        event("", 50),
        event("bench_press", 55),
    ]
    assert gate.refused == 1 and gate.held == [] and gate.pending is None  # "squat": still unknown
    assert gate.on_frame("ana_bench") == []
    assert gate.offer(event("ana_bench", 50)) == [event("ana_bench", 50)]  # named by frames: known
    assert gate.offer(event("deadlift")) == [event("deadlift")]  # a shipped pack: another estimator may run it
    assert gate.offer(event("upper_arm_r")) == [] and gate.refused == 2  # frames came and none named it
    counts = InputCounts()
    gate.count_refused(counts, "msk/s/load")
    gate.count_refused(counts, "msk/s/load")
    assert counts.as_dict()["dropped"] == {"msk/s/load": {"invalid": 2}}
    # held events are bounded: a flood of unknown exercises before the first frame is refused beyond the bound
    flood = LoadEventGate()
    for k in range(HELD_LOAD_EVENTS + 5):
        flood.offer(event(f"x{k}"))
    assert len(flood.held) == HELD_LOAD_EVENTS and flood.refused == 5
    assert flood.on_frame("bench_press") == [] and flood.refused == HELD_LOAD_EVENTS + 5
