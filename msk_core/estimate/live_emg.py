"""Live EMG for the estimator: raw chunks -> causal, MVC-normalised envelope per muscle group, aligned to kinematics.

Chain per source (one Trigno base, say), as :mod:`msk_core.signal.emg` defines it and ``msk emg envelope`` runs
offline: band-pass, full-wave rectification, 3rd-order 6 Hz Butterworth low-pass
(:class:`msk_core.signal.emg.EmgEnvelopeFilter`, carried filter state), then division by each channel's MVC amplitude
from the subject profile; channels mapped to the same group are averaged. A channel without an MVC amplitude is left
out and reported (``no_mvc``), never used raw.

Clocks. Every EMG sample has a *device time* from its sample index: ``device_time_ns`` of the chunk's row 0 plus
``row / sample_rate_hz``. A kinematics frame has its own time. ``ClockMode.DEVICE``: both streams share one clock
(recordings and synthetic sessions made on one time base), the EMG is read at the frame's device time.
``ClockMode.HOST``: each EMG source's clock is mapped onto the host clock by its receipt times
(:class:`msk_core.signal.host_clock.HostClock`: the smallest receipt minus device time of each chunk's last sample over
the last ``clock_window_s``, minus the source's stated latency), unless an offset measured another way was set for it
(:meth:`LiveEmg.set_offset`, e.g. from accelerations). The frames: with ``joints_clock="host"`` their times are on
the host clock already (the kinematics node mapped each tracker, ``--imu-clock host``); with ``"arrival"`` they are
mapped by their own receipt times the same way. :meth:`LiveEmg.clock_report` says, per stream, the offset applied,
its spread, the latency assumed and the method.
The group activation at time t is read from the envelope at ``t - emd`` (electromechanical delay: EMG leads force);
:meth:`LiveEmg.awaits` says whether that EMG is still on its way (a caller may hold the frame until it is here).

Problems are explicit: a jump in the sample index is a gap (counted, samples lost counted; the filter restarts
from rest after it and the envelope is not used for ``GAP_SETTLE_S``, flag ``emg_gap``); a source whose newest
sample is older than ``stall_s`` on the host clock, or that has not reached the frame's time by more than that, is
stalled (``emg_stalled``); repeated sample indices are dropped (counted as duplicates). An electrode the quality
monitor judges bad (:meth:`LiveEmg.exclude_channels`, :mod:`msk_core.estimate.live_quality`) is left out of its
group's envelope from the next chunk on, and a group whose every electrode is bad has no envelope (NaN) while they
are; the envelope samples so made, and the frames that read them, carry ``electrode_bad``.
"""

from __future__ import annotations

import bisect
import enum
import functools
from dataclasses import dataclass, field

import numpy as np

from msk_core.errors import ConfigError
from msk_core.estimate.emd import calibrated_delay
from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.flags import FLAG_ELECTRODE_BAD, FLAG_GAP, FLAG_NO_MVC, FLAG_NOT_FINITE, FLAG_STALLED
from msk_core.signal.emg import EmgEnvelopeFilter, EmgFilterConfig
from msk_core.signal.host_clock import (
    METHOD_ARRIVAL,
    METHOD_DEVICE,
    METHOD_HOST,
    WINDOW_S,
    ClockReport,
    HostClock,
    check_latency_ns,
)

GAP_SETTLE_S = 0.5  # the 6 Hz low-pass restarts from rest after a gap: ~3 time constants before it is trusted
HISTORY_S = (
    10.0  # envelope kept per source for the lookup at t - emd (kinematics may lag the EMG by seconds in a replay)
)


class ClockMode(str, enum.Enum):
    DEVICE = "device"
    HOST = "host"


class JointsClock(str, enum.Enum):
    """With ``ClockMode.HOST``: the clock of the kinematics frames' times."""

    HOST = "host"  # on the host clock already (the kinematics node mapped each tracker): used as they are
    ARRIVAL = "arrival"  # on a device clock: mapped onto the host clock by their receipt times, as an EMG source


JOINTS_STREAM = "joints"


def emg_stream(source: str) -> str:
    """The name of an EMG source's stream in clock reports (as its topic, ``emg/<source>``)."""
    return f"emg/{source}"


