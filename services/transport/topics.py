"""Zenoh key expressions of msk-live. docs/topics.md documents the same table; keep both in step.

Every key lives under ``msk/<session>/``. A session name is one key chunk: letters, digits, ``-`` and ``_``.
"""

from __future__ import annotations

import functools
import re
from enum import Enum

from msk_core.errors import ConfigError

ROOT = "msk"
ALL_TOPICS = f"{ROOT}/**"
#: ``msk/<session>/graph/<node>``: the readiness (liveliness) tokens of a session's nodes (services.nodes.readiness)
GRAPH_CHUNK = "graph"

_CHUNK = re.compile(r"^[A-Za-z0-9_\-.]+$")

#: (template after ``msk/<session>/``, protobuf type). A ``<name>`` part stands for exactly one key chunk.
TOPIC_TABLE: tuple[tuple[str, str], ...] = (
    ("emg/<source>", "msk.EmgChunk"),
    ("acc/<source>", "msk.AccChunk"),
    ("imu/<tracker>", "msk.ImuSample"),
    ("joints", "msk.JointAngles"),
    ("load", "msk.LoadEvent"),
    ("activations/<method>", "msk.ActivationFrame"),
    ("status/<device>", "msk.DeviceStatus"),
    ("envelopes", "msk.EmgEnvelope"),
)
_TYPE_OF_TEMPLATE = dict(TOPIC_TABLE)


class Delivery(Enum):
    """How a topic's publisher behaves when a subscriber does not keep up (docs/topics.md, "Delivery")."""

    #: reliable + blocking congestion control: the publisher waits for a slow subscriber, nothing is dropped
    LOSSLESS = "lossless"
    #: reliable + drop congestion control: a subscriber whose queue is full misses messages, nobody waits for it
    NEWEST_WINS = "newest-wins"


#: Per topic template: device data and what is derived from it frame by frame must reach the recorder and the
#: estimator whole; what views and apps read (activations, status) must never stall its publisher.
DELIVERY: dict[str, Delivery] = {
    "emg/<source>": Delivery.LOSSLESS,
    "acc/<source>": Delivery.LOSSLESS,
    "imu/<tracker>": Delivery.LOSSLESS,
    "joints": Delivery.LOSSLESS,
    "load": Delivery.LOSSLESS,
    "activations/<method>": Delivery.NEWEST_WINS,
    "envelopes": Delivery.NEWEST_WINS,  # like the activations they sit beside: for views and apps
    "status/<device>": Delivery.NEWEST_WINS,
}


def check_chunk(value: str, what: str) -> str:
    if not _CHUNK.match(value):
        raise ConfigError("must be a single key chunk of letters, digits, '-', '_' or '.'", field=what, value=value)
    return value


def session_prefix(session: str) -> str:
    return f"{ROOT}/{check_chunk(session, 'session')}"


def emg_key(session: str, source: str) -> str:
    return f"{session_prefix(session)}/emg/{check_chunk(source, 'source')}"


def acc_key(session: str, source: str) -> str:
    """The accelerometers on EMG source ``source``'s clock (Trigno AUX): ``msk/<session>/acc/<source>``."""
    return f"{session_prefix(session)}/acc/{check_chunk(source, 'source')}"


def imu_key(session: str, tracker: str) -> str:
    return f"{session_prefix(session)}/imu/{check_chunk(tracker, 'tracker')}"


def joints_key(session: str) -> str:
    return f"{session_prefix(session)}/joints"


def load_key(session: str) -> str:
    return f"{session_prefix(session)}/load"


def activations_key(session: str, method: str) -> str:
    return f"{session_prefix(session)}/activations/{check_chunk(method, 'method')}"


def envelopes_key(session: str) -> str:
    return f"{session_prefix(session)}/envelopes"


def status_key(session: str, device: str) -> str:
    return f"{session_prefix(session)}/status/{check_chunk(device, 'device')}"


def split_key(key: str) -> tuple[str, str]:
    """``msk/<session>/<rest>`` -> (session, rest)."""
    parts = str(key).split("/", 2)
    if len(parts) < 3 or parts[0] != ROOT:
        raise ConfigError("not an msk topic (expected msk/<session>/...)", field="key", value=str(key))
    return parts[1], parts[2]


def rename_session(key: str, new_session: str) -> str:
    _, rest = split_key(key)
    return f"{session_prefix(new_session)}/{rest}"


@functools.lru_cache(maxsize=4096)
def _template_for_key(key: str) -> str | None:
    """The table's template ``key`` matches (None: none); cached, since every node asks it for every message (a
    session has a few dozen keys; a key that is no msk topic raises and is not cached)."""
    _, rest = split_key(key)
    rest_parts = rest.split("/")
    for pattern, _type_name in TOPIC_TABLE:
        pattern_parts = pattern.split("/")
        if len(pattern_parts) == len(rest_parts) and all(
            p.startswith("<") or p == r for p, r in zip(pattern_parts, rest_parts)
        ):
            return pattern
    return None


def message_type_for_key(key: str) -> str | None:
    """The protobuf type carried by ``key``, or None when the key is not in the table."""
    template = _template_for_key(key)
    return None if template is None else _TYPE_OF_TEMPLATE[template]


def delivery_for_key(key: str) -> Delivery:
    """The delivery policy of ``key``; keys outside the table are lossless (the safe side for data)."""
    template = _template_for_key(key)
    return Delivery.LOSSLESS if template is None else DELIVERY[template]
