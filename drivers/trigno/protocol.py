"""Delsys Trigno SDK TCP protocol: command/reply framing, reply parsing and the float32 sample stream decoder.

Facts: ../shared/protocols/trigno-tcp.md (Delsys MAN-025, cross-checked between public clients). Where clients
disagree (banner spacing, UPSAMPLING reply, STARTINDEX base, EMG port) the helpers here accept every variant.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass

import numpy as np

from msk_core.errors import ProtocolError

TERMINATOR = b"\r\n\r\n"
COMMAND_PORT = 50040
FRAME_INTERVAL_S = 0.0135
N_SENSORS = 16
AUX_SLOTS_PER_SENSOR = 9
LEGACY_ACC_SLOTS_PER_SENSOR = 3  # legacy ACC port 50042: x, y, z per sensor
BYTES_PER_FLOAT = 4
MAX_REPLY_BYTES = 64 * 1024  # a reply longer than this means we are not talking to a Trigno server

ERROR_REPLIES = frozenset({"INVALID COMMAND", "CANNOT COMPLETE"})
UNSOLICITED_STOPPED = "STOPPED"
BANNER_PREFIX = "Delsys Trigno System Digital Protocol Version"


class EmgPort(enum.IntEnum):
    """EMG data port: 50043 carries every sensor type (Avanti); 50041 is the legacy port."""

    AVANTI = 50043
    LEGACY = 50041


class DataPort(enum.IntEnum):
    LEGACY_EMG = 50041
    LEGACY_ACC = 50042
    EMG = 50043
    AUX = 50044


#: Floats per sample on each data port.
FLOATS_PER_SAMPLE = {
    DataPort.LEGACY_EMG: 16,
    DataPort.LEGACY_ACC: 16 * LEGACY_ACC_SLOTS_PER_SENSOR,
    DataPort.EMG: 16,
    DataPort.AUX: 16 * AUX_SLOTS_PER_SENSOR,
}


class AuxLayout(enum.Enum):
    """What the auxiliary data port carries: 9 slots per sensor (Avanti AUX, 50044) or ACC x,y,z (legacy, 50042)."""

    AVANTI = "avanti"
    LEGACY_ACC = "legacy_acc"

    @property
    def slots_per_sensor(self) -> int:
        return AUX_SLOTS_PER_SENSOR if self is AuxLayout.AVANTI else LEGACY_ACC_SLOTS_PER_SENSOR

    @property
    def floats_per_sample(self) -> int:
        return N_SENSORS * self.slots_per_sensor

    @classmethod
    def for_port(cls, port: int) -> AuxLayout:
        """The layout of a default port number (ports are configurable: pass the layout explicitly otherwise)."""
        return cls.LEGACY_ACC if int(port) == DataPort.LEGACY_ACC else cls.AVANTI


class Endianness(enum.Enum):
    LITTLE = "LITTLE"
    BIG = "BIG"

    @property
    def dtype(self) -> np.dtype:
        return np.dtype("<f4") if self is Endianness.LITTLE else np.dtype(">f4")


class StopMode(enum.Enum):
    """How a client ends acquisition: ``STOP`` then ``QUIT`` (most clients) or ``QUIT`` alone (one client)."""

    STOP_THEN_QUIT = "stop+quit"
    QUIT_ONLY = "quit"


class NoReply(ProtocolError):
    """A command the server did not answer within the reply timeout (its reply, if it comes, is discarded)."""


class CommandFailed(ProtocolError):
    """The server answered ``INVALID COMMAND`` or ``CANNOT COMPLETE``."""

    def __init__(self, command: str, reply: str) -> None:
        self.command = command
        self.reply = reply
        super().__init__(f"Trigno command {command!r} failed: {reply}")


def encode_command(command: str) -> bytes:
    """One command, terminated as the SDK requires."""
    text = command.strip()
    if not text or "\r" in text or "\n" in text:
        raise ProtocolError(f"invalid Trigno command {command!r}")
    return text.encode("ascii") + TERMINATOR


def encode_commands(commands: list[str]) -> bytes:
    """Several commands in one packet: each ends with CRLF, the packet with a blank line."""
    if not commands:
        raise ProtocolError("no commands to send")
    return b"\r\n".join(c.strip().encode("ascii") for c in commands) + TERMINATOR


def split_packet(packet: str) -> list[str]:
    """Commands of one received packet (server side)."""
    return [part.strip() for part in packet.split("\r\n") if part.strip()]


class ReplyReader:
    """Splits the command-port byte stream into replies (explicit state; feed arbitrary fragments)."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, chunk: bytes) -> list[str]:
        self._buffer += chunk
        replies = []
        while True:
            index = self._buffer.find(TERMINATOR)
            if index < 0:
                break
            raw = bytes(self._buffer[:index])
            del self._buffer[: index + len(TERMINATOR)]
            # Variant: some servers put a space before the terminator, and a reply may carry extra blank lines.
            text = raw.decode("ascii", errors="replace").strip()
            if text:
                replies.append(text)
        if len(self._buffer) > MAX_REPLY_BYTES:
            size = len(self._buffer)
            self._buffer.clear()
            raise ProtocolError(f"no reply terminator in {size} bytes from the Trigno command port")
        return replies

    def pending(self) -> bytes:
        """What is buffered and not yet a reply (for errors: what came instead)."""
        return bytes(self._buffer)

    def take_line(self) -> str | None:
        """The first complete CRLF- (or LF-) terminated line still buffered, for a banner that lacks the blank
        line; None when there is none."""
        index = self._buffer.find(b"\n")
        if index < 0:
            return None
        raw = bytes(self._buffer[:index])
        del self._buffer[: index + 1]
        while self._buffer[:2] == b"\r\n" or self._buffer[:1] == b"\n":  # the blank line, when it is late
            del self._buffer[: 2 if self._buffer[:1] == b"\r" else 1]
        return raw.decode("ascii", errors="replace").strip() or None


