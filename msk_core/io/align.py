"""Put signals recorded at different rates on one time base (e.g. 1000 Hz EMG onto ~15 Hz kinematics).

Times are compared as given (the backmodel-lift files share Unix-epoch seconds); nothing is shifted silently.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msk_core.errors import InputError
from msk_core.io.storage import Storage


def resample_linear(
    time_src: np.ndarray, data_src: np.ndarray, time_dst: np.ndarray, *, max_gap_s: float | None = None
) -> np.ndarray:
    """Linear interpolation of ``data_src`` ``(n, m)`` at ``time_dst``. ``nan`` outside the source span and, when
    ``max_gap_s`` is given, inside source gaps longer than it (dropped samples are not invented)."""
    ts = np.asarray(time_src, dtype=float)
    td = np.asarray(time_dst, dtype=float)
    src = np.asarray(data_src, dtype=float)
    if src.ndim == 1:
        src = src[:, None]
    if ts.shape[0] != src.shape[0]:
        raise InputError("time and data lengths differ", field="time_src", value=(ts.shape[0], src.shape[0]))
    if ts.shape[0] < 2 or np.any(np.diff(ts) <= 0):
        raise InputError("source time must be strictly increasing with at least two samples", field="time_src")
    out = np.empty((td.shape[0], src.shape[1]))
    for j in range(src.shape[1]):
        out[:, j] = np.interp(td, ts, src[:, j], left=np.nan, right=np.nan)
    if max_gap_s is not None:
        k = np.clip(np.searchsorted(ts, td), 1, ts.shape[0] - 1)
        gap = ts[k] - ts[k - 1]
        exact = ts[k - 1] == td
        out[(gap > max_gap_s) & ~exact] = np.nan
    return out


def window_mean(time_src: np.ndarray, data_src: np.ndarray, time_dst: np.ndarray) -> np.ndarray:
    """Mean of the source samples in ``(t[i-1], t[i]]`` for each destination time (anti-aliased downsampling of
    an envelope onto slow kinematics). The first window is as long as the second. ``nan`` for empty windows."""
    ts = np.asarray(time_src, dtype=float)
    td = np.asarray(time_dst, dtype=float)
    src = np.asarray(data_src, dtype=float)
    if src.ndim == 1:
        src = src[:, None]
    if td.shape[0] < 2:
        raise InputError("need at least two destination times", field="time_dst")
    edges = np.concatenate([[td[0] - (td[1] - td[0])], td])
    idx = np.searchsorted(ts, edges, side="right")
    csum = np.vstack([np.zeros((1, src.shape[1])), np.cumsum(src, axis=0)])
    counts = np.diff(idx)
    sums = csum[idx[1:]] - csum[idx[:-1]]
    with np.errstate(invalid="ignore", divide="ignore"):
        out = sums / counts[:, None]
    out[counts == 0] = np.nan
    return out


@dataclass
class AlignedTrial:
    """EMG, kinematics and (optionally) joint moments on the kinematics time base."""

    time: np.ndarray
    emg: np.ndarray  # (n, n_emg) envelopes resampled to ``time``
    emg_columns: list[str]
    ik: Storage  # rows restricted to ``time``
    id: Storage | None = None

    def coordinate(self, name: str) -> np.ndarray:
        return self.ik.column(name)

    def emg_channel(self, name: str) -> np.ndarray:
        try:
            return self.emg[:, self.emg_columns.index(name)]
        except ValueError:
            raise InputError(f"no EMG channel {name!r}; available: {', '.join(self.emg_columns)}", field=name) from None


def _rows(s: Storage, keep: np.ndarray) -> Storage:
    return Storage(
        time=s.time[keep],
        columns=list(s.columns),
        data=s.data[keep],
        in_degrees=s.in_degrees,
        header=dict(s.header),
        name=s.name,
        path=s.path,
    )


def align_to_kinematics(
    emg: Storage,
    ik: Storage,
    id_: Storage | None = None,
    *,
    emg_columns: list[str] | None = None,
    tolerance_s: float = 1e-3,
    max_gap_s: float = 0.05,
) -> AlignedTrial:
    """Resample ``emg`` onto the ``ik`` times inside the span both cover; match ``id_`` rows to ``ik`` rows by
    timestamp (within ``tolerance_s``). Kinematics rows without an EMG value or an ID row are dropped."""
    cols = emg_columns if emg_columns is not None else list(emg.columns)
    values = emg.select(cols)
    keep = (ik.time >= emg.time[0]) & (ik.time <= emg.time[-1])
    id_rows = None
    if id_ is not None:
        j = np.clip(np.searchsorted(id_.time, ik.time), 1, max(id_.n_rows - 1, 1))
        nearest = np.where(np.abs(id_.time[j - 1] - ik.time) <= np.abs(id_.time[j] - ik.time), j - 1, j)
        matched = np.abs(id_.time[nearest] - ik.time) <= tolerance_s
        keep &= matched
        id_rows = nearest[keep]
    t = ik.time[keep]
    if t.shape[0] < 2:
        raise InputError(
            "EMG and kinematics do not overlap in time",
            path=ik.path,
            field="time",
            value=(float(emg.time[0]), float(ik.time[0])),
        )
    res = resample_linear(emg.time, values, t, max_gap_s=max_gap_s)
    ok = np.all(np.isfinite(res), axis=1)
    t, res = t[ok], res[ok]
    ik_kept = _rows(ik, np.flatnonzero(keep)[ok])
    id_kept = None
    if id_ is not None and id_rows is not None:
        id_kept = _rows(id_, id_rows[ok])
    return AlignedTrial(time=t, emg=res, emg_columns=list(cols), ik=ik_kept, id=id_kept)
