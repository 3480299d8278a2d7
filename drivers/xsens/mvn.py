"""Xsens MVN network streamer (UDP): the segment poses a motion-capture suit streams, as a second IMU input.

Datagrams are big-endian with a 24-byte header (``../shared/protocols/xsens-xbus.md``, "Xsens MVN network
streamer"): ``MXTP`` and two ASCII digits for the message type, u32 sample counter, u8 datagram counter (its most
significant bit marks the last datagram of a sample; 0x80 when one datagram carries it all), u8 item count, u32 time
(ms), u8 character id, u8 body segments, u8 props, u8 finger segments, 2 reserved bytes, u16 payload size. Type 02
(quaternion pose) carries per segment an i32 segment id, a 3-float position and a 4-float quaternion (re, i, j, k):
32 bytes. Segment ids are the index + 1 in MVN's order (:data:`SEGMENTS`). Only type 02 is read here; the others
(joint angles, Euler poses, ...) are counted and left out.

MVN's global frame is Z up with X to the direction defined at its calibration (north, or where the subject faced):
the orientations are passed on as ``NWU`` (x, y = x rotated 90° about up, z up), which the kinematics' static-pose
calibration then relates to the body as it does for any tracker.
"""

from __future__ import annotations

import socket
import struct
import time
from collections import Counter
from dataclasses import dataclass, field

from drivers.xsens import frames, xbus
from msk_core.errors import ProtocolError

MAGIC = b"MXTP"
HEADER = struct.Struct(">4s2sIBBIBBBB2xH")
assert HEADER.size == 24
POSE_QUATERNION = "02"
POSE_ITEM = struct.Struct(">i3f4f")
DEFAULT_PORT = 9763
PENDING_SAMPLES = 30  # a sample whose datagrams are not all in by this many samples later is left out
#: MVN's 23 body segments in streaming order (segment id = index + 1)
SEGMENTS = (
    "pelvis", "l5", "l3", "t12", "t8", "neck", "head",
    "right_shoulder", "right_upper_arm", "right_forearm", "right_hand",
    "left_shoulder", "left_upper_arm", "left_forearm", "left_hand",
    "right_upper_leg", "right_lower_leg", "right_foot", "right_toe",
    "left_upper_leg", "left_lower_leg", "left_foot", "left_toe",
)  # fmt: skip
#: the model packs' IMU segments (msk_core.imu.mapping) and the MVN segment that is each
PACK_SEGMENTS = {
    "pelvis": "pelvis",
    "torso": "t8",
    "upper_arm_r": "right_upper_arm",
    "forearm_r": "right_forearm",
    "thigh_r": "right_upper_leg",
    "shank_r": "right_lower_leg",
}


