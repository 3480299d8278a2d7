"""Driver nodes: acquisition loops that turn Trigno/Xsens driver events into EmgChunk, AccChunk, ImuSample and
DeviceStatus messages and hand them to a sink (Zenoh publishers, or an MCAP file for ``msk capture``).

Each loop runs in its own thread until ``stop`` is set or its deadline passes; sinks must be thread-safe. A loop's
last DeviceStatus of each device, published as it ends, says ``connected = False`` with the final counts: the driver
no longer delivers, whatever the link's state (``msk live`` records it, and its summary reads it).
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TypeVar

import numpy as np
import zenoh
from google.protobuf.message import Message

from drivers.trigno import protocol as tp
from drivers.trigno.client import AuxBlock, ClientState, EmgBlock, GapEvent, StatusEvent, TrignoClient
from drivers.xsens import xbus
from drivers.xsens.device import RECONNECT_FAILED, ImuReading, TrackerSet
from drivers.xsens.mvn import PACK_SEGMENTS as MVN_PACK_SEGMENTS
from drivers.xsens.mvn import MvnReceiver, Pose, SegmentPose
from drivers.xsens.mvn import parse_address as parse_mvn_address
from services.transport import messages, topics, zenoh_session

log = logging.getLogger(__name__)

#: sink(key, message, host_time_ns, device_time_ns)
Sink = Callable[[str, Message, int, int], None]
Chunk = TypeVar("Chunk", messages.EmgChunk, messages.AccChunk)


# ------------------------------------------------------------------------------------------------ conversions


def emg_columns(client: TrignoClient) -> list[tuple[str, int]]:
    """(label, 0-based slot) of the EMG channels to publish: every EMG channel of the active sensors (multi-channel
    sensors give one column per channel, ``sensorNN.EMGk``); all 16 slots when the server told us nothing."""
    return client.emg_columns or [(f"sensor{s:02d}.EMG", s - 1) for s in range(1, 17)]


def emg_chunk(block: EmgBlock, *, source_id: str, columns: list[tuple[str, int]]) -> messages.EmgChunk:
    """An EmgChunk of the given (label, slot) columns (float32 values as received: protobuf floats are float32)."""
    slots = [slot for _, slot in columns]
    rows = block.samples if slots == list(range(block.samples.shape[1])) else block.samples[:, slots]
    return _timed_chunk(
        messages.EmgChunk(source_id=source_id, channel_labels=[label for label, _ in columns], units="V"),
        block,
        rows,
        device_time_ns=block.device_time_ns,
        n_channels=rows.shape[1],
    )


def _timed_chunk(
    chunk: Chunk, block: EmgBlock | AuxBlock, values: np.ndarray, *, device_time_ns: int, **counts: int
) -> Chunk:
    """``chunk`` with the block's timing (rate, first sample index, device and host times), the sample count, the
    other ``counts`` (channels or sensors) and ``values`` as its packed samples."""
    chunk.sample_rate_hz = block.rate_hz
    chunk.first_sample_index = block.first_sample_index
    chunk.device_time_ns = device_time_ns
    chunk.host_time_ns = block.host_time_ns
    chunk.n_samples = values.shape[0]
    for name, count in counts.items():
        setattr(chunk, name, count)
    messages.add_packed_floats(chunk, "samples", values)
    return chunk


def acc_sensors(client: TrignoClient) -> list[tuple[str, int]]:
    """(label, sensor number 1..16) of the sensors whose accelerometers to publish: the active sensors (every slot
    when the server told us nothing), labelled ``sensorNN`` as their EMG channels ``sensorNN.EMG...``."""
    numbers = client.active_sensors or list(range(1, tp.N_SENSORS + 1))
    return [(f"sensor{n:02d}", n) for n in numbers]


def acc_chunk(
    block: AuxBlock, *, source_id: str, sensors: list[tuple[str, int]], layout: tp.AuxLayout
) -> messages.AccChunk:
    """An AccChunk of the given (label, sensor number) sensors: each sensor's ACC x, y, z in g, the first three of
    its slots on the AUX port (9 per sensor, Avanti) or its three on the legacy ACC port. Row k is AUX sample
    ``first_sample_index + k``, measured at EMG device time ``(first_sample_index + k) / rate`` (both counts start
    with START)."""
    rows = block.samples.reshape(len(block.samples), tp.N_SENSORS, layout.slots_per_sensor)
    values = rows[:, [n - 1 for _, n in sensors], :3]
    return _timed_chunk(
        messages.AccChunk(source_id=source_id, sensor_labels=[label for label, _ in sensors], units="g"),
        block,
        values,
        device_time_ns=int(round(block.first_sample_index * 1e9 / block.rate_hz)),
        n_sensors=values.shape[1],
    )


def imu_sample(reading: ImuReading, *, segment: str = "") -> messages.ImuSample:
    sample = messages.ImuSample(
        tracker_id=reading.tracker_id,
        segment=segment,
        packet_counter=reading.packet_counter or 0,
        sample_time_fine=reading.sample_time_fine or 0,
        device_time_ns=reading.device_time_ns,
        host_time_ns=reading.host_time_ns,
        coordinate_frame=reading.frame.name,
    )
    # the fields set in place (each present once touched, zeros too): no message built to be copied, ~40 % cheaper
    if reading.quaternion is not None:
        orientation = sample.orientation
        orientation.w, orientation.x, orientation.y, orientation.z = reading.quaternion
    for name, value in (
        ("acceleration", reading.acceleration),
        ("rate_of_turn", reading.rate_of_turn),
        ("magnetic_field", reading.magnetic_field),
    ):
        if value is not None:
            vector = getattr(sample, name)
            vector.x, vector.y, vector.z = value
    return sample


def device_status(
    *,
    device_id: str,
    kind: str,
    connected: bool,
    received: int,
    lost: int,
    errors: int,
    last_error: str,
    segment: str = "",
) -> messages.DeviceStatus:
    return messages.DeviceStatus(
        device_id=device_id,
        kind=kind,
        segment=segment,
        connected=connected,
        samples_received=received,
        samples_lost=lost,
        errors=errors,
        last_error=last_error,
        host_time_ns=messages.now_ns(),
    )


# ------------------------------------------------------------------------------------------------ loops


@dataclass
class LoopReport:
    """What a loop did (for the CLI summary and tests)."""

    device: str = ""
    messages: int = 0
    samples: int = 0
    gaps: list[GapEvent] = field(default_factory=list)
    states: list[str] = field(default_factory=list)
    lost: int = 0  # samples known lost: the Trigno's index gaps, the trackers' packet-counter jumps
    errors: int = 0  # messages that could not be used (the trackers' decode, device and framing errors)
    seconds_of_data: float | None = None  # the Trigno: the time its samples cover (a stream stopped early shows)
    ended: str = ""  # why the device ended the stream before it was asked to (e.g. the Trigno's STOPPED)

    def summary_line(self, verb: str = "") -> str:
        """e.g. ``xsens: 545 samples in 552 messages, 56 lost, 163 errors, disconnected 1x`` (``verb`` before the
        counts, e.g. "published")."""
        said = [f"{self.device}: {verb + ' ' if verb else ''}{self.samples} samples in {self.messages} messages"]
        if self.seconds_of_data is not None:
            said.append(f"{self.seconds_of_data:.1f} s of data")
        said.append(f"{self.lost} lost" + (f" in {len(self.gaps)} gaps" if self.gaps else ""))
        if self.errors:
            said.append(f"{self.errors} errors")
        # a tracker's disconnection, or the Trigno's link lost (its client reconnects by itself)
        away = back = 0
        for state in self.states:
            if state in ("disconnected", "reconnecting"):
                away += 1
            elif state == "reconnected" or (state == "streaming" and away > back):  # streaming again after a loss
                back += 1
        if away:
            said.append(f"disconnected {away}x, reconnected {back}x")
        return ", ".join(said) + (f"; ended early: {self.ended}" if self.ended else "")


class _TrignoChannels:
    """The EMG columns and ACC sensors to publish, as the base reported them at its last (re)connection: a base that
    comes back may have other sensors paired or switched on (a channel then published as zeros, another never)."""

    def __init__(self, client: TrignoClient) -> None:
        self.client = client
        self.emg = emg_columns(client)
        self.acc = acc_sensors(client)

    def refresh(self) -> None:
        emg, acc = emg_columns(self.client), acc_sensors(self.client)
        if emg != self.emg:
            before, after = {label for label, _ in self.emg}, {label for label, _ in emg}
            text = (
                f"the base's channels changed at its reconnection: {', '.join(sorted(after - before)) or 'none'} "
                f"added, {', '.join(sorted(before - after)) or 'none'} gone"
            )
            log.warning("%s", text)
            self.client.stats.last_error = text
        self.emg, self.acc = emg, acc


#: ``--duration`` counts the Trigno's data from its first EMG; this long at most is waited for it after START
FIRST_DATA_WAIT_S = 10.0


@dataclass
class _DataDeadline:
    """``duration_s`` of data, counted from the first data (:meth:`data_came`), waited for up to FIRST_DATA_WAIT_S;
    None: no deadline."""

    duration_s: float | None
    at: float = 0.0
    started: bool = False

    def __post_init__(self) -> None:
        self.at = time.monotonic() + (self.duration_s or 0.0) + FIRST_DATA_WAIT_S

    def data_came(self) -> None:
        if not self.started and self.duration_s is not None:
            self.at = time.monotonic() + self.duration_s
        self.started = True

    def passed(self) -> bool:
        return self.duration_s is not None and time.monotonic() >= self.at


def trigno_loop(
    client: TrignoClient,
    *,
    session: str,
    source_id: str,
    sink: Sink,
    stop: threading.Event,
    duration_s: float | None = None,
    status_interval_s: float = 1.0,
) -> LoopReport:
    """Start acquisition and publish until ``stop``/``duration_s``; then STOP/QUIT. The client must be connected.
    With an AUX port (``TrignoConfig.aux_port``) the sensors' accelerometers go to ``acc/<source_id>``."""
    report = LoopReport(device="trigno", seconds_of_data=0.0)  # a base that sends nothing covers 0 s
    emg_key = topics.emg_key(session, source_id)
    acc_key = topics.acc_key(session, source_id)
    status_key = topics.status_key(session, source_id)
    channels = _TrignoChannels(client)
    layout = client.config.resolved_aux_layout

    def publish_status(*, final: bool = False) -> None:
        stats = client.stats
        status = device_status(
            device_id=source_id,
            kind="trigno",
            connected=client.connected and not final,
            received=stats.samples_received,
            lost=stats.samples_lost,
            errors=stats.errors,
            last_error=stats.last_error,
        )
        sink(status_key, status, status.host_time_ns, 0)
        report.messages += 1

    deadline = _DataDeadline(duration_s)  # a real base sends its first EMG ~2 s after START

    def publish_data(event) -> None:
        if isinstance(event, EmgBlock):
            deadline.data_came()
            chunk = emg_chunk(event, source_id=source_id, columns=channels.emg)
            sink(emg_key, chunk, event.host_time_ns, event.device_time_ns)
            report.messages += 1
            report.samples += len(event.samples)
            report.seconds_of_data = report.samples / event.rate_hz
        elif isinstance(event, AuxBlock):
            accelerations = acc_chunk(event, source_id=source_id, sensors=channels.acc, layout=layout)
            sink(acc_key, accelerations, event.host_time_ns, accelerations.device_time_ns)
            report.messages += 1
        elif isinstance(event, GapEvent):
            report.gaps.append(event)
            report.lost += event.n_missing

    try:
        client.start()  # inside: a start that fails still ends with STOP/QUIT and the final status
        publish_status()
        next_status = time.monotonic() + status_interval_s
        while not stop.is_set() and not deadline.passed():
            for event in client.poll(0.05):
                if isinstance(event, StatusEvent):
                    report.states.append(event.state.value)
                    if event.state is ClientState.STREAMING:  # after a reconnection the base may pair other sensors
                        channels.refresh()
                    publish_status()
                    if event.state is ClientState.STOPPED:
                        report.ended = event.detail
                        return report
                else:
                    publish_data(event)
            if time.monotonic() >= next_status:
                publish_status()
                next_status += status_interval_s
    finally:
        for event in client.stop():  # the frames already on their way when we said STOP
            publish_data(event)
        publish_status(final=True)
        report.errors = int(client.stats.errors)
    return report


