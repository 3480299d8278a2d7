"""Recorder node: subscribes to ``msk/**`` and logs every message to an MCAP file, one channel per key.

Zenoh callbacks only enqueue (receive time stamped on arrival); one writer thread serialises to disk, so a slow disk
never stalls the network threads. Run ``python -m services.recorder --out FILE.mcap`` or ``msk recorder``.

Crashes: a chunk is completed and handed to the OS at least every ``--flush-interval`` seconds (also when data
pauses), so a recorder killed with SIGKILL loses at most what arrived in that interval. Started again with the same
``--out``, it continues into the next free ``FILE-001.mcap``, ``FILE-002.mcap``...: on start it fetches what the
device publishers keep (:func:`services.zenoh_session.declare_history_publisher`, the last 1000 messages per key) and
leaves out what the previous files already hold, so the parts join without a gap or a duplicate.

History and live samples are merged per key by :class:`HistoryMerge`: the live samples of a key wait until that
key's history is in (the first fetch at start, or a fetch on the first live sample of a key that appears later),
then whatever both delivered is written once, in publishing order.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import logging
import queue
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zenoh

from msk_core.errors import ConfigError
from services import messages, topics
from services.graph import ReadySpec, declare_ready
from services.mcap_io import McapRecorderWriter, device_time_ns
from services.mcap_io import read_messages
from services.zenoh_session import (
    DEVICE_HISTORY_SAMPLES,
    ZenohOptions,
    add_zenoh_arguments,
    fetch_history,
    keeps_history,
    open_session,
    options_from_args,
    type_name_of_sample,
)

DEFAULT_HISTORY_TIMEOUT_S = 10.0

log = logging.getLogger(__name__)


@dataclass
class RecorderStats:
    received: int = 0
    written: int = 0
    skipped_unknown: int = 0
    undecodable: int = 0
    already_recorded: int = 0  # samples written already (by the previous parts, or live and history both)
    history_fetched: int = 0  # samples the publishers' caches sent
    history_fetches: int = 0
    history_errors: int = 0


def resolve_type(key: str, sample_type: str | None) -> str | None:
    """Message type from the sample's encoding schema, else from the topic table."""
    if sample_type in messages.MESSAGE_TYPES:
        return sample_type
    try:
        return topics.message_type_for_key(key)
    except ConfigError:  # not an msk/<session>/... key
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
    already_recorded: dict[str, set[bytes]] | None = None,
) -> RecorderStats:
    """Record until ``duration_s`` elapses or ``stop_event`` is set. ``stats`` (if given) is updated live.

    ``history``: first fetch what history publishers keep (each fetch waits at most ``history_timeout_s``);
    ``already_recorded`` (topic -> digests of the last messages of the previous parts, :func:`recorded_tail_in`)
    drops what those parts hold.
    """
    stop_event = stop_event or threading.Event()
    stats = stats if stats is not None else RecorderStats()
    inbox: queue.SimpleQueue = queue.SimpleQueue()

    def on_sample(sample: zenoh.Sample) -> None:
        inbox.put(_Item(LIVE, messages.now_ns(), str(sample.key_expr), type_name_of_sample(sample), sample.payload.to_bytes()))

    with open_session(config) as session, McapRecorderWriter(out_path, flush_interval_s=flush_interval_s) as writer:
        merge = HistoryMerge(lambda item: _write(writer, item, stats), stats, already_recorded=already_recorded)

        def fetch(scope: str) -> None:  # on its own thread: the main loop goes on writing the other keys
            try:
                samples, errors = fetch_history(session, scope, timeout_s=history_timeout_s)
            except Exception as error:  # a closed session at shutdown, an access-control refusal...
                samples, errors = [], [f"{type(error).__name__}: {error}"]
            received_ns = messages.now_ns()
            for sample in samples:
                inbox.put(_Item(HISTORY, received_ns, str(sample.key_expr), type_name_of_sample(sample), sample.payload.to_bytes()))
            inbox.put(_FetchDone(scope, errors))

        def start_fetch(scope: str) -> None:
            threading.Thread(target=fetch, args=(scope,), name=f"history {scope}", daemon=True).start()

        subscriber = session.declare_subscriber(key_expr, on_sample)
        if history:  # after the subscriber: every message is then live, in a cache, or both (written once)
            merge.begin_fetch(key_expr, initial=True)
            start_fetch(key_expr)
        token = declare_ready(session, ready_key)  # noqa: F841 - alive while the node runs (services.graph)
        if ready_event is not None:
            ready_event.set()
        deadline = None if duration_s is None else time.monotonic() + duration_s
        try:
            while True:
                if stop_event.is_set() or (deadline is not None and time.monotonic() >= deadline):
                    break
                try:
                    item = inbox.get(timeout=0.05)
                except queue.Empty:
                    writer.flush_if_due()
                    continue
                for scope in merge.accept(item, fetch_new_keys=history):
                    start_fetch(scope)
        finally:
            subscriber.undeclare()
            while True:  # drain what already arrived: nothing received is lost on a clean stop
                try:
                    merge.accept(inbox.get_nowait(), fetch_new_keys=False)
                except queue.Empty:
                    break
            merge.release_all()  # live samples still waiting for a history that did not come in time
    return stats


