"""The session file of ``msk live`` (TOML): devices, tracker and electrode maps, pack, subject, load, output.

Format in docs/live.md. :func:`load_session_file` checks every key and raises :class:`msk_core.errors.ConfigError`
naming the file, the key and the value; nothing is guessed silently.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from drivers.trigno.protocol import N_SENSORS, AuxLayout
from drivers.xsens.mvn import parse_address as parse_mvn_address
from msk_core.errors import ConfigError, close_names
from msk_core.io.files import toml_key_line
from msk_core.signal.sets import DEFAULT_REST_S
from msk_core.units import load_problem
from services.transport import topics

if TYPE_CHECKING:
    from msk_core.model.names import DisplayNames

METHODS = ("proposed", "assisted", "so", "hybrid")
SIM_METHODS = ("proposed", "assisted", "so")
#: The method every surface (view, dashboard, report) shows by default: the first of these that ran. ``assisted`` runs
#: only where EMG is live (its frames carry the measured envelope), so it is the default there, ``proposed`` elsewhere.
PREFERRED_METHODS = ("assisted", "proposed", "so", "hybrid")


def default_method(methods: Iterable[str]) -> str | None:
    """The method a surface shows by default among those that ran: the first of :data:`PREFERRED_METHODS`, else the
    first in ``methods``' order; None without any."""
    methods = list(methods)
    return next((m for m in PREFERRED_METHODS if m in methods), methods[0] if methods else None)


_SECTIONS = {
    "session": {"name", "out", "pack", "subject", "load_kg", "methods", "athlete", "rest_s"},
    "trigno": {"host", "emg_port", "aux_port", "aux_layout", "id", "latency_ms"},
    "xsens": {"ports", "mvn", "rate_hz", "baud", "latency_ms", "tracker_latency_ms"},
    "trackers": None,  # free keys: tracker ids
    "electrodes": None,  # free keys: channel labels
    "names": None,  # free keys: the pack's groups and coordinates (session_names checks them against the pack)
}

#: The EMG channel labels the Trigno driver publishes (EmgChunk.channel_labels, drivers.trigno.client.TrignoClient
#: .emg_columns): ``sensorNN.EMG`` for a single-channel sensor, ``sensorNN.EMGk`` (k = 1..) for a multi-channel one;
#: NN is the sensor number, two digits. The driver publishes no AUX channel.
TRIGNO_CHANNEL_FORM = f"sensorNN.EMG, or sensorNN.EMGk for the channels of a multi-channel sensor (NN = 01..{N_SENSORS:02d}, k = 1..{N_SENSORS})"
_TRIGNO_CHANNEL = re.compile(r"sensor(\d\d)\.EMG([1-9]\d?)?")


#: Stated device latencies (docs/live.md, "Clocks"): what the host clock mappings take off each device's
#: fastest delivery. The Trigno: Delsys documents frames (13.5 ms of 26 or 27 EMG samples, ``FRAME INTERVAL?``) but
#: no delivery latency; the mapping already uses each frame's last sample, so the frame adds nothing, and what the
#: radio, base and Trigno Control Utility add is not known: 0 until measured (state it as ``trigno.latency_ms``).
TRIGNO_LATENCY_MS = 0.0
#: An MTi: from a physical event to the message on its output "far below 2 ms" (Xsens MTi User Manual MT0605P,
#: 5.4 "Communication timing"), then the message's serial transmission (:func:`tracker_latency_ms`).
MTI_PROCESSING_MS = 2.0


def tracker_latency_ms(baud: int, rate_hz: int) -> float:
    """The default stated latency of an MTi on a serial line: its processing (:data:`MTI_PROCESSING_MS`) plus the
    transmission of one MTData2 message of the driver's outputs at ``rate_hz`` at ``baud`` (8N1; 7.2 ms at the
    factory 115200 baud): the host stamps a sample when its message's last byte is in."""
    from drivers.xsens import xbus
    from drivers.xsens.device import output_settings

    bits_per_message = xbus.output_bits_per_second(output_settings(rate_hz)) / rate_hz
    return MTI_PROCESSING_MS + 1e3 * bits_per_message / baud