def xsens_loop(
    trackers: TrackerSet,
    *,
    session: str,
    sink: Sink,
    stop: threading.Event,
    segments: dict[str, str] | None = None,
    duration_s: float | None = None,
    status_interval_s: float = 1.0,
) -> LoopReport:
    """Publish every tracker's readings until ``stop``/``duration_s``; an unplugged tracker is reported, not fatal."""
    report = LoopReport(device="xsens")
    segments = segments or {}
    known = dict(trackers.devices)

    def publish_status(*, final: bool = False) -> None:
        for tracker_id, device in known.items():
            stats = device.stats
            status = device_status(
                device_id=tracker_id,
                kind="xsens",
                connected=tracker_id in trackers.devices and not final,
                received=stats.readings,
                lost=stats.packets_lost,
                errors=stats.decode_errors + stats.device_errors + device.parser.stats.errors,
                last_error=_tracker_error(trackers.disconnected.get(tracker_id), stats.last_error),
                segment=segments.get(tracker_id, ""),  # the views that read no IMU samples name it by this
            )
            sink(topics.status_key(session, tracker_id), status, status.host_time_ns, 0)
            report.messages += 1

    deadline = None if duration_s is None else time.monotonic() + duration_s
    publish_status()
    next_status = time.monotonic() + status_interval_s
    lost = set(trackers.disconnected)
    report.states.extend(["disconnected"] * len(lost))  # trackers away before the first read
    without_orientation: dict[str, int] = {}  # readings in a row without an orientation, per tracker
    try:
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            if not trackers.devices:
                time.sleep(0.05)
            for reading in trackers.read():
                _count_orientation(reading, without_orientation, trackers.devices.get(reading.tracker_id))
                message = imu_sample(reading, segment=segments.get(reading.tracker_id, ""))
                sink(topics.imu_key(session, reading.tracker_id), message, reading.host_time_ns, reading.device_time_ns)
                report.messages += 1
                report.samples += 1
            if set(trackers.disconnected) != lost:  # a tracker went away or came back (TrackerSet reconnects)
                now_lost = set(trackers.disconnected)
                report.states.extend(["disconnected"] * len(now_lost - lost) + ["reconnected"] * len(lost - now_lost))
                lost = now_lost
                publish_status()
            if time.monotonic() >= next_status:
                publish_status()
                next_status += status_interval_s
    finally:
        publish_status(final=True)
        report.lost = sum(device.stats.packets_lost for device in known.values())
        report.errors = sum(
            d.stats.decode_errors + d.stats.device_errors + d.parser.stats.errors for d in known.values()
        )
    return report