@dataclass(frozen=True)
class EmgSetup:
    """Which channel feeds which group, each channel's MVC amplitude (same units as the raw EMG) and the EMD."""

    channel_group: dict[str, str]
    mvc: dict[str, float]
    emd_s: float = 0.0

    @classmethod
    def from_profile(cls, profile, channel_group: dict[str, str] | None = None) -> EmgSetup:
        """From a subject profile's ``emg_normalisation`` (electrode -> group, divisor) and calibrated EMD;
        ``channel_group`` (a session file's electrode map, the estimator's ``--emg-map``) overrides the profile's map:
        a live channel to a muscle group, or to one of the profile's electrodes (the calibration trials' EMG column
        it was on), whose group and MVC the channel then takes."""
        norm = dict(getattr(profile, "emg_normalisation", {}) or {})
        mvc = {ch: float(info["divisor"]) for ch, info in norm.items() if "divisor" in info}
        if channel_group is None:
            return cls({ch: info["group"] for ch, info in norm.items()}, mvc, emd_s=calibrated_delay(profile))
        mapping = {}
        for channel, target in channel_group.items():
            electrode = norm.get(target) if channel not in norm else None
            mapping[channel] = electrode["group"] if electrode is not None else target
            if electrode is not None and "divisor" in electrode:
                mvc[channel] = float(electrode["divisor"])
        return cls(channel_group=mapping, mvc=mvc, emd_s=calibrated_delay(profile))


@dataclass
class EmgCounters:
    chunks: int = 0
    samples: int = 0
    gaps: int = 0
    samples_lost: int = 0
    duplicates: int = 0
    #: NaN or infinite samples (a base's fault, a corrupt value), taken as 0: one would hold every later envelope of
    #: its channel at NaN (the filter carries it on)
    not_finite_samples: int = 0
    unmapped_channels: list[str] = field(default_factory=list)
    no_mvc_channels: list[str] = field(default_factory=list)
    #: channels the electrode map names that no EMG source streams (a sensor not paired, a typo): their groups are
    #: estimated without EMG
    missing_channels: list[str] = field(default_factory=list)


@dataclass
class EnvelopeBlock:
    """The envelope of one chunk: ``envelope`` (n, n_groups of this source) normalised, per sample device time."""

    source: str
    groups: list[str]
    device_time_ns: np.ndarray
    envelope: np.ndarray
    flags: list[str]


