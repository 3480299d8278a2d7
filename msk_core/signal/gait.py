"""Gait events and the gait-cycle phase: a walk's repetitions are its gait cycles, heel strike to heel strike.

Heel strikes come from the vertical ground reaction force of one foot (a force plate or an instrumented treadmill,
e.g. OpenSim's ``ground_force_vy`` column of an external-loads ``.mot``): the instants it rises through a small
threshold after the foot was off the ground for a while. The gait-cycle phase is the time through each cycle in
[0, 1), the convention of :func:`msk_core.signal.reps.rep_phase` (``REST_PHASE`` / rep index -1 before the first and
after the last heel strike).
"""

from __future__ import annotations

import numpy as np

from msk_core.errors import ConfigError, InputError
from msk_core.signal.reps import REST_PHASE

CONTACT_THRESHOLD_N = 20.0  # vertical force above which the foot is on the ground (force-plate noise is a few N)
MIN_SWING_S = 0.1  # off the ground at least this long before a heel strike counts: longer than a force-plate
# flicker around the threshold (a few samples), shorter than any swing (a walking swing lasts ~0.4 s)


def heel_strikes(
    time: np.ndarray,
    vertical_force: np.ndarray,
    *,
    threshold_n: float = CONTACT_THRESHOLD_N,
    min_swing_s: float = MIN_SWING_S,
) -> np.ndarray:
    """Times (s) at which the foot lands: the force rises through ``threshold_n`` (interpolated between samples)
    after at least ``min_swing_s`` below it. Flickers around the threshold inside a stance or a swing do not count."""
    t = np.asarray(time, dtype=float)
    f = np.asarray(vertical_force, dtype=float)
    if t.ndim != 1 or t.shape != f.shape or t.size < 3:
        raise InputError(
            f"time and vertical force must be 1-D arrays of the same length >= 3, got {t.shape} and {f.shape}",
            field="vertical_force",
        )
    if not np.all(np.isfinite(t)) or not np.all(np.diff(t) > 0):
        raise InputError("time must be finite and increasing", field="time")
    if not np.all(np.isfinite(f)):
        bad = int(np.flatnonzero(~np.isfinite(f))[0])
        raise InputError(f"vertical force is not finite at t = {t[bad]:g} s", field="vertical_force", value=f[bad])
    if not threshold_n > 0 or not min_swing_s >= 0:
        raise ConfigError(
            "need threshold_n > 0 and min_swing_s >= 0", field="threshold_n", value=(threshold_n, min_swing_s)
        )
    contact = f > threshold_n
    rises = np.flatnonzero(contact[1:] & ~contact[:-1]) + 1
    falls = np.flatnonzero(~contact[1:] & contact[:-1]) + 1
    strikes = []
    for i in rises:
        before = falls[falls < i]
        # the foot left the ground at the last fall before this rise (or it was off from the start)
        left_at = t[before[-1]] if before.size else (t[0] if not contact[0] else np.nan)
        if np.isnan(left_at) or t[i] - left_at < min_swing_s:
            continue
        # linear interpolation of the threshold crossing between samples i-1 and i
        w = (threshold_n - f[i - 1]) / (f[i] - f[i - 1])
        strikes.append(t[i - 1] + w * (t[i] - t[i - 1]))
    return np.asarray(strikes)


def gait_cycle_phase(time: np.ndarray, strikes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phase, cycle index) per sample: cycle k runs from heel strike k to k+1, phase = time through it in [0, 1).
    Samples before the first or after the last heel strike get ``REST_PHASE`` and index -1 (no complete cycle)."""
    t = np.asarray(time, dtype=float)
    hs = np.asarray(strikes, dtype=float)
    if hs.ndim != 1 or hs.size < 2 or not np.all(np.diff(hs) > 0):
        raise InputError(f"need at least 2 increasing heel-strike times, got {hs.size}", field="strikes")
    k = np.searchsorted(hs, t, side="right") - 1
    inside = (k >= 0) & (k < hs.size - 1)
    phase = np.full(t.shape, REST_PHASE)
    index = np.full(t.shape, -1, dtype=int)
    kk = k[inside]
    phase[inside] = (t[inside] - hs[kk]) / (hs[kk + 1] - hs[kk])
    index[inside] = kk
    return phase, index
