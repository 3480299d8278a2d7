"""Xsens Xbus framing and the MTData2 payload codec (every precision and coordinate frame).

Frame (big-endian): ``FA | BID | MID | LEN | [LENext_hi LENext_lo] | DATA | CS``; the sum of every byte after the
preamble, checksum included, is 0 mod 256. Facts: ../shared/protocols/xsens-xbus.md (MT0101P rev 2020.A).
"""

from __future__ import annotations

import enum
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from msk_core.errors import ProtocolError

PREAMBLE = 0xFA
BID_MASTER = 0xFF
MAX_STANDARD_LENGTH = 254
EXTENDED_LENGTH_MARK = 0xFF
MAX_EXTENDED_LENGTH = 2048


class Mid(enum.IntEnum):
    """Xbus message identifiers (an acknowledgement is MID + 1)."""

    REQ_DID = 0x00
    DEVICE_ID = 0x01
    REQ_CONFIGURATION = 0x0C
    CONFIGURATION = 0x0D
    RESTORE_FACTORY_DEF = 0x0E
    GO_TO_MEASUREMENT = 0x10
    GO_TO_MEASUREMENT_ACK = 0x11
    REQ_FW_REV = 0x12
    FIRMWARE_REV = 0x13
    BAUDRATE = 0x18
    BAUDRATE_ACK = 0x19
    REQ_PRODUCT_CODE = 0x1C
    PRODUCT_CODE = 0x1D
    RUN_SELF_TEST = 0x24
    SYNC_SETTINGS = 0x2C
    GO_TO_CONFIG = 0x30
    GO_TO_CONFIG_ACK = 0x31
    MT_DATA = 0x32
    REQ_DATA = 0x34
    MT_DATA2 = 0x36
    WAKE_UP = 0x3E
    WAKE_UP_ACK = 0x3F
    RESET = 0x40
    RESET_ACK = 0x41
    ERROR = 0x42
    WARNING = 0x43
    OPTION_FLAGS = 0x48
    UTC_TIME = 0x60
    FILTER_PROFILE = 0x64
    RESET_ORIENTATION = 0xA4
    SET_OUTPUT_CONFIGURATION = 0xC0
    OUTPUT_CONFIGURATION = 0xC1
    ERROR_MODE = 0xDA


_MTDATA2 = int(Mid.MT_DATA2)  # a plain int: compared for every frame

#: Xbus error codes carried by an Error (0x42) message.
ERROR_CODES = {
    0x03: "invalid period",
    0x04: "invalid message",
    0x1E: "timer overflow",
    0x20: "invalid baud rate",
    0x21: "invalid parameter",
    0x28: "device error",
}


class Precision(enum.IntEnum):
    """MTData2 DataID bits 1-0."""

    FLOAT32 = 0
    FP1220 = 1
    FP1632 = 2
    FLOAT64 = 3


class CoordinateFrame(enum.IntEnum):
    """MTData2 DataID bits 3-2 (orientation, velocity, acceleration groups)."""

    ENU = 0x0
    NED = 0x4
    NWU = 0x8


#: Bytes per component of each precision.
PRECISION_SIZE = {Precision.FLOAT32: 4, Precision.FP1220: 4, Precision.FP1632: 6, Precision.FLOAT64: 8}
#: Smallest representable step of each precision near the values an IMU reports (|v| < 2**11).
PRECISION_RESOLUTION = {
    Precision.FLOAT32: 2.0**-23 * 2.0**11,  # float32 ulp at |v| ~ 2048; relative 1.2e-7
    Precision.FP1220: 2.0**-20,
    Precision.FP1632: 2.0**-32,
    Precision.FLOAT64: 2.0**-52 * 2.0**11,
}

