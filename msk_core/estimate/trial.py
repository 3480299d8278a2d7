"""Trial description (TOML) and loading: kinematics, torques, EMG and phase on one time base.

Keys (paths relative to the TOML file)::

    kinematics = "ik.sto"            # required; columns named as the pack's coordinates (radians, or inDegrees=yes)
    torques = "id.sto"               # optional; columns <coordinate>_moment (or _force), else <coordinate>; the
                                     # kinematics' own angles are refused. When absent the pack's
                                     # inverse dynamics computes them from q, qd, qdd (finite differences) and load_kg
    emg = "emg.sto"                  # optional
    emg_is_envelope = true           # false: raw EMG, made an envelope offline (zero-phase chain of msk_core.signal.emg)
    load_kg = 5.0                    # external load held in the hands (default 0)
    body_mass_kg = 70.0              # optional; torque errors are then also reported in N·m/kg
    start = 12.0                     # optional, in the files' own time unit (s; may be Unix epoch seconds)
    end = 30.0
    phase_signal = "torque:L5_S1_Flex_Ext"   # optional; a kinematics column, or torque:<coordinate>. Default: the
                                             # pack's phase coordinate (bench_press elbow_flex_r, deadlift
                                             # hip_flexion_r), else the torque of its first coordinate. A signal
                                             # without a complete rep leaves every frame at rest (``extra["no_reps"]``)
    grf = "walk_grf.mot"             # optional: ground reaction forces (OpenSim external loads). Given, the reps are
                                     # gait cycles, heel strike to heel strike of ``grf_foot``: its vertical force
                                     # rising through ``heel_strike_n`` (msk_core.signal.gait), instead of the
                                     # phase signal's reps (not both keys). The foot's vertical-force column is found
                                     # by name (r_ground_force_vy, ground_force_r_vy, ...; an unprefixed
                                     # ground_force_vy is the right foot when the left one's carries the l_ prefix),
                                     # or given as grf_column
    grf_foot = "r"                   # "r" (default) or "l"
    grf_column = "ground_force_vy"   # optional: the foot's vertical-force column, when its name does not say
    heel_strike_n = 20.0             # optional: contact threshold (N), default msk_core.signal.gait's
    isometric = true                 # optional: a static-pose trial (isometric MVC against a dynamometer or a fixed
                                     # bar). It needs ``torques``: the net joint moments the muscles produce, i.e. the
                                     # static inverse dynamics with the measured external force (dynamometer torque
                                     # plus the segments' own gravity moment) - inverse dynamics of the pose alone
                                     # cannot know the push. The pose may not move by more than ISOMETRIC_MAX_MOTION_DEG.
                                     # No reps or phase; it enters calibration with its torque and EMG terms only - a
                                     # contraction that isolates one muscle group is what separates that group's
                                     # strength from its synergists' (docs/estimation.md)
    lowpass_coordinates_hz = 6.0     # optional: low-pass the coordinates as OpenSim's AnalyzeTool does
                                     # (``lowpass_cutoff_frequency_for_coordinates``: padded, zero-phase
                                     # Butterworth, velocities and accelerations from a quintic spline); the whole
                                     # file is filtered, then [start, end] taken. Default: no filter, finite
                                     # differences
    lowpass_torques_hz = 6.0         # optional: low-pass the torque file the same way (whole file, zero phase), e.g.
                                     # an inverse dynamics whose ground reaction forces were not filtered like the
                                     # kinematics: its heel-strike spikes are no muscle torque (docs/estimation.md,
                                     # "The walk")
    [emg_map]                        # EMG column -> pack group
    rectabd_r = "rectabd_r"
    [emg_max]                        # optional: divide each EMG channel by this (normalisation); default: as is
    [coordinates]                    # optional: pack coordinate -> its column in the kinematics and torque files,
    knee_angle_r = "-knee_angle_r"   # "-" before it for a model whose coordinate runs the other way: the angle and
    hip_flexion_r = "hip_flex"       # its moment are both negated. Default: each pack coordinate's own name

The time base is the kinematics within [start, end]; torques and EMG are linearly interpolated onto it, and frames the
torque file does not cover are dropped (counted in ``dropped_frames``). Reps and phase: :mod:`msk_core.estimate.phase`.
"""

from __future__ import annotations

import re
import tomllib
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import overload

import numpy as np

from msk_core.errors import ConfigError, EstimationError, InputError, close_names
from msk_core.estimate.mechanics import TrialMechanics, mechanics_of
from msk_core.estimate.pack import PackLike, clamp_to_ranges, fitted_ranges
from msk_core.estimate.phase import DEFAULT_PHASE_COORDINATES, kinematic_phase, torque_phase
from msk_core.io import Storage, read_sto
from msk_core.io.files import toml_key_line
from msk_core.io.storage import seconds, uniform_step
from msk_core.signal.gait import CONTACT_THRESHOLD_N, gait_cycle_phase, heel_strikes
from msk_core.signal.kinematics_filter import lowpass_coordinates
from msk_core.signal.reps import REST_PHASE
from msk_core.units import GRAVITY, body_mass_problem, load_problem

#: Data files a trial describes: given where the trial's TOML is expected, they are named as such
DATA_SUFFIXES = frozenset({".sto", ".mot", ".trc", ".c3d", ".csv", ".txt", ".npz", ".mcap"})

KNOWN_KEYS = {
    "kinematics",
    "torques",
    "emg",
    "emg_is_envelope",
    "load_kg",
    "body_mass_kg",
    "start",
    "end",
    "phase_signal",
    "emg_map",
    "emg_max",
    "name",
    "isometric",
    "lowpass_coordinates_hz",
    "lowpass_torques_hz",
    "grf",
    "grf_foot",
    "grf_column",
    "heel_strike_n",
    "coordinates",
}
ISOMETRIC_MAX_MOTION_DEG = 10.0  # an isometric trial's coordinates stay within this range (a held test position)


