"""The one node runtime: subscribe, ordered bounded queue, check and decode, status, drain at stop.

Every node (estimator, kinematics, recorder) and every reader (``msk subscribe``, the dashboard bridge, the view)
takes its inputs through :class:`NodeInputs`, so they all treat a bad message alike. A message that is oversized,
does not decode, carries another type than its topic's or fails its type's checks (:func:`messages.problems`) is
counted per topic key and reason, logged once per (key, reason) and dropped; the node goes on with the next one.

Zenoh callbacks only check the size and enqueue (they run on Zenoh's threads and must stay short); decoding happens
on the node's own thread in :meth:`NodeInputs.get`, in arrival order across all of the node's subscriptions. The
queue is bounded: when the node falls behind by :data:`MAX_QUEUE` messages a callback waits (up to
:data:`QUEUE_WAIT_S`, which holds back a lossless publisher, docs/topics.md "Delivery") and then drops and counts
(``queue_full``). At stop, :meth:`NodeInputs.close` undeclares the subscribers and :meth:`NodeInputs.drain` hands out
what had already arrived, so nothing received is lost.

The counts travel in the node's :class:`DeviceStatus` (``kind = "node"``, ``dropped``) on ``msk/<session>/status/<node>``
(:class:`StatusReporter`: at start, every second, and a last one at stop), which the recorder
logs and ``msk live`` sums up in ``summary.json``; so do, for a node that maps device clocks onto the host clock, its
mappings per stream (``clocks``, :func:`clock_offsets`).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from enum import Enum

import zenoh
from google.protobuf.message import Message

from msk_core.signal.host_clock import ClockReport
from services import messages, topics
from services.zenoh_session import declare_data_publisher, fetch_history, publish, type_name_of_sample

log = logging.getLogger(__name__)

#: Largest payload a node takes (bytes). An EMG chunk of 16 channels at 2 kHz is ~4 kB per 30 ms; a replay batching a
#: whole second is 128 kB. 8 MiB leaves room for any real message and keeps a 50 MB blob out of the queue.
MAX_PAYLOAD_BYTES = 8 * 1024 * 1024
MAX_QUEUE = 20_000
QUEUE_WAIT_S = 1.0
STATUS_PERIOD_S = 1.0


class DropReason(str, Enum):
    """Why an input was dropped (the ``reason`` of :class:`messages.InputDrop`)."""

    OVERSIZED = "oversized"
    UNDECODABLE = "undecodable"
    WRONG_TYPE = "wrong_type"
    INVALID = "invalid"
    UNKNOWN_KEY = "unknown_key"
    QUEUE_FULL = "queue_full"


class Rejected(messages.MessageDecodeError):
    """A payload a node cannot use; ``reason`` says which check refused it."""

    def __init__(self, reason: DropReason, key: str, detail: str) -> None:
        self.reason = reason
        self.key = key
        self.detail = detail
        super().__init__(f"{key}: {reason.value}: {detail}")


def check_payload(
    key: str,
    payload: bytes,
    *,
    encoding_type: str | None = None,
    expected_type: str | None = None,
    max_bytes: int = MAX_PAYLOAD_BYTES,
) -> Message:
    """The message ``payload`` carries on ``key``, or :class:`Rejected` saying why it cannot be used.

    ``expected_type``: the type the reader wants (default: the topic table's for ``key``); ``encoding_type``: the type
    the sample's Zenoh encoding names, if any. Protobuf decodes many byte strings without complaint, so a payload
    that decodes is also refused when it carries fields the type does not have (bytes of another type, garbage) or
    fails the type's own checks (an empty JointAngles, an EMG chunk whose sample count does not match its shape).
    """
    if expected_type is None:
        try:
            expected_type = topics.message_type_for_key(key)
        except topics.ConfigError:
            expected_type = None
        if expected_type is None:
            raise Rejected(DropReason.UNKNOWN_KEY, key, "not a topic of docs/topics.md")
    if len(payload) > max_bytes:
        raise Rejected(DropReason.OVERSIZED, key, f"{len(payload)} bytes (at most {max_bytes})")
    if encoding_type is not None and encoding_type != expected_type:
        raise Rejected(DropReason.WRONG_TYPE, key, f"encoded as {encoding_type}, the topic carries {expected_type}")
    try:
        message = messages.decode(expected_type, payload)
    except messages.MessageDecodeError as error:
        raise Rejected(DropReason.UNDECODABLE, key, str(error)) from None
    if messages.has_unknown_fields(message):
        raise Rejected(DropReason.WRONG_TYPE, key, f"{len(payload)} bytes carry fields {expected_type} does not have")
    problems = messages.problems(message)
    if problems:
        raise Rejected(DropReason.INVALID, key, f"{expected_type}: {'; '.join(problems)}")
    return message


def publication_id(sample: zenoh.Sample) -> tuple[str, int, int] | None:
    """(publisher's Zenoh id, entity id, sequence number) of a sample, when Zenoh carries its source info."""
    info = sample.source_info
    if info is None:
        return None
    return str(info.source_id.zid), int(info.source_id.eid), int(info.source_sn)


@dataclass(frozen=True)
class Inbound:
    """One message a node took from its queue."""

    key: str
    type_name: str  # "" when rejected
    message: Message | None  # None when rejected (only with ``NodeInputs(keep_rejected=True)``)
    payload: bytes
    arrival_ns: int
    rejected: Rejected | None = None
    #: the publication's identity (publisher's session, entity, sequence number) when Zenoh carries it (history
    #: publishers: their cache replies carry the same, so a reader knows a publication it got both ways)
    source: tuple[str, int, int] | None = None


@dataclass
class InputCounts:
    """What a node's subscriptions delivered: received and dropped per topic key (thread-safe)."""

    received: Counter = field(default_factory=Counter)  # key -> messages taken
    dropped: Counter = field(default_factory=Counter)  # (key, reason value) -> messages dropped
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def count_received(self, key: str) -> None:
        with self._lock:
            self.received[key] += 1

    def count_dropped(self, key: str, reason: DropReason) -> int:
        with self._lock:
            self.dropped[(key, reason.value)] += 1
            return self.dropped[(key, reason.value)]

    @property
    def total_dropped(self) -> int:
        with self._lock:
            return sum(self.dropped.values())

    def drops(self) -> list[messages.InputDrop]:
        with self._lock:
            return [messages.InputDrop(key=k, reason=r, count=n) for (k, r), n in sorted(self.dropped.items())]

    def as_dict(self) -> dict:
        """``{"received": {key: n}, "dropped": {key: {reason: n}}}`` for summaries and logs."""
        with self._lock:
            dropped: dict[str, dict[str, int]] = {}
            for (key, reason), n in sorted(self.dropped.items()):
                dropped.setdefault(key, {})[reason] = n
            return {"received": dict(self.received), "dropped": dropped}


class NodeInputs:
    """A node's subscriptions with one ordered, bounded queue; see the module docstring.

    ``expected_type``: one type for every key (a reader of one topic); default: each key's type from the topic table.
    ``keep_rejected``: a payload that fails the checks (not an oversized one, never queued) is still handed out, with
    ``message`` None and ``rejected`` saying why, after being counted (the recorder keeps such payloads in a labelled
    channel of their own rather than losing them).
    """

    def __init__(
        self,
        zsession: zenoh.Session,
        node: str,
        *,
        max_payload_bytes: int = MAX_PAYLOAD_BYTES,
        max_queue: int = MAX_QUEUE,
        expected_type: str | None = None,
        keep_rejected: bool = False,
        role: str | None = None,
    ) -> None:
        """``role``: the access-control role the node joined with (``ZenohOptions.role``); a subscription the
        router would refuse to it is said at once (log and :attr:`refusals`), as the router says it only in its
        trace log."""
        self.node = node
        self.role = role
        self.refusals: list[str] = []
        self._keep_rejected = keep_rejected
        self.counts = InputCounts()
        self._zsession = zsession
        self._max_bytes = max_payload_bytes
        self._expected_type = expected_type
        self._queue: queue.Queue = queue.Queue(max_queue)
        self._subscribers: list[zenoh.Subscriber] = []
        self._closed = False

    def subscribe(self, key_expr: str) -> None:
        if self.role is not None:
            from services.security import refused

            reason = refused(self.role, "subscribe", key_expr)
            if reason is not None:
                self.refusals.append(reason)
                log.error("%s: subscription refused by the router's access control: %s", self.node, reason)
        self._subscribers.append(self._zsession.declare_subscriber(key_expr, self._on_sample))

    def fetch_history(self, key_expr: str, timeout_s: float = 2.0) -> int:
        """Queue what the publishers' history caches hold on ``key_expr`` (services.zenoh_session.fetch_history),
        e.g. the session facts ``msk live`` published before this reader started; returns how many samples came."""
        samples, errors = fetch_history(self._zsession, key_expr, timeout_s=timeout_s)
        for error in errors:
            log.warning("%s: history of %s: %s", self.node, key_expr, error)
        for sample in samples:
            self._on_sample(sample)
        return len(samples)

    def fetch_session_facts(self, session: str, timeout_s: float = 5.0) -> threading.Thread:
        """In the background: once this Zenoh session knows ``msk live``'s own node (its readiness token; a peer
        learns another's declarations only once connected to it, a moment after joining), queue the session facts
        (exercise, load, set) its load publisher keeps, published before this reader started. Without an ``msk live``
        (a replay) or with a role that may not see readiness tokens, nothing is fetched."""
        from services.graph import GraphTimeout, wait_for_nodes
        from services.session_graph import NODES

        def fetch() -> None:
            try:
                wait_for_nodes(self._zsession, session, (NODES["monitor"].name,), timeout_s)
                self.fetch_history(topics.load_key(session))
            except GraphTimeout:
                return
            except Exception as error:  # a session closed meanwhile: the facts come with the next change
                log.info("%s: session facts not fetched: %s", self.node, error)

        thread = threading.Thread(target=fetch, name=f"{self.node}-facts", daemon=True)
        thread.start()
        return thread

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        arrival_ns = messages.now_ns()
        size = len(sample.payload)
        if size > self._max_bytes:  # never copied, never queued
            self._dropped(key, DropReason.OVERSIZED, f"{size} bytes (at most {self._max_bytes})")
            return
        item = (key, type_name_of_sample(sample), sample.payload.to_bytes(), arrival_ns, publication_id(sample))
        try:
            self._queue.put(item, timeout=QUEUE_WAIT_S)
        except queue.Full:
            self._dropped(key, DropReason.QUEUE_FULL, f"the node is {self._queue.maxsize} messages behind")

    def _dropped(self, key: str, reason: DropReason, detail: str) -> None:
        if self.counts.count_dropped(key, reason) == 1:
            log.warning(
                "%s: dropped a message on %s: %s: %s (further ones are counted in its status)",
                self.node,
                key,
                reason.value,
                detail,
            )

    def get(self, timeout_s: float) -> Inbound | None:
        """The next usable message in arrival order, or None when none arrived within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return None
            inbound = self._checked(*item)
            if inbound is not None:
                return inbound

    def _checked(
        self, key: str, encoding_type: str | None, payload: bytes, arrival_ns: int, source: tuple[str, int, int] | None
    ) -> Inbound | None:
        try:
            message = check_payload(
                key, payload, encoding_type=encoding_type, expected_type=self._expected_type, max_bytes=self._max_bytes
            )
        except Rejected as error:
            self._dropped(key, error.reason, error.detail)
            return Inbound(key, "", None, payload, arrival_ns, error, source) if self._keep_rejected else None
        self.counts.count_received(key)
        return Inbound(key, messages.type_name(message), message, payload, arrival_ns, source=source)

    def close(self) -> None:
        """Undeclare the subscribers (nothing new arrives; :meth:`drain` then empties the queue)."""
        if self._closed:
            return
        self._closed = True
        for subscriber in self._subscribers:
            subscriber.undeclare()

    def drain(self) -> Iterator[Inbound]:
        """What arrived and was not taken yet, in order (call after :meth:`close`)."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            inbound = self._checked(*item)
            if inbound is not None:
                yield inbound


def serve(
    inputs: NodeInputs,
    handle,
    stop_event: threading.Event,
    reporter: StatusReporter | None = None,
    poll_s: float = 0.05,
    tick: Callable[[bool], None] | None = None,
) -> None:
    """The node loop: every usable input to ``handle(inbound)`` in arrival order, the status when due, until
    ``stop_event``; then the subscriptions closed, what had arrived still handled (nothing received is lost) and
    the last status published. ``tick(final)``: called after every input or ``poll_s`` without one (``False``),
    and once more after the last input (``True``), e.g. for a node that holds inputs back for a while."""
    try:
        while not stop_event.is_set():
            inbound = inputs.get(poll_s)
            if inbound is not None:
                handle(inbound)
            if tick is not None:
                tick(False)
            if reporter is not None:
                reporter.tick()
    finally:
        inputs.close()
        for inbound in inputs.drain():
            handle(inbound)
        if tick is not None:
            tick(True)
        if reporter is not None:
            reporter.final()


def clock_offsets(reports: Iterable[ClockReport]) -> list[messages.ClockOffset]:
    """Clock mappings (msk_core.signal.host_clock) as the status carries them, in ms, with the alignments they come
    from (msk_core.estimate.clock_alignment)."""
    out = []
    for r in reports:
        message = messages.ClockOffset(
            source=r.source,
            offset_ms=r.offset_ns / 1e6,
            spread_ms=r.spread_ns / 1e6,
            latency_ms=r.latency_ns / 1e6,
            method=r.method,
            samples=r.samples,
            reason=r.reason,
            alignments=[_alignment(a) for a in r.alignments],
        )
        if r.arrival_offset_ns is not None:
            message.arrival_offset_ms = r.arrival_offset_ns / 1e6
        out.append(message)
    return out


def _alignment(alignment) -> messages.ClockAlignment:
    """An ``Alignment`` (msk_core.estimate.clock_alignment): a ClockSync answer against one reference stream."""
    answer = alignment.offset
    return messages.ClockAlignment(
        reference=alignment.reference,
        status=answer.status.value,
        reason=answer.reason,
        device_offset_ms=(answer.offset_ns or 0) / 1e6,
        spread_ms=(answer.spread_ns or 0) / 1e6,
        drift_ppm=answer.drift_ppm or 0.0,
        peak_correlation=answer.peak_correlation or 0.0,
        sensor=answer.sensor or "",
        windows=answer.windows,
        host_offset_ms=(alignment.host_offset_ns or 0) / 1e6,
    )


class StatusReporter:
    """Publishes a node's :class:`DeviceStatus` on ``msk/<session>/status/<node>``: its inputs' counts (and, with
    ``clocks``, the clock mappings it applies; with ``electrodes``, the EMG electrodes' quality; with ``fatigue``, their
    fatigue index over the set), at start, every
    :data:`STATUS_PERIOD_S`, and once more (``connected`` False) at stop."""

    def __init__(
        self,
        zsession: zenoh.Session,
        session: str,
        node: str,
        inputs: NodeInputs,
        clocks: Callable[[], Iterable[ClockReport]] | None = None,
        electrodes: Callable[[], Iterable[messages.ElectrodeQuality]] | None = None,
        fatigue: Callable[[], Iterable[messages.ElectrodeFatigue]] | None = None,
    ) -> None:
        self.node = node
        self._clocks = clocks
        self._electrodes = electrodes
        self._fatigue = fatigue
        self.counts = inputs.counts
        self.errors = 0
        self.last_error = ""
        self._inputs = inputs  # its refusals count as errors: a node its role does not let read what it needs
        self._publisher = declare_data_publisher(zsession, topics.status_key(session, node), "msk.DeviceStatus")
        self._last_sent = 0.0

    def error(self, text: str) -> None:
        """An input the node decoded but could not use (logged by the caller); counted in the status."""
        self.errors += 1
        self.last_error = text

    def message(self, connected: bool = True) -> messages.DeviceStatus:
        refusals = self._inputs.refusals
        return messages.DeviceStatus(
            device_id=self.node,
            kind="node",
            connected=connected,
            samples_received=sum(self.counts.received.values()),
            samples_lost=self.counts.total_dropped,
            errors=self.errors + len(refusals),
            last_error=self.last_error or (refusals[-1] if refusals else ""),
            host_time_ns=messages.now_ns(),
            dropped=self.counts.drops(),
            clocks=clock_offsets(self._clocks()) if self._clocks is not None else [],
            electrodes=list(self._electrodes()) if self._electrodes is not None else [],
            fatigue=list(self._fatigue()) if self._fatigue is not None else [],
        )

    def tick(self, *, force: bool = False) -> None:
        """Publish when due (call from the node's loop): every :data:`STATUS_PERIOD_S`, so a view or dashboard that
        starts late sees every node within a second, as it sees every device."""
        now = time.monotonic()
        if not force and now - self._last_sent < STATUS_PERIOD_S:
            return
        self._last_sent = now
        publish(self._publisher, self.message())

    def final(self) -> None:
        publish(self._publisher, self.message(connected=False))
