"""One world for the simulators: the trial clock the Trigno and Xsens simulators of a session sample together.

Physical devices sample one world: whenever one starts, it measures what happens at that instant. A
:class:`TrialClock` is that world's time: the trial's sample 0 is measured at :attr:`TrialClock.start` (a
``time.monotonic()`` instant), its sample k of a stream at rate r at ``start + k / (r * speed)``. A simulator given
the clock that starts streaming at wall time t streams the trial from the first sample at or after t
(:meth:`TrialClock.first_index`), whatever the other devices did; its own clock and counters stay its own. A clock
made without a start begins when the first simulator starts streaming (the set begins as the first device is
switched on). Docs: docs/devices.md ("Simulators on one trial clock").
"""

from __future__ import annotations

import math
import threading

from msk_core.errors import ConfigError


class TrialClock:
    """The shared start instant of a session's simulated trial; thread-safe (simulators start from their own
    threads)."""

    def __init__(self, start: float | None = None) -> None:
        if start is not None and not math.isfinite(start):
            raise ConfigError("must be a time.monotonic() instant", field="start", value=start)
        self._start = start
        self._lock = threading.Lock()

    @property
    def start(self) -> float | None:
        """``time.monotonic()`` at which the trial's sample 0 is measured; None until a simulator starts streaming
        when the clock was made without one."""
        return self._start

    def origin(self, now: float) -> float:
        """The trial's start, fixed at ``now`` by the first caller when the clock was made without one."""
        with self._lock:
            if self._start is None:
                self._start = now
            return self._start

    def first_index(self, now: float, rate_hz: float, speed: float = 1.0) -> int:
        """Index, on the trial's sample grid at ``rate_hz``, of the first sample measured at or after ``now`` (wall
        time, ``time.monotonic()``; ``speed`` > 1: the trial runs faster than real time). Never before sample 0."""
        origin = self.origin(now)
        return max(0, math.ceil((now - origin) * speed * rate_hz - 1e-6))

    def instant(self, index: int, rate_hz: float, speed: float = 1.0) -> float:
        """Wall time (``time.monotonic()``) at which sample ``index`` of the grid at ``rate_hz`` is measured."""
        if self._start is None:
            raise ConfigError("the trial clock has not started: no simulator has started streaming", field="start")
        return self._start + index / (rate_hz * speed)