LIVE, HISTORY = "live", "history"


@dataclass(frozen=True)
class _Item:
    origin: str  # LIVE or HISTORY
    receive_ns: int
    key: str
    sample_type: str | None
    payload: bytes


@dataclass(frozen=True)
class _FetchDone:
    scope: str  # the key expression fetched
    errors: list[str]


class HistoryMerge:
    """Writes history and live samples once each, and for every key its history before its live samples.

    While a fetch is out, live samples wait (all of them, so the file keeps their arrival order across keys; a fetch
    takes milliseconds); when it is done the history is written, then the waiting samples. A sample already written (the same payload digest: every message
    carries its host time, so equal payloads are the same message) is counted in ``stats.already_recorded`` and left
    out, whether the earlier parts, the history or the live stream wrote it first. Per key the last
    ``2 * DEVICE_HISTORY_SAMPLES`` digests are remembered: more than one cache can send again.
    """

    def __init__(self, write, stats: RecorderStats, *, already_recorded: dict[str, set[bytes]] | None = None,
                 remembered_per_key: int = 2 * DEVICE_HISTORY_SAMPLES, keeps_history=keeps_history) -> None:
        self._write = write
        self._keeps_history = keeps_history  # asked once per new key, not per message
        self._stats = stats
        self._remembered_per_key = remembered_per_key
        self._recent: dict[str, tuple[collections.deque, set[bytes]]] = {}
        for key, digests in (already_recorded or {}).items():
            for digest in digests:
                self._remember(key, digest)
        self._initial_pending = False
        self._pending_keys: set[str] = set()  # keys with a fetch of their own out
        self._known_keys: set[str] = set()  # keys whose history was fetched (or found absent)
        self._waiting: list[_Item] = []  # live samples held, in arrival order

    def begin_fetch(self, scope: str, *, initial: bool = False) -> None:
        if initial:
            self._initial_pending = True
        else:
            self._pending_keys.add(scope)

    def accept(self, item, *, fetch_new_keys: bool) -> list[str]:
        """Take one inbox item; returns the keys whose history should be fetched now (``fetch_new_keys``: for a key
        first seen live whose publishers keep a history)."""
        if isinstance(item, _FetchDone):
            self._fetch_done(item)
            return []
        if item.origin == HISTORY:
            self._known_keys.add(item.key)
            self._emit(item)
            return []
        if (fetch_new_keys and not self._initial_pending and item.key not in self._known_keys
                and item.key not in self._pending_keys and self._keeps_history(item.key)):
            # a publisher that appeared after the start: it may have published before our subscription reached it
            self._pending_keys.add(item.key)
            self._waiting.append(item)
            return [item.key]
        if self._fetching():
            self._waiting.append(item)
            return []
        self._known_keys.add(item.key)
        self._emit(item)
        return []

    def release_all(self) -> None:
        self._initial_pending = False
        self._pending_keys.clear()
        self._release()

    def _fetch_done(self, done: _FetchDone) -> None:
        self._stats.history_fetches += 1
        self._stats.history_errors += len(done.errors)
        if done.errors:
            log.warning("history of %s: %d error replies (%s)", done.scope, len(done.errors), "; ".join(done.errors[:3]))
        if done.scope in self._pending_keys:
            self._pending_keys.discard(done.scope)
            self._known_keys.add(done.scope)
        else:
            self._initial_pending = False
        self._release()  # keys live during a fetch that no cache answered for have no history publisher

    def _fetching(self) -> bool:
        return self._initial_pending or bool(self._pending_keys)

    def _release(self) -> None:
        if self._fetching():
            return
        waiting, self._waiting = self._waiting, []
        for item in waiting:
            self._known_keys.add(item.key)
            self._emit(item)

    def _emit(self, item: _Item) -> None:
        if item.origin == HISTORY:
            self._stats.history_fetched += 1
        digest = _digest(item.payload)
        recent = self._recent.get(item.key)
        if recent is not None and digest in recent[1]:
            self._stats.already_recorded += 1
            return
        self._remember(item.key, digest)
        self._write(item)

    def _remember(self, key: str, digest: bytes) -> None:
        order, members = self._recent.setdefault(key, (collections.deque(), set()))
        order.append(digest)
        members.add(digest)
        if len(order) > self._remembered_per_key:
            members.discard(order.popleft())


