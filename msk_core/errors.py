"""Typed exceptions of msk-live. Every message names the file, line, field and value involved where there is one; the
one check of ``KEY=VALUE`` option items (:func:`parse_pairs`), whose error names the option and the item; and the one
search for the names a misspelt one may have meant (:func:`close_names`)."""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from pathlib import Path


class MskError(Exception):
    """Base class of every error msk-live raises on purpose."""


class InputError(MskError):
    """Bad user input: a file, a field or a value that cannot be used.

    The message always says where (file, line, field) and what (the value) when known.
    """

    def __init__(
        self,
        message: str,
        *,
        path: str | Path | None = None,
        line: int | None = None,
        field: str | None = None,
        value: object = None,
    ) -> None:
        self.message = message  # without the place and the value: for a caller that names them otherwise
        self.path = Path(path) if path is not None else None
        self.line = line
        self.field = field
        self.value = value
        where = []
        if path is not None:
            where.append(str(path))
        if line is not None:
            where.append(f"line {line}")
        if field is not None:
            where.append(f"field {field!r}")
        prefix = ": ".join([", ".join(where)]) + ": " if where else ""
        suffix = f" (got {value!r})" if value is not None else ""
        super().__init__(f"{prefix}{message}{suffix}")


class FileFormatError(InputError):
    """A file does not follow the format it claims to have."""


class ConfigError(InputError):
    """A configuration (TOML spec, CLI flag, JSON5 file) is invalid."""


class ModelError(MskError):
    """A musculoskeletal model or model pack is inconsistent or used outside its validity."""


class EstimationError(MskError):
    """An estimation problem could not be set up (never raised from the per-frame live loop)."""


class ProtocolError(MskError):
    """A device spoke something the protocol does not allow."""


def parse_pairs(items: Iterable[str], *, field: str, form: str) -> dict[str, str]:
    """``KEY=VALUE`` items (``form`` spells them for the user, e.g. ``CHANNEL=GROUP``) -> {key: value}, split at the
    first ``=``; an item without a key or a value is a :class:`ConfigError` naming ``field`` and the item."""
    pairs = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise ConfigError(f"expected {form}", field=field, value=item)
        pairs[key] = value
    return pairs


def close_names(
    name: str, choices: Iterable[str], *, n: int = 3, cutoff: float = 0.4, ignore_case: bool = True
) -> list[str]:
    """Up to ``n`` of ``choices`` close to ``name`` (difflib's ratio at least ``cutoff``), best first, for an error's
    hint; ``ignore_case``: "brd" finds "BRD_r" (the first of choices that differ only in case)."""
    if not ignore_case:
        return difflib.get_close_matches(name, list(choices), n=n, cutoff=cutoff)
    by_lower: dict[str, str] = {}
    for choice in choices:
        by_lower.setdefault(choice.lower(), choice)
    return [by_lower[hit] for hit in difflib.get_close_matches(name.lower(), list(by_lower), n=n, cutoff=cutoff)]
