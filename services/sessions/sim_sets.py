"""Sets with rests for ``msk live --sim``: the simulated athlete lifts N reps, then rests R seconds, as people lift.

The bundled trial (a static start, three reps, a short return to rest; docs/live.md) is played as it is recorded
for a set: round after round, cut after the set's N-th rep and closed by the trial's own return to rest, so a set's
first N reps are exactly the looped trial. Then the rest: the trial's static start repeated (joint angles held at the
start pose, the EMG of that pose: its rest level). One cycle (set + rest) is spliced from the trial's samples for
every stream (EMG, the sensors' accelerations, each tracker) at cuts on the streams' common sample grid (50 ms for
2000, 100 and 60 Hz), so every simulator loops the same cycle on the one shared trial clock
(:class:`drivers.trial_clock.TrialClock`). :func:`schedule` is the cycle as (trial start, duration) segments: the
trial instant of any moment of the cycle (``services.sessions.live_scoring.SimWorld``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import reduce
from typing import TYPE_CHECKING

import numpy as np

from msk_core.errors import ConfigError, InputError

if TYPE_CHECKING:
    from services.sessions.live import SimSources

#: Reps per set and rest between sets (s) of ``msk live --sim`` unless told: three rounds of the bundled trial
#: (its first 45 s are the trial as recorded), then a rest longer than the default rest detection (20 s).
DEFAULT_REPS = 9
DEFAULT_REST_S = 30.0

Segment = tuple[float, float]  # (trial start, duration) in s


@dataclass(frozen=True)
class SimSets:
    """``reps`` per set, ``rest_s`` between sets; ``reps = 0``: no sets, the trial loops (as before sets)."""

    reps: int = DEFAULT_REPS
    rest_s: float = DEFAULT_REST_S

    def __post_init__(self) -> None:
        if isinstance(self.reps, bool) or not isinstance(self.reps, int) or self.reps < 0:
            raise ConfigError(
                "must be a whole number of reps >= 0 (0: the trial loops, no sets)", field="--sim-reps", value=self.reps
            )
        if not (math.isfinite(self.rest_s) and self.rest_s >= 0):
            raise ConfigError("must be a time >= 0 s", field="--sim-rest", value=self.rest_s)


def grid_s(rates_hz: list[float]) -> float:
    """The streams' common sample grid: the shortest time that is a whole number of samples at every rate."""
    whole = [int(round(r)) for r in rates_hz]
    if any(abs(r - w) > 1e-9 or w <= 0 for r, w in zip(rates_hz, whole)):
        raise InputError("the simulated streams' rates must be whole numbers of Hz to splice sets", value=rates_hz)
    return 1.0 / reduce(math.gcd, whole)


def schedule(sets: SimSets, loop_s: float, rep_ends_s: tuple[float, ...], lead_s: float, grid: float) -> list[Segment]:
    """One cycle, set then rest, as (trial start, duration) segments of the trial (module doc); every boundary on
    ``grid``. ``rep_ends_s``: the end of each of the trial's reps, ``lead_s``: its static start."""
    if not rep_ends_s or lead_s < grid:
        raise InputError(
            "the trial has no reps, or no static start to rest in: it cannot be played as sets",
            value=(rep_ends_s, lead_s),
        )

    def on_grid(t: float) -> float:
        return round(t / grid) * grid

    per_loop = len(rep_ends_s)
    rounds, last = divmod(sets.reps, per_loop)
    segments: list[Segment] = [(0.0, loop_s)] * rounds
    if last:  # the last round cut after its rep, then the trial's own return to rest
        cut, tail = on_grid(rep_ends_s[last - 1]), on_grid(rep_ends_s[-1])
        segments += [(0.0, cut), (tail, loop_s - tail)]
    lead = math.floor(lead_s / grid + 1e-9) * grid
    rest = on_grid(sets.rest_s)
    segments += [(0.0, lead)] * int(rest // lead + 1e-9)
    if rest - lead * int(rest // lead + 1e-9) > grid / 2:
        segments.append((0.0, on_grid(rest - lead * int(rest // lead + 1e-9))))
    return [(a, d) for a, d in segments if d > grid / 2]


def splice(array: np.ndarray, rate_hz: float, segments: list[Segment]) -> np.ndarray:
    """The rows of ``array`` (a stream at ``rate_hz`` from the trial's start) of each segment, in order."""
    parts = []
    for start, duration in segments:
        a = int(round(start * rate_hz))
        b = a + int(round(duration * rate_hz))
        if b > array.shape[0]:
            raise InputError(f"a segment ends after the stream's {array.shape[0]} samples", value=(start, duration))
        parts.append(array[a:b])
    return np.concatenate(parts)


def with_sets(sources: SimSources, sets: SimSets) -> SimSources:
    """``sources`` played as sets with rests (one cycle spliced per stream); unchanged when ``sets.reps`` is 0."""
    if sets.reps == 0:
        return sources
    emg = sources.emg
    rates = (
        [emg.rate_hz]
        + [s.rate_hz for _, s in sources.imu.values()]
        + ([emg.acc_rate_hz] if emg.acc is not None else [])
    )
    loop_s = emg.n_samples / emg.rate_hz
    segments = schedule(sets, loop_s, sources.rep_ends_s, sources.lead_s, grid_s(rates))
    acc = None if emg.acc is None else splice(emg.acc, emg.acc_rate_hz, segments)
    spliced_emg = dataclasses.replace(emg, samples=splice(emg.samples, emg.rate_hz, segments), acc=acc)
    imu = {
        tracker: (
            segment,
            dataclasses.replace(
                source, arrays={name: splice(a, source.rate_hz, segments) for name, a in source.arrays.items()}
            ),
        )
        for tracker, (segment, source) in sources.imu.items()
    }
    return dataclasses.replace(
        sources, emg=spliced_emg, imu=imu, schedule=tuple(segments), sets=sets, trial_loop_s=loop_s
    )
