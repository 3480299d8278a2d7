"""``msk dashboard``: live page for coaches (browser, tablet) fed by a session's Zenoh topics."""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    from services.surfaces.dashboard import app

    parser = subparsers.add_parser(
        "dashboard", help="serve the live coaches' page of a session (browser)", description=app.__doc__
    )
    app.add_arguments(parser)
    parser.set_defaults(handler=app.run_from_args)
