"""Option values as users write them on a command line: ``KEY=VALUE`` items."""

from __future__ import annotations

from collections.abc import Iterable

from msk_core.errors import ConfigError


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