def _write(writer: McapRecorderWriter, item: _Item, stats: RecorderStats) -> None:
    receive_ns, key, sample_type, payload = item.receive_ns, item.key, item.sample_type, item.payload
    stats.received += 1
    type_name = resolve_type(key, sample_type)
    if type_name is None:
        stats.skipped_unknown += 1
        return
    try:
        message = messages.decode(type_name, payload)
        publish_ns = device_time_ns(message, receive_ns)
        if item.origin == HISTORY and getattr(message, "host_time_ns", 0):
            # from a cache, late: log it when the driver's host received it, where a live recorder would have
            receive_ns = min(receive_ns, int(message.host_time_ns))
    except messages.MessageDecodeError:
        stats.undecodable += 1
        publish_ns = receive_ns
    writer.write(key, type_name, payload, receive_ns, publish_ns)
    stats.written += 1


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


def recorded_tail_in(paths: list[Path], per_topic: int = DEVICE_HISTORY_SAMPLES) -> dict[str, set[bytes]]:
    """Per topic, digests of the last ``per_topic`` messages the (possibly truncated) files hold: all that a
    publisher's history can send again (every message carries its host time, so equal payloads are the same message)."""
    tails: dict[str, collections.deque] = {}
    for path in paths:
        for message in read_messages(path):
            tails.setdefault(message.topic, collections.deque(maxlen=per_topic)).append(_digest(message.data))
    return {topic: set(tail) for topic, tail in tails.items()}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--out", type=Path, required=True,
        help="MCAP file to write; if it exists (a previous run), continue into FILE-001.mcap, FILE-002.mcap...",
    )
    parser.add_argument("--flush-interval", type=float, default=1.0, metavar="S",
                        help="complete a chunk at least this often: the most a crash can lose (default 1 s)")
    parser.add_argument("--history", action=argparse.BooleanOptionalAction, default=True,
                        help="on start (and for each device key that appears later) fetch what the device publishers "
                             "keep, the last 1000 messages per key, leaving out what earlier parts hold (default: on)")
    parser.add_argument("--history-timeout", type=float, default=DEFAULT_HISTORY_TIMEOUT_S, metavar="S",
                        help="longest wait for a history fetch; that key's live messages wait with it (default 10 s)")
    parser.add_argument("--key", default=topics.ALL_TOPICS, help="key expression to record (default: msk/**)")
    parser.add_argument("--duration", type=float, default=None, help="seconds to record (default: until Ctrl-C)")
    parser.add_argument("--ready-key", default=None, help=argparse.SUPPRESS)  # graph readiness (services.graph)
    add_zenoh_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    if not args.flush_interval > 0:
        raise ConfigError("must be positive", field="--flush-interval", value=args.flush_interval)
    if not args.history_timeout > 0:
        raise ConfigError("must be positive", field="--history-timeout", value=args.history_timeout)
    previous = part_paths(args.out)
    out = next_part_path(args.out)
    already_recorded = recorded_tail_in(previous) if previous else None
    print(f"recording {args.key} to {out}" + (f" (continuing {len(previous)} earlier part(s))" if previous else ""),
          file=sys.stderr, flush=True)
    ready = None
    if args.ready_key:
        session, node = topics.split_key(args.ready_key)[0], args.ready_key.rsplit("/", 1)[-1]
        ready = ReadySpec(session, node)
    stats = main(options_from_args(args), out, key_expr=args.key, duration_s=args.duration, stop_event=stop,
                 flush_interval_s=args.flush_interval, history=args.history, history_timeout_s=args.history_timeout,
                 already_recorded=already_recorded,
                 ready_key=ready)
    print(
        f"recorded {stats.written} messages to {out}"
        + (f"; skipped {stats.skipped_unknown} on keys of unknown type" if stats.skipped_unknown else "")
        + (f"; {stats.undecodable} undecodable" if stats.undecodable else "")
        + (f"; history: {stats.history_fetched} messages from the publishers' caches" if stats.history_fetched else "")
        + (f" ({stats.history_errors} error replies)" if stats.history_errors else "")
        + (f"; left out {stats.already_recorded} already recorded" if stats.already_recorded else ""),
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(_parser)
    sys.exit(run_from_args(_parser.parse_args()))
