"""The live EMG clock measured against the trackers' clocks from the accelerations both devices sense.

The arrival mapping (:mod:`msk_core.signal.host_clock`) puts each device's samples on the host clock by their receipt
times less the device's *stated* latency: a latency nobody stated (a Trigno base buffering its frames) moves the
whole EMG stream that much later against the motion. The Trigno sensors' accelerometers (AUX port) run on the EMG
clock, and each tracker measures acceleration on its own; an EMG sensor on a tracker's segment senses the same
motion, so :class:`msk_core.signal.clock_sync.ClockSync` measures the offset between the two device clocks.

:class:`AccelerationAlignment` runs one ``ClockSync`` per EMG source and tracker, each started with the prior the
arrival mappings give (EMG host offset - tracker host offset). The trackers are mapped onto the host clock as the
kinematics node maps them (:class:`msk_core.signal.host_clock.DeviceClocks`: the same receipt times, the same stated
latencies, the same window), so their host instants are those of the joint frames. Once a tracker's estimate locks,
the EMG source's host mapping is that tracker's plus the measured offset (``ClockOffset.emg_host_offset_ns``): the
EMG then lands on the host clock where the tracker's samples of the same instant do, whatever the EMG's delivery
latency. With several trackers locked, the median of the mappings they imply is applied and their disagreement
counts in its spread. The source is then mapped with :meth:`LiveEmg.set_offset` (method ``"acceleration"``); while
no tracker is locked (waiting for a full window, rest, or no EMG sensor moving with any tracker) the arrival mapping
stays, and the clock report says why. :meth:`AccelerationAlignment.report` adds to each EMG stream's clock report
the arrival mapping it replaces (their difference is the arrival mapping's error) and every tracker's estimate.

No I/O, no clock read: the estimator feeds it the samples with their recorded receipt times, so a recording replayed
through it measures what the live session did.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from msk_core.errors import ConfigError, InputError
from msk_core.estimate.live_emg import ClockMode, LiveEmg, emg_stream
from msk_core.signal.clock_sync import AccUnit, ClockOffset, ClockSync, ClockSyncConfig
from msk_core.signal.host_clock import ClockReport, DeviceClocks

METHOD_ACCELERATION = "acceleration"
#: a device time this far behind the newest one is a restarted device clock (the estimate starts over); less, a
#: repeated or late sample (left out)
RESTART_NS = 1_000_000_000


@dataclass(frozen=True)
class Alignment:
    """One EMG source's clock measured against one tracker's: the :class:`ClockSync` answer (``offset.offset_ns``:
    tracker device time - EMG device time of one instant) and, once locked, the EMG host mapping it implies."""

    reference: str  # the tracker's stream, "imu/<tracker>"
    offset: ClockOffset
    host_offset_ns: int | None = None


@dataclass
class AlignmentCounters:
    restarts: int = 0  # estimates started over after a device clock went back (a restarted device)
    late_samples: int = 0  # repeated or out-of-order samples left out


@dataclass
class _Pair:
    sync: ClockSync
    answer: ClockOffset


@dataclass
class _Source:
    labels: tuple[str, ...] = ()
    last_ns: int | None = None
    applied: tuple[int, int] | None = None  # (host offset, spread) set on the LiveEmg source
    reason: str = ""
    alignments: tuple[Alignment, ...] = ()


@dataclass
class _Tracker:
    last_ns: int | None = None
    pairs: dict[str, _Pair] = field(default_factory=dict)  # per EMG source


class AccelerationAlignment:
    """Per EMG source and tracker a :class:`ClockSync`; maps each EMG source of ``live_emg`` (clock "host") through
    the trackers it locks on. ``trackers``: the trackers' host mappings (their stated latencies), as the kinematics
    node has them."""

    def __init__(self, live_emg: LiveEmg, trackers: DeviceClocks, config: ClockSyncConfig | None = None) -> None:
        if live_emg.clock is not ClockMode.HOST:
            raise ConfigError(
                "the EMG clock is measured against the trackers' when device clocks are mapped onto "
                "the host clock (clock 'host'); with one clock there is nothing to measure",
                field="clock",
                value=live_emg.clock.value,
            )
        self.live_emg = live_emg
        self.trackers = trackers
        self.config = config or ClockSyncConfig()
        self.counters = AlignmentCounters()
        self._sources: dict[str, _Source] = {}
        self._trackers: dict[str, _Tracker] = {}

    # ------------------------------------------------------------------------------------------ input
    def add_tracker_sample(self, tracker: str, device_ns: int, receipt_ns: int, acc_m_s2=None) -> None:
        """One tracker sample: its device time, the host's receipt time (``ImuSample.host_time_ns``) and its
        acceleration (m/s², gravity included; None when the tracker does not send it)."""
        device_ns = int(device_ns)
        self.trackers.to_host(tracker, device_ns, int(receipt_ns))
        state = self._trackers.setdefault(tracker, _Tracker())
        if acc_m_s2 is None:
            return
        if _restarted(state.last_ns, device_ns):  # its estimates start over with a new prior
            state.pairs.clear()
            self.counters.restarts += 1
        elif state.last_ns is not None and device_ns <= state.last_ns:
            self.counters.late_samples += 1
            return
        state.last_ns = device_ns
        acc = np.asarray(acc_m_s2, dtype=float).reshape(1, 3)
        for pair in state.pairs.values():
            pair.sync.add_tracker(np.array([device_ns], np.int64), acc, AccUnit.M_PER_S2)

    def add_acc(self, source: str, labels, device_ns, acc_g) -> None:
        """One block of the accelerometers on EMG source ``source``'s clock: ``labels`` (one per sensor), device
        times (n,) ns on the EMG clock, accelerations (n, sensors, 3) in g. Then the estimates are brought up to
        date (:meth:`update`)."""
        times = np.asarray(device_ns, dtype=np.int64).reshape(-1)
        acc = np.asarray(acc_g, dtype=float)
        labels = tuple(labels)
        if acc.shape != (times.size, len(labels), 3):
            raise InputError(
                "accelerations must be (samples, sensors, 3)",
                field=f"acc/{source}",
                value=(acc.shape, times.size, len(labels)),
            )
        if times.size == 0:
            return
        state = self._sources.setdefault(source, _Source())
        if state.labels != labels or _restarted(state.last_ns, int(times[0])):
            self._restart_source(source, state)
            state.labels = labels
        if state.last_ns is not None:  # a repeated block (or its repeated rows)
            keep = times > state.last_ns
            self.counters.late_samples += int(times.size - keep.sum())
            times, acc = times[keep], acc[keep]
            if times.size == 0:
                return
        state.last_ns = int(times[-1])
        self._start_pairs(source)
        for tracker in self._trackers.values():
            pair = tracker.pairs.get(source)
            if pair is not None:
                pair.sync.add_emg_sensors(labels, times, acc, AccUnit.G)
        self.update()

    def _restart_source(self, source: str, state: _Source) -> None:
        if state.last_ns is not None:
            self.counters.restarts += 1
        state.last_ns = None
        for tracker in self._trackers.values():
            tracker.pairs.pop(source, None)

    def _start_pairs(self, source: str) -> None:
        """A ClockSync for ``source`` and every tracker that has none yet, once both streams are mapped by their
        arrival (the prior: EMG host offset - tracker host offset)."""
        emg_offset = self.live_emg.arrival_offset_ns(source)
        if emg_offset is None:
            return
        for name, tracker in self._trackers.items():
            tracker_offset = self.trackers.offset_ns(name)
            if source not in tracker.pairs and tracker_offset is not None:
                sync = ClockSync(emg_offset - tracker_offset, self.config)
                tracker.pairs[source] = _Pair(sync, sync.update())

    # ------------------------------------------------------------------------------------------ estimate
    def update(self) -> None:
        """Every estimate up to date; each EMG source mapped through the trackers it locks on, or by its arrival."""
        for tracker in self._trackers.values():
            for pair in tracker.pairs.values():
                pair.answer = pair.sync.update()
        for source, state in self._sources.items():
            alignments: list[Alignment] = []
            hosts: list[tuple[int, int]] = []
            for name, tracker in self._trackers.items():
                found = tracker.pairs.get(source)
                if found is None:
                    continue
                tracker_offset = self.trackers.offset_ns(name)  # mapped before its pair was made: never None
                host = (
                    found.answer.emg_host_offset_ns(tracker_offset)
                    if found.answer.locked and tracker_offset is not None
                    else None
                )
                alignments.append(Alignment(f"imu/{name}", found.answer, host))
                if host is not None:
                    hosts.append((host, found.answer.spread_ns or 0))
            state.alignments = tuple(alignments)
            if hosts:
                applied = int(round(float(np.median([h for h, _ in hosts]))))
                spread = max([s for _, s in hosts] + [abs(h - applied) for h, _ in hosts])
                if state.applied != (applied, spread):
                    self.live_emg.set_offset(source, applied, spread, METHOD_ACCELERATION)
                    state.applied = (applied, spread)
                state.reason = f"{len(hosts)} of {len(alignments)} tracker(s) moved with an EMG sensor: " + "; ".join(
                    f"{a.reference} {a.offset.reason}" for a in alignments if a.host_offset_ns is not None
                )
            else:
                if state.applied is not None:
                    self.live_emg.set_offset(source, None)
                    state.applied = None
                state.reason = self._fallback_reason(alignments)

    def _fallback_reason(self, alignments: list[Alignment]) -> str:
        if not self._trackers:
            return "arrival mapping: no tracker accelerations (imu/<tracker>) yet"
        if not alignments:
            return "arrival mapping: the EMG and tracker streams are not both mapped by their arrival yet"
        return "arrival mapping: no tracker moved with an EMG sensor yet: " + "; ".join(
            f"{a.reference} {a.offset.status.value} ({a.offset.reason})" for a in alignments
        )

    # ------------------------------------------------------------------------------------------ report
    def alignments(self, source: str) -> tuple[Alignment, ...]:
        state = self._sources.get(source)
        return () if state is None else state.alignments

    def report(self, reports: list[ClockReport]) -> list[ClockReport]:
        """``reports`` (the EMG path's, :meth:`LiveEmg.clock_report`) with, for every EMG stream, why its method,
        the arrival mapping an acceleration offset replaces, and every tracker's estimate."""
        by_stream = {emg_stream(source): (source, state) for source, state in self._sources.items()}
        out = []
        for report in reports:
            if not report.source.startswith("emg/"):
                out.append(report)
                continue
            found = by_stream.get(report.source)
            if found is None:
                out.append(
                    dataclasses.replace(
                        report,
                        reason=(f"arrival mapping: no accelerations on this EMG clock (acc/{report.source[4:]})"),
                    )
                )
                continue
            source, state = found
            arrival = self.live_emg.arrival_offset_ns(source) if report.method == METHOD_ACCELERATION else None
            out.append(
                dataclasses.replace(report, arrival_offset_ns=arrival, reason=state.reason, alignments=state.alignments)
            )
        return out


def _restarted(last_ns: int | None, first_ns: int) -> bool:
    """A device time more than :data:`RESTART_NS` before the newest one seen: the device clock restarted."""
    return last_ns is not None and first_ns < last_ns - RESTART_NS
