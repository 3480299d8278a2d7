"""Find Xsens devices on USB (pyusb) and the serial ports they expose (pyserial's port list).

Xsens vendor 0x2639 (native-USB MTi, Awinda station/dongle, MTw, converters); older USB converters enumerate as FTDI
0x0403 with product ids 0xD388-0xD38F. Without libusb (no pyusb backend) the serial-port list alone is used.
"""

from __future__ import annotations

from dataclasses import dataclass

XSENS_VENDOR = 0x2639
FTDI_VENDOR = 0x0403
FTDI_XSENS_PRODUCTS = range(0xD388, 0xD390)

XSENS_PRODUCTS = {
    0x0001: "MTi-10 (native USB)",
    0x0002: "MTi-20 (native USB)",
    0x0003: "MTi-30 (native USB)",
    0x0011: "MTi-100 (native USB)",
    0x0012: "MTi-200 (native USB)",
    0x0013: "MTi-300 (native USB)",
    0x0017: "MTi-G-700 (native USB)",
    0x0101: "Awinda Station",
    0x0102: "Awinda Dongle",
    0x0200: "MTw",
    0x0300: "MT development board",
    0x0301: "MTi USB converter",
    0xD00D: "USB-serial converter",
}


@dataclass(frozen=True)
class UsbDevice:
    vendor_id: int
    product_id: int
    name: str
    serial_number: str = ""
    bus: int | None = None
    address: int | None = None
    port: str = ""  # serial device path (e.g. /dev/ttyUSB0), "" when none was matched

    @property
    def usb_id(self) -> str:
        return f"{self.vendor_id:04x}:{self.product_id:04x}"


@dataclass(frozen=True)
class PortInfo:
    """The parts of a pyserial ListPortInfo used for matching."""

    device: str
    vid: int | None
    pid: int | None
    serial_number: str = ""


def classify(vendor_id: int | None, product_id: int | None) -> str | None:
    """The Xsens product name for a USB id, or None when it is not an Xsens device."""
    if vendor_id == XSENS_VENDOR:
        return XSENS_PRODUCTS.get(product_id or 0, f"Xsens device 0x{product_id or 0:04X}")
    if vendor_id == FTDI_VENDOR and product_id in FTDI_XSENS_PRODUCTS:
        return "Awinda Station (FTDI)" if product_id == 0xD38D else "Xsens USB converter (FTDI)"
    return None


def match_ports(devices: list[UsbDevice], ports: list[PortInfo]) -> list[UsbDevice]:
    """Attach serial ports to USB devices by (vid, pid, serial number); ports of Xsens ids with no USB record
    (no libusb) become devices of their own."""
    remaining = [p for p in ports if classify(p.vid, p.pid) is not None]
    out = []
    for device in devices:
        port = next(
            (
                p
                for p in remaining
                if p.vid == device.vendor_id
                and p.pid == device.product_id
                and (not device.serial_number or not p.serial_number or p.serial_number == device.serial_number)
            ),
            None,
        )
        if port is not None:
            remaining.remove(port)
        out.append(
            UsbDevice(
                device.vendor_id,
                device.product_id,
                device.name,
                device.serial_number,
                device.bus,
                device.address,
                port.device if port else "",
            )
        )
    for port in remaining:
        out.append(
            UsbDevice(
                port.vid or 0, port.pid or 0, classify(port.vid, port.pid) or "", port.serial_number, port=port.device
            )
        )
    return out


def usb_devices() -> list[UsbDevice]:
    """Xsens devices pyusb can see (empty when no libusb backend is installed)."""
    try:
        import usb.core
    except ImportError:
        return []
    try:
        found = list(usb.core.find(find_all=True, custom_match=lambda d: classify(d.idVendor, d.idProduct) is not None))
    except usb.core.NoBackendError:
        return []
    out = []
    for dev in found:
        try:
            serial = usb.util.get_string(dev, dev.iSerialNumber) if dev.iSerialNumber else ""
        except (usb.core.USBError, ValueError, NotImplementedError):
            serial = ""  # reading strings needs permissions on the device node
        out.append(
            UsbDevice(
                dev.idVendor,
                dev.idProduct,
                classify(dev.idVendor, dev.idProduct) or "",
                serial or "",
                dev.bus,
                dev.address,
            )
        )
    return out


def serial_ports() -> list[PortInfo]:
    from serial.tools import list_ports

    return [PortInfo(p.device, p.vid, p.pid, p.serial_number or "") for p in list_ports.comports()]


def list_devices() -> list[UsbDevice]:
    """Every Xsens device on USB with its serial port when it has one."""
    return match_ports(usb_devices(), serial_ports())


def find_port() -> str:
    """The serial port of the first Xsens device, for ``--xsens usb``."""
    from msk_core.errors import ConfigError

    for device in list_devices():
        if device.port:
            return device.port
    raise ConfigError(
        "no Xsens device with a serial port found on USB (vendor 0x2639 or FTDI 0x0403:D388-D38F)",
        field="--xsens",
        value="usb",
    )