@dataclass
class TrialData:
    name: str
    path: Path
    time: np.ndarray  # (T,)
    q: np.ndarray  # (T, n_c) rad
    qd: np.ndarray
    qdd: np.ndarray
    torques: np.ndarray  # (T, n_c) N·m
    torque_source: str  # "file" or "inverse_dynamics"
    emg: dict[str, np.ndarray]  # group -> (T,) normalised envelope
    emg_channels: dict[str, str]  # channel -> group
    emg_normalisation: dict[str, dict]
    load_kg: float
    body_mass_kg: float | None
    phase: np.ndarray  # (T,) in [0, 1) inside a rep, REST_PHASE outside (isometric trials: every frame)
    rep_index: np.ndarray  # (T,) -1 outside reps
    phase_signal: str
    dropped_frames: int = 0
    phase_coordinate: str | None = None  # the pack coordinate the phase comes from (kinematic phase; live-trackable)
    isometric: bool = False  # static-pose trial: no reps, no phase (``isometric = true``)
    extra: dict = field(default_factory=dict)
    # moment arms, lengths and static optimisation of the frames, kept by :meth:`mechanics` (a copy made with
    # dataclasses.replace shares it while its coordinates and torques are the same arrays)
    mechanics_cache: TrialMechanics | None = field(default=None, repr=False, compare=False)

    def mechanics(self, pack: PackLike) -> TrialMechanics:
        """This trial's moment arms, lengths and static-optimisation activations with ``pack``
        (:mod:`msk_core.estimate.mechanics`), computed on first use and kept: every consumer reads the same ones."""
        if self.mechanics_cache is None or not self.mechanics_cache.serves(pack, self.q, self.torques):
            self.mechanics_cache = mechanics_of(pack, self.q, self.torques)
        return self.mechanics_cache

    @property
    def hand_load_newton(self) -> float:
        return self.load_kg * GRAVITY

    @property
    def n_frames(self) -> int:
        return int(self.time.size)


def _within(time: np.ndarray, source_time: np.ndarray) -> np.ndarray:
    """Times a hair outside the source's span (< 5 % of a sample, e.g. -2e-7 s vs 0 s) are moved onto its ends."""
    dt = float(np.median(np.diff(source_time))) if source_time.size > 1 else 0.0
    lo, hi = source_time[0], source_time[-1]
    clipped = np.clip(time, lo, hi)
    return np.where(np.abs(clipped - time) <= 0.05 * dt, clipped, time)


def _listed(names: list[str], most: int = 12) -> str:
    """``names`` for a message, the first ``most`` and how many more."""
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def _closest(name: str, options: list[str]) -> str:
    near = close_names(name, options, cutoff=0.6)  # difflib's default cutoff; 'rectabd_r' finds 'RECTABD_R'
    return f"; did you mean {', '.join(near)}?" if near else ""


@dataclass
class _TrialFile:
    """A parsed trial TOML: its path, text (for line numbers in errors) and table."""

    path: Path
    text: str
    spec: dict

    @classmethod
    def read(cls, path: str | Path) -> _TrialFile:
        path = Path(path)
        if path.suffix.lower() in DATA_SUFFIXES:
            raise ConfigError(
                f"a trial is a description (TOML) of its data files, not a {path.suffix} data file: write a "
                f'trial.toml with kinematics = "{path.name}" (and torques, emg, load_kg; docs/estimation.md, '
                "'Trial description') and give that",
                path=path,
            )
        try:
            text = path.read_text()
        except (OSError, UnicodeDecodeError) as exc:
            why = exc.strerror if isinstance(exc, OSError) else "not text (a binary file?)"
            raise ConfigError(f"cannot read trial file: {why}", path=path) from None
        try:
            spec = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            m = re.search(r"line (\d+)", str(exc))
            raise ConfigError(f"invalid TOML: {exc}", path=path, line=int(m.group(1)) if m else None) from None
        return cls(path, text, spec)

    def err(self, message: str, key: str, value: object = None) -> ConfigError:
        return ConfigError(message, path=self.path, line=toml_key_line(self.text, key), field=key, value=value)

    @overload
    def number(self, key: str, default: float) -> float: ...
    @overload
    def number(self, key: str, default: None) -> float | None: ...
    def number(self, key: str, default: float | None) -> float | None:
        """The key's number, ``default`` when absent (TOML has no null: a default number gives a number)."""
        value = self.spec.get(key, default)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
            raise self.err("must be a number", key, value)
        return float(value)

    def file_of(self, key: str) -> Path:
        value = self.spec[key]
        if not isinstance(value, str):
            raise self.err("must be a path string", key, value)
        target = (self.path.parent / value).resolve()
        if not target.is_file():
            raise self.err(f"file not found: {target}", key, value)
        return target


@dataclass(frozen=True)
class _TrialOptions:
    """The trial's scalar keys, validated."""

    load_kg: float
    body_mass_kg: float | None
    start: float | None
    end: float | None
    isometric: bool
    lowpass_coordinates_hz: float | None
    lowpass_torques_hz: float | None = None
    #: pack coordinate -> (its column in the kinematics and torque files, +1 or -1 for its sign convention)
    sources: dict[str, tuple[str, float]] = field(default_factory=dict)

    def column(self, coordinate: str) -> str:
        return self.sources.get(coordinate, (coordinate, 1.0))[0]

    def signs(self, coordinates: list[str]) -> np.ndarray:
        return np.array([self.sources.get(c, (c, 1.0))[1] for c in coordinates])


def _coordinate_sources(trial: _TrialFile, pack: PackLike) -> dict[str, tuple[str, float]]:
    """The ``[coordinates]`` table: pack coordinate -> (file column, sign); a leading "-" flips the convention."""
    table = trial.spec.get("coordinates", {})
    if not isinstance(table, dict):
        raise trial.err('must be a table: pack coordinate = "column" (or "-column" to flip its sign)', "coordinates")
    coords = list(pack.coordinates)
    sources: dict[str, tuple[str, float]] = {}
    for coordinate, column in table.items():
        if coordinate not in coords:
            raise trial.err(
                f"[coordinates] names {coordinate!r}, not a coordinate of pack {pack.name!r}"
                + (_closest(coordinate, coords) or f" (its coordinates: {_listed(coords)})"),
                coordinate,
                coordinate,
            )
        if not isinstance(column, str) or column.lstrip("-").strip() == "" or column.startswith("--"):
            raise trial.err(
                'must be the column name, with "-" before it to flip its sign (e.g. "-knee_angle_r")',
                coordinate,
                column,
            )
        sources[coordinate] = (column[1:], -1.0) if column.startswith("-") else (column, 1.0)
    return sources


