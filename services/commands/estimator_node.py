"""``msk estimator``: the live estimator node (joints in, activations out over Zenoh)."""

from __future__ import annotations

import argparse

from services.nodes import estimator


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "estimator", help="run the live activation estimator node", description=estimator.__doc__
    )
    estimator.add_arguments(parser)
    parser.set_defaults(handler=estimator.run_from_args)
