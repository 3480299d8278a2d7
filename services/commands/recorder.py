"""``msk recorder``: log every msk/** topic of a running session (Zenoh) to MCAP (``msk capture`` records the devices
directly, without Zenoh)."""

from __future__ import annotations

import argparse

from services.nodes import recorder


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "recorder", help="record every msk/** Zenoh topic to an MCAP file", description=recorder.__doc__
    )
    recorder.add_arguments(parser)
    parser.set_defaults(handler=recorder.run_from_args)
