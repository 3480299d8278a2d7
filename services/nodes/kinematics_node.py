"""Kinematics node: IMU orientations in, model joint coordinates out.

Subscribes to ``msk/<session>/imu/*`` (:class:`ImuSample`), groups the trackers' samples of the same instant
(:class:`msk_core.imu.stream.SegmentSynchroniser`), calibrates on the static pose at the start of every set, maps the
segment orientations to the pack's coordinates through the pack's IMU table (:mod:`msk_core.imu.mapping`), filters
them causally (angle, velocity, acceleration) and publishes :class:`JointAngles` on ``msk/<out-session>/joints`` at
the IMU rate. Zenoh callbacks only enqueue; one worker thread does the rest in arrival order. Nothing is dropped
silently: every sample or frame not published is counted in :class:`KinematicsStats`. With ``--imu-clock host`` each
tracker's clock is mapped onto the host clock by its receipt times less its stated latency (``--imu-latency-ms``,
:class:`msk_core.signal.host_clock.HostClock`), and the node's status carries each tracker's mapping
(``DeviceStatus.clocks``, ``imu/<tracker>``). Docs: docs/kinematics.md.
Run ``python -m services.nodes.kinematics_node --pack bench_press --session lab`` or ``msk kinematics``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivers.xsens.frames import to_enu
from drivers.xsens.xbus import CoordinateFrame
from msk_core.errors import ConfigError, FileFormatError, MskError
from msk_core.imu.kinematics import KinematicsFilterConfig
from msk_core.imu.mapping import ImuJointMapper, mapping_for, parse_pose
from msk_core.imu.stream import IncompleteFrame, SegmentSynchroniser, StreamingJointKinematics
from msk_core.model import load_pack
from msk_core.signal.host_clock import (
    METHOD_DEVICE,
    WINDOW_S,
    ClockReport,
    DeviceClocks,
    counts_again,
    latency_argv,
    newest_device_time,
    parse_latencies,
)
from msk_core.signal.reps import RepTemplate
from services.nodes.node_runtime import (
    InputCounts,
    NodeInputs,
    NodeProcess,
    StatusReporter,
    add_process_arguments,
    serve,
)
from services.nodes.readiness import ReadySpec, declare_ready
from services.transport import messages, topics
from services.transport.zenoh_session import ZenohOptions, declare_data_publisher, open_session, publish, run_script

log = logging.getLogger(__name__)
NODE_NAME = "kinematics"
CLOCKS = ("device", "host")
#: a 16-bit packet counter that moved on by less than this (and more than 1) skipped samples; a larger jump is a
#: device that started counting again (restart), not a loss
COUNTER_GAP_LIMIT = 0x8000
START_GRACE_S = 1.0  # trackers' first samples this far apart are a normal start, logged as information only


@dataclass(frozen=True)
class KinematicsSettings:
    """What one kinematics node computes and how, checked once where it is built: from the node's command line
    (:meth:`from_args`), by ``msk live`` from the session plan (services.sessions.live.kinematics_settings, which starts
    the node with :meth:`argv`), or by whoever runs the node in a thread (the demo, the tests).

    ``output_session``: publish the joints there (default ``session``); ``facing_deg``: compass direction the subject
    faces (0 north, 90 east); ``static_pose_deg``: the calibration pose over the pack table's; ``static_s``: seconds of
    static pose at the start of a set; ``gap_s``: an IMU gap that starts a new set; ``sync_tolerance_s``: trackers'
    samples this close are one instant, ``max_wait_s`` the longest wait for an instant's last tracker; ``imu_rate_hz``,
    ``jerk_std`` (rad/s^3) and ``angle_std_deg``: the Kalman filter (:attr:`filter_config`); ``phase_template`` (a
    subject profile or RepTemplate JSON) and ``phase_coordinate``: the rep phase, both or neither. ``clock="device"``:
    the trackers share one device clock (recordings, a Link/Awinda station); ``"host"``: each tracker's device time is
    mapped onto the host clock (msk_core.signal.host_clock, over the last ``clock_window_s``), less its stated latency
    (``latency_ns`` per tracker id, ``default_latency_ns`` for the others)."""

    pack: str
    session: str
    output_session: str | None = None
    facing_deg: float = 0.0
    static_pose_deg: dict[str, float] | None = None
    static_s: float = 0.5
    gap_s: float = 1.0
    sync_tolerance_s: float = 0.008
    max_wait_s: float = 0.5
    imu_rate_hz: float = 60.0
    jerk_std: float = 100.0
    angle_std_deg: float = 1.0
    phase_template: Path | None = None
    phase_coordinate: str | None = None
    clock: str = "device"
    latency_ns: dict[str, int] | None = None
    default_latency_ns: int = 0
    clock_window_s: float = WINDOW_S

    def __post_init__(self) -> None:
        for name, flag in (
            ("static_s", "--static-s"),
            ("gap_s", "--gap"),
            ("sync_tolerance_s", "--sync-tolerance-ms"),
            ("max_wait_s", "max_wait_s"),
            ("imu_rate_hz", "--imu-rate"),
            ("jerk_std", "--jerk-std"),
            ("angle_std_deg", "--angle-std-deg"),
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError("must be positive", field=flag, value=value)
        if self.clock not in CLOCKS:
            raise ConfigError(f"expected {' or '.join(CLOCKS)}", field="--imu-clock", value=self.clock)
        if (self.phase_template is None) != (self.phase_coordinate is None):
            raise ConfigError(
                "phase tracking needs both a rep template and a coordinate",
                field="--phase-coordinate",
                value=self.phase_coordinate,
            )

    @property
    def filter_config(self) -> KinematicsFilterConfig:
        return KinematicsFilterConfig(
            dt=1.0 / self.imu_rate_hz, jerk_std=self.jerk_std, angle_std=math.radians(self.angle_std_deg)
        )

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> KinematicsSettings:
        """The settings of the node's command line (:func:`add_arguments`); the pack must have an IMU table."""
        model = load_pack(args.pack)
        mapping_for(model.name)  # fail before joining the network when the pack has no IMU table
        latency_ns, default_latency_ns = parse_latencies(args.imu_latency_ms, "--imu-latency-ms")
        return cls(
            args.pack,
            args.session,
            output_session=args.out_session,
            facing_deg=args.facing_deg,
            static_pose_deg=parse_pose(args.static_pose, list(model.coordinates)) or None,
            static_s=args.static_s,
            gap_s=args.gap,
            sync_tolerance_s=args.sync_tolerance_ms / 1e3,
            imu_rate_hz=args.imu_rate,
            jerk_std=args.jerk_std,
            angle_std_deg=args.angle_std_deg,
            phase_template=args.phase_template,
            phase_coordinate=args.phase_coordinate,
            clock=args.imu_clock,
            latency_ns=latency_ns,
            default_latency_ns=default_latency_ns,
        )

    def argv(self) -> list[str]:
        """These settings as the node's command line, but ``max_wait_s`` and ``clock_window_s`` (:meth:`from_args`
        reads them back)."""
        pose = ",".join(f"{name}={deg!r}" for name, deg in (self.static_pose_deg or {}).items())
        return [
            *("--pack", self.pack, "--session", self.session, "--facing-deg", repr(self.facing_deg)),
            *(["--out-session", self.output_session] if self.output_session is not None else []),
            *(["--static-pose", pose] if pose else []),
            *("--static-s", repr(self.static_s), "--gap", repr(self.gap_s)),
            *("--sync-tolerance-ms", f"{self.sync_tolerance_s * 1e3:.15g}", "--imu-rate", repr(self.imu_rate_hz)),
            *("--jerk-std", repr(self.jerk_std), "--angle-std-deg", repr(self.angle_std_deg)),
            *(["--phase-template", str(self.phase_template)] if self.phase_template is not None else []),
            *(["--phase-coordinate", self.phase_coordinate] if self.phase_coordinate is not None else []),
            *("--imu-clock", self.clock),
            *latency_argv("--imu-latency-ms", self.latency_ns, self.default_latency_ns),
        ]


