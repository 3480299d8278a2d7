"""EMG recordings a Trigno simulator can stream: a C3D export, a simple .npz, or a synthetic session.

Formats (docs/devices.md has the full description):
- ``*.c3d``: analog channels whose label ends in ``.EMG<n>`` (or ``.IM EMG<n>``) fill sensor slot n (1..16), in volts.
- ``*.npz``: ``emg`` (n_samples, n_channels <= 16) volts, ``rate_hz`` scalar; optional ``labels`` (n_channels,)
  and ``sensors`` (n_channels,) 1-based slot numbers (default 1..n_channels); optional ``acc`` (m, n_channels, 3) in g
  with ``acc_rate_hz``: each sensor's accelerometer (Avanti ACC, streamed on the AUX port).
- ``*.bin``: raw EMG data-port bytes (little-endian float32, 16 per sample); the rate is given separately (2000 Hz).
- ``synthetic[:SECONDS[:SEED]]``: bursts of band-limited noise on 4 sensors at 2000 Hz.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers import load_source_spec, open_npz
from drivers.trigno.protocol import N_SENSORS
from msk_core.errors import ConfigError, FileFormatError, InputError
from msk_core.units import volts_per_unit

log = logging.getLogger(__name__)

_EMG_LABEL = re.compile(r"^(?P<name>.*?)\.(?P<im>IM )?EMG(?P<slot>\d+)$")


@dataclass(frozen=True)
class EmgSource:
    """Samples for the 16 sensor slots (unpaired slots are zero)."""

    samples: np.ndarray  # (n, 16) float32 volts
    rate_hz: float
    labels: tuple[str, ...]  # 16 names ("" for unpaired)
    paired: tuple[bool, ...]  # 16 flags
    name: str
    acc: np.ndarray | None = None  # (m, 16, 3) float32 g: each sensor's accelerometer; None: sensors lying flat
    acc_rate_hz: float = 0.0  # rate of ``acc``; it spans the same trial as ``samples``

    @property
    def n_samples(self) -> int:
        return int(self.samples.shape[0])


def load_source(spec: str | Path, *, rate_hz: float | None = None) -> EmgSource:
    """Load an EMG source from a path (.c3d, .npz, .bin) or a ``synthetic[:SECONDS[:SEED]]`` spec.

    ``rate_hz`` is the rate of a raw ``.bin`` stream (default 2000 Hz); other formats carry their own rate.
    """
    raw_rate_hz = 2000.0 if rate_hz is None else rate_hz
    if rate_hz is not None and not str(spec).lower().endswith(".bin"):
        raise ConfigError(
            "a rate is for a raw .bin stream only: .c3d, .npz and synthetic sources carry their own",
            field="--rate",
            value=rate_hz,
        )
    return load_source_spec(
        spec,
        "EMG",
        lambda seconds, seed: synthetic_source(seconds=seconds, seed=seed),
        {".c3d": load_c3d, ".npz": load_npz, ".bin": lambda path: load_raw_stream(path, rate_hz=raw_rate_hz)},
    )


def load_raw_stream(path: Path, *, rate_hz: float) -> EmgSource:
    """A capture of the EMG data port: little-endian float32, 16 per sample, no header. A capture cut inside its
    last sample (the stream has no framing, so a recording can stop anywhere) loses that sample with a warning."""
    data = path.read_bytes()
    row_bytes = N_SENSORS * 4
    if len(data) < row_bytes:
        raise FileFormatError(f"{len(data)} bytes is less than one {row_bytes}-byte sample (16 float32)", path=path)
    if len(data) % row_bytes:
        log.warning(
            "%s: %d trailing bytes are an incomplete sample (capture cut mid-sample); dropped",
            path,
            len(data) % row_bytes,
        )
        data = data[: len(data) - len(data) % row_bytes]
    if not 100.0 <= rate_hz <= 10000.0:
        raise InputError("rate must be within 100..10000 Hz", field="--rate", value=rate_hz)
    samples = np.frombuffer(data, dtype="<f4").reshape(-1, N_SENSORS).astype(np.float32)
    if not np.all(np.isfinite(samples)):
        raise FileFormatError("stream holds NaN or infinite values", path=path)
    paired = tuple(bool(np.any(samples[:, k])) for k in range(N_SENSORS))
    names = tuple(f"sensor{k + 1:02d}" if paired[k] else "" for k in range(N_SENSORS))
    return EmgSource(samples, rate_hz, names, paired, path.name)


def load_c3d(path: Path) -> EmgSource:
    import ezc3d  # imported here: only the C3D path needs it

    try:
        c3d = ezc3d.c3d(str(path))
    except Exception as error:  # ezc3d raises plain RuntimeError/IOError with its own text
        raise FileFormatError(f"cannot read C3D: {error}", path=path) from error
    analog = c3d["parameters"]["ANALOG"]
    labels = [str(label) for label in analog["LABELS"]["value"]]
    rate = float(np.atleast_1d(analog["RATE"]["value"])[0])
    data = np.asarray(c3d["data"]["analogs"])[0]  # (channels, frames)
    units = [str(u) for u in analog.get("UNITS", {}).get("value", ["V"] * len(labels))]
    samples = np.zeros((data.shape[1], N_SENSORS), dtype=np.float32)
    names = [""] * N_SENSORS
    paired = [False] * N_SENSORS
    for column, label in enumerate(labels):
        match = _EMG_LABEL.match(label)
        if match is None:
            continue
        slot = int(match.group("slot"))
        if not 1 <= slot <= N_SENSORS:
            raise FileFormatError("EMG slot outside 1..16", path=path, field="ANALOG:LABELS", value=label)
        values = data[column]
        if not np.any(np.nan_to_num(values)):
            continue  # an unpaired slot exported as zeros (or NaN); an IM sensor may own the slot instead
        if paired[slot - 1]:
            raise FileFormatError(
                "two EMG channels claim the same sensor slot", path=path, field="ANALOG:LABELS", value=label
            )
        unit = units[column] if column < len(units) else "V"
        scale = volts_per_unit(unit or "V")  # the Trigno streams volts
        if scale is None:
            raise FileFormatError(
                "EMG channel in a unit that is not a voltage (V, mV, uV)",
                path=path,
                field=f"ANALOG:UNITS {label}",
                value=unit,
            )
        if not np.all(np.isfinite(values)):
            first = int(np.argmax(~np.isfinite(values)))
            raise FileFormatError(
                f"EMG channel holds NaN or infinite samples, from t = {first / rate:g} s (a device streams numbers)",
                path=path,
                field=label,
            )
        samples[:, slot - 1] = values * scale
        names[slot - 1] = match.group("name")
        paired[slot - 1] = True
    if not any(paired):
        raise FileFormatError("no non-zero analog channel labelled <name>.EMG<n>", path=path, field="ANALOG:LABELS")
    return EmgSource(samples, rate, tuple(names), tuple(paired), path.name)


def load_npz(path: Path) -> EmgSource:
    with open_npz(path, ("emg", "rate_hz")) as archive:
        emg = np.asarray(archive["emg"], dtype=np.float32)
        if emg.ndim == 1:
            emg = emg[:, None]
        if emg.ndim != 2 or not 1 <= emg.shape[1] <= N_SENSORS or emg.shape[0] == 0:
            raise FileFormatError("emg must be (n_samples, 1..16 channels)", path=path, field="emg", value=emg.shape)
        if not np.all(np.isfinite(emg)):
            raise FileFormatError("emg holds NaN or infinite values", path=path, field="emg")
        rates = np.asarray(archive["rate_hz"]).reshape(-1)
        if rates.size != 1:
            raise FileFormatError("rate_hz must be one number", path=path, field="rate_hz", value=rates.tolist())
        rate = float(rates[0])
        if not 100.0 <= rate <= 10000.0:
            raise FileFormatError("rate_hz must be within 100..10000 Hz", path=path, field="rate_hz", value=rate)
        n_channels = emg.shape[1]
        labels = (
            [str(x) for x in archive["labels"]]
            if "labels" in archive.files
            else [f"sensor{k + 1:02d}" for k in range(n_channels)]
        )
        sensors = [int(x) for x in archive["sensors"]] if "sensors" in archive.files else list(range(1, n_channels + 1))
        acc, acc_rate = _npz_acc(archive, path, emg.shape[0] / rate, n_channels)
    if len(labels) != n_channels:
        raise FileFormatError("one label per emg column expected", path=path, field="labels", value=len(labels))
    if len(sensors) != n_channels or len(set(sensors)) != n_channels or not all(1 <= s <= N_SENSORS for s in sensors):
        raise FileFormatError(
            "sensors must be distinct slots 1..16, one per column", path=path, field="sensors", value=sensors
        )
    samples = np.zeros((emg.shape[0], N_SENSORS), dtype=np.float32)
    slot_acc = None
    if acc is not None:
        slot_acc = np.zeros((acc.shape[0], N_SENSORS, 3), dtype=np.float32)
        slot_acc[:, np.asarray(sensors) - 1] = acc  # the slots are distinct (checked above)
    names = [""] * N_SENSORS
    paired = [False] * N_SENSORS
    for column, slot in enumerate(sensors):
        samples[:, slot - 1] = emg[:, column]
        names[slot - 1] = labels[column]
        paired[slot - 1] = True
    return EmgSource(samples, rate, tuple(names), tuple(paired), path.name, slot_acc, acc_rate)


def _npz_acc(archive, path: Path, emg_s: float, n_channels: int) -> tuple[np.ndarray | None, float]:
    """The optional accelerometer arrays of a Trigno .npz: ``acc`` (m, n_channels, 3) g at ``acc_rate_hz``, spanning
    the EMG's duration (within two of its samples)."""
    if ("acc" in archive.files) != ("acc_rate_hz" in archive.files):
        raise FileFormatError("acc and acc_rate_hz go together", path=path, field="acc")
    if "acc" not in archive.files:
        return None, 0.0
    acc = np.asarray(archive["acc"], dtype=np.float32)
    rate = float(np.asarray(archive["acc_rate_hz"]).reshape(-1)[0])
    if not 1.0 <= rate <= 10000.0:
        raise FileFormatError("acc_rate_hz must be within 1..10000 Hz", path=path, field="acc_rate_hz", value=rate)
    if acc.ndim != 3 or acc.shape[1:] != (n_channels, 3) or acc.shape[0] < 2:
        raise FileFormatError(
            f"acc must be (m >= 2, {n_channels} channels, 3 axes)", path=path, field="acc", value=acc.shape
        )
    if not np.all(np.isfinite(acc)):
        raise FileFormatError("acc holds NaN or infinite values", path=path, field="acc")
    if abs(acc.shape[0] / rate - emg_s) > 2.0 / rate:
        raise FileFormatError(f"acc spans {acc.shape[0] / rate:.3f} s, the EMG {emg_s:.3f} s", path=path, field="acc")
    return acc, rate


