"""Opening Zenoh sessions and declaring loss-free publishers, the same way in every node.

Default: a peer that listens on loopback only and finds other peers by multicast scouting on loopback... is not
reliable in containers, so nodes instead agree on one well-known loopback endpoint: the first node to start
listens on it, the others connect to it (peer mode gossips the rest). Everything can be overridden by flags
(``--mode``, ``--connect``, ``--listen``) or a JSON5 config file (``--zenoh-config``).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import zenoh
from google.protobuf.message import Message

from msk_core.errors import ConfigError
from services.transport import messages, topics

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
LOOPBACK_ANY_PORT = "tcp/127.0.0.1:0"


@dataclass(frozen=True)
class ZenohOptions:
    """How a node joins the Zenoh network.

    ``connect``/``listen`` empty means: listen on :data:`DEFAULT_ENDPOINT` if it is free, else connect to it.
    Without a config file a node never listens beyond loopback unless told to with ``listen`` (Zenoh's own default
    for a peer is every interface). ``mode`` None: the config file's mode, else peer.
    """

    mode: str | None = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: Path | None = None
    multicast_scouting: bool = False
    #: how long a lossless put may wait for a slow reader before Zenoh closes that reader's link (None: Zenoh's 5 s);
    #: a replay at --rate max waits longer (services.nodes.replayer), a live node must not
    block_close_s: float | None = None

    @property
    def role(self) -> str | None:
        """The access-control role this node joins with (secured configs of ``msk certs``), else None."""
        if self.config_file is None:
            return None
        from services.transport.security import role_of_config  # security builds on this module

        return role_of_config(self.config_file)

    def to_config(self) -> zenoh.Config:
        if self.config_file is not None:
            path = Path(self.config_file)
            if not path.is_file():
                raise ConfigError("Zenoh config file not found", path=path)
            try:
                config = zenoh.Config.from_file(str(path))
            except Exception as error:  # zenoh raises its own ZError with the parser's message
                raise ConfigError(f"invalid Zenoh config: {error}", path=path) from error
        else:
            config = zenoh.Config()
        mode = self.mode if self.mode is not None else (None if self.config_file is not None else "peer")
        if mode is not None:
            if mode not in ("peer", "client", "router"):
                raise ConfigError("Zenoh mode must be peer, client or router", field="mode", value=mode)
            config.insert_json5("mode", json.dumps(mode))
        connect, listen = list(self.connect), list(self.listen)
        if self.config_file is None and not connect and not listen:
            if endpoint_is_free(DEFAULT_ENDPOINT):
                listen = [DEFAULT_ENDPOINT]
            else:
                connect = [DEFAULT_ENDPOINT]
        if self.config_file is None and not listen and mode in ("peer", "router"):
            listen = [LOOPBACK_ANY_PORT]  # Zenoh would listen on tcp/[::]:0 (every interface) otherwise
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(connect))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(listen))
        if self.config_file is None:
            config.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if self.block_close_s is not None:
            config.insert_json5(
                "transport/link/tx/queue/congestion_control/block/wait_before_close", str(int(self.block_close_s * 1e6))
            )
        return config


def endpoint_is_free(endpoint: str) -> bool:
    proto, _, address = endpoint.partition("/")
    if proto != "tcp":
        return True
    host, _, port = address.rpartition(":")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        # as Zenoh's own listener: a port whose last connections wait in TIME_WAIT (a session just stopped) is free,
        # and one with a listener is not (Linux refuses that bind even so); without it a restart was refused ~1 min
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, int(port)))
        except OSError:
            return False
    return True


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("Zenoh")
    group.add_argument(
        "--mode",
        choices=["peer", "client", "router"],
        default=None,
        help="Zenoh mode (default: the --zenoh-config file's, else peer)",
    )
    group.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/10.0.0.2:7447 (repeatable)",
    )
    group.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeatable)",
    )
    group.add_argument(
        "--zenoh-config", type=Path, default=None, metavar="FILE.json5", help="Zenoh JSON5 configuration file"
    )


#: Zenoh's link protocols whose address is HOST:PORT (others, e.g. unixsock-stream/PATH, are passed on as given).
HOST_PORT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")


def check_endpoint(endpoint: str, field: str) -> str:
    """``endpoint`` when Zenoh reads it (``PROTOCOL/ADDRESS[?METADATA][#CONFIG]``) and, for the protocols whose
    address is HOST:PORT, it has a host and a port in 0..65535; else a :class:`ConfigError` naming ``field``. Zenoh
    itself refuses a bad one only when a node opens its session, after a whole graph has been started."""
    try:
        zenoh.Config().insert_json5("connect/endpoints", json.dumps([endpoint]))
    except Exception:  # zenoh's ZError, with a parser's trace
        raise ConfigError(
            "not a Zenoh endpoint: PROTOCOL/ADDRESS[?METADATA][#CONFIG], e.g. tcp/127.0.0.1:7447",
            field=field,
            value=endpoint,
        ) from None
    protocol, _, address = endpoint.partition("/")
    host, _, port = re.split(r"[?#]", address, maxsplit=1)[0].rpartition(":")
    if protocol in HOST_PORT_PROTOCOLS and not (host and port.isdigit() and int(port) < 65536):
        raise ConfigError(
            f"a {protocol} endpoint is {protocol}/HOST:PORT, e.g. tcp/127.0.0.1:7447", field=field, value=endpoint
        )
    return endpoint


def options_from_args(args: argparse.Namespace) -> ZenohOptions:
    return ZenohOptions(
        mode=args.mode,
        connect=tuple(check_endpoint(e, "--connect") for e in args.connect),
        listen=tuple(check_endpoint(e, "--listen") for e in args.listen),
        config_file=args.zenoh_config,
    )


def run_script(
    description: str | None,
    add_arguments: Callable[[argparse.ArgumentParser], None],
    run_from_args: Callable[[argparse.Namespace], int],
    *,
    log_level: int | None = None,
) -> NoReturn:
    """The ``python -m services...`` entry of a node or page: its arguments (``add_arguments``) parsed from the
    command line, ``run_from_args`` run, its result the exit status; ``log_level`` also configures logging."""
    if log_level is not None:
        logging.basicConfig(level=log_level)
    parser = argparse.ArgumentParser(description=description)
    add_arguments(parser)
    sys.exit(run_from_args(parser.parse_args()))


class SessionUnavailable(ConfigError):
    """Zenoh could not open the session (an endpoint already in use, nobody answering a client): ``reason`` is
    Zenoh's own words, without the source location it appends."""

    def __init__(self, reason: str, options: ZenohOptions) -> None:
        self.reason = reason
        flag, where = ("--listen", options.listen) if options.listen else ("--connect", options.connect)
        super().__init__(
            f"cannot open the Zenoh session: {reason}",
            field=flag if where else "zenoh",
            value=", ".join(where) or (str(options.config_file) if options.config_file else None),
        )


#: Zenoh's words when a client reached none of its endpoints.
UNABLE_TO_CONNECT = "Unable to connect"
#: A Zenoh client tries its endpoints once; a router still starting (or restarting), or a TLS handshake on a busy
#: machine, made a node fail at once (seen on CI: a secured session's monitor). Bounded: a client nobody answers is
#: said after these attempts, with their count.
CLIENT_CONNECT_ATTEMPTS = 4
CLIENT_CONNECT_RETRY_S = 0.5


def open_session(options: ZenohOptions | None = None) -> zenoh.Session:
    """Open a Zenoh session; use it as ``with open_session(options) as session:``. Raises :class:`SessionUnavailable`
    (a :class:`ConfigError`, said in one line by the CLI) where Zenoh refuses, e.g. a listen endpoint in use or a
    client that reached none of its endpoints in :data:`CLIENT_CONNECT_ATTEMPTS` tries, and a
    :class:`ConfigError` naming the file and its field when a TLS file the config names is unusable (:func:`check_tls`)."""
    options = options or ZenohOptions()
    config = options.to_config()
    check_tls(config, options.config_file)
    started = time.monotonic()
    for attempt in range(1, CLIENT_CONNECT_ATTEMPTS + 1):
        try:
            return zenoh.open(config)
        except zenoh.ZError as error:  # its message ends in the Rust source location
            reason = str(error).split(" at /")[0].strip()
        if not reason.startswith(UNABLE_TO_CONNECT) or attempt == CLIENT_CONNECT_ATTEMPTS:
            break
        time.sleep(CLIENT_CONNECT_RETRY_S)
    if reason.startswith(UNABLE_TO_CONNECT):
        reason += f" ({attempt} attempts over {time.monotonic() - started:.1f} s)"
    raise SessionUnavailable(reason, options) from None


def check_tls(config: zenoh.Config, named_by: Path | None = None) -> None:
    """The files a config's TLS section names (certificates, keys, CA), checked before Zenoh opens the session
    (:func:`services.transport.security.check_zenoh_tls`): Zenoh refuses a missing, expired, foreign or mismatched
    one only as "Unable to connect" (a client) or "Cannot create a new TLS listener" (a router), naming no file."""
    from services.transport.security import check_zenoh_tls  # security builds on this module

    try:
        tls = json.loads(config.get_json("transport/link/tls"))
    except Exception:  # zenoh's ZError: no such section in this Zenoh version
        return
    if isinstance(tls, dict):
        check_zenoh_tls(tls, named_by)


def declare_data_publisher(
    session: zenoh.Session, key: str, type_name: str, *, delivery: topics.Delivery | None = None
) -> zenoh.Publisher:
    """A reliable publisher with protobuf encoding and the topic's delivery policy (:data:`services.transport.topics.DELIVERY`).

    Lossless topics block under congestion (a slow subscriber slows the publisher, nothing is dropped); newest-wins
    topics drop, per subscriber link, what a full queue cannot take, so a hung view never stalls its publisher.
    """
    messages.message_class(type_name)  # fail early on an unknown type
    if delivery is None:
        try:
            delivery = topics.delivery_for_key(key)
        except ConfigError:  # not an msk/<session>/... key
            delivery = topics.Delivery.LOSSLESS
    return session.declare_publisher(
        key,
        encoding=encoding_for(type_name),
        congestion_control=(
            zenoh.CongestionControl.BLOCK if delivery is topics.Delivery.LOSSLESS else zenoh.CongestionControl.DROP
        ),
        reliability=zenoh.Reliability.RELIABLE,
    )


#: Samples each device publisher keeps for a restarted recorder to fetch (per key; >= 10 s at 100 messages/s).
DEVICE_HISTORY_SAMPLES = 1000


def declare_history_publisher(
    session: zenoh.Session, key: str, type_name: str, *, history_samples: int = DEVICE_HISTORY_SAMPLES
):
    """A lossless data publisher that also keeps its last ``history_samples`` for late or restarted subscribers
    (a Zenoh AdvancedPublisher with a cache; :func:`fetch_history` fetches it)."""
    import zenoh.ext

    messages.message_class(type_name)
    return zenoh.ext.declare_advanced_publisher(
        session,
        key,
        encoding=encoding_for(type_name),
        congestion_control=zenoh.CongestionControl.BLOCK,
        reliability=zenoh.Reliability.RELIABLE,
        # replies block like the data: a burst of up to history_samples replies must not be dropped on a busy link
        # (a lost reply leaves the subscriber holding back live samples until its query times out)
        cache=zenoh.ext.CacheConfig(
            max_samples=history_samples,
            replies_config=zenoh.ext.RepliesConfig(congestion_control=zenoh.CongestionControl.BLOCK),
        ),
        # sequence numbers, no heartbeat (else the cache needs timestamping)
        sample_miss_detection=zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=None),
        publisher_detection=True,
    )


def keeps_history(key: str) -> bool:
    """Whether a key's publishers keep a history (:func:`declare_history_publisher`): the loss-free device topics."""
    try:
        return topics.delivery_for_key(key) is topics.Delivery.LOSSLESS
    except ConfigError:  # not an msk/<session>/... key
        return False


def history_selector(key_expr: str) -> str:
    """Where the caches of :func:`declare_history_publisher` answer for ``key_expr``: each publisher's cache is a
    queryable under ``<key>/@adv/...``, a verbatim chunk that ``**`` does not cover."""
    return f"{key_expr}/@adv/**" if key_expr.endswith("**") else f"{key_expr}/**/@adv/**"


def fetch_history(session: zenoh.Session, key_expr: str, *, timeout_s: float) -> tuple[list[zenoh.Sample], list[str]]:
    """Everything the caches of :func:`declare_history_publisher` hold on ``key_expr``, per publisher in publishing
    order; and the error replies (as text). Returns when every cache has answered, or after ``timeout_s`` with what
    arrived by then.

    Publishers are found by their liveliness tokens, then each cache is asked on its own key: under access control a
    reader may query each device key it may read, not a broader expression. A plain query rather than Zenoh's
    AdvancedSubscriber history: that one delivers live samples as soon as they come, and when one of a publisher
    arrives before the publisher's token, it drops the history older than that sample (about one restart in five on
    loopback). The caller holds the live samples of a key until its history is in (:class:`services.nodes.recorder.HistoryMerge`).
    """
    deadline = time.monotonic() + float(timeout_s)
    errors: list[str] = []
    caches = []
    for reply in session.liveliness().get(history_selector(key_expr), timeout=float(timeout_s)):
        if reply.ok is not None:
            caches.append(str(reply.ok.key_expr))
        elif reply.err is not None:
            errors.append(reply.err.payload.to_string())
    pending = [  # asked at once, read one after the other: the caches answer in parallel
        session.get(
            cache,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            accept_replies=zenoh.ReplyKeyExpr.ANY,  # a cache answers with the data key, not the one asked
            timeout=max(0.1, deadline - time.monotonic()),
        )
        for cache in caches
    ]
    key = zenoh.KeyExpr(key_expr)
    samples: list[zenoh.Sample] = []
    for replies in pending:
        for reply in replies:
            if reply.ok is not None:
                if key.intersects(reply.ok.key_expr):
                    samples.append(reply.ok)
            elif reply.err is not None:
                errors.append(reply.err.payload.to_string())
    return samples, errors


def fetch_missed(
    session: zenoh.Session, key: str, publisher: tuple[str, int], first: int, last: int, *, timeout_s: float
) -> tuple[list[zenoh.Sample], list[str]]:
    """The publications ``first``..``last`` (sequence numbers, both included) of one history publisher
    (:func:`declare_history_publisher`; ``publisher`` = its Zenoh id and entity id) on ``key``, as far as its cache
    still holds them, and the error replies. Its cache answers the ``_sn`` range itself (zenoh-ext's AdvancedCache).
    The publication after ``last`` (the one that showed the gap) is asked too, so that a running cache always answers
    (with that one at least, left out here); until it answers (a publisher whose declarations have not reached the
    router again yet) it is asked again, up to ``timeout_s``; then an error says nobody answered."""
    zid, eid = publisher
    selector = zenoh.Selector(f"{key}/@adv/pub/{zid}/{eid}/**", {"_sn": f"{first}..{last + 1}"})
    deadline = time.monotonic() + float(timeout_s)
    while True:
        samples: list[zenoh.Sample] = []
        errors: list[str] = []
        answered = False
        for reply in session.get(
            selector,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            accept_replies=zenoh.ReplyKeyExpr.ANY,  # a cache answers with the data key
            timeout=max(0.1, deadline - time.monotonic()),
        ):
            answered = True
            if reply.ok is not None:
                info = reply.ok.source_info
                if info is None or int(info.source_sn) <= last:
                    samples.append(reply.ok)
            elif reply.err is not None:
                errors.append(reply.err.payload.to_string())
        if answered:
            return samples, errors
        if time.monotonic() > deadline - 0.3:  # said as an error reply: not "no longer in the cache"
            return samples, [*errors, f"no answer from publisher {zid}/{eid}'s cache of {key} within {timeout_s:g} s"]
        time.sleep(0.3)


def encoding_for(type_name: str) -> zenoh.Encoding:
    return zenoh.Encoding.APPLICATION_PROTOBUF.with_schema(type_name)


def has_subscribers(publisher: zenoh.Publisher) -> bool:
    """Whether a subscriber matches the publisher's key now."""
    # zenoh 1.10's stub types matching_status as bool; it returns a MatchingStatus, whose .matching is the bool
    return bool(publisher.matching_status.matching)  # type: ignore[attr-defined]


def publish(publisher: zenoh.Publisher, message: Message) -> None:
    publisher.put(messages.encode(message))


def type_name_of_sample(sample: zenoh.Sample) -> str | None:
    """The protobuf type named in a sample's encoding schema (``application/protobuf;msk.EmgChunk``), if any."""
    text = str(sample.encoding)
    if ";" in text:
        return text.split(";", 1)[1] or None
    return None


def free_loopback_endpoint() -> str:
    """A loopback TCP endpoint nobody listens on now: a private network for a self-contained graph (demo, tests)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{probe.getsockname()[1]}"