@dataclass
class KinematicsStats:
    samples_in: int = 0
    ignored: int = 0  # samples of segments the pack's table does not use (e.g. another exercise's trackers)
    without_orientation: int = 0  # samples that carry no orientation (an MTi-G's GNSS messages): no pose in them
    undecodable: int = 0
    unknown_frame: int = 0  # samples in a global frame other than ENU/NED/NWU
    out_of_order: int = 0  # a tracker's sample not newer than its previous one
    frames_synced: int = 0  # instants at which every needed segment had a sample
    frames_incomplete: int = 0  # instants some needed segment missed (its samples of others discarded, counted)
    samples_discarded: int = 0  # samples thrown away with incomplete instants
    missing: dict[str, int] = field(default_factory=dict)  # segment -> instants it missed
    calibration_frames: int = 0  # frames spent as the static pose (not published)
    calibrations: int = 0
    calibration_failures: int = 0
    restarts: int = 0  # gaps longer than --gap: a new set, recalibrated
    resumes: int = 0  # gaps longer than --gap of samples lost on their way (the network): calibration kept
    bad_frames: int = 0  # non-finite or zero quaternions
    rejected: int = 0  # samples that raised an input error while being processed
    frames_out: int = 0
    samples_done: int = 0  # samples whose joint frames (if any) are published: a waiter's exact end condition
    last_error: str = ""
    inputs: InputCounts | None = None  # received and dropped inputs per key (services.nodes.node_runtime)