def is_trigno_channel(label: str) -> bool:
    """Whether ``label`` is a channel label the Trigno driver can publish (:data:`TRIGNO_CHANNEL_FORM`)."""
    match = _TRIGNO_CHANNEL.fullmatch(label)
    return (
        match is not None
        and 1 <= int(match.group(1)) <= N_SENSORS
        and (match.group(2) is None or int(match.group(2)) <= N_SENSORS)
    )


@dataclass(frozen=True)
class LiveSession:
    """A parsed session file (paths resolved against the file's folder). Frozen: a value decided later (a command-line
    option, what ``--sim`` fills in) makes a changed copy (:func:`dataclasses.replace`) where it is decided."""

    path: Path | None
    name: str = "live"
    athlete: str = ""  # who lifts (shown in report headers); "" when not named
    out: Path = Path("out/live")
    pack: str = "bench_press"  # a shipped pack name, or the resolved path of a pack JSON file
    subject: Path | None = None
    load_kg: float = 0.0
    rest_s: float = DEFAULT_REST_S  # rest detection: a set ends after this long without a rep (msk_core.signal.sets)
    methods: tuple[str, ...] = ()
    solver: str = "active-set"  # the estimator's per-frame QP: "active-set" (hot start, PIQP fallback) or "piqp"
    live_synergists: bool = True  # assisted: groups without EMG follow their measured synergist's live envelope
    trigno_host: str | None = None  # HOST[:PORT]
    trigno_emg_port: int | None = None
    trigno_aux_port: int | None = None  # the accelerometers' port (None: the TCU's beside its EMG port; 0: off)
    trigno_aux_layout: AuxLayout | None = None  # what that port carries (None: from its number, 50042 legacy ACC)
    trigno_id: str = "trigno"
    xsens_ports: tuple[str, ...] = ()  # serial ports or "usb"
    xsens_mvn: str | None = None  # [HOST:]PORT of an MVN network stream (UDP) to listen on
    imu_rate_hz: int = 100
    xsens_baud: int = 115200
    trigno_latency_ms: float | None = None  # stated Trigno latency (None: TRIGNO_LATENCY_MS, or the simulator's)
    xsens_latency_ms: float | None = None  # stated latency of every tracker not named below (None: the default)
    tracker_latency_ms: dict[str, float] = field(default_factory=dict)  # tracker id -> its stated latency
    trackers: dict[str, str] = field(default_factory=dict)  # tracker id (8 hex digits) -> segment
    electrodes: dict[str, str] = field(default_factory=dict)  # Trigno channel label -> profile electrode or group
    names: dict[str, object] = field(default_factory=dict)  # [names] as written: group or coordinate -> display name
    given: frozenset[str] = frozenset()  # dotted keys present in the file


def stated_latencies(
    session: LiveSession, trackers: dict[str, str], *, simulated: bool
) -> tuple[float, dict[str, float]]:
    """(Trigno latency, {tracker id: latency}) in ms as the session states them, each defaulting to the documented
    value (:data:`TRIGNO_LATENCY_MS`, :func:`tracker_latency_ms` at the session's baud and rate) on real devices, to
    0 (the simulators' own latency, which the stated one replaces) under ``--sim``. A tracker named in
    ``xsens.tracker_latency_ms`` that is not one of ``trackers`` is an error (file, key, value)."""
    for tracker in session.tracker_latency_ms:
        if tracker not in trackers:
            raise session_error(
                session.path,
                f"xsens.tracker_latency_ms.{tracker}",
                f"not a tracker of this session ({', '.join(trackers) or 'none'})",
                tracker,
            )
    trigno = session.trigno_latency_ms
    every_tracker = session.xsens_latency_ms
    if trigno is None:
        trigno = 0.0 if simulated else TRIGNO_LATENCY_MS
    if every_tracker is None:
        every_tracker = 0.0 if simulated else tracker_latency_ms(session.xsens_baud, session.imu_rate_hz)
    return trigno, {t: session.tracker_latency_ms.get(t, every_tracker) for t in trackers}


