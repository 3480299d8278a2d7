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
    DataPort.LEGACY_ACC: 48,
    DataPort.EMG: 16,
    DataPort.AUX: 16 * AUX_SLOTS_PER_SENSOR,
}


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


def parse_banner(text: str) -> str:
    """The protocol version from the connection banner (with or without trailing space)."""
    text = text.strip()
    if not text.startswith(BANNER_PREFIX):
        raise ProtocolError(f"unexpected Trigno banner {text!r} (expected {BANNER_PREFIX!r} ...)")
    return text[len(BANNER_PREFIX) :].strip()


def is_error(reply: str) -> bool:
    return reply.strip().upper() in ERROR_REPLIES


def parse_yes_no(reply: str, *, command: str = "") -> bool:
    """``YES``/``NO`` and the variants ``UPSAMPLING ON|OFF``, ``ON``/``OFF``, ``TRUE``/``FALSE``."""
    text = reply.strip().upper()
    words = text.split()
    last = words[-1] if words else ""
    if last in ("YES", "ON", "TRUE"):
        return True
    if last in ("NO", "OFF", "FALSE"):
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


def normalise_start_index(sensor: int, reported: int, slots_per_sensor: int = 1) -> int:
    """0-based first slot of ``sensor`` (1..16) whatever base the server uses for ``STARTINDEX?``.

    One client reads the reply as 1-based, another as 0-based; a server following either is accepted.
    """
    zero_based = (sensor - 1) * slots_per_sensor
    if reported == zero_based:
        return zero_based
    if reported == zero_based + 1:
        return zero_based
    raise ProtocolError(
        f"STARTINDEX of sensor {sensor} is {reported}; expected {zero_based} (0-based) or {zero_based + 1} (1-based)"
    )


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
