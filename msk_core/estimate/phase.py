"""Offline repetition detection and phase (minimal version used by calibration and evaluation).

A repetition is an excursion of a kinematic signal (e.g. trunk tilt in a lift, elbow angle on the bench) away from its
rest level. Rest = median of the signal's first and last 0.5 s; the excursion direction is that of the largest
deviation. A rep is where the deviation exceeds ``enter`` x the 98th-percentile deviation, widened to where it falls
back below ``leave`` x that; reps shorter than ``min_duration_s`` are dropped. Phase = time through the rep in [0, 1].
This is offline (it looks at the whole trial); the live phase comes from the signal chain's causal rep tracker.
"""

from __future__ import annotations

import numpy as np

from msk_core.errors import EstimationError


def detect_reps(
    time: np.ndarray,
    signal: np.ndarray,
    *,
    enter: float = 0.5,
    leave: float = 0.15,
    min_duration_s: float = 0.5,
    rest_window_s: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """(phase, rep_index) per sample; samples outside any rep get phase NaN and rep_index -1."""
    time = np.asarray(time, dtype=float)
    x = np.asarray(signal, dtype=float)
    if time.shape != x.shape or x.size < 3 or not np.all(np.isfinite(x)):
        raise EstimationError("rep detection needs a finite signal with at least 3 samples, aligned with time")
    edge = (time - time[0] <= rest_window_s) | (time[-1] - time <= rest_window_s)
    direction = np.sign(np.median(x) - np.median(x[edge])) or 1.0
    dev = direction * x
    dev = dev - np.percentile(dev, 2)  # rest level = the most rest-like values (robust minimum)
    scale = float(np.percentile(dev, 98))
    if scale <= 0:
        raise EstimationError("signal never leaves its rest level: no repetition to detect")
    runs = _runs(dev > enter * scale)
    quiet = dev <= leave * scale
    phase = np.full(x.shape, np.nan)
    rep_index = np.full(x.shape, -1, dtype=int)
    k = 0
    prev_end = 0
    for j, (r0, r1) in enumerate(runs):
        nxt = runs[j + 1][0] if j + 1 < len(runs) else x.size
        q_before = np.flatnonzero(quiet[prev_end:r0])
        start = prev_end + q_before[-1] if q_before.size else prev_end + int(np.argmin(dev[prev_end : r0 + 1]))
        q_after = np.flatnonzero(quiet[r1:nxt])
        if q_after.size:
            end = r1 + int(q_after[0])
        elif r1 < nxt:
            end = r1 + int(np.argmin(dev[r1:nxt]))
        else:  # the excursion lasts to the end of the recording
            end = x.size - 1
        prev_end = end
        if time[end] - time[start] < min_duration_s:
            continue
        phase[start : end + 1] = (time[start : end + 1] - time[start]) / (time[end] - time[start])
        rep_index[start : end + 1] = k
        k += 1
    if k == 0:
        raise EstimationError("no repetition found in the phase signal")
    return phase, rep_index


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) index pairs of the True runs of a boolean array."""
    d = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))
