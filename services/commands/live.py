"""``msk live SESSION.toml``: run a whole session (drivers, kinematics, estimator, recorder, live view) on the
real devices; ``msk live --sim`` on the Trigno/Xsens simulators fed by the bundled synthetic session. Ctrl-C,
SIGTERM, closing its terminal (SIGHUP) or ``--duration`` stop it cleanly: OUT/session.mcap and OUT/summary.json, exit code 0. When a node it
started fails (e.g. a driver that cannot reach its device), the session stops, the terminal says which node failed,
with its exit code and the end of its log (OUT/logs/<node>.log), and the exit code is 3. Docs: docs/live.md."""

from __future__ import annotations

import argparse
import ast
import math
import signal
import sys
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from msk_core.errors import ConfigError
from services.nodes.estimator_options import add_live_synergists_argument, add_solver_argument
from services.sessions.sim_sets import DEFAULT_REPS, DEFAULT_REST_S
from services.transport.stop_signals import exit_text

if TYPE_CHECKING:
    from drivers.trigno.simulator import SensorFault
    from services.sessions.live_session import LiveSession

#: ``msk live``'s exit code when a node of the session failed (2: a bad session file or option, before the start)
EXIT_NODE_FAILED = 3
LOG_TAIL_LINES = 12
_NODE_FAILED = "node failed: "  # services.sessions.live.run_graph: stopped_by = "node failed: " + repr(graph.failed())


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "live", help="run a live session (devices or --sim) with recording and live view", description=__doc__
    )
    parser.add_argument(
        "session_file",
        nargs="?",
        type=Path,
        default=None,
        metavar="SESSION.toml",
        help="session file (docs/live.md); optional with --sim",
    )
    parser.add_argument(
        "--sim",
        action="store_true",
        help="simulated Trigno (TCP) and Xsens (pty) devices streaming the bundled synthetic session",
    )
    parser.add_argument(
        "--sim-fault",
        action="append",
        default=[],
        metavar="SENSOR:KIND:START-END",
        help="with --sim: the simulated Trigno injects an electrode fault, KIND lift_off, hum, "
        "saturation or flat, on sensor SENSOR from START to END s after it starts streaming "
        "(repeatable; e.g. 5:hum:20-30; docs/live.md)",
    )
    parser.add_argument(
        "--sim-reps",
        type=int,
        default=DEFAULT_REPS,
        metavar="N",
        help=f"with --sim: reps per set (default {DEFAULT_REPS}; 0: the trial loops without rests)",
    )
    parser.add_argument(
        "--sim-rest",
        type=float,
        default=DEFAULT_REST_S,
        metavar="SECONDS",
        help=f"with --sim: rest between sets, the athlete still at the start pose (default {DEFAULT_REST_S:g})",
    )
    parser.add_argument(
        "--duration", type=float, default=None, metavar="SECONDS", help="stop after this long (default: Ctrl-C)"
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        metavar="DIR",
        help="output folder: DIR/session.mcap, DIR/summary.json (default: the file's session.out, else out/live)",
    )
    parser.add_argument("--no-view", action="store_true", help="no live terminal view (scripts, CI)")
    parser.add_argument(
        "--listen",
        default=None,
        metavar="ENDPOINT",
        help="the graph's Zenoh endpoint (default: tcp/127.0.0.1:7447 when free, else a free loopback "
        "port; printed at start and written to OUT/session.json)",
    )
    parser.add_argument(
        "--pki",
        type=Path,
        default=None,
        metavar="DIR",
        help="secured mode: a TLS router with access control, every node with its role's certificate "
        "from DIR (written by `msk certs --out DIR`)",
    )
    _add_estimator_arguments(parser)
    parser.set_defaults(handler=run)


def _add_estimator_arguments(parser: argparse.ArgumentParser) -> None:
    """How the session's estimator estimates (as the estimator node's options of the same names)."""
    add_solver_argument(parser, default=None)  # None: the session file's
    add_live_synergists_argument(parser)


def session_from_args(args: argparse.Namespace) -> LiveSession:
    """The session of the command line: its file (or, with ``--sim`` alone, the simulators' session) with the
    options that override the file (``--out``, ``--solver``, ``--live-synergists``)."""
    from services.sessions.live_session import LiveSession, load_session_file

    if args.session_file is not None:
        session = load_session_file(args.session_file, require_devices=not args.sim)
    elif args.sim:
        session = LiveSession(None, name="sim")
    else:
        raise ConfigError("give a session file (docs/live.md), or --sim to run on the simulators", field="SESSION.toml")
    return replace(
        session,
        out=session.out if args.out is None else args.out,
        solver=session.solver if args.solver is None else args.solver,
        live_synergists=args.live_synergists == "on",
    )


