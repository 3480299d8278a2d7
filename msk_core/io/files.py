"""Writing a file so that no reader ever sees half of it."""

from __future__ import annotations

import os
import threading
from pathlib import Path


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
