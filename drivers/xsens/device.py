"""Xsens MTi/MTw control over Xbus: wake-up handling, configuration, measurement, and several trackers by id."""

from __future__ import annotations

import collections
import logging
import threading
import time
from collections import Counter
from dataclasses import dataclass, field

from drivers.xsens import frames, xbus
from drivers.xsens.serial_transport import DeviceDisconnected, ReopenableTransport, Transport
from msk_core.errors import ProtocolError

#: What the project asks a tracker for (PacketCounter and SampleTimeFine with every message).
DEFAULT_QUANTITIES = (0x2010, 0x4020, 0x8020, 0xC020)
#: SampleTimeFine counts at 10 kHz; it wraps after one day on 10/100-series devices, others wrap at 2^32.
SAMPLE_TIME_FINE_HZ = 10_000
SAMPLE_TIME_FINE_DAY = 864_000_000
#: Steps of SampleTimeFine whose smallest is a device's own message period when it sends slower than configured.
LOSS_PERIOD_STEPS = 32
#: A sample may arrive this much older than the newest (an MTi-G's GNSS messages: 42-62 ms); a step back beyond it is
#: the device's clock starting again (SampleTimeFine ticks at 10 kHz).
MAX_LATE_TICKS = 10_000
#: Error codes a measuring device sends of itself (no request's answer): counted, and a request's wait goes on.
STREAM_ERROR_CODES = frozenset({0x1E})  # timer overflow: the device could not keep its sample period
RECONNECT_FAILED = "reconnect failed"

log = logging.getLogger(__name__)


class XbusDeviceError(ProtocolError):
    """The device answered with an Error (0x42) message."""

    def __init__(self, code: int, request: str, port: str = "") -> None:
        self.code = code
        where = f"{port}: " if port else ""  # with several trackers, which one
        super().__init__(
            f"{where}Xsens device error 0x{code:02X} ({xbus.ERROR_CODES.get(code, 'unknown')}) after {request}"
        )


@dataclass(frozen=True)
class ImuReading:
    """One MTData2 message as plain values (None when the device did not send that quantity)."""

    tracker_id: str
    bus_id: int
    packet_counter: int | None
    sample_time_fine: int | None
    quaternion: tuple[float, float, float, float] | None  # in ``frame``, w first
    acceleration: tuple[float, float, float] | None
    rate_of_turn: tuple[float, float, float] | None
    magnetic_field: tuple[float, float, float] | None
    frame: xbus.CoordinateFrame
    host_time_ns: int
    data: xbus.MtData2
    sample_time_offset: int = 0  # ticks added by unwrapping SampleTimeFine (a day per wrap on 10/100-series)
    #: without SampleTimeFine: the time :meth:`XsensDevice.read` gave it instead (its unwrapped PacketCounter times
    #: the message period of the applied outputs, else its arrival), ns
    time_without_clock_ns: int | None = None

    @property
    def device_time_ns(self) -> int:
        """Device time since power-up, continuous across SampleTimeFine wraps; without SampleTimeFine the time the
        reader gave it (:attr:`time_without_clock_ns`), 0 when it gave none."""
        if self.sample_time_fine is not None:
            return (self.sample_time_fine + self.sample_time_offset) * 100_000
        return self.time_without_clock_ns or 0

    def quaternion_enu(self) -> tuple[float, float, float, float] | None:
        return None if self.quaternion is None else frames.to_enu(self.quaternion, self.frame)


#: An incomplete frame that stays so this long while nothing arrives is noise that looked like a header (a frame
#: of the longest standard length takes 22 ms at 115200 baud): the frames behind it are released.
STALLED_FRAME_S = 0.2

#: How often :meth:`XsensDevice.ask` sends a request that changes nothing before it gives up.
REQUEST_ATTEMPTS = 3


@dataclass
class DeviceStats:
    messages: int = 0
    readings: int = 0
    decode_errors: int = 0
    packets_lost: int = 0  # from PacketCounter jumps: corrupted or dropped messages
    device_errors: int = 0
    restarts: int = 0  # WakeUp seen while measuring: the device reset itself (counters start again)
    reconnects: int = 0  # reopened and reconfigured after an unplug
    requests_repeated: int = 0  # a request that changes nothing asked again when no reply came in time
    device_warnings: int = 0  # Xbus Warning (0x43) messages: said in last_error, not counted as errors
    last_error: str = ""
    # the last_error a minor condition set (note(minor=True)), which the next one may replace
    _minor_text: str = field(default="", repr=False)

    def note(self, text: str, *, minor: bool = False) -> None:
        """Say ``text`` in last_error. A minor condition (line noise counted so far, a device warning) does not
        replace a message it did not set: a device error, a restart or a configuration the device applied otherwise
        would be lost within a second to "N bad Xbus frames so far" (found by an independent imitation), and its
        count alone does not say what it was."""
        if minor:
            if self.last_error and self.last_error != self._minor_text:
                return
            self._minor_text = text
        self.last_error = text