_BANNER_VERSION = re.compile(r"\bversion\b\s*[:=]?\s*(\S+)", re.IGNORECASE)


def parse_banner(text: str) -> str:
    """The protocol version from the connection banner.

    The documented banner is ``Delsys Trigno System Digital Protocol Version 3.6.0``, but the wording differs
    between TCU and Trigno Discover releases, so any first line naming Delsys or Trigno is accepted: the version is
    the word after ``Version`` (the whole line when there is none). Anything else is not a Trigno server.
    """
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    first = lines[0] if lines else ""
    upper = first.upper()
    if "DELSYS" not in upper and "TRIGNO" not in upper:
        raise ProtocolError(f"unexpected Trigno banner {text.strip()!r} (expected {BANNER_PREFIX!r} ...)")
    match = _BANNER_VERSION.search(first)
    return match.group(1) if match else first


def is_error(reply: str) -> bool:
    """``INVALID COMMAND`` / ``CANNOT COMPLETE``, also with words after them (a detail some servers may add)."""
    text = " ".join(reply.strip().upper().split())
    return any(text == e or text.startswith(e + " ") or text.startswith(e + ":") for e in ERROR_REPLIES)


def parse_yes_no(reply: str, *, command: str = "") -> bool:
    """``YES``/``NO`` and the variants ``UPSAMPLING ON|OFF``, ``ON``/``OFF``, ``TRUE``/``FALSE``."""
    # the last yes/no word decides: "UPSAMPLING ON", "YES", and wordier variants such as "YES MASTER"
    for word in reversed(reply.strip().upper().replace(".", " ").split()):
        if word in ("YES", "ON", "TRUE"):
            return True
        if word in ("NO", "OFF", "FALSE"):
            return False
    raise ProtocolError(f"reply {reply!r} to {command!r} is not YES/NO or ON/OFF")


def parse_int(reply: str, *, command: str = "") -> int:
    match = re.search(r"-?\d+", reply)
    if match is None:
        raise ProtocolError(f"reply {reply!r} to {command!r} is not an integer")
    return int(match.group())


def parse_float(reply: str, *, command: str = "") -> float:
    match = re.search(r"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?", reply)
    if match is None:
        raise ProtocolError(f"reply {reply!r} to {command!r} is not a number")
    return float(match.group())