#: an MVN stream silent this long is said (the suit's software stopped streaming, or the network)
MVN_SILENT_S = 3.0


def open_mvn(address: str) -> MvnReceiver:
    """A receiver listening on ``[HOST:]PORT`` (all interfaces without a host)."""
    from msk_core.errors import ConfigError

    try:
        host, port = parse_mvn_address(address)
    except ValueError as error:
        raise ConfigError(str(error), field="--mvn", value=address) from None
    return MvnReceiver(host or "0.0.0.0", port).open()


def mvn_loop(
    receiver: MvnReceiver,
    *,
    session: str,
    sink: Sink,
    stop: threading.Event,
    duration_s: float | None = None,
    status_interval_s: float = 1.0,
) -> LoopReport:
    """Publish the packs' segments of each MVN quaternion pose as IMU samples of trackers ``mvn-<MVN segment>``
    (their ``segment`` the pack's name, e.g. upper_arm_r), until ``stop`` or ``duration_s`` of data."""
    report, stats = LoopReport(device="mvn"), receiver.stats
    watch = _MvnWatch(receiver, report)
    deadline = _DataDeadline(duration_s)  # a suit may start streaming after the capture

    def publish_status(*, final: bool = False) -> None:
        status = device_status(
            device_id="mvn", kind="mvn", connected=watch.streaming and not final, received=stats.poses,
            lost=stats.samples_lost, errors=stats.errors + stats.incomplete, last_error=stats.last_error,
        )  # fmt: skip
        sink(topics.status_key(session, "mvn"), status, status.host_time_ns, 0)
        report.messages += 1

    next_status = time.monotonic()
    while not stop.is_set() and not deadline.passed():
        for pose in receiver.read(0.05):
            deadline.data_came()
            watch.pose()
            for segment in pose.segments:
                if segment.name not in MVN_SEGMENT_OF_PACK:
                    continue
                if not _unit_quaternion(segment.quaternion):
                    stats.errors += 1
                    stats.last_error = f"MVN sample {pose.sample_counter}: {segment.name}'s quaternion is not one"
                    continue
                sample = mvn_sample(pose, segment, MVN_SEGMENT_OF_PACK[segment.name])
                sink(topics.imu_key(session, sample.tracker_id), sample, pose.host_time_ns, sample.device_time_ns)
                report.messages += 1
                report.samples += 1
        watch.check()
        if time.monotonic() >= next_status:
            publish_status()
            next_status += status_interval_s
    publish_status(final=True)
    report.lost, report.errors = stats.samples_lost, stats.errors + stats.incomplete
    return report


