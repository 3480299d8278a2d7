"""Readiness of a graph's nodes over Zenoh liveliness, and the bounded wait for it.

A node is ready when its subscribers are declared; it then declares a Zenoh *liveliness token* on
``msk/<session>/graph/<node>`` (:func:`declare_ready`). A publisher that must not lose the first messages (the
replayer, the device drivers of ``msk live``) waits with :func:`wait_for_nodes` until its *own* Zenoh session sees
the token of every node of the graph. A session learns a peer's declarations in the order the peer made them, so a
token seen means that node's subscribers are known to the publisher's session and its data are routed to them.

Why not Zenoh's matching status: it turns true as soon as *one* subscriber matches (e.g. the recorder on ``msk/**``)
while a node that connected later (a kinematics node) is not yet known to the publisher; its first messages went to
the recorder only, and the demo waited for them for ever (issue 15, "start-up races").

Every wait is bounded and, when it expires, raises :class:`GraphTimeout` saying what it waited for and what arrived.
"""

from __future__ import annotations

import argparse
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import zenoh

from msk_core.errors import MskError
from services.transport import topics

GRAPH_CHUNK = topics.GRAPH_CHUNK


class GraphTimeout(MskError):
    """A bounded wait of the graph expired; the message says what was awaited and what arrived (counts)."""


def ready_key(session: str, node: str) -> str:
    return f"{topics.session_prefix(session)}/{GRAPH_CHUNK}/{topics.check_chunk(node, 'node')}"


#: How long a graph waits for its nodes to be ready: a cold start (numba compiling the model kernels in each node, the
#: first time after install) took over 60 s on 2 busy cores; a bound that expires still names the nodes missing.
NODE_READY_TIMEOUT_S = 180.0


@dataclass(frozen=True)
class ReadySpec:
    """How a node says it is ready: its token key and the nodes it publishes to (``after``), which its own session
    must know before the token is declared, so the node's first published messages reach them too."""

    session: str
    node: str
    after: tuple[str, ...] = ()
    timeout_s: float = NODE_READY_TIMEOUT_S

    @property
    def key(self) -> str:
        return ready_key(self.session, self.node)


def add_ready_arguments(parser: argparse.ArgumentParser) -> None:
    """A node process's readiness flags: :meth:`services.sessions.graph.Graph.add_process` appends them (its
    token key ``msk/<session>/graph/<node>`` and, repeated, the nodes it publishes to); :func:`ready_from_args`."""
    parser.add_argument(
        "--ready-key",
        default=None,
        metavar="KEY",
        help="declare this node ready on msk/<session>/graph/<name> once its subscribers are up (msk live sets it; "
        "for a node started by hand, what `msk replay --wait-node <name>` waits for)",
    )
    parser.add_argument("--ready-after", action="append", default=[], help=argparse.SUPPRESS)


def ready_from_args(args: argparse.Namespace) -> ReadySpec | None:
    """The :class:`ReadySpec` of :func:`add_ready_arguments`' flags (session and node from the token key); None
    without ``--ready-key`` (a node started by hand declares no token)."""
    if not args.ready_key:
        return None
    session, rest = topics.split_key(args.ready_key)
    return ReadySpec(session, rest.rsplit("/", 1)[-1], tuple(args.ready_after))


def declare_ready(zsession: zenoh.Session, spec: ReadySpec | None):
    """Say "my subscribers are declared" (call after declaring them); keep the returned token for the node's life.

    With ``spec.after``, first wait (bounded) until this session knows those nodes' subscribers."""
    if spec is None:
        return None
    if spec.after:
        wait_for_nodes(zsession, spec.session, spec.after, spec.timeout_s)
    return zsession.liveliness().declare_token(spec.key)


def wait_for_nodes(
    zsession: zenoh.Session,
    session: str,
    nodes: Sequence[str],
    timeout_s: float,
    give_up: Callable[[], str | None] | None = None,
) -> float:
    """Block until ``zsession`` sees the readiness token of every node in ``nodes``; return the seconds waited.

    Raises :class:`GraphTimeout` naming the nodes still missing when ``timeout_s`` expires, or at once (checked every
    0.1 s) when ``give_up`` returns a reason, e.g. a node process that exited: nothing is waited for that cannot come.
    """
    wanted = {ready_key(session, n): n for n in nodes}
    if not wanted:
        return 0.0
    seen: set[str] = set()
    changed = threading.Condition()

    def on_token(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with changed:
            if sample.kind == zenoh.SampleKind.PUT:
                seen.add(key)
            else:
                seen.discard(key)
            changed.notify_all()

    started = time.monotonic()
    deadline = started + timeout_s
    subscriber = zsession.liveliness().declare_subscriber(
        f"{topics.session_prefix(session)}/{GRAPH_CHUNK}/*", on_token, history=True
    )
    try:
        with changed:
            while not set(wanted) <= seen:
                left = deadline - time.monotonic()
                if left <= 0:
                    missing = sorted(n for k, n in wanted.items() if k not in seen)
                    raise GraphTimeout(
                        f"waited {timeout_s:g} s for {len(wanted)} nodes of session {session!r} to be ready: "
                        f"{len(wanted) - len(missing)} ready, missing {missing}"
                    )
                reason = give_up() if give_up is not None else None
                if reason:
                    missing = sorted(n for k, n in wanted.items() if k not in seen)
                    raise GraphTimeout(
                        f"stopped waiting for {len(wanted)} nodes of session {session!r} to be ready after "
                        f"{time.monotonic() - started:.1f} s: {reason}; {len(wanted) - len(missing)} ready, "
                        f"missing {missing}"
                    )
                changed.wait(min(left, 0.1))
    finally:
        subscriber.undeclare()
    return time.monotonic() - started