def parse_endianness(reply: str) -> Endianness:
    text = reply.strip().upper()
    if "BIG" in text:
        return Endianness.BIG
    if "LITTLE" in text:
        return Endianness.LITTLE
    raise ProtocolError(f"reply {reply!r} to 'ENDIANNESS?' is neither LITTLE nor BIG")


def is_new_master(reply: str) -> bool:
    return "NEW MASTER" in reply.upper()


def normalise_start_indices(
    reported: dict[int, int], slots: int = N_SENSORS, channels: dict[int, int] | None = None
) -> dict[int, int]:
    """0-based first slot of each sensor (1..16) from its ``STARTINDEX?`` reply, whatever base the server uses.

    One client reads the reply as 1-based, another as 0-based, so the base is decided over all sensors at once, from
    how the port is laid out: its slots are in sensor order, sensor n owning slot n-1 unless a multi-channel sensor
    before it (``channels``: EMGCHANNELCOUNT?, 1 when unknown) pushed it further. A reading is ruled out first by
    sensors whose channels fall outside the port (a reply of 0 read 1-based, of ``slots`` read 0-based), then by
    sensors that would start before their own slot (0-based replies 1 and 3 of a 2-channel sensor 2 and sensor 3,
    read 1-based, would put sensor 2 in sensor 1's slot); still tied, the base under which more sensors sit in their
    own slot wins, then 1-based (the SDK manual's examples). Only an index outside the port's slots is dropped (-1):
    slot information is informative, a strange value must not stop acquisition.
    """
    width = {n: max(1, (channels or {}).get(n, 1)) for n in reported}

    def misfits(base: int) -> tuple[int, int, int]:
        outside = sum(1 for n, v in reported.items() if not (0 <= v - base and v - base + width[n] <= slots))
        early = sum(1 for n, v in reported.items() if 0 <= v - base < n - 1)
        own = sum(1 for n, v in reported.items() if v - base == n - 1)
        return outside, early, -own

    base = 0 if misfits(0) < misfits(1) else 1
    return {n: (v - base if 0 <= v - base < slots else -1) for n, v in reported.items()}


def samples_per_frame(rate_hz: float) -> int:
    return int(round(rate_hz * FRAME_INTERVAL_S))


def rate_for(samples_in_frame: int) -> float:
    return samples_in_frame / FRAME_INTERVAL_S


@dataclass
class DecoderStats:
    bytes_in: int = 0
    samples_out: int = 0


class SampleDecoder:
    """Turns a raw float32 data-port stream into rows of ``channels`` floats, whatever the TCP fragmentation.

    Partial samples stay buffered until their remaining bytes arrive; :meth:`discard_partial` drops them (after a
    broken connection they can never complete) and returns how many bytes were lost.
    """

    def __init__(self, channels: int, endianness: Endianness = Endianness.LITTLE) -> None:
        if channels <= 0:
            raise ProtocolError(f"channel count must be positive, got {channels}")
        self.channels = channels
        self.endianness = endianness
        self.sample_bytes = channels * BYTES_PER_FLOAT
        self._partial = bytearray()
        self.stats = DecoderStats()

    @property
    def pending_bytes(self) -> int:
        return len(self._partial)

    def feed(self, chunk: bytes | bytearray | memoryview) -> np.ndarray:
        """Complete samples in ``chunk`` (plus buffered bytes) as a float32 array of shape (n, channels)."""
        self.stats.bytes_in += len(chunk)
        data: bytes | bytearray | memoryview
        if self._partial:
            self._partial += chunk
            data = self._partial
        else:
            data = chunk
        n = len(data) // self.sample_bytes
        used = n * self.sample_bytes
        rows = np.frombuffer(data, dtype=self.endianness.dtype, count=n * self.channels).reshape(n, self.channels)
        rows = rows.astype(np.float32)  # copy (native order) so the buffer can be reused
        rest = bytes(data[used:])
        self._partial = bytearray(rest)
        self.stats.samples_out += n
        return rows

    def discard_partial(self) -> int:
        lost = len(self._partial)
        self._partial = bytearray()
        return lost


def encode_samples(rows: np.ndarray, endianness: Endianness = Endianness.LITTLE) -> bytes:
    """Rows of floats as the server sends them."""
    return np.ascontiguousarray(rows, dtype=endianness.dtype).tobytes()