def load_template(path: Path) -> RepTemplate:
    """The rep template of a subject profile (``msk calibrate``'s ``phase_model``, the one the estimator tracks) or a
    bare ``RepTemplate.to_dict()``."""
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise FileFormatError(f"cannot read the rep template: {exc}", path=str(path)) from None
    if not isinstance(doc, dict):
        raise FileFormatError("expected a JSON object", path=str(path))
    if "phase_model" in doc:
        if not isinstance(doc["phase_model"], dict):
            raise FileFormatError(
                "the subject profile has no rep template (calibrated without a kinematic phase coordinate)",
                path=str(path),
                field="phase_model",
            )
        doc = doc["phase_model"].get("template", {})
    return RepTemplate.from_dict(doc)


def _segment_of(key: str, sample) -> str:
    return sample.segment or key.rsplit("/", 1)[1]


class KinematicsNode:
    """The node's state between Zenoh and the IMU kinematics: segment synchroniser, streaming kinematics, counters.
    :meth:`handle` takes one IMU message and returns the JointAngles to publish (no Zenoh in here)."""

    def __init__(self, settings: KinematicsSettings, stats: KinematicsStats) -> None:
        """A tracker's latency (``settings.latency_ns``, by tracker id, the last chunk of its topic) applies with
        ``settings.clock`` "host" only: with one device clock nothing is mapped."""
        s = settings
        self.clock = clock = s.clock
        # per tracker: its device clock -> the host clock (the estimator maps the trackers with the same rule)
        self.host_clocks = DeviceClocks(
            "imu", latency_ns=s.latency_ns, default_latency_ns=s.default_latency_ns, window_s=s.clock_window_s
        )
        if clock == "device" and (self.host_clocks.default_latency_ns or any(self.host_clocks.latency_ns.values())):
            raise ConfigError(
                "a tracker latency is applied when the trackers' clocks are mapped onto the host clock "
                "(--imu-clock host); with one device clock nothing is mapped",
                field="latency",
                value={**self.host_clocks.latency_ns, "default": self.host_clocks.default_latency_ns},
            )
        self.device_trackers: set[str] = set()  # trackers seen on the shared device clock
        self.stats = stats
        self.model = load_pack(s.pack)
        # ENU: x east, y north; the mapping's heading is counter-clockwise from x
        self.mapper = ImuJointMapper.for_pack(self.model, heading_rad=math.radians(90.0 - s.facing_deg))
        if s.phase_coordinate is not None and s.phase_coordinate not in self.mapper.coordinates:
            raise ConfigError(
                f"not a coordinate of pack {self.model.name!r} ({self.mapper.coordinates})",
                field="phase_coordinate",
                value=s.phase_coordinate,
            )
        self.kinematics = StreamingJointKinematics(
            self.mapper,
            static_pose_rad=self.mapper.static_pose(s.static_pose_deg),
            static_s=s.static_s,
            gap_s=s.gap_s,
            filter_config=s.filter_config,
            phase_template=load_template(s.phase_template) if s.phase_template is not None else None,
            phase_coordinate=s.phase_coordinate,
        )
        self.sync = SegmentSynchroniser(
            self.mapper.segments, tolerance_ns=int(s.sync_tolerance_s * 1e9), max_wait_ns=int(s.max_wait_s * 1e9)
        )
        self.needed = set(self.mapper.segments)
        self._last_counter: dict[str, int] = {}  # per tracker, the packet counter of its newest sample
        self._newest_device_ns: dict[str, int] = {}  # per tracker, its newest device time since its clock started
        self._first_instant_ns: int | None = None  # of the first instant synchronised, complete or not
        self._incomplete_said = False  # an incomplete instant is logged as an error once, after start-up's grace
        self.coordinates = list(self.mapper.coordinates)
        self.prefix = f"{topics.session_prefix(s.session)}/imu/"

    def handle(self, key: str, payload: messages.ImuSample | bytes, missed: int = 0) -> list[messages.JointAngles]:
        """One IMU message in; the joint-angle frames it completes out. A bad sample is counted, never raised.
        ``missed``: publications of its publisher lost on their way just before it (:attr:`Inbound.missed`): a gap
        they make resumes the set instead of recalibrating (:meth:`StreamingJointKinematics.lost_before`)."""
        try:
            return self._handle(key, payload, missed)
        except MskError as error:  # one bad sample must not stop the node: count it, say why, go on
            self.stats.rejected += 1
            self.stats.last_error = f"{key}: {error}"
            if self.stats.rejected == 1:
                log.error("%s", self.stats.last_error)
            return []

    def _handle(self, key: str, payload: messages.ImuSample | bytes, missed: int = 0) -> list[messages.JointAngles]:
        stats = self.stats
        stats.samples_in += 1
        try:
            imu = messages.as_message(messages.ImuSample, payload)
        except messages.MessageDecodeError as exc:
            stats.undecodable += 1
            stats.last_error = f"{key}: {exc}"
            return []
        segment = _segment_of(key, imu)
        if segment not in self.needed:
            stats.ignored += 1
            return []
        if not imu.HasField("orientation"):  # an MTi-G's GNSS message (its first one too): no pose, but counted by
            stats.without_orientation += 1  # the tracker, so its counter is taken in turn (no false gap after it)
            tracker, counter = key.rsplit("/", 1)[1], int(imu.packet_counter)
            previous = self._last_counter.get(tracker)
            if previous is None or (counter - previous) & 0xFFFF == 1:  # a gap before it stays for the next sample
                self._last_counter[tracker] = counter
            return []
        try:
            frame = CoordinateFrame[(imu.coordinate_frame or "ENU").upper()]  # Xsens' default output is ENU
        except KeyError:
            stats.unknown_frame += 1
            stats.last_error = f"{key}: unknown coordinate_frame {imu.coordinate_frame!r} (ENU, NED or NWU)"
            return []
        o = imu.orientation
        quat = np.array(to_enu((o.w, o.x, o.y, o.z), frame))
        before = self.sync.out_of_order
        time_ns, tracker = int(imu.device_time_ns), key.rsplit("/", 1)[1]
        newest = self._newest_device_ns.get(tracker)
        # the tracker's clock counting again (power cycle, a stream started again): a new start, whatever its counter
        clock_restarted = counts_again(newest, time_ns)
        self._newest_device_ns[tracker] = newest_device_time(None if clock_restarted else newest, time_ns)
        if self.clock == "host":  # each tracker's own clock mapped onto the host clock (see main)
            time_ns = self.host_clocks.to_host(tracker, time_ns, int(imu.host_time_ns))
        else:
            self.device_trackers.add(tracker)
        counter, previous = int(imu.packet_counter), self._last_counter.get(tracker)
        self._last_counter[tracker] = counter
        # samples the tracker counted but that never came (lost between the device and its driver: a serial line,
        # an MVN suit's network): the set goes on as for publications lost on their way
        skipped = 0 if previous is None else (counter - previous - 1) & 0xFFFF
        if not clock_restarted and (missed or 0 < skipped < COUNTER_GAP_LIMIT):
            self.kinematics.lost_before(time_ns)
        events = self.sync.push(segment, time_ns, quat)
        stats.out_of_order += self.sync.out_of_order - before
        return [joints for event in events if (joints := self._frame(event)) is not None]

    def clock_report(self) -> list[ClockReport]:
        """Per tracker seen (``imu/<tracker>``): the mapping onto the host clock its samples get (``device``: none)."""
        if self.clock == "device":
            return [ClockReport(f"imu/{t}", 0, 0, 0, METHOD_DEVICE) for t in sorted(self.device_trackers)]
        return self.host_clocks.reports()

    def _frame(self, event) -> messages.JointAngles | None:
        stats = self.stats
        if self._first_instant_ns is None:
            self._first_instant_ns = event.time_ns
        if isinstance(event, IncompleteFrame):
            stats.frames_incomplete += 1
            stats.samples_discarded += event.samples
            for s in event.missing:
                stats.missing[s] = stats.missing.get(s, 0) + 1
            after_s = (event.time_ns - self._first_instant_ns) / 1e9
            stats.last_error = (
                f"no sample from segment(s) {list(event.missing)} {after_s:.2f} s after the first tracker sample "
                f"(t={event.time_ns} ns; topics {self.prefix}<tracker>; pack {self.model.name!r} needs "
                f"{self.mapper.segments})"
            )
            # trackers start streaming a few samples apart: an instant missing one before any was complete, within
            # the grace, is the start, not a fault
            if stats.frames_synced == 0 and after_s <= START_GRACE_S:
                log.info("%s: waiting for every tracker's first sample", stats.last_error)
            elif not self._incomplete_said:
                self._incomplete_said = True
                log.error("%s", stats.last_error)
            return None
        stats.frames_synced += 1
        out = self.kinematics.step(event)
        _copy_counters(self.kinematics, stats)
        if out is None:
            return None
        joints = messages.JointAngles(
            coordinates=self.coordinates,
            q=out.q.tolist(),
            qd=out.qd.tolist(),
            qdd=out.qdd.tolist(),
            device_time_ns=out.time_ns,
            host_time_ns=messages.now_ns(),
        )
        if np.isfinite(out.phase):  # left unset = unknown (no rep template); -1 = between reps
            joints.phase = out.phase
        stats.frames_out += 1
        return joints


