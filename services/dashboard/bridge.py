"""Zenoh -> dashboard bridge: subscribes to a session's topics and keeps only the newest frame of each.

Zenoh callbacks decode each sample into a small JSON-ready dict and overwrite the previous one of its topic under a
lock; page connections take what changed since their last send (:meth:`DashboardState.changes`). A slow page therefore
skips frames, it never makes anything queue. What must not be lost to skipping is counted here, on every sample:
repetitions (from the phase), per-device samples, gaps and arrival rate.

Topics (``msk/<session>/...``): ``activations/<method>``, ``joints``, ``load``, ``status/<device>``, ``envelopes``
(when the estimator publishes EMG envelopes), and ``emg/<source>`` / ``imu/<tracker>`` for device health
(counted, not forwarded). ``ActivationFrame.measured_envelope`` is read only when the schema has that field.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field

import zenoh
from google.protobuf import json_format
from google.protobuf.message import DecodeError

from msk_core.errors import MskError
from services import messages, topics
from services.schemas import msk_pb2
from services.zenoh_session import ZenohOptions, open_session, type_name_of_sample

log = logging.getLogger(__name__)

HAS_MEASURED_ENVELOPE = "measured_envelope" in messages.ActivationFrame.DESCRIPTOR.fields_by_name
#: Host clocks further apart than this are not a latency (a replayed recording carries its original host times).
MAX_PLAUSIBLE_LATENCY_S = 60.0
#: A device whose last sample is older than this is shown as not delivering.
DEVICE_SILENT_AFTER_S = 1.0


def _message_class(type_name: str | None):
    """The generated class of ``msk.<Type>``, also for types newer than :data:`messages.MESSAGE_TYPES` (e.g. EmgEnvelope)."""
    if not type_name:
        return None
    if type_name in messages.MESSAGE_TYPES:
        return messages.MESSAGE_TYPES[type_name]
    package, _, name = type_name.rpartition(".")
    if package != "msk" or name not in msk_pb2.DESCRIPTOR.message_types_by_name:
        return None
    return getattr(msk_pb2, name, None)


def _finite(values) -> list[float | None]:
    """JSON has no NaN: missing values (no electrode, no estimate) become null."""
    return [float(v) if math.isfinite(v) else None for v in values]


def activation_dict(frame, arrival_ns: int) -> dict:
    out = {
        "method": frame.method,
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
        "flags": list(frame.flags),
        "solver_status": frame.solver_status,
        "estimator_latency_ms": (frame.publish_ns - frame.input_arrival_ns) / 1e6 if frame.publish_ns and frame.input_arrival_ns else None,
        "transport_latency_ms": (arrival_ns - frame.publish_ns) / 1e6 if frame.publish_ns else None,
    }
    return out


class RepCounter:
    """Counts repetitions from a phase stream: [0, 1) inside a rep, negative at rest, None unknown.

    A rep ends when the phase leaves a rep for rest, or wraps from late in one rep to early in the next. A new set
    (a load event with a mass) starts the count again; the total over the session is kept.
    """

    def __init__(self) -> None:
        self.in_set = 0
        self.total = 0
        self.sets = 0
        self.phase: float | None = None
        self._previous: float | None = None

    def new_set(self) -> None:
        self.sets += 1
        self.in_set = 0
        self._previous = None

    def update(self, phase: float | None) -> None:
        self.phase = phase
        if phase is None or not math.isfinite(phase):
            self._previous = None
            return
        previous = self._previous
        if previous is not None and previous >= 0.0 and (phase < 0.0 or phase < previous - 0.5):
            self.in_set += 1
            self.total += 1
        self._previous = phase

    def as_dict(self) -> dict:
        return {"in_set": self.in_set, "total": self.total, "set": self.sets, "phase": self.phase}


@dataclass
class DeviceHealth:
    """One device as the bridge sees it: its own status messages and the samples it delivers."""

    kind: str
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
            "kind": self.kind, "messages": self.messages, "samples": self.samples, "samples_lost": self.samples_lost,
            "connected": self.connected, "delivering": age is not None and age < DEVICE_SILENT_AFTER_S,
            "age_s": age, "errors": self.errors, "last_error": self.last_error, "latency_ms": self.latency_ms,
        }


def _latency_ms(arrival_ns: int, host_time_ns: int) -> float | None:
    if not host_time_ns:
        return None
    latency = (arrival_ns - host_time_ns) / 1e6
    return latency if abs(latency) < MAX_PLAUSIBLE_LATENCY_S * 1e3 else None


class DashboardState:
    """The newest frame of every topic of one session, plus counters; safe to feed from Zenoh's threads."""

    def __init__(self, session: str) -> None:
        self.session = session
        self.prefix = topics.session_prefix(session) + "/"
        self._lock = threading.Lock()
        self._seq = 0
        self._latest: dict[str, tuple[int, object]] = {}  # topic (after the prefix) -> (seq, JSON-ready value)
        self._reps = RepCounter()
        self._joints_have_phase = False
        self._phase_method: str | None = None  # activation stream counted when the joints carry no phase
        self._devices: dict[str, DeviceHealth] = {}
        self._devices_seq = 0
        self.last_data_ns = 0  # arrival of the newest data sample (activations, joints, devices)
        self.last_activation_ns = 0  # arrival of the newest activation frame: what the page is about
        self.received = 0
        self.decode_errors = 0

    # ---- input (Zenoh threads) ---------------------------------------------------------------------------------
    def on_sample(self, key: str, type_name: str | None, payload: bytes, arrival_ns: int | None = None) -> None:
        if not key.startswith(self.prefix):
            return
        rest = key[len(self.prefix):]
        arrival_ns = arrival_ns or time.time_ns()
        kind = rest.split("/", 1)[0]
        try:
            type_name = type_name or topics.message_type_for_key(key)
            message_class = _message_class(type_name)
            if message_class is None:
                return
            message = message_class()
            message.ParseFromString(payload)
        except (MskError, DecodeError) as error:
            with self._lock:
                self.decode_errors += 1
            log.warning("%s: %s", key, error)
            return
        with self._lock:
            self.received += 1
            if kind == "activations":
                self._put(rest, activation_dict(message, arrival_ns))
                self.last_data_ns = self.last_activation_ns = arrival_ns
                if not self._joints_have_phase:
                    self._phase_method = self._phase_method or message.method
                    if message.method == self._phase_method:
                        self._reps.update(message.phase if message.HasField("phase") else None)
                        self._put("reps", self._reps.as_dict())
            elif kind == "joints":
                self.last_data_ns = arrival_ns
                has_phase = message.HasField("phase")
                self._joints_have_phase = self._joints_have_phase or has_phase
                if has_phase:
                    self._reps.update(message.phase)
                    self._put("reps", self._reps.as_dict())
                self._put("joints", {"coordinates": list(message.coordinates), "q": _finite(message.q),
                                      "phase": message.phase if has_phase else None})
            elif kind == "load":
                if message.barbell_mass_kg > 0:
                    self._reps.new_set()
                    self._put("reps", self._reps.as_dict())
                self._put("load", {"mass_kg": message.barbell_mass_kg, "exercise": message.exercise})
            elif kind == "status":
                device = self._device(message.device_id or rest.split("/", 1)[-1], message.kind)
                device.connected = bool(message.connected)
                device.samples_lost = max(device.samples_lost, int(message.samples_lost))
                device.errors, device.last_error = int(message.errors), message.last_error
                self._devices_seq = self._next()
            elif kind in ("emg", "imu"):
                self._count_device_sample(kind, rest.split("/", 1)[-1], message, arrival_ns)
            elif kind == "envelopes":  # the estimator's EMG envelopes: shown as a stream in the health table
                device = self._device("EMG envelopes", "estimator")
                device.messages += 1
                device.samples += 1
                device.last_arrival_ns = self.last_data_ns = arrival_ns
                self._devices_seq = self._next()
                self._put("envelopes", json_format.MessageToDict(message))

    def _count_device_sample(self, kind: str, source: str, message, arrival_ns: int) -> None:
        if kind == "emg":
            device = self._device(message.source_id or source, "trigno")
            n = int(message.n_samples)
            if device._next_index is not None and message.first_sample_index > device._next_index:
                device.samples_lost += int(message.first_sample_index - device._next_index)
            device._next_index = int(message.first_sample_index) + n
        else:
            device = self._device("xsens", "xsens")  # one Xsens station carries every tracker
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

    # ---- output (page connections) -----------------------------------------------------------------------------
    def changes(self, since: int, now_ns: int | None = None) -> tuple[int, dict]:
        """Everything newer than ``since`` as ``{"topics": {...}, "devices": {...}?}`` and the sequence to ask next."""
        now_ns = now_ns or time.time_ns()
        with self._lock:
            changed = {topic: value for topic, (seq, value) in self._latest.items() if seq > since}
            update: dict = {"topics": changed}
            if self._devices_seq > since or any(d.last_arrival_ns for d in self._devices.values()):
                update["devices"] = {name: d.as_dict(now_ns) for name, d in self._devices.items()}
            update["data_age_s"] = (now_ns - self.last_data_ns) / 1e9 if self.last_data_ns else None
            update["activation_age_s"] = (now_ns - self.last_activation_ns) / 1e9 if self.last_activation_ns else None
            return self._seq, update


#: what the page reads, under msk/<session>/
TOPIC_FAMILIES = ("activations/**", "status/**", "envelopes", "joints", "load", "emg/**", "imu/**")


@dataclass
class Bridge:
    """The Zenoh side: a subscriber per topic family of ``msk/<session>/`` feeding a :class:`DashboardState`."""

    options: ZenohOptions
    state: DashboardState
    _session: zenoh.Session | None = None
    _subscribers: list = field(default_factory=list)

    def start(self) -> None:
        self._session = open_session(self.options)

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                self.state.on_sample(str(sample.key_expr), type_name_of_sample(sample), sample.payload.to_bytes())
            except Exception:  # a callback must never raise into Zenoh; the count shows it on the page
                log.exception("dashboard bridge: sample on %s", sample.key_expr)

        # One subscriber per topic family, not one on msk/<s>/**: on the secured network a tablet may read only
        # activations and status, and the router refuses a subscription it cannot grant whole.
        for family in TOPIC_FAMILIES:
            self._subscribers.append(self._session.declare_subscriber(f"{self.state.prefix}{family}", on_sample))

    def stop(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers.clear()
        if self._session is not None:
            self._session.close()
            self._session = None