def session_error(path: Path | None, key: str, message: str, value=None) -> ConfigError:
    """The refusal of ``key``'s value, at its line of the session file when the file says it."""
    line = None
    if path is not None:
        try:
            line = toml_key_line(Path(path).read_text(), key)
        except (OSError, UnicodeDecodeError):  # the message still names the file and the key
            pass
    return ConfigError(message, path=path, line=line, field=key, value=value)


def _type(path, key, value, kind, what):
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise session_error(path, key, f"must be {what}", value)
    return value


def _latency_ms(path, key, value) -> float:
    number = _type(path, key, value, (int, float), "a latency in milliseconds")
    if not (math.isfinite(number) and 0 <= number <= 1000):
        raise session_error(path, key, "must be a latency within 0..1000 ms", number)
    return float(number)


def _int_within(path, key, value, low: int, high: int, what: str, out_of_range: str) -> int:
    number = _type(path, key, value, int, what)
    if not low <= number <= high:
        raise session_error(path, key, out_of_range, number)
    return number


def parse_session(doc: dict, path: Path | None = None, *, require_devices: bool = True) -> LiveSession:
    """Check a session document; ``require_devices=False`` (``--sim``): the simulators replace the device keys and
    the bundled session provides pack, subject, maps and load when the file leaves them out."""
    base = path.parent if path is not None else Path.cwd()
    _check_sections(doc, path)
    session = LiveSession(path, given=frozenset({f"{s}.{k}" for s, t in doc.items() for k in t} | set(doc)))
    session = _parse_session_table(session, doc.get("session", {}), path, base, require_devices)
    if (trigno := doc.get("trigno")) is not None:
        session = _parse_trigno(session, trigno, path, require_devices)
    if (xsens := doc.get("xsens")) is not None:
        session = _parse_xsens(session, xsens, path, require_devices)
    session = _parse_maps(session, doc, path)
    if require_devices:
        _check_devices(session, path)
    return session


def _check_sections(doc: dict, path: Path | None) -> None:
    """Every section is a known table, with known keys."""
    for section, value in doc.items():
        if section not in _SECTIONS:
            raise session_error(path, section, f"unknown section (expected {', '.join(_SECTIONS)})", section)
        if not isinstance(value, dict):
            raise session_error(path, section, "must be a table ([" + section + "])", value)
        allowed = _SECTIONS[section]
        for key in value:
            if allowed is not None and key not in allowed:
                raise session_error(
                    path, f"{section}.{key}", f"unknown key (expected {', '.join(sorted(allowed))})", key
                )


def _parse_session_table(
    session: LiveSession, s: dict, path: Path | None, base: Path, require_devices: bool
) -> LiveSession:
    """[session]: name, out, athlete, pack, subject, load_kg, rest_s, methods."""
    name, out, athlete, pack, subject = session.name, session.out, session.athlete, session.pack, session.subject
    if "name" in s:
        try:
            name = topics.check_chunk(_type(path, "session.name", s["name"], str, "a string"), "session")
        except ConfigError as error:
            raise session_error(path, "session.name", f"not a valid key chunk ({error})", s["name"]) from None
    if "out" in s:
        out = base / _type(path, "session.out", s["out"], str, "a folder path")
    if "athlete" in s:
        athlete = _type(path, "session.athlete", s["athlete"], str, "a string (who lifts)")
        if not athlete.isprintable():
            raise session_error(path, "session.athlete", "must be one line of printable text", athlete)
    if "pack" in s:
        pack = _pack(
            path, base, _type(path, "session.pack", s["pack"], str, "a pack name (bench_press, deadlift) or path")
        )
    elif require_devices:
        raise session_error(path, "session.pack", 'missing: the model pack (e.g. "bench_press")')
    if "subject" in s:
        subject = base / _type(path, "session.subject", s["subject"], str, "a path to a subject profile JSON")
        if not subject.is_file():
            raise session_error(
                path, "session.subject", "subject profile not found (make one with `msk calibrate`)", str(subject)
            )
    session = replace(session, name=name, out=out, athlete=athlete, pack=pack, subject=subject)
    return _parse_lift(session, s, path, require_devices)


