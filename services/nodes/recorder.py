"""Recorder node: subscribes to ``msk/**`` and logs every message to an MCAP file, one channel per key.

Inputs come through :class:`services.nodes.node_runtime.NodeInputs` like every node's (``keep_rejected=True``): Zenoh
callbacks only enqueue (receive time stamped on arrival); this node's thread checks each payload against its topic's
type and serialises to disk, so a slow disk never stalls the network threads. Run
``python -m services.nodes.recorder --out FILE.mcap`` or ``msk recorder``.

Typed channels hold messages only: a payload that fails the checks of :func:`services.nodes.node_runtime.check_payload`
(garbage, another type's bytes, a message failing its type's checks, a key outside the topic table) goes into a
channel of its own per key and reason, without a schema and labelled with the reason
(:meth:`services.transport.mcap_io.McapRecorderWriter.write_rejected`), which :func:`services.transport.mcap_io.read_messages`, and so
``msk report`` and ``msk replay``, leave out. A payload larger than :data:`services.nodes.node_runtime.MAX_PAYLOAD_BYTES`
is never copied, only counted. The counts per key and reason travel in the recorder's status on
``msk/<session>/status/recorder`` (:class:`services.nodes.node_runtime.StatusReporter`; the session of the graph, of
``--key`` or ``--session``), and its last status is written into the file at stop.

Batches: the recorder writes what its queue holds, then sleeps :data:`BATCH_S` while the next batch gathers (every
input is still checked and counted one by one, in arrival order): waking up per batch rather than per message is
most of its CPU (docs/deployment.md, "Where the CPU goes").

Crashes: a chunk is completed and handed to the OS at least every ``--flush-interval`` seconds (also when data
pauses), so a recorder killed with SIGKILL loses at most what arrived in that interval (plus one batch). Started again with the same
``--out``, it continues into the next free ``FILE-001.mcap``, ``FILE-002.mcap``...: on start it fetches what the
device publishers keep (:func:`services.transport.zenoh_session.declare_history_publisher`, the last 1000 messages per key) and
leaves out what the previous files already hold, so the parts join without a gap or a duplicate.

History and live samples are merged per key by :class:`HistoryMerge`: the live samples of a key wait until that
key's history is in (the first fetch at start, or a fetch on the first live sample of a key that appears later),
then the history is written, then the live samples, in publishing order.

Reconnection (the router restarted, the network between the recorder and the router down): the device publishers
number their publications, so a live sample that skips numbers (:attr:`services.nodes.node_runtime.Inbound.missed`) says
which ones this recorder missed; their cache is asked for exactly those (:func:`services.transport.zenoh_session.fetch_missed`)
while the key's live samples wait, and they are written before them. What the cache no longer holds (it keeps the
last :data:`DEVICE_HISTORY_SAMPLES` per key: an outage longer than that) is lost, counted per key
(``RecorderStats.unrecovered``), in the summary line and in the status (``outages.missed``/``recovered``).

What is left out as recorded already. Zenoh delivers each publication once to a subscription, so live samples are
never compared with one another: identical messages (a publisher that leaves ``host_time_ns`` unset) are as many
messages, and each is written. A copy can only come from a history fetch, compared by payload digest and occurrence
(each recorded occurrence cancels one copy, never more):

* against the previous parts: a cache sends again the newest messages those parts end with, so per key the oldest
  history samples that match the last :data:`DEVICE_HISTORY_SAMPLES` messages of the parts
  (:func:`recorded_tail_in`) are left out;
* against the live stream: a sample published between the subscription and the cache's answer comes both ways, so
  per key the newest history samples that match a live sample held for this fetch and received before the fetch
  returned are left out (the live copy is written, with its true arrival time). A publication whose identity is
  known (Zenoh's source info) is matched exactly, and its live copy is written in the history sample's place: the
  cache's answer can hold publications whose live copies have not arrived yet, and the file keeps publishing order.

Messages that carry their host time or a sample index (every driver node's) are therefore never confused. Identical
bytes can be: a cache holding more copies than the file tail or the overlap holds loses as many as those hold.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import logging
import queue
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import zenoh
from google.protobuf.message import Message

from msk_core.errors import ConfigError
from services.nodes.node_runtime import (
    MAX_PAYLOAD_BYTES,
    DropReason,
    Inbound,
    InputCounts,
    NodeInputs,
    NodeProcess,
    Rejected,
    StatusReporter,
    add_process_arguments,
    check_payload,
    publication_id,
)
from services.nodes.readiness import ReadySpec, declare_ready
from services.transport import messages, topics
from services.transport.mcap_io import REJECTED_REASON, McapRecorderWriter, device_time_ns, read_messages
from services.transport.zenoh_session import (
    DEVICE_HISTORY_SAMPLES,
    ZenohOptions,
    fetch_history,
    fetch_missed,
    keeps_history,
    open_session,
    run_script,
    type_name_of_sample,
)

DEFAULT_HISTORY_TIMEOUT_S = 10.0
#: Once it has written everything queued, the recorder sleeps this long and then takes what gathered meanwhile, in
#: arrival order (s): one wake-up per batch instead of one per message (a session sends ~1000 messages a second).
#: Nothing waits for the file (it is flushed every ``--flush-interval``), so this costs no one latency.
BATCH_S = 0.05
FETCH_JOIN_S = 2.0  # at the end, how long the history fetches may take in all to return once the session is closed
NODE_NAME = "recorder"

log = logging.getLogger(__name__)


@dataclass
class RecorderStats:
    received: int = 0  # inputs handed to the file (after leaving out what was recorded already)
    written: int = 0  # messages written to the typed channels
    node_status: int = 0  # of which the graph's nodes' own status (kind "node"): not data a waiter counts
    rejected: int = (
        0  # payloads kept in the rejected channels (services.transport.mcap_io.McapRecorderWriter.write_rejected)
    )
    already_recorded: int = 0  # history samples written already (by the previous parts, or live too)
    history_fetched: int = 0  # samples the publishers' caches sent
    history_fetches: int = 0
    history_errors: int = 0
    inputs: InputCounts | None = None  # received and dropped per key and reason (the recorder's status)
    missed: int = 0  # publications of history publishers that never arrived live (skipped sequence numbers)
    recovered: int = 0  # of those, fetched again from the publishers' caches and written
    unrecovered: collections.Counter = field(default_factory=collections.Counter)  # key -> missed, not in the cache
    unreadable: str = ""  # what of its key expression the recorder's role may not read (the access control), if any


def status_session(key_expr: str, ready_key: ReadySpec | None, session: str | None = None) -> str | None:
    """The session whose ``status/recorder`` key the recorder reports on: ``session``, else the graph's, else the one
    ``key_expr`` names (``msk/<session>/**``); None when it records several sessions and none was given."""
    if session is not None:
        return topics.check_chunk(session, "--session")
    if ready_key is not None:
        return ready_key.session
    parts = key_expr.split("/")
    if len(parts) < 2 or parts[0] != topics.ROOT:
        return None
    try:
        return topics.check_chunk(parts[1], "session")
    except ConfigError:  # a wildcard: several sessions
        return None


def main(
    config: ZenohOptions,
    out_path: Path,
    *,
    key_expr: str = topics.ALL_TOPICS,
    duration_s: float | None = None,
    stop_event: threading.Event | None = None,
    ready_event: threading.Event | None = None,
    ready_key: ReadySpec | None = None,
    flush_interval_s: float = 1.0,
    stats: RecorderStats | None = None,
    history: bool = True,
    history_timeout_s: float = DEFAULT_HISTORY_TIMEOUT_S,
    already_recorded: Mapping[str, Iterable[bytes]] | None = None,
    session: str | None = None,
    max_payload_bytes: int = MAX_PAYLOAD_BYTES,
    batch_s: float = BATCH_S,
) -> RecorderStats:
    """Record until ``duration_s`` elapses or ``stop_event`` is set. ``stats`` (if given) is updated live.

    ``history``: first fetch what history publishers keep (each fetch waits at most ``history_timeout_s``);
    ``already_recorded`` (topic -> digests of the last messages of the previous parts, :func:`recorded_tail_in`)
    drops what those parts hold. ``session``: where the recorder's status goes (:func:`status_session`).
    ``batch_s``: how long the queue gathers inputs once the recorder has written all it had (:data:`BATCH_S`).
    """
    stop_event = stop_event or threading.Event()
    stats = stats if stats is not None else RecorderStats()
    reporting_session = status_session(key_expr, ready_key, session)
    check_readable(config, key_expr)
    fetched: queue.SimpleQueue[_Fetched] = queue.SimpleQueue()

    fetchers = _Fetchers()
    try:
        with (
            open_session(config) as zsession,
            McapRecorderWriter(out_path, flush_interval_s=flush_interval_s) as writer,
        ):
            inputs = NodeInputs(
                zsession, NODE_NAME, keep_rejected=True, max_payload_bytes=max_payload_bytes, role=config.role
            )
            stats.inputs = inputs.counts
            reporter = (
                StatusReporter(zsession, reporting_session, NODE_NAME, inputs)
                if reporting_session is not None
                else None
            )
            merge = HistoryMerge(
                lambda item: _write(writer, item, stats, inputs.counts), stats, already_recorded=already_recorded
            )

            def start_fetches(scopes: list[str]) -> None:  # each on its own thread: the loop goes on writing
                for scope in scopes:
                    job = (zsession, scope, merge.take_missing(scope), fetched, inputs.counts, history_timeout_s)
                    fetchers.start(_fetch, (*job, max_payload_bytes), f"history {scope}")

            start_fetches(_subscribe(inputs, merge, key_expr, stats, history=history))
            token = declare_ready(zsession, ready_key)  # noqa: F841 - alive while the node runs (readiness)
            if ready_event is not None:
                ready_event.set()
            if reporter is not None:
                reporter.tick(force=True)
            deadline = None if duration_s is None else time.monotonic() + duration_s
            try:
                while not stop_event.is_set() and (deadline is None or time.monotonic() < deadline):
                    start_fetches(_take_fetched(fetched, inputs, merge, fetch_new_keys=history))
                    inbound = inputs.get(0.0)
                    if inbound is None:  # all written: wake up again when a batch has gathered (module docstring)
                        writer.flush_if_due()
                        stop_event.wait(batch_s)
                    else:
                        start_fetches(merge.accept(_live_item(inbound), fetch_new_keys=history))
                    if reporter is not None:
                        inputs.continuity.recovered = stats.recovered
                        reporter.tick()
            finally:
                _finish(inputs, fetched, merge, stats, writer, reporter, reporting_session)
    finally:  # the session is closed: a fetch still running returns
        fetchers.join(FETCH_JOIN_S)
    return stats


def _subscribe(
    inputs: NodeInputs, merge: HistoryMerge, key_expr: str, stats: RecorderStats, *, history: bool
) -> list[str]:
    """Subscribe to what the role may read of ``key_expr`` (all of it, or its parts: said in the log, kept in
    ``stats.unreadable``); returns the scopes whose history to fetch first (with ``history``)."""
    parts = inputs.subscribe_readable(key_expr)
    stats.unreadable = inputs.refusals[-1] if inputs.refusals else ""
    if not history:
        return []
    for part in parts:  # after the subscriber: every message is then live, in a cache, or both (written once)
        merge.begin_fetch(part, initial=True)
    return list(parts)


def check_readable(config: ZenohOptions, key_expr: str) -> None:
    """A :class:`ConfigError` when the role of ``config`` (the secured network's access control) may read nothing
    of ``key_expr``: such a recorder would write an empty file and say nothing."""
    from services.transport.roles import parts_text, permitted_parts

    role = config.role
    if role is not None and not permitted_parts(role, "subscribe", key_expr):
        text = parts_text(role, "subscribe", key_expr, ())
        raise ConfigError(f"{text}: the recorder would record nothing", path=config.config_file)


class _Fetchers:
    """The history fetches' threads. :meth:`join` waits, once the session is closed, for those still running: a
    thread still inside Zenoh when the interpreter exits aborts the process ("FATAL: exception not rethrown")."""

    def __init__(self) -> None:
        self._threads: list[threading.Thread] = []

    def start(self, target: Callable[..., None], args: tuple, name: str) -> None:
        self._threads = [t for t in self._threads if t.is_alive()]
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    def join(self, timeout_s: float) -> None:
        """Join every fetch within ``timeout_s`` in all; log those still running."""
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
        stuck = [t.name for t in self._threads if t.is_alive()]
        if stuck:
            log.warning(
                "recorder: %d history fetches still running %g s after the end: %s", len(stuck), timeout_s, stuck
            )


def _finish(
    inputs: NodeInputs,
    fetched: queue.SimpleQueue,
    merge: HistoryMerge,
    stats: RecorderStats,
    writer: McapRecorderWriter,
    reporter: StatusReporter | None,
    reporting_session: str | None,
) -> None:
    """A stop: nothing received is lost, what is queued and the fetches that came back meanwhile are written."""
    inputs.close()
    _take_fetched(fetched, inputs, merge, fetch_new_keys=False)
    for inbound in inputs.drain():
        merge.accept(_live_item(inbound), fetch_new_keys=False)
    merge.release_all()  # live samples still waiting for a history that did not come in time
    inputs.continuity.recovered = stats.recovered
    if reporter is not None and reporting_session is not None:  # a reporter exists for a session only
        _record_final_status(writer, reporter, reporting_session)


def _fetch(
    zsession: zenoh.Session,
    scope: str,
    missing: list[Missing],
    fetched: queue.SimpleQueue,
    counts: InputCounts,
    timeout_s: float,
    max_bytes: int,
) -> None:
    """Fetch ``scope``'s history (with ``missing``: those publications only) and hand it to ``fetched``."""
    samples: list[zenoh.Sample] = []
    errors: list[str] = []
    try:
        if not missing:
            samples, errors = fetch_history(zsession, scope, timeout_s=timeout_s)
        for gap in missing:  # publications skipped live: those of their cache
            got, failed = fetch_missed(zsession, scope, gap.publisher, gap.first, gap.last, timeout_s=timeout_s)
            samples, errors = samples + got, errors + failed
    except Exception as error:  # a closed session at shutdown, an access-control refusal...
        errors.append(f"{type(error).__name__}: {error}")
    finished_ns = messages.now_ns()
    items = [item for sample in samples if (item := _history_item(sample, finished_ns, counts, max_bytes)) is not None]
    fetched.put(_Fetched(scope, tuple(items), errors, finished_ns, tuple(missing)))


def _take_fetched(
    fetched: queue.SimpleQueue, inputs: NodeInputs, merge: HistoryMerge, *, fetch_new_keys: bool
) -> list[str]:
    """Hand the fetches that came back to ``merge``, each after the live samples received before it returned (those
    are the ones its history can hold too). Returns the keys to fetch next."""
    scopes: list[str] = []
    while True:
        try:
            done = fetched.get_nowait()
        except queue.Empty:
            return scopes
        while (inbound := inputs.get(0.0)) is not None:
            scopes += merge.accept(_live_item(inbound), fetch_new_keys=fetch_new_keys)
            if inbound.arrival_ns > done.finished_ns:
                break
        scopes += merge.accept(done, fetch_new_keys=fetch_new_keys)


def _record_final_status(writer: McapRecorderWriter, reporter: StatusReporter, session: str) -> None:
    """Publish the last status and write it into the file too (the subscription is closed: it would not come back)."""
    reporter.final()
    status = reporter.message(connected=False)
    writer.write(
        topics.status_key(session, NODE_NAME),
        "msk.DeviceStatus",
        messages.encode(status),
        status.host_time_ns,
        status.host_time_ns,
    )


LIVE, HISTORY = "live", "history"


@dataclass(frozen=True)
class _Item:
    origin: str  # LIVE or HISTORY
    receive_ns: int
    key: str
    payload: bytes
    message: Message | None  # None when rejected
    rejected: Rejected | None = None
    source: tuple[str, int, int] | None = None  # the publication's identity, when Zenoh carries it
    missed: int = 0  # publications of its publisher skipped just before it (services.nodes.node_runtime.Inbound.missed)


@dataclass(frozen=True)
class Missing:
    """Publications a live sample showed this recorder missed: one publisher's sequence numbers first..last."""

    publisher: tuple[str, int]  # Zenoh id, entity id
    first: int
    last: int

    def holds(self, source: tuple[str, int, int] | None) -> bool:
        return source is not None and source[:2] == self.publisher and self.first <= source[2] <= self.last


@dataclass(frozen=True)
class _Fetched:
    """A history fetch that came back: its samples, per publisher in publishing order, and its error replies."""

    scope: str  # the key expression fetched
    items: tuple[_Item, ...]
    errors: list[str]
    finished_ns: int  # when the fetch returned: a live sample received later cannot be in its history
    missing: tuple[Missing, ...] = ()  # a recovery: the publications asked for (none: the whole history)


def _live_item(inbound: Inbound) -> _Item:
    return _Item(
        LIVE,
        inbound.arrival_ns,
        inbound.key,
        inbound.payload,
        inbound.message,
        inbound.rejected,
        inbound.source,
        inbound.missed,
    )


def _history_item(sample: zenoh.Sample, received_ns: int, counts: InputCounts, max_bytes: int) -> _Item | None:
    """A cache's sample checked like a live one (an oversized one is counted and never copied)."""
    key = str(sample.key_expr)
    size = len(sample.payload)
    if size > max_bytes:
        _count_dropped(counts, Rejected(DropReason.OVERSIZED, key, f"{size} bytes (at most {max_bytes})"))
        return None
    payload = sample.payload.to_bytes()
    source = publication_id(sample)
    try:
        message = check_payload(key, payload, encoding_type=type_name_of_sample(sample), max_bytes=max_bytes)
    except Rejected as error:
        return _Item(HISTORY, received_ns, key, payload, None, error, source)
    return _Item(HISTORY, received_ns, key, payload, message, source=source)


def _count_dropped(counts: InputCounts, rejected: Rejected) -> None:
    if counts.count_dropped(rejected.key, rejected.reason) == 1:
        log.warning("%s: %s (from a publisher's history; further ones are counted in its status)", NODE_NAME, rejected)


class HistoryMerge:
    """Writes history and live samples once each, and for every key its history before its live samples.

    While a fetch is out, live samples wait (all of them, so the file keeps their arrival order across keys; a fetch
    takes milliseconds); when it is done the history is written, less what the previous parts or the live samples
    already hold (the module docstring's rule), then the waiting samples. Live samples are never left out.
    """

    def __init__(
        self,
        write: Callable[[_Item], None],
        stats: RecorderStats,
        *,
        already_recorded: Mapping[str, Iterable[bytes]] | None = None,
        keeps_history: Callable[[str], bool] = keeps_history,
    ) -> None:
        self._write = write
        self._keeps_history = keeps_history  # asked once per new key, not per message
        self._stats = stats
        # per key, the digests the previous parts end with (occurrences: each cancels one copy from a cache)
        self._earlier: dict[str, collections.Counter] = {
            key: collections.Counter(digests) for key, digests in (already_recorded or {}).items()
        }
        self._initial_pending = 0  # first fetches out (one per part of the key expression its role may read)
        self._pending_keys: set[str] = set()  # keys with a fetch of their own out
        self._known_keys: set[str] = set()  # keys whose history was fetched (or found absent)
        self._waiting: list[_Item] = []  # live samples held, in arrival order
        # per key, the publications written from a history fetch (identity from Zenoh's source info): the live copy
        # of one may still arrive after the fetch returned (replies and data take different paths through a router)
        self._from_history: dict[str, collections.deque] = {}
        self._from_history_set: dict[str, set] = {}
        self._missing: dict[str, list[Missing]] = {}  # per key, publications skipped live, not asked for yet

    def begin_fetch(self, scope: str, *, initial: bool = False) -> None:
        if initial:
            self._initial_pending += 1
        else:
            self._pending_keys.add(scope)

    def accept(self, item: _Item | _Fetched, *, fetch_new_keys: bool) -> list[str]:
        """Take a live sample or a fetch that came back; returns the keys whose history should be fetched now
        (``fetch_new_keys``: for a key first seen live whose publishers keep a history)."""
        if isinstance(item, _Fetched):
            return self._fetched(item)
        if item.source is not None and item.source in self._from_history_set.get(item.key, ()):
            self._stats.already_recorded += 1  # this very publication came with a history fetch, written then
            return []
        if item.missed and item.source is not None and self._keeps_history(item.key):
            gap = Missing(item.source[:2], item.source[2] - item.missed, item.source[2] - 1)
            self._stats.missed += item.missed
            if fetch_new_keys:
                return self._recover(item, gap)
            self._stats.unrecovered[item.key] += item.missed  # stopping: no more fetches
        if (
            fetch_new_keys
            and not self._initial_pending
            and item.key not in self._known_keys
            and item.key not in self._pending_keys
            and self._keeps_history(item.key)
        ):
            # a publisher that appeared after the start: it may have published before our subscription reached it
            self._pending_keys.add(item.key)
            self._waiting.append(item)
            return [item.key]
        if self._fetching():
            self._waiting.append(item)
            return []
        self._known_keys.add(item.key)
        self._write(item)
        return []

    def _recover(self, item: _Item, gap: Missing) -> list[str]:
        """Hold ``item`` (and every live sample after it) until the publications it shows missing are fetched."""
        self._missing.setdefault(item.key, []).append(gap)
        self._waiting.append(item)
        if item.key in self._pending_keys:
            return []  # asked for when the fetch out now returns
        self._pending_keys.add(item.key)
        return [item.key]

    def take_missing(self, scope: str) -> list[Missing]:
        """The publications of ``scope`` to ask its publishers' caches for (empty: fetch its whole history)."""
        return self._missing.pop(scope, [])

    def release_all(self) -> None:
        self._initial_pending = 0
        self._pending_keys.clear()
        self._release()

    def _fetched(self, done: _Fetched) -> list[str]:
        self._stats.history_fetches += 1
        self._stats.history_errors += len(done.errors)
        self._stats.history_fetched += len(done.items)
        if done.errors:
            log.warning(
                "history of %s: %d error replies (%s)", done.scope, len(done.errors), "; ".join(done.errors[:3])
            )
        for item in self._recovered(done) if done.missing else self._new_history(done):
            self._known_keys.add(item.key)
            self._write(item)
        if done.scope in self._pending_keys:
            if self._missing.get(done.scope):
                return [done.scope]  # more were skipped while this fetch was out: asked for now, the key still held
            self._pending_keys.discard(done.scope)
            self._known_keys.add(done.scope)
        else:
            self._initial_pending = max(0, self._initial_pending - 1)
        self._release()  # keys live during a fetch that no cache answered for have no history publisher
        return []

    def _recovered(self, done: _Fetched) -> list[_Item]:
        """The publications a recovery asked for that its caches still held, once each, in publishing order; those
        they no longer held are counted lost."""
        live = {item.source for item in self._waiting if item.key == done.scope and item.source is not None}
        written = self._from_history_set.get(done.scope, set())
        kept: dict[tuple[str, int, int], _Item] = {}
        for item in done.items:
            source = item.source
            if source is None or source in live or source in written or source in kept:
                continue
            if any(gap.holds(source) for gap in done.missing):
                kept[source] = item
        for gap in done.missing:  # written already (a whole-history fetch of the key), live or fetched now: not lost
            present = sum(
                1
                for n in range(gap.first, gap.last + 1)
                if (s := (*gap.publisher, n)) in kept or s in written or s in live
            )
            lost = gap.last - gap.first + 1 - present
            if lost:
                self._stats.unrecovered[done.scope] += lost
                log.warning(
                    "%s: %d of the %d publications missed (numbers %d..%d) %s: lost",
                    done.scope,
                    lost,
                    gap.last - gap.first + 1,
                    gap.first,
                    gap.last,
                    f"were not recovered ({'; '.join(done.errors[:2])})"
                    if done.errors
                    else "are no longer in their publisher's cache",
                )
        self._stats.recovered += len(kept)
        for source in kept:
            self._remember_history(done.scope, source)
        return [kept[source] for source in sorted(kept, key=lambda s: s[2])]

    def _new_history(self, done: _Fetched) -> list[_Item]:
        """The fetch's samples less those the previous parts or the live samples hold (one for one, by digest)."""
        per_key: dict[str, list[int]] = {}
        for index, item in enumerate(done.items):
            per_key.setdefault(item.key, []).append(index)
        keep = [True] * len(done.items)
        in_place: dict[int, _Item] = {}  # history index -> the live copy of that publication, written in its place
        for key, indices in per_key.items():
            live_copies = {item.source: item for item in self._waiting if item.key == key and item.source is not None}
            seen: set[tuple[str, int, int]] = set()
            for index in indices:
                source = done.items[index].source
                if source is None:
                    continue
                if source in seen:  # one publication twice in a fetch (two caches, or one answering twice): once
                    keep[index] = False
                elif source in live_copies:  # exact: the same publication, already held live
                    keep[index] = False
                    in_place[index] = live_copies[source]
                seen.add(source)
            indices = [index for index in indices if keep[index]]
            digests = {index: _digest(done.items[index].payload) for index in indices}
            earlier = self._earlier.pop(key, collections.Counter())
            for index in indices:  # oldest first: the previous parts end where the cache begins
                if earlier[digests[index]] > 0:
                    earlier[digests[index]] -= 1
                    keep[index] = False
            # without an identity (a publisher without source info), by digest: only what arrived before the fetch
            # returned can be in its history
            live = collections.Counter(
                _digest(item.payload)
                for item in self._waiting
                if item.key == key and item.source is None and item.receive_ns <= done.finished_ns
            )
            for index in reversed(indices):  # newest first: the live samples begin where the cache ends
                if keep[index] and done.items[index].source is None and live[digests[index]] > 0:
                    live[digests[index]] -= 1
                    keep[index] = False
        self._stats.already_recorded += keep.count(False)
        for index, item in enumerate(done.items):
            if keep[index] and item.source is not None:
                self._remember_history(item.key, item.source)
        if in_place:  # the cache may hold publications newer than a live copy held (its reply overtook the data)
            moved = {id(item) for item in in_place.values()}
            self._waiting = [item for item in self._waiting if id(item) not in moved]
        return [
            item if keep[index] else in_place[index]
            for index, item in enumerate(done.items)
            if keep[index] or index in in_place
        ]

    def _remember_history(self, key: str, source: tuple[str, int, int]) -> None:
        recent = self._from_history.setdefault(key, collections.deque())
        known = self._from_history_set.setdefault(key, set())
        recent.append(source)
        known.add(source)
        if len(recent) > 2 * DEVICE_HISTORY_SAMPLES:
            known.discard(recent.popleft())

    def _fetching(self) -> bool:
        return self._initial_pending > 0 or bool(self._pending_keys)

    def _release(self) -> None:
        if self._fetching():
            return
        waiting, self._waiting = self._waiting, []
        for item in waiting:
            self._known_keys.add(item.key)
            self._write(item)


def _write(writer: McapRecorderWriter, item: _Item, stats: RecorderStats, counts: InputCounts) -> None:
    stats.received += 1
    if item.rejected is not None:
        if item.origin == HISTORY:  # a live one was counted by NodeInputs
            _count_dropped(counts, item.rejected)
        writer.write_rejected(item.key, item.rejected.reason.value, item.rejected.detail, item.payload, item.receive_ns)
        stats.rejected += 1
        return
    message = item.message
    assert message is not None, "an item is decoded unless it was rejected"
    receive_ns = item.receive_ns
    publish_ns = device_time_ns(message, receive_ns)
    if item.origin == HISTORY:
        counts.count_received(item.key)
        host_time_ns = int(getattr(message, "host_time_ns", 0))  # the device messages' field
        if host_time_ns:
            # from a cache, late: log it when the driver's host received it, where a live recorder would have
            receive_ns = min(receive_ns, host_time_ns)
    writer.write(item.key, messages.type_name(message), item.payload, receive_ns, publish_ns)
    stats.written += 1
    if isinstance(message, messages.DeviceStatus) and message.kind == "node":
        stats.node_status += 1


def part_paths(out_path: Path) -> list[Path]:
    """``out_path`` and its continuation parts ``<stem>-001.mcap``... that exist, in order."""
    out_path = Path(out_path)
    parts = [out_path] if out_path.exists() else []
    index = 1
    while (candidate := out_path.with_name(f"{out_path.stem}-{index:03d}{out_path.suffix}")).exists():
        parts.append(candidate)
        index += 1
    return parts


def next_part_path(out_path: Path) -> Path:
    """Where a (re)started recorder writes: ``out_path`` itself, or the next free continuation part."""
    out_path = Path(out_path)
    existing = part_paths(out_path)
    if not existing:
        return out_path
    return out_path.with_name(f"{out_path.stem}-{len(existing):03d}{out_path.suffix}")


def _digest(payload: bytes) -> bytes:
    return hashlib.blake2b(payload, digest_size=16).digest()


def recorded_tail_in(paths: list[Path], per_topic: int = DEVICE_HISTORY_SAMPLES) -> dict[str, list[bytes]]:
    """Per topic, digests of the last ``per_topic`` payloads the (possibly truncated) files hold, typed or rejected,
    in file order, one per occurrence: all that a publisher's history can send again."""
    tails: dict[str, collections.deque] = {}
    for path in paths:
        for message in read_messages(path, include_rejected=True):
            tails.setdefault(message.topic, collections.deque(maxlen=per_topic)).append(_digest(message.data))
    return {topic: list(tail) for topic, tail in tails.items()}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help="MCAP file to write; if it exists (a previous run), continue into FILE-001.mcap, FILE-002.mcap...",
    )
    parser.add_argument(
        "--flush-interval",
        type=float,
        default=1.0,
        metavar="S",
        help="complete a chunk at least this often: the most a crash can lose (default 1 s)",
    )
    parser.add_argument(
        "--history",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="on start (and for each device key that appears later) fetch what the device publishers "
        "keep, the last 1000 messages per key, leaving out what earlier parts hold (default: on)",
    )
    parser.add_argument(
        "--history-timeout",
        type=float,
        default=DEFAULT_HISTORY_TIMEOUT_S,
        metavar="S",
        help="longest wait for a history fetch; that key's live messages wait with it (default 10 s)",
    )
    parser.add_argument("--key", default=topics.ALL_TOPICS, help="key expression to record (default: msk/**)")
    parser.add_argument("--duration", type=float, default=None, help="seconds to record (default: until Ctrl-C)")
    parser.add_argument(
        "--session",
        default=None,
        help="report the recorder's status (inputs received and dropped) on msk/SESSION/status/recorder "
        "(default: the session --key names; with msk/** and no --session, no status)",
    )
    add_process_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    process = NodeProcess.from_args(args)
    if not args.flush_interval > 0:
        raise ConfigError("must be positive", field="--flush-interval", value=args.flush_interval)
    if not args.history_timeout > 0:
        raise ConfigError("must be positive", field="--history-timeout", value=args.history_timeout)
    if Path(args.out).is_dir():  # else taken for an earlier part of the recording ("MCAP file not found")
        raise ConfigError(
            "is a folder: give the recording's file, e.g. FOLDER/session.mcap", field="--out", value=str(args.out)
        )
    check_readable(process.options, args.key)  # before saying "recording"
    previous = part_paths(args.out)
    out = next_part_path(args.out)
    already_recorded = recorded_tail_in(previous) if previous else None
    print(
        f"recording {args.key} to {out}" + (f" (continuing {len(previous)} earlier part(s))" if previous else ""),
        file=sys.stderr,
        flush=True,
    )
    stats = main(
        process.options,
        out,
        key_expr=args.key,
        duration_s=args.duration,
        stop_event=process.stop,
        flush_interval_s=args.flush_interval,
        history=args.history,
        history_timeout_s=args.history_timeout,
        already_recorded=already_recorded,
        ready_key=process.ready,
        session=args.session,
    )
    print(summary_line(stats, out), file=sys.stderr)
    return 0


def summary_line(stats: RecorderStats, out: Path) -> str:
    """What a recorder run wrote, kept apart and dropped, in one line."""
    dropped = stats.inputs.as_dict()["dropped"] if stats.inputs is not None else {}
    oversized = sum(reasons.get(DropReason.OVERSIZED.value, 0) for reasons in dropped.values())
    queue_full = sum(reasons.get(DropReason.QUEUE_FULL.value, 0) for reasons in dropped.values())
    return (
        f"recorded {stats.written} messages to {out}"
        + (f" ({stats.unreadable})" if stats.unreadable else "")
        + (
            f"; kept {stats.rejected} rejected payloads apart, in channels labelled {REJECTED_REASON}"
            if stats.rejected
            else ""
        )
        + (f"; dropped {oversized} oversized payloads" if oversized else "")
        + (f"; dropped {queue_full} on a full queue" if queue_full else "")
        + (f"; history: {stats.history_fetched} messages from the publishers' caches" if stats.history_fetched else "")
        + (f" ({stats.history_errors} error replies)" if stats.history_errors else "")
        + (f"; left out {stats.already_recorded} already recorded" if stats.already_recorded else "")
        + (
            f"; missed {stats.missed} publications live, fetched {stats.recovered} of them again from the "
            f"publishers' caches, lost {sum(stats.unrecovered.values())}"
            + (
                " (" + ", ".join(f"{k} {n}" for k, n in sorted(stats.unrecovered.items())) + ")"
                if stats.unrecovered
                else ""
            )
            if stats.missed
            else ""
        )
    )


if __name__ == "__main__":
    run_script(__doc__, add_arguments, run_from_args)
