"""Delsys CSV exports: EMGworks and Trigno Discover (formats: shared/protocols/trigno-tcp.md).

Both give every channel its own time column, because channels run at different rates (EMG ~1926 or 2000 Hz,
ACC/GYRO ~148 Hz); slower channels end early and leave empty cells. So a CSV row is not one instant: the reader
returns one :class:`DelsysChannel` per channel, and :meth:`DelsysExport.recording` stacks channels sharing a rate.

* EMGworks: a label row ``X[s],"Avanti sensor 1: EMG 1",X[s],"Avanti sensor 1: ACC.X 1",...`` (possibly after
  free-text lines), then values. EMG in volts. Rates from the time columns.
* Trigno Discover: ``Application:``, ``Date/Time:``, ``Collection Length (seconds):`` rows, a sensor row
  (name at each sensor's first column), a ``sensor mode:`` row, channel names with units (``EMG 1 Time Series (s)``,
  ``EMG 1 (mV)``, ``ACC X (G)``), a rate row (``1925.9259 Hz``), an optional period row, then values. EMG in mV.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msk_core.errors import FileFormatError, InputError
from msk_core.io.analog import AnalogRecording

_UNIT = re.compile(r"^(.*?)\s*\(([^()]*)\)\s*$")
_RATE = re.compile(r"^\s*([0-9.eE+-]+)\s*Hz\s*$")
_TO_VOLTS = {"v": 1.0, "volts": 1.0, "mv": 1e-3, "uv": 1e-6, "µv": 1e-6}


@dataclass
class DelsysChannel:
    sensor: str
    name: str  # e.g. "EMG 1", "ACC X", "ACC.X 1"
    unit: str
    rate_hz: float
    time: np.ndarray
    values: np.ndarray

    @property
    def is_emg(self) -> bool:
        return self.name.upper().startswith("EMG")


@dataclass
class DelsysExport:
    application: str
    channels: list[DelsysChannel]
    header: dict[str, str] = field(default_factory=dict)
    path: Path | None = None

    def recording(self, *, emg_only: bool = True, to_volts: bool = True) -> AnalogRecording:
        """Channels (EMG by default) as one recording. They must share a rate; the length is the shortest channel.
        ``to_volts`` converts mV/uV EMG to volts, the unit of the Trigno TCP stream."""
        chans = [c for c in self.channels if c.is_emg] if emg_only else list(self.channels)
        if not chans:
            raise InputError("no EMG channel in the export" if emg_only else "no channel", path=self.path)
        rates = sorted({round(c.rate_hz, 3) for c in chans})
        if len(rates) > 1:
            raise InputError(
                "channels have different rates; select channels of one rate",
                path=self.path,
                field="rate_hz",
                value=rates,
            )
        n = min(c.values.shape[0] for c in chans)
        data = np.column_stack([c.values[:n] for c in chans])
        units = [c.unit for c in chans]
        if to_volts:
            for j, c in enumerate(chans):
                factor = _TO_VOLTS.get(c.unit.strip().lower())
                if c.is_emg and factor is not None:
                    data[:, j] *= factor
                    units[j] = "V"
        return AnalogRecording(
            time=chans[0].time[:n].copy(),
            labels=[f"{c.sensor}: {c.name}" for c in chans],
            data=data,
            rate_hz=chans[0].rate_hz,
            units=units,
            header=dict(self.header),
            path=self.path,
        )


def _rows(path: Path) -> list[list[str]]:
    try:
        with path.open(newline="", encoding="utf-8-sig", errors="replace") as fh:
            return [[c.strip() for c in row] for row in csv.reader(fh)]
    except OSError as exc:
        raise InputError(f"cannot read Delsys export: {exc.strerror}", path=path) from exc


def _column(rows: list[list[str]], first: int, j: int, path: Path, label: str) -> np.ndarray:
    """Numeric column ``j`` from row ``first`` on, stopping at its first empty cell (the channel ended)."""
    out: list[float] = []
    for i in range(first, len(rows)):
        row = rows[i]
        cell = row[j] if j < len(row) else ""
        if cell == "":
            break
        try:
            out.append(float(cell))
        except ValueError:
            raise FileFormatError("not a number", path=path, line=i + 1, field=label, value=cell) from None
    return np.array(out)


def _rate_from_time(t: np.ndarray, path: Path, label: str) -> float:
    if t.shape[0] < 2:
        raise FileFormatError("fewer than two samples: no rate", path=path, field=label)
    dt = float(np.median(np.diff(t)))
    if not dt > 0:
        raise FileFormatError("time column does not increase", path=path, field=label)
    return 1.0 / dt


def read_emgworks_csv(path: str | Path) -> DelsysExport:
    """Read an EMGworks CSV export (time column before every channel)."""
    path = Path(path)
    rows = _rows(path)
    head = next((i for i, r in enumerate(rows) if r and r[0].upper().startswith("X[")), None)
    if head is None:
        raise FileFormatError("no label row starting with 'X[s]': not an EMGworks export", path=path)
    labels = rows[head]
    while labels and labels[-1] == "":
        labels = labels[:-1]
    if len(labels) % 2:
        raise FileFormatError("labels must come in (X[s], channel) pairs", path=path, line=head + 1)
    channels = []
    for j in range(0, len(labels), 2):
        if not labels[j].upper().startswith("X["):
            raise FileFormatError("expected a time column 'X[s]'", path=path, line=head + 1, field=labels[j])
        label = labels[j + 1]
        sensor, _, name = label.rpartition(":")
        t = _column(rows, head + 1, j, path, f"{labels[j]} of {label}")
        v = _column(rows, head + 1, j + 1, path, label)
        if t.shape != v.shape:
            raise FileFormatError(f"{t.shape[0]} times for {v.shape[0]} values", path=path, field=label)
        name = name.strip() or label
        unit = "V" if name.upper().startswith("EMG") else ""
        channels.append(DelsysChannel(sensor.strip(), name, unit, _rate_from_time(t, path, label), t, v))
    header = {"preamble": " | ".join(",".join(r) for r in rows[:head] if any(r))} if head else {}
    return DelsysExport(application="EMGworks", channels=channels, header=header, path=path)


def read_trigno_discover_csv(path: str | Path) -> DelsysExport:
    """Read a Trigno Discover CSV export (multi-row header, time column before every channel)."""
    path = Path(path)
    rows = _rows(path)
    header: dict[str, str] = {}
    i = 0
    while i < len(rows) and rows[i] and rows[i][0].endswith(":"):
        header[rows[i][0][:-1]] = rows[i][1] if len(rows[i]) > 1 else ""
        i += 1
    if "Application" not in header:
        raise FileFormatError("no 'Application:' row: not a Trigno Discover export", path=path, line=1)
    sensor_row, mode_row, name_row = i, i + 1, i + 2
    rate_row = i + 3
    if rate_row >= len(rows) or not any(_RATE.match(c) for c in rows[rate_row]):
        raise FileFormatError("expected the rate row ('... Hz') 4 rows after the header", path=path, line=rate_row + 1)
    if not any(c.lower().startswith("sensor mode") for c in rows[mode_row]):
        raise FileFormatError("expected the 'sensor mode:' row", path=path, line=mode_row + 1)
    first = rate_row + 1
    if first < len(rows) and any(re.match(r"^[0-9.eE+-]+\s*s$", c) for c in rows[first]):
        first += 1  # optional sample-period row
    while first < len(rows) and not any(rows[first]):
        first += 1
    names = rows[name_row]
    sensors = rows[sensor_row]
    channels = []
    current_sensor = ""
    for j, label in enumerate(names):
        if j < len(sensors) and sensors[j]:
            current_sensor = sensors[j]
        if not label or "time series" in label.lower() or j == 0:
            continue
        m = _UNIT.match(label)
        name, unit = (m.group(1), m.group(2)) if m else (label, "")
        rate_cell = rows[rate_row][j] if j < len(rows[rate_row]) else ""
        rm = _RATE.match(rate_cell)
        if not rm:
            raise FileFormatError(
                "no rate for this channel", path=path, line=rate_row + 1, field=label, value=rate_cell
            )
        if "time series" not in names[j - 1].lower():
            raise FileFormatError("channel without its time column", path=path, line=name_row + 1, field=label)
        t = _column(rows, first, j - 1, path, names[j - 1])
        v = _column(rows, first, j, path, label)
        if t.shape != v.shape:
            raise FileFormatError(f"{t.shape[0]} times for {v.shape[0]} values", path=path, field=label)
        channels.append(DelsysChannel(current_sensor, name, unit, float(rm.group(1)), t, v))
    if not channels:
        raise FileFormatError("no channel columns found", path=path, line=name_row + 1)
    return DelsysExport(application=header["Application"], channels=channels, header=header, path=path)


def read_delsys_csv(path: str | Path) -> DelsysExport:
    """Either export, recognised by its first non-empty line."""
    path = Path(path)
    rows = _rows(path)
    first = next((r for r in rows if any(r)), [])
    if first and first[0].startswith("Application"):
        return read_trigno_discover_csv(path)
    return read_emgworks_csv(path)
