"""Live electrode quality for the estimator: one :class:`msk_core.signal.quality.ElectrodeQualityMonitor` per EMG
source on the raw chunks as they arrive, each electrode's state (unknown, good, check, bad) with its reasons, and what
a session sums up per electrode: the time spent in check and in bad, and the fault episodes.

An episode starts at the verdict that takes an electrode from good (or unknown) to check or bad and ends at the
verdict that gives it back good; it records its worst state and every fault raised during it. Times are the EMG's
device times of the verdicts' windows' ends (the chunk's ``device_time_ns`` plus the sample's offset), so an episode
can be laid beside the samples that caused it. A jump in ``first_sample_index`` (samples lost) restarts the source's
monitor (a window across the gap would mix two signals): its electrodes are unknown until the first windows after the
gap are in, and an episode under way stays open through it (it ends only on a good verdict). Repeated rows (a re-sent
chunk) are judged once. Samples arrive in the chunk's ``units`` (:func:`msk_core.units.volts_per_unit`); a source in other units
(already normalised EMG) is not judged and its electrodes stay unknown with the reason.
"""

from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field

from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.signal.quality import (
    ElectrodeQualityMonitor,
    ElectrodeState,
    Fault,
    QualityConfig,
    QualityVerdict,
)
from msk_core.units import volts_per_unit

#: Episodes kept per electrode for the report (the count and the faults' tallies cover all of them).
EPISODES_KEPT = 16


@dataclass
class FaultEpisode:
    """A stretch of check or bad: from ``start_ns`` to ``end_ns`` (device times; ``end_ns`` None while under way)."""

    start_ns: int
    worst: ElectrodeState
    faults: list[Fault] = field(default_factory=list)  # in the order they were first raised
    end_ns: int | None = None


@dataclass
class ElectrodeReport:
    """One electrode as the estimator's status says it."""

    source: str
    channel: str  # the channel label, e.g. "sensor03.EMG"
    group: str  # the muscle group it feeds ("" when the electrode map names none)
    state: ElectrodeState
    faults: tuple[Fault, ...]  # worst first
    detail: str  # the verdict in words with its window's numbers (QualityVerdict.describe)
    since_ns: int  # device time of the verdict that gave the current state (0: none yet)
    check_s: float  # time spent in check (verdicts x hop)
    bad_s: float
    episodes: int
    episode_faults: dict[Fault, int]  # per fault: the episodes it was raised in
    recent: list[FaultEpisode]  # the last EPISODES_KEPT episodes, oldest first


@dataclass
class _Electrode:
    channel: str
    group: str
    state: ElectrodeState = ElectrodeState.UNKNOWN
    faults: tuple[Fault, ...] = ()
    since_ns: int = 0
    check_s: float = 0.0
    bad_s: float = 0.0
    episodes: int = 0
    episode_faults: Counter = field(default_factory=Counter)
    recent: deque = field(default_factory=lambda: deque(maxlen=EPISODES_KEPT))
    open: FaultEpisode | None = None

    def update(self, state: ElectrodeState, faults: tuple[Fault, ...], time_ns: int, hop_s: float) -> bool:
        """One verdict; True when the state or its faults changed."""
        changed = state is not self.state or faults != self.faults
        if state is not self.state:
            self.since_ns = time_ns
        self.state, self.faults = state, faults
        if state is ElectrodeState.CHECK:
            self.check_s += hop_s
        elif state is ElectrodeState.BAD:
            self.bad_s += hop_s
        if state.severity >= ElectrodeState.CHECK.severity:
            if self.open is None:
                self.open = FaultEpisode(time_ns, state)
                self.episodes += 1
                self.recent.append(self.open)
            if state.severity > self.open.worst.severity:
                self.open.worst = state
            for fault in faults:
                if fault not in self.open.faults:
                    self.open.faults.append(fault)
                    self.episode_faults[fault] += 1
        elif state is ElectrodeState.GOOD and self.open is not None:
            self.open.end_ns = time_ns
            self.open = None
        return changed


