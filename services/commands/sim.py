"""``msk sim``: run a device simulator standalone.

``msk sim trigno --from FILE`` serves the Trigno SDK protocol on TCP (command 50040, EMG 50043 and 50041, AUX 50044,
legacy ACC 50042 unless ``--legacy-acc-port -1``);
``msk sim xsens --from FILE`` opens a pseudo-terminal speaking Xbus and prints its path on the first line;
``msk sim mvn --to HOST:PORT`` streams a recording's segment orientations as an Xsens MVN suit does (UDP).
FILE formats are described in docs/devices.md (C3D, .npz, raw .bin captures, or ``synthetic[:SECONDS[:SEED]]``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from drivers.trigno.protocol import COMMAND_PORT, DataPort
from msk_core.errors import ConfigError

#: the data ports' flags and the TCU's port each defaults to (with ``--port 0``: a free one unless given)
DATA_PORT_FLAGS = {
    "emg_port": ("--emg-port", "EMG data port", DataPort.EMG),
    "legacy_emg_port": ("--legacy-emg-port", "legacy EMG port", DataPort.LEGACY_EMG),
    "aux_port": ("--aux-port", "AUX data port", DataPort.AUX),
}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sim", help="run a Trigno or Xsens device simulator", description=__doc__)
    devices = parser.add_subparsers(dest="device", metavar="DEVICE", required=True)

    trigno = devices.add_parser("trigno", help="Trigno Control Utility simulator (TCP)")
    trigno.add_argument(
        "--from", dest="source", required=True, metavar="FILE", help=".c3d, .npz, .bin or synthetic[:SECONDS[:SEED]]"
    )
    trigno.add_argument("--rate", type=float, default=None, help="sample rate of a raw .bin source (default 2000 Hz)")
    trigno.add_argument("--host", default="127.0.0.1")
    trigno.add_argument(
        "--port",
        type=int,
        default=COMMAND_PORT,
        help=f"command port (default {COMMAND_PORT}, the TCU's); 0: a free one, and free data ports unless given",
    )
    for flag, what, tcu in DATA_PORT_FLAGS.values():
        trigno.add_argument(flag, type=int, default=None, help=f"{what} (default {tcu:d}); 0: a free one")
    trigno.add_argument(
        "--legacy-acc-port",
        type=int,
        default=None,
        help=f"legacy ACC port, as a real TCU listens on it (48 floats per sample; default {DataPort.LEGACY_ACC:d}); "
        "-1: off, 0: a free one",
    )
    trigno.add_argument("--speed", type=float, default=1.0, help="time scale (>1 faster than real time)")
    trigno.add_argument("--no-loop", action="store_true", help="stop streaming at the end of the recording")
    trigno.add_argument(
        "--fragment-max", type=int, default=None, metavar="BYTES", help="split frames into random TCP pieces"
    )
    trigno.add_argument(
        "--upsampling", choices=["on", "off"], default=None, help="initial upsampling (default: match the source rate)"
    )
    trigno.add_argument("--banner-space", action="store_true", help="quirk: a space before the banner's CRLFs")
    trigno.add_argument("--start-index-base", type=int, choices=[0, 1], default=1, help="quirk: STARTINDEX? base")
    trigno.add_argument(
        "--upsampling-reply", choices=["on_off", "yes_no"], default="on_off", help="quirk: UPSAMPLING? reply style"
    )
    trigno.add_argument(
        "--no-auto-master", action="store_true", help="quirk: the first connection is not master until MASTER"
    )
    trigno.add_argument(
        "--stop-trigger-after", type=float, default=None, metavar="S", help="quirk: send STOPPED after S s of streaming"
    )
    trigno.add_argument(
        "--start-delay", type=float, default=0.0, metavar="S", help="quirk: first data S s after START (real: ~2)"
    )
    trigno.add_argument(
        "--quit-keeps-streaming", action="store_true", help="quirk: QUIT alone does not stop acquisition"
    )
    trigno.add_argument(
        "--duration", type=float, default=None, metavar="S", help="exit after S seconds (default: until Ctrl-C)"
    )
    trigno.set_defaults(handler=run_trigno)

    xsens = devices.add_parser("xsens", help="Xsens MTi simulator on a pseudo-terminal")
    xsens.add_argument(
        "--from",
        dest="source",
        required=True,
        metavar="FILE",
        help=".bin Xbus capture, .npz or synthetic[:SECONDS[:SEED]]",
    )
    xsens.add_argument("--speed", type=float, default=1.0)
    xsens.add_argument("--no-loop", action="store_true")
    xsens.add_argument("--device-id", default="03700ABC", help="device id, 8 hex digits")
    xsens.add_argument(
        "--bit-flip", type=float, default=0.0, metavar="P", help="probability of a flipped bit per message"
    )
    xsens.add_argument(
        "--drop-byte", type=float, default=0.0, metavar="P", help="probability of a dropped byte per message"
    )
    xsens.add_argument(
        "--garbage", type=float, default=0.0, metavar="P", help="probability of garbage before a message"
    )
    xsens.add_argument("--unplug-after", type=int, default=None, metavar="N", help="close the pty after N messages")
    xsens.add_argument("--seed", type=int, default=0)
    xsens.add_argument("--duration", type=float, default=None, metavar="S")
    xsens.set_defaults(handler=run_xsens)
    _add_mvn(devices)


def _add_mvn(devices: argparse._SubParsersAction) -> None:
    mvn = devices.add_parser("mvn", help="Xsens MVN network streamer simulator (UDP)")
    mvn.add_argument(
        "--to", default="127.0.0.1:9763", metavar="HOST:PORT", help="where to send (default 127.0.0.1:9763)"
    )
    mvn.add_argument(
        "--from",
        dest="source",
        type=Path,
        default=None,
        metavar="RECORDING.mcap",
        help="an msk recording whose IMU samples carry the packs' segments (default: the bundled demo session)",
    )
    mvn.add_argument(
        "--exercise",
        choices=("bench_press", "deadlift"),
        default="bench_press",
        help="whose segments: the bench press's upper arm and forearm (default), or the deadlift's pelvis, torso, "
        "thigh and shank",
    )
    mvn.add_argument("--speed", type=float, default=1.0, help="time scale (>1 faster than the recording)")
    mvn.add_argument("--no-loop", action="store_true", help="stop at the end of the recording")
    mvn.add_argument("--duration", type=float, default=None, metavar="S", help="exit after S seconds")
    mvn.set_defaults(handler=run_mvn)


def recorded_segment_poses(recording: Path, segments: list[str]) -> list[tuple[int, dict]]:
    """(ns since the first, {segment: quaternion ENU}) of every instant of ``recording`` at which each of ``segments``
    has an IMU sample (its orientation in ENU)."""
    from drivers.xsens import frames, xbus
    from services.transport import messages
    from services.transport.mcap_io import read_messages

    rows: dict[int, dict[str, tuple[float, float, float, float]]] = {}
    for recorded in read_messages(recording):
        if recorded.type_name != "msk.ImuSample":
            continue
        sample = recorded.decode(messages.ImuSample)
        if sample.segment in segments and sample.HasField("orientation"):
            o = sample.orientation
            frame = xbus.CoordinateFrame[(sample.coordinate_frame or "ENU").upper()]
            rows.setdefault(sample.device_time_ns, {})[sample.segment] = frames.to_enu((o.w, o.x, o.y, o.z), frame)
    times = sorted(t for t, found in rows.items() if len(found) == len(segments))
    if not times:
        raise ConfigError(f"no instant with an orientation of each of {segments}", field="--from", value=str(recording))
    return [(t - times[0], rows[t]) for t in times]


def run_mvn(args: argparse.Namespace) -> int:
    import socket

    from drivers.xsens import mvn
    from msk_core.imu.mapping import mapping_for

    try:
        host, port = mvn.parse_address(args.to)
    except ValueError:
        host = ""
    if not host:
        raise ConfigError("HOST:PORT", field="--to", value=args.to)
    if not args.speed > 0:
        raise ConfigError("must be positive", field="--speed", value=args.speed)
    recording = args.source or Path(__file__).resolve().parents[2] / "recordings" / "demo_session.mcap"
    poses = recorded_segment_poses(recording, list(mapping_for(args.exercise).segments))
    period_ns = poses[-1][0] + (poses[-1][0] - poses[-2][0] if len(poses) > 1 else 16_666_667)
    print(f"MVN simulator -> udp {args.to}: {args.exercise} from {recording}, {len(poses)} poses", file=sys.stderr)
    deadline = None if args.duration is None else time.monotonic() + args.duration
    sent, start = 0, time.monotonic()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
        while deadline is None or time.monotonic() < deadline:
            loop, k = divmod(sent, len(poses))
            if loop and args.no_loop:
                break
            t_ns, orientations = poses[k]
            due_ns = loop * period_ns + t_ns
            time.sleep(max(0.0, start + due_ns / 1e9 / args.speed - time.monotonic()))
            for datagram in mvn.encode_pose(sent, due_ns // 1_000_000, mvn.body_pose(orientations)):
                sender.sendto(datagram, (host, port))
            sent += 1
    print(f"sent {sent} poses", file=sys.stderr)
    return 0


def _wait(duration: float | None, alive=lambda: True) -> None:
    deadline = None if duration is None else time.monotonic() + duration
    while alive() and (deadline is None or time.monotonic() < deadline):
        time.sleep(0.05)


def _free(host: str, port: int) -> bool:
    """Whether ``port`` on ``host`` can be listened on now (to name the flag whose port is taken)."""
    import socket

    with socket.socket() as probe:
        try:
            probe.bind((host, port))
        except OSError:
            return False
    return True


def _data_ports(args: argparse.Namespace) -> dict[str, int]:
    """Each data port: as given, else the TCU's, or a free one (0) when the command port is free too: a second
    simulator with ``--port 0`` must not collide with the first on the fixed data ports."""
    defaults = {name: tcu for name, (_, _, tcu) in DATA_PORT_FLAGS.items()} | {"legacy_acc_port": DataPort.LEGACY_ACC}
    chosen = {}
    for name, tcu in defaults.items():
        given = getattr(args, name)
        chosen[name] = int(given if given is not None else (0 if args.port == 0 else tcu))
        if not -1 <= chosen[name] <= 65535 or (chosen[name] == -1 and name != "legacy_acc_port"):
            flag = DATA_PORT_FLAGS[name][0] if name in DATA_PORT_FLAGS else "--legacy-acc-port"
            raise ConfigError("must be a port number, 0 for a free one", field=flag, value=given)
    return chosen


def run_trigno(args: argparse.Namespace) -> int:
    from drivers.trigno.simulator import SimulatorConfig, TrignoQuirks, TrignoSimulator, UpsamplingReply
    from drivers.trigno.source import load_source

    if args.speed <= 0:
        raise ConfigError("must be positive", field="--speed", value=args.speed)
    source = load_source(args.source, rate_hz=args.rate)
    quirks = TrignoQuirks(
        banner_trailing_space=args.banner_space,
        start_index_base=args.start_index_base,
        upsampling_reply=UpsamplingReply(args.upsampling_reply),
        first_connection_is_master=not args.no_auto_master,
        stop_trigger_after_s=args.stop_trigger_after,
        quit_stops_acquisition=not args.quit_keeps_streaming,
        start_delay_s=args.start_delay,
    )
    ports = _data_ports(args)
    config = SimulatorConfig(
        host=args.host,
        command_port=args.port,
        emg_port=ports["emg_port"],
        legacy_emg_port=ports["legacy_emg_port"],
        aux_port=ports["aux_port"],
        legacy_acc_port=None if ports["legacy_acc_port"] < 0 else ports["legacy_acc_port"],
        upsampling=None if args.upsampling is None else args.upsampling == "on",
        speed=args.speed,
        loop=not args.no_loop,
        fragment_max=args.fragment_max,
        quirks=quirks,
    )
    try:
        sim = TrignoSimulator(source, config).start()
    except OSError as error:  # the simulator closed what it had bound: the port still taken is the culprit
        asked = {"--port": args.port, **{DATA_PORT_FLAGS[k][0]: v for k, v in ports.items() if k in DATA_PORT_FLAGS}}
        asked["--legacy-acc-port"] = ports["legacy_acc_port"]
        taken = [flag for flag, port in asked.items() if port > 0 and not _free(args.host, port)]
        raise ConfigError(
            f"cannot listen on {args.host}: {error.strerror or error}",
            field=", ".join(taken) or "--port",
            value=", ".join(str(asked[f]) for f in taken) or args.port,
        ) from error
    with sim:
        paired = [f"{k + 1}:{name}" for k, name in enumerate(source.labels) if source.paired[k]]
        print(
            f"Trigno simulator on {args.host}: command {sim.ports['command']}, emg {sim.ports['emg']}, "
            f"legacy emg {sim.ports.get('legacy_emg')}, aux {sim.ports.get('aux')}, legacy acc {sim.ports.get('legacy_acc')}; {source.name} at {source.rate_hz:g} Hz, "
            f"sensors {' '.join(paired)}",
            flush=True,
        )
        _wait(args.duration)
    return 0


def run_xsens(args: argparse.Namespace) -> int:
    from drivers.xsens.simulator import FaultConfig, XsensSimulator
    from drivers.xsens.source import load_imu_source

    try:
        device_id = int(args.device_id, 16)
    except ValueError:
        raise ConfigError("must be hexadecimal", field="--device-id", value=args.device_id) from None
    for name in ("bit_flip", "drop_byte", "garbage"):
        if not 0.0 <= getattr(args, name) <= 1.0:
            raise ConfigError(
                "probability must be within 0..1", field=f"--{name.replace('_', '-')}", value=getattr(args, name)
            )
    source = load_imu_source(args.source)
    faults = FaultConfig(
        bit_flip=args.bit_flip,
        drop_byte=args.drop_byte,
        garbage=args.garbage,
        unplug_after_messages=args.unplug_after,
        seed=args.seed,
    )
    with XsensSimulator(source, device_id=device_id, faults=faults, speed=args.speed, loop=not args.no_loop) as sim:
        print(sim.path, flush=True)
        print(f"Xsens simulator {device_id:08X}: {source.name} at {source.rate_hz:g} Hz", file=sys.stderr, flush=True)
        _wait(args.duration, alive=lambda: not sim.unplugged)
        stats = sim.stats
        print(
            f"sent {stats.messages_sent} messages, corrupted {len(stats.corrupted_counters)}",
            file=sys.stderr,
            flush=True,
        )
    return 0
