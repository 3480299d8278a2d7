"""``msk report``: the HTML report of a recorded session (per muscle and rep, balance, methods, device health)."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    from services.surfaces.dashboard import report

    parser = subparsers.add_parser(
        "report", help="write the HTML report of a recorded session", description=report.__doc__
    )
    report.add_arguments(parser)
    parser.set_defaults(handler=report.run_from_args)
