"""``msk drivers``: run the Trigno and/or Xsens driver nodes, publishing EmgChunk, ImuSample and DeviceStatus
on msk/<session>/emg/<source>, msk/<session>/imu/<tracker> and msk/<session>/status/<device>.

Ctrl-C or SIGTERM ends acquisition cleanly (STOP/QUIT, final status) and prints what was published."""

from __future__ import annotations

import argparse
import sys

from services.nodes import driver_nodes
from services.nodes.node_runtime import NodeProcess, add_process_arguments
from services.nodes.readiness import declare_ready
from services.transport import topics, zenoh_session


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("drivers", help="publish live Trigno/Xsens data on Zenoh", description=__doc__)
    driver_nodes.add_device_arguments(parser)
    parser.add_argument("--session", default="live", help="session name used in the topic keys (default: live)")
    parser.add_argument(
        "--duration", type=float, default=None, metavar="SECONDS", help="stop after this long (default: until Ctrl-C)"
    )
    add_process_arguments(parser)  # readiness: wait for the nodes it publishes to before acquiring
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    topics.check_chunk(args.session, "session")
    devices = driver_nodes.device_settings(args)
    process = NodeProcess.from_args(args)  # the loops end cleanly and report on a signal, rather than being torn down
    with zenoh_session.open_session(process.options) as session:
        token = declare_ready(session, process.ready)  # noqa: F841 - alive while the node runs
        sink = driver_nodes.ZenohSink(session)
        try:
            reports = driver_nodes.run_devices(
                devices, sink, session=args.session, duration_s=args.duration, stop=process.stop
            )
        finally:
            sink.close()
    for report in reports:
        print(report.summary_line("published"), flush=True)
    ended = [f"{r.device}: {r.ended}" for r in reports if r.ended]
    if ended:  # not asked to stop: the session has lost this device's data (msk live names this node and why)
        print("msk drivers: error: " + "; ".join(ended), file=sys.stderr, flush=True)
        return 2
    return 0
