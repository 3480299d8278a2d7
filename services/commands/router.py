"""``msk router``: run the Zenoh router every node of a multi-machine deployment connects to."""

from __future__ import annotations

import argparse

from services.nodes import router


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "router", help="run the Zenoh router (loopback by default; TLS + ACL with a config)", description=router.__doc__
    )
    router.add_arguments(parser)
    parser.set_defaults(handler=router.run_from_args)