class _Source:
    def __init__(
        self,
        name: str,
        labels: tuple[str, ...],
        rate_hz: float,
        setup: EmgSetup,
        config: EmgFilterConfig,
        counters: EmgCounters,
        clock: HostClock,
    ) -> None:
        self.name = name
        self.labels = labels
        self.rate_hz = rate_hz
        self.filter = EmgEnvelopeFilter(config, len(labels))
        mapped = [i for i, ch in enumerate(labels) if ch in setup.channel_group]
        for ch in labels:
            if ch not in setup.channel_group and ch not in counters.unmapped_channels:
                counters.unmapped_channels.append(ch)
        self.no_mvc = [labels[i] for i in mapped if labels[i] not in setup.mvc]
        for ch in self.no_mvc:
            if ch not in counters.no_mvc_channels:
                counters.no_mvc_channels.append(ch)
        usable = [i for i in mapped if labels[i] in setup.mvc]
        self.groups = sorted({setup.channel_group[labels[i]] for i in usable})
        self.groups_without_mvc = sorted({setup.channel_group[labels[i]] for i in mapped} - set(self.groups))
        # group envelope = mean of its channels' normalised envelopes: one (channels x groups) averaging matrix
        self.membership = np.zeros((len(labels), len(self.groups)))
        self.scale = np.ones(len(labels))
        for i in usable:
            g = self.groups.index(setup.channel_group[labels[i]])
            self.membership[i, g] = 1.0
            self.scale[i] = 1.0 / setup.mvc[labels[i]]
        self.excluded: frozenset[str] = frozenset()  # usable channels left out (bad electrodes)
        self.weights = self.membership / np.maximum(self.membership.sum(axis=0, keepdims=True), 1.0)
        self.without = np.zeros(len(self.groups), dtype=bool)  # groups whose every electrode is left out
        self.next_index: int | None = None
        self.settled_from_ns = 0  # device time from which the envelope is trusted (after start or a gap)
        self.max_age_ns = int(2e9 / rate_hz) + 1  # a sample stands for its period (rounding to whole ns)
        self.starts: list[int] = []  # device time of each kept chunk's first sample
        self.times: list[np.ndarray] = []
        self.values: list[np.ndarray] = []
        self.masked: list[bool] = []  # per kept chunk: made with an electrode left out
        self.last_device_ns = -1
        self.last_arrival_ns = 0
        self.clock = clock  # the arrival mapping: device time -> host clock
        self.measured: ClockReport | None = None  # an offset set from outside (LiveEmg.set_offset): used instead

    @property
    def offset_ns(self) -> int | None:
        """Device time + this = host instant the sample was measured (None: no mapping yet)."""
        return self.measured.offset_ns if self.measured is not None else self.clock.offset_ns

    def clock_report(self) -> ClockReport | None:
        return self.measured if self.measured is not None else self.clock.report()

    def exclude(self, channels: frozenset[str]) -> None:
        """Leave the electrodes ``channels`` out of their groups' envelopes from the next chunk on (the others of a
        group are averaged without them; a group with none left has no envelope)."""
        excluded = frozenset(ch for ch in channels if ch in self.labels)
        if excluded == self.excluded:
            return
        self.excluded = excluded
        kept = self.membership * np.array([ch not in excluded for ch in self.labels], dtype=float)[:, None]
        counts = kept.sum(axis=0, keepdims=True)
        self.weights = kept / np.maximum(counts, 1.0)
        self.without = (counts[0] == 0) & (self.membership.sum(axis=0) > 0)

    @property
    def masking(self) -> bool:
        """Whether an electrode that feeds a group is left out now."""
        return any(self.membership[self.labels.index(ch)].any() for ch in self.excluded)

    def lookup(self, t: int) -> tuple[np.ndarray, bool] | None:
        """Envelope of the newest sample at or before device time ``t`` and whether an electrode was left out of it
        (None: before the history)."""
        c = bisect.bisect_right(self.starts, t) - 1
        if c < 0:
            return None
        times = self.times[c]
        k = int(np.searchsorted(times, t, side="right")) - 1
        if t - times[k] > self.max_age_ns:  # t falls in a gap between chunks
            return None
        return self.values[c][k], self.masked[c]

    def keep(self, times: np.ndarray, values: np.ndarray, masked: bool) -> None:
        self.starts.append(int(times[0]))
        self.times.append(times)
        self.values.append(values)
        self.masked.append(masked)
        if len(self.starts) > 64 and self.starts[0] < times[-1] - HISTORY_S * 1e9:
            drop = bisect.bisect_left(self.starts, int(times[-1] - HISTORY_S * 1e9))
            del self.starts[:drop], self.times[:drop], self.values[:drop], self.masked[:drop]


