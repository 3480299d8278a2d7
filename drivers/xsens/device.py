"""Xsens MTi/MTw control over Xbus: wake-up handling, configuration, measurement, and several trackers by id."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from drivers.xsens import frames, xbus
from drivers.xsens.serial_transport import DeviceDisconnected, Transport
from msk_core.errors import ProtocolError

#: What the project asks a tracker for (PacketCounter and SampleTimeFine with every message).
DEFAULT_QUANTITIES = (0x2010, 0x4020, 0x8020, 0xC020)


class XbusDeviceError(ProtocolError):
    """The device answered with an Error (0x42) message."""

    def __init__(self, code: int, request: str) -> None:
        self.code = code
        super().__init__(f"Xsens device error 0x{code:02X} ({xbus.ERROR_CODES.get(code, 'unknown')}) after {request}")


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

    @property
    def device_time_ns(self) -> int:
        return 0 if self.sample_time_fine is None else self.sample_time_fine * 100_000

    def quaternion_enu(self) -> tuple[float, float, float, float] | None:
        return None if self.quaternion is None else frames.to_enu(self.quaternion, self.frame)


@dataclass
class DeviceStats:
    messages: int = 0
    readings: int = 0
    decode_errors: int = 0
    packets_lost: int = 0  # from PacketCounter jumps: corrupted or dropped messages
    device_errors: int = 0
    last_error: str = ""


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
        self._queue: list[xbus.XbusMessage] = []  # data frames read while waiting for a reply
        self._last_counter: dict[int, int] = {}

    @property
    def tracker_id(self) -> str:
        return f"{self.device_id:08X}" if self.device_id is not None else self.transport.name

    # ------------------------------------------------------------------------------------------ messaging
    def send(self, mid: int, data: bytes = b"") -> None:
        self.transport.write(xbus.encode_message(mid, data, self.bid))

    def _read_messages(self) -> list[xbus.XbusMessage]:
        return self.parser.feed(self.transport.read(4096))

    def request(self, mid: int, data: bytes = b"", *, reply_mid: int | None = None, timeout: float | None = None) -> xbus.XbusMessage:
        """Send ``mid`` and wait for ``reply_mid`` (default mid + 1); MTData2 frames in between are kept for read()."""
        expected = mid + 1 if reply_mid is None else reply_mid
        self.send(mid, data)
        deadline = time.monotonic() + (self.reply_timeout_s if timeout is None else timeout)
        name = _mid_name(mid)
        while time.monotonic() < deadline:
            messages = self._read_messages()
            for index, message in enumerate(messages):
                if message.mid == expected:
                    # frames after the reply (data right after GoToMeasurementAck) belong to read()
                    self._queue += [m for m in messages[index + 1 :] if m.mid == xbus.Mid.MT_DATA2]
                    return message
                if message.mid == xbus.Mid.ERROR:
                    self.stats.device_errors += 1
                    raise XbusDeviceError(message.data[0] if message.data else -1, name)
                if message.mid == xbus.Mid.WAKE_UP:
                    self.send(xbus.Mid.WAKE_UP_ACK)
                elif message.mid == xbus.Mid.MT_DATA2:
                    self._queue.append(message)
        raise ProtocolError(f"no reply 0x{expected:02X} to {name} within {timeout or self.reply_timeout_s} s")

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

    def go_to_config(self, *, attempts: int = 3) -> None:
        """Enter Config state (a streaming device may need more than one request at high rates)."""
        for attempt in range(attempts):
            try:
                self.request(xbus.Mid.GO_TO_CONFIG)
                self._queue.clear()  # data from before the configuration is stale
                return
            except XbusDeviceError:
                raise
            except ProtocolError:
                if attempt == attempts - 1:
                    raise

    def request_device_id(self) -> int:
        reply = self.request(xbus.Mid.REQ_DID)
        if len(reply.data) not in (4, 8):
            raise ProtocolError(f"DeviceID reply has {len(reply.data)} bytes, expected 4")
        self.device_id = int.from_bytes(reply.data[:4], "big")
        return self.device_id

    def request_product_code(self) -> str:
        reply = self.request(xbus.Mid.REQ_PRODUCT_CODE)
        return reply.data.decode("ascii", errors="replace").strip().strip("\x00")

    def request_firmware_revision(self) -> FirmwareRevision:
        reply = self.request(xbus.Mid.REQ_FW_REV)
        if len(reply.data) < 3:
            raise ProtocolError(f"FirmwareRev reply has {len(reply.data)} bytes, expected at least 3")
        return FirmwareRevision(*reply.data[:3])

    def set_output_configuration(self, settings: list[xbus.OutputSetting]) -> list[xbus.OutputSetting]:
        """Apply an output configuration; returns what the device says it applied."""
        reply = self.request(xbus.Mid.SET_OUTPUT_CONFIGURATION, xbus.encode_output_configuration(settings))
        return xbus.decode_output_configuration(reply.data)

    def request_output_configuration(self) -> list[xbus.OutputSetting]:
        return xbus.decode_output_configuration(self.request(xbus.Mid.SET_OUTPUT_CONFIGURATION).data)

    def go_to_measurement(self) -> None:
        self.request(xbus.Mid.GO_TO_MEASUREMENT)
        self._last_counter.clear()

    def configure(self, rate_hz: int = 100, *, precision=xbus.Precision.FLOAT32, frame=xbus.CoordinateFrame.ENU) -> dict:
        """The usual sequence: GoToConfig, identify, set outputs, GoToMeasurement. Returns the device's identity."""
        self.go_to_config()
        device_id = self.request_device_id()
        product = self.request_product_code()
        firmware = self.request_firmware_revision()
        applied = self.set_output_configuration(output_settings(rate_hz, precision=precision, frame=frame))
        self.go_to_measurement()
        return {"device_id": f"{device_id:08X}", "product_code": product, "firmware": str(firmware), "outputs": applied}

    # ------------------------------------------------------------------------------------------ measurement
    def read(self) -> list[ImuReading]:
        """Readings available now (waits at most the transport timeout). Raises DeviceDisconnected when unplugged."""
        messages, self._queue = self._queue, []
        messages += self._read_messages()
        readings = []
        now = time.time_ns()
        for message in messages:
            self.stats.messages += 1
            if message.mid == xbus.Mid.ERROR:
                self.stats.device_errors += 1
                self.stats.last_error = f"device error 0x{message.data[0] if message.data else 0:02X}"
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
        counter = data.first("packet_counter")
        if counter is not None:
            last = self._last_counter.get(bid)
            if last is not None:
                self.stats.packets_lost += (counter - last - 1) & 0xFFFF
            self._last_counter[bid] = counter
        tracker = self.tracker_id if bid == xbus.BID_MASTER else f"{self.tracker_id}-{bid:02d}"
        return ImuReading(
            tracker_id=tracker,
            bus_id=bid,
            packet_counter=counter,
            sample_time_fine=data.first("sample_time_fine"),
            quaternion=data.get("quaternion"),
            acceleration=data.get("acceleration"),
            rate_of_turn=data.get("rate_of_turn"),
            magnetic_field=data.get("magnetic_field"),
            frame=data.frame(),
            host_time_ns=now,
            data=data,
        )

    def close(self) -> None:
        self.transport.close()


def _mid_name(mid: int) -> str:
    try:
        return xbus.Mid(mid).name
    except ValueError:
        return f"MID 0x{mid:02X}"


@dataclass
class TrackerSet:
    """Several devices keyed by tracker id (device id as 8 hex digits)."""

    devices: dict[str, XsensDevice] = field(default_factory=dict)
    disconnected: dict[str, str] = field(default_factory=dict)

    def add(self, device: XsensDevice) -> str:
        if device.device_id is None:
            device.request_device_id()
        key = device.tracker_id
        if key in self.devices:
            raise ProtocolError(f"two devices report the same id {key}")
        self.devices[key] = device
        return key

    def read(self) -> list[ImuReading]:
        """Readings of every connected tracker; an unplugged one moves to ``disconnected`` (reason kept)."""
        out = []
        for key, device in list(self.devices.items()):
            try:
                out += device.read()
            except DeviceDisconnected as error:
                self.disconnected[key] = str(error)
                del self.devices[key]
                device.close()
        return out

    def close(self) -> None:
        for device in self.devices.values():
            device.close()
        self.devices.clear()
