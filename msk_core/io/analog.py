"""Multichannel analog recordings (EMG, force plates) and the readers of ``.anc`` and C3D analogs."""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from msk_core.errors import FileFormatError, InputError, close_names
from msk_core.io.storage import float_cells
from msk_core.units import VOLTS_PER_UNIT, volts_per_unit


@dataclass
class AnalogRecording:
    """Channels sampled together: ``data[i, j]`` is channel ``labels[j]`` at ``time[i]`` (seconds)."""

    time: np.ndarray
    labels: list[str]
    data: np.ndarray
    rate_hz: float
    units: list[str]
    header: dict[str, str] = field(default_factory=dict)
    channel_info: dict[str, list[str]] = field(default_factory=dict)  # per-channel header rows, e.g. "Range"
    path: Path | None = None
    # channels the file itself says are not EMG -> why (a force-plate channel, a unit that is not a voltage)
    not_emg: dict[str, str] = field(default_factory=dict)

    def emg_only(self) -> AnalogRecording:
        """The recording without the channels :attr:`not_emg` names (all of them when it is empty)."""
        keep = [lab for lab in self.labels if lab not in self.not_emg]
        if not keep:
            by_reason: dict[str, list[str]] = {}
            for channel, why in self.not_emg.items():
                by_reason.setdefault(why, []).append(channel)
            raise InputError(
                f"no EMG channel: all {len(self.labels)} analog channels are not EMG ("
                + "; ".join(f"{why}: {', '.join(channels)}" for why, channels in by_reason.items())
                + ")",
                path=self.path,
            )
        return self.select(keep)

    def in_volts(self) -> tuple[AnalogRecording, list[str]]:
        """The recording with every channel whose file says how in volts: a unit V, mV or µV, or an ``.anc``'s ADC
        counts through the channel's ``Range`` (mV full scale), the file's ``BitDepth`` and ``Polarity``; and the
        labels of the channels left in their own unit (none given, or not a voltage)."""
        scale = np.ones(len(self.labels))
        units = list(self.units)
        kept = []
        for j, label in enumerate(self.labels):
            factor = self._volts_per_unit(j)
            if factor is None:
                kept.append(label)
            else:
                scale[j], units[j] = factor, "V"
        return replace(self, data=self.data * scale, units=units), kept

    def _volts_per_unit(self, j: int) -> float | None:
        unit = self.units[j]
        if unit != ADC_COUNTS:
            return volts_per_unit(unit) if unit else None
        ranges = self.channel_info.get("Range")
        try:
            full_scale_mv = float(ranges[j]) if ranges else float("nan")
            bits = int(self.header.get("BitDepth", "16"))
        except ValueError:
            return None
        if not (full_scale_mv > 0 and 2 <= bits <= 32):
            return None
        if self.header.get("Polarity", "Bipolar").strip().lower().startswith("uni"):
            return full_scale_mv * 1e-3 / 2**bits  # 0 .. 2^bits counts span 0 .. Range
        return full_scale_mv * 1e-3 / 2 ** (bits - 1)  # a bipolar ADC: +-2^(bits-1) counts span +-Range

    def index(self, label: str) -> int:
        if self.labels.count(label) > 1:  # which of them is meant cannot be said by the name
            columns = [str(k + 1) for k, lab in enumerate(self.labels) if lab == label]
            raise InputError(
                f"{self.labels.count(label)} channels are named {label!r} (analog columns {', '.join(columns)}): "
                "rename them in the file to choose one",
                path=self.path,
                field=label,
            )
        try:
            return self.labels.index(label)
        except ValueError:
            near = close_names(label, self.labels, cutoff=0.5)  # case aside: "sol" finds "SOL"
            emg = [lab for lab in self.labels if lab not in self.not_emg]
            other = f"; not EMG: {', '.join(self.not_emg)}" if self.not_emg else ""
            raise InputError(
                f"no channel {label!r}"
                + (f"; did you mean {', '.join(near)}?" if near else "")
                + f"; EMG channels: {', '.join(emg)}{other}",
                path=self.path,
                field=label,
            ) from None

    def channel(self, label: str) -> np.ndarray:
        return self.data[:, self.index(label)]

    def select(self, labels: list[str]) -> AnalogRecording:
        """A recording with only ``labels``, in that order."""
        idx = [self.index(lab) for lab in labels]
        return AnalogRecording(
            time=self.time,
            labels=list(labels),
            data=np.ascontiguousarray(self.data[:, idx]),
            rate_hz=self.rate_hz,
            units=[self.units[i] for i in idx],
            header=dict(self.header),
            channel_info={k: [v[i] for i in idx] for k, v in self.channel_info.items()},
            path=self.path,
            not_emg={lab: self.not_emg[lab] for lab in labels if lab in self.not_emg},
        )


