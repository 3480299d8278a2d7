"""Zenoh -> dashboard bridge: subscribes to a session's topics and keeps only the newest frame of each.

The bridge takes its inputs through :class:`services.nodes.node_runtime.NodeInputs`: Zenoh callbacks only check the size and
enqueue, the bridge's own thread decodes and checks each message (a malformed one is dropped and counted per topic and
reason, the page shows the counts) and hands it to :meth:`DashboardState.on_message`, which turns it into a small
JSON-ready dict that overwrites the previous one of its topic under a lock. Page connections take what changed since
their last send (:meth:`DashboardState.changes`). A slow page therefore skips frames, it never makes anything queue.
What must not be lost to skipping is counted here, on every message: repetitions (from the phase), per-device
samples, gaps and arrival rate.

Topics (``msk/<session>/...``): ``activations/<method>``, ``joints``, ``load``, ``status/<device>``, ``envelopes``
(when the estimator publishes EMG envelopes), and ``emg/<source>`` / ``imu/<tracker>`` for device health (counted,
not forwarded). Each device is one row under its own id, the one its ``DeviceStatus`` uses: the Trigno base by
``EmgChunk.source_id``, each Xsens tracker by ``ImuSample.tracker_id``. A ``DeviceStatus`` of kind ``node`` is a
node's own status (its dropped inputs), shown apart from the devices; the estimator's carries each EMG electrode's
signal quality (``DeviceStatus.electrodes``), forwarded as the ``electrodes`` entry: per electrode its muscle group,
state (unknown, good, check, bad), reasons and the verdict in words; and each electrode's fatigue index over the set
(``DeviceStatus.fatigue``), forwarded as the ``fatigue`` entry: median and mean frequency per rep, the median
frequency's slope and the change since the set's first reps.

The page's header comes from the ``session`` entry: exercise, load and athlete, and the display names of the frames'
muscle groups and joints with their units (the pack's, with the session file's ``[names]`` that ``LoadEvent.names``
carries; msk_core.model.names).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field

import zenoh
from google.protobuf import json_format
from google.protobuf.message import Message

from msk_core.errors import ConfigError
from msk_core.estimate.fatigue_verdict import tiring
from msk_core.estimate.flags import flag_text
from msk_core.model.pack import names_for
from msk_core.signal.reps import PhaseRepCounter, joint_movement
from msk_core.signal.sets import SetTracker
from services.nodes.node_runtime import (
    InputCounts,
    LoadEventGate,
    NodeInputs,
    apply_load_event,
    estimates_ended,
    serve,
)
from services.sessions.facts import join_late
from services.sessions.live_session import default_method
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session, publish

log = logging.getLogger(__name__)

HAS_MEASURED_ENVELOPE = "measured_envelope" in messages.ActivationFrame.DESCRIPTOR.fields_by_name
#: Host clocks further apart than this are not a latency (a replayed recording carries its original host times).
MAX_PLAUSIBLE_LATENCY_S = 60.0
#: A device whose last sample is older than this is shown as not delivering.
DEVICE_SILENT_AFTER_S = 1.0
#: The row of the bridge's own inputs among the nodes.
BRIDGE_NODE = "dashboard"
#: The figures of the set under way go to the page at most this often (s) when no set or rep changed.
SETS_EVERY_S = 0.5
#: How long the bridge's thread waits for a message before looking at its stop flag again.
POLL_S = 0.1


def _finite(values) -> list[float | None]:
    """JSON has no NaN: missing values (no electrode, no estimate) become null."""
    return [float(v) if math.isfinite(v) else None for v in values]


def activation_dict(frame: messages.ActivationFrame, arrival_ns: int) -> dict:
    return {
        "method": frame.method,
        "exercise": frame.exercise,
        "time_s": frame.time_s,
        "groups": list(frame.groups),
        "activations": _finite(frame.activations),
        "std": _finite(frame.activation_std),
        "envelope": _finite(frame.measured_envelope) if HAS_MEASURED_ENVELOPE else [],
        "torques": [
            {"coordinate": t.coordinate, "inverse_dynamics_nm": t.inverse_dynamics_nm, "model_nm": t.model_nm}
            for t in frame.torques
        ],
        "phase": frame.phase if frame.HasField("phase") else None,
        "flags": [flag_text(flag) for flag in frame.flags],
        "solver_status": frame.solver_status,
        "estimator_latency_ms": (frame.publish_ns - frame.input_arrival_ns) / 1e6
        if frame.publish_ns and frame.input_arrival_ns
        else None,
        "transport_latency_ms": (arrival_ns - frame.publish_ns) / 1e6 if frame.publish_ns else None,
    }


#: the page's set buttons publish only while the session has sent something this recently (msk set refuses the same
#: way when no msk live runs): a mark after the session ended would be confirmed, and nobody would record it
SET_MARK_QUIET_S = 10.0


class RepCounter:
    """Repetitions over the session, from a phase stream ([0, 1) inside a rep, negative at rest, None unknown),
    counted by :class:`msk_core.signal.reps.PhaseRepCounter` (the rule the session report uses), and the sets with
    their reps by :class:`msk_core.signal.sets.SetTracker` (operator marks, rest detection; the report's sets).
    """

    def __init__(self) -> None:
        self.total = 0
        self.phase: float | None = None
        self.movement: str | None = None  # lifting / lowering / turning inside a rep (msk_core.signal.reps.movement)
        self.time_s: float | None = None  # the newest sample's time
        self.sets = SetTracker()
        self._reps = PhaseRepCounter()

    @property
    def in_set(self) -> int:
        """Reps done in the set under way (0 at rest)."""
        current = self.sets.current
        return len(current.reps) if current is not None else 0

    def new_set(self, number: int = 0) -> None:
        """The operator starts set ``number`` (or the next when 0) now: a rep under way is not counted in it."""
        self.sets.start(self.time_s if self.time_s is not None else 0.0, number)

    def update(self, t: float, phase: float | None) -> None:
        """The phase of the sample at time ``t`` (s, the stream's own clock)."""
        self.phase, self.time_s = phase, t
        self.sets.update(t, phase)
        if self._reps.update(t, phase) is not None:
            self.total += 1

    def end_of_data(self) -> None:
        """No sample follows (the estimator stopped): the rep under way counts if long enough, the set under way ends,
        as in the report."""
        if self._reps.finish() is not None:
            self.total += 1
        self.sets.finish()

    def as_dict(self) -> dict:
        """What the page's header shows: set N and rep n of the set (the rep under way, else the last done), reps
        done in the set and in the session, resting, the time in the set (s) and the phase."""
        status = self.sets.status(self.time_s)
        done = self.sets.sets[-1] if status["resting"] and self.sets.sets else None
        return {
            "in_set": self.in_set,
            # resting after a set ("N done"): its reps, the last one done (the set tracker says 0 at rest)
            "rep": len(done.reps) if done is not None else status["rep"],
            "total": self.total,
            "set": status["set"],
            "resting": status["resting"],
            "time_in_set_s": status["time_in_set_s"],
            "phase": self.phase,
            "movement": self.movement if self.phase is not None and self.phase >= 0 else None,
        }


@dataclass
class DeviceHealth:
    """One device as the bridge sees it: its own status messages and the samples it delivers."""

    kind: str
    segment: str = ""  # an Xsens tracker's body segment (ImuSample.segment), when the driver knows it
    messages: int = 0
    samples: int = 0
    samples_lost: int = 0  # gaps in EmgChunk.first_sample_index; DeviceStatus.samples_lost when larger
    connected: bool | None = None  # from DeviceStatus; None when the device publishes no status
    errors: int = 0
    last_error: str = ""
    last_arrival_ns: int = 0
    latency_ms: float | None = None  # bridge arrival - host_time_ns of the driver's receipt
    _next_index: int | None = None

    def as_dict(self, now_ns: int) -> dict:
        age = (now_ns - self.last_arrival_ns) / 1e9 if self.last_arrival_ns else None
        return {
            "kind": self.kind,
            "segment": self.segment,
            "messages": self.messages,
            "samples": self.samples,
            "samples_lost": self.samples_lost,
            "connected": self.connected,
            "delivering": age is not None and age < DEVICE_SILENT_AFTER_S,
            "age_s": age,
            "errors": self.errors,
            "last_error": self.last_error,
            "latency_ms": self.latency_ms,
        }


def node_dict(status: messages.DeviceStatus) -> dict:
    """A node's own status (``kind = "node"``): running or stopped, inputs taken, inputs dropped (per topic, reason)."""
    return {
        "running": bool(status.connected),
        "received": int(status.samples_received),
        "dropped": sum(int(d.count) for d in status.dropped),
        "drops": [[d.key, d.reason, int(d.count)] for d in status.dropped],
        "errors": int(status.errors),
        "last_error": status.last_error,
    }


def _electrode_names(electrode: messages.ElectrodeQuality | messages.ElectrodeFatigue) -> dict:
    """Which electrode a row of the page is about: its device, channel and muscle group."""
    return {"source": electrode.source, "channel": electrode.channel, "group": electrode.group}


def electrode_dict(electrode: messages.ElectrodeQuality) -> dict:
    """One electrode's signal quality as the page shows it (``ElectrodeQuality``)."""
    return {
        **_electrode_names(electrode),
        "state": electrode.state,
        "reasons": list(electrode.reasons),
        "detail": electrode.detail,
    }


def fatigue_dict(electrode: messages.ElectrodeFatigue) -> dict:
    """One electrode's fatigue index over the set as the page shows it (``ElectrodeFatigue``; null for no value)."""
    return {
        **_electrode_names(electrode),
        "set_number": int(electrode.set_number),
        "median_hz": _finite(electrode.median_hz),
        "mean_hz": _finite(electrode.mean_hz),
        "median_slope_hz_per_rep": _finite([electrode.median_slope_hz_per_rep])[0],
        "median_slope_pct_per_rep": _finite([electrode.median_slope_pct_per_rep])[0],
        "median_change_pct": _finite([electrode.median_change_pct])[0],
        "mean_change_pct": _finite([electrode.mean_change_pct])[0],
        "tiring": tiring(
            list(electrode.median_hz),
            electrode.median_slope_hz_per_rep,
            electrode.median_slope_se_hz_per_rep,
            electrode.median_change_pct,
        ),
    }


def counts_dict(counts: InputCounts, errors: int) -> dict:
    """The bridge's own inputs, in the shape of :func:`node_dict`."""
    drops = counts.drops()
    return {
        "running": True,
        "received": sum(counts.as_dict()["received"].values()),
        "dropped": sum(int(d.count) for d in drops),
        "drops": [[d.key, d.reason, int(d.count)] for d in drops],
        "errors": errors,
        "last_error": "",
    }


def _latency_ms(arrival_ns: int, host_time_ns: int) -> float | None:
    if not host_time_ns:
        return None
    latency = (arrival_ns - host_time_ns) / 1e6
    return latency if abs(latency) < MAX_PLAUSIBLE_LATENCY_S * 1e3 else None


class DashboardState:
    """The newest frame of every topic of one session, plus counters; fed by the bridge's thread, read by pages.

    ``input_counts``: what the bridge's :class:`NodeInputs` took and dropped (shown as the ``dashboard`` node).
    """

    def __init__(self, session: str, input_counts: InputCounts | None = None) -> None:
        self.session = session
        self.prefix = topics.session_prefix(session) + "/"
        self.input_counts = input_counts or InputCounts()
        self._lock = threading.Lock()
        self._seq = 0
        self._latest: dict[str, tuple[int, object]] = {}  # topic (after the prefix) -> (seq, JSON-ready value)
        self._reps = RepCounter()
        self._sets_key: tuple[int, int, int] | None = None  # what the last ``sets`` entry showed
        self._sets_put_ns = 0
        self._joints_have_phase = False
        self._torques: dict[str, float] = {}  # the latest frame's inverse-dynamics torques: lifting or lowering
        self._phase_method: str | None = None  # activation stream counted when the joints carry no phase
        self._methods: list[str] = []  # the methods seen, in order
        self._figures_method: str | None = None  # the default of those: whose frames the sets' figures are of
        self._devices: dict[str, DeviceHealth] = {}
        self._devices_seq = 0
        self._nodes: dict[str, dict] = {}  # node -> node_dict of its newest status
        self._electrodes: dict[str, list[dict]] = {}  # node -> its electrodes' quality (the estimator's status)
        self._fatigue: dict[str, list[dict]] = {}  # node -> its electrodes' fatigue index over the set
        self._load: messages.LoadEvent | None = None
        self._loads = LoadEventGate()  # load events as the estimator takes them
        self._frame_exercise = ""  # ActivationFrame.exercise of the newest frame: the exercise when no LoadEvent came
        self._frame_groups: tuple[str, ...] = ()  # the newest frame's groups: whose display names the page shows
        self._names: dict[str, str] = {}  # the session file's display names (LoadEvent.names), kept until others come
        self.last_data_ns = 0  # arrival of the newest data sample (activations, joints, devices)
        self.last_activation_ns = 0  # arrival of the newest activation frame: what the page is about
        self.received = 0
        self.errors = 0  # messages that passed the checks but could not be shown (logged by the bridge)

    def announce_exercise(self, exercise: str) -> None:
        """The exercise the session announces it estimates (``msk live``'s pack), for the notice of a page that starts
        while the estimator is paused (:meth:`LoadEventGate.paused_notice`)."""
        with self._lock:
            self._loads.session_exercise = exercise

    # ---- input (the bridge's thread) ---------------------------------------------------------------------------
    def on_message(self, key: str, message: Message, arrival_ns: int | None = None) -> None:
        """One checked message of ``key`` (its topic's type, :func:`services.nodes.node_runtime.check_payload`: so the type
        says the topic)."""
        if not key.startswith(self.prefix):
            return
        rest = key[len(self.prefix) :]
        name = rest.partition("/")[2]
        arrival_ns = arrival_ns or time.time_ns()
        with self._lock:
            self.received += 1
            if isinstance(message, messages.ActivationFrame):
                self._on_activations(rest, message, arrival_ns)
            elif isinstance(message, messages.JointAngles):
                self._on_joints(message, arrival_ns)
            elif isinstance(message, messages.LoadEvent):
                self._apply_loads(key, self._loads.offer(message))
            elif isinstance(message, messages.DeviceStatus):
                self._on_status(name, message)
            elif isinstance(message, (messages.EmgChunk, messages.ImuSample)):
                self._count_device_sample(message, arrival_ns)
            elif isinstance(message, messages.EmgEnvelope):  # the estimator's envelopes: a stream in the health table
                device = self._device("EMG envelopes", "estimator")
                device.messages += 1
                device.samples += 1
                device.last_arrival_ns = self.last_data_ns = arrival_ns
                self._devices_seq = self._next()
                self._put("envelopes", json_format.MessageToDict(message))

    def _on_activations(self, topic: str, frame: messages.ActivationFrame, arrival_ns: int) -> None:
        self._apply_loads(self.prefix + "load", self._loads.on_frame(frame.exercise))
        self._put(topic, activation_dict(frame, arrival_ns))
        self.last_data_ns = self.last_activation_ns = arrival_ns
        if frame.exercise != self._frame_exercise or tuple(frame.groups) != self._frame_groups:
            self._frame_exercise, self._frame_groups = frame.exercise, tuple(frame.groups)
            self._put_session()
        self._phase_method = self._phase_method or frame.method
        if frame.method not in self._methods:
            self._methods.append(frame.method)
            if default_method(self._methods) != self._figures_method:
                self._figures_method = default_method(self._methods)
                self._put_session()  # the page says whose frames the sets' figures are of
        phase = frame.phase if frame.HasField("phase") else None
        if frame.method == self._phase_method:  # the first method's frames: the sets' reps
            self._torques = {t.coordinate: t.inverse_dynamics_nm for t in frame.torques}
            if not self._joints_have_phase:
                self._reps.update(frame.time_s, phase)
                self._put("reps", self._reps.as_dict())
        if frame.method == self._figures_method:  # the sets' figures: the report's method, not the first
            self._reps.sets.add_activations(frame.time_s, phase, frame.groups, frame.activations)
        if frame.method == self._phase_method:
            self._put_sets(arrival_ns)

    def _on_joints(self, joints: messages.JointAngles, arrival_ns: int) -> None:
        self.last_data_ns = arrival_ns
        has_phase = joints.HasField("phase")
        self._joints_have_phase = self._joints_have_phase or has_phase
        self._reps.movement = joint_movement(self._torques, joints.coordinates, joints.qd)
        if has_phase:
            self._reps.update(joints.device_time_ns / 1e9, joints.phase)
            self._put("reps", self._reps.as_dict())
            self._put_sets(arrival_ns)
        self._put(
            "joints",
            {
                "coordinates": list(joints.coordinates),
                "q": _finite(joints.q),
                "phase": joints.phase if has_phase else None,
            },
        )

    def _apply_loads(self, key: str, loads: list[messages.LoadEvent]) -> None:
        """The load events the gate lets through; those it refused are counted as the bridge's invalid inputs."""
        for load in loads:
            self._on_load(load)
        self._loads.count_refused(self.input_counts, key)

    def _on_load(self, load: messages.LoadEvent) -> None:
        """The operator's set marks and set numbers, as :meth:`SetTracker.on_facts` reads them (a new set number or
        a start mark starts a set, a stop mark ends it; a load change within a set does not restart the count)."""
        apply_load_event(self._reps.sets, load)
        self._put("reps", self._reps.as_dict())
        self._put_sets(0)
        if load.names:  # a load event without names (msk load) leaves the session's names in effect
            self._names = dict(load.names)
        self._load = load
        self._put(
            "load",
            {
                "mass_kg": load.barbell_mass_kg,
                "exercise": load.exercise,
                "set_number": int(load.set_number),
                "athlete": load.athlete,
            },
        )
        self._put_session()

    def _put_sets(self, arrival_ns: int) -> None:
        """The ``sets`` entry (every set: number, reps, time under tension, peak and mean per group; the page's table
        of sets) when a set or rep changed, else at most every :data:`SETS_EVERY_S` (the figures of the set under way
        move with every frame); ``arrival_ns`` 0: now."""
        tracker = self._reps.sets
        current = tracker.current
        key = (len(tracker.sets), tracker.number, len(current.reps) if current is not None else -1)
        if key == self._sets_key and arrival_ns and arrival_ns - self._sets_put_ns < SETS_EVERY_S * 1e9:
            return
        self._sets_key, self._sets_put_ns = key, arrival_ns or time.time_ns()
        self._put("sets", [record.as_dict() for record in tracker.sets])

    def _put_session(self) -> None:
        """Exercise (the load event's, else the activation frames'), load and athlete, for the page's header, and the
        display names of the frames' groups and coordinates (of the frames' pack, else the session's exercise)."""
        load = self._load
        exercise = (load.exercise if load is not None else "") or self._frame_exercise
        names = names_for(self._frame_exercise or exercise, self._frame_groups, self._names)
        self._put(
            "session",
            {
                "exercise": exercise or None,
                "load_kg": load.barbell_mass_kg if load is not None else None,
                "athlete": load.athlete if load is not None and load.athlete else None,
                "names": names.as_dict(),
                "set_figures_method": self._figures_method,
                # shown when no estimates arrive: the declared exercise is not the one the estimator estimates
                "paused": self._loads.paused_notice(load.exercise if load is not None else "") or None,
            },
        )

    def _on_status(self, name: str, status: messages.DeviceStatus) -> None:
        if estimates_ended(status):
            self._reps.end_of_data()
            self._put("reps", self._reps.as_dict())
            self._put_sets(0)
        if status.kind == "node":
            self._nodes[status.device_id or name] = node_dict(status)
            self._devices_seq = self._next()
            if status.electrodes or (status.device_id or name) in self._electrodes:
                self._electrodes[status.device_id or name] = [electrode_dict(e) for e in status.electrodes]
                self._put("electrodes", [e for node in sorted(self._electrodes) for e in self._electrodes[node]])
            if status.fatigue or (status.device_id or name) in self._fatigue:
                self._fatigue[status.device_id or name] = [fatigue_dict(f) for f in status.fatigue]
                self._put("fatigue", [f for node in sorted(self._fatigue) for f in self._fatigue[node]])
            return
        device = self._device(status.device_id or name, status.kind)
        device.segment = status.segment or device.segment
        device.connected = bool(status.connected)
        device.samples_lost = max(device.samples_lost, int(status.samples_lost))
        device.errors, device.last_error = int(status.errors), status.last_error
        self._devices_seq = self._next()

    def _count_device_sample(self, message: messages.EmgChunk | messages.ImuSample, arrival_ns: int) -> None:
        """A sample of the device that sent it: the Trigno base by ``source_id``, each tracker by ``tracker_id`` (the
        ids their DeviceStatus use; :func:`messages.problems` guarantees both are set)."""
        if isinstance(message, messages.EmgChunk):
            device = self._device(message.source_id, "trigno")
            n = int(message.n_samples)
            if device._next_index is not None and message.first_sample_index > device._next_index:
                device.samples_lost += int(message.first_sample_index - device._next_index)
            device._next_index = int(message.first_sample_index) + n
        else:
            device = self._device(message.tracker_id, "xsens")
            device.segment = message.segment or device.segment
            n = 1
        device.messages += 1
        device.samples += n
        device.last_arrival_ns = arrival_ns
        device.latency_ms = _latency_ms(arrival_ns, message.host_time_ns)
        self.last_data_ns = arrival_ns
        self._devices_seq = self._next()

    def _device(self, device_id: str, kind: str) -> DeviceHealth:
        device = self._devices.get(device_id)
        if device is None:
            device = self._devices[device_id] = DeviceHealth(kind=kind or "device")
        return device

    def _next(self) -> int:
        self._seq += 1
        return self._seq

    def _put(self, topic: str, value: object) -> None:
        self._latest[topic] = (self._next(), value)

    def set_mark_event(self, mark: str) -> messages.LoadEvent:
        """The session fact of the operator's set ``mark`` (the page's buttons), with the facts in effect."""
        from services.sessions.facts import set_mark_event

        if mark not in ("start", "stop"):
            raise ConfigError("must be start or stop", field="mark", value=mark)
        with self._lock:
            load = self._load if self._load is not None else self._loads.pending
            return set_mark_event(load, self._reps.sets.settled[0], mark)

    def count_error(self) -> None:
        with self._lock:
            self.errors += 1

    # ---- output (page connections) -----------------------------------------------------------------------------
    def changes(self, since: int, now_ns: int | None = None) -> tuple[int, dict]:
        """Everything newer than ``since`` as ``{"topics": {...}, "devices": {...}?, "nodes": {...}, ...}`` and the
        sequence to ask next."""
        now_ns = now_ns or time.time_ns()
        with self._lock:
            changed = {topic: value for topic, (seq, value) in self._latest.items() if seq > since}
            update: dict = {"topics": changed}
            if self._devices_seq > since or any(d.last_arrival_ns for d in self._devices.values()):
                update["devices"] = {name: d.as_dict(now_ns) for name, d in self._devices.items()}
            update["nodes"] = dict(self._nodes) | {BRIDGE_NODE: counts_dict(self.input_counts, self.errors)}
            update["data_age_s"] = (now_ns - self.last_data_ns) / 1e9 if self.last_data_ns else None
            update["activation_age_s"] = (now_ns - self.last_activation_ns) / 1e9 if self.last_activation_ns else None
            return self._seq, update


#: what the page reads, under msk/<session>/
TOPIC_FAMILIES = ("activations/**", "status/**", "envelopes", "joints", "load", "emg/**", "imu/**")


@dataclass
class Bridge:
    """The Zenoh side: :class:`NodeInputs` on each topic family of ``msk/<session>/`` and a thread feeding its
    checked messages to a :class:`DashboardState`."""

    options: ZenohOptions
    state: DashboardState
    _session: zenoh.Session | None = None
    _inputs: NodeInputs | None = None
    _thread: threading.Thread | None = None
    _stop: threading.Event = field(default_factory=threading.Event)
    _load_publisher: zenoh.Publisher | None = None  # the operator's set marks (the page's buttons), once used
    _publisher_lock: threading.Lock = field(default_factory=threading.Lock)

    def start(self) -> None:
        self._session = open_session(self.options)
        self._inputs = NodeInputs(self._session, BRIDGE_NODE)
        self.state.input_counts = self._inputs.counts
        # One subscriber per topic family, not one on msk/<s>/**: on the secured network a tablet may read only
        # activations and status, and the router refuses a subscription it cannot grant whole.
        for family in TOPIC_FAMILIES:
            self._inputs.subscribe(f"{self.state.prefix}{family}")
        self.state.announce_exercise(join_late(self._inputs, self.state.session))  # the facts before this page
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, args=(self._inputs,), name="dashboard-bridge", daemon=True)
        self._thread.start()

    def _run(self, inputs: NodeInputs) -> None:
        serve(
            inputs,
            lambda inbound: self._take(inbound.key, inbound.message, inbound.arrival_ns),
            self._stop,
            poll_s=POLL_S,
        )

    def _take(self, key: str, message: Message, arrival_ns: int) -> None:
        try:
            self.state.on_message(key, message, arrival_ns)
        except Exception:  # a message the checks let through must not stop the page; the count shows it
            self.state.count_error()
            log.exception("dashboard bridge: message on %s", key)

    def publish_set_mark(self, mark: str) -> messages.LoadEvent:
        """Publish the operator's set ``mark`` on ``msk/<session>/load`` (the page's buttons, as ``msk set``); the
        bridge reads it back like any session fact. RuntimeError when the bridge is not running."""
        if self._session is None:
            raise RuntimeError("the dashboard's bridge is not running")
        quiet_s = (messages.now_ns() - self.state.last_data_ns) / 1e9 if self.state.last_data_ns else None
        if quiet_s is None or quiet_s > SET_MARK_QUIET_S:  # nobody would record it: msk live has stopped
            heard = "nothing yet" if quiet_s is None else f"nothing for {quiet_s:.0f} s"
            raise RuntimeError(
                f"session {self.state.session!r} sends {heard}: is msk live running? (a set mark goes to its nodes)"
            )
        key = topics.load_key(self.state.session)
        from services.transport.roles import facts_refusal

        reason = facts_refusal(self.options.role, self.state.session)
        if reason is not None:
            raise RuntimeError(f"this dashboard's role cannot mark sets: {reason}")
        event = self.state.set_mark_event(mark)
        with self._publisher_lock:
            if self._load_publisher is None:
                self._load_publisher = declare_data_publisher(self._session, key, "msk.LoadEvent")
            publish(self._load_publisher, event)
        return event

    def stop(self) -> None:
        self._stop.set()
        with self._publisher_lock:
            if self._load_publisher is not None:
                self._load_publisher.undeclare()
                self._load_publisher = None
        if self._inputs is not None:
            self._inputs.close()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        self._inputs = None
        if self._session is not None:
            self._session.close()
            self._session = None
