"""``msk kinematics``: the live kinematics node (IMU orientations in, model joint coordinates out over Zenoh)."""

from __future__ import annotations

import argparse

from services.commands import described
from services.nodes import kinematics_node


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = described(
        subparsers.add_parser("kinematics", help="run the live IMU-to-joint-angles node"), kinematics_node.__doc__
    )
    kinematics_node.add_arguments(parser)
    parser.set_defaults(handler=kinematics_node.run_from_args)
