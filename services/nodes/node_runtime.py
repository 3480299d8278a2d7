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

Outages of the inputs are counted there too (``outages``, :class:`InputContinuity`): a stream the node reads silent
for longer than :data:`OUTAGE_MIN_S` (or :data:`OUTAGE_PERIODS` of its own period, when longer) between two of its
messages, e.g. the network between the node and the router down; and the publications of history publishers that
never arrived, by their sequence numbers (:attr:`Inbound.missed`: the recorder fetches those again).
"""

from __future__ import annotations

import argparse
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

from msk_core.model.pack import is_known_exercise
from msk_core.signal.host_clock import ClockReport
from msk_core.signal.sets import SetTracker
from services.nodes.readiness import ReadySpec, add_ready_arguments, ready_from_args
from services.transport import messages, topics
from services.transport.stop_signals import stop_on_signals
from services.transport.zenoh_session import (
    ZenohOptions,
    add_zenoh_arguments,
    declare_data_publisher,
    fetch_history,
    options_from_args,
    publish,
    type_name_of_sample,
)

log = logging.getLogger(__name__)

#: Largest payload a node takes (bytes). An EMG chunk of 16 channels at 2 kHz is ~4 kB per 30 ms; a replay batching a
#: whole second is 128 kB. 8 MiB leaves room for any real message and keeps a 50 MB blob out of the queue.
MAX_PAYLOAD_BYTES = 8 * 1024 * 1024
MAX_QUEUE = 20_000
QUEUE_WAIT_S = 1.0
STATUS_PERIOD_S = 1.0
FACTS_JOIN_S = 3.0  # close() waits this long for fetch_session_facts (its history query times out after 2 s)
#: the shortest silence of an input stream counted as an outage (s); a stream slower than 1/20 s needs 10 periods
OUTAGE_MIN_S = 0.5
OUTAGE_PERIODS = 10
#: a key's first messages, from which its period is known (its silences count from then on)
STREAM_MESSAGES = 20
#: topics that carry events or a heartbeat, not a stream: their silences are no outage (docs/topics.md)
NOT_STREAMS = ("load", "status")


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
    #: publications of the same publisher that never arrived just before this one (sequence numbers skipped)
    missed: int = 0


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


@dataclass
class _Stream:
    """One input key's arrivals: the last one, its first intervals (whose median is its period), then its period."""

    last_ns: int
    intervals: list[int] = field(default_factory=list)
    period_ns: float | None = None  # None until STREAM_MESSAGES arrived: silences do not count before


