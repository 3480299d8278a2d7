"""``msk capture`` (alias ``msk record``): acquire from real devices (or their simulators) straight to an MCAP file in
the project's schemas, without Zenoh (``msk recorder`` records what a running session publishes).

EMG chunks hold the samples exactly as received (float32 volts of the paired sensors); IMU samples hold the values
as decoded from MTData2; DeviceStatus messages report connection, counts, losses and errors.
"""

from __future__ import annotations

import argparse
import threading
from pathlib import Path

from msk_core.errors import ConfigError
from services.nodes import driver_nodes
from services.nodes.recorder import next_part_path
from services.transport import topics
from services.transport.mcap_io import McapRecorderWriter
from services.transport.stop_signals import StopOnSignals


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "capture",
        help="acquire Trigno/Xsens data straight to an MCAP file (no Zenoh)",
        aliases=["record"],
        description=__doc__,
    )
    driver_nodes.add_device_arguments(parser)
    parser.add_argument(
        "--duration",
        type=float,
        required=True,
        metavar="SECONDS",
        help="how long to record: seconds of data per device (the Trigno's from its first EMG, waited for up to 10 s)",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="FILE.mcap", help="MCAP file to write")
    parser.add_argument("--session", default="live", help="session name used in the topic keys (default: live)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if not args.duration > 0:
        raise ConfigError("must be positive", field="--duration", value=args.duration)
    if args.out.suffix.lower() != ".mcap":
        raise ConfigError("output must be a .mcap file", field="--out", value=str(args.out))
    topics.check_chunk(args.session, "session")
    devices = driver_nodes.device_settings(args)
    stop = threading.Event()
    # never over an earlier recording: the next free FILE-001.mcap..., as msk recorder continues
    out = next_part_path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    sink = None
    try:
        with McapRecorderWriter(out) as writer, StopOnSignals(interrupt_twice=True, event=stop):
            sink = driver_nodes.McapSink(writer)
            reports = driver_nodes.run_devices(devices, sink, session=args.session, duration_s=args.duration, stop=stop)
    except BaseException:
        if sink is None or sink.count == 0:  # a device that did not open: no empty recording left behind
            out.unlink(missing_ok=True)
        raise
    for report in reports:
        print(report.summary_line())
        if report.ended:
            print(f"{report.device}: {report.ended}; the capture of it ended there")
        elif report.seconds_of_data is not None and report.seconds_of_data < 0.8 * args.duration:
            print(
                f"{report.device}: its data cover {report.seconds_of_data:.1f} s of the {args.duration:g} s asked: the "
                "stream stopped or started late (another client's STOP stops a Trigno base for every client; see its "
                "status in the recording)"
            )
    moved = f" ({args.out} exists: this capture continues into the next part)" if out != args.out else ""
    print(f"wrote {sink.count} messages to {out}{moved}")
    return 0