@dataclass(frozen=True)
class FirmwareRevision:
    major: int
    minor: int
    revision: int

    def __str__(self) -> str:
        return f"{self.major}.{self.minor}.{self.revision}"


def output_settings(
    rate_hz: int,
    *,
    precision: xbus.Precision = xbus.Precision.FLOAT32,
    frame: xbus.CoordinateFrame = xbus.CoordinateFrame.ENU,
    quantities: tuple[int, ...] = DEFAULT_QUANTITIES,
) -> list[xbus.OutputSetting]:
    """PacketCounter + SampleTimeFine with every message, then ``quantities`` at ``rate_hz``."""
    if not 1 <= rate_hz <= 2000:
        raise ProtocolError(f"output rate must be 1..2000 Hz, got {rate_hz}")
    settings = [xbus.OutputSetting(0x1020, 0xFFFF), xbus.OutputSetting(0x1060, 0xFFFF)]
    settings += [xbus.OutputSetting(xbus.make_data_id(q, precision, frame), rate_hz) for q in quantities]
    return settings


class XsensDevice:
    """One Xbus device on a transport. Methods block for at most ``reply_timeout_s``; errors raise typed exceptions,
    except in :meth:`read`, which counts decode errors and lost packets instead."""

    def __init__(self, transport: Transport, *, reply_timeout_s: float = 1.0, bid: int = xbus.BID_MASTER) -> None:
        self.transport = transport
        self.reply_timeout_s = reply_timeout_s
        self.bid = bid
        self.parser = xbus.XbusParser()
        self.stats = DeviceStats()
        self.device_id: int | None = None
        self.device_id_size = 4  # bytes of the DeviceID reply (4, or 8 on newer devices): hex digits of tracker_id
        self.output_configuration: list[xbus.OutputSetting] = []  # as the device echoed it (what it applied)
        self._queue: list[xbus.XbusMessage] = []  # data frames read while waiting for a reply
        self._stalled_since: float | None = None  # since when an incomplete frame waits with nothing arriving
        self._last_counter: dict[int, int] = {}
        self._last_time: dict[int, int] = {}  # last SampleTimeFine per bus id
        #: per bus id, without a PacketCounter: (newest unwrapped SampleTimeFine, its recent steps) for the loss count
        self._time_loss: dict[int, tuple[int, collections.deque]] = {}
        self._time_offset: dict[int, int] = {}  # unwrapping offset per bus id
        self._long_clock: set[int] = set()  # bus ids whose SampleTimeFine went past a day: they wrap at 2^32
        self._counter_ticks: dict[int, int] = {}  # messages since the counter's first (unwrapped), per bus id
        #: per bus id, (device time ns, counter ticks) of the latest message with SampleTimeFine
        self._clock_anchor: dict[int, tuple[int, int]] = {}
        self._untimed: set[int] = set()  # bus ids whose messages came without SampleTimeFine (said once)
        # configure()'s arguments (rate, precision, frame), replayed by reconnect()
        self._configured: tuple[int, xbus.Precision, xbus.CoordinateFrame] | None = None

    @property
    def tracker_id(self) -> str:
        return f"{self.device_id:0{2 * self.device_id_size}X}" if self.device_id is not None else self.transport.name

    # ------------------------------------------------------------------------------------------ messaging
    def send(self, mid: int, data: bytes = b"") -> None:
        self.transport.write(xbus.encode_message(mid, data, self.bid))

    def _read_messages(self) -> list[xbus.XbusMessage]:
        """The frames of what the transport has now; an incomplete frame that stays incomplete while nothing arrives
        for STALLED_FRAME_S is a false header and is released (:meth:`XbusParser.release_stalled`)."""
        chunk = self.transport.read(4096)
        messages = self.parser.feed(chunk)
        if chunk or messages or not self.parser.pending:
            self._stalled_since = None
            return messages
        now = time.monotonic()
        if self._stalled_since is None:
            self._stalled_since = now
        elif now - self._stalled_since >= STALLED_FRAME_S:
            self._stalled_since = None
            messages = self.parser.release_stalled()
        return messages

    def request(
        self, mid: int, data: bytes = b"", *, reply_mid: int | None = None, timeout: float | None = None
    ) -> xbus.XbusMessage:
        """Send ``mid`` and wait for ``reply_mid`` (default mid + 1); MTData2 frames in between are kept for read()."""
        expected = mid + 1 if reply_mid is None else reply_mid
        self.send(mid, data)
        deadline = time.monotonic() + (self.reply_timeout_s if timeout is None else timeout)
        name = _mid_name(mid)
        parsed = self.parser.stats
        before = (parsed.bytes_in, parsed.bytes_skipped, parsed.errors)
        other: Counter[str] = Counter()  # the messages that came instead of the reply
        while time.monotonic() < deadline:
            messages = self._read_messages()
            other.update(_mid_name(m.mid) for m in messages if m.mid != expected)
            for index, message in enumerate(messages):
                if message.mid == expected:
                    # frames after the reply (data right after GoToMeasurementAck) belong to read()
                    self._queue += [m for m in messages[index + 1 :] if m.mid == xbus.Mid.MT_DATA2]
                    return message
                if message.mid == xbus.Mid.ERROR:
                    self.stats.device_errors += 1
                    code = message.data[0] if message.data else -1
                    if code in STREAM_ERROR_CODES:  # the measurement's, sent while the reply is on its way
                        self.stats.last_error = f"device error 0x{code:02X} ({xbus.ERROR_CODES[code]}) while measuring"
                        continue
                    raise XbusDeviceError(code, name, self.transport.name)
                if message.mid == xbus.Mid.WAKE_UP:
                    self.send(xbus.Mid.WAKE_UP_ACK)
                elif message.mid == xbus.Mid.MT_DATA2:
                    self._queue.append(message)
        got = parsed.bytes_in - before[0]
        garbled = got and not other and parsed.bytes_skipped > before[1]
        arrived = (
            f"received {got} bytes"
            + (
                f": {sum(other.values())} Xbus messages ({', '.join(f'{n} {m}' for m, n in other.most_common())}), "
                f"{parsed.bytes_skipped - before[1]} bytes not Xbus, {parsed.errors - before[2]} bad frames"
                if got
                else ""
            )
            + (
                f"; bytes but no Xbus frame: is the device's baud rate {getattr(self.transport, 'baudrate', '?')}? "
                "(--xsens-baud sets the host side only; the device keeps the rate set in MT Manager, factory 115200)"
                if garbled
                else ""
            )
        )
        raise ProtocolError(
            f"{self.transport.name}: no reply 0x{expected:02X} to {name} within {timeout or self.reply_timeout_s} s "
            f"({arrived})"
        )

    # ------------------------------------------------------------------------------------------ control
    def wait_for_wakeup(self, timeout: float = 1.0) -> bool:
        """After power-up or Reset: acknowledge WakeUp so the device stays in Config state. False if none came."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for message in self._read_messages():
                if message.mid == xbus.Mid.WAKE_UP:
                    self.send(xbus.Mid.WAKE_UP_ACK)
                    return True
        return False

    def reset(self, *, timeout: float = 1.0) -> bool:
        """Reset the device and catch its WakeUp so it stays in Config state; True when the WakeUp was acked."""
        self.send(xbus.Mid.RESET)  # ResetAck, then WakeUp: both are consumed by wait_for_wakeup
        return self.wait_for_wakeup(timeout)

    def set_baudrate(self, rate: int, *, timeout: float = 1.0) -> None:
        """Move the device and the host port to ``rate`` bit/s: SetBaudrate (stored by the device, effective after a
        restart), Reset, host port switched after the ResetAck, WakeUp acknowledged at the new rate (Config state)."""
        code = xbus.baud_code(rate)
        switch = getattr(self.transport, "set_baudrate", None)
        if switch is None:
            raise ProtocolError(f"{self.transport.name}: this transport has no baud rate to change")
        self.go_to_config()
        self.request(xbus.Mid.BAUDRATE, bytes((code,)))
        self.send(xbus.Mid.RESET)
        deadline = time.monotonic() + timeout
        switched = False
        while time.monotonic() < deadline:
            for message in self._read_messages():
                if message.mid == xbus.Mid.RESET_ACK and not switched:
                    switch(rate)  # the ack came at the old rate; what follows comes at the new one
                    switched = True
                elif message.mid == xbus.Mid.WAKE_UP:
                    if not switched:
                        switch(rate)
                    self.send(xbus.Mid.WAKE_UP_ACK)
                    self._counting_starts_again()
                    return
        raise ProtocolError(f"{self.transport.name}: no WakeUp at {rate} bit/s within {timeout} s of the reset")

    def ask(self, mid: int, data: bytes = b"", *, attempts: int = REQUEST_ATTEMPTS) -> xbus.XbusMessage:
        """:meth:`request` for a request that changes nothing when repeated and whose late reply says what the next
        one's would (GoToConfig, ReqDID, the product code and firmware queries, one output configuration set
        again, GoToMeasurement): asked again when no reply comes in time, as a request lost on the line or a device
        busy streaming (or starting, on a loaded host) would need."""
        for attempt in range(1, attempts + 1):
            try:
                return self.request(mid, data)
            except XbusDeviceError:
                raise
            except ProtocolError as error:
                if attempt == attempts:
                    raise ProtocolError(f"{error} (asked {attempts} times)") from None
                self.stats.requests_repeated += 1
        raise AssertionError("unreachable")

    def go_to_config(self, *, attempts: int = REQUEST_ATTEMPTS) -> None:
        """Enter Config state (a streaming device may need more than one request at high rates)."""
        self.ask(xbus.Mid.GO_TO_CONFIG, attempts=attempts)
        self._queue.clear()  # data from before the configuration is stale

    def request_device_id(self) -> int:
        reply = self.ask(xbus.Mid.REQ_DID)
        if len(reply.data) not in (4, 8):
            raise ProtocolError(f"DeviceID reply has {len(reply.data)} bytes, expected 4 or 8")
        self.device_id = int.from_bytes(reply.data, "big")  # 8-byte ids (newer devices) kept whole: unique keys
        self.device_id_size = len(reply.data)
        return self.device_id

    def request_product_code(self) -> str:
        reply = self.ask(xbus.Mid.REQ_PRODUCT_CODE)
        return reply.data.decode("ascii", errors="replace").strip().strip("\x00")

    def request_firmware_revision(self) -> FirmwareRevision:
        reply = self.ask(xbus.Mid.REQ_FW_REV)
        if len(reply.data) < 3:
            raise ProtocolError(f"FirmwareRev reply has {len(reply.data)} bytes, expected at least 3")
        return FirmwareRevision(*reply.data[:3])

    def set_output_configuration(self, settings: list[xbus.OutputSetting]) -> list[xbus.OutputSetting]:
        """Apply an output configuration; returns what the device says it applied (its ack echoes the applied
        configuration, which may differ from the request: rates rounded to what the device can do, 0 for 0xFFFF).
        Differences are logged and counted in ``stats.last_error``; an echo without payload means "as requested"."""
        try:
            reply = self.ask(xbus.Mid.SET_OUTPUT_CONFIGURATION, xbus.encode_output_configuration(settings))
        except XbusDeviceError as error:  # which outputs, so that the user knows what to change
            asked = ", ".join(
                f"0x{s.data_id:04X} at {'every message' if s.frequency in xbus.EVERY_MESSAGE else f'{s.frequency} Hz'}"
                for s in settings
            )
            error.args = (f"{error.args[0]}; asked for {asked} (a lower --imu-rate may be what it can do)",)
            raise
        applied = xbus.decode_output_configuration(reply.data) if reply.data else list(settings)
        differences = configuration_differences(settings, applied)
        if differences:
            self.stats.last_error = f"{self.transport.name}: output configuration applied differs: {differences}"
            log.warning("%s", self.stats.last_error)
        self.output_configuration = applied
        return applied

    def request_baudrate(self) -> int:
        """The device's serial baud rate in bit/s (ReqBaudrate 0x18 with no data; the reply carries the code)."""
        reply = self.request(xbus.Mid.BAUDRATE)  # not repeated: SetBaudrate shares its reply id
        if len(reply.data) != 1 or reply.data[0] not in xbus.BAUD_CODES:
            raise ProtocolError(f"Baudrate reply {reply.data.hex() or 'empty'} is not one Xbus baud-rate code")
        return xbus.BAUD_CODES[reply.data[0]]

    def request_output_configuration(self) -> list[xbus.OutputSetting]:
        # not repeated: a late reply would be taken for the ack of a SetOutputConfiguration after it
        return xbus.decode_output_configuration(self.request(xbus.Mid.SET_OUTPUT_CONFIGURATION).data)

    def go_to_measurement(self) -> None:
        """Enter Measurement. A device whose acknowledgement is late or lost but whose data already flow is
        measuring: taken as done (a slow tracker was given up while it streamed)."""
        try:
            self.ask(xbus.Mid.GO_TO_MEASUREMENT)
        except XbusDeviceError:
            raise
        except ProtocolError as error:
            if not any(m.mid == xbus.Mid.MT_DATA2 for m in self._queue):
                raise
            log.warning("%s; its data flow: measuring", error)
        self._counting_starts_again()

    def configure(
        self, rate_hz: int = 100, *, precision=xbus.Precision.FLOAT32, frame=xbus.CoordinateFrame.ENU
    ) -> dict:
        """The usual sequence: GoToConfig, identify, set outputs, GoToMeasurement. Returns the device's identity."""
        self._configured = (rate_hz, precision, frame)
        self.go_to_config()
        self.request_device_id()
        product, firmware = self._informative_identity()
        applied = self.set_output_configuration(output_settings(rate_hz, precision=precision, frame=frame))
        self._check_line_capacity(applied)
        self.go_to_measurement()
        return {"device_id": self.tracker_id, "product_code": product, "firmware": str(firmware), "outputs": applied}

    def _informative_identity(self) -> tuple[str, FirmwareRevision | str]:
        """The product code and firmware, which only inform: a device that answers either with an Error is still
        configured (said in the status), as its outputs and data do not depend on them."""
        answers: list[str | FirmwareRevision] = []
        for name, ask in (("product code", self.request_product_code), ("firmware", self.request_firmware_revision)):
            try:
                answers.append(ask())
            except XbusDeviceError as error:
                answers.append("unknown")
                self.stats.last_error = f"{error}: its {name} is not known, the device is configured without it"
                log.warning("%s", self.stats.last_error)
        return str(answers[0]), answers[1]

    def _check_line_capacity(self, settings: list[xbus.OutputSetting]) -> None:
        """Warn when the outputs need more than the serial line carries (the device then drops messages; the
        factory 115200 baud holds about 11 kB/s). Native USB devices have no line rate (no ``baudrate``)."""
        baudrate = getattr(self.transport, "baudrate", None)
        needed = xbus.output_bits_per_second(settings)
        if baudrate and needed > 0.9 * baudrate:
            self.stats.last_error = (
                f"{self.transport.name}: outputs need {needed / 1000:.0f} kbit/s, the line carries {baudrate / 1000:.0f}"
                " kbit/s: lower the rate or precision, or raise the baud rate"
            )
            log.warning("%s", self.stats.last_error)

    # ------------------------------------------------------------------------------------------ measurement
    def read(self) -> list[ImuReading]:
        """Readings available now (waits at most the transport timeout). Raises DeviceDisconnected when unplugged."""
        messages, self._queue = self._queue, []
        errors_before = self.parser.stats.errors
        messages += self._read_messages()
        if self.parser.stats.errors != errors_before:  # counted by the parser: said here, for the status
            self.stats.note(line_errors_text(self.parser.stats), minor=True)
        readings: list[ImuReading] = []
        now = time.time_ns()
        for message in messages:
            self.stats.messages += 1
            if message.mid == xbus.Mid.ERROR:
                self.stats.device_errors += 1
                code = message.data[0] if message.data else 0
                self.stats.note(f"device error 0x{code:02X} ({xbus.ERROR_CODES.get(code, 'unknown')})")
                continue
            if message.mid == xbus.Mid.WARNING:  # reported by the device, not a fault of the data: said, counted
                self.stats.device_warnings += 1
                detail = f" (payload {message.data.hex(' ')})" if message.data else ""
                self.stats.note(
                    f"{self.stats.device_warnings} device warning(s) (Xbus Warning 0x43) so far, the last{detail}",
                    minor=True,
                )
                continue
            if message.mid == xbus.Mid.WAKE_UP:
                # The device reset itself (power dip, watchdog). Not acknowledged: without a WakeUpAck it returns
                # to Measurement with its stored outputs; its PacketCounter starts again, which is no packet loss.
                if self.stats.readings or readings:
                    self.stats.restarts += 1
                    self.stats.last_error = "device restarted (WakeUp while measuring)"
                self._counting_starts_again(clock_too=True)
                continue
            if message.mid != xbus.Mid.MT_DATA2:
                continue
            try:
                data = xbus.decode_mtdata2(message.data)
            except ProtocolError as error:
                self.stats.decode_errors += 1
                self.stats.last_error = str(error)
                continue
            readings.append(self._reading(message.bid, data, now))
        self.stats.readings += len(readings)
        return readings

    def _reading(self, bid: int, data: xbus.MtData2, now: int) -> ImuReading:
        counter = data.first("packet_counter")  # first: a counter that went back says "restart", not "wrap"
        if counter is not None:
            last = self._last_counter.get(bid)
            ticks = 0  # the first message, or the first after a restart
            if last is not None:
                skipped = (counter - last - 1) & 0xFFFF
                if skipped >= 0x8000:  # the counter went back: a restart whose WakeUp was lost, not 65k lost packets
                    self._restarted_without_wakeup(bid, f"its packet counter went back from {last} to {counter}")
                else:
                    self.stats.packets_lost += skipped
                    ticks = self._counter_ticks.get(bid, 0) + skipped + 1
            self._last_counter[bid] = counter
            self._counter_ticks[bid] = ticks
        sample_time = data.first("sample_time_fine")
        offset = 0 if sample_time is None else self._unwrapped_offset(bid, sample_time)
        if counter is None and sample_time is not None:
            self._count_lost_by_time(bid, sample_time + offset)
        tracker = self.tracker_id if bid == xbus.BID_MASTER else f"{self.tracker_id}-{bid:02d}"
        untimed = None if sample_time is not None else self._time_without_clock(bid, tracker, counter is not None, now)
        if sample_time is not None and counter is not None:  # where a message without it continues from
            self._clock_anchor[bid] = ((sample_time + offset) * 100_000, self._counter_ticks[bid])
        return ImuReading(
            tracker_id=tracker,
            bus_id=bid,
            packet_counter=counter,
            sample_time_fine=sample_time,
            sample_time_offset=offset,
            quaternion=orientation_quaternion(data),
            acceleration=data.get("acceleration"),
            rate_of_turn=data.get("rate_of_turn"),
            magnetic_field=data.get("magnetic_field"),
            frame=data.frame(),
            host_time_ns=now,
            data=data,
            time_without_clock_ns=untimed,
        )

    def _counting_starts_again(self, *, clock_too: bool = False) -> None:
        """The device's messages are counted anew (it entered Measurement again): no loss is reckoned across the
        break, by counter or by SampleTimeFine, and a message without SampleTimeFine no longer continues the old count.
        ``clock_too``: its SampleTimeFine starts again as well (a restart, another device on the port)."""
        self._last_counter.clear()
        self._time_loss.clear()
        self._clock_anchor.clear()
        if clock_too:
            self._last_time.clear()
            self._time_offset.clear()

    def _count_lost_by_time(self, bid: int, ticks: int) -> None:
        """A device that sends no PacketCounter (it did not apply 0x1020): the messages missing between two
        SampleTimeFines more than a message period apart are counted lost, as the counter would have counted them
        (uncounted before 28 Nov: 1 message in 10 lost, ``packets_lost`` 0). The period is the applied outputs' rate's,
        or the smallest of the recent steps when longer: a device sending slower than configured (an Awinda tracker's
        rate limit with many trackers) is not losing every other message. ``ticks``: unwrapped SampleTimeFine."""
        newest, steps = self._time_loss.get(bid, (None, None))
        if newest is None or steps is None or ticks < newest - MAX_LATE_TICKS:  # the first, or the clock restarted
            self._time_loss[bid] = (ticks, collections.deque(maxlen=LOSS_PERIOD_STEPS))
            return
        step = ticks - newest
        if step <= 0:  # late (an MTi-G's GNSS message, 42-62 ms older) or the same instant: no step of the clock
            return
        steps.append(step)
        self._time_loss[bid] = (ticks, steps)
        rate = xbus.message_rate_hz(self.output_configuration)
        period = max(SAMPLE_TIME_FINE_HZ / rate if rate else 0.0, float(min(steps)))
        self.stats.packets_lost += max(0, round(step / period) - 1)

    def _time_without_clock(self, bid: int, tracker: str, counted: bool, now: int) -> int:
        """The time of a message without SampleTimeFine (a device that did not apply it, or keeps its own outputs):
        its unwrapped PacketCounter ("+1 per message") times the message period of the applied outputs, else its
        arrival. Said once per bus id: downstream the samples are placed by it."""
        rate = xbus.message_rate_hz(self.output_configuration)
        if counted and rate:  # from the last message that had SampleTimeFine, when one had: the one clock
            anchor_ns, anchor_ticks = self._clock_anchor.get(bid, (0, 0))
            how = f"its PacketCounter at {rate:g} Hz"
            value = anchor_ns + int(round((self._counter_ticks[bid] - anchor_ticks) * 1e9 / rate))
        else:
            how, value = "their arrival (nor a PacketCounter and an output rate)", now
        if bid not in self._untimed:
            self._untimed.add(bid)
            self.stats.last_error = f"{tracker}: its messages carry no SampleTimeFine; timed by {how}"
            log.warning("%s", self.stats.last_error)
        return value

    def _unwrapped_offset(self, bid: int, sample_time: int) -> int:
        """Ticks to add to this SampleTimeFine to continue the device's clock past its wraps (a day, or 2^32 on devices
        that count on). Judged by the signed step from the newest sample, so a sample that arrives late (an MTi-G's
        GNSS messages carry times some 50 ms older than the message before) is placed before it, also across a wrap,
        and never moves the newest time back. A step back of more than ``MAX_LATE_TICKS`` is a restart."""
        last = self._last_time.get(bid)
        offset = self._time_offset.get(bid, 0)
        if last is None:
            self._last_time[bid] = sample_time
            return offset
        if last >= SAMPLE_TIME_FINE_DAY:  # this device counts past a day: it wraps at 2^32 (also after a wrap)
            self._long_clock.add(bid)
        period = 1 << 32 if bid in self._long_clock else SAMPLE_TIME_FINE_DAY
        step = sample_time - last
        if step < -period // 2:  # the clock wrapped between the newest sample and this one
            offset += period
            self._time_offset[bid], self._last_time[bid] = offset, sample_time
        elif step > period // 2:  # from before a wrap that a newer sample already crossed, arriving late
            return offset - period
        elif step >= 0:
            self._last_time[bid] = sample_time
        elif step < -MAX_LATE_TICKS:
            self._restarted_without_wakeup(bid, f"its sample time went back {-step / 10_000:.1f} s")
            self._last_time[bid] = sample_time
            return 0
        return offset

    def _restarted_without_wakeup(self, bid: int, why: str) -> None:
        """The device started again and its WakeUp never reached us (garbled, or sent while the port was closed):
        its counters and clock restart, which loses nothing."""
        if bid in self._last_counter or bid in self._last_time:
            self.stats.restarts += 1
            self.stats.last_error = f"device restarted ({why}; its WakeUp was not received)"
        self._last_counter.pop(bid, None)
        self._last_time.pop(bid, None)
        self._time_loss.pop(bid, None)
        self._clock_anchor.pop(bid, None)
        self._time_offset.pop(bid, None)

    def close(self) -> None:
        self.transport.close()

    @property
    def can_reconnect(self) -> bool:
        return self._configured is not None and isinstance(self.transport, ReopenableTransport)

    def reconnect(self, *, probe_timeout_s: float = 0.3) -> None:
        """Open the port again and redo configure() with the same arguments (after an unplug). The device must
        report the same device id. Raises DeviceDisconnected while it is absent, ProtocolError when it does not
        answer or is another device; statistics carry on. A single short GoToConfig probes first: a port that is
        back without its device (a USB-serial converter whose sensor is off) must not block the caller for the
        full configure() timeouts."""
        configured = self._configured
        if configured is None or not isinstance(self.transport, ReopenableTransport):  # as can_reconnect says
            raise ProtocolError(
                f"{self.transport.name}: cannot reconnect (never configured, or the transport cannot reopen)"
            )
        previous = self.device_id
        transport = self.transport.reopen()
        self.transport = transport
        self.parser = xbus.XbusParser()
        self._queue.clear()
        self._counting_starts_again(clock_too=True)
        size = self.device_id_size
        try:
            self.request(xbus.Mid.GO_TO_CONFIG, timeout=probe_timeout_s)
            self.request_device_id()  # before its outputs are set: another device here keeps its own (the probe
            # above did put it in Config state)
            if previous is not None and self.device_id != previous:
                found = self.tracker_id
                self.device_id, self.device_id_size = previous, size  # the tracker keeps its id
                raise ProtocolError(
                    f"{transport.name}: device {found} answered where {self.tracker_id} was; left unconfigured"
                )
            rate_hz, precision, frame = configured
            self.configure(rate_hz, precision=precision, frame=frame)
        except BaseException:
            transport.close()
            raise
        self.stats.reconnects += 1


