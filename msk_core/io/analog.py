"""Multichannel analog recordings (EMG, force plates) and the readers of ``.anc`` and C3D analogs."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msk_core.errors import FileFormatError, InputError


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

    def index(self, label: str) -> int:
        try:
            return self.labels.index(label)
        except ValueError:
            raise InputError(
                f"no channel {label!r}; available: {', '.join(self.labels)}", path=self.path, field=label
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
        )


def read_anc(path: str | Path) -> AnalogRecording:
    """Read an ``.anc`` file (Motion Analysis "Analog R/C ASCII"): ``key:<tab>value`` header pairs, then ``Name``,
    ``Rate`` and ``Range`` rows, then one row per sample (time then ADC counts). Values stay in ADC counts."""
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
        raise FileFormatError("channels with different rates are not supported", path=path,
                              line=rows["Rate"][0] + 1, field="Rate", value=sorted(rates))
    rate = rates.pop()

    table: list[list[float]] = []
    for i in range(first_data if first_data is not None else len(lines), len(lines)):
        cells = [c for c in lines[i].split("\t") if c.strip()]
        if not cells:
            continue
        if len(cells) != n + 1:
            raise FileFormatError(f"expected {n + 1} values, found {len(cells)}", path=path, line=i + 1)
        try:
            table.append([float(c) for c in cells])
        except ValueError:
            for j, c in enumerate(cells):
                try:
                    float(c)
                except ValueError:
                    label = "time" if j == 0 else labels[j - 1]
                    raise FileFormatError("not a number", path=path, line=i + 1, field=label, value=c) from None
    if not table:
        raise FileFormatError("no samples", path=path)
    arr = np.array(table)
    info = {"Rate": rows["Rate"][1]}
    if "Range" in rows:
        info["Range"] = rows["Range"][1]
    return AnalogRecording(
        time=arr[:, 0].copy(),
        labels=labels,
        data=np.ascontiguousarray(arr[:, 1:]),
        rate_hz=rate,
        units=["counts"] * n,
        header=header,
        channel_info=info,
        path=path,
    )


def read_c3d_analogs(path: str | Path) -> AnalogRecording:
    """Analog channels of a C3D file via ezc3d (scaled to physical units by ezc3d: SCALE, OFFSET, GEN_SCALE)."""
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
    units = [str(u) for u in params["UNITS"]["value"]] if "UNITS" in params else [""] * len(labels)
    point_rate = float(c3d["header"]["points"]["frame_rate"]) or rate
    t0 = float(c3d["header"]["points"]["first_frame"]) / point_rate
    time = t0 + np.arange(analogs.shape[0]) / rate
    return AnalogRecording(
        time=time,
        labels=labels,
        data=np.ascontiguousarray(analogs, dtype=float),
        rate_hz=rate,
        units=units,
        header={"point_rate": str(point_rate)},
        path=path,
    )
