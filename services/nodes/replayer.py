"""Replayer node: publishes the messages of an MCAP recording on their keys, through the same Zenoh graph.

``--rate 1`` keeps the original timing (from ``log_time``), ``--rate 2`` plays twice as fast, ``--rate max`` as fast as
the network accepts (blocking congestion control: nothing is dropped). ``--session NAME`` republishes under
``msk/NAME/...``. Run ``python -m services.nodes.replayer FILE.mcap`` or ``msk replay``.

Only messages of the msk types are published: the payloads the recorder kept apart as rejected (and any channel
without an msk protobuf type) are left out and counted per key and reason, never published as typed data.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import zenoh
from tqdm import tqdm

from msk_core.errors import ConfigError
from services.nodes.readiness import wait_for_nodes
from services.transport import topics
from services.transport.mcap_io import ReadReport, check_mcap_magic, chosen_session, read_messages
from services.transport.zenoh_session import (
    ZenohOptions,
    add_zenoh_arguments,
    declare_data_publisher,
    has_subscribers,
    open_session,
    options_from_args,
    run_script,
)


@dataclass
class ReplayStats:
    published: int = 0
    excluded: int = 0
    other_sessions: int = 0  # messages of recorded sessions other than the one played
    truncated: bool = False
    damage: str = ""  # what of the file could not be read (ReadReport.damage_text)
    left_out: dict[tuple[str, str], int] = field(default_factory=dict)  # (topic, reason) -> rejected payloads


def parse_rate(text: str | float | None) -> float | None:
    """'max' -> None (no pacing); a positive number -> speed factor."""
    if text is None or text == "max":
        return None
    try:
        rate = float(text)
    except ValueError:
        raise ConfigError("rate must be a positive number or 'max'", field="--rate", value=text) from None
    if not rate > 0:
        raise ConfigError("rate must be a positive number or 'max'", field="--rate", value=text)
    return rate


def wait_for_subscribers(publisher: zenoh.Publisher, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if has_subscribers(publisher):
            return True
        time.sleep(0.01)
    return False


def main(
    config: ZenohOptions,
    mcap_path: Path,
    *,
    rate: float | None = 1.0,
    session_name: str | None = None,
    wait_subscribers_s: float = 0.0,
    progress: bool = False,
    exclude: tuple[str, ...] = (),
    wait_nodes: tuple[str, ...] = (),
    wait_nodes_s: float = 60.0,
    recorded_session: str | None = None,
) -> ReplayStats:
    """Publish every message of ``mcap_path`` (only recorded session ``recorded_session``'s when given) except those
    whose (renamed) key matches an ``exclude`` key expression.

    ``wait_nodes``: names of graph nodes (:mod:`services.nodes.readiness`) of session ``session_name`` whose subscribers this
    session must know before the first message goes out (:class:`services.nodes.readiness.GraphTimeout` after ``wait_nodes_s``).
    """
    stats = ReplayStats()
    excluded_keys = [zenoh.KeyExpr(pattern) for pattern in exclude]
    keep: dict[str, bool] = {}
    renamed: dict[str, str] = {}  # recorded topic -> key published
    foreign: set[str] = set()  # recorded topics of other sessions than ``recorded_session``
    report = ReadReport()
    publishers: dict[str, zenoh.Publisher] = {}
    with open_session(config) as session:
        if wait_nodes:
            if session_name is None:
                raise ConfigError("waiting for graph nodes needs the session they belong to", field="session_name")
            wait_for_nodes(session, session_name, wait_nodes, wait_nodes_s)
        start: tuple[float, int] | None = None  # (wall clock, log time) of the first message replayed at a rate
        iterator = read_messages(mcap_path, report=report)
        for recorded in tqdm(iterator, desc=f"replay {Path(mcap_path).name}", unit="msg", disable=not progress):
            key = renamed.get(recorded.topic)
            if key is None:  # once per topic, not per message
                key = renamed[recorded.topic] = (
                    topics.rename_session(recorded.topic, session_name) if session_name else recorded.topic
                )
                keep[key] = not any(pattern.intersects(zenoh.KeyExpr(key)) for pattern in excluded_keys)
                if recorded_session is not None and not recorded.topic.startswith(
                    f"{topics.session_prefix(recorded_session)}/"
                ):
                    foreign.add(recorded.topic)
            if recorded.topic in foreign:
                stats.other_sessions += 1
                continue
            if not keep[key]:
                stats.excluded += 1
                continue
            publisher = publishers.get(key)
            if publisher is None:
                # every topic lossless, the newest-wins ones too: a replay reproduces the recording whole (at
                # --rate max a DROP publisher lost activation frames and statuses towards the recorder)
                publisher = declare_data_publisher(session, key, recorded.type_name, delivery=topics.Delivery.LOSSLESS)
                publishers[key] = publisher
                if wait_subscribers_s > 0:
                    wait_for_subscribers(publisher, wait_subscribers_s)
            if rate is not None:
                if start is None:
                    start = (time.monotonic(), recorded.log_time_ns)
                start_wall, start_log = start
                due = start_wall + (recorded.log_time_ns - start_log) / 1e9 / rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            publisher.put(recorded.data)
            stats.published += 1
        for publisher in publishers.values():
            publisher.undeclare()
    stats.truncated = report.truncated
    stats.damage = report.damage_text()
    stats.left_out = dict(report.left_out)
    return stats


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("mcap", type=Path, help="MCAP recording to play")
    parser.add_argument(
        "--rate",
        default="1",
        help="speed factor (1 = original timing) or 'max' (default: 1). Faster than the recording, a live estimator "
        "waits for EMG by the wall clock and aligns the EMG clock on what has arrived, so 'assisted' can differ from "
        "the original without a flag on the frame; to reproduce a session, replay at 1",
    )
    parser.add_argument(
        "--session", default=None, help="republish under msk/<SESSION>/... instead of the recorded session"
    )
    parser.add_argument(
        "--from-session",
        default=None,
        metavar="NAME",
        help="play only recorded session NAME (needed with --session when the recording holds several)",
    )
    parser.add_argument(
        "--exclude",
        action="append",
        default=[],
        metavar="KEYEXPR",
        help="do not publish keys matching this key expression, e.g. 'msk/*/joints' to recompute joints live (repeatable)",
    )
    parser.add_argument(
        "--wait-subscribers",
        type=float,
        default=2.0,
        metavar="S",
        help="wait up to S seconds for a subscriber on each new key before publishing on it (default 2)",
    )
    parser.add_argument(
        "--wait-node",
        action="append",
        default=[],
        metavar="NAME",
        help="publish nothing before graph node NAME of --session has its subscribers up (services.nodes.readiness; repeatable; "
        "an error naming the missing nodes after --wait-nodes-timeout); a node started by hand says so with "
        "--ready-key msk/<session>/graph/NAME",
    )
    parser.add_argument("--wait-nodes-timeout", type=float, default=60.0, metavar="S", help="default 60")
    add_zenoh_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    check_mcap_magic(args.mcap)  # an empty or foreign file is no recording, not one cut short
    if args.session is not None:
        topics.check_chunk(args.session, "--session")  # '' would replay under the recorded name
    # renamed, several recorded sessions would be merged into one: one of them, named, or the only one
    recorded = args.from_session
    if args.session is not None or recorded is not None:
        recorded = chosen_session(args.mcap, recorded, "--from-session")
    stats = main(
        options_from_args(args),
        args.mcap,
        rate=parse_rate(args.rate),
        session_name=args.session,
        wait_subscribers_s=args.wait_subscribers,
        progress=sys.stderr.isatty(),
        exclude=tuple(args.exclude),
        wait_nodes=tuple(args.wait_node),
        wait_nodes_s=args.wait_nodes_timeout,
        recorded_session=recorded,
    )
    note = (
        f" (the recording could not be read whole: {stats.damage}; replayed its readable part)" if stats.damage else ""
    )
    skipped = f", left out {stats.excluded} on excluded keys" if stats.excluded else ""
    if stats.other_sessions:
        skipped += f", left out {stats.other_sessions} of other recorded sessions than {recorded!r}"
    if stats.left_out:
        skipped += (
            f", left out {sum(stats.left_out.values())} rejected payloads ("
            + ", ".join(f"{topic}: {n} {reason}" for (topic, reason), n in sorted(stats.left_out.items()))
            + ")"
        )
    print(f"published {stats.published} messages from {args.mcap}{skipped}{note}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    run_script(__doc__, add_arguments, run_from_args)