def orientation_quaternion(data: xbus.MtData2) -> tuple[float, float, float, float] | None:
    """The message's orientation as a quaternion (w first) in its output frame: the quaternion output, else the one
    of its rotation matrix or Euler angles (a device that applied one of these instead of the quaternion asked for, or
    that kept a configuration of its own); None when the message carries no orientation (an MTi-G's GNSS message)."""
    quaternion = data.get("quaternion")
    if quaternion is not None:
        return quaternion
    matrix = data.get("rotation_matrix")
    if matrix is not None:
        return frames.quat_from_rotation_matrix(matrix)
    euler = data.get("euler")
    if euler is not None:
        return frames.quat_from_euler_deg(*euler)
    return None


def configuration_differences(requested: list[xbus.OutputSetting], applied: list[xbus.OutputSetting]) -> list[str]:
    """What the device applied differently from the request (0 and 0xFFFF, "every message", are the same)."""

    def normal(frequency: int) -> int:
        return 0xFFFF if frequency in xbus.EVERY_MESSAGE else frequency

    wanted = {s.data_id: normal(s.frequency) for s in requested}
    got = {s.data_id: normal(s.frequency) for s in applied}
    out = [f"0x{i:04X} missing" for i in wanted if i not in got]
    out += [f"0x{i:04X} at {got[i]} Hz instead of {f}" for i, f in wanted.items() if i in got and got[i] != f]
    out += [f"0x{i:04X} added" for i in got if i not in wanted]
    return out


