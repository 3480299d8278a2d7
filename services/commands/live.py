"""``msk live SESSION.toml``: run a whole session (drivers, kinematics, estimator, recorder, live view) on the
real devices; ``msk live --sim`` on the Trigno/Xsens simulators fed by the bundled synthetic session. Ctrl-C,
SIGTERM or ``--duration`` stop it cleanly: OUT/session.mcap and OUT/summary.json. Docs: docs/live.md."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from msk_core.errors import ConfigError


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("live", help="run a live session (devices or --sim) with recording and live view",
                                   description=__doc__)
    parser.add_argument("session_file", nargs="?", type=Path, default=None, metavar="SESSION.toml",
                        help="session file (docs/live.md); optional with --sim")
    parser.add_argument("--sim", action="store_true",
                        help="simulated Trigno (TCP) and Xsens (pty) devices streaming the bundled synthetic session")
    parser.add_argument("--duration", type=float, default=None, metavar="SECONDS", help="stop after this long (default: Ctrl-C)")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="output folder: DIR/session.mcap, DIR/summary.json (default: the file's session.out, else out/live)")
    parser.add_argument("--no-view", action="store_true", help="no live terminal view (scripts, CI)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from services import live
    from services.live_session import LiveSession, load_session_file

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ConfigError("must be a positive number of seconds", field="--duration", value=args.duration)
    if args.session_file is not None:
        session = load_session_file(args.session_file, require_devices=not args.sim)
    elif args.sim:
        session = LiveSession(None, name="sim")
    else:
        raise ConfigError("give a session file (docs/live.md), or --sim to run on the simulators", field="SESSION.toml")
    if args.out is not None:
        session.out = args.out
    live.main(session, sim=args.sim, duration_s=args.duration, view=not args.no_view)
    return 0