def _parse_lift(session: LiveSession, s: dict, path: Path | None, require_devices: bool) -> LiveSession:
    """[session]: load_kg, rest_s, methods."""
    load_kg, rest_s, methods = session.load_kg, session.rest_s, session.methods
    if "load_kg" in s:
        load = _type(path, "session.load_kg", s["load_kg"], (int, float), "a number of kilograms")
        if (problem := load_problem(load)) is not None:
            raise session_error(path, "session.load_kg", problem, load)
        load_kg = float(load)
    elif require_devices:
        raise session_error(path, "session.load_kg", "missing: the barbell mass in kg (0 for none)")
    if "rest_s" in s:
        rest = _type(path, "session.rest_s", s["rest_s"], (int, float), "a number of seconds")
        if not (math.isfinite(rest) and rest > 0):
            raise session_error(
                path, "session.rest_s", "must be a time > 0 s (a set ends after this long without a rep)", rest
            )
        rest_s = float(rest)
    if "methods" in s:
        listed = _type(path, "session.methods", s["methods"], list, f"a list of methods ({', '.join(METHODS)})")
        if not listed:
            raise session_error(path, "session.methods", "must name at least one method", listed)
        for m in listed:
            if m not in METHODS:
                raise session_error(path, "session.methods", f"unknown method (expected {', '.join(METHODS)})", m)
        methods = tuple(dict.fromkeys(listed))
    return replace(session, load_kg=load_kg, rest_s=rest_s, methods=methods)


def _parse_trigno(session: LiveSession, t: dict, path: Path | None, require_devices: bool) -> LiveSession:
    """[trigno]: host, emg_port, aux_port, aux_layout, id, latency_ms; the session's values where the file states
    none."""
    given: dict[str, Any] = {}
    if "host" in t:
        given["trigno_host"] = _type(path, "trigno.host", t["host"], str, "HOST or HOST:PORT")
    elif require_devices:  # under --sim the simulator is the device: its other keys (id, latency) still apply
        raise session_error(path, "trigno.host", "missing: the Trigno Control Utility address, HOST or HOST:PORT")
    if "emg_port" in t:
        given["trigno_emg_port"] = _int_within(
            path, "trigno.emg_port", t["emg_port"], 1, 65535, "a TCP port number", "must be a TCP port 1..65535"
        )
    if "aux_port" in t:
        given["trigno_aux_port"] = _int_within(
            path,
            "trigno.aux_port",
            t["aux_port"],
            0,
            65535,
            "a TCP port number",
            "must be a TCP port 1..65535, or 0: off",
        )
    if "aux_layout" in t:
        layouts = [layout.value for layout in AuxLayout]
        if t["aux_layout"] not in layouts:
            raise session_error(path, "trigno.aux_layout", f"must be one of {', '.join(layouts)}", t["aux_layout"])
        given["trigno_aux_layout"] = AuxLayout(t["aux_layout"])
    if "id" in t:
        given["trigno_id"] = topics.check_chunk(_type(path, "trigno.id", t["id"], str, "a name"), "trigno.id")
    if "latency_ms" in t:
        given["trigno_latency_ms"] = _latency_ms(path, "trigno.latency_ms", t["latency_ms"])
    return replace(session, **given)