def _parse_options(trial: _TrialFile, pack: PackLike) -> _TrialOptions:
    spec = trial.spec
    unknown = sorted(set(spec) - KNOWN_KEYS)
    if unknown:
        raise trial.err(f"unknown key{_closest(unknown[0], sorted(KNOWN_KEYS))}", unknown[0], unknown[0])
    if "kinematics" not in spec:
        raise ConfigError("missing required key", path=trial.path, field="kinematics")
    if not isinstance(spec.get("name", ""), str) or spec.get("name") == "":
        raise trial.err("must be a non-empty string (the trial's name in reports)", "name", spec.get("name"))
    if re.search(r"[/\\\x00]", spec.get("name", "")) or spec.get("name") in (".", ".."):
        raise trial.err("must not contain / or \\ (reports name their files after the trial)", "name", spec.get("name"))
    load_kg = trial.number("load_kg", 0.0)
    if (problem := load_problem(load_kg)) is not None:
        raise trial.err(problem, "load_kg", load_kg)
    body_mass = trial.number("body_mass_kg", None)
    if body_mass is not None and (problem := body_mass_problem(body_mass)) is not None:
        raise trial.err(problem, "body_mass_kg", body_mass)
    isometric = spec.get("isometric", False)
    if not isinstance(isometric, bool):
        raise trial.err("must be true or false", "isometric", isometric)
    if isometric and "torques" not in spec:
        raise trial.err(
            "an isometric trial needs the measured joint torques (`torques = ...`): inverse dynamics of a static pose "
            "knows nothing of the push against the dynamometer",
            "isometric",
            isometric,
        )
    cutoffs: dict[str, float | None] = {}
    for key in ("lowpass_coordinates_hz", "lowpass_torques_hz"):
        cutoff = cutoffs[key] = trial.number(key, None)
        if cutoff is not None and cutoff <= 0:
            raise trial.err("must be > 0 (leave the key out for no filtering)", key, cutoff)
    if cutoffs["lowpass_torques_hz"] is not None and "torques" not in spec:
        raise trial.err(
            "filters the torque file; without `torques` the torques come from the pack's inverse dynamics of the "
            "(filtered) coordinates",
            "lowpass_torques_hz",
            cutoffs["lowpass_torques_hz"],
        )
    return _TrialOptions(
        load_kg,
        body_mass,
        trial.number("start", None),
        trial.number("end", None),
        isometric,
        cutoffs["lowpass_coordinates_hz"],
        cutoffs["lowpass_torques_hz"],
        _coordinate_sources(trial, pack),
    )


@dataclass
class _Kinematics:
    storage: Storage
    selected: np.ndarray  # rows of the storage within [start, end]
    time: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray


#: Kinematics sampled slower than this are not a movement's (motion capture and IMUs give 15-200 Hz): times in
#: milliseconds read as seconds would otherwise pass, with every delay and rate 1000 times off (a file of up to
#: 1 kHz then reads as 1 Hz or slower). Isometric trials are exempt: a held pose may be two rows seconds apart.
MIN_KINEMATICS_RATE_HZ = 2.0


def _check_motion_rate(kin: Storage) -> None:
    if kin.n_rows < 2:
        return
    interval = float(np.median(np.diff(kin.time)))
    if interval > 1.0 / MIN_KINEMATICS_RATE_HZ:
        raise InputError(
            f"the kinematics are sampled every {interval:g} s ({1 / interval:.3g} Hz), slower than "
            f"{MIN_KINEMATICS_RATE_HZ:g} Hz: are the times in milliseconds? The time column must be in seconds "
            "(a held pose, two rows seconds apart, is an isometric trial: isometric = true)",
            path=kin.path,
            field="time",
        )


def _read_kinematics(trial: _TrialFile, options: _TrialOptions, pack: PackLike) -> _Kinematics:
    coords = list(pack.coordinates)
    kin = read_sto(trial.file_of("kinematics"))
    kin.check_increasing("kinematics")
    if not options.isometric:  # a held pose may be written as two rows seconds apart
        _check_motion_rate(kin)
    for c in coords:
        column = options.column(c)
        if not kin.has_column(column):
            # no close name: another model's kinematics (found with held-out data); say what each side has
            hint = (
                f"{_closest(column, kin.columns)} (its columns: {_listed(kin.columns)}; pack {pack.name!r} needs "
                f"{_listed(coords)}: kinematics of the pack's model, or the trial's [coordinates] table naming each "
                f'one\'s column: {c} = "<its column>", or "-<its column>" for the other sign convention)'
            )
            named = f"column {column!r} (its [coordinates] entry) for" if column != c else "column for"
            raise InputError(f"kinematics has no {named} pack coordinate {c!r}{hint}", path=kin.path, field=column)
    q_all = kin.select([options.column(c) for c in coords]) * options.signs(coords)
    if kin.in_degrees:
        q_all = np.deg2rad(q_all)  # pack coordinates are rotational
    sel = np.ones(kin.n_rows, dtype=bool)
    if options.start is not None:
        sel &= kin.time >= options.start
    if options.end is not None:
        sel &= kin.time <= options.end
    if options.start is not None and options.end is not None and options.start >= options.end:
        raise trial.err(f"start must come before end (end = {options.end:g})", "start", options.start)
    if sel.sum() < 3:
        raise trial.err(
            f"fewer than 3 kinematics frames between start and end ({int(sel.sum())}); the kinematics span "
            f"{seconds(kin.time[0])} .. {seconds(kin.time[-1])} s",
            "start" if options.start is not None else "end",
            (options.start, options.end),
        )
    time = kin.time[sel]
    if options.lowpass_coordinates_hz is not None:
        # as OpenSim's AnalyzeTool prepares a coordinates file: whole file filtered, then the window taken
        try:
            filtered = lowpass_coordinates(kin.time, q_all, options.lowpass_coordinates_hz)
        except InputError as exc:
            raise trial.err(
                f"{exc} (kinematics {kin.path})", "lowpass_coordinates_hz", options.lowpass_coordinates_hz
            ) from None
        q, qd, qdd = (x[sel] for x in filtered)
    else:
        q = q_all[sel]
        qd = np.gradient(q, time, axis=0)
        qdd = np.gradient(qd, time, axis=0)
    _check_within_ranges(kin, q, coords, pack)
    return _Kinematics(kin, sel, time, q, qd, qdd)


MOSTLY_OUT_OF_RANGE = 0.5  # a trial this much outside the pack's ranges is refused: wrong units or the wrong model


