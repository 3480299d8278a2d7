"""``msk replay``: play an MCAP recording back through Zenoh, on its topics."""

from __future__ import annotations

import argparse

from services.nodes import replayer


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "replay", help="publish an MCAP recording on its Zenoh topics", description=replayer.__doc__
    )
    replayer.add_arguments(parser)
    parser.set_defaults(handler=replayer.run_from_args)
