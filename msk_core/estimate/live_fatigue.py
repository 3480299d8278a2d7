"""Live fatigue index for the estimator: per EMG source a :class:`msk_core.signal.fatigue.FatigueTracker` on the raw
chunks as they arrive, reps from the phase of the frames, and per electrode the median and mean frequency of each
rep of the set under way with their trend (slope per rep, change from the set's first reps).

Reps. Every estimated frame brings its phase and, per EMG source, the device time of the EMG sample it reads (the
frame's instant on that source's clock less the electromechanical delay, :attr:`LiveEmg.read_at_ns`). A
:class:`msk_core.signal.reps.PhaseRepCounter` per source, fed those times, gives each rep's span on the source's
own clock, so the rep's raw EMG is cut on the clock it was sampled with. A rep's values exist once the EMG up to its
end has arrived (the tracker waits for it).

Sets: :meth:`LiveFatigue.start_set` (the operator's ``LoadEvent.set_number``) starts the trend again; an operator's
mark drops the rep under way (:meth:`LiveFatigue.drop_rep_under_way`: counting resumes after the next rest sample, as
:class:`msk_core.signal.sets.SetTracker` does, so the fatigue panel and the set table count the same reps). Samples lost (a
jump in ``first_sample_index``) start the source's tracker again from the chunk after the gap, keeping the set's
values; a rep that began before the gap has no values (counted in ``reps_skipped``). Re-sent rows are taken once.
Samples arrive in the chunk's ``units`` (:func:`msk_core.units.volts_per_unit`, since the noise
floor below which a rep has no value is in volts); a source in other units has no values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from msk_core.errors import InputError
from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.signal.fatigue import FatigueConfig, FatigueTracker, FatigueTrend, RepSpectrum
from msk_core.signal.reps import PhaseRepCounter
from msk_core.units import volts_per_unit


@dataclass
class ElectrodeFatigueReport:
    """One electrode's fatigue index over the set under way (per rep lists in rep order; trend values NaN when
    there are too few reps)."""

    source: str
    channel: str
    group: str
    set_number: int
    median_hz: list[float]
    mean_hz: list[float]
    rep_end_s: list[float]  # each rep's end on the EMG device clock
    median_slope_hz_per_rep: float
    median_slope_se_hz_per_rep: float
    median_slope_pct_per_rep: float
    median_change_pct: float
    mean_slope_pct_per_rep: float
    mean_change_pct: float


class _SourceFatigue:
    def __init__(self, chunk: RawEmgChunk, channel_group: dict[str, str]) -> None:
        self.stream = chunk.stream
        labels, rate_hz, units = chunk.stream
        self.labels = labels
        # the electrodes tracked: those of the electrode map (every channel without one)
        self.columns = [c for c, ch in enumerate(labels) if ch in channel_group or not channel_group]
        self.rate_hz = rate_hz
        self.units = units
        self.volts_per_unit = volts_per_unit(units or "V")  # None: no values (no unit: the Trigno's volts)
        self.config = FatigueConfig(rate_hz=rate_hz)
        self.tracker: FatigueTracker | None = None  # made at the first chunk (its sample 0 is that chunk's row 0)
        self.next_index: int | None = None
        self.reps = PhaseRepCounter()
        self.spectra: list[RepSpectrum] = []  # the set's reps, kept across a restart of the tracker

    def restart(self, device_time_ns: int) -> None:
        """A tracker whose sample 0 is at ``device_time_ns``, holding the set's values so far."""
        self.tracker = FatigueTracker(self.config, max(len(self.columns), 1), t0=device_time_ns / 1e9)
        self.tracker.spectra = self.spectra