#: MVN's segment name -> the packs' segment it is
MVN_SEGMENT_OF_PACK = {mvn: pack for pack, mvn in MVN_PACK_SEGMENTS.items()}


def _unit_quaternion(q: tuple[float, float, float, float]) -> bool:
    return abs(math.fsum(v * v for v in q) - 1.0) < 0.01  # NaN fails too


class _MvnWatch:
    """What an MVN stream's loop says on its own: a stream silent for MVN_SILENT_S (and when it comes back), other
    message types only (a suit set to stream Euler poses), other characters left out."""

    def __init__(self, receiver: MvnReceiver, report: LoopReport) -> None:
        self.receiver, self.report = receiver, report
        self.last_pose = time.monotonic()
        self.silent = False
        self.characters_said: set[int] = set()

    @property
    def streaming(self) -> bool:
        return self.receiver.stats.poses > 0 and not self.silent

    def pose(self) -> None:
        self.last_pose = time.monotonic()
        if self.silent:
            self.silent = False
            self.report.states.append("reconnected")

    def check(self) -> None:
        stats = self.receiver.stats
        others = set(stats.other_characters) - self.characters_said
        if others:
            self.characters_said |= others
            stats.last_error = (
                f"MVN streams characters {sorted(self.characters_said)} besides {self.receiver.character}: left out "
                f"(one athlete's segments follow character {self.receiver.character}, the first heard)"
            )
            log.warning("%s", stats.last_error)
        if not self.silent and time.monotonic() - self.last_pose > MVN_SILENT_S:
            self.silent = True
            types = ", ".join(f"{n} of type {t}" for t, n in stats.other_types.most_common()) or "none"
            stats.last_error = (
                f"no MVN quaternion pose (type 02) on UDP {self.receiver.host}:{self.receiver.port} for "
                f"{MVN_SILENT_S:g} s; datagrams of other types so far: {types}"
            )
            self.report.states.append("disconnected")
            log.warning("%s", stats.last_error)


