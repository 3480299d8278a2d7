"""``msk demo``: the embedded demo session through calibration and the live Zenoh graph, scored against truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.commands import described
from services.nodes import replayer
from services.sessions import demo


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = described(
        subparsers.add_parser("demo", help="run the demo on the embedded synthetic session"), demo.__doc__
    )
    add_arguments(parser)
    parser.set_defaults(handler=run_from_args)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: out/demo)")
    parser.add_argument(
        "--recordings",
        type=Path,
        default=demo.DEFAULT_RECORDINGS,
        help="folder with demo_session.mcap and demo/ (default: the embedded one)",
    )
    parser.add_argument("--rate", default="max", help="replay speed: 'max' (default) or a factor, 1 = real time")
    parser.add_argument(
        "--exercise", action="append", default=None, help="only this exercise (repeatable; default: all)"
    )
    parser.add_argument(
        "--joints-from",
        choices=["imu", "recorded"],
        default="imu",
        help="imu (default): kinematics nodes compute joint angles from the replayed IMU streams, as on a real rig; "
        "recorded: replay the session's joint angles",
    )


def run_from_args(args: argparse.Namespace) -> int:
    demo.main(
        recordings=args.recordings,
        out=args.out,
        rate=replayer.parse_rate(args.rate),
        exercises=args.exercise,
        joints_from=args.joints_from,
    )
    return 0