class LiveFatigue:
    """Per EMG source a fatigue tracker, per electrode its values over the set. ``channel_group``: the electrode
    map (channel label -> muscle group); with one, only its electrodes are tracked and reported."""

    def __init__(self, channel_group: dict[str, str] | None = None) -> None:
        self.channel_group = dict(channel_group or {})
        self.sources: dict[str, _SourceFatigue] = {}
        self.set_number = 0
        self.reps_done = 0  # reps with values, over the session
        self.reps_skipped = 0  # reps whose EMG the tracker did not hold whole (a gap, the start of the stream)
        self._phase: float | None = None  # the newest frame's phase
        self._wait_rest = False  # an operator's mark dropped the rep under way: no rep until a rest sample

    def add_chunk(self, chunk: RawEmgChunk) -> list[RepSpectrum]:
        """One chunk of raw EMG; returns the reps it completed."""
        state = self.sources.get(chunk.source)
        if state is None or state.stream != chunk.stream:
            state = self.sources[chunk.source] = _SourceFatigue(chunk, self.channel_group)
        if state.volts_per_unit is None or not state.columns:
            return []
        if state.next_index is None or chunk.first_sample_index > state.next_index:  # the start, or samples lost
            state.restart(chunk.device_time_ns)
        else:  # re-sent rows: taken once
            chunk = chunk.rows_from(state.next_index)
        x, first = chunk.samples, chunk.first_sample_index
        if x.shape[0] == 0:
            return []
        state.next_index = first + x.shape[0]
        assert state.tracker is not None  # made by restart() at the first chunk
        done = state.tracker.process(x[:, state.columns] * state.volts_per_unit)
        self.reps_done += len(done)
        return done

    def add_frame(self, read_at_ns: dict[str, int], phase: float | None) -> list[RepSpectrum]:
        """One estimated frame: its ``phase`` and, per source, the device time of the EMG it reads; returns the reps
        whose EMG had all arrived when they ended."""
        done: list[RepSpectrum] = []
        self._phase = phase
        if self._wait_rest:
            if phase is not None and phase >= 0.0:
                return done
            self._wait_rest = False
        for source, t_ns in read_at_ns.items():
            state = self.sources.get(source)
            if state is None or state.tracker is None:
                continue
            span = state.reps.update(t_ns / 1e9, phase)
            if span is None:
                continue
            try:
                done += state.tracker.end_rep(*span)
            except InputError:  # the rep began before the EMG the tracker holds (its start, a gap)
                self.reps_skipped += 1
        self.reps_done += len(done)
        return done

    def drop_rep_under_way(self) -> None:
        """The operator marked a set (started or ended one) during a rep: that rep is not counted, and counting
        resumes after the next rest sample."""
        for state in self.sources.values():
            state.reps = PhaseRepCounter()
        self._wait_rest = self._phase is not None and self._phase >= 0.0

    def start_set(self, number: int = 0) -> None:
        """The reps from now on belong to set ``number`` (0: not counted): its trend starts again."""
        self.set_number = int(number)
        for state in self.sources.values():
            state.spectra = []
            if state.tracker is not None:
                state.tracker.start_set()
                state.tracker.spectra = state.spectra

    def report(self) -> list[ElectrodeFatigueReport]:
        """Every electrode (of the electrode map, when there is one), per source in arrival order and channel order."""
        out = []
        for source, state in self.sources.items():
            trend = state.tracker.trend if state.tracker is not None and state.volts_per_unit is not None else None
            for c, column in enumerate(state.columns):
                out.append(self._electrode(source, c, state.labels[column], state.spectra, trend))
        return out

    def _electrode(
        self, source: str, c: int, channel: str, spectra: list[RepSpectrum], trend: FatigueTrend | None
    ) -> ElectrodeFatigueReport:
        nan = float("nan")

        def of(values: np.ndarray | None) -> float:
            return nan if values is None else float(values[c])

        median, mean = (trend.median, trend.mean) if trend is not None else (None, None)
        return ElectrodeFatigueReport(
            source=source,
            channel=channel,
            group=self.channel_group.get(channel, ""),
            set_number=self.set_number,
            median_hz=[float(s.median_hz[c]) for s in spectra],
            mean_hz=[float(s.mean_hz[c]) for s in spectra],
            rep_end_s=[float(s.t_end) for s in spectra],
            median_slope_hz_per_rep=of(median.slope_hz_per_rep if median else None),
            median_slope_se_hz_per_rep=of(median.slope_se_hz_per_rep if median else None),
            median_slope_pct_per_rep=of(median.slope_pct_per_rep if median else None),
            median_change_pct=of(median.change_pct if median else None),
            mean_slope_pct_per_rep=of(mean.slope_pct_per_rep if mean else None),
            mean_change_pct=of(mean.change_pct if mean else None),
        )