def _parse_xsens(session: LiveSession, x: dict, path: Path | None, require_devices: bool) -> LiveSession:
    """[xsens]: ports, rate_hz, baud, latency_ms, tracker_latency_ms; the session's values where the file states none."""
    given: dict[str, Any] = {}
    if "ports" in x:
        ports = [x["ports"]] if isinstance(x["ports"], str) else x["ports"]
        if not isinstance(ports, list) or not ports or not all(isinstance(p, str) and p for p in ports):
            raise session_error(path, "xsens.ports", 'must be a list of serial ports or "usb"', x["ports"])
        given["xsens_ports"] = tuple(ports)
    elif require_devices and "mvn" not in x:
        raise session_error(path, "xsens.ports", 'missing: the trackers\' serial ports, or ["usb"] (or mvn = PORT)')
    if "mvn" in x:  # a suit's network stream: a UDP port (9763 by default in MVN), or "HOST:PORT"
        mvn = str(x["mvn"]) if isinstance(x["mvn"], int) and not isinstance(x["mvn"], bool) else x["mvn"]
        try:
            if not isinstance(mvn, str) or parse_mvn_address(mvn)[1] == 0:  # the suit is told where to send: no port 0
                raise ValueError('a UDP port, e.g. 9763, or "HOST:PORT"')
        except ValueError as error:
            raise session_error(path, "xsens.mvn", f"must be {error}", x["mvn"]) from None
        given["xsens_mvn"] = mvn
    if "rate_hz" in x:
        given["imu_rate_hz"] = _int_within(
            path, "xsens.rate_hz", x["rate_hz"], 1, 2000, "an integer rate in Hz", "must be within 1..2000 Hz"
        )
    if "baud" in x:
        given["xsens_baud"] = baud = _type(path, "xsens.baud", x["baud"], int, "a baud rate")
        if baud <= 0:
            raise session_error(path, "xsens.baud", "must be a positive baud rate", baud)
    if "latency_ms" in x:
        given["xsens_latency_ms"] = _latency_ms(path, "xsens.latency_ms", x["latency_ms"])
    per_tracker = x.get("tracker_latency_ms", {})
    if not isinstance(per_tracker, dict):
        raise session_error(
            path, "xsens.tracker_latency_ms", "must be a table: tracker id -> latency in ms", per_tracker
        )
    tracker_latency = dict(session.tracker_latency_ms)
    for tracker, value in per_tracker.items():
        key = f"xsens.tracker_latency_ms.{tracker}"
        tracker_latency[_tracker_id(path, key, tracker)] = _latency_ms(path, key, value)
    return replace(session, **given, tracker_latency_ms=tracker_latency)


def _parse_maps(session: LiveSession, doc: dict, path: Path | None) -> LiveSession:
    """[trackers], [names] and [electrodes]; a tracker latency only for a tracker of [trackers]."""
    trackers = dict(session.trackers)
    listed: dict[str, str] = {}  # tracker id -> as the file writes it
    for tracker, segment in doc.get("trackers", {}).items():
        key = f"trackers.{tracker}"
        tracker_id = _tracker_id(path, key, tracker)
        if tracker_id in listed:  # one device listed twice (ids differing in case): the second replaced the first
            raise session_error(path, key, f"the same tracker as {listed[tracker_id]!r} (ids ignore case)", tracker)
        listed[tracker_id] = tracker
        trackers[tracker_id] = _type(path, key, segment, str, "a body segment name")
    for tracker in session.tracker_latency_ms:
        if trackers and tracker not in trackers:
            raise session_error(
                path,
                f"xsens.tracker_latency_ms.{tracker}",
                f"not a tracker of [trackers] ({', '.join(trackers)})",
                tracker,
            )
    electrodes = dict(session.electrodes)
    for label, target in doc.get("electrodes", {}).items():
        if not is_trigno_channel(label):
            raise session_error(
                path, f"electrodes.{label}", f"not a channel the Trigno driver publishes: {TRIGNO_CHANNEL_FORM}", label
            )
        electrodes[label] = _type(path, f"electrodes.{label}", target, str, "an electrode or group name")
    return replace(session, trackers=trackers, electrodes=electrodes, names=dict(doc.get("names", {})))


