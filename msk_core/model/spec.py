"""Pack specifications (TOML): which coordinates, muscle groups, locked pose, couplings and load a pack compiles.

Angles in a spec are in degrees (``*_deg`` keys), everything else SI. See docs/models.md for the format.

Two tables are declarations about the pack, not inputs of its fit (a change needs no recompile, see
:func:`msk_core.model.pack.with_names`): ``[names]`` (display names, msk_core.model.names) and ``[balance]`` (the
pairs the report compares: left/right groups, agonists/antagonists of a coordinate; :func:`parse_balance`).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeGuard

from msk_core.errors import ConfigError, close_names
from msk_core.io.files import line_of
from msk_core.model.names import ROTATION_UNIT, DisplayNames, parse_names


@dataclass(frozen=True)
class CoordinateSpec:
    """One pack coordinate: fitted range, reference value and the model coordinates that follow it linearly."""

    name: str
    lower: float  # rad
    upper: float  # rad
    reference: float  # rad, value used when building the rigid-body model
    coupled: dict[str, float] = field(default_factory=dict)  # dependent coordinate -> ratio (dq_dep/dq_driver)

    @property
    def unit(self) -> str:
        """The unit people read it in: a pack coordinate is a rotation (its range is given in degrees)."""
        return ROTATION_UNIT


@dataclass(frozen=True)
class LoadPoint:
    """A point (in body coordinates, m) where a share of the hand load acts along gravity."""

    body: str
    point: tuple[float, float, float]


@dataclass(frozen=True)
class DynamicsSpec:
    """How the reduced rigid-body model is rooted, loaded and shared between sides."""

    root: str = "ground"
    gravity: tuple[float, float, float] | None = None  # None: the model's gravity
    # where the hand load (barbell, box) acts; () = the pack has no hand load: its external loads, if any (ground
    # reaction forces of a walk), are in the recorded inverse dynamics a trial gives as torques
    load_points: tuple[LoadPoint, ...] = ()
    load_share: float = 1.0  # fraction of hand_load_newton carried by the modelled side (split over load_points)
    shared_from: str = ""  # bodies distal (from the root) to this body carry mass * load_share ...
    exclude_bodies: tuple[str, ...] = ()  # subtrees (seen from the root) left out of the model
    # subtrees that hang freely from their body's origin (a pendulum, e.g. the arms from the shoulders): their mass
    # and their load points act at that pivot, along gravity (quasi-static: plumb below the pivot at any trunk angle)
    hanging: tuple[str, ...] = ()

    @property
    def has_hand_load(self) -> bool:
        """Whether the pack carries a hand load at all (``load_points`` given)."""
        return bool(self.load_points)


@dataclass(frozen=True)
class FitSpec:
    samples: int = 300
    max_degree: int = 6
    holdout: float = 0.2
    seed: int = 1


@dataclass(frozen=True)
class JointBalance:
    """The groups pulling one coordinate in its positive direction (the direction its display name says, e.g.
    "Elbow flexion": the flexors) against those pulling it back, under a label people read ("Elbow flexors /
    extensors")."""

    coordinate: str
    agonists: tuple[str, ...]
    antagonists: tuple[str, ...]
    label: str


@dataclass(frozen=True)
class BalanceSpec:
    """The pairs a pack declares for balance metrics (``[balance]``); none declared: no balance is reported."""

    left_right: tuple[tuple[str, str], ...] = ()  # (left group, right group)
    agonist_antagonist: tuple[JointBalance, ...] = ()

    @property
    def empty(self) -> bool:
        return not self.left_right and not self.agonist_antagonist


@dataclass(frozen=True)
class PackSpec:
    name: str
    version: str
    description: str
    source_model: str
    coordinates: tuple[CoordinateSpec, ...]
    locked: dict[str, float]  # model coordinate -> value (rad or m)
    groups: dict[str, list[str]]
    dynamics: DynamicsSpec
    fit: FitSpec
    path: Path | None = None
    text: str = ""
    names: dict[str, str] = field(default_factory=dict)  # group or coordinate -> display name ([names])
    balance: BalanceSpec = field(default_factory=BalanceSpec)  # the pairs balance metrics compare ([balance])

    @property
    def coordinate_names(self) -> list[str]:
        return [c.name for c in self.coordinates]

    def display_names(self) -> DisplayNames:
        """The display names of the groups and coordinates (their model names where ``[names]`` gives none)."""
        return DisplayNames.of(self.groups, {c.name: c.unit for c in self.coordinates}, self.names)

    def line_of(self, token: str) -> int | None:
        """1-based line of the first occurrence of ``token`` in the spec text (for error messages)."""
        return line_of(self.text, token)


def closest(name: str, choices: list[str], n: int = 3) -> str:
    """'closest: a, b, c' hint for an unknown name (case aside: "brd" finds "BRD_r")."""
    hits = close_names(name, choices, n=n)
    return f"closest: {', '.join(hits)}" if hits else "no similar name"


def _need(table: dict, key: str, kind: type, path: Path | None, text: str, where: str) -> Any:
    if key not in table:
        raise ConfigError(f"missing required key in [{where}]", path=path, field=key)
    value = table[key]
    if not isinstance(value, kind):
        raise _invalid(f"must be {kind.__name__}", path, text, f"{where}.{key}", value, key)
    return value


def _invalid(message: str, path: Path | None, text: str, fieldname: str, value: object, token: str) -> ConfigError:
    """The error for a bad value of ``fieldname``, at the spec's first line holding ``token``."""
    return ConfigError(message, path=path, field=fieldname, value=value, line=line_of(text, token))


def _vector3(values: list[float]) -> tuple[float, float, float]:
    """A checked [x, y, z] list (three numbers) as floats."""
    x, y, z = values
    return float(x), float(y), float(z)


TOP_KEYS = ("name", "version", "description", "source_model", "coordinates", "locked", "groups", "dynamics", "fit",
            "scaling",  # read by msk_core.model.scale
            "names", "balance")  # fmt: skip
COORDINATE_KEYS = ("range_deg", "reference_deg", "coupled")
FIT_KEYS = ("samples", "max_degree", "holdout", "seed")


def _known_keys(
    table: dict, known: tuple[str, ...], where: str, path: Path | None, text: str, error: Callable | None = None
) -> None:
    """Refuse a key the spec format does not have (a misspelt table or key was ignored: a [lock] table left every
    coordinate at the model's default), naming the closest known one; ``error`` makes the error (default
    :func:`_invalid`; ``[balance]``'s own, which looks for the line inside that table)."""
    unknown = sorted(set(table) - set(known))
    if unknown:
        field_name = f"{where}.{unknown[0]}" if where else unknown[0]
        message = f"unknown key ({closest(unknown[0], list(known))})"
        raise (error or _invalid)(message, path, text, field_name, unknown[0], unknown[0])


def _deg_pair(value: object, path: Path | None, text: str, fieldname: str) -> tuple[float, float]:
    if not (isinstance(value, list) and len(value) == 2 and all(_is_number(v) for v in value) and value[0] < value[1]):
        token = fieldname.split(".")[-2] if "." in fieldname else fieldname
        raise _invalid("must be [lower, upper] in degrees with lower < upper", path, text, fieldname, value, token)
    return math.radians(value[0]), math.radians(value[1])


def parse_spec(text: str, path: Path | None = None) -> PackSpec:
    """Parse a spec from TOML text; errors name the file, line, field and value."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"not valid TOML: {exc}", path=path) from exc
    _known_keys(raw, TOP_KEYS, "", path, text)
    name = _need(raw, "name", str, path, text, "top level")
    coordinates = _parse_coordinates(_need(raw, "coordinates", dict, path, text, "top level"), path, text)
    locked = _parse_locked(raw.get("locked", {}), path, text)
    both = sorted(set(locked) & {c.name for c in coordinates})
    if both:
        message = "is a pack coordinate and locked at once: leave it in one of [coordinates] and [locked]"
        raise _invalid(message, path, text, f"locked.{both[0]}", both[0], both[0])
    for c in coordinates:
        pack_coordinate = next((d for d in c.coupled if d in {o.name for o in coordinates} | set(locked)), None)
        if pack_coordinate is not None:
            message = (
                f"couples {pack_coordinate!r}, which the spec already sets (a pack coordinate or a locked one): a "
                "coupled coordinate is a model coordinate that follows this one"
            )
            raise _invalid(message, path, text, f"coordinates.{c.name}.coupled", pack_coordinate, c.name)
    groups = _parse_groups(_need(raw, "groups", dict, path, text, "top level"), path, text)
    dynamics = _parse_dynamics(raw.get("dynamics", {}), path, text)
    fit = _parse_fit(raw.get("fit", {}), path, text)
    return PackSpec(
        name=name,
        version=str(raw.get("version", "1")),
        description=str(raw.get("description", "")),
        source_model=str(raw.get("source_model", "")),
        coordinates=coordinates,
        locked=locked,
        groups=groups,
        dynamics=dynamics,
        fit=fit,
        path=path,
        text=text,
        names=parse_names(
            raw.get("names", {}), [*groups, *(c.name for c in coordinates)], path=path, text=text, defined_here=True
        ),
        balance=parse_balance(raw.get("balance", {}), groups, [c.name for c in coordinates], path=path, text=text),
    )


def _parse_fit(fit_raw: object, path: Path | None, text: str) -> FitSpec:
    """The [fit] table: samples per muscle (>= 10), polynomial degree (>= 1), held-out share in [0, 1), seed."""
    if not isinstance(fit_raw, dict):
        raise ConfigError("must be a table", path=path, field="fit", line=line_of(text, "[fit]"))
    _known_keys(fit_raw, FIT_KEYS, "fit", path, text)
    checks = (
        ("samples", 300, lambda v: isinstance(v, int) and v >= 10, "a whole number >= 10"),
        ("max_degree", 6, lambda v: isinstance(v, int) and v >= 1, "a whole number >= 1"),
        ("holdout", 0.2, lambda v: _is_number(v) and 0 <= v < 1, "a share in [0, 1)"),
        ("seed", 1, lambda v: isinstance(v, int), "a whole number"),
    )
    values = {}
    for key, default, ok, what in checks:
        value = fit_raw.get(key, default)
        if isinstance(value, bool) or not ok(value):
            raise _invalid(f"must be {what}", path, text, f"fit.{key}", value, key)
        values[key] = value
    return FitSpec(**values)


def _parse_coordinates(coords_raw: dict, path: Path | None, text: str) -> tuple[CoordinateSpec, ...]:
    """The [coordinates] table: at least one, each with range_deg, optional reference_deg and coupled ratios."""
    if not coords_raw:
        raise ConfigError("needs at least one coordinate", path=path, field="coordinates")
    coordinates = []
    for cname, entry in coords_raw.items():
        where = f"coordinates.{cname}"
        if not isinstance(entry, dict):
            raise ConfigError("must be a table", path=path, field=where, line=line_of(text, cname))
        _known_keys(entry, COORDINATE_KEYS, where, path, text)
        lo, hi = _deg_pair(entry.get("range_deg"), path, text, f"{where}.range_deg")
        reference = entry.get("reference_deg", 0.0)
        if not _is_number(reference):
            raise _invalid("must be a number of degrees", path, text, f"{where}.reference_deg", reference, cname)
        ref = math.radians(float(reference))
        if not lo <= ref <= hi:
            message = (
                f"reference_deg {reference:g}"
                + ("" if "reference_deg" in entry else " (the default)")
                + f" outside range_deg [{math.degrees(lo):g}, {math.degrees(hi):g}]"
            )
            raise _invalid(message, path, text, f"{where}.reference_deg", reference, cname)
        coupled = entry.get("coupled", {})
        if not isinstance(coupled, dict) or not all(_is_number(v) for v in coupled.values()):
            message = "coupled must map coordinate names to ratios"
            raise _invalid(message, path, text, f"{where}.coupled", coupled, cname)
        coordinates.append(CoordinateSpec(cname, lo, hi, ref, {k: float(v) for k, v in coupled.items()}))
    return tuple(coordinates)


def _parse_locked(locked_raw: dict, path: Path | None, text: str) -> dict[str, float]:
    """The [locked] table: model coordinate -> value (``{ deg = .. }`` in rad, ``{ m = .. }`` in m)."""
    locked = {}
    if not isinstance(locked_raw, dict):
        raise ConfigError("must be a table", path=path, field="locked", line=line_of(text, "[locked]"))
    for lname, value in locked_raw.items():
        if isinstance(value, dict) and len(value) == 1 and "deg" in value and _is_number(value["deg"]):
            locked[lname] = math.radians(float(value["deg"]))
        elif isinstance(value, dict) and len(value) == 1 and "m" in value and _is_number(value["m"]):
            locked[lname] = float(value["m"])
        else:
            raise _invalid("locked values are { deg = .. } or { m = .. }", path, text, f"locked.{lname}", value, lname)
    return locked


def _parse_groups(groups_raw: dict, path: Path | None, text: str) -> dict[str, list[str]]:
    """The [groups] table: group name -> non-empty list of muscle names."""
    groups = {}
    for gname, members in groups_raw.items():
        if not isinstance(members, list) or not members or not all(isinstance(m, str) for m in members):
            message = "a group is a non-empty list of muscle names"
            raise _invalid(message, path, text, f"groups.{gname}", members, gname)
        groups[gname] = list(members)
    return groups


DYNAMICS_KEYS = ("root", "gravity", "load_points", "load_share", "shared_from", "exclude_bodies", "hanging")


def _parse_dynamics(dyn_raw: object, path: Path | None, text: str) -> DynamicsSpec:
    """The [dynamics] table. Without ``load_points`` the pack has no hand load (its inverse dynamics takes none);
    ``load_share`` is then only meaningful with ``shared_from`` (the share of the shared bodies' mass)."""
    if not isinstance(dyn_raw, dict):
        raise ConfigError("must be a table", path=path, field="dynamics", line=line_of(text, "[dynamics]"))
    _known_keys(dyn_raw, DYNAMICS_KEYS, "dynamics", path, text)
    loads = _parse_load_points(dyn_raw.get("load_points", []), path, text)
    shared_from = str(dyn_raw.get("shared_from", ""))
    share = dyn_raw.get("load_share", 1.0)
    if "load_share" in dyn_raw:
        _check_load_share(share, bool(loads) or bool(shared_from), path, text)
    gravity = dyn_raw.get("gravity")
    if gravity is not None and not (
        isinstance(gravity, list) and len(gravity) == 3 and all(_is_number(v) for v in gravity)
    ):
        raise _invalid("must be [x, y, z] in m/s²", path, text, "dynamics.gravity", gravity, "gravity")
    return DynamicsSpec(
        root=str(dyn_raw.get("root", "ground")),
        gravity=None if gravity is None else _vector3(gravity),
        load_points=tuple(loads),
        load_share=float(share),
        shared_from=shared_from,
        exclude_bodies=tuple(dyn_raw.get("exclude_bodies", [])),
        hanging=tuple(dyn_raw.get("hanging", [])),
    )


def _parse_load_points(points: object, path: Path | None, text: str) -> list[LoadPoint]:
    """``dynamics.load_points``: a list of ``{ body = "..", point = [x, y, z] }``."""
    if not isinstance(points, list):
        message = 'must be a list of { body = "..", point = [x, y, z] } (leave it out for a pack without a hand load)'
        raise _invalid(message, path, text, "dynamics.load_points", points, "load_points")
    loads = []
    for item in points:
        point = item.get("point") if isinstance(item, dict) else None
        if not (
            isinstance(item, dict)
            and isinstance(item.get("body"), str)
            and isinstance(point, list)
            and len(point) == 3
            and all(_is_number(v) for v in point)
        ):
            message = 'load_points entries are { body = "..", point = [x, y, z] }'
            raise _invalid(message, path, text, "dynamics.load_points", item, "load_points")
        loads.append(LoadPoint(item["body"], _vector3(point)))
    return loads


def _check_load_share(share: object, shares_something: bool, path: Path | None, text: str) -> None:
    """``dynamics.load_share`` is in (0, 1] and has something to share (load points or shared bodies)."""
    if not _is_number(share) or not 0.0 < share <= 1.0:
        message = (
            "must be a number in (0, 1]: the share of the hand load (and of the shared_from bodies' mass) this "
            "side carries; a pack without a hand load leaves load_points and load_share out"
        )
        raise _invalid(message, path, text, "dynamics.load_share", share, "load_share")
    if not shares_something:
        message = (
            "load_share without load_points or shared_from shares nothing: this pack has no hand load (no "
            "load_points) and no shared bodies; leave load_share out"
        )
        raise _invalid(message, path, text, "dynamics.load_share", share, "load_share")


def _is_number(value: object) -> TypeGuard[int | float]:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


BALANCE_KEYS = ("left_right", "agonist_antagonist")
JOINT_BALANCE_KEYS = ("coordinate", "agonists", "antagonists", "label")


def parse_balance(
    table: object,
    groups: list[str] | dict[str, list[str]],
    coordinates: list[str],
    *,
    path: Path | None,
    text: str = "",
) -> BalanceSpec:
    """The ``[balance]`` table, checked against the pack's ``groups`` and ``coordinates``::

        [balance]
        left_right = [["psoas_l", "psoas_r"]]  # [left, right]
        agonist_antagonist = [
          { coordinate = "r_elbow_flex", agonists = ["BRA"], antagonists = ["TRIlat"], label = "Elbow flexors / extensors" },
        ]

    Errors name the file, line, field and value: an unknown key, group or coordinate, a group on both sides of a
    pair, a pair or list of the wrong shape, an empty label."""
    if not isinstance(table, dict):
        raise ConfigError("must be a table", path=path, field="balance", value=table, line=line_of(text, "[balance]"))
    _known_keys(table, BALANCE_KEYS, "balance", path, text, _bad)
    known = list(groups)
    pairs_raw = table.get("left_right", [])
    if not isinstance(pairs_raw, list):
        raise _bad(
            "must be a list of [left group, right group]", path, text, "balance.left_right", pairs_raw, "left_right"
        )
    pairs: list[tuple[str, str]] = []
    for k, pair in enumerate(pairs_raw):
        where = f"balance.left_right[{k}]"
        if not (isinstance(pair, list) and len(pair) == 2 and all(isinstance(g, str) for g in pair)):
            raise _bad("must be [left group, right group]", path, text, where, pair, "left_right")
        for g in pair:
            _known_group(g, known, path, text, where)
        if pair[0] == pair[1]:
            raise _bad("a group on both sides of the pair", path, text, where, pair[0], pair[0])
        paired = [g for g in pair if any(g in p for p in pairs)]
        if paired:
            raise _bad("a group already in another left/right pair", path, text, where, paired[0], paired[0])
        pairs.append((pair[0], pair[1]))
    joints_raw = table.get("agonist_antagonist", [])
    if not isinstance(joints_raw, list):
        message = "must be a list of { coordinate, agonists, antagonists, label }"
        raise _bad(message, path, text, "balance.agonist_antagonist", joints_raw, "agonist_antagonist")
    joints = [
        _joint_balance(entry, f"balance.agonist_antagonist[{k}]", known, coordinates, path, text)
        for k, entry in enumerate(joints_raw)
    ]
    return BalanceSpec(tuple(pairs), tuple(joints))


def _joint_balance(
    entry: object, where: str, groups: list[str], coordinates: list[str], path: Path | None, text: str
) -> JointBalance:
    """One ``agonist_antagonist`` entry of ``[balance]`` (:func:`parse_balance`)."""
    if not isinstance(entry, dict):
        message = "must be { coordinate = .., agonists = [..], antagonists = [..], label = .. }"
        raise _bad(message, path, text, where, entry, "agonist_antagonist")
    _known_keys(entry, JOINT_BALANCE_KEYS, where, path, text, _bad)
    for key in JOINT_BALANCE_KEYS:
        if key not in entry:
            raise _bad("missing required key", path, text, f"{where}.{key}", None, "agonist_antagonist")
    coordinate = entry["coordinate"]
    if coordinate not in coordinates:
        message = f"not a coordinate of the pack ({closest(str(coordinate), coordinates)})"
        raise _bad(message, path, text, f"{where}.coordinate", coordinate, str(coordinate))
    sides: dict[str, tuple[str, ...]] = {}
    for key in ("agonists", "antagonists"):
        members = entry[key]
        if not isinstance(members, list) or not members or not all(isinstance(g, str) for g in members):
            raise _bad("must be a non-empty list of group names", path, text, f"{where}.{key}", members, key)
        for g in members:
            _known_group(g, groups, path, text, f"{where}.{key}")
        sides[key] = tuple(members)
    both = [g for g in sides["agonists"] if g in sides["antagonists"]]
    if both:
        message = "a group on both sides (agonists and antagonists)"
        raise _bad(message, path, text, f"{where}.antagonists", both[0], both[0])
    label = entry["label"]
    if not isinstance(label, str) or not label.strip() or "\n" in label:
        raise _bad("must be a one-line label", path, text, f"{where}.label", label, "label")
    return JointBalance(coordinate, sides["agonists"], sides["antagonists"], label.strip())


def _known_group(group: str, groups: list[str], path: Path | None, text: str, where: str) -> None:
    if group not in groups:
        message = f"not a muscle group of the pack ({closest(group, groups)})"
        raise _bad(message, path, text, where, group, group)


def _bad(message: str, path: Path | None, text: str, fieldname: str, value: object, token: str) -> ConfigError:
    """The error for a bad value in ``[balance]``, at the table's first line holding ``token``."""
    line = line_of(text, token, after="[balance]") or line_of(text, "[balance]")
    return ConfigError(message, path=path, field=fieldname, value=value, line=line)


def load_spec(path: str | Path) -> PackSpec:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read spec: {exc.strerror}", path=path) from exc
    return parse_spec(text, path)
