"""``msk demo``: the embedded demo session through calibration and the live Zenoh graph, scored against truth."""

from __future__ import annotations

import argparse

from services import demo


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="run the demo on the embedded synthetic session",
        description=demo.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_arguments(parser)
    parser.set_defaults(handler=demo.run_from_args)