@dataclass
class Outage:
    """Input streams silent together: from the arrival of the last message before to that of the first after."""

    start_ns: int
    end_ns: int
    keys: set[str]

    @property
    def seconds(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9


class InputContinuity:
    """A node's input outages (the module docstring) and the publications it missed; thread-safe.

    Per key, the period is the median of its first :data:`STREAM_MESSAGES` intervals, then follows the intervals
    shorter than the threshold (mean over the last ~100); a silence longer than ``max(min_s, OUTAGE_PERIODS *
    period)`` ends as an outage when the key's next message arrives. Silences of several keys that overlap in time
    are one outage (a network cut silences every stream at once). :attr:`recovered` is for a node that fetches
    missed publications again (the recorder)."""

    def __init__(self, min_s: float = OUTAGE_MIN_S, stream_messages: int = STREAM_MESSAGES) -> None:
        self.min_ns = int(min_s * 1e9)
        self._stream_messages = stream_messages
        self._streams: dict[str, _Stream | None] = {}  # None: not a stream (NOT_STREAMS)
        self._sequence: dict[tuple[str, int], int] = {}  # publisher -> newest sequence number
        self._lock = threading.Lock()
        self.recent: list[Outage] = []  # the last outages (merging looks back over these)
        self.count = 0
        self._earlier_ns = 0  # total of the outages no longer in ``recent``
        self.longest_ns = 0
        self.missed = 0
        self.recovered = 0

    def arrived(self, key: str, arrival_ns: int, source: tuple[str, int, int] | None = None) -> int:
        """Note one message's arrival; returns how many publications of its publisher were skipped just before it."""
        with self._lock:
            missed = self._skipped(source) if source is not None else 0
            stream = self._streams.get(key, _NO_STREAM)
            if stream is _NO_STREAM:
                self._streams[key] = _Stream(arrival_ns) if _is_stream(key) else None
            elif stream is not None:
                self._arrival(key, stream, arrival_ns)
            return missed

    def _skipped(self, source: tuple[str, int, int]) -> int:
        publisher, number = (source[0], source[1]), source[2]
        newest = self._sequence.get(publisher)
        if newest is not None and number <= newest:
            return 0  # a repeat, or a late one (from a history fetch)
        self._sequence[publisher] = number
        if newest is None or number == newest + 1:
            return 0
        self.missed += number - newest - 1
        return number - newest - 1

    def _threshold_ns(self, stream: _Stream) -> float:
        return max(self.min_ns, OUTAGE_PERIODS * (stream.period_ns or 0.0))

    def _arrival(self, key: str, stream: _Stream, arrival_ns: int) -> None:
        gap = arrival_ns - stream.last_ns
        if gap < 0:  # stamped on another Zenoh thread a moment earlier
            return
        stream.last_ns = arrival_ns
        if stream.period_ns is None:
            stream.intervals.append(gap)
            if len(stream.intervals) >= self._stream_messages:
                stream.period_ns = float(sorted(stream.intervals)[len(stream.intervals) // 2])
                stream.intervals = []
        elif gap > self._threshold_ns(stream):
            self._outage(Outage(arrival_ns - gap, arrival_ns, {key}))
        else:
            stream.period_ns += (gap - stream.period_ns) / 100

    def _outage(self, new: Outage) -> None:
        """Count a silence, merged with the recent outages it overlaps."""
        while self.recent and new.start_ns <= self.recent[-1].end_ns and new.end_ns >= self.recent[-1].start_ns:
            old = self.recent.pop()
            self.count -= 1
            new = Outage(min(new.start_ns, old.start_ns), max(new.end_ns, old.end_ns), new.keys | old.keys)
        self.recent.append(new)
        self.count += 1
        self.longest_ns = max(self.longest_ns, new.end_ns - new.start_ns)
        while len(self.recent) > 16:
            old = self.recent.pop(0)
            self._earlier_ns += old.end_ns - old.start_ns

    def report(self, now_ns: int) -> messages.InputOutages:
        """The counts as the node's status carries them; ``silent_*``: the streams silent now beyond the threshold."""
        with self._lock:
            silent = {
                key: s.last_ns
                for key, s in self._streams.items()
                if s is not None and s.period_ns is not None and now_ns - s.last_ns > self._threshold_ns(s)
            }
            last = self.recent[-1] if self.recent else None
            return messages.InputOutages(
                count=self.count,
                total_s=(self._earlier_ns + sum(o.end_ns - o.start_ns for o in self.recent)) / 1e9,
                longest_s=self.longest_ns / 1e9,
                last_start_ns=last.start_ns if last else 0,
                last_end_ns=last.end_ns if last else 0,
                last_keys=sorted(last.keys) if last else [],
                silent_s=(now_ns - min(silent.values())) / 1e9 if silent else 0.0,
                silent_keys=sorted(silent),
                threshold_s=self.min_ns / 1e9,
                missed=self.missed,
                recovered=self.recovered,
            )


_NO_STREAM = _Stream(-1)  # a key not seen yet


def _is_stream(key: str) -> bool:
    parts = key.split("/")
    return len(parts) >= 3 and parts[2] not in NOT_STREAMS


def outages_summary(outages: messages.InputOutages) -> dict:
    """A node's input outages as ``summary.json`` says them (times in s; the last one's start and end host times
    as ISO 8601 UTC)."""
    from datetime import UTC, datetime

    def when(ns: int) -> str | None:
        return datetime.fromtimestamp(ns / 1e9, tz=UTC).isoformat(timespec="milliseconds") if ns else None

    return {
        "count": int(outages.count),
        "total_s": round(outages.total_s, 3),
        "longest_s": round(outages.longest_s, 3),
        "last_start": when(outages.last_start_ns),
        "last_end": when(outages.last_end_ns),
        "last_keys": list(outages.last_keys),
        "threshold_s": outages.threshold_s,
        "missed": int(outages.missed),
        "recovered": int(outages.recovered),
    }


def outages_text(outages: messages.InputOutages) -> str:
    """One line: ``2 input outages (10.3 s, longest 7.1 s); 310 publications missed, 310 recovered``."""
    text = f"{outages.count} input outage{'s' if outages.count != 1 else ''}" + (
        f" ({outages.total_s:.1f} s, longest {outages.longest_s:.1f} s)" if outages.count else ""
    )
    if outages.missed:
        text += f"; {outages.missed} publications missed, {outages.recovered} recovered"
    return text


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
        self.continuity = InputContinuity()
        self._zsession = zsession
        self._max_bytes = max_payload_bytes
        self._expected_type = expected_type
        self._queue: queue.Queue = queue.Queue(max_queue)
        self._subscribers: list[zenoh.Subscriber] = []
        self._closed = False
        self._facts: threading.Thread | None = None  # fetch_session_facts' thread, joined by close()
        self._close_lock = threading.Lock()

    def subscribe(self, key_expr: str) -> None:
        if self.role is not None:
            from services.transport.security import refused

            reason = refused(self.role, "subscribe", key_expr)
            if reason is not None:
                self.refusals.append(reason)
                log.error("%s: subscription refused by the router's access control: %s", self.node, reason)
        self._subscribers.append(self._zsession.declare_subscriber(key_expr, self._on_sample))

    def subscribe_readable(self, key_expr: str) -> tuple[str, ...]:
        """Subscribe to what of ``key_expr`` the node's role may read (all of it without a role), one subscription per
        part (:func:`services.transport.roles.permitted_parts`: the router refuses a declaration its rules do not
        wholly cover, so ``msk/<s>/**`` as a tablet would read nothing); what the role may not read is said at once,
        as :meth:`subscribe` says a refusal. Returns the parts subscribed to (none: the role may read none of it)."""
        if self.role is None:
            self.subscribe(key_expr)
            return (key_expr,)
        from services.transport.roles import parts_text, permitted_parts

        parts = permitted_parts(self.role, "subscribe", key_expr)
        if parts == (key_expr,):
            self.subscribe(key_expr)
            return parts
        reason = parts_text(self.role, "subscribe", key_expr, parts)
        self.refusals.append(reason)
        if parts:
            log.warning("%s: subscription narrowed by the router's access control: %s", self.node, reason)
        else:
            log.error("%s: subscription refused by the router's access control: %s", self.node, reason)
        for part in parts:
            self._subscribers.append(self._zsession.declare_subscriber(part, self._on_sample))
        return parts

    def fetch_history(self, key_expr: str, timeout_s: float = 2.0) -> int:
        """Queue what the publishers' history caches hold on ``key_expr`` (services.transport.zenoh_session.fetch_history),
        e.g. the session facts ``msk live`` published before this reader started; returns how many samples came."""
        samples, errors = fetch_history(self._zsession, key_expr, timeout_s=timeout_s)
        for error in errors:
            log.warning("%s: history of %s: %s", self.node, key_expr, error)
        for sample in samples:
            self._on_sample(sample)
        return len(samples)

    def fetch_session_facts(
        self,
        session: str,
        timeout_s: float = 5.0,
        current: Callable[[], list[messages.LoadEvent]] | None = None,
    ) -> threading.Thread:
        """In the background: once this Zenoh session knows ``msk live``'s own node (its readiness token; a peer
        learns another's declarations only once connected to it, a moment after joining), queue the session facts
        (exercise, load, set) its load publisher keeps, published before this reader started. Without an ``msk live``
        (a replay) or with a role that may not see readiness tokens, nothing is fetched.

        That cache holds the session's opening facts only (the operator's later ones came from commands that have
        left); ``current`` gives the facts in effect now (what msk live announces on this machine,
        :func:`services.sessions.facts.announced_events`), queued after them as if they had arrived on the load key
        (also when msk live's node was not seen), so a page that starts late neither shows nor, with its set buttons,
        publishes the opening load again."""
        from services.nodes.readiness import GraphTimeout, wait_for_nodes
        from services.transport.session_graph import NODES

        def closed() -> str | None:
            return "the reader closed" if self._closed else None

        def fetch() -> None:
            try:
                wait_for_nodes(self._zsession, session, (NODES["monitor"].name,), timeout_s, give_up=closed)
                if not self._closed:
                    self.fetch_history(topics.load_key(session))
            except GraphTimeout as error:  # a replay has no msk live: not a fault, but said
                log.info("%s: no opening session facts fetched (%s)", self.node, error)
            except Exception as error:  # a session closed meanwhile: the facts come with the next change
                log.info("%s: session facts not fetched: %s", self.node, error)
                return
            for event in current() if current is not None and not self._closed else []:
                key = topics.load_key(session)
                self._enqueue((key, messages.type_name(event), event.SerializeToString(), messages.now_ns(), None, 0))

        thread = threading.Thread(target=fetch, name=f"{self.node}-facts", daemon=True)
        self._facts = thread
        thread.start()
        return thread

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        arrival_ns = messages.now_ns()
        size = len(sample.payload)
        if size > self._max_bytes:  # never copied, never queued
            self._dropped(key, DropReason.OVERSIZED, f"{size} bytes (at most {self._max_bytes})")
            return
        source = publication_id(sample)
        missed = self.continuity.arrived(key, arrival_ns, source)
        self._enqueue((key, type_name_of_sample(sample), sample.payload.to_bytes(), arrival_ns, source, missed))

    def _enqueue(self, item: tuple) -> None:
        """One input (key, type name, payload, arrival, source, missed) for the node's thread, or counted as
        dropped when the node is too far behind."""
        try:
            self._queue.put(item, timeout=QUEUE_WAIT_S)
        except queue.Full:
            self._dropped(item[0], DropReason.QUEUE_FULL, f"the node is {self._queue.maxsize} messages behind")

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
        self,
        key: str,
        encoding_type: str | None,
        payload: bytes,
        arrival_ns: int,
        source: tuple[str, int, int] | None,
        missed: int = 0,
    ) -> Inbound | None:
        try:
            message = check_payload(
                key, payload, encoding_type=encoding_type, expected_type=self._expected_type, max_bytes=self._max_bytes
            )
        except Rejected as error:
            self._dropped(key, error.reason, error.detail)
            return Inbound(key, "", None, payload, arrival_ns, error, source, missed) if self._keep_rejected else None
        self.counts.count_received(key)
        return Inbound(key, messages.type_name(message), message, payload, arrival_ns, source=source, missed=missed)

    def close(self) -> None:
        """Undeclare the subscribers (nothing new arrives; :meth:`drain` then empties the queue). A second caller
        returns once the first one's close is done."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True  # the facts' fetch reads it and gives up
            if self._facts is not None:
                # A thread still inside Zenoh when the interpreter exits aborts the process ("FATAL: exception not
                # rethrown"): the fetch gives up within 0.1 s of the close, or its history query within its timeout.
                self._facts.join(FACTS_JOIN_S)
                if self._facts.is_alive():
                    log.warning("%s: the session facts' fetch did not stop within %g s", self.node, FACTS_JOIN_S)
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


def apply_load_event(sets: SetTracker, event: messages.LoadEvent) -> None:
    """The set facts of a load event (set number, start/stop mark, barbell mass, rest time) into ``sets``, at the
    event's time (none when it carries none: :meth:`SetTracker.on_facts` then takes its newest phase sample's), as
    every node and page that follows the sets reads them (the estimator, the view, the dashboard)."""
    sets.on_facts(
        event.device_time_ns / 1e9 if event.device_time_ns else None,
        set_number=int(event.set_number),
        set_mark=event.set_mark,
        mass_kg=event.barbell_mass_kg,
        rest_s=event.set_rest_s,
        set_start_s=event.set_start_s if event.HasField("set_start_s") else None,
        rep_spans=list(zip(event.set_rep_spans_s[::2], event.set_rep_spans_s[1::2])),
        set_end_s=event.set_end_s if event.HasField("set_end_s") else None,
        set_ended_by=event.set_ended_by,
        set_started_by=event.set_started_by,
        rep_start_s=event.set_rep_start_s if event.HasField("set_rep_start_s") else None,
    )


#: Load events a page holds while no frame has said whether their exercise is the session's (bounded: a publisher
#: that floods unknown exercises before the first frame cannot grow a page's memory).
HELD_LOAD_EVENTS = 100


@dataclass
class LoadEventGate:
    """The load events a page or report applies, as the estimator takes them (``EstimatorNode.handle_load``): one
    naming an exercise that no shipped pack has and no activation frame has named is refused, set facts and names
    included, so the page never shows as current an exercise the estimator does not estimate.

    Before the first frame names it, such an exercise may still be the session's own pack (a subject-scaled JSON):
    its events are held, and every event after them too, so that the facts are applied in the order the estimator
    applied them. When a frame names an exercise, the held events are released in order, those naming an exercise
    still unknown refused."""

    frame_exercises: set[str] = field(default_factory=set)
    #: the exercise (pack) the session announces it estimates: what a page that starts while the estimator is paused,
    #: before any frame, knows of it (:meth:`paused_notice`)
    session_exercise: str = ""
    held: list[messages.LoadEvent] = field(default_factory=list)
    refused: int = 0
    _counted: int = 0  # of the refused, those already in an InputCounts

    def count_refused(self, counts: InputCounts, key: str) -> None:
        """The events refused since the last call, as ``counts``' invalid inputs of ``key`` (the page's input row)."""
        while self._counted < self.refused:
            self._counted += 1
            counts.count_dropped(key, DropReason.INVALID)

    @property
    def pending(self) -> messages.LoadEvent | None:
        """The newest held event: the facts in effect as far as the page can tell while they wait (what an
        operator's set mark carries on, rather than no load at all)."""
        return self.held[-1] if self.held else None

    def _known(self, event: messages.LoadEvent) -> bool:
        return not event.exercise or is_known_exercise(event.exercise, tuple(self.frame_exercises))

    def offer(self, event: messages.LoadEvent) -> list[messages.LoadEvent]:
        """The events to apply now: ``event`` when its exercise is known and nothing waits before it, else none (it
        waits, or is refused)."""
        if self._known(event) and not self.held:
            return [event]
        if not self._known(event) and self.frame_exercises:
            self.refused += 1  # frames already say which exercises the session estimates, and this is none of them
        elif len(self.held) >= HELD_LOAD_EVENTS:
            self.refused += 1
        else:
            self.held.append(event)
        return []

    def paused_notice(self, declared: str) -> str:
        """Why estimates stop while the operator's load events declare ``declared``: the estimator skips the frames
        of an exercise other than its pack's (``EstimatorNode.frames_for_joints``), so a page that sees no estimates
        says that rather than asking whether the estimator runs; "" while ``declared`` is one the frames named."""
        estimated = sorted(self.frame_exercises or ({self.session_exercise} - {""}))
        if not declared or not estimated or declared in estimated:
            return ""
        names = " or ".join(e.replace("_", " ") for e in estimated)
        return (
            f"The operator's load event declares {declared.replace('_', ' ')}, and this session "
            f"estimates {names}. They resume when a load event names it again "
            f"(msk load --exercise {estimated[0]})."
        )

    def on_frame(self, exercise: str) -> list[messages.LoadEvent]:
        """A frame of ``exercise`` arrived: the held events, in order, that are now known (the others are refused)."""
        if not exercise or exercise in self.frame_exercises:
            return []
        self.frame_exercises.add(exercise)
        released = [e for e in self.held if self._known(e)]
        self.refused += len(self.held) - len(released)
        self.held.clear()
        return released


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


#: The estimator node's name (its status on ``msk/<s>/status/estimator``).
ESTIMATOR_NODE = "estimator"


def estimates_ended(status: messages.DeviceStatus) -> bool:
    """Whether ``status`` is the estimator's last (:meth:`StatusReporter.final`): no activation frame follows, so a
    view closes the rep under way as the report does at the end of the recording (``SetTracker.finish``)."""
    return status.kind == "node" and status.device_id == ESTIMATOR_NODE and not status.connected


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
            outages=self._inputs.continuity.report(messages.now_ns()),
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


def add_process_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags every node process takes from the graph that starts it (services.sessions.graph.Graph.add_process):
    its Zenoh connection and its readiness (hidden)."""
    add_ready_arguments(parser)
    add_zenoh_arguments(parser)


@dataclass(frozen=True)
class NodeProcess:
    """What a node started as a process runs with: its Zenoh options and readiness (:func:`add_process_arguments`;
    ``ready`` None when started by hand) and the stop flag that SIGINT/SIGTERM set, so it ends cleanly and reports."""

    options: ZenohOptions
    ready: ReadySpec | None
    stop: threading.Event

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> NodeProcess:
        """From the flags of :func:`add_process_arguments`; installs the signal handlers (call it once, in the process's
        main thread)."""
        return cls(options_from_args(args), ready_from_args(args), stop_on_signals())