def mvn_sample(pose: Pose, segment: SegmentPose, pack_segment: str) -> messages.ImuSample:
    """One segment of an MVN pose as an IMU sample (MVN's global frame passed on as NWU; its time in ms; the sample
    counter's low 16 bits as the packet counter, as an Xbus tracker's, so that readers count gaps alike)."""
    sample = messages.ImuSample(
        tracker_id=f"mvn-{segment.name}" if pose.character == 0 else f"mvn{pose.character}-{segment.name}",
        segment=pack_segment,
        packet_counter=pose.sample_counter & 0xFFFF,
        device_time_ns=pose.time_ms * 1_000_000,
        host_time_ns=pose.host_time_ns,
        coordinate_frame="NWU",
    )
    orientation = sample.orientation
    orientation.w, orientation.x, orientation.y, orientation.z = segment.quaternion
    return sample


def _tracker_error(disconnected: str | None, last_error: str) -> str:
    """A tracker's status text: why it went away and, while it is away, why the last attempt to bring it back failed."""
    if disconnected is None:
        return last_error
    return f"{disconnected}; {last_error}" if last_error.startswith(RECONNECT_FAILED) else disconnected


#: Readings in a row without an orientation before it is said: one such message is no fault (an MTi-G's first message
#: and its GNSS messages carry none), a device configured without one never gives one.
NO_ORIENTATION_READINGS = 50