def _check_within_ranges(kin: Storage, q: np.ndarray, coords: list[str], pack: PackLike) -> None:
    """:class:`InputError` when most frames lie outside the pack's fitted ranges (every such frame would be refused,
    so the estimate would be NaN throughout), naming the coordinate that is out most often, its values against the
    range, and a likely cause."""
    ranges = fitted_ranges(pack)
    if ranges is None or q.size == 0:
        return
    _, usable = clamp_to_ranges(q, ranges)
    finite = np.all(np.isfinite(q), axis=1)
    if np.count_nonzero(finite & ~usable) <= MOSTLY_OUT_OF_RANGE * max(int(finite.sum()), 1):
        return
    # the coordinate that leaves its range beyond the clamp most often (one coordinate at a time, by the one rule)
    refused = [
        np.count_nonzero(finite & ~clamp_to_ranges(q[:, k : k + 1], (ranges[0][k : k + 1], ranges[1][k : k + 1]))[1])
        for k in range(q.shape[1])
    ]
    j = int(np.argmax(refused))
    values = np.degrees(q[finite, j])
    looks_like_degrees = not kin.in_degrees and np.nanmax(np.abs(q[finite])) > 2 * np.pi
    raise InputError(
        f"{np.count_nonzero(finite & ~usable)} of {int(finite.sum())} frames lie outside the fitted ranges of pack "
        f"{pack.name!r}, e.g. {coords[j]} at {values.min():.1f} .. {values.max():.1f} deg against "
        f"[{np.degrees(ranges[0][j]):.1f}, {np.degrees(ranges[1][j]):.1f}] deg"
        + (
            (
                "; the angles look like degrees in a file whose header says inDegrees=no"
                if any(key.lower() == "indegrees" for key in kin.header)
                else "; the angles look like degrees in a file whose header has no inDegrees line (read as radians): "
                "add inDegrees=yes before endheader"
            )
            if looks_like_degrees
            else "; is this the pack's model and sign convention?"
        ),
        path=kin.path,
        field=coords[j],
    )


#: The model's root (OpenSim's pelvis free joint) columns of a kinematics file: rotations (deg or rad as the file
#: says) and translations (m)
ROOT_ROTATIONS = ("pelvis_tilt", "pelvis_list", "pelvis_rotation")
ROOT_TRANSLATIONS = ("pelvis_tx", "pelvis_ty", "pelvis_tz")
#: A root that turns or moves this much within the trial is not the fixed, upright root of the pack's dynamics
ROOT_MAX_TURN_DEG = 5.0
ROOT_MAX_MOVE_M = 0.10


def _check_root_still(trial: _TrialFile, kin: _Kinematics) -> None:
    """Refuse to compute a trial's torques with the pack's inverse dynamics when its kinematics move the model's root:
    the pack holds the pelvis fixed and upright (its dynamics are rooted at the ground) and knows no ground reaction
    force, so a stoop whose pelvis tilts 65 deg got an L5/S1 torque of half the recorded one, without a word."""
    storage, rows = kin.storage, kin.selected
    moved = []
    for name in ROOT_ROTATIONS:
        if storage.has_column(name):
            values = storage.column(name)[rows]
            span = float(np.ptp(values if storage.in_degrees else np.degrees(values))) if values.size else 0.0
            if span > ROOT_MAX_TURN_DEG:
                moved.append(f"{name} spans {span:.1f} deg")
    for name in ROOT_TRANSLATIONS:
        if storage.has_column(name):
            values = storage.column(name)[rows]
            span = float(np.ptp(values)) if values.size else 0.0
            if span > ROOT_MAX_MOVE_M:
                moved.append(f"{name} spans {span:.2f} m")
    if moved:
        raise trial.err(
            f"no torques file, and the pack's inverse dynamics cannot stand in for one here: in {storage.path} the "
            f"pelvis moves by more than {ROOT_MAX_TURN_DEG:g} deg or {ROOT_MAX_MOVE_M:g} m ({'; '.join(moved)}), "
            "where the pack holds it fixed and upright, with no ground reaction force. Give the trial's inverse "
            "dynamics as torques (e.g. OpenSim's, with its external loads)",
            "torques",
            None,
        )


def _torque_column(tq: Storage, coordinate: str) -> str:
    """The torque column of ``coordinate``: OpenSim's inverse-dynamics name (``<c>_moment``, ``<c>_force`` for a
    translation) before the bare name, which in a file that also holds the angles is the angle."""
    for name in (f"{coordinate}_moment", f"{coordinate}_force", coordinate):
        if tq.has_column(name):
            return name
    raise InputError(
        f"torque file has none of {coordinate + '_moment'!r}, {coordinate + '_force'!r}, {coordinate!r}"
        f"{_closest(coordinate, tq.columns)}",
        path=tq.path,
        field=coordinate,
    )


def _check_not_angles(tq: Storage, cols: list[str], raw: np.ndarray, kin: _Kinematics) -> None:
    """Refuse torque columns that are the kinematics' angles (a kinematics file given as the torques): the same
    values, in radians or in degrees, at the same times."""
    angles = kin.storage
    if not all(angles.has_column(c) for c in cols) or not np.array_equal(tq.time, angles.time):
        return
    q = angles.select(cols)
    same = np.allclose(raw, q, equal_nan=True) or np.allclose(raw, np.degrees(q), equal_nan=True)
    same = same or np.allclose(raw, np.radians(q), equal_nan=True)
    if same:
        raise InputError(
            f"the torque columns ({', '.join(cols)}) hold the same values as the kinematics file {angles.path}: "
            "angles, not torques. Give the trial's inverse dynamics (e.g. OpenSim's, columns <coordinate>_moment)",
            path=tq.path,
            field="torques",
        )


