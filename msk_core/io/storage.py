"""OpenSim ``.sto`` / ``.mot`` storage files: reader and writer.

The reader accepts every dialect found in real files: OpenSim 4 headers (``version=1``, ``nRows``, ``nColumns``,
``inDegrees``), old headers without ``version``, free-text header lines, tab-, comma- (spreadsheet exports with
trailing commas) or space-delimited columns, padded numbers, trailing delimiters, CRLF line ends, NaN and infinity as
MSVC and older C runtimes print them (``-nan(ind)``, ``1.#QNAN``, ``1.#INF``), and SIMM's motion headers
(``datacolumns``/``datarows``/``range``, in degrees as OpenSim reads them unless ``inDegrees`` says otherwise).
``nRows``/``nColumns`` are kept in :attr:`Storage.header` but not trusted: real files disagree with them.

The column-label line is split as OpenSim 4 splits it (``FileAdapter::tokenize``, what ``TimeSeriesTable`` and the
tools read): a run of delimiters is one separator and leading or trailing ones are ignored, so a label line that
indents the first label or separates the labels with two tabs while the rows use one is read; labels are trimmed.
Data rows are split on every delimiter, as OpenSim does: an empty cell inside a row (two tabs) is an error, like
OpenSim's "unexpected number of columns". Where OpenSim reads a file that is still refused here, it is on purpose:
duplicate labels (a column could not be named) and text that is not a number (OpenSim reads it as NaN).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msk_core.errors import FileFormatError, InputError

_KEY_VALUE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_ ]*?)\s*=\s*(.*?)\s*$")
_SIMM_KEY = re.compile(r"^(datacolumns|datarows|range)(\s|$)", re.IGNORECASE)  # SIMM .mot header lines: "datarows 100"
#: an interval this far from the median, as a share of it, is a gap (a lost or doubled sample) and not the rounding of
#: a time column printed to a few decimals (1925.926 Hz at 5 decimals: intervals of 0.00051 and 0.00052 s)
MAX_INTERVAL_DEVIATION = 0.25


def uniform_step(time: np.ndarray) -> float:
    """The mean sample interval of uniformly sampled ``time``; :class:`InputError` saying where it is not (the
    interval furthest from the median, and when it starts): a filter designed for one rate is wrong across a gap."""
    time = np.asarray(time, dtype=float)
    dt = np.diff(time)
    if dt.size == 0:
        raise InputError("needs a uniform sample rate, so at least two samples")
    step = float(np.median(dt))
    worst = int(np.argmax(np.abs(dt - step)))
    if step <= 0 or abs(dt[worst] - step) > MAX_INTERVAL_DEVIATION * step:
        raise InputError(
            f"needs a uniform sample rate: samples {step:g} s apart (median), but {dt[worst]:g} s from t = "
            f"{seconds(time[worst])} s (intervals range {dt.min():g} .. {dt.max():g} s)"
        )
    return float((time[-1] - time[0]) / dt.size)  # the mean: exact for a rounded time column


@dataclass
class Storage:
    """A table of time series: ``data[i, j]`` is column ``columns[j]`` at ``time[i]``."""

    time: np.ndarray
    columns: list[str]
    data: np.ndarray
    in_degrees: bool = False
    header: dict[str, str] = field(default_factory=dict)
    name: str = ""
    path: Path | None = None

    def column(self, name: str) -> np.ndarray:
        """The values of one column (a view), by exact name."""
        try:
            j = self.columns.index(name)
        except ValueError:
            raise InputError(
                f"no column {name!r}; available: {', '.join(self.columns)}", path=self.path, field=name
            ) from None
        return self.data[:, j]

    def has_column(self, name: str) -> bool:
        return name in self.columns

    @property
    def n_rows(self) -> int:
        return int(self.time.shape[0])

    @property
    def rate(self) -> float:
        """Mean sample rate in Hz (``nan`` with fewer than two rows)."""
        if self.n_rows < 2:
            return float("nan")
        return float((self.n_rows - 1) / (self.time[-1] - self.time[0]))

    def check_increasing(self, what: str) -> None:
        """:class:`InputError` naming the file and the first row whose time does not increase (``what``: what the
        file is for, e.g. "kinematics"): interpolation onto another time base would silently mix up its rows."""
        if self.n_rows == 0:
            raise InputError(f"{what} file has a header but no data rows", path=self.path)
        back = np.flatnonzero(np.diff(self.time) <= 0)
        if back.size:
            k = int(back[0]) + 1
            raise InputError(
                f"{what} time must increase: data row {k + 1} has t = {seconds(self.time[k])} s after "
                f"{seconds(self.time[k - 1])} s "
                f"({back.size} such row{'s' if back.size != 1 else ''})",
                path=self.path,
                field="time",
            )

    def select(self, names: list[str]) -> np.ndarray:
        """Columns ``names`` as an ``(n_rows, len(names))`` array."""
        return np.column_stack([self.column(n) for n in names]) if names else np.empty((self.n_rows, 0))


def seconds(t: float) -> str:
    """A time in a message, exact to the microsecond whatever its origin: ``29.268``, and a Unix-epoch time stamp as
    ``1667315600.123456`` rather than ``1.66732e+09``, under which two times a minute apart read the same."""
    return f"{t:.6f}".rstrip("0").rstrip(".")


def _strip_cell(line: str) -> str:
    # Spreadsheet exports pad every header line with the column delimiter.
    return line.strip().rstrip(",\t ").strip()


def _delimiter(column_line: str) -> str | None:
    if "\t" in column_line:
        return "\t"
    if "," in column_line:
        return ","
    return None  # any run of whitespace


def _split(line: str, delimiter: str | None) -> list[str]:
    """A data row's cells: every delimiter separates (trailing ones ignored)."""
    cells = line.split(delimiter) if delimiter else line.split()
    cells = [c.strip() for c in cells]
    while cells and cells[-1] == "":
        cells.pop()
    return cells


