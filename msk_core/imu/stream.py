"""Live IMU kinematics: per-segment samples in, synchronised frames, static calibration, filtered pack coordinates out.

:class:`SegmentSynchroniser` groups the trackers' samples that belong to the same instant (within a tolerance; each
tracker's own stream must be in time order, trackers may arrive in any order relative to each other) and reports
instants some segment missed, naming it. :class:`StreamingJointKinematics` calibrates on the first ``static_s``
seconds of synchronised frames (the subject holds the static pose), and restarts calibration after a gap longer
than ``gap_s`` (a new set: trackers may have been re-strapped). Then it maps every frame to the pack's coordinates
(:class:`msk_core.imu.mapping.ImuJointMapper`), filters them causally (angle, velocity, acceleration:
:class:`msk_core.imu.kinematics.JointKinematicsFilter`) and, given a rep template, tracks the phase causally.
Everything is explicit state; nothing is dropped without being counted in :class:`KinematicsCounters`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from msk_core.errors import InputError
from msk_core.imu.kinematics import JointKinematicsFilter, KinematicsFilterConfig
from msk_core.imu.mapping import ImuJointMapper
from msk_core.signal.reps import PhaseTracker, RepTemplate


@dataclass(frozen=True)
class SyncedFrame:
    time_ns: int
    quats: dict[str, np.ndarray]  # segment -> (4,) w, x, y, z


@dataclass(frozen=True)
class IncompleteFrame:
    time_ns: int
    missing: tuple[str, ...]  # segments without a sample at this instant
    samples: int  # samples of the other segments discarded with it


class SegmentSynchroniser:
    """Groups samples of ``segments`` taken within ``tolerance_ns`` of each other into frames.

    State: one time-ordered buffer per segment. An instant is complete when every segment has a sample within the
    tolerance; it is incomplete once some segment has moved past it without one, or when a segment has been silent
    for ``max_wait_ns`` of the others' data (a dead tracker must not stall the others forever)."""

    def __init__(self, segments: list[str], *, tolerance_ns: int, max_wait_ns: int) -> None:
        self.segments = list(segments)
        self.tolerance_ns = int(tolerance_ns)
        self.max_wait_ns = int(max_wait_ns)
        self.buffers: dict[str, deque[tuple[int, np.ndarray]]] = {s: deque() for s in self.segments}
        self.last_time: dict[str, int] = {}
        self.out_of_order = 0

    def push(self, segment: str, time_ns: int, quat: np.ndarray) -> list[SyncedFrame | IncompleteFrame]:
        last = self.last_time.get(segment)
        if last is not None and time_ns <= last:
            self.out_of_order += 1  # a repeated or older sample of the same tracker: not a new instant
            return []
        self.last_time[segment] = time_ns
        self.buffers[segment].append((int(time_ns), np.asarray(quat, dtype=float)))
        return self._drain()

    def _drain(self) -> list[SyncedFrame | IncompleteFrame]:
        out: list[SyncedFrame | IncompleteFrame] = []
        tol = self.tolerance_ns
        while True:
            heads = {s: b[0][0] for s, b in self.buffers.items() if b}
            if not heads:
                return out
            t0 = min(heads.values())
            at_t0 = [s for s, t in heads.items() if t <= t0 + tol]
            if len(at_t0) == len(self.segments):
                quats = {s: self.buffers[s].popleft()[1] for s in self.segments}
                out.append(SyncedFrame(int(np.mean([heads[s] for s in self.segments])), quats))
                continue
            # a segment whose stream is already past t0 (or silent for too long) has no sample for this instant
            newest = max(b[-1][0] for b in self.buffers.values() if b)
            missing = [
                s
                for s in self.segments
                if s not in at_t0
                and (s in heads or self.last_time.get(s, t0) > t0 + tol or newest - t0 > self.max_wait_ns)
            ]
            waiting = [s for s in self.segments if s not in at_t0 and s not in missing]
            if not missing or waiting:
                return out  # some segment may still deliver a sample for t0
            for s in at_t0:
                self.buffers[s].popleft()
            out.append(IncompleteFrame(t0, tuple(s for s in self.segments if s not in at_t0), len(at_t0)))

    def reset(self) -> None:
        for b in self.buffers.values():
            b.clear()
        self.last_time.clear()


@dataclass
class KinematicsCounters:
    frames: int = 0  # synchronised frames seen
    calibration_frames: int = 0  # frames used as the static pose (not published)
    calibrations: int = 0
    calibration_failures: int = 0  # the subject moved during the static window: calibration restarted
    published: int = 0
    bad_frames: int = 0  # non-finite or zero quaternions
    restarts: int = 0  # gaps longer than gap_s (or time going backwards): recalibrated
    resumes: int = 0  # gaps longer than gap_s of samples lost on their way (lost_before): calibration kept
    last_error: str = ""
    errors: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class JointOutput:
    time_ns: int
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    phase: float  # [0, 1) inside a rep, REST_PHASE (msk_core.signal.reps) between reps, NaN when unknown (no template)


