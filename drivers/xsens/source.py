"""IMU recordings an Xsens simulator can stream: a raw Xbus capture, a simple .npz, or a synthetic motion.

Formats (docs/devices.md has the full description):
- ``*.bin``: raw serial bytes of a device (MTData2 frames; other frames ignored). Streamed verbatim while the
  output configuration is the recorded one (``<stem>_outputconfig.bin`` beside it, else the DataIDs of the first
  message); re-encoded from the decoded values after a SetOutputConfiguration (a quaternion from the Euler angles of
  a capture that has none: the device computes both from one orientation).
- ``*.npz``: ``rate_hz`` scalar and any of ``quaternion`` (n, 4, w first, ENU), ``acceleration`` (n, 3, m/s^2),
  ``rate_of_turn`` (n, 3, rad/s), ``magnetic_field`` (n, 3, a.u.), ``free_acceleration`` (n, 3), ``euler`` (n, 3, deg).
- ``synthetic[:SECONDS[:SEED]]``: a sensor swinging about two axes at 100 Hz (consistent quaternion/gyro/acc).
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivers import load_source_spec, open_npz
from drivers.xsens import frames, xbus
from msk_core.errors import FileFormatError, InputError, ProtocolError
from msk_core.units import GRAVITY

#: Quantities a source may carry, with their component counts.
QUANTITIES = {
    "quaternion": 4,
    "acceleration": 3,
    "free_acceleration": 3,
    "rate_of_turn": 3,
    "magnetic_field": 3,
    "euler": 3,
    "delta_q": 4,
    "delta_v": 3,
    "temperature": 1,
}
DEFAULT_RATE_HZ = 100.0  # an MTi's factory output rate, assumed only when a capture carries no rate information

log = logging.getLogger(__name__)


@dataclass
class ImuSource:
    rate_hz: float
    arrays: dict[str, np.ndarray]  # quantity name -> (n, components) float64, ENU
    name: str
    raw_payloads: list[bytes] = field(default_factory=list)  # recorded MTData2 payloads (verbatim replay)
    recorded_config: list[xbus.OutputSetting] = field(default_factory=list)

    @property
    def n_samples(self) -> int:
        return len(next(iter(self.arrays.values()))) if self.arrays else len(self.raw_payloads)


def load_imu_source(spec: str | Path) -> ImuSource:
    """Load an IMU source from a path (.bin, .npz) or a ``synthetic[:SECONDS[:SEED]]`` spec."""
    return load_source_spec(
        spec,
        "IMU",
        lambda seconds, seed: synthetic_imu(seconds=seconds, seed=seed),
        {".bin": load_capture, ".npz": load_imu_npz},
    )


def load_capture(path: Path) -> ImuSource:
    data = path.read_bytes()
    parser = xbus.XbusParser()
    messages = [m for m in parser.feed(data) if m.mid == xbus.Mid.MT_DATA2]
    if not messages:
        raise FileFormatError(f"no valid MTData2 frame in {len(data)} bytes", path=path)
    if parser.stats.bytes_skipped or parser.pending:
        log.warning(
            "%s: %d bytes outside valid frames skipped, %d trailing bytes of an incomplete frame dropped",
            path,
            parser.stats.bytes_skipped,
            parser.pending,
        )
    bus_ids = Counter(m.bid for m in messages)
    if len(bus_ids) > 1:  # several trackers in one stream (bus ids): one source is one tracker
        bid = xbus.BID_MASTER if xbus.BID_MASTER in bus_ids else bus_ids.most_common(1)[0][0]
        log.warning("%s: MTData2 from bus ids %s; using 0x%02X only", path, sorted(bus_ids), bid)
        messages = [m for m in messages if m.bid == bid]
    columns: dict[str, list] = {}
    counters = []
    for index, message in enumerate(messages):
        try:
            decoded = xbus.decode_mtdata2(message.data)
        except ProtocolError as error:
            raise FileFormatError(f"MTData2 message {index} does not decode: {error}", path=path) from error
        counters.append(decoded.first("packet_counter"))
        for name in QUANTITIES:
            values = decoded.get(name)
            if values is not None:
                columns.setdefault(name, []).append(values)
    arrays = {}
    full = len(messages)
    for name, rows in columns.items():
        if len(rows) >= 0.9 * full:  # quantities present in (nearly) every message; others are occasional
            arrays[name] = np.asarray(rows, dtype=np.float64)
    n = min((len(a) for a in arrays.values()), default=0)
    arrays = {k: v[:n] for k, v in arrays.items()}
    config_path = path.with_name(path.stem + "_outputconfig.bin")
    if config_path.is_file():
        recorded = xbus.decode_output_configuration(config_path.read_bytes())
    else:
        recorded = [xbus.OutputSetting(data_id, 0xFFFF) for data_id, _ in xbus.item_layout(messages[0].data)]
    rate = _rate_from_counters(messages)
    if rate is None and config_path.is_file():
        rate = xbus.message_rate_hz(recorded)
    if rate is None:
        rate = DEFAULT_RATE_HZ
        log.warning(
            "%s: no SampleTimeFine in the capture and no output configuration beside it (%s); "
            "assuming the factory default of %.0f Hz",
            path,
            config_path.name,
            rate,
        )
    if "quaternion" not in arrays and "euler" in arrays:
        # the Euler output's frame from the configuration, else from a message carrying it (ENU: the default)
        ids = [s.data_id for s in recorded] + [d for m in messages[:50] for d, _ in xbus.item_layout(m.data)]
        euler_id = next((d for d in ids if d & 0xFFF0 == 0x2030), 0x2030)
        arrays["quaternion"] = _quaternions_from_euler(arrays["euler"], xbus.frame_of(euler_id))
        log.info("%s: no quaternion in the capture; the device's own from its Euler angles", path)
    return ImuSource(rate, arrays, path.name, [m.data for m in messages], recorded)


def _quaternions_from_euler(euler: np.ndarray, frame: xbus.CoordinateFrame) -> np.ndarray:
    """(n, 4) ENU quaternions of a capture's Euler output in ``frame``: the device computes both from one
    orientation, so a device whose driver asks for quaternions gives these (a capture of Euler angles only is
    replayed as such a device)."""
    return np.array([frames.to_enu(frames.quat_from_euler_deg(*row), frame) for row in euler.tolist()])


def _rate_from_counters(messages: list[xbus.XbusMessage]) -> float | None:
    """Rate from SampleTimeFine (10 kHz ticks) over the capture, when present."""
    times = []
    for message in messages:
        value = xbus.decode_mtdata2(message.data).first("sample_time_fine")
        if value is not None:
            times.append(value)
    if len(times) < 2:
        return None
    steps = np.diff(np.asarray(times, dtype=np.int64))
    step = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 0.0
    return 1e4 / step if step > 0 else None


def load_imu_npz(path: Path) -> ImuSource:
    with open_npz(path, ("rate_hz",)) as archive:
        rate = float(np.asarray(archive["rate_hz"]).reshape(-1)[0])
        arrays = {}
        for name, width in QUANTITIES.items():
            if name in archive.files:
                value = np.asarray(archive[name], dtype=np.float64)
                if value.ndim != 2 or value.shape[1] != width or value.shape[0] == 0:
                    raise FileFormatError(f"must be (n, {width})", path=path, field=name, value=value.shape)
                if not np.all(np.isfinite(value)):
                    raise FileFormatError("holds NaN or infinite values", path=path, field=name)
                arrays[name] = value
    if not 1.0 <= rate <= 2000.0:
        raise FileFormatError("rate_hz must be within 1..2000 Hz", path=path, field="rate_hz", value=rate)
    if not arrays:
        raise FileFormatError(f"no IMU quantity (expected any of {', '.join(QUANTITIES)})", path=path)
    lengths = {name: len(a) for name, a in arrays.items()}
    if len(set(lengths.values())) != 1:
        raise FileFormatError("all quantities must have the same number of samples", path=path, value=lengths)
    return ImuSource(rate, arrays, path.name)


def synthetic_imu(*, seconds: float = 30.0, seed: int = 0, rate_hz: float = 100.0) -> ImuSource:
    """A segment swinging about x and z; the quaternion integrates the gyro, acc is gravity in the sensor frame."""
    if seconds <= 0:
        raise InputError("synthetic IMU needs seconds > 0", value=seconds)
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate_hz))
    t = np.arange(n) / rate_hz
    roll = 0.6 * np.sin(2 * np.pi * 0.4 * t)
    yaw = 0.3 * np.sin(2 * np.pi * 0.25 * t + 1.0)
    half_r, half_y = roll / 2, yaw / 2
    # q = qz(yaw) * qx(roll)
    quaternion = np.stack(
        [
            np.cos(half_y) * np.cos(half_r),
            np.cos(half_y) * np.sin(half_r),
            np.sin(half_y) * np.sin(half_r),
            np.sin(half_y) * np.cos(half_r),
        ],
        axis=1,
    )
    gyro = np.stack([np.gradient(roll, t), np.zeros(n), np.gradient(yaw, t)], axis=1)
    gyro[:, 1] = -np.sin(roll) * gyro[:, 2]
    gyro[:, 2] = np.cos(roll) * gyro[:, 2]
    acc = np.stack([np.zeros(n), GRAVITY * np.sin(roll), GRAVITY * np.cos(roll)], axis=1)
    acc += rng.normal(0.0, 0.02, acc.shape)
    mag = np.stack([np.cos(-yaw), np.sin(-yaw) * np.cos(roll), -np.sin(-yaw) * np.sin(roll)], axis=1)
    return ImuSource(
        rate_hz,
        {"quaternion": quaternion, "acceleration": acc, "rate_of_turn": gyro, "magnetic_field": mag},
        f"synthetic:{seconds:g}:{seed}",
    )
