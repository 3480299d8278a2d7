"""Byte transport to an Xsens device: a serial port (pyserial), including pseudo-terminals and USB-serial adapters."""

from __future__ import annotations

from typing import Protocol

from msk_core.errors import ConfigError, MskError

#: Baud rates an MTi accepts (Xbus baud codes in ../shared/protocols/xsens-xbus.md); 115200 8N1 is the default.
BAUD_RATES = (9600, 57600, 115200, 230400, 460800, 921600, 2000000, 4000000)


class DeviceDisconnected(MskError):
    """The device went away (unplugged, port closed); the driver reports it and stops reading."""


class Transport(Protocol):
    name: str

    def read(self, max_bytes: int = 4096) -> bytes: ...

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...


class SerialTransport:
    """A serial port; ``read`` returns what is available within ``timeout`` seconds (possibly nothing)."""

    def __init__(self, port: str, *, baudrate: int = 115200, timeout: float = 0.02) -> None:
        import serial  # pyserial; imported here so the codec is usable without it

        if baudrate not in BAUD_RATES:
            raise ConfigError(f"unsupported baud rate; use one of {BAUD_RATES}", field="baudrate", value=baudrate)
        self.name = port
        try:
            self._serial = serial.Serial(port, baudrate=baudrate, timeout=timeout, write_timeout=2.0)
        except (serial.SerialException, OSError) as error:
            raise DeviceDisconnected(f"cannot open serial port {port}: {error}") from error
        self._errors = (serial.SerialException, OSError)

    def read(self, max_bytes: int = 4096) -> bytes:
        try:
            first = self._serial.read(1)  # waits up to the timeout
            if not first:
                return b""
            waiting = min(self._serial.in_waiting, max_bytes - 1)
            return first + self._serial.read(waiting) if waiting > 0 else first
        except self._errors as error:
            raise DeviceDisconnected(f"{self.name}: {error}") from error

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

    def fileno(self) -> int:
        return self._serial.fileno()
