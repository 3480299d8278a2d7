"""The session graph, declared once: which nodes run, the role each runs as, the topics each publishes and reads.

Everything that wires nodes together is derived from :data:`NODES` and :data:`CLIENTS`:

* ``msk live`` starts the nodes of :func:`live_nodes` and lets each publisher wait for the nodes that read what it
  publishes (:func:`readers_of`), so no first message is lost;
* the access-control policy of the secured router (:func:`role_policies`, used by ``services.transport.security``) lets each
  role publish and read exactly the keys of its nodes, plus the readiness tokens under ``msk/<s>/graph/``;
* ``docker-compose.yml`` and ``docker-compose.secure.yml`` are generated from it (``services.sessions.deploy_files``;
  ``tests/test_compose.py`` checks the committed files are what it generates).

Topic templates are those of :data:`services.transport.topics.TOPIC_TABLE` (``"emg/<source>"``); :data:`EVERY_TOPIC` stands for
all of them and :data:`OWN_STATUS` for ``status/<the node's own name>`` (a node reports its inputs there,
``services.nodes.node_runtime.StatusReporter``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import zenoh

from msk_core.errors import ConfigError
from services.transport import topics

EVERY_TOPIC = "**"
#: the session's one-chunk topics (joints, load, envelopes) in one subscription ``msk/<s>/*``: a reader that needs a
#: load event and the joint frames after it in their publication order reads them so
SESSION_TOPICS = "*"
OWN_STATUS = "status/<self>"
DEVICE_STATUS = "status/<device>"


@dataclass(frozen=True)
class NodeDecl:
    """One participant of a session: a node of the graph (declares a readiness token) or a client (reads or
    publishes without being waited for)."""

    name: str
    role: str
    publishes: tuple[str, ...] = ()
    subscribes: tuple[str, ...] = ()
    #: the msk sub-command that runs it (compose files); "" for participants that are part of another command
    command: str = ""
    #: a node (readiness token ``msk/<s>/graph/<name>``) or a client (no token)
    is_node: bool = True

    def publish_keys(self) -> tuple[str, ...]:
        """Key expressions after ``msk/<session>/`` that this participant publishes on."""
        return tuple(_key(t, self.name) for t in self.publishes)

    def subscribe_keys(self) -> tuple[str, ...]:
        return tuple(_key(t, self.name) for t in self.subscribes)


def _key(template: str, own_name: str) -> str:
    if template in (EVERY_TOPIC, SESSION_TOPICS):
        return template
    if template == OWN_STATUS:
        return f"status/{own_name}"
    known = {t for t, _ in topics.TOPIC_TABLE}
    if template not in known:
        raise ConfigError(
            f"not a topic template of services/transport/topics.py (known: {sorted(known)})",
            field="template",
            value=template,
        )
    # a trailing <name> chunk as **: a reader may subscribe to emg/* or emg/** alike and the access control lets
    # both through (every key actually published is one chunk deep: services.transport.topics.check_chunk)
    parts = template.split("/")
    return "/".join(("**" if i == len(parts) - 1 else "*") if p.startswith("<") else p for i, p in enumerate(parts))


#: The nodes of a live session. ``monitor`` is ``msk live`` itself: it publishes the session facts (exercise, load,
#: set) and watches the flow so that the stop waits until every joint frame is answered.
NODES: dict[str, NodeDecl] = {
    n.name: n
    for n in (
        NodeDecl("recorder", "recorder", publishes=(OWN_STATUS,), subscribes=(EVERY_TOPIC,), command="recorder"),
        # the estimator reads the trackers' and the EMG sensors' accelerations to measure the EMG clock against each
        # tracker's (msk_core/estimate/clock_alignment.py)
        NodeDecl(
            "estimator",
            "estimator",
            publishes=("activations/<method>", "envelopes", OWN_STATUS),
            subscribes=(SESSION_TOPICS, "emg/<source>", "acc/<source>", "imu/<tracker>"),
            command="estimator",
        ),
        NodeDecl(
            "kinematics",
            "kinematics",
            publishes=("joints", OWN_STATUS),
            subscribes=("imu/<tracker>",),
            command="kinematics",
        ),
        NodeDecl(
            "drivers-trigno", "driver", publishes=("emg/<source>", "acc/<source>", DEVICE_STATUS), command="drivers"
        ),
        NodeDecl("drivers-xsens", "driver", publishes=("imu/<tracker>", DEVICE_STATUS), command="drivers"),
        NodeDecl(
            "monitor", "operator", publishes=("load",), subscribes=("joints", "activations/<method>", DEVICE_STATUS)
        ),
    )
}

#: Participants that join a session without being one of its nodes.
CLIENTS: dict[str, NodeDecl] = {
    n.name: n
    for n in (
        # a second terminal's view, dashboard, `msk subscribe` and `msk load` on the rack PC
        NodeDecl("operator", "operator", publishes=("load",), subscribes=(EVERY_TOPIC,), is_node=False),
        # a coach's tablet: what the estimator says and whether the devices deliver, nothing else
        NodeDecl(
            "tablet", "tablet", subscribes=("activations/<method>", DEVICE_STATUS), command="dashboard", is_node=False
        ),
        # `msk replay`: a recording's device data, load and joints back on the wire
        NodeDecl(
            "replayer",
            "replayer",
            publishes=("emg/<source>", "acc/<source>", "imu/<tracker>", DEVICE_STATUS, "load", "joints"),
            command="replay",
            is_node=False,
        ),
    )
}


def live_nodes(*, trigno: bool, xsens: bool) -> list[NodeDecl]:
    """The nodes ``msk live`` starts, in start order (readers before the publishers that wait for them)."""
    names = ["recorder", "monitor", "estimator", "kinematics"]
    names += ["drivers-trigno"] if trigno else []
    names += ["drivers-xsens"] if xsens else []
    return [NODES[n] for n in names]


def instance(kind: str, name: str) -> NodeDecl:
    """A node of kind ``kind`` (a key of :data:`NODES`) under another name, e.g. one estimator per exercise in the
    demo (``estimator-deadlift``)."""
    return dataclasses.replace(NODES[kind], name=name)


def _matches(published: str, subscribed: str) -> bool:
    # what is published is one chunk deep under a <name> part: emg/** stands for emg/<source> here
    concrete = published[: -len("**")] + "*" if published.endswith("/**") else published
    return zenoh.KeyExpr(f"s/{concrete}").intersects(zenoh.KeyExpr(f"s/{subscribed}"))


def readers_of(node: NodeDecl, graph: list[NodeDecl]) -> tuple[str, ...]:
    """The nodes started before ``node`` in ``graph`` that read something it publishes: it waits for their
    readiness before it declares its own (services.nodes.readiness.ReadySpec.after). Only earlier nodes, so the waits never
    form a cycle; a node started later that reads from an earlier one (the estimator reading msk live's load)
    is covered by the start order: ``msk live`` publishes the session facts once the whole graph is ready."""
    earlier = graph[: graph.index(node)]
    return tuple(
        other.name
        for other in earlier
        if other.is_node and any(_matches(p, s) for p in node.publish_keys() for s in other.subscribe_keys())
    )


def start_declared(declared: list[NodeDecl], start: Callable[[NodeDecl, tuple[str, ...]], None]) -> None:
    """Start the nodes of a declared graph in its order, each told the earlier nodes that read what it publishes
    (:func:`readers_of`, its ``after``): ``start(node, after)`` adds it to a :class:`services.sessions.graph.Graph` as a
    thread or a process. ``msk live`` and ``msk demo`` start their graphs through it."""
    for node in declared:
        start(node, readers_of(node, declared))


@dataclass(frozen=True)
class RoleKeys:
    """What one role may do, as key expressions under ``msk/*/``: publish, subscribe, declare readiness tokens and
    watch them."""

    publish: tuple[str, ...]
    subscribe: tuple[str, ...]
    tokens: tuple[str, ...]
    watches_tokens: bool


def role_keys() -> dict[str, RoleKeys]:
    """Per role, the union of its participants' keys (sorted, without duplicates)."""
    grouped: dict[str, list[NodeDecl]] = {}
    for decl in [*NODES.values(), *CLIENTS.values()]:
        grouped.setdefault(decl.role, []).append(decl)
    keys = {}
    for role, decls in grouped.items():
        publish = _collapse(k for d in decls for k in d.publish_keys())
        subscribe = _collapse(k for d in decls for k in d.subscribe_keys())
        tokens = tuple(sorted(f"{topics.GRAPH_CHUNK}/{d.name}" for d in decls if d.is_node))
        # every participant that publishes waits for its readers' tokens (and msk live, the operator, for all)
        keys[role] = RoleKeys(publish, subscribe, tokens, watches_tokens=bool(publish) or role == "operator")
    return keys


def _collapse(keys) -> tuple[str, ...]:
    """Sorted unique keys, dropping those another key of the set already covers (``**`` covers all)."""
    unique = sorted(set(keys))
    if EVERY_TOPIC in unique:
        return (EVERY_TOPIC,)
    return tuple(k for k in unique if not any(o != k and _covers(o, k) for o in unique))


def _covers(general: str, specific: str) -> bool:
    return zenoh.KeyExpr(f"s/{general}").includes(zenoh.KeyExpr(f"s/{specific}"))
