"""Recorder node: subscribes to ``msk/**`` and logs every message to an MCAP file, one channel per key.

Zenoh callbacks only enqueue (receive time stamped on arrival); one writer thread serialises to disk, so a slow disk
never stalls the network threads. Run ``python -m services.recorder --out FILE.mcap`` or ``msk recorder``.

Crashes: a chunk is completed and handed to the OS at least every ``--flush-interval`` seconds (also when data
pauses), so a recorder killed with SIGKILL loses at most what arrived in that interval. Started again with the same
``--out``, it continues into the next free ``FILE-001.mcap``, ``FILE-002.mcap``...: on start it fetches the last
``--history`` seconds the device publishers keep (:func:`services.zenoh_session.declare_history_publisher`) and
leaves out what the previous files already hold, so the parts join without a gap or a duplicate.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
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
    declare_history_subscriber,
    open_session,
    options_from_args,
    type_name_of_sample,
)

DEFAULT_HISTORY_S = 10.0


@dataclass
class RecorderStats:
    received: int = 0
    written: int = 0
    skipped_unknown: int = 0
    undecodable: int = 0
    already_recorded: int = 0  # history samples the previous parts already hold


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
    history_s: float = DEFAULT_HISTORY_S,
    already_recorded: dict[str, set[bytes]] | None = None,
) -> RecorderStats:
    """Record until ``duration_s`` elapses or ``stop_event`` is set. ``stats`` (if given) is updated live.

    ``history_s`` > 0 first fetches what history publishers kept from that many seconds; ``already_recorded`` (topic ->
    digests of the last messages of the previous parts, :func:`recorded_tail_in`) drops what those parts hold.
    """
    stop_event = stop_event or threading.Event()
    stats = stats if stats is not None else RecorderStats()
    inbox: queue.SimpleQueue = queue.SimpleQueue()

    def on_sample(sample: zenoh.Sample) -> None:
        inbox.put((messages.now_ns(), str(sample.key_expr), type_name_of_sample(sample), sample.payload.to_bytes()))

    with open_session(config) as session, McapRecorderWriter(out_path, flush_interval_s=flush_interval_s) as writer:
        if history_s > 0:
            subscriber = declare_history_subscriber(session, key_expr, on_sample, history_s=history_s)
        else:
            subscriber = session.declare_subscriber(key_expr, on_sample)
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
                _write(writer, item, stats, already_recorded)
        finally:
            subscriber.undeclare()
            while True:  # drain what already arrived: nothing received is lost on a clean stop
                try:
                    _write(writer, inbox.get_nowait(), stats, already_recorded)
                except queue.Empty:
                    break
    return stats


def _write(writer: McapRecorderWriter, item, stats: RecorderStats, already_recorded: dict[str, set[bytes]] | None = None) -> None:
    receive_ns, key, sample_type, payload = item
    stats.received += 1
    if already_recorded and _digest(payload) in already_recorded.get(key, ()):
        stats.already_recorded += 1
        return
    type_name = resolve_type(key, sample_type)
    if type_name is None:
        stats.skipped_unknown += 1
        return
    try:
        message = messages.decode(type_name, payload)
        publish_ns = device_time_ns(message, receive_ns)
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
    parser.add_argument("--history", type=float, default=DEFAULT_HISTORY_S, metavar="S",
                        help="on start, fetch what device publishers kept from the last S seconds (default 10; 0: off)")
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
                 flush_interval_s=args.flush_interval, history_s=args.history, already_recorded=already_recorded,
                 ready_key=ready)
    print(
        f"recorded {stats.written} messages to {out}"
        + (f"; skipped {stats.skipped_unknown} on keys of unknown type" if stats.skipped_unknown else "")
        + (f"; {stats.undecodable} undecodable" if stats.undecodable else "")
        + (f"; left out {stats.already_recorded} the earlier parts hold" if stats.already_recorded else ""),
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(_parser)
    sys.exit(run_from_args(_parser.parse_args()))