#: Real-valued MTData2 quantities: DataID with precision/frame bits cleared -> (name, component count).
FLOAT_QUANTITIES: dict[int, tuple[str, int]] = {
    0x0810: ("temperature", 1),
    0x2010: ("quaternion", 4),
    0x2020: ("rotation_matrix", 9),
    0x2030: ("euler", 3),
    0x4010: ("delta_v", 3),
    0x4020: ("acceleration", 3),
    0x4030: ("free_acceleration", 3),
    0x4040: ("acceleration_hr", 3),
    0x5020: ("altitude_ellipsoid", 1),
    0x5030: ("position_ecef", 3),
    0x5040: ("lat_lon", 2),
    0x8020: ("rate_of_turn", 3),
    0x8030: ("delta_q", 4),
    0x8040: ("rate_of_turn_hr", 3),
    0xC020: ("magnetic_field", 3),
    0xD010: ("velocity", 3),
}
#: Integer/structured quantities: exact DataID -> (name, struct format).
RAW_QUANTITIES: dict[int, tuple[str, str]] = {
    0x1010: ("utc_time", ">IHBBBBBB"),
    0x1020: ("packet_counter", ">H"),
    0x1060: ("sample_time_fine", ">I"),
    0x1070: ("sample_time_coarse", ">I"),
    0x3010: ("baro_pressure", ">I"),
    0xE010: ("status_byte", ">B"),
    0xE020: ("status_word", ">I"),
}
#: Groups whose DataID bits 3-2 select a coordinate frame (orientation and velocity).
FRAME_GROUPS = frozenset({0x2000, 0xD000})


def precision_of(data_id: int) -> Precision:
    return Precision(data_id & 0x3)


def frame_of(data_id: int) -> CoordinateFrame:
    if (data_id & 0xF800) not in FRAME_GROUPS:
        return CoordinateFrame.ENU
    bits = data_id & 0xC
    return CoordinateFrame(bits) if bits != 0xC else CoordinateFrame.ENU


def make_data_id(
    quantity: int, precision: Precision = Precision.FLOAT32, frame: CoordinateFrame = CoordinateFrame.ENU
) -> int:
    frame_bits = int(frame) if (quantity & 0xF800) in FRAME_GROUPS else 0
    return (quantity & 0xFFF0) | frame_bits | int(precision)


# --------------------------------------------------------------------------------------------------- framing


def checksum(body: bytes | bytearray | memoryview) -> int:
    """Checksum byte for ``BID..DATA`` (everything after the preamble, before CS)."""
    return (-sum(body)) & 0xFF


def encode_message(mid: int, data: bytes = b"", bid: int = BID_MASTER) -> bytes:
    """A complete Xbus frame."""
    n = len(data)
    if n > MAX_EXTENDED_LENGTH:
        raise ProtocolError(f"Xbus payload of {n} bytes exceeds the {MAX_EXTENDED_LENGTH}-byte maximum")
    if n <= MAX_STANDARD_LENGTH:
        header = bytes((bid, mid, n))
    else:
        header = bytes((bid, mid, EXTENDED_LENGTH_MARK, n >> 8, n & 0xFF))
    body = header + bytes(data)
    return bytes((PREAMBLE,)) + body + bytes((checksum(body),))


class XbusMessage(NamedTuple):
    """One frame (a NamedTuple: created per message at high rates, so it must be cheap)."""

    bid: int
    mid: int
    data: bytes

    def encode(self) -> bytes:
        return encode_message(self.mid, self.data, self.bid)


@dataclass
class ParserStats:
    """Counters of a :class:`XbusParser`; errors are counted, never raised."""

    messages: int = 0
    bytes_in: int = 0
    bytes_skipped: int = 0
    checksum_errors: int = 0
    length_errors: int = 0
    structure_errors: int = 0
    resyncs: int = 0  # stretches of discarded bytes between two valid frames

    @property
    def errors(self) -> int:
        return self.checksum_errors + self.length_errors + self.structure_errors


def mtdata2_structure_ok(data: bytes | bytearray | memoryview, start: int = 0, end: int | None = None) -> bool:
    """True when the MTData2 item sizes tile the payload exactly (guards against false frames after garbage)."""
    i = start
    end = len(data) if end is None else end
    while i + 3 <= end:
        i += 3 + data[i + 2]
    return i == end


