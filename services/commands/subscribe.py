"""``msk subscribe KEY [--json]``: print the decoded messages of any msk topic (a key expression, e.g.
``msk/demo/activations/*`` or ``msk/demo/**``), one line each: the key and the message as protobuf text or JSON.

The type comes from the sample's encoding (``application/protobuf;msk.<Type>``), else from the topic table
(docs/topics.md). Stops after ``--count`` messages or ``--duration`` seconds, else at Ctrl-C.
"""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time

from google.protobuf import json_format, text_format

from msk_core.errors import ConfigError
from services import messages, topics
from services.zenoh_session import add_zenoh_arguments, open_session, options_from_args, type_name_of_sample


def render(key: str, type_name: str | None, payload: bytes, *, as_json: bool) -> str:
    """One printed line for one sample (undecodable or untyped payloads say so rather than vanish)."""
    if type_name is None:
        try:
            type_name = topics.message_type_for_key(key)
        except ConfigError:
            type_name = None
    if type_name is None:
        return json.dumps({"key": key, "error": f"unknown type, {len(payload)} bytes"}) if as_json else f"{key} <unknown type, {len(payload)} bytes>"
    try:
        message = messages.decode(type_name, payload)
    except messages.MessageDecodeError as error:
        return json.dumps({"key": key, "error": str(error)}) if as_json else f"{key} <{error}>"
    if as_json:
        body = json_format.MessageToDict(message, preserving_proto_field_name=True)
        return json.dumps({"key": key, "type": type_name, "message": body}, allow_nan=True)
    return f"{key} {type_name} {text_format.MessageToString(message, as_one_line=True)}"


def run(args: argparse.Namespace) -> int:
    try:
        import zenoh

        zenoh.KeyExpr(args.key)
    except Exception as error:  # zenoh's own error type
        raise ConfigError(f"not a valid key expression: {error}", field="KEY", value=args.key) from None
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    printed = 0
    deadline = None if args.duration is None else time.monotonic() + args.duration
    with open_session(options_from_args(args)) as session:
        subscriber = session.declare_subscriber(
            args.key, lambda s: inbox.put((str(s.key_expr), type_name_of_sample(s), s.payload.to_bytes()))
        )
        print(f"msk subscribe: subscribed to {args.key}", file=sys.stderr, flush=True)
        try:
            while (args.count is None or printed < args.count) and (deadline is None or time.monotonic() < deadline):
                try:
                    key, type_name, payload = inbox.get(timeout=0.05)
                except queue.Empty:
                    continue
                print(render(key, type_name, payload, as_json=args.json), flush=True)
                printed += 1
        except KeyboardInterrupt:
            pass
        finally:
            subscriber.undeclare()
    print(f"msk subscribe: {printed} messages on {args.key}", file=sys.stderr)
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("subscribe", help="print decoded messages of any msk topic", description=__doc__)
    parser.add_argument("key", metavar="KEY", help="key expression, e.g. msk/demo/activations/* or msk/demo/**")
    parser.add_argument("--json", action="store_true", help="one JSON object per line instead of protobuf text")
    parser.add_argument("--count", type=int, default=None, help="stop after this many messages")
    parser.add_argument("--duration", type=float, default=None, metavar="SECONDS", help="stop after this long")
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=run)