def _count_orientation(reading, without: dict[str, int], device) -> None:
    """Say once, when a tracker's samples have carried no orientation ``NO_ORIENTATION_READINGS`` times in a row (a
    device that kept outputs of its own, e.g. inertial data and orientation increments only), that every reader that
    needs one refuses them, in its log and status; and take it back when orientations come."""
    tracker_id = reading.tracker_id
    if reading.quaternion is not None:
        if without.pop(tracker_id, 0) >= NO_ORIENTATION_READINGS and device is not None:
            if device.stats.last_error.startswith(f"tracker {tracker_id}: its samples carry no orientation"):
                device.stats.last_error = ""
                log.info("tracker %s: its samples carry an orientation again", tracker_id)
        return
    without[tracker_id] = count = without.get(tracker_id, 0) + 1
    if count != NO_ORIENTATION_READINGS:
        return
    text = (
        f"tracker {tracker_id}: its samples carry no orientation (the device kept an output configuration without "
        "one); the kinematics gets no pose from them: give it an orientation output (quaternion) in MT Manager, "
        "or let the driver configure it (docs/devices.md)"
    )
    log.warning("%s", text)
    if device is not None:
        device.stats.last_error = text


# ------------------------------------------------------------------------------------------------ sinks


class ZenohSink:
    """Publishes each message on its key with a loss-free publisher declared on first use, which keeps the last
    :data:`~services.transport.zenoh_session.DEVICE_HISTORY_SAMPLES` for a restarted recorder."""

    def __init__(self, session: zenoh.Session) -> None:
        self._session = session
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()

    def __call__(self, key: str, message: Message, host_time_ns: int, device_time_ns: int) -> None:
        with self._lock:
            publisher = self._publishers.get(key)
            if publisher is None:
                type_name = messages.type_name(message)
                if zenoh_session.keeps_history(key):
                    publisher = zenoh_session.declare_history_publisher(self._session, key, type_name)
                else:
                    publisher = zenoh_session.declare_data_publisher(self._session, key, type_name)
                self._publishers[key] = publisher
        zenoh_session.publish(publisher, message)

    def close(self) -> None:
        with self._lock:
            for publisher in self._publishers.values():
                publisher.undeclare()
            self._publishers.clear()


class McapSink:
    """Writes each message to an MCAP file (log time = host receive time, publish time = device time)."""

    def __init__(self, writer) -> None:
        self._writer = writer
        self._lock = threading.Lock()
        self.count = 0

    def __call__(self, key: str, message: Message, host_time_ns: int, device_time_ns: int) -> None:
        payload = messages.encode(message)
        with self._lock:
            self._writer.write(key, messages.type_name(message), payload, host_time_ns, device_time_ns or host_time_ns)
            self.count += 1


def run_threads(targets: list[Callable[[], LoopReport]], stop: threading.Event) -> list[LoopReport | BaseException]:
    """Run loops side by side; each result is its report or the exception it raised. Ctrl-C sets ``stop`` and
    lets the loops end cleanly (STOP/QUIT, final status) before re-raising."""
    results: list[LoopReport | BaseException] = [RuntimeError("did not finish")] * len(targets)

    def runner(index: int, target: Callable[[], LoopReport]) -> None:
        try:
            results[index] = target()
        except BaseException as error:  # reported by the caller; a thread must not die silently
            results[index] = error

    threads = [threading.Thread(target=runner, args=(k, t), daemon=True) for k, t in enumerate(targets)]
    for thread in threads:
        thread.start()
    interrupted = False
    for thread in threads:
        while thread.is_alive():
            try:
                thread.join(0.2)
            except KeyboardInterrupt:
                stop.set()
                interrupted = True
    if interrupted:
        raise KeyboardInterrupt
    return results


# ------------------------------------------------------------------------------------------------ opening devices (CLI)