#: Bus ids a frame may carry: master, or a device on a bus (stand-alone MT 0x01, wireless trackers 0x01..0x20).
VALID_BIDS = frozenset({BID_MASTER, *range(0x01, 0x21)})
#: Message ids in public Xsens sources beyond :class:`Mid` (MT0101P, XDA headers, ethzasl_xsens_driver mtdef.py):
#: InitMT 0x02, SetPeriod 0x04, ReqDataLength 0x0A, SetProcessingFlags 0x20, SetNoRotation 0x22,
#: AvailableScenarios 0x62, GravityMagnitude 0x66, LeverArmGPS 0x68, MagneticDeclination 0x6A, LatLonAlt 0x6E,
#: Heading 0x82, LocationID 0x84, ExtOutputMode 0x86, StringOutputTypes 0x8E, GPSStatus 0xA6, AdjustUTCTime 0xA8,
#: OutputMode 0xD0, OutputSettings 0xD2, OutputSkipFactor 0xD4, SyncIn/Out 0xD6/0xD8, TransmitDelay 0xDC,
#: ObjectAlignment 0xE0, AlignmentRotation 0xEC; and the wireless (Awinda/MTw) range 0xB0-0xCF.
OTHER_PUBLIC_MIDS = frozenset(
    {
        0x02,
        0x04,
        0x0A,
        0x20,
        0x22,
        0x62,
        0x66,
        0x68,
        0x6A,
        0x6E,
        0x82,
        0x84,
        0x86,
        0x8E,
        0xA6,
        0xA8,
        0xD0,
        0xD2,
        0xD4,
        0xD6,
        0xD8,
        0xDC,
        0xE0,
        0xEC,
    }
)
#: Message ids a frame may carry (requests, set messages, replies and acks). A device may send any of them (e.g.
#: a Warning, or the answer to another program's request on a shared port): they must parse, not count as errors.
VALID_MIDS = frozenset(
    {int(m) for m in Mid}
    | {int(m) + 1 for m in Mid}
    | OTHER_PUBLIC_MIDS
    | {m + 1 for m in OTHER_PUBLIC_MIDS}
    | set(range(0xB0, 0xD0))
)

#: Xbus baud-rate codes (SetBaudrate 0x18 payload) -> bits per second; 0x80 and 0x0A both mean 921600.
BAUD_CODES = {
    0x80: 921600,
    0x0A: 921600,
    0x00: 460800,
    0x01: 230400,
    0x02: 115200,
    0x03: 76800,
    0x04: 57600,
    0x05: 38400,
    0x06: 28800,
    0x07: 19200,
    0x08: 14400,
    0x09: 9600,
    0x0B: 4800,
    0x0C: 2000000,
    0x0D: 4000000,
}


def baud_code(rate: int) -> int:
    """The Xbus code of a baud rate (0x80 for 921600, the code the manual lists first)."""
    for code, value in BAUD_CODES.items():
        if value == rate:
            return code
    raise ProtocolError(f"no Xbus baud-rate code for {rate} bit/s (known: {sorted(set(BAUD_CODES.values()))})")