def main(
    config: ZenohOptions,
    settings: KinematicsSettings,
    *,
    stop_event: threading.Event | None = None,
    ready_event: threading.Event | None = None,
    ready_key: ReadySpec | None = None,
    stats: KinematicsStats | None = None,
) -> KinematicsStats:
    """Run the node of ``settings`` until ``stop_event``; returns its stats (``stats``, filled as it runs)."""
    stop_event = stop_event or threading.Event()
    stats = stats if stats is not None else KinematicsStats()
    node = KinematicsNode(settings, stats)
    session, output_session = settings.session, settings.output_session
    with open_session(config) as zsession:
        publisher = declare_data_publisher(zsession, topics.joints_key(output_session or session), "msk.JointAngles")
        inputs = NodeInputs(zsession, NODE_NAME, expected_type="msk.ImuSample", role=config.role)
        reporter = StatusReporter(zsession, output_session or session, NODE_NAME, inputs, clocks=node.clock_report)
        stats.inputs = inputs.counts
        inputs.subscribe(f"{node.prefix}*")
        token = declare_ready(zsession, ready_key)  # noqa: F841 - alive while the node runs (services.nodes.readiness)
        if ready_event is not None:
            ready_event.set()
        reporter.tick(force=True)

        def process(item) -> None:
            rejected = stats.rejected
            for joints in node.handle(item.key, item.message, item.missed):
                publish(publisher, joints)
            if stats.rejected != rejected:
                reporter.error(stats.last_error)
            stats.samples_done += 1

        serve(inputs, process, stop_event, reporter)  # what arrived before the stop is still published
    return stats


