"""``msk drivers``: run the Trigno and/or Xsens driver nodes, publishing EmgChunk, ImuSample and DeviceStatus
on msk/<session>/emg/<source>, msk/<session>/imu/<tracker> and msk/<session>/status/<device>."""

from __future__ import annotations

import argparse
import threading

from services import driver_nodes, topics, zenoh_session


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("drivers", help="publish live Trigno/Xsens data on Zenoh", description=__doc__)
    driver_nodes.add_device_arguments(parser)
    parser.add_argument("--session", default="live", help="session name used in the topic keys (default: live)")
    parser.add_argument("--duration", type=float, default=None, metavar="SECONDS", help="stop after this long (default: until Ctrl-C)")
    zenoh_session.add_zenoh_arguments(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    topics.check_chunk(args.session, "session")
    stop = threading.Event()
    with zenoh_session.open_session(zenoh_session.options_from_args(args)) as session:
        sink = driver_nodes.ZenohSink(session)
        try:
            reports = driver_nodes.run_devices(args, sink, session=args.session, duration_s=args.duration, stop=stop)
        finally:
            sink.close()
    for report in reports:
        print(f"published {report.samples} samples in {report.messages} messages, {len(report.gaps)} gaps", flush=True)
    return 0