class XbusParser:
    """Incremental Xbus frame parser with resynchronisation.

    Feed it arbitrary byte chunks; it returns every valid frame. After garbage, a bad checksum or an impossible
    length it drops one byte and searches the next preamble, so intact frames after a corruption are recovered.
    With ``validate`` (default) a frame must also carry a known BID and MID, and an MTData2 payload must be
    structurally valid (item sizes tile the payload): a false frame assembled from garbage would otherwise pass the
    checksum once in 256 tries and swallow the intact frame after it.
    """

    def __init__(self, *, validate: bool = True) -> None:
        self._buffer = bytearray()
        self._validate = validate
        self._skipping = False
        self._aligned = False
        self.stats = ParserStats()

    def reset(self) -> None:
        self._buffer.clear()
        self._skipping = False
        self._aligned = False

    @property
    def pending(self) -> int:
        return len(self._buffer)

    def feed(self, chunk: bytes | bytearray | memoryview) -> list[XbusMessage]:
        buf = self._buffer
        buf += chunk
        stats = self.stats
        stats.bytes_in += len(chunk)
        out: list[XbusMessage] = []
        pos = 0
        n = len(buf)
        while True:
            start = buf.find(PREAMBLE, pos)
            if start < 0:
                self._skip(n - pos)
                pos = n
                break
            if start > pos:
                self._skip(start - pos)
            pos = start
            if n - pos < 4:
                break
            if self._validate and (buf[pos + 1] not in VALID_BIDS or buf[pos + 2] not in VALID_MIDS):
                # reject an impossible header at once rather than waiting for the bytes its length claims
                stats.structure_errors += 1
                self._skip(1)
                pos += 1
                continue
            length = buf[pos + 3]
            header = 4
            if length == EXTENDED_LENGTH_MARK:
                if n - pos < 6:
                    break
                length = (buf[pos + 4] << 8) | buf[pos + 5]
                header = 6
                if length > MAX_EXTENDED_LENGTH:
                    stats.length_errors += 1
                    self._skip(1)
                    pos += 1
                    continue
            end = pos + header + length + 1
            if end > n:
                break
            if sum(buf[pos + 1 : end]) & 0xFF:
                stats.checksum_errors += 1
                self._skip(1)
                pos += 1
                continue
            mid = buf[pos + 2]
            # A false frame (1/256 checksum odds) can start in garbage, or be a frame that lost a byte and took the
            # next preamble as its checksum. So unless the frame follows a valid one and is followed by a preamble,
            # an MTData2 payload must also be structurally valid.
            if (
                self._validate
                and mid == _MTDATA2
                and (not self._aligned or end >= n or buf[end] != PREAMBLE)
                and not mtdata2_structure_ok(buf, pos + header, end - 1)
            ):
                stats.structure_errors += 1
                self._skip(1)
                pos += 1
                continue
            out.append(XbusMessage(buf[pos + 1], mid, bytes(buf[pos + header : end - 1])))
            stats.messages += 1
            self._skipping = False
            self._aligned = True
            pos = end
        if pos:
            del buf[:pos]
        return out

    def release_stalled(self) -> list[XbusMessage]:
        """Give up on the incomplete frame the buffer starts with and parse the rest again; returns the frames found.
        Noise that looks like a header holds every frame behind it until the bytes its length claims arrive, which a
        device that went quiet (waiting for our next request) never sends: its first byte is skipped, counted as a
        length error."""
        if not self._buffer:
            return []
        self.stats.length_errors += 1
        self._skip(1)
        del self._buffer[:1]
        return self.feed(b"")

    def _skip(self, count: int) -> None:
        if count <= 0:
            return
        self._aligned = False
        if not self._skipping:
            self.stats.resyncs += 1
            self._skipping = True
        self.stats.bytes_skipped += count


# --------------------------------------------------------------------------------------------------- MTData2

_FP1220_SCALE = 1.0 / (1 << 20)
_FP1632_SCALE = 1.0 / (1 << 32)
_FP1632 = struct.Struct(">Ih")


@dataclass(frozen=True, slots=True)
class MtItem:
    """One decoded MTData2 item: values are floats (real quantities) or ints (counters, status, UTC fields)."""

    data_id: int
    name: str
    values: tuple

    @property
    def precision(self) -> Precision:
        return precision_of(self.data_id)

    @property
    def frame(self) -> CoordinateFrame:
        return frame_of(self.data_id)


@dataclass(slots=True)
class MtData2:
    """A decoded MTData2 message: values and DataIDs keyed by quantity name, unknown items kept raw."""

    values: dict[str, tuple] = field(default_factory=dict)
    ids: dict[str, int] = field(default_factory=dict)
    unknown: list[tuple[int, bytes]] = field(default_factory=list)

    @property
    def items(self) -> dict[str, MtItem]:
        return {name: MtItem(self.ids[name], name, v) for name, v in self.values.items()}

    def get(self, name: str) -> tuple | None:
        return self.values.get(name)

    def first(self, name: str):
        values = self.values.get(name)
        return None if values is None else values[0]

    def frame(self) -> CoordinateFrame:
        for name in ("quaternion", "rotation_matrix", "euler", "velocity"):
            data_id = self.ids.get(name)
            if data_id is not None:
                return frame_of(data_id)
        return CoordinateFrame.ENU


_Decoder = tuple[str, object]


