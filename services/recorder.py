"""Recorder node: subscribes to ``msk/**`` and logs every message to an MCAP file, one channel per key.

Zenoh callbacks only enqueue (receive time stamped on arrival); one writer thread serialises to disk, so a slow disk
never stalls the network threads. Run ``python -m services.recorder --out FILE.mcap`` or ``msk recorder``.
"""

from __future__ import annotations

import argparse
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
from services.zenoh_session import ZenohOptions, add_zenoh_arguments, open_session, options_from_args, type_name_of_sample


@dataclass
class RecorderStats:
    received: int = 0
    written: int = 0
    skipped_unknown: int = 0
    undecodable: int = 0


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
) -> RecorderStats:
    """Record until ``duration_s`` elapses or ``stop_event`` is set. ``stats`` (if given) is updated live."""
    stop_event = stop_event or threading.Event()
    stats = stats if stats is not None else RecorderStats()
    inbox: queue.SimpleQueue = queue.SimpleQueue()

    def on_sample(sample: zenoh.Sample) -> None:
        inbox.put((messages.now_ns(), str(sample.key_expr), type_name_of_sample(sample), sample.payload.to_bytes()))

    with open_session(config) as session, McapRecorderWriter(out_path, flush_interval_s=flush_interval_s) as writer:
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
                    continue
                _write(writer, item, stats)
        finally:
            subscriber.undeclare()
            while True:  # drain what already arrived: nothing received is lost on a clean stop
                try:
                    _write(writer, inbox.get_nowait(), stats)
                except queue.Empty:
                    break
    return stats


def _write(writer: McapRecorderWriter, item, stats: RecorderStats) -> None:
    receive_ns, key, sample_type, payload = item
    stats.received += 1
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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="MCAP file to write")
    parser.add_argument("--key", default=topics.ALL_TOPICS, help="key expression to record (default: msk/**)")
    parser.add_argument("--duration", type=float, default=None, help="seconds to record (default: until Ctrl-C)")
    parser.add_argument("--ready-key", default=None, help=argparse.SUPPRESS)  # graph readiness (services.graph)
    add_zenoh_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    print(f"recording {args.key} to {args.out}", file=sys.stderr, flush=True)
    ready = None
    if args.ready_key:
        session, node = topics.split_key(args.ready_key)[0], args.ready_key.rsplit("/", 1)[-1]
        ready = ReadySpec(session, node)
    stats = main(options_from_args(args), args.out, key_expr=args.key, duration_s=args.duration, stop_event=stop,
                 ready_key=ready)
    print(
        f"recorded {stats.written} messages to {args.out}"
        + (f"; skipped {stats.skipped_unknown} on keys of unknown type" if stats.skipped_unknown else "")
        + (f"; {stats.undecodable} undecodable" if stats.undecodable else ""),
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    _parser = argparse.ArgumentParser(description=__doc__)
    add_arguments(_parser)
    sys.exit(run_from_args(_parser.parse_args()))
