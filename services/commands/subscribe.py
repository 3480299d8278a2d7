"""``msk subscribe KEY [--json]``: print the decoded messages of any msk topic (a key expression, e.g.
``msk/demo/activations/*`` or ``msk/demo/**``), one line each: the key and the message as protobuf text or JSON.

Inputs come through :class:`services.nodes.node_runtime.NodeInputs`, like every node's: a key expression whose topics all
carry one type (``msk/demo/activations/*``) expects that type, a broader one (``msk/demo/**``) each key's type from
the topic table (docs/topics.md). A message that is oversized, does not decode, carries another type or fails its
type's checks is not printed: it is counted per key and reason (the first of each is logged on stderr) and the
counts are printed at the end. Stops after ``--count`` messages or ``--duration`` seconds, else at Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

import zenoh
from google.protobuf import json_format, text_format
from google.protobuf.message import Message

from msk_core.errors import ConfigError
from services.nodes.node_runtime import InputCounts, NodeInputs
from services.sessions import discovery
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, add_zenoh_arguments, open_session, options_from_args

#: How long the loop waits for a message before looking at the deadline again.
POLL_S = 0.05


def topic_types(key_expr: str) -> set[str]:
    """The message types of the topics of docs/topics.md that ``key_expr`` can match (any session)."""
    try:
        wanted = zenoh.KeyExpr(key_expr)
    except Exception as error:  # zenoh's own error type
        raise ConfigError(f"not a valid key expression: {error}", field="KEY", value=key_expr) from None
    found = set()
    for template, type_name in topics.TOPIC_TABLE:
        pattern = "/".join("*" if part.startswith("<") else part for part in template.split("/"))
        if wanted.intersects(zenoh.KeyExpr(f"{topics.ROOT}/*/{pattern}")):
            found.add(type_name)
    return found


def expected_type(key_expr: str) -> str | None:
    """The one type every topic ``key_expr`` matches carries, or None when it spans several (each key's own type
    then); :class:`ConfigError` when it matches no msk topic at all."""
    found = topic_types(key_expr)
    if not found:
        raise ConfigError("matches no msk topic (msk/<session>/..., docs/topics.md)", field="KEY", value=key_expr)
    return found.pop() if len(found) == 1 else None


def render(key: str, message: Message, *, as_json: bool) -> str:
    """One printed line for one checked message."""
    type_name = messages.type_name(message)
    if as_json:
        body = json_format.MessageToDict(message, preserving_proto_field_name=True)
        return json.dumps({"key": key, "type": type_name, "message": body}, allow_nan=True)
    return f"{key} {type_name} {text_format.MessageToString(message, as_one_line=True)}"


def dropped_summary(counts: InputCounts) -> str:
    """``; dropped 3 (msk/s/joints: oversized 1, ...)``, or "" when nothing was dropped."""
    drops = counts.drops()
    if not drops:
        return ""
    return (
        f"; dropped {sum(d.count for d in drops)} (" + ", ".join(f"{d.key}: {d.reason} {d.count}" for d in drops) + ")"
    )


def check_readable(role: str | None, key_expr: str, options: ZenohOptions) -> tuple[str, ...]:
    """What of ``key_expr`` the ``role`` of the secured network may read (:func:`services.transport.roles
    .permitted_parts`): all of it, or its readable parts, said in one line; a :class:`ConfigError` naming the role and
    what it may read when that is none of it (the router would refuse the subscription without a word)."""
    from services.transport.roles import parts_text, permitted_parts

    parts = permitted_parts(role, "subscribe", key_expr)
    if role is None or parts == (key_expr,):
        return parts
    if not parts:
        raise ConfigError(parts_text(role, "subscribe", key_expr, parts), path=options.config_file)
    print(f"msk subscribe: {parts_text(role, 'subscribe', key_expr, parts)}", file=sys.stderr, flush=True)
    return parts


def run(args: argparse.Namespace) -> int:
    wanted_type = expected_type(args.key)
    printed = 0
    deadline = None if args.duration is None else time.monotonic() + args.duration
    named = args.key.split("/")[1] if args.key.count("/") >= 2 and "*" not in args.key.split("/")[1] else None
    options, _ = discovery.client_options(options_from_args(args), named, named or "", "msk subscribe")
    readable = check_readable(options.role, args.key, options)
    with open_session(options) as session:
        inputs = NodeInputs(session, "subscribe", expected_type=wanted_type)
        for part in readable:
            inputs.subscribe(part)
        print(f"msk subscribe: subscribed to {', '.join(readable)}", file=sys.stderr, flush=True)
        quiet = threading.Event()
        discovery.silence_notice("msk subscribe", lambda: (args.key, options), lambda: printed, stop=quiet)
        try:
            while (args.count is None or printed < args.count) and (deadline is None or time.monotonic() < deadline):
                inbound = inputs.get(POLL_S)
                if inbound is None or inbound.message is None:  # none in time (rejected ones are not kept here)
                    continue
                print(render(inbound.key, inbound.message, as_json=args.json), flush=True)
                printed += 1
        except KeyboardInterrupt:
            pass
        finally:
            quiet.set()
            inputs.close()
    print(f"msk subscribe: {printed} messages on {args.key}{dropped_summary(inputs.counts)}", file=sys.stderr)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("subscribe", help="print decoded messages of any msk topic", description=__doc__)
    parser.add_argument("key", metavar="KEY", help="key expression, e.g. msk/demo/activations/* or msk/demo/**")
    parser.add_argument("--json", action="store_true", help="one JSON object per line instead of protobuf text")
    parser.add_argument("--count", type=int, default=None, help="stop after this many messages")
    parser.add_argument("--duration", type=float, default=None, metavar="SECONDS", help="stop after this long")
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=run)