@dataclass(frozen=True)
class DeviceSettings:
    """The devices a driver process opens and how (``msk capture`` and ``msk drivers``; from their command line by
    :func:`device_settings`). At least one device."""

    trigno: str | None = None  # Trigno Control Utility HOST[:PORT]
    trigno_emg_port: int = int(tp.EmgPort.AVANTI)
    trigno_aux_port: int | None = None  # the sensors' accelerometers; None: not read
    trigno_aux_layout: tp.AuxLayout | None = None  # what that port carries; None: from its number (50042: legacy ACC)
    trigno_stop: tp.StopMode = tp.StopMode.STOP_THEN_QUIT
    trigno_id: str = "trigno"  # source id in topics and messages
    xsens: tuple[str, ...] = ()  # tracker serial ports, or "usb" for every Xsens USB device
    xsens_baud: int = 115200
    imu_rate_hz: int = 100
    imu_precision: xbus.Precision = xbus.Precision.FLOAT32
    imu_frame: xbus.CoordinateFrame = xbus.CoordinateFrame.ENU
    segments: dict[str, str] = field(default_factory=dict)  # tracker id (upper case) -> body segment
    mvn: str | None = None  # [HOST:]PORT to listen on for an Xsens MVN network stream (UDP)

    def __post_init__(self) -> None:
        if not self.trigno and not self.xsens and not self.mvn:
            from msk_core.errors import ConfigError

            raise ConfigError(
                "name at least one device: --trigno HOST[:PORT], --xsens PORT|usb and/or --mvn [HOST:]PORT",
                field="devices",
            )


def add_device_arguments(parser) -> None:
    """``--trigno HOST[:PORT]`` and ``--xsens PORT|usb`` with their options (shared by ``msk capture`` and ``msk drivers``;
    :func:`device_settings` reads them)."""
    group = parser.add_argument_group("Delsys Trigno")
    group.add_argument(
        "--trigno",
        metavar="HOST[:PORT]",
        default=None,
        help="Trigno Control Utility address (command port, default 50040)",
    )
    group.add_argument(
        "--trigno-emg-port",
        type=int,
        default=int(tp.EmgPort.AVANTI),
        metavar="PORT",
        help="EMG data port: 50043 (default) or legacy 50041",
    )
    group.add_argument(
        "--trigno-aux-port",
        type=int,
        default=None,
        metavar="PORT",
        help="also read the sensors' accelerometers from this port (50044 AUX, or legacy ACC 50042) and "
        "publish them on msk/<session>/acc/<id> (default: not read)",
    )
    group.add_argument(
        "--trigno-aux-layout",
        choices=[layout.value for layout in tp.AuxLayout],
        default=None,
        help="what the accelerometer port carries: avanti (9 slots a sensor) or legacy_acc (x, y, z a sensor); "
        "default: from the port number (50042 legacy_acc, else avanti), for a base whose ports were moved",
    )
    group.add_argument(
        "--trigno-stop",
        choices=[m.value for m in tp.StopMode],
        default=tp.StopMode.STOP_THEN_QUIT.value,
        help="how to end acquisition",
    )
    group.add_argument("--trigno-id", default="trigno", help="source id used in topics and messages (default: trigno)")
    group = parser.add_argument_group("Xsens")
    group.add_argument(
        "--xsens",
        action="append",
        default=[],
        metavar="SERIAL_PORT|usb",
        help="tracker serial port, or 'usb' for every Xsens USB device (repeatable)",
    )
    group.add_argument("--xsens-baud", type=int, default=115200, help="serial baud rate (default 115200)")
    group.add_argument("--imu-rate", type=int, default=100, help="IMU output rate in Hz (default 100)")
    group.add_argument("--imu-precision", choices=[p.name.lower() for p in xbus.Precision], default="float32")
    group.add_argument("--imu-frame", choices=[f.name for f in xbus.CoordinateFrame], default="ENU")
    group.add_argument(
        "--segment",
        action="append",
        default=[],
        metavar="TRACKER=SEGMENT",
        help="body segment of a tracker id, e.g. 03700ABC=upper_arm_r",
    )
    group = parser.add_argument_group("Xsens MVN (a suit's network stream)")
    group.add_argument(
        "--mvn",
        metavar="[HOST:]PORT",
        default=None,
        help="listen for MVN's network streamer (UDP, quaternion pose, default port 9763) and publish the packs' "
        "segments as trackers mvn-<segment>",
    )