def _check_devices(session: LiveSession, path: Path | None) -> None:
    """Without --sim: at least one device, and the maps the devices need."""
    if session.trigno_host is None and not session.xsens_ports and session.xsens_mvn is None:
        raise session_error(path, "trigno", "no device: give [trigno] host and/or [xsens] ports or mvn")
    if session.xsens_ports and not session.trackers:
        raise session_error(
            path, "trackers", 'missing: the tracker -> segment map ([trackers] "00B4EB80" = "upper_arm_r")'
        )
    if session.trigno_host is not None and not session.electrodes:
        raise session_error(
            path, "electrodes", 'missing: the electrode -> group map ([electrodes] "sensor01.EMG" = ...)'
        )


def _tracker_id(path: Path | None, key: str, tracker: str) -> str:
    """A tracker id as the drivers publish it (8 hexadecimal digits, upper case), else an error naming ``key``."""
    try:
        int(tracker, 16)
    except ValueError:
        raise session_error(path, key, "a tracker id is the device id in 8 hexadecimal digits", tracker) from None
    if len(tracker) != 8:
        raise session_error(path, key, "a tracker id is the device id in 8 hexadecimal digits", tracker)
    return tracker.upper()


def _pack(path: Path | None, base: Path, value: str) -> str:
    """A shipped pack name as it is; anything else is a pack JSON file, relative to the session file's folder (as
    ``load_pack`` takes a name or a file), returned resolved."""
    from msk_core.model.pack import available_packs

    packs = available_packs()
    if value in packs:
        return value
    candidate = base / value
    if value.endswith(".json") or "/" in value or "\\" in value or candidate.is_file():
        if not candidate.is_file():
            raise session_error(path, "session.pack", "pack file not found", str(candidate))
        return str(candidate)
    raise session_error(
        path, "session.pack", f"unknown pack (shipped: {', '.join(packs)}; or the path of a pack JSON file)", value
    )


def load_session_file(path: Path, *, require_devices: bool = True) -> LiveSession:
    path = Path(path)
    if not path.is_file():
        raise ConfigError("session file not found", path=path)
    try:
        doc = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"not valid TOML: {error}", path=path) from None
    return parse_session(doc, path, require_devices=require_devices)


def check_against_pack(
    session: LiveSession, groups: list[str], segments: list[str], profile_electrodes: dict[str, dict]
) -> None:
    """Maps that name things the pack or the profile do not have are errors (file, key, value); [trackers], when
    given, puts one tracker on every segment the pack's IMU table uses (the kinematics needs each: with one missing,
    or two on one segment, the session ran without a single joint frame)."""
    by_segment: dict[str, str] = {}
    for tracker, segment in session.trackers.items():
        if segment not in segments:
            raise session_error(
                session.path,
                f"trackers.{tracker}",
                f"not a segment the pack's IMU table uses ({', '.join(segments)})",
                segment,
            )
        if segment in by_segment:
            raise session_error(
                session.path, f"trackers.{tracker}", f"tracker {by_segment[segment]} is on it too", segment
            )
        by_segment[segment] = tracker
    missing = [segment for segment in segments if segment not in by_segment]
    if session.trackers and missing:
        raise session_error(
            session.path,
            "trackers",
            f"no tracker on {', '.join(missing)}: the pack's joint angles need one on each of {', '.join(segments)}",
            dict(session.trackers),
        )
    for label, target in session.electrodes.items():
        if target not in profile_electrodes and target not in groups:
            close = close_names(target, [*profile_electrodes, *groups], n=1)
            raise session_error(
                session.path,
                f"electrodes.{label}",
                "neither an electrode of the subject profile "
                f"({', '.join(profile_electrodes) or 'none'}) nor a muscle group of the pack"
                + (f"; did you mean {close[0]!r}?" if close else ""),
                target,
            )


def session_names(session: LiveSession, pack_names: DisplayNames) -> dict[str, str]:
    """The session file's ``[names]`` (group or coordinate = "display name"), checked against the pack's groups and
    coordinates (errors name the file, field and value): the names that replace the pack's on every surface."""
    from msk_core.model.names import parse_names

    return parse_names(
        session.names,
        [*pack_names.groups, *pack_names.coordinates],
        path=session.path,
        what="a muscle group or coordinate of the session's pack",
    )
