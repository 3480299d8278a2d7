"""Protobuf message types of msk-live and their (de)serialisation.

The schema is ``services/schemas/msk.proto``; ``msk_pb2`` is generated from it with grpcio-tools' protoc and
committed (``tests/test_schemas.py`` regenerates it and checks that both agree).
"""

from __future__ import annotations

import time
from typing import TypeAlias

from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError, Message

from msk_core.errors import MskError
from services.schemas import msk_pb2

EmgChunk = msk_pb2.EmgChunk
ImuSample = msk_pb2.ImuSample
JointAngles = msk_pb2.JointAngles
LoadEvent = msk_pb2.LoadEvent
ActivationFrame = msk_pb2.ActivationFrame
CoordinateTorque = msk_pb2.CoordinateTorque
DeviceStatus = msk_pb2.DeviceStatus
EmgEnvelope = msk_pb2.EmgEnvelope
Vector3 = msk_pb2.Vector3
Quaternion = msk_pb2.Quaternion

AnyMessage: TypeAlias = Message

#: Top-level message types that travel on topics, by protobuf full name (e.g. ``"msk.EmgChunk"``).
MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.DESCRIPTOR.full_name: cls
    for cls in (EmgChunk, ImuSample, JointAngles, LoadEvent, ActivationFrame, DeviceStatus, EmgEnvelope)
}


class MessageDecodeError(MskError):
    """Bytes on a topic are not a valid message of the expected type."""


def type_name(message: Message) -> str:
    return message.DESCRIPTOR.full_name


def message_class(name: str) -> type[Message]:
    try:
        return MESSAGE_TYPES[name]
    except KeyError:
        raise MessageDecodeError(f"unknown message type {name!r}; known: {sorted(MESSAGE_TYPES)}") from None


def encode(message: Message) -> bytes:
    return message.SerializeToString()


def decode(name: str, payload: bytes) -> Message:
    cls = message_class(name)
    message = cls()
    try:
        message.ParseFromString(bytes(payload))
    except DecodeError as error:
        raise MessageDecodeError(f"{len(payload)} bytes are not a valid {name}: {error}") from error
    return message


def file_descriptor_set() -> bytes:
    """The serialised FileDescriptorSet of msk.proto (self-contained: it imports nothing), as MCAP wants it."""
    fds = descriptor_pb2.FileDescriptorSet()
    file_proto = fds.file.add()
    msk_pb2.DESCRIPTOR.CopyToProto(file_proto)
    return fds.SerializeToString()


def now_ns() -> int:
    """Host time in ns (CLOCK_REALTIME), the ``host_time_ns`` / MCAP ``log_time`` clock."""
    return time.time_ns()