def _attach_torques(trial: _TrialFile, options: _TrialOptions, pack: PackLike, kin: _Kinematics):
    """(torques, frames kept of the kinematics window, torque source, frames dropped); trims ``kin`` to the kept frames."""
    coords = list(pack.coordinates)
    if "torques" not in trial.spec:
        _check_root_still(trial, kin)
        torques = _modelled_torques(pack, kin, options.load_kg, np.arange(len(kin.time)))
        return torques, np.ones(len(kin.time), dtype=bool), "inverse_dynamics", _DroppedFrames()
    tq = read_sto(trial.file_of("torques"))
    tq.check_increasing("torque")
    cols = [_torque_column(tq, options.column(c)) for c in coords]
    raw = tq.select(cols)
    _check_not_angles(tq, cols, raw, kin)
    raw = raw * options.signs(coords)  # a flipped coordinate's moment flips with its angle
    if options.lowpass_torques_hz is not None:
        # the same zero-phase filter as the coordinates' (whole file, then the window), without the spline's derivatives
        try:
            raw = lowpass_coordinates(tq.time, raw, options.lowpass_torques_hz)[0]
        except InputError as exc:
            raise trial.err(f"{exc} (torques {tq.path})", "lowpass_torques_hz", options.lowpass_torques_hz) from None
    at = _within(kin.time, tq.time)
    torques = np.column_stack(
        [np.interp(at, tq.time, raw[:, j], left=np.nan, right=np.nan) for j in range(len(coords))]
    )
    keep = np.all(np.isfinite(torques), axis=1)
    outside = (at < tq.time[0]) | (at > tq.time[-1])
    dropped = _DroppedFrames(
        outside=int(np.count_nonzero(outside)),
        not_finite=int(np.count_nonzero(~keep & ~outside)),
        first_not_finite_s=float(kin.time[~keep & ~outside][0]) if np.any(~keep & ~outside) else None,
        torque_span=f"{seconds(tq.time[0])} .. {seconds(tq.time[-1])} s",
        kinematics_span=f"{seconds(kin.time[0])} .. {seconds(kin.time[-1])} s",
    )
    kin.time, kin.q, kin.qd, kin.qdd = kin.time[keep], kin.q[keep], kin.qd[keep], kin.qdd[keep]
    if not options.isometric:  # a maximal contraction's torques are its own, far above the pose's gravity
        against = _check_torque_units(tq, pack, kin, torques[keep], options.load_kg)
        dropped = replace(dropped, against_model=against)
    return torques[keep], keep, "file", dropped


#: The recorded torques' RMS against the pack's inverse dynamics of the same motion: 1.0-1.3 on every trial of
#: recordings/ (the walk with its ground reaction forces, the real lifts, the synthetic lifts), 8-12 for a lift whose
#: load_kg is left out, more for forces the pack does not model (a cable, a dynamometer); N·m/kg gives about
#: 1/60-1/80, N·mm about 1000. Only ratios that far off are refused: they are units, not physics.
TORQUE_SCALE_BOUNDS = (1 / 30, 300.0)


def _modelled_torques(pack: PackLike, kin: _Kinematics, load_kg: float, frames: np.ndarray) -> np.ndarray:
    """The pack's inverse dynamics at ``frames`` of the kinematics with ``load_kg`` in the hands; NaN where a pose lies
    outside the fitted ranges by the one rule the estimator applies (clamped within the tolerance: a tutorial motion
    starting 0.1 deg below the range was refused here; no torque further out)."""
    q, usable = clamp_to_ranges(kin.q[frames], fitted_ranges(pack))
    qd, qdd, hand = kin.qd[frames], kin.qdd[frames], load_kg * GRAVITY
    n_c = len(pack.coordinates)
    return np.array(
        [pack.inverse_dynamics(q[i], qd[i], qdd[i], hand) if usable[i] else np.full(n_c, np.nan) for i in range(len(q))]
    ).reshape(len(q), n_c)


def _check_torque_units(
    tq: Storage, pack: PackLike, kin: _Kinematics, torques: np.ndarray, load_kg: float
) -> tuple[tuple[str, float], ...]:
    """Refuse torques that are not in N·m (their RMS over 60 frames against the pack's inverse dynamics there) or
    whose every column runs against it (external moments, the other sign convention); return the columns that alone
    run against it (correlation below -:data:`TORQUE_SIGN_R`), for a note."""
    frames = np.flatnonzero(clamp_to_ranges(kin.q, fitted_ranges(pack))[1])
    if frames.size < 10:
        return ()
    frames = frames[np.linspace(0, frames.size - 1, 60).astype(int)]
    modelled = _modelled_torques(pack, kin, load_kg, frames)
    expected = float(np.sqrt(np.mean(modelled**2)))
    if not expected > 0:
        return ()
    against = _against_model(list(pack.coordinates), modelled, torques[frames])
    if against and len(against) == len(pack.coordinates):
        raise InputError(
            "every torque column runs against the pack's inverse dynamics of the same motion (correlation "
            + ", ".join(f"{c} {r:+.2f}" for c, r in against)
            + f" over {frames.size} frames): external moments, or the opposite sign convention? The pack's torques "
            "are the muscles' (internal) moments along its coordinates",
            path=tq.path,
            field="torques",
        )
    scale = float(np.sqrt(np.mean(torques[frames] ** 2))) / expected
    low, high = TORQUE_SCALE_BOUNDS
    if not low <= scale <= high:
        guess = "N·m/kg (divided by the body mass)?" if scale < low else "N·mm?"
        raise InputError(
            f"the torques are {scale:.3g} times the pack's inverse dynamics of the same motion with load_kg = "
            f"{load_kg:g} (RMS over {frames.size} frames; between {low:.3g} and {high:g} for torques in N·m): are "
            f"they in {guess} Torques must be N·m (body_mass_kg only adds N·m/kg to the reports)",
            path=tq.path,
            field="torques",
        )
    return against


#: A recorded torque column whose correlation with the pack's inverse dynamics of the same motion is below minus this
#: runs against it. Measured on every trial of recordings/: 0.72-0.74 on the real lifts, 1.00 on the synthetic ones,
#: 0.19-0.49 on the walk (whose ground reaction forces the pack does not model); a column with its sign flipped gives
#: the negative of those (a held-out walk's knee in the other model's convention: -0.35).
TORQUE_SIGN_R = 0.15


def _against_model(coords: list[str], modelled: np.ndarray, recorded: np.ndarray) -> tuple[tuple[str, float], ...]:
    """(coordinate, correlation) of the recorded torque columns that run against the modelled ones."""
    out = []
    for j, coordinate in enumerate(coords):
        ok = np.isfinite(modelled[:, j]) & np.isfinite(recorded[:, j])
        a, b = modelled[ok, j], recorded[ok, j]
        if ok.sum() >= 10 and np.std(a) > 0 and np.std(b) > 0:
            r = float(np.corrcoef(a, b)[0, 1])
            if r < -TORQUE_SIGN_R:
                out.append((coordinate, round(r, 2)))
    return tuple(out)