def _split_labels(line: str, delimiter: str | None) -> list[str]:
    """The column labels as OpenSim tokenizes them: runs of delimiters are one separator, labels trimmed."""
    return [c for c in _split(line, delimiter) if c]


def _parse_bool(text: str, path: Path, line: int, key: str) -> bool:
    value = text.strip().lower()
    if value in ("yes", "true", "1"):
        return True
    if value in ("no", "false", "0"):
        return False
    raise FileFormatError("expected yes or no", path=path, line=line, field=key, value=text)


def read_sto(path: str | Path) -> Storage:
    """Read an OpenSim ``.sto`` or ``.mot`` file. Errors name the file, line and column."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise InputError(f"cannot read storage file: {exc.strerror}", path=path) from exc
    lines = text.splitlines()
    end = next((i for i, raw in enumerate(lines) if _strip_cell(raw).lower() == "endheader"), None)
    if end is None:
        raise FileFormatError("no 'endheader' line: not an OpenSim storage file", path=path)
    header, name, in_degrees = _read_header(lines[:end], path)
    col_index, delimiter, labels = _read_labels(lines, end, path)
    table = _read_rows(lines, col_index, delimiter, labels, path)
    time = np.ascontiguousarray(table[:, 0])
    bad = np.flatnonzero(~np.isfinite(time))
    if bad.size:
        raise FileFormatError("time is not finite", path=path, field="time", value=float(time[bad[0]]))
    return Storage(
        time=time,
        columns=labels[1:],
        data=np.ascontiguousarray(table[:, 1:]),
        in_degrees=in_degrees,
        header=header,
        name=name,
        path=path,
    )


def _read_header(lines: list[str], path: Path) -> tuple[dict[str, str], str, bool]:
    """(key = value pairs, name: a first line that is not one, inDegrees) of the lines before ``endheader``."""
    header: dict[str, str] = {}
    name = ""
    in_degrees = False
    for i, raw in enumerate(lines):
        cell = _strip_cell(raw)
        if not cell:
            continue
        match = _KEY_VALUE.match(cell)
        if match:
            key, value = match.group(1), match.group(2)
            header[key] = value
            if key.lower() == "indegrees":
                in_degrees = _parse_bool(value, path, i + 1, key)
        elif _SIMM_KEY.match(cell):
            header[cell.split()[0].lower()] = cell.split(maxsplit=1)[1] if len(cell.split()) > 1 else ""
        elif i == 0:
            name = cell
    if not any(k.lower() == "indegrees" for k in header) and {"datacolumns", "datarows"} & set(header):
        in_degrees = True  # SIMM's motion format (datacolumns/datarows/range): angles in degrees, as OpenSim reads it
    return header, name, in_degrees


def _read_labels(lines: list[str], end: int, path: Path) -> tuple[int, str | None, list[str]]:
    """(index of the column-label line, the delimiter, the labels): the first non-empty line after ``endheader``,
    starting with time, no label twice."""
    col_index = next((i for i in range(end + 1, len(lines)) if lines[i].strip(" ,\t")), None)
    if col_index is None:
        raise FileFormatError("no column-label line after 'endheader'", path=path, line=end + 1)
    delimiter = _delimiter(lines[col_index])
    labels = _split_labels(lines[col_index], delimiter)
    if not labels or labels[0].lower() != "time":
        raise FileFormatError(
            "first column must be 'time'",
            path=path,
            line=col_index + 1,
            field="time",
            value=labels[0] if labels else "",
        )
    duplicates = sorted({c for c in labels if labels.count(c) > 1})
    if duplicates:
        raise FileFormatError(f"duplicate column labels {duplicates}", path=path, line=col_index + 1)
    return col_index, delimiter, labels


#: How C runtimes other than glibc's print NaN and infinity (MSVC's printf: "-nan(ind)", older ones "1.#QNAN",
#: "-1.#IND", "1.#INF"): OpenSim's reader, built with them, reads them back; Python's float() does not.
_OTHER_SPELLINGS = {
    **dict.fromkeys(
        ("nan(ind)", "-nan(ind)", "nan(snan)", "-nan(snan)", "1.#qnan", "-1.#qnan", "1.#ind", "-1.#ind"), float("nan")
    ),
    "1.#inf": float("inf"),
    "-1.#inf": float("-inf"),
}


def float_cells(cells: list[str], labels: list[str], path: Path, line: int) -> list[float]:
    """One row of a text table as numbers; a cell that is not a number is a FileFormatError naming the file, the
    line and the cell's column (``labels[j]`` for ``cells[j]``)."""
    try:
        return [float(c) for c in cells]
    except ValueError:
        values = []
        for label, cell in zip(labels, cells, strict=False):
            try:
                values.append(float(cell))
            except ValueError:
                spelled = _OTHER_SPELLINGS.get(cell.strip().lower())
                if spelled is None:
                    raise FileFormatError("not a number", path=path, line=line, field=label, value=cell) from None
                values.append(spelled)
        return values