def _make_decoder(data_id: int, size: int) -> _Decoder | None:
    """A (name, fn(buffer, offset) -> tuple) for this DataID and size, or None for an unknown DataID."""
    raw_spec = RAW_QUANTITIES.get(data_id)
    if raw_spec is not None:
        name, fmt = raw_spec
        s = struct.Struct(fmt)
        if size != s.size:
            raise ProtocolError(f"MTData2 item 0x{data_id:04X} ({name}) has {size} bytes, expected {s.size}")
        return name, s.unpack_from
    spec = FLOAT_QUANTITIES.get(data_id & 0xFFF0)
    if spec is None:
        return None
    name, count = spec
    precision = Precision(data_id & 0x3)
    if size != count * PRECISION_SIZE[precision]:
        raise ProtocolError(
            f"MTData2 item 0x{data_id:04X} ({name}, {precision.name}) has {size} bytes, "
            f"expected {count * PRECISION_SIZE[precision]}"
        )
    if precision is Precision.FLOAT32:
        return name, struct.Struct(f">{count}f").unpack_from
    if precision is Precision.FLOAT64:
        return name, struct.Struct(f">{count}d").unpack_from
    if precision is Precision.FP1220:
        unpack_i = struct.Struct(f">{count}i").unpack_from
        return name, lambda buf, off: tuple([v * _FP1220_SCALE for v in unpack_i(buf, off)])
    unpack_fp = struct.Struct(">" + "Ih" * count).unpack_from

    def fp1632(buf, off):
        parts = unpack_fp(buf, off)
        return tuple([parts[k + 1] + parts[k] * _FP1632_SCALE for k in range(0, 2 * count, 2)])

    return name, fp1632


# struct.Struct.unpack_from: the values it reads are ints, floats or bytes, as the format says.
_Unpack = Callable[[bytes | bytearray | memoryview], tuple[Any, ...]]


class _Layout(NamedTuple):
    """A compiled MTData2 item sequence. A device repeats the same DataIDs and sizes in message after message, so
    recognising the sequence (one struct call over the item headers) replaces walking the items one by one."""

    check: _Unpack  # unpack_from reading every item header
    headers: tuple[int, ...]  # what ``check`` returns for this sequence
    unpack_from: _Unpack  # unpack_from reading every item's data
    names: tuple[str, ...]
    slices: tuple[slice, ...]  # slice of the flat tuple per name
    ids: dict[str, int]
    conversions: tuple[int, ...]  # per field: 0 none, 1 fixed 12.20, 2 fixed 16.32, 3 unknown (raw bytes)
    plain: bool
    fx20: tuple[int, ...]  # flat indices of every fixed 12.20 component
    fx32: tuple[int, ...]  # flat indices of the fraction of every fixed 16.32 component (its integer part follows)
    targets: tuple[tuple[str, int, slice], ...]  # (name, 0 = flat / 1 = converted list, slice) for every known item


_LAYOUTS: dict[int, list[_Layout]] = {}
_MAX_LAYOUTS = 1024  # bounded: garbage payloads must not grow the cache without limit


def _walk(payload) -> list[tuple[int, int, int]]:
    """(offset, data_id, size) of each item; ProtocolError when the sizes do not tile the payload."""
    items = []
    i, n = 0, len(payload)
    while i < n:
        if i + 3 > n:
            raise ProtocolError(f"MTData2 payload truncated in an item header at byte {i} of {n}")
        data_id = (payload[i] << 8) | payload[i + 1]
        size = payload[i + 2]
        if i + 3 + size > n:
            raise ProtocolError(f"MTData2 item 0x{data_id:04X} claims {size} bytes, only {n - i - 3} left")
        items.append((i, data_id, size))
        i += 3 + size
    return items