def parse_address(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` -> (host, "" when none, port 0..65535); ValueError naming the expected form."""
    host, _, port = text.rpartition(":")
    if not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError('a UDP port, e.g. 9763, or "HOST:PORT"')
    return host, int(port)


@dataclass(frozen=True)
class Datagram:
    """One datagram: its header fields and the raw items."""

    message_type: str
    sample_counter: int
    datagram_index: int  # 0, 1, ... within its sample
    last: bool  # the last datagram of its sample
    items: int
    time_ms: int
    character: int
    payload: bytes


@dataclass(frozen=True)
class SegmentPose:
    segment_id: int
    position: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]  # w (re) first

    @property
    def name(self) -> str:
        """MVN's name of the segment (``segment_<id>`` beyond the 23 body segments: props, fingers)."""
        return SEGMENTS[self.segment_id - 1] if 1 <= self.segment_id <= len(SEGMENTS) else f"segment_{self.segment_id}"


@dataclass(frozen=True)
class Pose:
    """Every segment of one sample of one character."""

    sample_counter: int
    time_ms: int
    character: int
    host_time_ns: int
    segments: tuple[SegmentPose, ...]


def parse_datagram(data: bytes) -> Datagram:
    """A datagram's header and payload; ProtocolError naming what is wrong (magic, size)."""
    if len(data) < HEADER.size:
        raise ProtocolError(f"MVN datagram of {len(data)} bytes: shorter than its {HEADER.size}-byte header")
    magic, kind, counter, datagram, items, time_ms, character, _, _, _, size = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ProtocolError(f"not an MVN datagram: starts {data[:6]!r}, expected {MAGIC!r} and a type")
    payload = data[HEADER.size :]
    if size != len(payload):
        raise ProtocolError(f"MVN datagram says {size} payload bytes, carries {len(payload)}")
    return Datagram(
        kind.decode("ascii", errors="replace"),
        counter,
        datagram & 0x7F,
        bool(datagram & 0x80),
        items,
        time_ms,
        character,
        payload,
    )


def parse_pose_items(payload: bytes) -> list[SegmentPose]:
    """The type-02 items of a payload (32 bytes each)."""
    if len(payload) % POSE_ITEM.size:
        raise ProtocolError(
            f"MVN quaternion pose payload of {len(payload)} bytes: not whole {POSE_ITEM.size}-byte items"
        )
    return [
        SegmentPose(segment, (x, y, z), (w, i, j, k)) for segment, x, y, z, w, i, j, k in POSE_ITEM.iter_unpack(payload)
    ]


def body_pose(orientations_enu: dict[str, tuple[float, float, float, float]]) -> list[SegmentPose]:
    """The 23 body segments of a pose as MVN streams them: the packs' segments given (by the pack's name, e.g.
    upper_arm_r; orientation sensor-to-world in ENU, w first) turned into MVN's frame (NWU), every other segment
    still (identity). What ``msk sim mvn`` and the tests send."""
    to_nwu = frames.ENU_TO[xbus.CoordinateFrame.NWU]
    by_mvn = {PACK_SEGMENTS[pack]: q for pack, q in orientations_enu.items()}
    return [
        SegmentPose(
            index + 1,
            (0.0, 0.0, 1.0),
            frames.quat_multiply(to_nwu, by_mvn[name]) if name in by_mvn else (1.0, 0.0, 0.0, 0.0),
        )
        for index, name in enumerate(SEGMENTS)
    ]


def encode_pose(
    sample_counter: int,
    time_ms: int,
    segments: list[SegmentPose],
    *,
    character: int = 0,
    per_datagram: int = 23,
) -> list[bytes]:
    """The datagrams of one quaternion pose (split ``per_datagram`` items each, as MVN does for large bodies)."""
    chunks = [segments[k : k + per_datagram] for k in range(0, len(segments), per_datagram)] or [[]]
    out = []
    for index, chunk in enumerate(chunks):
        payload = b"".join(POSE_ITEM.pack(s.segment_id, *s.position, *s.quaternion) for s in chunk)
        counter = index | (0x80 if index == len(chunks) - 1 else 0)
        header = HEADER.pack(
            MAGIC, POSE_QUATERNION.encode(), sample_counter, counter, len(chunk), time_ms, character,
            len(SEGMENTS), 0, 0, len(payload),
        )  # fmt: skip
        out.append(header + payload)
    return out


@dataclass
class ReceiverStats:
    datagrams: int = 0
    poses: int = 0
    samples_lost: int = 0  # sample-counter jumps
    other_types: Counter[str] = field(default_factory=Counter)  # datagrams of other message types, per type (left out)
    errors: int = 0  # datagrams that are not MVN's, or broken
    incomplete: int = 0  # samples whose datagrams did not all arrive
    repeated: int = 0  # datagrams that came again or too late for their sample (left out)
    other_characters: Counter[int] = field(default_factory=Counter)  # poses of characters not followed (left out)
    restarts: int = 0  # the stream started again (its sample counter went back)
    last_error: str = ""


@dataclass
class MvnReceiver:
    """Listens on a UDP port and assembles each sample's quaternion pose from its datagrams, in whatever order they
    come (by the sample counter and the datagram index; the last one's index says how many there are), once each.
    It follows one character: ``character``, or the first one heard; the others are counted and left out (two suits
    streamed as one athlete's segments alternated in the joint angles)."""

    host: str = "0.0.0.0"
    port: int = DEFAULT_PORT
    character: int | None = None
    stats: ReceiverStats = field(default_factory=ReceiverStats)
    _socket: socket.socket | None = None
    _pending: dict[int, dict[int, Datagram]] = field(default_factory=dict)  # sample -> datagram index -> datagram
    _last_counter: int | None = None  # of the newest sample put together

    def open(self) -> MvnReceiver:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((self.host, self.port))
        except OSError as error:
            sock.close()
            raise ProtocolError(f"cannot listen for MVN on UDP {self.host}:{self.port}: {error}") from None
        self._socket = sock
        self.port = sock.getsockname()[1]
        return self

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def __enter__(self) -> MvnReceiver:
        return self if self._socket is not None else self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def read(self, timeout_s: float = 0.05) -> list[Pose]:
        """The poses completed by the datagrams that arrive within ``timeout_s`` (all that are waiting, then)."""
        assert self._socket is not None, "open() first"
        self._socket.settimeout(timeout_s)
        poses: list[Pose] = []
        while True:
            try:
                data = self._socket.recv(65535)
            except (TimeoutError, BlockingIOError):
                return poses
            self._socket.settimeout(0.0)  # the rest of what is waiting, without waiting again
            pose = self._take(data, time.time_ns())
            if pose is not None:
                poses.append(pose)

    def _take(self, data: bytes, host_time_ns: int) -> Pose | None:
        self.stats.datagrams += 1
        try:
            datagram = parse_datagram(data)
            if datagram.message_type != POSE_QUATERNION:
                if not datagram.message_type.isdigit():
                    raise ProtocolError(f"MVN datagram of type {datagram.message_type!r}: not two digits")
                self.stats.other_types[datagram.message_type] += 1
                return None
            if self.character is None:
                self.character = datagram.character
            if datagram.character != self.character:
                self.stats.other_characters[datagram.character] += int(datagram.last)
                return None
            parts = self._assembled(datagram)
            if parts is None:
                return None
            segments = [s for p in parts for s in parse_pose_items(p.payload)]
        except ProtocolError as error:
            self.stats.errors += 1
            self.stats.last_error = str(error)
            return None
        return self._pose(datagram, tuple(segments), host_time_ns)

    def _assembled(self, datagram: Datagram) -> list[Datagram] | None:
        """The sample's datagrams in order once all have come (None until then, or for one seen already)."""
        counter, last = datagram.sample_counter, self._last_counter
        if last is not None and last - PENDING_SAMPLES <= counter <= last:
            # a datagram of a sample put together (or passed) already, or the whole sample again: the poses go
            # out in counter order, a late one is left out (counted lost when its successor came)
            self.stats.repeated += 1
            return None
        parts = self._pending.setdefault(counter, {})
        if datagram.datagram_index in parts:
            self.stats.repeated += 1
            return None
        parts[datagram.datagram_index] = datagram
        final = next((p for p in parts.values() if p.last), None)
        if final is None or len(parts) < final.datagram_index + 1:
            return None
        del self._pending[counter]
        return [parts[k] for k in sorted(parts)]

    def _pose(self, datagram: Datagram, segments: tuple[SegmentPose, ...], host_time_ns: int) -> Pose:
        counter, last = datagram.sample_counter, self._last_counter
        for stale in [k for k in self._pending if k < counter - PENDING_SAMPLES or k > counter + PENDING_SAMPLES]:
            del self._pending[stale]  # samples a datagram of which never came
            self.stats.incomplete += 1
            self.stats.last_error = f"MVN sample {stale}: a datagram never came, sample left out"
        if last is not None and counter > last + 1:
            self.stats.samples_lost += counter - last - 1
        elif last is not None and counter < last:  # far back (near ones are left out as late): a new stream
            self.stats.restarts += 1
            self.stats.last_error = f"the MVN stream started again (sample {counter} after {last})"
        self._last_counter = counter
        self.stats.poses += 1
        return Pose(counter, datagram.time_ms, datagram.character, host_time_ns, segments)