def line_errors_text(parsed: xbus.ParserStats) -> str:
    """What the serial line delivered that was not a frame, so far: e.g. "14 bad Xbus frames so far (checksum 12,
    length 2); 310 bytes skipped" (a noisy cable, a wrong baud rate or another device's protocol)."""
    kinds = [
        f"{name} {n}"
        for name, n in (
            ("checksum", parsed.checksum_errors),
            ("length", parsed.length_errors),
            ("structure", parsed.structure_errors),
        )
        if n
    ]
    return f"{parsed.errors} bad Xbus frames so far ({', '.join(kinds)}); {parsed.bytes_skipped} bytes skipped"


def _mid_name(mid: int) -> str:
    try:
        return xbus.Mid(mid).name
    except ValueError:
        return f"MID 0x{mid:02X}"


@dataclass
class TrackerSet:
    """Several devices keyed by tracker id (device id as 8 hex digits). An unplugged device moves to
    ``disconnected`` (reason kept); with ``reconnect`` its port is reopened after ``retry_interval_s``, the delay
    doubling after each failure up to ``retry_max_s``, and once the same device answers it is reconfigured as before
    and returns to ``devices`` (same XsensDevice object). Each attempt runs in a thread of its own: a device that
    answers slowly may hold its attempt for seconds (its configure requests are asked again), while the other
    trackers are read on."""

    devices: dict[str, XsensDevice] = field(default_factory=dict)
    disconnected: dict[str, str] = field(default_factory=dict)
    reconnect: bool = True
    retry_interval_s: float = 0.5
    retry_max_s: float = 5.0
    stall_s: float = 3.0  # a connected tracker that gives no reading for this long has stopped streaming: lost
    _last_data: dict[str, float] = field(default_factory=dict)  # monotonic time of each tracker's newest reading
    _lost: dict[str, XsensDevice] = field(default_factory=dict)
    _next_attempt: dict[str, float] = field(default_factory=dict)
    _delay: dict[str, float] = field(default_factory=dict)
    _attempts: dict[str, threading.Thread] = field(default_factory=dict)  # reconnection attempts under way
    _failures: dict[str, Exception | None] = field(default_factory=dict)  # a finished attempt's error (None: back)
    _closed: threading.Event = field(default_factory=threading.Event)  # close() was called

    @property
    def reconnecting(self) -> list[str]:
        """The trackers whose reconnection attempt is under way now."""
        return [key for key, attempt in self._attempts.items() if attempt.is_alive()]

    def add(self, device: XsensDevice) -> str:
        if device.device_id is None:
            device.request_device_id()
        key = device.tracker_id
        if key in self.devices:
            raise ProtocolError(f"two devices report the same id {key}")
        self.devices[key] = device
        self._last_data[key] = time.monotonic()
        return key

    def read(self) -> list[ImuReading]:
        """Readings of every connected tracker; an unplugged one, or one silent for ``stall_s`` (a tracker that
        stopped streaming while its port stays open: nothing else would notice), moves to ``disconnected`` with the
        reason, and is reconnected (reconfigured) like an unplugged one."""
        out = []
        for key, device in list(self.devices.items()):
            now = time.monotonic()
            try:
                readings = device.read()
            except DeviceDisconnected as error:
                self._lose(key, device, str(error))
                continue
            out += readings
            if readings:
                self._last_data[key] = now
            elif now - self._last_data.get(key, now) > self.stall_s:
                self._lose(
                    key,
                    device,
                    f"{device.transport.name}: no reading from tracker {key} for {now - self._last_data[key]:.1f} s "
                    f"(its port open, {device.parser.stats.bytes_in} bytes received in all): it stopped streaming",
                )
        if self._lost:
            self._try_reconnect()
        return out

    def _lose(self, key: str, device: XsensDevice, reason: str) -> None:
        log.warning("tracker %s lost: %s", key, reason)
        self.disconnected[key] = reason
        del self.devices[key]
        device.close()
        if self.reconnect and device.can_reconnect:
            self._lost[key] = device
            self._delay[key] = self.retry_interval_s
            self._next_attempt[key] = time.monotonic() + self.retry_interval_s

    def _try_reconnect(self) -> None:
        """Take the finished attempts (a device back, or the next attempt's delay doubled) and start those due."""
        now = time.monotonic()
        for key, device in list(self._lost.items()):
            attempt = self._attempts.get(key)
            if attempt is not None:
                if attempt.is_alive():
                    continue
                del self._attempts[key]
                error = self._failures.pop(key)
                if error is None:
                    del self._lost[key], self._next_attempt[key], self._delay[key], self.disconnected[key]
                    self.devices[key] = device
                    self._last_data[key] = time.monotonic()
                    if device.stats.last_error.startswith(RECONNECT_FAILED):  # that is over now
                        device.stats.last_error = ""
                    continue
                device.stats.last_error = f"{RECONNECT_FAILED}: {error}"  # ``disconnected`` keeps why it went away
                self._delay[key] = min(2 * self._delay[key], self.retry_max_s)
                self._next_attempt[key] = time.monotonic() + self._delay[key]
            elif now >= self._next_attempt[key]:
                attempt = threading.Thread(
                    target=self._reconnect, args=(key, device), name=f"xsens-reconnect-{key}", daemon=True
                )
                self._attempts[key] = attempt
                attempt.start()

    def _reconnect(self, key: str, device: XsensDevice) -> None:
        """One attempt (in its own thread): its outcome for :meth:`_try_reconnect`; the port closed again when the
        set was closed meanwhile."""
        outcome: Exception | None = RuntimeError("the reconnection attempt ended without an outcome")
        try:
            device.reconnect()
            outcome = None
        except (DeviceDisconnected, ProtocolError) as error:
            outcome = error
        except Exception as error:  # not a device's answer: a fault here, logged whole, and retried like the others
            log.exception("%s: reconnection attempt failed", key)
            outcome = error
        finally:
            self._failures[key] = outcome
            if outcome is None and self._closed.is_set():
                device.close()

    def retry_delay(self, key: str) -> float | None:
        """Seconds between reconnection attempts for a lost tracker now (None when it is not lost)."""
        return self._delay.get(key)

    def close(self) -> None:
        """Close every port; an attempt still under way closes its own when it ends (waited for up to 5 s here)."""
        self._closed.set()
        deadline = time.monotonic() + 5.0
        for attempt in self._attempts.values():
            attempt.join(timeout=max(0.0, deadline - time.monotonic()))
        for key, device in self._lost.items():
            if key in self._failures and self._failures[key] is None:  # reconnected after the last read: port open
                device.close()
        for device in self.devices.values():
            device.close()
        self.devices.clear()
        self._lost.clear()
        self._attempts.clear()