def _compile_layout(items: list[tuple[int, int, int]]) -> _Layout:
    header_fmt, data_fmt = [">"], [">"]
    headers: list[int] = []
    names, slices, conversions = [], [], []
    ids: dict[str, int] = {}
    position = 0
    for _offset, data_id, size in items:
        header_fmt.append(f"HB{size}x" if size else "HB")  # the header, then skip the item's data
        headers += [data_id, size]
        data_fmt.append("3x")
        decoder = _make_decoder(data_id, size)  # validates the size of known quantities
        if decoder is None:
            data_fmt.append(f"{size}s")
            fields, conversion, name = 1, 3, f"0x{data_id:04X}"
        else:
            name = decoder[0]
            raw_spec = RAW_QUANTITIES.get(data_id)
            if raw_spec is not None:
                data_fmt.append(raw_spec[1][1:])
                fields, conversion = len(struct.unpack(raw_spec[1], bytes(size))), 0
            else:
                precision = Precision(data_id & 0x3)
                count = FLOAT_QUANTITIES[data_id & 0xFFF0][1]
                code = {Precision.FLOAT32: "f", Precision.FLOAT64: "d", Precision.FP1220: "i"}.get(precision)
                data_fmt.append(f"{count}{code}" if code else "Ih" * count)
                fields = count if code else 2 * count
                conversion = {Precision.FP1220: 1, Precision.FP1632: 2}.get(precision, 0)
            ids[name] = data_id
        names.append(name)
        slices.append(slice(position, position + fields))
        conversions.append(conversion)
        position += fields
    header_struct = struct.Struct("".join(header_fmt))
    # Fixed-point components of all items are converted in one pass: 12.20 ones first, then 16.32 ones.
    fx20 = [k for part, c in zip(slices, conversions) if c == 1 for k in range(part.start, part.stop)]
    fx32 = [k for part, c in zip(slices, conversions) if c == 2 for k in range(part.start, part.stop, 2)]
    targets = []
    next20, next32 = 0, len(fx20)
    for name, part, conversion in zip(names, slices, conversions):
        if conversion == 0:
            targets.append((name, 0, part))
        elif conversion == 1:
            count = part.stop - part.start
            targets.append((name, 1, slice(next20, next20 + count)))
            next20 += count
        elif conversion == 2:
            count = (part.stop - part.start) // 2
            targets.append((name, 1, slice(next32, next32 + count)))
            next32 += count
    return _Layout(
        header_struct.unpack_from,
        tuple(headers),
        struct.Struct("".join(data_fmt)).unpack_from,
        tuple(names),
        tuple(slices),
        ids,
        tuple(conversions),
        not any(conversions),
        tuple(fx20),
        tuple(fx32),
        tuple(targets),
    )


def decode_mtdata2(payload: bytes | bytearray | memoryview) -> MtData2:
    """Decode an MTData2 payload; unknown DataIDs are kept raw in ``unknown`` (skipped by size)."""
    n = len(payload)
    candidates = _LAYOUTS.get(n)
    layout = None
    if candidates:
        for candidate in candidates:
            if candidate.check(payload) == candidate.headers:
                layout = candidate
                break
    if layout is None:
        layout = _compile_layout(_walk(payload))
        if sum(len(v) for v in _LAYOUTS.values()) < _MAX_LAYOUTS:
            _LAYOUTS.setdefault(n, []).append(layout)
    flat = layout.unpack_from(payload)
    if layout.plain:
        return MtData2(dict(zip(layout.names, map(flat.__getitem__, layout.slices))), dict(layout.ids), [])
    converted = [flat[k] * _FP1220_SCALE for k in layout.fx20] + [
        flat[k + 1] + flat[k] * _FP1632_SCALE for k in layout.fx32
    ]
    sources = (flat, converted)
    values = {name: tuple(sources[source][part]) for name, source, part in layout.targets}
    unknown = [
        (layout.headers[2 * index], flat[part][0])
        for index, (part, conversion) in enumerate(zip(layout.slices, layout.conversions))
        if conversion == 3
    ]
    return MtData2(values, dict(layout.ids), unknown)


def item_layout(payload: bytes | bytearray | memoryview) -> list[tuple[int, bytes]]:
    """The ``(data_id, raw bytes)`` items of an MTData2 payload in wire order, undecoded."""
    out = []
    i, n = 0, len(payload)
    while i + 3 <= n:
        data_id = (payload[i] << 8) | payload[i + 1]
        j = i + 3 + payload[i + 2]
        if j > n:
            raise ProtocolError(f"MTData2 item 0x{data_id:04X} runs past the payload end")
        out.append((data_id, bytes(payload[i + 3 : j])))
        i = j
    if i != n:
        raise ProtocolError(f"MTData2 payload has {n - i} trailing bytes")
    return out