@dataclass(frozen=True)
class _DroppedFrames:
    """Kinematics frames without a torque: outside the torque file's span, or where it is not finite."""

    outside: int = 0
    not_finite: int = 0
    first_not_finite_s: float | None = None
    torque_span: str = ""
    kinematics_span: str = ""
    against_model: tuple[tuple[str, float], ...] = ()  # torque columns against the pack's inverse dynamics (sign)

    @property
    def total(self) -> int:
        return self.outside + self.not_finite

    def notes(self) -> dict:
        """For ``TrialData.extra`` (what :func:`trial_notes` says)."""
        out: dict = {}
        if self.outside:
            out["torque_frames_outside"] = self.outside
        if self.not_finite:
            out["torque_frames_not_finite"] = (self.not_finite, self.first_not_finite_s)
        if self.against_model:
            out["torques_against_model"] = dict(self.against_model)
        return out


def _check_held_pose(kin: _Kinematics, coords: list[str]) -> None:
    """An isometric trial holds one pose (on the frames used; gaps (NaN) in the kinematics do not hide a movement)."""
    motion = np.degrees(np.nan_to_num(np.nanmax(kin.q, axis=0) - np.nanmin(kin.q, axis=0), nan=0.0))
    worst = int(np.argmax(motion))
    if motion[worst] > ISOMETRIC_MAX_MOTION_DEG:
        raise InputError(
            f"an isometric trial holds one pose, but {coords[worst]!r} moves by {motion[worst]:.1f} deg "
            f"(> {ISOMETRIC_MAX_MOTION_DEG:g}); drop `isometric = true` or trim with start/end",
            path=kin.storage.path,
            field=coords[worst],
            value=round(float(motion[worst]), 1),
        )


@dataclass
class _Phase:
    phase: np.ndarray
    rep_index: np.ndarray
    signal: str
    coordinate: str | None
    extra: dict


def _trial_phase(
    trial: _TrialFile,
    options: _TrialOptions,
    pack: PackLike,
    kin: _Kinematics,
    torques: np.ndarray,
    kin_keep: np.ndarray,
) -> _Phase:
    """Reps and phase from the trial's phase signal (``phase_signal``, else the pack's default)."""
    coords = list(pack.coordinates)
    default_signal = DEFAULT_PHASE_COORDINATES.get(pack.name)
    if default_signal not in coords:
        default_signal = f"torque:{coords[0]}"
    phase_signal = trial.spec.get("phase_signal", default_signal)
    if not isinstance(phase_signal, str):
        raise trial.err("must be a string", "phase_signal", phase_signal)
    if options.isometric and "phase_signal" in trial.spec:
        raise trial.err("an isometric trial has no reps, so no phase", "phase_signal", phase_signal)
    n = kin.time.size
    if options.isometric:
        return _Phase(np.full(n, REST_PHASE), np.full(n, -1), "none (isometric)", None, {})
    if "grf" in trial.spec:
        if "phase_signal" in trial.spec:
            raise trial.err("grf and phase_signal both define the reps: keep one", "phase_signal", phase_signal)
        return _gait_cycles(trial, kin.time)
    if phase_signal.startswith("torque:"):
        c = phase_signal.split(":", 1)[1]
        if c not in coords:
            raise trial.err(f"not a pack coordinate{_closest(c, coords)}", "phase_signal", phase_signal)
        coordinate, signal, phase_of = None, torques[:, coords.index(c)], torque_phase
    elif phase_signal in coords:  # radians, as the live node sees it
        coordinate, signal, phase_of = phase_signal, kin.q[:, coords.index(phase_signal)], kinematic_phase
    elif kin.storage.has_column(phase_signal):
        coordinate, signal = None, kin.storage.column(phase_signal)[kin.selected][kin_keep]
        phase_of = kinematic_phase
    else:
        raise trial.err(
            f"no such kinematics column{_closest(phase_signal, kin.storage.columns)}", "phase_signal", phase_signal
        )
    if not np.all(np.isfinite(signal)):
        bad = int(np.flatnonzero(~np.isfinite(signal))[0])
        raise trial.err(
            f"the phase signal is not finite at t = {seconds(kin.time[bad])} s", "phase_signal", phase_signal
        )
    try:
        phase, rep_index = phase_of(kin.time, signal)
    except EstimationError as exc:
        # msk_core.signal.reps only counts complete reps (rest - excursion - rest): a trial of a single movement
        # (arm26's one flexion) has none; it still serves what needs no phase (static optimisation, inverse dynamics)
        return _Phase(np.full(n, REST_PHASE), np.full(n, -1), phase_signal, None, {"no_reps": str(exc)})
    return _Phase(phase, rep_index, phase_signal, coordinate, {})


GRF_FEET = ("r", "l")


def vertical_grf_column(columns: list[str], foot: str, path: Path | None = None) -> str:
    """The vertical ground-reaction-force column of ``foot`` ("r" or "l") among an external-loads file's columns:
    a name that carries the side (``r_ground_force_vy``, ``ground_force_r_vy``, ``R_ground_force_vy``,
    ``right_ground_force_vy``, ...), else the unprefixed ``ground_force_vy`` when the other foot's column carries
    its side (OpenSim's examples name the right foot's force ground_force_* and the left one's l_ground_force_*).
    :class:`InputError` naming the vertical-force columns there are when none or several match."""
    if foot not in GRF_FEET:
        raise ConfigError("must be 'r' or 'l'", field="grf_foot", value=foot)
    other = "l" if foot == "r" else "r"
    word = {"r": "right", "l": "left"}

    vertical = [c for c in columns if c.lower().endswith("_vy") and "force" in c.lower()]

    def sided(side: str) -> list[str]:
        return [c for c in vertical if {side, word[side]} & set(re.split(r"[_\W]+", c.lower()))]

    mine, theirs = sided(foot), sided(other)
    if len(mine) == 1:
        return mine[0]
    if len(mine) > 1:
        raise InputError(
            f"several vertical-force columns of foot {foot!r}: {mine}; name one as grf_column", path=path, field="grf"
        )
    unsided = [c for c in vertical if c not in theirs]
    if theirs and len(unsided) == 1:
        return unsided[0]
    raise InputError(
        f"no vertical ground-reaction-force column of foot {foot!r} by name (vertical-force columns: "
        f"{vertical or 'none'}); name it as grf_column",
        path=path,
        field="grf",
    )