def synthetic_source(*, seconds: float = 30.0, seed: int = 0, rate_hz: float = 2000.0, sensors: int = 4) -> EmgSource:
    """Bursty EMG-like noise (10-400 Hz content, ~1 mV peaks) on the first ``sensors`` slots."""
    if seconds <= 0 or not 1 <= sensors <= N_SENSORS:
        raise InputError("synthetic source needs seconds > 0 and 1..16 sensors", value=(seconds, sensors))
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate_hz))
    t = np.arange(n) / rate_hz
    samples = np.zeros((n, N_SENSORS), dtype=np.float32)
    kernel = np.exp(-np.arange(40) / 6.0)
    kernel -= kernel.mean()  # zero mean: removes DC like a real differential EMG amplifier
    for k in range(sensors):
        envelope = 0.05 + 0.95 * np.clip(np.sin(2 * np.pi * 0.5 * t + k), 0.0, None) ** 2
        noise = np.convolve(rng.standard_normal(n), kernel, mode="same")
        samples[:, k] = (3e-4 * envelope * noise).astype(np.float32)
    names = tuple(f"muscle{k + 1}" if k < sensors else "" for k in range(N_SENSORS))
    paired = tuple(k < sensors for k in range(N_SENSORS))
    return EmgSource(samples, rate_hz, names, paired, f"synthetic:{seconds:g}:{seed}")


def resample(samples: np.ndarray, rate_in: float, rate_out: float) -> np.ndarray:
    """Linear resampling (used when the simulated upsampling setting differs from the recording's rate)."""
    if abs(rate_in - rate_out) < 1e-9:
        return samples
    n_out = int(np.floor((samples.shape[0] - 1) * rate_out / rate_in)) + 1
    t_out = np.arange(n_out) / rate_out
    t_in = np.arange(samples.shape[0]) / rate_in
    return np.stack([np.interp(t_out, t_in, samples[:, k]) for k in range(samples.shape[1])], axis=1).astype(np.float32)
