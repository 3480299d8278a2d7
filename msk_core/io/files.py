"""Writing files: never half of one (:func:`write_text_atomic`), and JSON that every parser reads
(:func:`json_text`)."""

from __future__ import annotations

import json
import math
import os
import re
import threading
from pathlib import Path
from typing import Any

import numpy as np


def write_text_atomic(path: str | Path, text: str, *, mode: int | None = None) -> None:
    """Write ``text`` to ``path`` through a temporary file beside it, renamed over ``path`` once complete: a reader
    (another process reusing a cached profile, a dashboard reading its tokens) sees the old file or the new one,
    never a partial one, and a writer stopped half-way leaves the old file intact. ``mode``: permission bits to set
    before the rename (default: the process's umask applies, as for a plain write)."""
    path = Path(path)
    # one temporary name per process and thread: two writers of one path never share a temporary file
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        temporary.write_text(text)
        if mode is not None:
            temporary.chmod(mode)
        temporary.replace(path)
    finally:
        temporary.unlink(missing_ok=True)


def json_ready(value: Any) -> Any:
    """``value`` with numpy scalars and arrays as Python numbers and lists, tuples as lists, and every NaN or
    infinity as None: ``NaN`` is not JSON, and strict parsers (a browser's ``JSON.parse``) refuse the whole file."""
    if isinstance(value, dict):
        return {str(k) if not isinstance(k, str) else k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def json_text(value: Any, *, indent: int | None = 2, default: Any = None) -> str:
    """``value`` as strict JSON text (:func:`json_ready`), ending in a newline; ``default`` as json.dumps's."""
    return json.dumps(json_ready(value), indent=indent, allow_nan=False, default=default) + "\n"


def line_of(text: str, token: str, *, after: str = "", key: bool = False) -> int | None:
    """1-based line of the first line of ``text`` holding ``token`` (``key``: a line that assigns it, ``token = ...``,
    bare or quoted), at or after the line ``after`` (a table's header) when given and present; for the line numbers
    of error messages about TOML specs, trial and session files."""
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if after and line.split("#", 1)[0].strip() == after), 0)
    assigns = re.compile(rf"\s*[\"']?{re.escape(token)}[\"']?\s*=")
    for number, line in enumerate(lines[start:], start=start + 1):
        if assigns.match(line) if key else token in line:
            return number
    return None


def toml_key_line(text: str, key: str) -> int | None:
    """The line of ``key`` in a TOML ``text``: a top-level key or table, or ``table.key`` inside ``[table]`` (else
    the table's header line); None when neither is there."""
    table, _, inner = key.partition(".")
    header = line_of(text, table, key=True) or next(
        (  # a header may carry a comment: "[emg_map]  # the envelopes ..."
            n for n, line in enumerate(text.splitlines(), start=1) if line.split("#", 1)[0].strip() == f"[{table}]"
        ),
        None,
    )
    if header is None or not inner:
        return header
    found = line_of(text, inner, after=f"[{table}]", key=True)
    next_table = next(
        (n for n, line in enumerate(text.splitlines()[header:], start=header + 1) if line.strip().startswith("[")),
        None,
    )
    return found if found is not None and (next_table is None or found < next_table) else header
