"""Display names: what people call a pack's muscle groups and coordinates, with each coordinate's unit.

A pack spec's ``[names]`` table gives each group and coordinate its display name (``TriLat = "Triceps brachii,
lateral and medial heads"``, ``elv_angle_r = "Shoulder flexion"``); a session file's ``[names]`` table overrides
them for one session (docs/live.md). A group or coordinate the table leaves out keeps its model name (listed in
:attr:`DisplayNames.missing`; every shipped pack names all of them, a test checks it). The model names are the
abbreviations, shown only where space forces it, with a legend (:meth:`DisplayNames.legend`).

Units: a pack coordinate is a rotation (its spec gives ``range_deg``), read in degrees, its torque in N·m; a
translation would be read in metres, its force in N (:data:`TORQUE_UNITS`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from msk_core.errors import ConfigError, close_names
from msk_core.io.files import line_of

ROTATION_UNIT = "deg"
TRANSLATION_UNIT = "m"
#: The generalised force of a coordinate of each unit: the torque about a rotation, the force along a translation.
TORQUE_UNITS = {ROTATION_UNIT: "N·m", TRANSLATION_UNIT: "N"}
#: Longest display name: a name is a label on a screen, not a description.
MAX_NAME_CHARS = 60


@dataclass(frozen=True)
class DisplayNames:
    """Display names of one pack's groups and coordinates (model name -> display name), and the coordinates' units.

    Lookups of a name the pack does not have (a group of another pack) return the model name: a surface always has
    something to show."""

    groups: dict[str, str]  # every group of the pack, in the pack's order
    coordinates: dict[str, str]  # every coordinate of the pack, in the pack's order
    units: dict[str, str]  # coordinate -> ROTATION_UNIT or TRANSLATION_UNIT
    missing: tuple[str, ...] = ()  # groups and coordinates without a display name (shown by their model name)
    overridden: tuple[str, ...] = field(default=())  # names a session file gave instead of the pack's

    @classmethod
    def of(cls, groups: Iterable[str], units: Mapping[str, str], names: Mapping[str, str]) -> DisplayNames:
        """The display names of a pack with ``groups`` and coordinates ``units`` (coordinate -> unit) from a checked
        ``names`` table (:func:`parse_names`); the groups and coordinates it leaves out keep their model names."""
        groups, coordinates = list(groups), list(units)
        return cls(
            groups={g: names.get(g, g) for g in groups},
            coordinates={c: names.get(c, c) for c in coordinates},
            units=dict(units),
            missing=tuple(n for n in groups + coordinates if n not in names),
        )

    def group(self, group: str) -> str:
        return self.groups.get(group, group)

    def coordinate(self, coordinate: str) -> str:
        return self.coordinates.get(coordinate, coordinate)

    def unit(self, coordinate: str) -> str:
        """The unit the coordinate is read in ("deg", "m"); "" for a coordinate of another pack."""
        return self.units.get(coordinate, "")

    def torque_unit(self, coordinate: str) -> str:
        """The unit of the coordinate's generalised force ("N·m" about a rotation, "N" along a translation)."""
        return TORQUE_UNITS.get(self.unit(coordinate), "")

    def with_overrides(self, overrides: Mapping[str, str]) -> DisplayNames:
        """These names with a session's ``overrides`` (checked by :func:`parse_names`) in place; names of another
        pack's groups or coordinates are left out (the session may change exercise)."""
        own = {n: v for n, v in overrides.items() if n in self.groups or n in self.coordinates}
        if not own:
            return self
        return DisplayNames(
            groups={g: own.get(g, v) for g, v in self.groups.items()},
            coordinates={c: own.get(c, v) for c, v in self.coordinates.items()},
            units=self.units,
            missing=tuple(n for n in self.missing if n not in own),
            overridden=tuple(dict.fromkeys(self.overridden + tuple(own))),
        )

    def legend(self, names: Iterable[str]) -> str:
        """``BRA: Brachialis · TriLat: Triceps brachii, lateral and medial heads``: the abbreviations (model names)
        a surface shows where space forces it, explained; names without a display name are left out."""
        pairs = [(n, self.groups.get(n) or self.coordinates.get(n) or n) for n in names]
        return " · ".join(f"{n}: {full}" for n, full in pairs if full != n)

    def as_dict(self) -> dict:
        """JSON-ready: ``{"groups": {g: name}, "coordinates": {c: {"name", "unit", "torque_unit"}}}``."""
        return {
            "groups": dict(self.groups),
            "coordinates": {
                c: {"name": name, "unit": self.unit(c), "torque_unit": self.torque_unit(c)}
                for c, name in self.coordinates.items()
            },
        }


def fallback_names(groups: Iterable[str], coordinates: Iterable[str] = ()) -> DisplayNames:
    """The names of a pack that has none: every group and coordinate by its model name (coordinates: rotations)."""
    return DisplayNames.of(groups, {c: ROTATION_UNIT for c in coordinates}, {})


def parse_names(
    table: object,
    known: Iterable[str],
    *,
    path: Path | None,
    text: str = "",
    where: str = "names",
    what: str = "a muscle group or coordinate of the pack",
    defined_here: bool = False,
) -> dict[str, str]:
    """A ``[names]`` table (``model name = "display name"``) checked against the ``known`` model names: a table of
    one-line strings of at most :data:`MAX_NAME_CHARS` characters, every key known. Errors name the file, line,
    field and value (``defined_here``: the file defines the known names too, as a pack spec does)."""
    if not isinstance(table, dict):
        raise ConfigError(
            'must be a table of model name = "display name"',
            path=path,
            field=where,
            value=table,
            line=line_of(text, f"[{where}]"),
        )
    known = list(known)
    names = {}
    for key, value in table.items():
        fieldname = f"{where}.{key}"
        line = line_of(text, key, after=f"[{where}]", key=True)
        if key not in known:
            hits = close_names(key, known, ignore_case=False)
            # the table may be right and the name it names misspelt where it is defined: say both
            hint = f"closest: {', '.join(hits)}" if hits else "no similar name"
            if hits and defined_here:  # the spec that has the table defines the names too: either may be misspelt
                hint += f"; or is {hits[0]!r} the misspelt one, where the pack defines it?"
            raise ConfigError(
                f"not {what} ({hint})",
                path=path,
                field=fieldname,
                value=key,
                line=line,
            )
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(
                "must be a display name (a non-empty string)", path=path, field=fieldname, value=value, line=line
            )
        if not value.isprintable() or value != value.strip() or len(value) > MAX_NAME_CHARS:
            raise ConfigError(
                f"must be one line of printable text without surrounding spaces, at most {MAX_NAME_CHARS} characters",
                path=path,
                field=fieldname,
                value=value,
                line=line,
            )
        names[key] = value
    return names