def _gait_cycles(trial: _TrialFile, time: np.ndarray) -> _Phase:
    """Reps = gait cycles from the force plate: heel strikes of ``grf_foot`` within the trial's window."""
    path = trial.file_of("grf")
    grf = read_sto(path)
    foot = trial.spec.get("grf_foot", "r")
    if foot not in GRF_FEET:
        raise trial.err("must be 'r' or 'l'", "grf_foot", foot)
    column = trial.spec.get("grf_column")
    if column is None:
        column = vertical_grf_column(list(grf.columns), foot, path)
    elif not isinstance(column, str) or not grf.has_column(column):
        raise trial.err(
            f"no such column in {path.name}{_closest(str(column), list(grf.columns))}", "grf_column", column
        )
    threshold = trial.number("heel_strike_n", CONTACT_THRESHOLD_N)
    if threshold <= 0:
        raise trial.err("must be > 0", "heel_strike_n", threshold)
    strikes = heel_strikes(grf.time, grf.column(column), threshold_n=threshold)
    half = 0.5 * float(np.median(np.diff(time))) if time.size > 1 else 0.0
    strikes = strikes[(strikes >= time[0] - half) & (strikes <= time[-1] + half)]
    signal = f"grf:{column}"
    if strikes.size < 2:
        no = (
            f"{strikes.size} heel strike(s) of {column} > {threshold:g} N within the trial "
            f"({seconds(time[0])} .. {seconds(time[-1])} s; {path.name} spans {seconds(grf.time[0])} .. "
            f"{seconds(grf.time[-1])} s): no complete gait cycle"
        )
        return _Phase(np.full(time.size, REST_PHASE), np.full(time.size, -1), signal, None, {"no_reps": no})
    phase, index = gait_cycle_phase(time, strikes)
    return _Phase(phase, index, signal, None, {"heel_strikes": strikes})


def trial_notes(trial: TrialData) -> list[str]:
    """What loading left out of a trial, in words for the commands to print (nothing when it used everything)."""
    notes = []
    if "no_reps" in trial.extra and not trial.isometric:
        notes.append(f"{trial.extra['no_reps']}: every frame counts as rest, and per-cycle plots stay empty")
    if outside := trial.extra.get("torque_frames_outside"):
        notes.append(
            f"{outside} kinematics frames outside the torque file's time span left out ({trial.n_frames} kept)"
        )
    if not_finite := trial.extra.get("torque_frames_not_finite"):
        count, first = not_finite
        notes.append(
            f"{count} kinematics frames left out where the torque file is not finite (NaN), the first at t = "
            f"{seconds(first)} s ({trial.n_frames} kept)"
        )
    for coordinate, r in trial.extra.get("torques_against_model", {}).items():
        notes.append(
            f"the torque of {coordinate} runs against the pack's inverse dynamics of the same motion (correlation "
            f"{r:+.2f}): is its sign the pack's (the muscles' moment along its coordinate)? Its angles are (they lie "
            "in the pack's ranges), so the moment alone runs the other way: an external moment, or inverse dynamics "
            "of another convention than the kinematics; negate that column of the torque file (the trial file's "
            "[coordinates] table flips a coordinate's angle and moment together, for kinematics of the other "
            "convention too)"
        )
    for group, envelope in trial.emg.items():
        missing = int(np.count_nonzero(~np.isfinite(envelope)))
        if missing:
            notes.append(
                f"EMG of {group}: {missing} of {envelope.size} frames not measured (NaN, or outside the EMG file's "
                "time span); those frames carry no EMG term for it"
            )
    return notes


def load_trial(path: str | Path, pack: PackLike) -> TrialData:
    """Read a trial TOML and everything it points to, checked against the pack."""
    trial = _TrialFile.read(path)
    options = _parse_options(trial, pack)
    coords = list(pack.coordinates)
    kin = _read_kinematics(trial, options, pack)
    torques, kin_keep, source, dropped = _attach_torques(trial, options, pack, kin)
    if kin.time.size < 3:
        raise InputError(
            f"fewer than 3 frames left where the torque file covers the kinematics ({kin.time.size}): the torque file "
            f"spans {dropped.torque_span}, the kinematics between start and end {dropped.kinematics_span}"
            + (f"; {dropped.not_finite} frames have a torque that is not finite" if dropped.not_finite else ""),
            path=trial.path,
            field="torques",
        )
    if options.isometric:
        _check_held_pose(kin, coords)
    if "emg" in trial.spec:
        emg, channels, norm = _load_emg(trial.spec, trial.path, trial.text, trial.file_of, trial.err, pack, kin.time)
    else:
        emg, channels, norm = {}, {}, {}
    phase = _trial_phase(trial, options, pack, kin, torques, kin_keep)
    extra = dict(phase.extra) | dropped.notes()
    if options.lowpass_coordinates_hz is not None:
        extra["lowpass_coordinates_hz"] = options.lowpass_coordinates_hz
    return TrialData(
        # without a name: the file's, or its folder's for a trial.toml (a folder of trials, one per folder)
        name=str(trial.spec.get("name", trial.path.parent.name if trial.path.stem == "trial" else trial.path.stem)),
        path=trial.path,
        time=kin.time,
        q=kin.q,
        qd=kin.qd,
        qdd=kin.qdd,
        torques=torques,
        torque_source=source,
        emg=emg,
        emg_channels=channels,
        emg_normalisation=norm,
        load_kg=options.load_kg,
        body_mass_kg=options.body_mass_kg,
        phase=phase.phase,
        rep_index=phase.rep_index,
        phase_signal=phase.signal,
        dropped_frames=dropped.total,
        phase_coordinate=phase.coordinate,
        isometric=options.isometric,
        extra=extra,
    )


#: EMG recordings that are not OpenSim storages: ``msk emg envelope`` reads them and writes one
_EMG_RECORDING_SUFFIXES = (".c3d", ".anc", ".csv")


#: The first line of an envelope file ``msk emg envelope`` wrote without ``--mvc`` (services/commands/emg.py).
_UNNORMALISED_ENVELOPES = re.compile(r"^EMG envelopes \((V|file units)\)")


