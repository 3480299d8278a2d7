"""A device clock mapped onto the host clock by the host's receipt times, measured over a sliding window.

A device stamps its samples on its own clock (the Trigno counts samples from START, an MTi counts SampleTimeFine from
its power-up); the host stamps the moment their bytes arrive (``host_time_ns``, CLOCK_REALTIME). A sample measured at
host instant T with device time d arrives at T + delivery, so ``receipt - d`` is the clock offset plus that sample's
delivery delay. The mapping of one stream, :class:`HostClock`:

    host instant measured = device time + offset,   offset = min over the window (receipt - device time) - latency

The fastest delivery in the window bounds the offset from above; the device's stated ``latency`` (the part of the
delivery no sample escapes: a Trigno base's buffering, a USB link's polling) is taken off, so that what is left is
the host instant the sample was measured at, up to the fastest delivery's excess over the stated latency. The window
(default :data:`WINDOW_S`, by receipt time) lets the mapping follow a device clock that drifts against the host's
(tens of ppm: ms per minute) and recover, within the window, from a host clock that steps; a minimum over all time
keeps an offset that no longer holds. A device clock that restarts (a power-cycled tracker, a Trigno's new
acquisition, an MVN stream started again: its time back by more than :data:`RESTART_BACK_S`) starts the window anew
at once: the old clock's samples would hold the offset of a clock that is gone for a whole window. A route that
becomes slower for good (a busier hub) reads as a longer latency: the mapping moves by as much, as with a wrong
stated latency.

How sure: the spread of ``receipt - device time`` over the window (95th percentile minus minimum) says how much the
delivery varies; a stream whose every sample is delivered equally late has spread 0 and its mapping is as good as
its stated latency. :meth:`HostClock.report` gives offset, spread, latency and method as a :class:`ClockReport`.

A stream of samples sent in blocks (a Trigno frame of 27 samples) must feed the mapping with each block's *last*
sample: the block leaves when that one is measured, its first sample a block earlier.

:func:`windowed_offsets` is the same mapping over a whole recording at once (non-decreasing receipt times, as one
device's are): the streaming mapping after each sample equals it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from msk_core.errors import ConfigError

WINDOW_S = 5.0  # long enough to hold a fast delivery every few seconds, short enough to follow drift (ms per minute)
#: A device time this far behind the stream's newest is its clock counting again (a device never goes back; samples
#: of one stream arrive in order, give or take a reordered datagram's milliseconds)
RESTART_BACK_S = 1.0
SPREAD_PERCENTILE = 95.0


def counts_again(newest_device_ns: int | None, device_ns: int) -> bool:
    """Whether a sample at ``device_ns`` is its device clock counting again: more than :data:`RESTART_BACK_S`
    behind the stream's newest time (None: the stream's first sample)."""
    return newest_device_ns is not None and device_ns < newest_device_ns - RESTART_BACK_S * 1e9


def newest_device_time(newest_device_ns: int | None, device_ns: int) -> int:
    """A stream's newest device time after a sample at ``device_ns`` (``newest_device_ns`` None: the clock began
    again, or this is the first sample)."""
    return int(device_ns) if newest_device_ns is None else max(newest_device_ns, int(device_ns))


METHOD_ARRIVAL = "arrival"  # offset from the host's receipt times (this module)
METHOD_DEVICE = "device"  # the streams share one clock: no mapping (recordings, synthetic sessions)
METHOD_HOST = "host"  # the stream's times are on the host clock already (a node upstream mapped them)


@dataclass(frozen=True)
class ClockReport:
    """What the mapping of one stream applies: ``offset_ns`` (device time + offset = host instant measured),
    ``spread_ns`` (how sure, see the module docstring), the stated ``latency_ns`` taken off, the ``method`` that
    gave the offset and how many samples the window holds (0: from outside the window, e.g. another method)."""

    source: str
    offset_ns: int
    spread_ns: int
    latency_ns: int
    method: str
    samples: int = 0
    #: with an offset measured another way (e.g. "acceleration"): the arrival mapping's offset at the same moment,
    #: which it replaces (arrival minus applied: how much later the arrival mapping would put every sample)
    arrival_offset_ns: int | None = None
    reason: str = ""  # why this method (e.g. why no other way has an offset yet)
    #: how the stream's clock was measured against other device clocks
    #: (msk_core.estimate.clock_alignment.Alignment, one per tracker)
    alignments: tuple = ()


def check_latency_ns(latency_ns: int, field: str = "latency") -> int:
    """A stated device latency: a whole number of ns in [0, 1 s]; else :class:`ConfigError` naming ``field``."""
    if isinstance(latency_ns, bool) or not isinstance(latency_ns, (int, np.integer)) or not 0 <= latency_ns <= 10**9:
        raise ConfigError(
            "a device latency must be a whole number of ns within 0..1e9 (0..1000 ms)", field=field, value=latency_ns
        )
    return int(latency_ns)


def latency_ns_from_ms(ms, field: str) -> int:
    """A latency stated in milliseconds (a number within 0..1000) in ns; else :class:`ConfigError` naming ``field``."""
    if (
        isinstance(ms, bool)
        or not isinstance(ms, (int, float, np.integer, np.floating))
        or not (np.isfinite(ms) and 0 <= ms <= 1000)
    ):
        raise ConfigError("a device latency is a number of milliseconds within 0..1000", field=field, value=ms)
    return int(round(float(ms) * 1e6))


def parse_latencies(items: list[str], field: str) -> tuple[dict[str, int], int]:
    """Command-line ``[NAME=]MS`` items -> ({name: latency in ns}, the latency of every name not given, ns; 0 when
    no item gives it); a :class:`ConfigError` naming ``field`` and the item otherwise."""
    named: dict[str, int] = {}
    default = 0
    for item in items:
        name, sep, value = item.rpartition("=")
        try:
            ms = float(value)
        except ValueError:
            raise ConfigError("expected [NAME=]MS, a latency in milliseconds", field=field, value=item) from None
        if sep and not name:
            raise ConfigError("expected [NAME=]MS: the name is empty", field=field, value=item)
        latency = latency_ns_from_ms(ms, f"{field} {item}")
        if sep:
            named[name] = latency
        else:
            default = latency
    return named, default


def latency_argv(flag: str, named_ns: dict[str, int] | None, default_ns: int) -> list[str]:
    """The inverse of :func:`parse_latencies`: latencies in ns as ``flag [NAME=]MS`` items (15 significant digits,
    so that they read back to the same ns), the default one only when it is not 0."""
    items = [f"{name}={ns / 1e6:.15g}" for name, ns in (named_ns or {}).items()]
    items += [f"{default_ns / 1e6:.15g}"] if default_ns else []
    return [a for item in items for a in (flag, item)]


class HostClock:
    """The sliding-window host mapping of one stream (explicit state: the window's samples and their minimum)."""

    def __init__(self, source: str, *, latency_ns: int = 0, window_s: float = WINDOW_S) -> None:
        if not (np.isfinite(window_s) and window_s > 0):
            raise ConfigError("the clock window must be a positive number of seconds", field="window_s", value=window_s)
        self.source = source
        self.latency_ns = check_latency_ns(latency_ns, f"latency of {source}")
        self.window_ns = int(round(window_s * 1e9))
        self._window: deque[tuple[int, int]] = deque()  # (receipt, receipt - device time), in receipt order
        self._minimum: deque[tuple[int, int]] = deque()  # increasing delays: the window's minimum first
        self._newest_ns: int | None = None
        self._newest_device_ns: int | None = None
        self.restarts = 0  # times the device clock counted again (:data:`RESTART_BACK_S`)

    def add(self, device_ns: int, receipt_ns: int) -> None:
        """One sample (a block's last one) with device time ``device_ns`` received by the host at ``receipt_ns``."""
        receipt_ns, delay = int(receipt_ns), int(receipt_ns) - int(device_ns)
        if counts_again(self._newest_device_ns, device_ns):
            self.restarts += 1  # the window's offsets belong to the clock that was
            self._window.clear()
            self._minimum.clear()
            self._newest_device_ns = None
        self._newest_device_ns = newest_device_time(self._newest_device_ns, device_ns)
        self._newest_ns = receipt_ns if self._newest_ns is None else max(self._newest_ns, receipt_ns)
        self._window.append((receipt_ns, delay))
        while self._minimum and self._minimum[-1][1] >= delay:
            self._minimum.pop()
        self._minimum.append((receipt_ns, delay))
        oldest = self._newest_ns - self.window_ns
        while self._window[0][0] < oldest:
            self._window.popleft()
        while self._minimum[0][0] < oldest:
            self._minimum.popleft()

    @property
    def offset_ns(self) -> int | None:
        """Device time + this = the host instant the sample was measured; None before the first sample."""
        if not self._minimum:
            return None
        return self._minimum[0][1] - self.latency_ns

    def spread_ns(self) -> int:
        """95th percentile minus minimum of (receipt - device time) over the window (0 before any sample)."""
        if not self._window:
            return 0
        delays = np.fromiter((d for _, d in self._window), dtype=np.int64, count=len(self._window))
        return int(round(np.percentile(delays, SPREAD_PERCENTILE) - delays.min()))

    def report(self) -> ClockReport | None:
        offset = self.offset_ns
        if offset is None:
            return None
        return ClockReport(self.source, offset, self.spread_ns(), self.latency_ns, METHOD_ARRIVAL, len(self._window))


class DeviceClocks:
    """The host mappings of streams that each run on their own device clock (one MTi per tracker): a
    :class:`HostClock` per stream, made on its first sample with its stated latency (``latency_ns`` by name, else
    ``default_latency_ns``). The kinematics node maps its trackers with it and the estimator the same trackers again,
    from the same samples, to the same host instants. ``prefix``: the streams' names in reports (``imu`` ->
    ``imu/<name>``)."""

    def __init__(
        self,
        prefix: str,
        *,
        latency_ns: dict[str, int] | None = None,
        default_latency_ns: int = 0,
        window_s: float = WINDOW_S,
    ) -> None:
        self.prefix = prefix
        self.latency_ns = {
            name: check_latency_ns(value, f"latency of {prefix}/{name}") for name, value in (latency_ns or {}).items()
        }
        self.default_latency_ns = check_latency_ns(default_latency_ns, f"default latency of {prefix}")
        self.window_s = window_s
        self.clocks: dict[str, HostClock] = {}

    def to_host(self, name: str, device_ns: int, receipt_ns: int) -> int:
        """Add stream ``name``'s sample (device time, host receipt time) to its mapping; the host instant it was
        measured at, by the mapping after it."""
        clock = self.clocks.get(name)
        if clock is None:
            clock = self.clocks[name] = HostClock(
                f"{self.prefix}/{name}",
                window_s=self.window_s,
                latency_ns=self.latency_ns.get(name, self.default_latency_ns),
            )
        clock.add(device_ns, receipt_ns)
        offset = clock.offset_ns
        assert offset is not None  # a clock with a sample has an offset
        return int(device_ns) + offset

    def offset_ns(self, name: str) -> int | None:
        """Stream ``name``'s current offset (device time + this = host instant measured); None before its first
        sample."""
        clock = self.clocks.get(name)
        return None if clock is None else clock.offset_ns

    def reports(self) -> list[ClockReport]:
        return [r for r in (c.report() for c in self.clocks.values()) if r is not None]


def windowed_offsets(device_ns, receipt_ns, *, latency_ns: int = 0, window_s: float = WINDOW_S) -> np.ndarray:
    """:class:`HostClock`'s offset after each sample of a whole stream at once (receipt times non-decreasing): per
    sample i, the smallest (receipt - device time) of the samples j <= i received no more than the window before it
    and since the device clock last counted again (:data:`RESTART_BACK_S`), minus the latency."""
    device = np.asarray(device_ns, dtype=np.int64)
    receipt = np.asarray(receipt_ns, dtype=np.int64)
    if device.shape != receipt.shape or device.ndim != 1:
        raise ConfigError(
            "device and receipt times must be two 1-d arrays of one length",
            field="receipt_ns",
            value=(device.shape, receipt.shape),
        )
    if np.any(np.diff(receipt) < 0):
        raise ConfigError(
            "receipt times must not decrease (one device's samples, in the order they came)", field="receipt_ns"
        )
    latency_ns = check_latency_ns(latency_ns)
    delay = receipt - device
    first = np.maximum(
        np.searchsorted(receipt, receipt - int(round(window_s * 1e9)), side="left"), _clock_starts(device)
    )
    # range minimum over [first[i], i] from a sparse table of minimums over runs of 2^k samples
    table = [delay]
    while 2 ** len(table) <= len(delay):
        half = 2 ** (len(table) - 1)
        table.append(np.minimum(table[-1][:-half], table[-1][half:]))
    index = np.arange(len(delay))
    length = index - first + 1
    level = np.floor(np.log2(np.maximum(length, 1))).astype(int)
    out = np.empty(len(delay), dtype=np.int64)
    for k in np.unique(level):
        rows = level == k
        out[rows] = np.minimum(table[k][first[rows]], table[k][index[rows] - 2**k + 1])
    return out - latency_ns


def _clock_starts(device: np.ndarray) -> np.ndarray:
    """Per sample, the index where its device clock's count began: 0, or the latest sample whose time was more than
    :data:`RESTART_BACK_S` behind the newest before it since the previous such start (:meth:`HostClock.add`)."""
    starts = np.zeros(len(device), dtype=np.int64)
    begin, back_ns = 0, RESTART_BACK_S * 1e9
    while begin < len(device):
        newest_before = np.maximum.accumulate(device[begin:])[:-1]
        restarted = np.flatnonzero(device[begin + 1 :] < newest_before - back_ns)
        if restarted.size == 0:
            starts[begin:] = begin
            break
        nxt = begin + 1 + int(restarted[0])
        starts[begin:nxt] = begin
        begin = nxt
    return starts