class _SourceQuality:
    def __init__(self, chunk: RawEmgChunk, channel_group: dict[str, str]) -> None:
        self.stream = chunk.stream
        labels, rate_hz, units = chunk.stream
        self.labels = labels
        self.rate_hz = rate_hz
        self.units = units
        self.volts_per_unit = volts_per_unit(units or "V")  # None: units not judged (no unit: the Trigno's volts)
        self.monitor = ElectrodeQualityMonitor(QualityConfig(rate_hz), len(labels))
        self.electrodes = [_Electrode(ch, channel_group.get(ch, "")) for ch in labels]
        self.next_index: int | None = None
        self.origin_ns = 0  # device time of the monitor's sample 0
        self.latest: QualityVerdict | None = None

    def restart(self, device_time_ns: int) -> None:
        self.monitor.reset()
        self.origin_ns = int(device_time_ns)
        self.latest = None
        for electrode in self.electrodes:  # unknown until the windows after the gap are in; episodes stay open
            electrode.state, electrode.faults = ElectrodeState.UNKNOWN, ()


class LiveQuality:
    """Per EMG source a quality monitor and per electrode its state, time in check and bad and its episodes.
    ``channel_group``: the electrode map (channel label -> muscle group), for the reports."""

    def __init__(self, channel_group: dict[str, str] | None = None) -> None:
        self.channel_group = dict(channel_group or {})
        self.sources: dict[str, _SourceQuality] = {}

    def add_chunk(self, chunk: RawEmgChunk) -> bool:
        """Judge one chunk of raw EMG; True when some electrode's state or reasons changed."""
        state = self.sources.get(chunk.source)
        if state is None or state.stream != chunk.stream:
            state = self.sources[chunk.source] = _SourceQuality(chunk, self.channel_group)
        if state.volts_per_unit is None:
            return False
        if state.next_index is None:
            state.origin_ns = chunk.device_time_ns
        elif chunk.first_sample_index > state.next_index:  # samples lost: windows across the gap would mix signals
            state.restart(chunk.device_time_ns)
        else:  # re-sent rows: judged once
            chunk = chunk.rows_from(state.next_index)
        x, first, period_ns = chunk.samples, chunk.first_sample_index, 1e9 / state.rate_hz
        if x.shape[0] == 0:
            return False
        state.next_index = first + x.shape[0]
        changed = False
        hop_s = state.monitor.config.hop_samples / state.rate_hz
        for verdict in state.monitor.process(x * state.volts_per_unit):
            time_ns = state.origin_ns + int(round(verdict.end_sample * period_ns))
            for electrode, channel in zip(state.electrodes, verdict.channels):
                changed |= electrode.update(channel.state, channel.faults, time_ns, hop_s)
            state.latest = verdict
        return changed

    def bad_channels(self, source: str) -> frozenset[str]:
        """The channels of ``source`` whose electrode is bad now."""
        state = self.sources.get(source)
        if state is None:
            return frozenset()
        return frozenset(e.channel for e in state.electrodes if e.state is ElectrodeState.BAD)

    def report(self) -> list[ElectrodeReport]:
        """Every electrode seen, per source in arrival order and channel order."""
        out = []
        for source, state in self.sources.items():
            for c, e in enumerate(state.electrodes):
                if state.volts_per_unit is None:
                    detail = f"not judged: raw EMG in {state.units!r}, not in volts"
                elif state.latest is None:
                    detail = e.state.value
                else:
                    detail = state.latest.describe(c)
                out.append(
                    ElectrodeReport(
                        source,
                        e.channel,
                        e.group,
                        e.state,
                        e.faults,
                        detail,
                        e.since_ns,
                        round(e.check_s, 3),
                        round(e.bad_s, 3),
                        e.episodes,
                        dict(e.episode_faults),
                        list(e.recent),
                    )
                )
        return out