#: a frame up to this long before the first sample after a loss still ends the loss's gap (the other trackers'
#: samples of that instant are within the synchroniser's tolerance, milliseconds)
LOST_MARGIN_NS = 100_000_000


class StreamingJointKinematics:
    """Synchronised frames -> calibrated, filtered pack coordinates (+ phase). Explicit state, one frame at a time."""

    def __init__(
        self,
        mapper: ImuJointMapper,
        *,
        static_pose_rad: np.ndarray,
        static_s: float = 0.5,
        gap_s: float = 1.0,
        filter_config: KinematicsFilterConfig,
        phase_template: RepTemplate | None = None,
        phase_coordinate: str | None = None,
    ) -> None:
        self.mapper = mapper
        self.static_pose = np.asarray(static_pose_rad, dtype=float)
        self.static_ns = int(round(static_s * 1e9))
        self.gap_ns = int(round(gap_s * 1e9))
        self.filter_config = filter_config
        self.phase_index = None if phase_coordinate is None else mapper.coordinates.index(phase_coordinate)
        self.phase_template = phase_template
        self.counters = KinematicsCounters()
        self._lost_ns: int | None = None  # the newest instant just before which samples were lost on their way
        self._restart()

    def _restart(self) -> None:
        """A new set: calibrate again, then filter and track the phase from scratch."""
        self.static: dict[str, list[np.ndarray]] = {s: [] for s in self.mapper.segments}
        self.static_start_ns: int | None = None
        self.calibrated = False
        self._resume()

    def _resume(self) -> None:
        """The same set after a gap: the calibration holds, the filter and the phase tracking start from scratch."""
        self.filter = JointKinematicsFilter(len(self.mapper.coordinates), self.filter_config)
        self.tracker = PhaseTracker(self.phase_template) if self.phase_template is not None else None
        self.last_ns: int | None = None

    def lost_before(self, time_ns: int) -> None:
        """The trackers' samples just before ``time_ns`` were lost on their way (their publications skipped: the
        network to the node, or the router, was down) while the trackers kept measuring on the body. A gap that
        ends there is not a new set: the calibration holds (it is not redone on whatever pose the lift is in when
        the samples come back), the filter and the phase restart (``resumes``)."""
        self._lost_ns = time_ns if self._lost_ns is None else max(self._lost_ns, time_ns)

    def _error(self, kind: str, message: str) -> None:
        self.counters.errors[kind] = self.counters.errors.get(kind, 0) + 1
        self.counters.last_error = message

    def step(self, frame: SyncedFrame) -> JointOutput | None:
        """One synchronised frame; returns the coordinates, or ``None`` while calibrating or for a bad frame."""
        c = self.counters
        c.frames += 1
        lost = self._lost_ns
        if lost is not None and lost <= frame.time_ns:
            self._lost_ns = None  # this frame is past the loss
        if self.last_ns is not None and not 0 < frame.time_ns - self.last_ns <= self.gap_ns:
            if self.calibrated and lost is not None and self.last_ns < lost <= frame.time_ns + LOST_MARGIN_NS:
                c.resumes += 1  # the samples of the gap were lost on their way: the same set goes on
                self._resume()
            else:
                c.restarts += 1  # a new set (or a clock jump): the trackers may have moved on the body
                self._restart()
        quats = {s: np.asarray(frame.quats[s], dtype=float) for s in self.mapper.segments}
        if not all(np.all(np.isfinite(q)) and np.linalg.norm(q) > 1e-6 for q in quats.values()):
            c.bad_frames += 1
            self._error("bad_quaternion", f"non-finite or zero quaternion at t={frame.time_ns} ns")
            return None
        dt_s = None if self.last_ns is None else (frame.time_ns - self.last_ns) / 1e9
        self.last_ns = frame.time_ns
        if not self.calibrated:
            c.calibration_frames += 1
            if self.static_start_ns is None:
                self.static_start_ns = frame.time_ns
            for s, q in quats.items():
                self.static[s].append(q)
            if frame.time_ns - self.static_start_ns >= self.static_ns:
                try:
                    self.mapper.calibrate({s: np.array(v) for s, v in self.static.items()}, self.static_pose)
                    self.calibrated = True
                    c.calibrations += 1
                except InputError as exc:
                    c.calibration_failures += 1
                    self._error("calibration", f"static calibration failed, retrying: {exc}")
                    self.static = {s: [] for s in self.mapper.segments}
                    self.static_start_ns = None
            return None
        angles = self.mapper.angles({s: q[None, :] for s, q in quats.items()})[0]
        q, qd, qdd = self.filter.step(angles, dt=dt_s)
        phase = float("nan")
        if self.tracker is not None and self.phase_index is not None:
            phase = self.tracker.update(frame.time_ns / 1e9, float(q[self.phase_index]))
        c.published += 1
        return JointOutput(frame.time_ns, q, qd, qdd, phase)