#: the unit of an ``.anc``'s values (:meth:`AnalogRecording.in_volts` converts them)
ADC_COUNTS = "counts"
# Motion Analysis names a force plate's analog channels F1X, F1Y, F1Z, M1X, M1Y, M1Z (plate 1), ...; an .anc file
# carries no unit or plate table that would say so otherwise
_ANC_FORCE_PLATE_NAME = re.compile(r"^[FM](\d+[XYZ]|[XYZ]\d+)$", re.IGNORECASE)
ANC_FORCE_PLATE = "force-plate channel (F<plate><axis> / M<plate><axis>, the .anc naming)"


def read_anc(path: str | Path) -> AnalogRecording:
    """Read an ``.anc`` file (Motion Analysis "Analog R/C ASCII"): ``key:<tab>value`` header pairs, then ``Name``,
    ``Rate`` and ``Range`` rows, then one row per sample (time then ADC counts). Values stay in ADC counts
    (:meth:`AnalogRecording.in_volts`); the force-plate channels are named in :attr:`AnalogRecording.not_emg`."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    except OSError as exc:
        raise InputError(f"cannot read analog file: {exc.strerror}", path=path) from exc

    header: dict[str, str] = {}
    rows: dict[str, tuple[int, list[str]]] = {}
    first_data = None
    for i, raw in enumerate(lines):
        cells = [c.strip() for c in raw.split("\t")]
        while cells and not cells[-1]:
            cells.pop()
        if not cells:
            continue
        head = cells[0]
        if head in ("Name", "Rate", "Range"):
            rows[head] = (i, cells[1:])
            continue
        if "Name" in rows and "Rate" in rows:
            first_data = i
            break
        # header line: key:, value, key:, value, ...
        for k in range(0, len(cells) - 1, 2):
            if cells[k].endswith(":"):
                header[cells[k][:-1]] = cells[k + 1]
    if "Name" not in rows or "Rate" not in rows:
        raise FileFormatError("missing 'Name' or 'Rate' row: not an .anc file", path=path)
    labels = rows["Name"][1]
    n = len(labels)
    for key, (line_no, cells) in rows.items():
        if len(cells) != n:
            raise FileFormatError(f"{len(cells)} entries for {n} channels", path=path, line=line_no + 1, field=key)
    rates = {float(r) for r in rows["Rate"][1]}
    if len(rates) != 1:
        raise FileFormatError(
            "channels with different rates are not supported",
            path=path,
            line=rows["Rate"][0] + 1,
            field="Rate",
            value=sorted(rates),
        )
    rate = rates.pop()

    table: list[list[float]] = []
    for i in range(first_data if first_data is not None else len(lines), len(lines)):
        cells = [c for c in lines[i].split("\t") if c.strip()]
        if not cells:
            continue
        if len(cells) != n + 1:
            raise FileFormatError(f"expected {n + 1} values, found {len(cells)}", path=path, line=i + 1)
        table.append(float_cells(cells, ["time", *labels], path, i + 1))
    if not table:
        raise FileFormatError("no samples", path=path)
    arr = np.array(table)
    not_emg = {lab: ANC_FORCE_PLATE for lab in labels if _ANC_FORCE_PLATE_NAME.match(lab)}
    info = {"Rate": rows["Rate"][1]}
    if "Range" in rows:
        info["Range"] = rows["Range"][1]
    return AnalogRecording(
        time=arr[:, 0].copy(),
        labels=labels,
        data=np.ascontiguousarray(arr[:, 1:]),
        rate_hz=rate,
        units=[ADC_COUNTS] * n,
        header=header,
        channel_info=info,
        path=path,
        not_emg=not_emg,
    )


# units an EMG channel may carry (ANALOG:UNITS, compared case-insensitively); any other given unit is not EMG
VOLTAGE_UNITS = frozenset(VOLTS_PER_UNIT)


def read_c3d_analogs(path: str | Path) -> AnalogRecording:
    """Analog channels of a C3D file via ezc3d (scaled to physical units by ezc3d: SCALE, OFFSET, GEN_SCALE).

    A gait C3D keeps force plates and EMG in one analog block. The file says which channels are not EMG, and the
    recording's :attr:`AnalogRecording.not_emg` records them: the channels FORCE_PLATFORM:CHANNEL assigns to the
    FORCE_PLATFORM:USED plates (1-based analog channel numbers), and channels whose ANALOG:UNITS entry is given and is
    not a voltage (N, Nmm, g, deg ...). Channels without a unit stay EMG candidates."""
    import ezc3d  # local import: only this reader needs it

    path = Path(path)
    if not path.is_file():
        raise InputError("no such C3D file", path=path)
    try:
        c3d = ezc3d.c3d(str(path))
    except Exception as exc:  # ezc3d raises bare RuntimeError/IOError with a message
        raise FileFormatError(f"ezc3d cannot read it: {exc}", path=path) from exc
    params = c3d["parameters"]["ANALOG"]
    labels = [str(s).strip() for s in params["LABELS"]["value"]]
    analogs = np.asarray(c3d["data"]["analogs"])[0].T  # (n_samples, n_channels)
    rate = float(c3d["header"]["analogs"]["frame_rate"])
    if analogs.shape[1] != len(labels):
        raise FileFormatError(f"{len(labels)} labels for {analogs.shape[1]} channels", path=path, field="ANALOG:LABELS")
    units = [str(u).strip() for u in params["UNITS"]["value"]] if "UNITS" in params else [""] * len(labels)
    if len(units) < len(labels):  # a short UNITS list leaves the last channels without a unit
        units += [""] * (len(labels) - len(units))
    point_rate = float(c3d["header"]["points"]["frame_rate"]) or rate
    t0 = float(c3d["header"]["points"]["first_frame"]) / point_rate
    time = t0 + np.arange(analogs.shape[0]) / rate
    not_emg = _force_plate_channels(c3d["parameters"], labels, path)
    for label, unit in zip(labels, units):
        if label not in not_emg and unit and unit.lower() not in VOLTAGE_UNITS:
            not_emg[label] = f"unit {unit!r} is not a voltage (ANALOG:UNITS)"
    return AnalogRecording(
        time=time,
        labels=labels,
        data=np.ascontiguousarray(analogs, dtype=float),
        rate_hz=rate,
        units=units[: len(labels)],
        header={"point_rate": str(point_rate)},
        path=path,
        not_emg=not_emg,
    )


def _force_plate_channels(parameters, labels: list[str], path: Path) -> dict[str, str]:
    """Analog channels of the used force plates (FORCE_PLATFORM:CHANNEL, one column of 1-based channel numbers
    per plate, the first FORCE_PLATFORM:USED columns) -> 'force plate k (FORCE_PLATFORM:CHANNEL)'."""
    if "FORCE_PLATFORM" not in parameters:
        return {}
    group = parameters["FORCE_PLATFORM"]
    used_raw = np.asarray(group["USED"]["value"]).reshape(-1) if "USED" in group else np.zeros(0)
    used = int(used_raw[0]) if used_raw.size else 0
    if used <= 0:
        return {}
    if "CHANNEL" not in group:
        raise FileFormatError(
            f"FORCE_PLATFORM:USED is {used} but there is no FORCE_PLATFORM:CHANNEL",
            path=path,
            field="FORCE_PLATFORM:CHANNEL",
        )
    channels = np.asarray(group["CHANNEL"]["value"], dtype=float)
    if channels.ndim == 1:
        channels = channels[:, None]
    if channels.shape[1] < used or not np.all(channels == np.round(channels)):
        raise FileFormatError(
            f"expected integer channel numbers for {used} plates, got shape {channels.shape}",
            path=path,
            field="FORCE_PLATFORM:CHANNEL",
            value=channels.tolist(),
        )
    found: dict[str, str] = {}
    for plate in range(used):
        for number in channels[:, plate].astype(int).tolist():
            if number == 0:  # unassigned slot (plates of a type with fewer channels)
                continue
            if not 1 <= number <= len(labels):
                raise FileFormatError(
                    f"force plate {plate + 1} names analog channel {number}, but there are {len(labels)} channels",
                    path=path,
                    field="FORCE_PLATFORM:CHANNEL",
                    value=number,
                )
            found[labels[number - 1]] = f"force plate {plate + 1} (FORCE_PLATFORM:CHANNEL)"
    return found
