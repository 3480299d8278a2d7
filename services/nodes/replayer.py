"""Replayer node: publishes the messages of an MCAP recording on their keys, through the same Zenoh graph.

``--rate 1`` keeps the original timing (from ``log_time``), ``--rate 2`` plays twice as fast, ``--rate max`` as fast as
the network accepts (blocking congestion control: nothing is dropped). ``--session NAME`` republishes under
``msk/NAME/...``. Run ``python -m services.nodes.replayer FILE.mcap`` or ``msk replay``.

Only messages of the msk types are published: the payloads the recorder kept apart as rejected (and any channel
without an msk protobuf type) are left out and counted per key and reason, never published as typed data.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import zenoh
from tqdm import tqdm

from msk_core.errors import ConfigError
from services.nodes.readiness import wait_for_nodes
from services.transport import topics
from services.transport.mcap_io import (
    ReadReport,
    channel_kind,
    check_mcap_magic,
    chosen_session,
    file_summary,
    read_messages,
)
from services.transport.zenoh_session import (
    ZenohOptions,
    add_zenoh_arguments,
    declare_data_publisher,
    has_subscribers,
    open_session,
    options_from_args,
    run_script,
)

log = logging.getLogger(__name__)
#: How long a put may wait for a slow reader before Zenoh lets that reader go (its link closed): longer than a live
#: node's 5 s, since a replay has no latency to keep. A reader far slower than the replay can still lose its link
#: (docs/topics.md, "Known limit").
REPLAY_BLOCK_CLOSE_S = 60.0


@dataclass
class ReplayStats:
    published: int = 0
    excluded: int = 0
    other_sessions: int = 0  # messages of recorded sessions other than the one played
    truncated: bool = False
    damage: str = ""  # what of the file could not be read (ReadReport.damage_text)
    left_out: dict[tuple[str, str], int] = field(default_factory=dict)  # (topic, reason) -> rejected payloads
    refused: dict[str, int] = field(default_factory=dict)  # key -> messages its role may not publish (not sent)
    role: str | None = None  # the role it published as (secured network), which may not publish those
    unread: list[str] = field(default_factory=list)  # keys with no subscriber after the wait (published anyway)

    def count_left_out(self, key: str, fate: str) -> None:
        """One message not published: of another recorded session, on an excluded key, or refused to the role."""
        if fate == OTHER_SESSION:
            self.other_sessions += 1
        elif fate == EXCLUDED:
            self.excluded += 1
        else:
            self.refused[key] = self.refused.get(key, 0) + 1


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


class Routes:
    """Where each recorded topic goes, decided once per topic: the key it is published on (renamed to
    ``session_name``) and its fate: :data:`PUBLISH`, or left out as :data:`OTHER_SESSION` (not of
    ``recorded_session``), :data:`EXCLUDED` (matches an ``exclude`` key expression) or :data:`REFUSED` (a key that
    ``role``, the secured network's access control, may not publish: the router would drop it without a word)."""

    def __init__(
        self,
        role: str | None,
        session_name: str | None = None,
        recorded_session: str | None = None,
        exclude: tuple[str, ...] = (),
    ) -> None:
        self.role = role
        self._session_name = session_name
        self._recorded_session = recorded_session
        self._excluded = [zenoh.KeyExpr(pattern) for pattern in exclude]
        self._routes: dict[str, tuple[str, str]] = {}
        self.refusal = ""  # the access control's words for the first key refused

    def of(self, topic: str) -> tuple[str, str]:
        """(key, fate) of recorded ``topic``."""
        route = self._routes.get(topic)
        if route is None:
            route = self._routes[topic] = self._route(topic)
        return route

    def _route(self, topic: str) -> tuple[str, str]:
        key = topics.rename_session(topic, self._session_name) if self._session_name else topic
        if self._recorded_session is not None and not topic.startswith(
            f"{topics.session_prefix(self._recorded_session)}/"
        ):
            return key, OTHER_SESSION
        if any(pattern.intersects(zenoh.KeyExpr(key)) for pattern in self._excluded):
            return key, EXCLUDED
        if self.role is not None:
            from services.transport.security import refused

            reason = refused(self.role, "publish", key)
            if reason is not None:
                self.refusal = self.refusal or reason
                return key, REFUSED
        return key, PUBLISH


PUBLISH, OTHER_SESSION, EXCLUDED, REFUSED = "publish", "other session", "excluded", "refused"


def topic_counts(mcap_path: Path) -> Counter[str]:
    """Messages per topic that :func:`read_messages` hands out (its typed channels): from the file's statistics, or
    read through when it has none (a file cut short)."""
    counts: Counter[str] = Counter()
    summary = file_summary(Path(mcap_path))
    if summary is not None and summary.statistics is not None:
        per_channel = summary.statistics.channel_message_counts
        for channel in summary.channels.values():
            if channel_kind(channel, summary.schemas.get(channel.schema_id))[0]:
                counts[channel.topic] += per_channel.get(channel.id, 0)
        return counts
    for recorded in read_messages(mcap_path):
        counts[recorded.topic] += 1
    return counts


def check_publishable(routes: Routes, mcap_path: Path, config_file: Path | None) -> dict[str, int]:
    """Before publishing: the keys of the recording that ``routes``' role may not publish, with their message
    counts, said on stderr one per key; a :class:`ConfigError` when it may publish none of what it would play."""
    if routes.role is None:
        return {}
    refused: Counter[str] = Counter()
    publishable = 0
    for topic, count in topic_counts(mcap_path).items():
        key, fate = routes.of(topic)
        if fate == REFUSED:
            refused[key] += count
        elif fate == PUBLISH:
            publishable += count
    if not refused:
        return {}
    if not publishable:
        raise ConfigError(
            f"{routes.refusal.split(';')[0]}: the router would drop all {sum(refused.values())} messages of "
            f"{Path(mcap_path).name} it would play ({len(refused)} keys)",
            path=config_file,
        )
    print(
        f"replay: {routes.refusal.split(';')[0]}: not sending the {sum(refused.values())} messages on "
        f"{len(refused)} keys the router would drop:",
        file=sys.stderr,
    )
    for key, count in sorted(refused.items()):
        print(f"replay:   {key}: {count} message{'s' if count != 1 else ''}", file=sys.stderr)
    sys.stderr.flush()
    return dict(refused)


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
    whose (renamed) key matches an ``exclude`` key expression, and those the role of ``config`` may not publish
    (:func:`check_publishable`: said before the first message; none publishable is a :class:`ConfigError`).

    ``wait_nodes``: names of graph nodes (:mod:`services.nodes.readiness`) of session ``session_name`` whose subscribers this
    session must know before the first message goes out (:class:`services.nodes.readiness.GraphTimeout` after ``wait_nodes_s``).
    """
    stats = ReplayStats()
    routes = Routes(config.role, session_name, recorded_session, exclude)
    check_publishable(routes, mcap_path, config.config_file)
    stats.role = routes.role
    report = ReadReport()
    publishers: dict[str, zenoh.Publisher] = {}
    sequence: dict[str, int] = {}  # key -> the number of its last publication
    # a reader slower than the replay (a recorder on a busy machine) slows it for up to REPLAY_BLOCK_CLOSE_S a put,
    # where Zenoh lets it go after 5 s; a reader hung longer is still let go
    with open_session(replace(config, block_close_s=config.block_close_s or REPLAY_BLOCK_CLOSE_S)) as session:
        if wait_nodes:
            if session_name is None:
                raise ConfigError("waiting for graph nodes needs the session they belong to", field="session_name")
            wait_for_nodes(session, session_name, wait_nodes, wait_nodes_s)
        start: tuple[float, int] | None = None  # (wall clock, log time) of the first message replayed at a rate
        iterator = read_messages(mcap_path, report=report)
        for recorded in tqdm(iterator, desc=f"replay {Path(mcap_path).name}", unit="msg", disable=not progress):
            key, fate = routes.of(recorded.topic)  # once per topic, not per message
            if fate != PUBLISH:
                stats.count_left_out(key, fate)
                continue
            publisher = publishers.get(key)
            if publisher is None:
                # every topic lossless, the newest-wins ones too: a replay reproduces the recording whole (at
                # --rate max a DROP publisher lost activation frames and statuses towards the recorder)
                publisher = declare_data_publisher(session, key, recorded.type_name, delivery=topics.Delivery.LOSSLESS)
                publishers[key] = publisher
                if wait_subscribers_s > 0:
                    waited_from = time.monotonic()
                    if not wait_for_subscribers(publisher, wait_subscribers_s):
                        stats.unread.append(key)
                        log.info("waited %g s for a subscriber of %s: none; publishing anyway", wait_subscribers_s, key)
                    if start is not None:  # the paced clock does not count the wait: no burst after it
                        start = (start[0] + time.monotonic() - waited_from, start[1])
            if rate is not None:
                if start is None:
                    start = (time.monotonic(), recorded.log_time_ns)
                start_wall, start_log = start
                due = start_wall + (recorded.log_time_ns - start_log) / 1e9 / rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            # numbered per key, as the drivers' publications are: a reader that misses some counts them
            sequence[key] = sequence.get(key, 0) + 1
            publisher.put(recorded.data, source_info=zenoh.SourceInfo(publisher.id, sequence[key]))
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
    if stats.refused:
        skipped += (
            f"; refused {sum(stats.refused.values())} on {len(stats.refused)} keys role {stats.role!r} may not "
            "publish (the router would drop them), not sent"
        )
    if stats.unread:
        skipped += (
            f"; no subscriber within {args.wait_subscribers:g} s on {len(stats.unread)} of the keys ("
            + ", ".join(stats.unread[:3])
            + (", ..." if len(stats.unread) > 3 else "")
            + "): is the reader running, on this --session?"
        )
    print(f"published {stats.published} messages from {args.mcap}{skipped}{note}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    run_script(__doc__, add_arguments, run_from_args)
