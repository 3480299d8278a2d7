"""Calibration trials from a recorded session (``msk trials``): a lab's first day is `msk live` without a profile,
then a profile calibrated on what it recorded.

Per set of the recording (its sets as ``msk report`` finds them: the operator's marks and load events, else the whole
session), a folder ``set<N>/`` with the trial files ``msk calibrate`` reads (msk_core.estimate.trial):

* ``ik.sto``: the joint angles the kinematics node published (the pack's coordinates, radians), on the joints' clock;
* ``emg.sto``: the raw EMG of the electrodes of the session file's ``[electrodes]`` map (volts as recorded), each
  sample placed on the joints' clock as the live estimator placed it: with the offset of the session's
  ``summary.json`` (``clocks``, e.g. by the accelerations) when the recording has one beside it, else by the
  host's receipt times (:func:`msk_core.signal.host_clock.windowed_offsets`, the arrival mapping, no stated
  latency), the set's median offset; samples the base never delivered are NaN rows;
* ``trial.toml``: both, ``emg_is_envelope = false`` (the offline zero-phase chain makes the envelope), the set's load,
  ``[emg_map]`` and ``[emg_max]``: each channel's MVC divisor, the peak of its envelope over the sets given as MVC
  efforts (``mvc_sets``; those are not exported as lift trials), else over every exported set (the "maximum over all
  trials" normalisation of docs/signal.md), as the file's comment says.

Times count from the recording's first joint frame, so every trial of one export shares one time axis. No torques
file: the pack's inverse dynamics computes them from the angles and the load, as for the live estimate.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msk_core.errors import ConfigError, InputError
from msk_core.io import write_sto
from msk_core.signal.emg import EmgFilterConfig, envelope_zero_phase_noncausal
from msk_core.signal.host_clock import windowed_offsets
from services.surfaces.dashboard.report import SessionData, SetWindow, read_session, set_windows
from services.transport import messages, topics
from services.transport.mcap_io import read_messages

#: EMG kept on either side of a set: the zero-phase chain's edges settle outside the set's frames
EMG_MARGIN_S = 1.0
#: Joint frames whose device time is further than this from their host time are on a device clock of their own
HOST_CLOCK_TOLERANCE_S = 1.0


@dataclass
class EmgStream:
    """One EMG source's chunks of one channel layout (a Trigno's channels; a new layout is another stream): per chunk
    its first sample index, sample count, its last sample's device time and its receipt (0: none recorded). The
    samples themselves are read per set (:func:`read_rows`): an hour at 2 kHz would not fit in memory at once."""

    source: str
    labels: tuple[str, ...]
    rate_hz: float
    first_index: np.ndarray
    n_samples: np.ndarray
    device_ns: np.ndarray
    host_ns: np.ndarray

    def row_span(self, start_s: float, end_s: float, offset_ns: float) -> tuple[int, np.ndarray]:
        """(first sample index, instants in s on the joints' clock) of the samples within [start, end], with
        ``offset_ns`` (device time + offset = that instant); device times from the stream's sample count."""
        last = self.first_index + self.n_samples - 1
        anchor_ns = float(self.device_ns[0]) - float(last[0]) * 1e9 / self.rate_hz  # device time of index 0
        first = max(
            int(math.ceil((start_s * 1e9 - offset_ns - anchor_ns) * self.rate_hz / 1e9)), int(self.first_index[0])
        )
        stop = min(int(math.floor((end_s * 1e9 - offset_ns - anchor_ns) * self.rate_hz / 1e9)), int(last[-1]))
        index = np.arange(first, stop + 1)
        return first, (anchor_ns + index * 1e9 / self.rate_hz + offset_ns) / 1e9


@dataclass
class ExportedTrial:
    name: str
    path: Path
    window: SetWindow
    frames: int
    emg_channels: int


def _session_messages(recording: Path, session: str | None, types: tuple[str, ...]):
    """(topic, decoded message) of every message of ``types`` of the recording (of ``session``), in recorded order."""
    prefix = None if session is None else f"{topics.session_prefix(session)}/"
    for recorded in read_messages(recording):
        if recorded.type_name in types and (prefix is None or recorded.topic.startswith(prefix)):
            yield recorded.topic, recorded.decode()


def _stream_key(topic: str, chunk: messages.EmgChunk) -> tuple[str, tuple[str, ...]]:
    return chunk.source_id or topic.rsplit("/", 1)[-1], tuple(chunk.channel_labels)


def read_timing(
    recording: Path, session: str | None
) -> tuple[dict[tuple[str, tuple[str, ...]], EmgStream], np.ndarray]:
    """In one pass over the recording: every EMG stream, by (source, channel labels), its chunks' indices and times;
    and how long after its instant each joint frame was received (s; none for frames without a receipt time)."""
    rows: dict[tuple[str, tuple[str, ...]], list[tuple[int, int, int, int, float]]] = {}
    late_s = []
    for topic, m in _session_messages(recording, session, ("msk.EmgChunk", "msk.JointAngles")):
        if isinstance(m, messages.JointAngles):
            if m.host_time_ns:
                late_s.append((m.host_time_ns - m.device_time_ns) / 1e9)
            continue
        n, rate = int(m.n_samples), float(m.sample_rate_hz)
        device_last = int(m.device_time_ns) + round((n - 1) * 1e9 / rate)
        rows.setdefault(_stream_key(topic, m), []).append(
            (int(m.first_sample_index), n, device_last, int(m.host_time_ns), rate)
        )
    streams = {}
    for key, chunks in rows.items():
        a = np.array(sorted(chunks), dtype=float)
        streams[key] = EmgStream(
            key[0], key[1], float(a[0, 4]), a[:, 0].astype(np.int64), a[:, 1].astype(np.int64),
            a[:, 2].astype(np.int64), a[:, 3].astype(np.int64),
        )  # fmt: skip
    return streams, np.array(late_s)


def read_rows(recording: Path, session: str | None, key, spans: dict[int, tuple[int, int]]) -> dict[int, np.ndarray]:
    """Per set, the raw rows of stream ``key`` over its sample-index span [first, first + n): NaN where the base
    delivered none."""
    out = {number: np.full((n, len(key[1])), np.nan) for number, (_, n) in spans.items()}
    for topic, c in _session_messages(recording, session, ("msk.EmgChunk",)):
        first, n = int(c.first_sample_index), int(c.n_samples)
        overlaps = [
            (nb, start, count) for nb, (start, count) in spans.items() if start < first + n and first < start + count
        ]
        if not overlaps or _stream_key(topic, c) != key:
            continue
        block = np.asarray(c.samples, dtype=float).reshape(n, int(c.n_channels))
        for number, start, count in overlaps:
            lo, hi = max(first, start), min(first + n, start + count)
            out[number][lo - start : hi - start] = block[lo - first : hi - first]
    return out


def stated_offsets_ns(recording: Path) -> dict[str, tuple[float, str]]:
    """Per EMG source, the offset the live estimator applied at the end, from ``summary.json`` beside the
    recording (``msk live``'s output folder), with its method; empty without one."""
    summary = Path(recording).with_name("summary.json")
    if not summary.is_file():
        return {}
    try:
        clocks = json.loads(summary.read_text()).get("clocks") or {}
    except (OSError, ValueError):
        return {}
    return {
        name.split("/", 1)[1]: (float(c["offset_ms"]) * 1e6, str(c.get("method", "")))
        for name, c in clocks.items()
        if name.startswith("emg/") and isinstance(c, dict) and "offset_ms" in c
    }


def joint_series(
    recording: Path, data: SessionData, coordinates: list[str], late_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(time in s on the joints' clock, angles (n, coordinates)) of the recorded joint frames of ``coordinates``;
    refused when there are none, or when they are on a device clock of their own, received ``late_s`` after their
    instants by far more than a delivery (their EMG could not be placed)."""
    frames = data.joint_q.get(tuple(coordinates))
    if not frames:
        found = ", ".join("/".join(c) for c in data.joint_q) or "none"
        raise InputError(
            f"no joint frames of the pack's coordinates {coordinates} (frames of: {found}); record with the session's "
            "pack, or give --pack",
            path=recording,
        )
    time = np.array([t for t, _ in frames])
    if late_s.size and abs(float(np.median(late_s))) > HOST_CLOCK_TOLERANCE_S:
        raise InputError(
            "the joint frames are on a device clock of their own (the kinematics node's --imu-clock device), not the "
            "host's: their EMG cannot be placed on it",
            path=recording,
        )
    return time, np.array([q for _, q in frames])


def electrode_channels(streams: dict, electrodes: dict[str, str], groups: list[str]) -> tuple:
    """(the EMG stream, {channel label: group}) of the electrode map, or, without one, of the channels named as the
    pack's groups: the stream that records every mapped channel."""
    mapping = dict(electrodes)
    if not mapping:
        best = max(streams.values(), key=lambda s: sum(label in groups for label in s.labels))
        mapping = {label: label for label in best.labels if label in groups}
    if not mapping:
        labels = sorted({label for s in streams.values() for label in s.labels})
        raise ConfigError(
            f"no electrode map: give the session file whose [electrodes] maps the recorded channels ({labels}) to "
            "the pack's groups",
            field="--session-file",
        )
    for label, group in mapping.items():
        if group not in groups:
            raise ConfigError(
                f"not a group of the pack ({', '.join(groups)})", field=f"electrodes.{label}", value=group
            )
    having = [key for key, s in streams.items() if all(label in s.labels for label in mapping)]
    if not having:
        recorded = sorted({label for s in streams.values() for label in s.labels})
        raise InputError(
            f"no EMG stream recorded every channel of the electrode map {sorted(mapping)} (recorded: {recorded})",
            field="electrodes",
        )
    return having[0], mapping


def arrival_offsets_ns(stream: EmgStream) -> np.ndarray | None:
    """Per chunk, the arrival mapping's offset (device time + offset = host instant); None without receipt times
    (a synthetic recording, on one clock)."""
    if not np.any(stream.host_ns):
        return None
    return windowed_offsets(stream.device_ns, np.maximum.accumulate(stream.host_ns))


def set_offset_ns(stream: EmgStream, window: SetWindow, offsets: np.ndarray | None) -> float:
    """The offset placing the stream on the joints' clock for a set: the set's median arrival offset (``offsets``,
    :func:`arrival_offsets_ns`), 0 without them."""
    if offsets is None:
        return 0.0
    mapped = (stream.device_ns + offsets) / 1e9
    within = (mapped >= window.start_s) & (mapped <= window.end_s)
    return float(np.median(offsets[within] if within.any() else offsets))


def export_trials(
    recording: Path,
    out: Path,
    pack,
    *,
    electrodes: dict[str, str] | None = None,
    mvc_sets: tuple[int, ...] = (),
    mvc: tuple[dict[str, float], str] | None = None,
    session: str | None = None,
    log=print,
) -> list[ExportedTrial]:
    """Write a trial folder per set of the recording's ``pack`` sets under ``out`` (module doc); the lift trials.
    Each channel's MVC: the peak of its envelope over ``mvc_sets``, or ``mvc`` (channel -> divisor, and where they
    come from: :func:`given_divisors`)."""
    if not mvc_sets and not mvc:
        raise ConfigError(
            "the EMG needs each electrode's MVC: record each muscle's maximal voluntary contraction as a set of its "
            "own (msk set start / msk set stop around it) and name those sets, or give the divisors of an earlier "
            "profile or trial (--mvc-from). Normalising by the lifts' own peaks instead makes every muscle peak at "
            "100 % (measured on the demo: activation RMSE 0.128 against static optimisation's 0.059)",
            field="--mvc-set",
        )
    data = read_session(recording, session=session)
    coordinates, groups = list(pack.coordinates), list(pack.groups)
    streams, late_s = read_timing(recording, session)
    joint_time, joint_q = joint_series(recording, data, coordinates, late_s)
    windows = [w for w in set_windows(data) if w.exercise in ("", pack.name)]
    if not windows:
        raise InputError(f"no set of pack {pack.name!r} in the recording", path=recording)
    numbers = {w.number or w.index for w in windows}
    unknown = sorted(set(mvc_sets) - numbers)
    if unknown:
        raise ConfigError(f"not a set of the recording (its sets: {sorted(numbers)})", field="--mvc-set", value=unknown)
    if not streams:
        raise InputError("no EMG recorded: calibration needs the electrodes' EMG", path=recording)
    key, mapping = electrode_channels(streams, electrodes or {}, groups)
    stream, stated = streams[key], stated_offsets_ns(recording).get(key[0])
    t0 = float(joint_time[0])
    columns = [stream.labels.index(label) for label in mapping]
    per_set = sets_emg(recording, session, key, stream, windows, columns, stated)
    if mvc:
        missing = [label for label in mapping if label not in mvc[0]]
        if missing:
            raise ConfigError(f"no MVC divisor for channel(s) {missing} in {mvc[1]}", field="--mvc-from")
        divisors = {label: float(mvc[0][label]) for label in mapping}
    else:
        divisors = mvc_divisors(per_set, set(mvc_sets), stream.rate_hz, list(mapping))
    placed = f"offset of {recording.with_name('summary.json').name} ({stated[1]})" if stated else "arrival mapping"
    exported = []
    for number, (window, time, raw) in per_set.items():
        if number in mvc_sets:
            continue
        inside = (joint_time >= window.start_s) & (joint_time <= window.end_s)
        folder = out / f"set{number}"
        folder.mkdir(parents=True, exist_ok=True)
        write_sto(folder / "ik.sto", joint_time[inside] - t0, coordinates, joint_q[inside], name=f"set {number} joints")
        delivered = np.all(np.isfinite(raw), axis=1)  # rows the base never delivered are left out, not invented
        write_sto(folder / "emg.sto", time[delivered] - t0, list(mapping), raw[delivered], name=f"set {number} raw EMG")
        if not window.load_kg > 0:
            log(
                f"set {number}: its load is not in the recording; the trial says load_kg = 0: give the bar's mass there"
            )
        lost = _interior_gaps(delivered)  # rows before the first or after the last delivered one: not recorded
        if lost:
            log(f"set {number}: {lost} EMG samples within it were never delivered: msk calibrate will say where")
        (folder / "trial.toml").write_text(
            trial_toml(
                f"set{number}", window, mapping, divisors, placed, set(mvc_sets), recording, mvc[1] if mvc else ""
            )
        )
        exported.append(ExportedTrial(f"set{number}", folder / "trial.toml", window, int(inside.sum()), len(mapping)))
    return exported


def sets_emg(recording: Path, session: str | None, key, stream: EmgStream, windows, columns, stated) -> dict:
    """Per set number: (its window, its EMG rows' instants on the joints' clock, the rows of ``columns``), with the
    margins :data:`EMG_MARGIN_S` on either side."""
    by_number = {window.number or window.index: window for window in windows}
    arrival = None if stated is not None else arrival_offsets_ns(stream)
    spans, times = {}, {}
    for number, window in by_number.items():
        offset = stated[0] if stated is not None else set_offset_ns(stream, window, arrival)
        first, times[number] = stream.row_span(window.start_s - EMG_MARGIN_S, window.end_s + EMG_MARGIN_S, offset)
        spans[number] = (first, times[number].size)
    rows = read_rows(recording, session, key, spans)
    return {number: (window, times[number], rows[number][:, columns]) for number, window in by_number.items()}


def _interior_gaps(delivered: np.ndarray) -> int:
    """Rows not delivered between the first and the last delivered one."""
    if not delivered.any():
        return 0
    first, last = int(delivered.argmax()), len(delivered) - int(delivered[::-1].argmax())
    return int((~delivered[first:last]).sum())


def mvc_divisors(per_set: dict, numbers: set[int], rate_hz: float, labels: list[str]) -> dict[str, float]:
    """Per channel, the peak of its zero-phase envelope over the sets ``numbers`` (the MVC efforts, or every set)."""
    peaks = np.zeros(len(labels))
    for number in numbers:
        _, _, raw = per_set[number]
        delivered = np.all(np.isfinite(raw), axis=1)
        if delivered.sum() > 30:  # the filters' padding needs a few samples
            envelope = envelope_zero_phase_noncausal(raw[delivered], EmgFilterConfig(rate_hz=rate_hz))
            peaks = np.maximum(peaks, np.max(envelope, axis=0))
    silent = [label for label, peak in zip(labels, peaks) if not peak > 0]
    if silent:
        raise InputError(f"no EMG from electrode(s) {silent} in the sets the MVC is taken from", field="--mvc-set")
    return {label: float(peak) for label, peak in zip(labels, peaks)}


def trial_toml(
    name: str,
    window: SetWindow,
    mapping: dict[str, str],
    divisors: dict[str, float],
    placed: str,
    mvc_sets: set[int],
    recording: Path,
    mvc_source: str = "",
) -> str:
    """The trial description of one exported set (msk_core.estimate.trial)."""
    mvc = f"the peak of its envelope over set(s) {sorted(mvc_sets)} (MVC efforts)" if mvc_sets else mvc_source
    lines = [
        f"# {window.name}, from {recording} (msk trials); EMG placed by the {placed}",
        f'name = "{name}"',
        'kinematics = "ik.sto"',
        'emg = "emg.sto"',
        "emg_is_envelope = false",
        f"load_kg = {window.load_kg:g}" if window.load_kg > 0 and math.isfinite(window.load_kg) else "load_kg = 0",
        "",
        "[emg_map]",
        *(f'"{label}" = "{group}"' for label, group in mapping.items()),
        "",
        f"[emg_max]  # each channel's divisor: {mvc}",
        *(f'"{label}" = {divisors[label]!r}' for label in mapping),
        "",
    ]
    return "\n".join(lines)


def profile_electrodes(path: Path) -> dict[str, str]:
    """Channel -> group of a subject profile's MVC normalisation (e.g. `msk live`'s OUT/subject_session.json, keyed
    by the live channel names); empty for a trial TOML."""
    from msk_core.estimate.profile import SubjectProfile

    if path.suffix.lower() != ".json":
        return {}
    norm = SubjectProfile.load(path).emg_normalisation
    return {ch: str(info["group"]) for ch, info in norm.items() if "group" in info}


def given_divisors(path: Path) -> tuple[dict[str, float], str]:
    """Channel -> MVC divisor of an earlier subject profile (JSON: its ``emg_normalisation``) or trial (TOML: its
    ``[emg_max]``), and a phrase saying where they come from."""
    import tomllib

    from msk_core.estimate.profile import SubjectProfile

    if path.suffix.lower() == ".json":
        norm = SubjectProfile.load(path).emg_normalisation
        divisors = {ch: float(info["divisor"]) for ch, info in norm.items() if "divisor" in info}
        where = f"the MVC divisors of profile {path}"
    else:
        try:
            table = tomllib.loads(path.read_text()).get("emg_max")
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as error:
            raise ConfigError(f"not a readable trial TOML: {error}", path=path, field="--mvc-from") from None
        if not isinstance(table, dict):
            raise ConfigError("no [emg_max] table of MVC divisors", path=path, field="emg_max")
        divisors = {str(ch): float(v) for ch, v in table.items()}
        where = f"the [emg_max] of trial {path}"
    if not divisors or not all(math.isfinite(v) and v > 0 for v in divisors.values()):
        raise ConfigError("no positive MVC divisors", path=path, field="--mvc-from", value=divisors)
    return divisors, where