def encode_real(values, precision: Precision) -> bytes:
    """Encode components at ``precision`` (fixed-point values are rounded to the nearest step)."""
    values = [float(v) for v in values]
    if precision is Precision.FLOAT32:
        return struct.pack(f">{len(values)}f", *values)
    if precision is Precision.FLOAT64:
        return struct.pack(f">{len(values)}d", *values)
    if precision is Precision.FP1220:
        ints = [round(v * (1 << 20)) for v in values]
        if any(not -(1 << 31) <= i < (1 << 31) for i in ints):
            raise ProtocolError(f"value out of fixed 12.20 range: {values}")
        return struct.pack(f">{len(ints)}i", *ints)
    out = bytearray()
    for v in values:
        i = round(v * (1 << 32))
        if not -(1 << 47) <= i < (1 << 47):
            raise ProtocolError(f"value out of fixed 16.32 range: {v}")
        out += _FP1632.pack(i & 0xFFFFFFFF, i >> 32)
    return bytes(out)


def encode_item(data_id: int, values) -> bytes:
    """One MTData2 item ``[DataID][size][data]`` from values (real quantities in the DataID's precision)."""
    raw_spec = RAW_QUANTITIES.get(data_id)
    if raw_spec is not None:
        raw = struct.pack(raw_spec[1], *values)
    elif (data_id & 0xFFF0) in FLOAT_QUANTITIES:
        raw = encode_real(values, precision_of(data_id))
    else:
        raw = bytes(values)
    if len(raw) > 255:
        raise ProtocolError(f"MTData2 item 0x{data_id:04X} too large ({len(raw)} bytes)")
    return struct.pack(">HB", data_id, len(raw)) + raw


def encode_mtdata2(items: Sequence[tuple[int, object]]) -> bytes:
    """An MTData2 payload from ``(data_id, values)`` pairs (values as bytes for unknown IDs)."""
    return b"".join(encode_item(data_id, values) for data_id, values in items)


# --------------------------------------------------------------------------------------------------- output configuration


@dataclass(frozen=True)
class OutputSetting:
    data_id: int
    frequency: int  # Hz; 0 or 0xFFFF = every message (counters, time)


def decode_output_configuration(payload: bytes) -> list[OutputSetting]:
    if len(payload) % 4:
        raise ProtocolError(f"output configuration of {len(payload)} bytes is not a list of 4-byte entries")
    return [OutputSetting(*struct.unpack_from(">HH", payload, k)) for k in range(0, len(payload), 4)]


def encode_output_configuration(settings: list[OutputSetting]) -> bytes:
    if len(settings) > 32:
        raise ProtocolError(f"at most 32 output settings, got {len(settings)}")
    return b"".join(struct.pack(">HH", s.data_id, s.frequency) for s in settings)


def item_size(data_id: int) -> int | None:
    """Data bytes of one MTData2 item of this DataID (None when the quantity is not in the tables)."""
    raw_spec = RAW_QUANTITIES.get(data_id)
    if raw_spec is not None:
        return struct.calcsize(raw_spec[1])
    spec = FLOAT_QUANTITIES.get(data_id & 0xFFF0)
    return None if spec is None else spec[1] * PRECISION_SIZE[Precision(data_id & 0x3)]


#: Output frequencies meaning "with every message" (equivalent in a SetOutputConfiguration echo).
EVERY_MESSAGE = (0, 0xFFFF)


def message_rate_hz(settings: list[OutputSetting]) -> float | None:
    """The MTData2 message rate of an output configuration: its highest output frequency (:data:`EVERY_MESSAGE`
    carries no rate); None when no output states one."""
    rates = [s.frequency for s in settings if s.frequency not in EVERY_MESSAGE]
    return float(max(rates)) if rates else None


def output_bits_per_second(settings: list[OutputSetting]) -> float:
    """Serial line load of an output configuration (8N1: 10 bits per byte): MTData2 messages at the highest output
    rate, each item at its own rate (0/0xFFFF: in every message). Unknown DataIDs count their 3-byte header only."""
    message_rate = message_rate_hz(settings) or 100.0
    payload = sum(
        (3 + (item_size(s.data_id) or 0)) * (message_rate if s.frequency in EVERY_MESSAGE else s.frequency)
        for s in settings
    )
    overhead = message_rate * (6 + 1)  # FA BID MID LEN [LENext] ... CS (extended header counted: worst case)
    return 10.0 * (payload + overhead)


def iter_capture(data: bytes) -> list[XbusMessage]:
    """Every frame of a raw serial capture."""
    return XbusParser().feed(data)