def device_settings(args: argparse.Namespace) -> DeviceSettings:
    """The :class:`DeviceSettings` of a command line parsed with :func:`add_device_arguments`."""
    devices = DeviceSettings(  # refuses a command line without a device before its --segment values are read
        trigno=args.trigno,
        trigno_emg_port=args.trigno_emg_port,
        trigno_aux_port=args.trigno_aux_port,
        trigno_aux_layout=None if args.trigno_aux_layout is None else tp.AuxLayout(args.trigno_aux_layout),
        trigno_stop=tp.StopMode(args.trigno_stop),
        trigno_id=args.trigno_id,
        xsens=tuple(args.xsens),
        xsens_baud=args.xsens_baud,
        imu_rate_hz=args.imu_rate,
        imu_precision=xbus.Precision[args.imu_precision.upper()],
        imu_frame=xbus.CoordinateFrame[args.imu_frame],
        mvn=args.mvn,
    )
    return replace(devices, segments=parse_segments(args.segment))


def open_trigno(devices: DeviceSettings) -> TrignoClient:
    from drivers.trigno.client import TrignoConfig, parse_address

    if devices.trigno is None:
        from msk_core.errors import ConfigError

        raise ConfigError("no Trigno address: give --trigno HOST[:PORT]", field="--trigno")
    host, port = parse_address(devices.trigno)
    client = TrignoClient(
        TrignoConfig(
            host=host,
            command_port=port,
            emg_port=devices.trigno_emg_port,
            aux_port=devices.trigno_aux_port,
            aux_layout=devices.trigno_aux_layout,
            stop_mode=devices.trigno_stop,
        )
    )
    try:
        client.connect()
    except OSError as error:
        from msk_core.errors import ConfigError

        raise ConfigError(f"cannot reach the Trigno server: {error}", field="--trigno", value=devices.trigno) from error
    return client


def open_xsens(devices: DeviceSettings) -> TrackerSet:
    from drivers.xsens import usb
    from drivers.xsens.device import XsensDevice
    from drivers.xsens.serial_transport import SerialTransport

    ports: list[str] = []
    for spec in devices.xsens:
        ports += [d.port for d in usb.list_devices() if d.port] if spec == "usb" else [spec]
    if not ports:
        from msk_core.errors import ConfigError

        raise ConfigError("no Xsens serial port found", field="--xsens", value=list(devices.xsens))
    trackers = TrackerSet()
    try:
        for port in ports:
            device = XsensDevice(SerialTransport(port, baudrate=devices.xsens_baud))
            device.configure(devices.imu_rate_hz, precision=devices.imu_precision, frame=devices.imu_frame)
            trackers.add(device)
    except BaseException:
        trackers.close()
        raise
    return trackers


def parse_segments(items: list[str]) -> dict[str, str]:
    """``--segment TRACKER=SEGMENT`` items -> {tracker id in capitals: segment}."""
    from msk_core.errors import parse_pairs

    pairs = parse_pairs(items, field="--segment", form="TRACKER=SEGMENT")
    return {tracker.upper(): segment for tracker, segment in pairs.items()}


def run_devices(
    devices: DeviceSettings, sink: Sink, *, session: str, duration_s: float | None, stop: threading.Event
) -> list[LoopReport]:
    """Open ``devices`` and run their loops side by side into ``sink``: one report per device, the Trigno's first."""
    targets = []
    client: TrignoClient | None = None
    trackers: TrackerSet | None = None
    receiver: MvnReceiver | None = None
    try:  # whatever fails (a device that cannot be opened, a loop's error), the base is told QUIT, the ports closed
        if devices.trigno:
            client = open_trigno(devices)
            targets.append(
                lambda: trigno_loop(
                    client, session=session, source_id=devices.trigno_id, sink=sink, stop=stop, duration_s=duration_s
                )
            )
        if devices.xsens:
            trackers = open_xsens(devices)
            targets.append(
                lambda: xsens_loop(
                    trackers, session=session, sink=sink, stop=stop, segments=devices.segments, duration_s=duration_s
                )
            )
        if devices.mvn:
            receiver = open_mvn(devices.mvn)
            targets.append(lambda: mvn_loop(receiver, session=session, sink=sink, stop=stop, duration_s=duration_s))
        results = run_threads(targets, stop)
    finally:
        if trackers is not None:
            trackers.close()
        if receiver is not None:
            receiver.close()
        if client is not None:
            client.close()
    reports: list[LoopReport] = []
    for result in results:
        if isinstance(result, BaseException):
            raise result
        reports.append(result)
    return reports