def _sim_fault(text: str) -> SensorFault:
    """``--sim-fault TEXT`` as a :class:`SensorFault`, its errors naming the flag and the text given."""
    from drivers.trigno.simulator import SensorFault

    try:
        return SensorFault.parse(text)
    except ConfigError as error:
        said = f"{error.field}: {error.message}" if error.field else error.message  # its value is the flag's
        raise ConfigError(said, field="--sim-fault", value=text) from None


def run(args: argparse.Namespace) -> int:
    from services.sessions import live

    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise ConfigError("must be a positive number of seconds", field="--duration", value=args.duration)
    if args.listen is not None:
        from services.transport.zenoh_session import check_endpoint, endpoint_is_free

        check_endpoint(args.listen, "--listen")
        if not endpoint_is_free(args.listen):  # before anything starts (it started the graph, then a traceback)
            raise ConfigError(
                "is in use by another program (another msk live? msk router?): choose a free port",
                field="--listen",
                value=args.listen,
            )
    session = session_from_args(args)
    faults = tuple(_sim_fault(text) for text in args.sim_fault)
    from services.sessions.sim_sets import SimSets

    sets = SimSets(reps=args.sim_reps, rest_s=args.sim_rest)
    summary = live.main(
        session,
        sim=args.sim,
        duration_s=args.duration,
        view=not args.no_view,
        listen=args.listen,
        pki=args.pki,
        sim_faults=faults,
        sim_sets=sets,
    )
    failures = node_failures(summary, session.out / "logs")
    for failure in failures:
        print(f"msk live: error: {failure.text()}", file=sys.stderr)
    return EXIT_NODE_FAILED if failures else 0


@dataclass(frozen=True)
class NodeFailure:
    """A node of the session that failed: it ended by itself while the session ran (named in ``stopped_by``), or
    ended with a non-zero exit code, or did not stop when asked and was killed (exit code None)."""

    node: str
    exit_code: int | None
    during_session: bool  # it ended by itself while the session ran (what stopped the session)
    detail: str  # what the graph said of it (``stopped_by``), e.g. "exit 2"
    log: Path

    def text(self) -> str:
        code = self.exit_code
        if code is None:
            how = (
                f"ended while the session ran ({self.detail})"
                if self.during_session
                else "did not stop when asked (SIGINT) and was killed"
            )
        else:
            how = exit_text(code)
            how += " while the session ran, which stopped the session" if self.during_session else " when stopped"
        return f"node {self.node} failed: it {how}; " + log_tail(self.log, LOG_TAIL_LINES)


def log_tail(path: Path, lines: int) -> str:
    """The last ``lines`` non-blank lines of a node's log, indented, after a line naming the file."""
    if not path.is_file():
        return f"no log at {path}"
    tail = [line for line in path.read_text(errors="replace").splitlines() if line.strip()][-lines:]
    if not tail:
        return f"its log {path} is empty"
    return f"the end of its log {path}:\n" + "\n".join(f"    {line}" for line in tail)


def node_failures(summary: dict, logs: Path) -> list[NodeFailure]:
    """The failed nodes of a session from its summary (``stopped_by``, ``exit_codes``); none after a clean stop
    (``--duration``, SIGINT, SIGTERM, SIGHUP) where every node exited 0 when ``msk live`` stopped it."""
    stopped_by = str(summary.get("stopped_by", ""))
    codes: dict[str, int | None] = summary.get("exit_codes", {})
    ended: dict[str, str] = {}  # node -> detail, for the nodes that ended by themselves
    if stopped_by.startswith(_NODE_FAILED):
        try:
            entries = ast.literal_eval(stopped_by[len(_NODE_FAILED) :])
        except (ValueError, SyntaxError):
            entries = None
        if not isinstance(entries, list) or not all(isinstance(e, str) for e in entries):
            entries = [stopped_by[len(_NODE_FAILED) :]]
        for entry in entries:
            node, _, detail = entry.partition(": ")
            ended[node] = detail
    failures = [
        NodeFailure(node, codes.get(node), True, detail, logs / f"{node}.log") for node, detail in ended.items()
    ]
    # after a node failed, the others were stopped at once: one stopped by the signal, or killed when it did not
    # answer it (e.g. waiting on the endpoint the failed node should have served), only followed the failure
    followed = {None, -signal.SIGINT, -signal.SIGTERM} if ended else set()
    failures += [
        NodeFailure(node, code, False, "", logs / f"{node}.log")
        for node, code in codes.items()
        if node not in ended and code != 0 and code not in followed
    ]
    return failures