def _copy_counters(kinematics: StreamingJointKinematics, stats: KinematicsStats) -> None:
    c = kinematics.counters
    stats.calibration_frames, stats.calibrations = c.calibration_frames, c.calibrations
    stats.calibration_failures, stats.restarts, stats.bad_frames = c.calibration_failures, c.restarts, c.bad_frames
    stats.resumes = c.resumes
    if c.last_error:
        stats.last_error = c.last_error
        c.last_error = ""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add = parser.add_argument
    add("--pack", required=True, help="model pack with an IMU table: bench_press or deadlift")
    add("--session", required=True, help="session name: reads msk/<session>/imu/*")
    add("--out-session", default=None, help="publish on msk/<OUT>/joints (default: --session)")
    add(
        "--facing-deg",
        type=float,
        default=0.0,
        help="compass direction the subject faces during calibration, degrees (0 north, 90 east; default 0)",
    )
    add(
        "--static-pose",
        default="",
        metavar="NAME=DEG,...",
        help="pose held during calibration, degrees (default: the pack table's, see docs/kinematics.md)",
    )
    add("--static-s", type=float, default=0.5, help="seconds of static pose at the start of a set (default 0.5)")
    add("--gap", type=float, default=1.0, help="an IMU gap longer than this (s) starts a new set (default 1)")
    add("--sync-tolerance-ms", type=float, default=8.0, help="trackers' samples this close are one instant (default 8)")
    add("--jerk-std", type=float, default=100.0, help="Kalman process noise, rad/s^3 (default 100)")
    add("--angle-std-deg", type=float, default=1.0, help="Kalman measurement noise, degrees (default 1)")
    add("--imu-rate", type=float, default=60.0, help="nominal IMU rate, Hz (default 60; dt comes from timestamps)")
    add("--phase-coordinate", default=None, help="track the rep phase on this coordinate (needs --phase-template)")
    add(
        "--phase-template",
        type=Path,
        default=None,
        help="rep template JSON (a subject profile from msk calibrate, or a RepTemplate dict) learnt in radians",
    )
    add(
        "--imu-clock",
        choices=["device", "host"],
        default="device",
        help="device: the trackers share one clock (recordings); host: separate trackers, each device clock mapped "
        "to the host clock (docs/kinematics.md)",
    )
    add(
        "--imu-latency-ms",
        action="append",
        default=[],
        metavar="[TRACKER=]MS",
        help="with --imu-clock host: the stated latency of tracker TRACKER (without TRACKER=: of every tracker not "
        "named), taken off before its clock is mapped (repeatable; default 0)",
    )
    add_process_arguments(parser)


def run_from_args(args: argparse.Namespace) -> int:
    settings, process = KinematicsSettings.from_args(args), NodeProcess.from_args(args)
    out = settings.output_session or settings.session
    print(
        f"kinematics: msk/{settings.session}/imu/* -> msk/{out}/joints with pack {settings.pack}",
        file=sys.stderr,
        flush=True,
    )
    stats = main(process.options, settings, stop_event=process.stop, ready_key=process.ready)
    print(
        f"published {stats.frames_out} frames; calibrations {stats.calibrations} (gaps: {stats.restarts} new sets, "
        f"{stats.resumes} resumed after samples lost on their way); incomplete instants "
        f"{stats.frames_incomplete} (missing {stats.missing or 'none'}); ignored samples {stats.ignored}; "
        f"samples without orientation {stats.without_orientation}"
        + (f"; last error: {stats.last_error}" if stats.last_error else ""),
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    run_script(__doc__, add_arguments, run_from_args, log_level=logging.INFO)
