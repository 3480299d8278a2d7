"""``msk recorder`` (log every msk/** topic to MCAP) and ``msk replay`` (play an MCAP back through Zenoh)."""

from __future__ import annotations

import argparse

from services.nodes import recorder, replayer


def register(subparsers: argparse._SubParsersAction) -> None:
    rec = subparsers.add_parser(
        "recorder", help="record every msk/** Zenoh topic to an MCAP file", description=recorder.__doc__
    )
    recorder.add_arguments(rec)
    rec.set_defaults(handler=recorder.run_from_args)
    rep = subparsers.add_parser(
        "replay", help="publish an MCAP recording on its Zenoh topics", description=replayer.__doc__
    )
    replayer.add_arguments(rep)
    rep.set_defaults(handler=replayer.run_from_args)