class LiveEmg:
    """Explicit state: per source the envelope filter state, the next expected sample index, the clock offset and a
    short envelope history; counters for gaps, lost and duplicate samples and channels without MVC."""

    def __init__(
        self,
        groups: list[str],
        setup: EmgSetup,
        *,
        clock: ClockMode | str = ClockMode.DEVICE,
        stall_s: float = 0.25,
        bandpass_hz: tuple[float, float] | None = (20.0, 450.0),
        lowpass_hz: float = 6.0,
        lowpass_order: int = 3,
        joints_clock: JointsClock | str = JointsClock.ARRIVAL,
        latency_ns: dict[str, int] | None = None,
        default_latency_ns: int = 0,
        clock_window_s: float = WINDOW_S,
    ) -> None:
        """``latency_ns``: per EMG source id, its stated device latency (a sample measured at host instant T is
        received at T + latency at the soonest); sources not named have ``default_latency_ns``. Only with
        ``ClockMode.HOST`` (with one clock nothing is mapped)."""
        self.groups = list(groups)
        unknown = sorted({g for g in setup.channel_group.values() if g not in self.groups})
        if unknown:
            raise ConfigError(
                f"electrode map names groups that are not in the pack {self.groups}", field="emg_map", value=unknown
            )
        if not 0 <= setup.emd_s <= 0.5:
            raise ConfigError("electromechanical delay must be in [0, 0.5] s", field="emd_s", value=setup.emd_s)
        self.setup = setup
        self.clock = ClockMode(clock)
        self.joints_clock = JointsClock(joints_clock)
        self.latency_ns = {
            source: check_latency_ns(value, f"latency of EMG source {source}")
            for source, value in (latency_ns or {}).items()
        }
        self.default_latency_ns = check_latency_ns(default_latency_ns, "default EMG latency")
        if self.clock is ClockMode.DEVICE and (self.default_latency_ns or any(self.latency_ns.values())):
            raise ConfigError(
                "a device latency is applied when device clocks are mapped onto the host clock "
                "(clock 'host'); with one clock (clock 'device') nothing is mapped",
                field="latency",
                value={**self.latency_ns, "default": self.default_latency_ns},
            )
        self.clock_window_s = float(clock_window_s)
        self._joints_clock = HostClock(JOINTS_STREAM, window_s=self.clock_window_s)
        self._measured: dict[str, ClockReport] = {}  # offsets set from outside, per EMG source id
        self.stall_ns = int(stall_s * 1e9)
        # a source's envelope filter at its rate (known with its first chunk)
        self._filter_config = functools.partial(
            EmgFilterConfig, bandpass_hz=bandpass_hz, lowpass_hz=lowpass_hz, lowpass_order=lowpass_order
        )
        self.sources: dict[str, _Source] = {}
        self._excluded: dict[str, frozenset[str]] = {}  # per EMG source id, the electrodes left out (exclude_channels)
        self.counters = EmgCounters()
        self._group_index = {g: i for i, g in enumerate(self.groups)}
        # per EMG source, the device time of the EMG the latest frame read (its instant on the source's clock less
        # the EMD): where the fatigue index cuts a rep (msk_core.estimate.live_fatigue); sources not mapped yet absent
        self.read_at_ns: dict[str, int] = {}

    @property
    def electrode_groups(self) -> list[str]:
        """Pack groups an electrode is mapped to (in pack order)."""
        mapped = set(self.setup.channel_group.values())
        return [g for g in self.groups if g in mapped]

    def add_chunk(self, chunk: RawEmgChunk, arrival_ns: int, receipt_ns: int | None = None) -> EnvelopeBlock | None:
        """Filter one chunk of raw EMG. Returns the normalised group envelope of its new samples.

        ``arrival_ns``: when this node got the chunk (host clock; stalls are judged on it); ``receipt_ns``: when the
        host received the chunk's bytes from the device (the driver's ``host_time_ns``, recorded with the chunk, so a
        replay maps the clock as live did); default ``arrival_ns``."""
        source = chunk.source
        state = self.sources.get(source)
        if state is None or state.labels != chunk.labels or state.rate_hz != chunk.rate_hz:
            config = self._filter_config(rate_hz=chunk.rate_hz)
            clock = HostClock(
                emg_stream(source),
                latency_ns=self.latency_ns.get(source, self.default_latency_ns),
                window_s=self.clock_window_s,
            )
            state = self.sources[source] = _Source(
                source, chunk.labels, chunk.rate_hz, self.setup, config, self.counters, clock
            )
            state.measured = self._measured.get(source)
            state.exclude(self._excluded.get(source, frozenset()))
            streamed = {label for other in self.sources.values() for label in other.labels}
            self.counters.missing_channels = sorted(set(self.setup.channel_group) - streamed)
        self.counters.chunks += 1
        flags: list[str] = []
        if state.next_index is not None and chunk.first_sample_index != state.next_index:
            if chunk.first_sample_index > state.next_index:  # samples never arrived: restart the filter at rest
                self.counters.gaps += 1
                self.counters.samples_lost += chunk.first_sample_index - state.next_index
                state.filter.reset()
                state.settled_from_ns = int(chunk.device_time_ns + GAP_SETTLE_S * 1e9)
                flags.append(FLAG_GAP)
            else:  # repeated rows (a re-sent chunk): keep only the new ones
                new = chunk.rows_from(state.next_index)
                self.counters.duplicates += chunk.n_samples - new.n_samples
                chunk = new
        elif state.next_index is None:
            state.settled_from_ns = chunk.device_time_ns
        x, n, period_ns = chunk.samples, chunk.n_samples, 1e9 / state.rate_hz
        if n == 0:
            return None
        self.counters.samples += n
        not_finite = ~np.isfinite(x)
        if not_finite.any():
            self.counters.not_finite_samples += int(np.count_nonzero(not_finite))
            x = np.where(not_finite, 0.0, x)
            flags.append(FLAG_NOT_FINITE)
        envelope = state.filter.process(x)  # every channel, a bad one too: its filter is settled when it recovers
        group_env = (envelope * state.scale) @ state.weights
        group_env[:, state.without] = np.nan
        masked = state.masking
        times = chunk.device_time_ns + np.round(np.arange(n) * period_ns).astype(np.int64)
        state.next_index = chunk.first_sample_index + n
        state.last_device_ns = int(times[-1])
        state.last_arrival_ns = int(arrival_ns)
        if self.clock is ClockMode.HOST:  # the block left the device when its last sample was measured
            state.clock.add(int(times[-1]), int(arrival_ns if receipt_ns is None else receipt_ns))
        state.keep(times, group_env, masked)
        if state.no_mvc:
            flags.append(FLAG_NO_MVC)
        if masked:
            flags.append(FLAG_ELECTRODE_BAD)
        return EnvelopeBlock(source, state.groups, times, group_env, flags)

    def exclude_channels(self, source: str, channels) -> None:
        """Leave the electrodes ``channels`` (labels) of EMG source ``source`` out of their groups' envelopes from its
        next chunk on, e.g. those the quality monitor judges bad; an empty set takes every electrode back. Given
        before the source's first chunk they are kept until it comes."""
        self._excluded[source] = frozenset(channels)
        if source in self.sources:
            self.sources[source].exclude(self._excluded[source])

    def set_offset(self, source: str, offset_ns: int | None, spread_ns: int = 0, method: str = "") -> None:
        """Map EMG source ``source`` with an offset measured another way (device time + ``offset_ns`` = host instant
        measured; ``spread_ns`` how sure; ``method`` names the way, e.g. "acceleration") instead of its arrival
        mapping, from now on; ``offset_ns`` None goes back to the arrival mapping. Only with ``ClockMode.HOST``."""
        if self.clock is not ClockMode.HOST:
            raise ConfigError(
                "an offset is set only when device clocks are mapped onto the host clock (clock 'host')",
                field="clock",
                value=self.clock.value,
            )
        if offset_ns is None:
            self._measured.pop(source, None)
        else:
            if not method or method in (METHOD_ARRIVAL, METHOD_DEVICE, METHOD_HOST):
                raise ConfigError(
                    "name the way the offset was measured (not arrival, device or host, which are this module's own)",
                    field="method",
                    value=method,
                )
            if int(spread_ns) < 0:
                raise ConfigError("a spread is >= 0 ns", field="spread_ns", value=spread_ns)
            self._measured[source] = ClockReport(
                emg_stream(source),
                int(offset_ns),
                int(spread_ns),
                self.latency_ns.get(source, self.default_latency_ns),
                method,
            )
        if source in self.sources:
            self.sources[source].measured = self._measured.get(source)

    def arrival_offset_ns(self, source: str) -> int | None:
        """EMG source ``source``'s arrival mapping (its receipt times less its stated latency), whether or not an
        offset measured another way replaces it; None before its first chunk or with ``ClockMode.DEVICE``."""
        state = self.sources.get(source)
        return None if state is None or self.clock is not ClockMode.HOST else state.clock.offset_ns

    def awaits(self, device_time_ns: int, now_ns: int) -> bool:
        """Whether the EMG of the kinematics frame at ``device_time_ns`` is still on its way at host time ``now_ns``:
        some source that feeds groups delivers (its newest chunk is less than ``stall_s`` old) but has not reached
        the frame's instant (less the EMD) yet. A device that delivers later than the trackers (a base station
        buffering its frames) makes every frame wait for it; :meth:`at` reads the newest sample it has otherwise."""
        frame_ns = int(device_time_ns)
        if self.clock is ClockMode.HOST and self.joints_clock is JointsClock.ARRIVAL:
            if self._joints_clock.offset_ns is None:
                return False
            frame_ns += self._joints_clock.offset_ns
        for state in self.sources.values():
            if not state.groups or now_ns - state.last_arrival_ns > self.stall_ns:
                continue
            t = int(frame_ns - self.setup.emd_s * 1e9)
            if self.clock is ClockMode.HOST:
                if state.offset_ns is None:
                    continue
                t -= state.offset_ns
            if t > state.last_device_ns:
                return True
        return False

    def clock_report(self) -> list[ClockReport]:
        """Per stream (each EMG source seen, ``emg/<source>``, then ``joints``): the offset applied onto the host
        clock, its spread, the latency assumed and the method; a stream not mapped yet is left out."""
        if self.clock is ClockMode.DEVICE:
            return [
                ClockReport(name, 0, 0, 0, METHOD_DEVICE) for name in [*map(emg_stream, self.sources), JOINTS_STREAM]
            ]
        reports = [r for r in (state.clock_report() for state in self.sources.values()) if r is not None]
        if self.joints_clock is JointsClock.HOST:
            reports.append(ClockReport(JOINTS_STREAM, 0, 0, 0, METHOD_HOST))
        elif (joints := self._joints_clock.report()) is not None:
            reports.append(joints)
        return reports

    def at(self, device_time_ns: int, arrival_ns: int, receipt_ns: int | None = None) -> tuple[np.ndarray, list[str]]:
        """Measured envelope of every pack group for the kinematics frame at ``device_time_ns`` (its clock) that
        arrived at ``arrival_ns`` (``receipt_ns``: its receipt stamp for the arrival mapping of ``joints_clock``
        "arrival", e.g. the JointAngles' ``host_time_ns``; default ``arrival_ns``): NaN where no electrode, no MVC, a
        gap, a stalled source, or every electrode of the group bad. Plus the frame's flags."""
        out = np.full(len(self.groups), np.nan)
        flags: set[str] = set()
        frame_ns = int(device_time_ns)  # the frame's instant on the clock the EMG is mapped onto
        if self.clock is ClockMode.HOST and self.joints_clock is JointsClock.ARRIVAL:
            self._joints_clock.add(frame_ns, int(arrival_ns if receipt_ns is None else receipt_ns))
            offset = self._joints_clock.offset_ns
            assert offset is not None  # a clock with a sample has an offset (as DeviceClocks.to_host says)
            frame_ns += offset
        wanted_groups = set(self.setup.channel_group.values())
        served: set[str] = set()
        self.read_at_ns = {}
        for name, state in self.sources.items():
            if state.groups_without_mvc:
                flags.add(FLAG_NO_MVC)
            if not state.groups:
                continue
            t = int(frame_ns - self.setup.emd_s * 1e9)
            if self.clock is ClockMode.HOST:
                if state.offset_ns is None:
                    continue
                t -= state.offset_ns  # the frame's host instant -> this source's device time
            self.read_at_ns[name] = t
            stalled = arrival_ns - state.last_arrival_ns > self.stall_ns or t - state.last_device_ns > self.stall_ns
            if stalled:
                flags.add(FLAG_STALLED)
                continue
            # newest sample at or before t (causal: never a later sample); the frame may be ahead by < stall_s
            if t < state.settled_from_ns:
                found = None
            elif t >= state.last_device_ns:  # the EMG for t has not arrived yet (< stall_s behind): newest sample
                found = state.values[-1][-1], state.masked[-1]
            else:
                found = state.lookup(t)
            if found is None:
                flags.add(FLAG_GAP)
                continue
            value, masked = found
            if masked:
                flags.add(FLAG_ELECTRODE_BAD)
            for j, g in enumerate(state.groups):
                out[self._group_index[g]] = value[j]
                served.add(g)
        if wanted_groups - served and not self.sources:
            flags.add(FLAG_STALLED)  # electrodes are configured but no EMG has arrived yet
        return out, sorted(flags)