def _load_emg(spec, path, text, file_of, err, pack: PackLike, time):
    emg_file = file_of("emg")
    if Path(emg_file).suffix.lower() in _EMG_RECORDING_SUFFIXES:
        raise err(
            f"a trial's EMG is an OpenSim storage (.sto/.mot) of normalised envelopes or raw EMG; make one from this "
            f"recording with: msk emg envelope {emg_file} --zero-phase --mvc MVC_TRIAL -o emg.sto (normalised by the "
            f'MVC trial; then emg = "emg.sto"), or without --mvc and each channel\'s MVC as [emg_max]',
            "emg",
            str(spec.get("emg")),
        )
    storage: Storage = read_sto(emg_file)
    storage.check_increasing("EMG")
    mapping = spec.get("emg_map")
    if not isinstance(mapping, dict) or not mapping:
        raise err("an [emg_map] table (EMG column -> group) is required with emg", "emg_map", mapping)
    maxima = spec.get("emg_max", {})
    unscaled = [ch for ch in mapping if not isinstance(maxima, dict) or ch not in maxima]
    if _UNNORMALISED_ENVELOPES.match(storage.name) and unscaled:
        # volts at an amplifier's output pass the range checks below (peaks 0.007-0.12 V on a held-out walk): the
        # file's own first line says what it holds
        raise err(
            f"{Path(emg_file).name} holds EMG envelopes that are not normalised (its first line: {storage.name!r}, as "
            "msk emg envelope writes them without --mvc), and activation is 0-1: make them again with --mvc "
            "MVC_TRIAL, or give each channel's MVC amplitude in the file's units as [emg_max]",
            f"emg_map.{unscaled[0]}",
            unscaled[0],
        )
    is_envelope = spec.get("emg_is_envelope", True)
    if not isinstance(is_envelope, bool):
        raise err("must be true or false", "emg_is_envelope", is_envelope)
    if not isinstance(maxima, dict):
        raise err("must be a table channel -> value", "emg_max", maxima)
    groups = list(pack.groups)
    channels = list(mapping)
    for ch, group in mapping.items():
        if not storage.has_column(ch):
            raise err(f"EMG file has no column {ch!r}{_closest(ch, storage.columns)}", f"emg_map.{ch}", ch)
        if group not in groups:
            raise err(f"not a group of pack {pack.name!r}{_closest(str(group), groups)}", f"emg_map.{ch}", group)
    for ch in maxima:
        if ch not in mapping:  # a misspelt channel would be left unnormalised without a word
            raise err(f"not a channel of [emg_map]{_closest(str(ch), channels)}", f"emg_max.{ch}", ch)
    raw = storage.select(channels)
    if not is_envelope:
        from msk_core.signal.emg import EmgFilterConfig, envelope_zero_phase_noncausal

        try:
            step = uniform_step(storage.time)
        except InputError as exc:
            raise InputError(f"raw EMG (emg_is_envelope = false) {exc}", path=storage.path, field="time") from None
        raw = envelope_zero_phase_noncausal(raw, EmgFilterConfig(rate_hz=1.0 / step))
    by_group: dict[str, list[np.ndarray]] = {}
    norm: dict[str, dict] = {}
    for j, ch in enumerate(channels):
        scale = maxima.get(ch, 1.0)
        if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
            raise err("must be a positive number", f"emg_max.{ch}", scale)
        x = np.interp(_within(time, storage.time), storage.time, raw[:, j] / scale, left=np.nan, right=np.nan)
        _check_normalised(x, ch, storage, time, err, given=ch in maxima)
        group = mapping[ch]
        by_group.setdefault(group, []).append(x)
        norm[ch] = {
            "group": group,
            "divisor": float(scale),
            "source": "emg_max in trial file" if ch in maxima else "as recorded (already normalised)",
            "envelope": "as recorded" if is_envelope else "zero-phase offline chain (msk_core.signal.emg)",
        }
    with warnings.catch_warnings():  # a frame no channel of a group measured stays NaN (said by trial_notes)
        warnings.simplefilter("ignore", RuntimeWarning)
        # several channels of one group: the mean of all of them, each weighing the same
        emg = {g: xs[0] if len(xs) == 1 else np.nanmean(xs, axis=0) for g, xs in by_group.items()}
    return emg, dict(mapping), norm


#: A normalised envelope is activation, 0-1: above about 1 only briefly (a dynamic effort beyond the MVC test's).
#: One whose 99th percentile exceeds this is in other units (% of MVC, mV, ADC counts).
MAX_NORMALISED_P99 = 3.0
#: One whose largest value is below this is in volts (a raw envelope is 1e-6-1e-3 V) or a dead electrode.
MIN_NORMALISED_PEAK = 1e-3


def _check_normalised(x: np.ndarray, channel: str, storage: Storage, time: np.ndarray, err, given: bool) -> None:
    """Refuse an EMG column that gives no sample within the trial's frames, or that is not a normalised envelope
    (activation 0-1) after its ``emg_max`` divisor: it would be fitted as activation without a word."""
    finite = x[np.isfinite(x)]
    if finite.size == 0:
        inside = (storage.time >= time[0]) & (storage.time <= time[-1])
        why = (
            f"its values there are all NaN ({int(np.count_nonzero(inside))} samples)"
            if inside.any()
            else f"the EMG file spans {seconds(storage.time[0])} .. {seconds(storage.time[-1])} s"
        )
        raise err(
            f"EMG column {channel!r} has no sample within the trial's frames ({seconds(time[0])} .. "
            f"{seconds(time[-1])} s): {why}",
            f"emg_map.{channel}",
            channel,
        )
    divisor = f"after its divisor [emg_max] {channel}" if given else "with no [emg_max] divisor"
    p99, peak = float(np.percentile(finite, 99)), float(np.max(np.abs(finite)))
    if p99 > MAX_NORMALISED_P99:
        raise err(
            f"EMG column {channel!r} is not a normalised envelope ({divisor}): its 99th percentile is {p99:.4g}, where "
            "activation is 0-1; give its MVC as [emg_max] (e.g. 100 for % of MVC) or export it normalised",
            f"emg_max.{channel}" if given else f"emg_map.{channel}",
            p99,
        )
    if peak < MIN_NORMALISED_PEAK:
        raise err(
            f"EMG column {channel!r} is not a normalised envelope ({divisor}): its largest value is {peak:.3g}, raw "
            "units such as volts or a dead electrode; give its MVC as [emg_max] (the envelope's value at maximal "
            "effort, in the file's units) or leave the channel out of [emg_map]",
            f"emg_max.{channel}" if given else f"emg_map.{channel}",
            peak,
        )
