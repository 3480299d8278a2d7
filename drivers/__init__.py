"""Device protocols (Delsys Trigno TCP SDK, Xsens Xbus) and faithful simulators of the devices.

Drivers turn device bytes into plain Python/numpy records; the Zenoh nodes in ``services`` publish them.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TypeVar

import numpy as np

from msk_core.errors import FileFormatError, InputError

Source = TypeVar("Source")


def parse_synthetic_spec(text: str) -> tuple[float, int] | None:
    """``synthetic[:SECONDS[:SEED]]`` (the simulators' built-in sources) -> (seconds, seed); None for a file path."""
    if not text.startswith("synthetic"):
        return None
    parts = text.split(":")
    try:
        seconds = float(parts[1]) if len(parts) > 1 and parts[1] else 30.0
        seed = int(parts[2]) if len(parts) > 2 else 0
    except ValueError:
        raise InputError("synthetic source is synthetic[:SECONDS[:SEED]]", field="--from", value=text) from None
    return seconds, seed


def load_source_spec(
    spec: str | Path,
    kind: str,
    synthetic: Callable[[float, int], Source],
    loaders: Mapping[str, Callable[[Path], Source]],
) -> Source:
    """A simulator's source from ``spec``: ``synthetic[:SECONDS[:SEED]]`` -> ``synthetic(seconds, seed)``, else a file
    read by the loader of its suffix (``loaders``: lower-case suffix -> loader); ``kind`` ("EMG", "IMU") names the
    source in the errors for a missing file or an unsupported suffix."""
    text = str(spec)
    parsed = parse_synthetic_spec(text)
    if parsed is not None:
        return synthetic(*parsed)
    path = Path(text)
    if not path.is_file():
        raise InputError(f"{kind} source file not found", path=path)
    loader = loaders.get(path.suffix.lower())
    if loader is None:
        expected = ", ".join(loaders)
        raise FileFormatError(
            f"unsupported {kind} source (expected {expected} or synthetic[:SECONDS])", path=path, value=path.suffix
        )
    return loader(path)


def open_npz(path: Path, required: tuple[str, ...]) -> np.lib.npyio.NpzFile:
    """A simulator's ``.npz`` source opened (no pickled objects) with the arrays ``required`` in it, else a
    FileFormatError naming the file (and the first missing array); use as ``with open_npz(path, (...)) as archive``."""
    try:
        archive = np.load(path, allow_pickle=False)
    except Exception as error:
        raise FileFormatError(f"cannot read .npz: {error}", path=path) from error
    missing = [key for key in required if key not in archive.files]
    if missing:
        archive.close()
        raise FileFormatError("missing array", path=path, field=missing[0])
    return archive
