"""Byte transport to an Xsens device: a serial port (pyserial), including pseudo-terminals and USB-serial adapters."""

from __future__ import annotations

import os
import select
from typing import Protocol, runtime_checkable

from msk_core.errors import ConfigError, MskError

#: Baud rates an MTi accepts (the Xbus baud codes, xbus.BAUD_CODES); 115200 8N1 is the factory default.
BAUD_RATES = (4800, 9600, 14400, 19200, 28800, 38400, 57600, 76800, 115200, 230400, 460800, 921600, 2000000, 4000000)


class DeviceDisconnected(MskError):
    """The device went away (unplugged, port closed); the driver reports it and stops reading."""


class Transport(Protocol):
    name: str

    def read(self, max_bytes: int = 4096) -> bytes: ...

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...


@runtime_checkable
class ReopenableTransport(Transport, Protocol):
    """A transport that can open its port again (same path, same settings) after the device came back: what
    :meth:`drivers.xsens.device.XsensDevice.reconnect` needs."""

    def reopen(self) -> Transport: ...


class SerialTransport:
    """A serial port; ``read`` returns what is available within ``timeout`` seconds (possibly nothing)."""

    def __init__(self, port: str, *, baudrate: int = 115200, timeout: float = 0.02) -> None:
        import serial  # pyserial; imported here so the codec is usable without it

        if baudrate not in BAUD_RATES:
            raise ConfigError(f"unsupported baud rate; use one of {BAUD_RATES}", field="baudrate", value=baudrate)
        self.name = port
        self.baudrate = baudrate
        self.timeout = timeout
        try:
            self._serial = serial.Serial(port, baudrate=baudrate, timeout=timeout, write_timeout=2.0)
        except (serial.SerialException, OSError) as error:
            raise DeviceDisconnected(f"cannot open serial port {port}: {error}") from error
        self._errors = (serial.SerialException, OSError)

    def read(self, max_bytes: int = 4096) -> bytes:
        """What has arrived, waiting up to ``timeout`` s for the first byte: one ``select`` and one ``read`` of the
        port (pyserial's ``read(1)``, ``in_waiting`` and a second ``read`` cost three system calls and their Python
        more for every Xbus message). As pyserial's read, a port that is readable but gives no bytes is gone."""
        try:
            fd = self._serial.fileno()
            if not select.select([fd], [], [], self.timeout)[0]:
                return b""
            data = os.read(fd, max_bytes)
        except BlockingIOError:  # readable a moment ago, drained meanwhile (pyserial opens the port non-blocking)
            return b""
        except self._errors as error:
            raise DeviceDisconnected(f"{self.name}: {error}") from error
        if not data:
            raise DeviceDisconnected(f"{self.name}: readable but no data (device disconnected?)")
        return data

    def write(self, data: bytes) -> None:
        try:
            self._serial.write(data)
            self._serial.flush()
        except self._errors as error:
            raise DeviceDisconnected(f"{self.name}: {error}") from error

    def close(self) -> None:
        try:
            self._serial.close()
        except self._errors:
            pass

    def set_baudrate(self, baudrate: int) -> None:
        """Change the line rate of the open port (after the device was told to switch)."""
        if baudrate not in BAUD_RATES:
            raise ConfigError(f"unsupported baud rate; use one of {BAUD_RATES}", field="baudrate", value=baudrate)
        try:
            self._serial.baudrate = baudrate
        except self._errors as error:
            raise DeviceDisconnected(f"{self.name}: {error}") from error
        self.baudrate = baudrate

    def reopen(self) -> SerialTransport:
        """The same port opened again: after an unplug, a stable path (/dev/serial/by-id/...) names the replugged
        device. Raises DeviceDisconnected while it is still absent."""
        return SerialTransport(self.name, baudrate=self.baudrate, timeout=self.timeout)

    def fileno(self) -> int:
        return self._serial.fileno()
