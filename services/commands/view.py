"""``msk view``: the live terminal view of a session (services/surfaces/view.py)."""

from __future__ import annotations

import argparse

from services.surfaces import view


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "view", help="live terminal view of a session (activations, EMG, torques, devices)", description=view.__doc__
    )
    view.add_arguments(parser)
    parser.set_defaults(handler=view.run_from_args)