def _read_rows(lines: list[str], col_index: int, delimiter: str | None, labels: list[str], path: Path) -> np.ndarray:
    """The data rows after the label line as a (rows, columns) table; a row with another number of cells or a cell
    that is not a number is an error naming its line (and column)."""
    n_cols = len(labels)
    rows: list[list[float]] = []
    for i in range(col_index + 1, len(lines)):
        raw = lines[i]
        if not raw.strip(" ,\t"):
            continue
        cells = _split(raw, delimiter)
        if len(cells) != n_cols and delimiter == "\t" and "\t" not in raw:
            # labels tab-separated, this row by spaces: OpenSim's Storage (its tools' reader) splits at any
            # whitespace; a row with tabs keeps them as its separators, so an empty cell still counts
            cells = raw.split()
        if len(cells) != n_cols:
            raise FileFormatError(
                f"expected {n_cols} values, found {len(cells)} (one value per column label on line "
                f"{col_index + 1}; an empty cell between two delimiters counts)",
                path=path,
                line=i + 1,
                value=raw[:80],
            )
        rows.append(float_cells(cells, labels, path, i + 1))
    return np.array(rows, dtype=float).reshape(len(rows), n_cols)


def write_sto(
    path: str | Path,
    time: np.ndarray,
    columns: list[str],
    data: np.ndarray,
    *,
    in_degrees: bool = False,
    name: str = "msk-live",
) -> Path:
    """Write an OpenSim 4 ``.sto``/``.mot`` (tab-delimited, lossless float text). Returns the path written."""
    path = Path(path)
    time = np.asarray(time, dtype=float).reshape(-1)
    data = np.asarray(data, dtype=float)
    if data.ndim == 1:
        data = data[:, None]
    if data.shape != (time.shape[0], len(columns)):
        raise InputError(
            f"data shape {data.shape} does not match (len(time), len(columns)) = {(time.shape[0], len(columns))}",
            path=path,
            field="data",
        )
    for c in columns:
        if not c or any(ch in c for ch in "\t\n\r,") or c != c.strip():
            raise InputError(
                "column labels must be non-empty, without tabs, commas or line breaks",
                path=path,
                field="columns",
                value=c,
            )
    if len(set(columns)) != len(columns) or "time" in columns:
        raise InputError("column labels must be unique and not 'time'", path=path, field="columns", value=columns)
    if not np.all(np.isfinite(time)):
        raise InputError("time must be finite", path=path, field="time")
    if "\n" in name or "=" in name or not name.strip():
        raise InputError("name must be one non-empty line without '='", path=path, field="name", value=name)

    head = [
        name.strip(),
        "version=1",
        f"nRows={time.shape[0]}",
        f"nColumns={len(columns) + 1}",
        f"inDegrees={'yes' if in_degrees else 'no'}",
        "endheader",
        "\t".join(["time", *columns]),
    ]
    # repr() is the shortest text that reads back to the same double (Unix-epoch times keep their microseconds).
    body = ["\t".join(map(repr, row)) for row in np.column_stack([time, data]).tolist()]
    path.write_text("\n".join(head + body) + "\n", encoding="utf-8")
    return path
