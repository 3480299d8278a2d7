"""Repetition kinematics: minimum-jerk moves between a top and a bottom pose with realistic, varying tempo.

A trial is rest at the top pose, ``n_reps`` cycles of (eccentric down, pause at the bottom, concentric up, pause at the
top) and rest again. Every move is a minimum-jerk profile s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ on a per-coordinate time warp
τ_w = τ + k τ (1 − τ) (|k| < 1 keeps it monotonic), so joints do not all move in lock-step (in the deadlift the knees
lead the hips off the floor). Velocity and acceleration vanish at every keyframe; q, qd and qdd are exact closed forms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msk_core.signal.reps import REST_PHASE
from msk_core.synth.rng import stream


@dataclass(frozen=True)
class Tempo:
    """Phase durations in seconds (ranges drawn uniformly per repetition)."""

    eccentric_s: tuple[float, float] = (1.5, 2.5)
    bottom_pause_s: tuple[float, float] = (0.1, 0.4)
    concentric_s: tuple[float, float] = (1.0, 1.5)
    top_pause_s: tuple[float, float] = (0.5, 1.0)
    rest_s: float = 1.0  # before the first and after the last repetition


@dataclass(frozen=True)
class Move:
    """One keyframe-to-keyframe segment of a trial."""

    t0: float
    duration: float
    q0: np.ndarray
    q1: np.ndarray
    warp: np.ndarray  # per-coordinate k of the time warp
    rep: int  # repetition index, -1 for rest
    kind: str  # "rest", "eccentric", "bottom", "concentric", "top"


@dataclass(frozen=True)
class RepPlan:
    moves: tuple[Move, ...]
    rep_starts: np.ndarray  # start time of each repetition (top, about to descend)
    rep_ends: np.ndarray
    duration: float


def _min_jerk(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    s = tau**3 * (10 - 15 * tau + 6 * tau**2)
    ds = 30 * tau**2 * (1 - tau) ** 2
    dds = 60 * tau * (1 - tau) * (1 - 2 * tau)
    return s, ds, dds


def plan_reps(
    top: np.ndarray,
    bottom: np.ndarray,
    n_reps: int,
    *,
    seed: int,
    key: tuple,
    tempo: Tempo = Tempo(),
    depth_jitter: float = 0.06,
    warp: np.ndarray | None = None,
    lo: np.ndarray | None = None,
    hi: np.ndarray | None = None,
) -> RepPlan:
    """Draw the timing and depth of ``n_reps`` repetitions (rep-to-rep variability from the ``key`` stream).

    ``depth_jitter``: standard deviation of the bottom pose per repetition, as a fraction of the range of motion."""
    rng = stream(seed, "reps", *key)
    top = np.asarray(top, dtype=float)
    bottom = np.asarray(bottom, dtype=float)
    n = top.shape[0]
    base_warp = np.zeros(n) if warp is None else np.asarray(warp, dtype=float)
    lo = np.full(n, -np.inf) if lo is None else lo
    hi = np.full(n, np.inf) if hi is None else hi
    moves: list[Move] = []
    zero = np.zeros(n)
    t = 0.0
    moves.append(Move(t, tempo.rest_s, top, top, zero, -1, "rest"))
    t += tempo.rest_s
    starts, ends = [], []
    for rep in range(n_reps):
        depth = np.clip(bottom + rng.normal(0.0, 1.0, n) * depth_jitter * np.abs(bottom - top), lo, hi)
        w_down = np.clip(base_warp + rng.normal(0.0, 0.1, n), -0.8, 0.8)
        w_up = np.clip(base_warp + rng.normal(0.0, 0.1, n), -0.8, 0.8)
        ecc = rng.uniform(*tempo.eccentric_s)
        pause_b = rng.uniform(*tempo.bottom_pause_s)
        con = rng.uniform(*tempo.concentric_s)
        pause_t = rng.uniform(*tempo.top_pause_s)
        starts.append(t)
        for dur, q0, q1, w, kind in (
            (ecc, top, depth, -w_down, "eccentric"),
            (pause_b, depth, depth, zero, "bottom"),
            (con, depth, top, w_up, "concentric"),
            (pause_t, top, top, zero, "top"),
        ):
            moves.append(Move(t, dur, q0, q1, w, rep, kind))
            t += dur
        ends.append(t)
    moves.append(Move(t, tempo.rest_s, top, top, zero, -1, "rest"))
    t += tempo.rest_s
    return RepPlan(tuple(moves), np.asarray(starts), np.asarray(ends), t)


def evaluate(plan: RepPlan, time: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """q, qd, qdd (n_samples, n_coordinates), phase in [0, 1) (REST_PHASE outside repetitions) and rep index (−1 at
    rest)."""
    time = np.asarray(time, dtype=float)
    n = plan.moves[0].q0.shape[0]
    q = np.empty((time.size, n))
    qd = np.zeros_like(q)
    qdd = np.zeros_like(q)
    phase = np.full(time.size, REST_PHASE)
    rep_index = np.full(time.size, -1, dtype=np.int64)
    bounds = np.asarray([m.t0 for m in plan.moves])
    which = np.clip(np.searchsorted(bounds, time, side="right") - 1, 0, len(plan.moves) - 1)
    for i, move in enumerate(plan.moves):
        sel = which == i
        if not sel.any():
            continue
        tau = np.clip((time[sel] - move.t0) / move.duration, 0.0, 1.0)[:, None]
        k = move.warp[None, :]
        tw = tau + k * tau * (1 - tau)
        dtw = (1 + k * (1 - 2 * tau)) / move.duration
        ddtw = (-2 * k) / move.duration**2
        s, ds, dds = _min_jerk(tw)
        dq = (move.q1 - move.q0)[None, :]
        q[sel] = move.q0 + dq * s
        qd[sel] = dq * ds * dtw
        qdd[sel] = dq * (dds * dtw**2 + ds * ddtw)
        rep_index[sel] = move.rep
    for a, b in zip(plan.rep_starts, plan.rep_ends):
        sel = (time >= a) & (time < b)
        phase[sel] = (time[sel] - a) / (b - a)
    return q, qd, qdd, phase, rep_index
